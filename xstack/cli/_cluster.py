"""``--scheduler`` and ``--workers``: where a command's dask work runs.

:func:`add_cluster_options` adds both to a sub-command's parser (one call per parser);
:func:`xstack.cli.main` then runs the command inside :func:`xstack._cluster.use_cluster`
with their values, so every stage computes on that cluster. Without either, dask's own
configuration decides (``DASK_SCHEDULER_ADDRESS``), else the threaded default.
"""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator
from typing import Any


def add_cluster_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--scheduler ADDRESS`` and ``--workers N`` to one sub-command's parser."""
    group = parser.add_argument_group("cluster")
    where = group.add_mutually_exclusive_group()
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="run the dask work on an existing dask.distributed scheduler: "
                            "its address (tcp://host:8786) or its scheduler file (JSON); "
                            "default: DASK_SCHEDULER_ADDRESS if set, else threads in this "
                            "process")
    where.add_argument("--workers", type=int, default=None, metavar="N",
                       help="start a local cluster of N worker processes (cores / N threads "
                            "each) for this command and close it at the end")
    parser.set_defaults(_cluster=True)


@contextlib.contextmanager
def cluster_of(args: argparse.Namespace) -> Iterator[Any | None]:
    """The cluster a parsed command line asks for (nothing for commands without the options)."""
    if not getattr(args, "_cluster", False):
        yield None
        return
    from xstack._cluster import use_cluster

    with use_cluster(scheduler=args.scheduler, workers=args.workers) as client:
        yield client
