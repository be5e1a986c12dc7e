"""How the process's C heap hands freed memory back: bounded by the chunk, not the data.

Measured (``benchmarks/bench_uvstack_memory.py``): stacking a store of 30 MB chunks on two
threads grew to 17x the chunk above the start - about the whole data set - although at most
two chunks are ever in use. glibc's malloc raises its mmap threshold after a large block is
freed (up to 32 MB), so later chunk-sized arrays come from per-thread heaps (arenas: dask's
threads and numba's) that keep what was freed. A fixed threshold of 1 MiB serves every
chunk-sized array by mmap and returns it on free: the same run peaks at ~9x (two chunks in
flight, ~4.6x each). The cost is a page fault per 4 KiB of every new large array,
unmeasurable beside the kernels (same benchmark).

The command line sets it for its process (:func:`bound_heap`); a Python session can call it
once, and dask.distributed workers take the environment variable
``MALLOC_MMAP_THRESHOLD_=1048576`` (``docs/cluster.md``).
"""

from __future__ import annotations

#: glibc's ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

#: Arrays at least this large (bytes) are mapped and unmapped on their own.
MMAP_THRESHOLD_BYTES = 1 << 20


def bound_heap(threshold: int = MMAP_THRESHOLD_BYTES) -> bool:
    """Serve allocations of ``threshold`` bytes or more by mmap, returned to the OS on free.

    Parameters
    ----------
    threshold
        Size in bytes from which malloc maps memory directly (glibc's ``M_MMAP_THRESHOLD``;
        setting it also stops glibc's dynamic raising of the threshold); the heap's free top
        is trimmed above the same size.

    Returns
    -------
    bool
        True if set (glibc), False where the C library has no ``mallopt`` (macOS, musl):
        nothing changes there.
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return False
    ok = bool(mallopt(_M_MMAP_THRESHOLD, int(threshold)))
    return bool(mallopt(_M_TRIM_THRESHOLD, int(threshold))) and ok
