"""Lazy results: a stage's numbers as a dask collection, computed together with others.

``xstack.stack_uv(..., compute=False)`` returns a :class:`LazyResult` instead of running its
pass over the data. Several lazy results computed together - :func:`compute` or dask's own
``dask.compute(a, b)`` - run as one dask graph: the chunks of a store they share are read
once (the stores' dask keys are deterministic), and on a ``distributed.Client`` every task
runs on the cluster. What turns the computed sums into the result (weights, warnings,
tables) runs in the calling process, where the inputs are, with :func:`compute` and
:meth:`LazyResult.compute`; ``dask.compute`` runs it as the graph's last task (on a cluster,
on a worker).

A lazy result may carry a pending store write (``stack_uv(..., out=..., compute=False)``):
its graph holds the chunk writes, and its finishing completes the store
(:class:`xstack.schema.StoreWrite`). Nothing half-written ever opens as a store: a failed
:func:`compute` (or :meth:`LazyResult.compute`) removes the temporary, and so does dropping
the result uncomputed (a ``weakref.finalize``). A result whose store was written (or given
up) is spent: computing it again is an error, never a second write. The store is finished
only in the process that planned it: on a distributed cluster compute such a result with
:func:`compute` (``dask.compute`` would finish it on a worker: an error there, and the
temporary goes when the result is dropped).
"""

from __future__ import annotations

import contextlib
import os
import weakref
from collections.abc import Callable, Sequence
from typing import Any

from xstack.errors import XstackError


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
    write
        A pending store write (:class:`xstack.schema.StoreWrite`) whose chunk writes are among
        ``parts``; ``finish`` must finish it (or abort it on failure). Aborted when this
        result is dropped uncomputed or its :func:`compute` fails.
    """

    def __init__(self, parts: Sequence[Any], finish: Callable[[list[Any]], Any], name: str,
                 write: Any = None) -> None:
        import dask

        self._name = name
        self._finish = finish
        self._write = write
        self._refusal: Any = None
        # one Delayed over the parts: dask merges and optimises their graphs, this object only
        # delegates to it (no graph internals here, whatever dask's graph representation)
        self._delayed = dask.delayed(list(parts), traverse=True)
        if write is not None:
            # dropped uncomputed (or after a failed dask.compute): remove the temporary. The
            # callback holds the write, never this object, so that it can be collected
            self._finalizer = weakref.finalize(self, write.abort)

    def __repr__(self) -> str:
        return f"<LazyResult of {self._name}: compute with xstack.compute or .compute()>"

    @property
    def pending_write(self) -> Any:
        """The store write this result completes when computed (None: it writes nothing, or
        it was written or given up already)."""
        w = self._write
        return w if w is not None and w.state == "open" else None

    def _graph(self) -> Any:
        """The Delayed this collection delegates to: its parts, or once its store was
        written or given up, one task that says so (a store is written once)."""
        w = self._write
        if w is None or w.state == "open":
            return self._delayed
        if self._refusal is None:
            import dask

            why = ("was written by an earlier compute of this lazy result (a store is written "
                   "once)" if w.state == "finished" else
                   "was given up after a failed compute (nothing of it was kept)")
            msg = f"{self._name}: the store {w.name} {why}: call {self._name} again to write it"
            self._refusal = dask.delayed(_refuse, pure=False)(msg)
        return self._refusal

    # -- dask collection protocol (docs.dask.org: custom collections) ---------------------
    def __dask_graph__(self) -> Any:
        return self._graph().__dask_graph__()

    def __dask_keys__(self) -> Any:
        return self._graph().__dask_keys__()

    def __dask_layers__(self) -> Any:
        return self._graph().__dask_layers__()

    def __dask_tokenize__(self) -> Any:
        return self._graph().__dask_tokenize__()

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


def _refuse(message: str) -> None:
    raise XstackError(message)


def _finish_values(results: Any, finish: Callable[[list[Any]], Any]) -> Any:
    """dask's postcompute: ``results`` holds the one Delayed's value (the list of parts);
    :func:`compute` calls it with that value itself."""
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

    Notes
    -----
    When some results write stores, a failure anywhere removes what those writes wrote
    (after the chunk writes still running have stopped: on dask's threaded scheduler they
    run in an own thread pool, shut down first). ``dask.compute`` itself cannot do that: its
    failure leaves the temporary until the lazy result is dropped (never a store that opens).
    """
    import dask

    from xstack._cluster import active_client

    # each lazy result's parts are computed as a plain Delayed (no finishing task in the
    # graph: dask runs a collection's finishing as a task, on a worker of a cluster) and
    # finished here, in the calling process, where its pending store write is
    lazy = {i: r for i, r in enumerate(results) if isinstance(r, LazyResult)}
    args = [r._graph() if i in lazy else r for i, r in enumerate(results)]
    writes = [w for r in lazy.values() if (w := r.pending_write) is not None]
    pool = None
    if writes:
        from concurrent.futures import ThreadPoolExecutor

        import dask.threaded

        scheduler = dask.base.get_scheduler(scheduler=kwargs.get("scheduler"),
                                            collections=[a for a in args
                                                         if dask.is_dask_collection(a)])
        if scheduler is dask.threaded.get and dask.config.get("pool", None) is None:
            # as write_store: an own pool, shut down before a failure removes the
            # temporary, so that no chunk write still running recreates it
            pool = ThreadPoolExecutor(dask.config.get("num_workers", None) or os.cpu_count()
                                      or 1)
    client = active_client() if writes and kwargs.get("scheduler") is None else None
    try:
        with dask.config.set(pool=pool) if pool is not None else contextlib.nullcontext():
            values = list(dask.compute(*args, **kwargs))
        for i, r in lazy.items():
            values[i] = r._finish(list(values[i]))
        return tuple(values)
    except BaseException:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        for w in writes:
            w.abort()
        if client is not None:
            # tasks already running on the workers are not stopped by the failure: wait for
            # them, then remove what they wrote meanwhile
            _wait_for_running_tasks(client)
            for w in writes:
                w.remove_leftovers()
        raise
    finally:
        if pool is not None:
            pool.shutdown(wait=True)


def _running(dask_worker: Any) -> int:
    state = dask_worker.state
    return len(state.executing) + len(state.long_running)


def _wait_for_running_tasks(client: Any, timeout: float = 30.0) -> None:
    """Wait (at most ``timeout`` seconds) until no task runs on the client's workers."""
    import time

    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            if not any(client.run(_running).values()):
                return
        except Exception:  # a worker gone or the client closing: nothing more to wait for
            return
        time.sleep(0.1)
