"""A real LocalCluster of 2 worker processes (1 thread each) for tests, with a scheduler
plugin that records the tasks it runs: the proof that work ran on the cluster."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import Any

import dask
import distributed


class TaskCounter(distributed.diagnostics.plugin.SchedulerPlugin):
    """The tasks the scheduler ran: keys (and workers) of those that finished, in order, and
    the keys that started processing. ``scheduler`` is set by :func:`local_cluster`."""

    name = "xstack-test-task-counter"

    def __init__(self) -> None:
        self.finished = 0
        self.keys: list[str] = []
        self.workers: list[str] = []
        self.processing: list[str] = []
        self.scheduler: Any = None

    def transition(self, key, start, finish, *args, **kwargs) -> None:
        if finish == "processing":
            self.processing.append(str(key))
        if finish == "memory" and start == "processing":
            self.finished += 1
            self.keys.append(str(key))
            self.workers.append(str(kwargs.get("worker")))
            self.on_finished(key)

    def on_finished(self, key: Any) -> None:
        """Called for every task that finished (subclasses look at it more closely)."""


@contextlib.contextmanager
def local_cluster(counter: TaskCounter | None = None) -> Iterator[Any]:
    """A ``LocalCluster`` of 2 single-threaded worker processes whose scheduler (in this
    process) carries ``counter`` as ``cluster.counter``; closed at the end."""
    with dask.config.set({"distributed.comm.timeouts.connect": "3s"}):
        cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                           dashboard_address=None, silence_logs=logging.ERROR)
        try:
            cluster.counter = counter or TaskCounter()
            cluster.counter.scheduler = cluster.scheduler
            cluster.scheduler.add_plugin(cluster.counter)
            yield cluster
        finally:
            cluster.close()
