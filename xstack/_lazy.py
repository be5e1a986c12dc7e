"""Lazy results: a stage's numbers as a dask collection, computed together with others.

``xstack.stack_uv(..., compute=False)`` returns a :class:`LazyResult` instead of running its
pass over the data. Several lazy results computed together - :func:`compute` or dask's own
``dask.compute(a, b)`` - run as one dask graph: the chunks of a store they share are read
once (the stores' dask keys are deterministic), and on a ``distributed.Client`` every task
runs on the cluster. What turns the computed sums into the result (weights, warnings,
tables) runs in the calling process, where the inputs are.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any


class LazyResult:
    """A result whose dask graph has not been computed yet (a dask collection).

    Parameters
    ----------
    parts
        Dask collections (arrays, delayed) whose computed values ``finish`` needs.
    finish
        ``finish(values)`` -> the result, with ``values`` the computed ``parts`` (a list of
        numpy arrays or objects, in order); runs in the calling process.
    name
        What it is, for ``repr`` (e.g. ``"stack_uv"``).
    """

    def __init__(self, parts: Sequence[Any], finish: Callable[[list[Any]], Any], name: str) -> None:
        import dask

        self._name = name
        self._finish = finish
        # one Delayed over the parts: dask merges and optimises their graphs, this object only
        # delegates to it (no graph internals here, whatever dask's graph representation)
        self._delayed = dask.delayed(list(parts), traverse=True)

    def __repr__(self) -> str:
        return f"<LazyResult of {self._name}: compute with xstack.compute or .compute()>"

    # -- dask collection protocol (docs.dask.org: custom collections) ---------------------
    def __dask_graph__(self) -> Any:
        return self._delayed.__dask_graph__()

    def __dask_keys__(self) -> Any:
        return self._delayed.__dask_keys__()

    def __dask_layers__(self) -> Any:
        return self._delayed.__dask_layers__()

    def __dask_tokenize__(self) -> Any:
        return self._delayed.__dask_tokenize__()

    @staticmethod
    def __dask_optimize__(dsk: Any, keys: Any, **kwargs: Any) -> Any:
        from dask.delayed import Delayed

        return Delayed.__dask_optimize__(dsk, keys, **kwargs)

    def __dask_scheduler__(self, *args: Any, **kwargs: Any) -> Any:  # pragma: no cover - dask's
        return type(self._delayed).__dask_scheduler__(*args, **kwargs)

    def __dask_postcompute__(self) -> tuple[Callable[..., Any], tuple[Any, ...]]:
        return _finish_values, (self._finish,)

    def __dask_postpersist__(self) -> tuple[Callable[..., Any], tuple[Any, ...]]:
        raise NotImplementedError("a lazy xstack result cannot be persisted: compute it")

    def compute(self, **kwargs: Any) -> Any:
        """Run the graph (dask's active scheduler, e.g. a distributed Client) and finish."""
        return compute(self, **kwargs)[0]


def _finish_values(results: Any, finish: Callable[[list[Any]], Any]) -> Any:
    """dask's postcompute: ``results`` holds the one Delayed's value (the list of parts)."""
    values = results[0] if isinstance(results, (list, tuple)) and len(results) == 1 else results
    return finish(list(values))


def compute(*results: Any, **kwargs: Any) -> tuple[Any, ...]:
    """Compute lazy xstack results (and any other dask collections) in one pass.

    Parameters
    ----------
    *results
        :class:`LazyResult` objects (``stack_uv(..., compute=False)``), dask collections or
        plain values (returned as they are).
    **kwargs
        Passed to :func:`dask.compute` (e.g. ``scheduler=``).

    Returns
    -------
    tuple
        The finished results, in order.
    """
    import dask

    return dask.compute(*results, **kwargs)
