"""Progress reporting on stderr: a tqdm bar for dask computations and for plain loops.

The command line allows bars only when stderr is a terminal and neither ``-q`` nor
``--no-progress`` is given (:func:`set_allowed`); library calls show them when asked to.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterable, Iterator
from typing import Any, TypeVar

from dask.callbacks import Callback
from tqdm.auto import tqdm

T = TypeVar("T")

_allowed = True


def set_allowed(allowed: bool) -> bool:
    """Allow (or forbid) every progress bar of this process; returns the previous setting."""
    global _allowed
    previous, _allowed = _allowed, bool(allowed)
    return previous


class _TqdmCallback(Callback):
    """Dask local-scheduler callback that advances a tqdm bar as tasks finish."""

    def __init__(self, description: str) -> None:
        super().__init__()
        self.description = description
        self.bar: Any = None

    def _start_state(self, dsk: Any, state: dict) -> None:
        total = sum(len(state[k]) for k in ("ready", "waiting", "running", "finished"))
        self.bar = tqdm(total=total, desc=self.description, file=sys.stderr, unit="task",
                        leave=False, dynamic_ncols=True)

    def _posttask(self, key: Any, result: Any, dsk: Any, state: dict, worker_id: Any) -> None:
        if self.bar is not None:
            self.bar.update(1)

    def _finish(self, dsk: Any, state: dict, errored: bool) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _distributed_bar_class() -> type:
    """A ``distributed`` progress bar (scheduler-side task counts) drawn on a tqdm bar."""
    from distributed.diagnostics.progressbar import TextProgressBar

    class _TqdmDistributedBar(TextProgressBar):
        """Follows every task behind ``keys`` on the scheduler; advances ``bar`` to match."""

        def __init__(self, keys: Any, bar: Any, **kwargs: Any) -> None:
            self.bar = bar
            super().__init__(keys, **kwargs)

        def _draw_bar(self, remaining: int, all: int, **kwargs: Any) -> None:  # noqa: A002
            if self.bar.total != all:
                self.bar.total = all
            self.bar.update(all - remaining - self.bar.n)

        def _draw_stop(self, **kwargs: Any) -> None:
            pass

    return _TqdmDistributedBar


def _distributed_get(client: Any, description: str) -> Any:
    """A dask ``scheduler=`` function: compute on ``client``, a tqdm bar following the tasks.

    The local-scheduler callback never fires for a distributed computation, so the graph is
    submitted as futures and the scheduler reports progress over them (counting every task
    they depend on, as ``distributed.progress`` does); the results are gathered at the end.
    """
    from dask.core import flatten

    def get(dsk: Any, keys: Any, **kwargs: Any) -> Any:
        futures = client.get(dsk, keys, sync=False, **kwargs)
        flat = [f for f in flatten(futures) if hasattr(f, "key")]
        bar = tqdm(total=len(flat), desc=description, file=sys.stderr, unit="task",
                   leave=False, dynamic_ncols=True)
        try:
            if flat:
                _distributed_bar_class()(flat, bar, scheduler=client.scheduler.address,
                                         interval="100ms")
            return client.gather(futures)
        finally:
            bar.close()

    return get


@contextlib.contextmanager
def dask_progress(description: str = "computing", enabled: bool = True) -> Iterator[None]:
    """Show a progress bar on stderr for dask computations run inside the block.

    On the local schedulers a dask callback advances the bar per task; when a
    ``distributed.Client`` is the default, computations of the block without an explicit
    ``scheduler=`` go to it and the bar follows the scheduler's task counts.
    """
    if not (enabled and _allowed):
        yield
        return
    from xstack._cluster import active_client

    client = active_client()
    if client is not None:
        import dask

        with dask.config.set(scheduler=_distributed_get(client, description)):
            yield
        return
    with _TqdmCallback(description):
        yield


def progress_iter(items: Iterable[T], description: str = "", enabled: bool = True,
                  total: int | None = None) -> Iterable[T]:
    """Wrap an iterable in a tqdm bar on stderr when ``enabled``.

    Where bars are not allowed (:func:`set_allowed`) an asked-for bar is a silent stand-in
    with the same ``update``/``close`` methods.
    """
    if not enabled:
        return items
    if not _allowed:
        return _SilentBar(items)
    return tqdm(items, desc=description, total=total, file=sys.stderr, leave=False,
                dynamic_ncols=True)


class _SilentBar:
    """Iterates like the wrapped iterable; ``update`` and ``close`` do nothing."""

    def __init__(self, items: Iterable[Any]) -> None:
        self._items = items

    def __iter__(self) -> Iterator[Any]:
        return iter(self._items)

    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass
