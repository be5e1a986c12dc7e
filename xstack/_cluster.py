"""Where dask work runs: the threaded scheduler, a local cluster, or an existing one.

Every stage computes through dask's *active* scheduler: a ``distributed.Client`` set as the
default wins, else dask's threaded scheduler. :func:`use_cluster` is the one place that
decides which it is for a block of work (the command line wraps every command in it), and
:func:`active_client` is how a stage asks. :func:`cap_numba_threads` keeps xstack's numba
kernels from using every core of the node in every worker of a cluster.

``distributed`` is imported only when a cluster is asked for or already imported, so the
threaded default pays nothing for it.
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from typing import Any

from xstack.errors import OptionError, XstackError

#: Longest wait for a scheduler to answer, seconds (dask's connect timeout if shorter).
CONNECT_TIMEOUT_S = 10.0

_DISTRIBUTED_NAMES = ("distributed", "dask.distributed")


def active_client() -> Any | None:
    """The ``distributed.Client`` that dask computations of this process go to, or None.

    None inside a task running on a distributed worker (a stage called from a task computes
    there, as before) and when ``distributed`` was never imported (no client can exist).
    """
    dist = sys.modules.get("distributed")
    if dist is None or in_worker():
        return None
    try:
        return dist.default_client()
    except ValueError:
        return None


def in_worker() -> bool:
    """True inside a task running on a ``dask.distributed`` worker."""
    dist = sys.modules.get("distributed")
    if dist is None:
        return False
    try:
        dist.get_worker()
    except ValueError:
        return False
    return True


def local_scheduler(preferred: str) -> str | None:
    """The ``scheduler=`` for a stage's ``dask.compute``: ``preferred`` unless a client is active.

    Stages keep the local scheduler that measured best for them (e.g. ``"threads"``) but a
    client set as the default always wins (None: dask's active scheduler).
    """
    return None if active_client() is not None else preferred


def cap_numba_threads() -> int | None:
    """On a distributed worker: numba threads of this thread = the worker's threads.

    numba's thread count is per calling thread and defaults to every core of the node; with
    several worker processes per node every worker would start that many threads
    (oversubscription). Kernel wrappers call this before launching a parallel kernel; outside
    a worker it does nothing. Returns the thread count set (None outside a worker).
    """
    dist = sys.modules.get("distributed")
    if dist is None:
        return None
    try:
        worker = dist.get_worker()
    except ValueError:
        return None
    import numba

    n = max(1, min(int(worker.state.nthreads), int(numba.config.NUMBA_NUM_THREADS)))
    if numba.get_num_threads() != n:
        numba.set_num_threads(n)
    return n


def _configured() -> tuple[str | None, bool]:
    """(scheduler address from dask's configuration, whether 'distributed' is asked for)."""
    import dask

    address = dask.config.get("scheduler-address", None) or os.environ.get("DASK_SCHEDULER_ADDRESS")
    name = dask.config.get("scheduler", None) or os.environ.get("DASK_SCHEDULER")
    wants = isinstance(name, str) and name.lower() in _DISTRIBUTED_NAMES
    return (str(address) if address else None), wants


def _timeout() -> float:
    import dask
    from dask.utils import parse_timedelta

    configured = dask.config.get("distributed.comm.timeouts.connect", None)
    seconds = parse_timedelta(configured, default="s") if configured else CONNECT_TIMEOUT_S
    return min(float(seconds), CONNECT_TIMEOUT_S)


def _is_scheduler_file(target: str) -> bool:
    return "://" not in target and (target.endswith(".json") or os.path.isfile(target))


def connect(scheduler: str, source: str | None = None) -> Any:
    """A ``distributed.Client`` (set as the default) to a scheduler address or scheduler file.

    ``source`` names where the address came from in messages (e.g. an environment variable);
    None: the ``scheduler`` parameter.

    Raises
    ------
    OptionError
        One line when the file does not exist or the scheduler does not answer within
        :data:`CONNECT_TIMEOUT_S` seconds (or dask's shorter connect timeout).
    """
    from distributed import Client

    timeout = _timeout()
    target = str(scheduler).strip()
    where = f"scheduler={target}" if source is None else f"{target} ({source})"
    option = "scheduler" if source is None else None
    try:
        if _is_scheduler_file(target):
            if not os.path.isfile(target):
                raise OptionError(f"no scheduler file at {where}", option=option)
            return Client(scheduler_file=target, timeout=timeout, set_as_default=True)
        return Client(target, timeout=timeout, set_as_default=True)
    except XstackError:
        raise
    except Exception as exc:  # OSError/TimeoutError/ValueError... all mean "cannot reach it"
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise OptionError(f"cannot reach the dask scheduler at {where}: {reason}",
                          option=option) from None


@contextlib.contextmanager
def use_cluster(scheduler: str | None = None, workers: int | None = None) -> Iterator[Any | None]:
    """Run the dask work of the block on a cluster, or on the default scheduler.

    Parameters
    ----------
    scheduler : str, optional
        Address of a running scheduler (``tcp://host:8786``) or path of its scheduler file
        (JSON, e.g. written by ``dask scheduler --scheduler-file``).
    workers : int, optional
        Start a ``LocalCluster`` of this many worker processes (threads per worker: the
        cores // ``workers``, at least 1) for the block and close it at the end.

    With neither, dask's configuration decides: ``scheduler-address``
    (``DASK_SCHEDULER_ADDRESS``) connects there; ``scheduler`` (``DASK_SCHEDULER``) set to
    ``distributed`` without an address is an error; else an already active client is used,
    or dask's threaded scheduler (the default, nothing is started).

    Yields
    ------
    distributed.Client or None
        The client every ``.compute()`` of the block goes to (None: the local default).

    Raises
    ------
    OptionError
        Both parameters given, ``workers`` < 1, or ``distributed`` asked for without an
        address; :func:`connect`'s errors for an unreachable scheduler.
    """
    if scheduler and workers is not None:
        raise OptionError("give either a scheduler address (scheduler=) or a number of local "
                          "workers (workers=), not both", option=("scheduler", "workers"))
    if workers is not None:
        if int(workers) < 1:
            raise OptionError(f"workers={workers}: must be at least 1", option="workers")
        with _local_cluster(int(workers)) as client:
            yield client
        return
    source = None
    if not scheduler:
        scheduler, wants = _configured()
        source = "DASK_SCHEDULER_ADDRESS"
        if not scheduler:
            current = active_client()
            if wants and current is None:
                raise OptionError("dask's scheduler is set to 'distributed' (DASK_SCHEDULER) "
                                  "but no scheduler address is given: pass scheduler=ADDRESS "
                                  "or set DASK_SCHEDULER_ADDRESS", option="scheduler")
            yield current
            return
    client = connect(scheduler, source)
    try:
        yield client
    finally:
        # only this connection closes; the cluster belongs to whoever started it
        client.close()


#: dask configuration of the local clusters xstack starts (``--workers N``), recommended for
#: any scheduler that runs xstack (docs/cluster.md). ``worker-saturation`` 1.0: the scheduler
#: gives a worker at most one root task (a chunk read) per thread at a time (distributed's
#: default 1.1 rounds up to two per thread), so a single-threaded worker holds 3.5-4.0 chunks
#: instead of 5.3-7.7 at the peak of a uv-stack (benchmarks/bench_scale.py, 1-16 GB); and
#: the workers return freed chunk arrays to the OS (what :func:`xstack._memory.bound_heap`
#: does for the command line's process).
LOCAL_CLUSTER_CONFIG = {
    "distributed.scheduler.worker-saturation": 1.0,
    "distributed.nanny.pre-spawn-environ.MALLOC_MMAP_THRESHOLD_": 1048576,
}


@contextlib.contextmanager
def _local_cluster(workers: int) -> Iterator[Any]:
    import logging

    import dask
    from dask.system import CPU_COUNT
    from distributed import Client, LocalCluster

    threads = max(1, CPU_COUNT // workers)
    with dask.config.set(LOCAL_CLUSTER_CONFIG):
        spawn_env = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
        with _environ_kept(spawn_env):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=threads,
                                   processes=True, dashboard_address=None,
                                   silence_logs=logging.ERROR)
    try:
        client = Client(cluster, set_as_default=True)
        try:
            yield client
        finally:
            client.close()
    finally:
        with _environ_kept(spawn_env):  # a worker restarted meanwhile set them again
            cluster.close()


@contextlib.contextmanager
def _environ_kept(names: Any) -> Iterator[None]:
    """Restore this process's environment variables ``names`` on leaving the block.

    distributed's nanny sets its ``pre-spawn-environ`` (OMP_NUM_THREADS=1, MKL_NUM_THREADS=1,
    ...) in the *parent's* ``os.environ`` before it spawns a worker, and leaves them there:
    a library imported later in this process (ducc0 sizes its thread pool from
    OMP_NUM_THREADS on import) or a program started from it (CASA) would run on one thread.
    The workers keep the variables; this process gets its own back.
    """
    before = {name: os.environ.get(name) for name in names}
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
