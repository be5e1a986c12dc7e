"""MeasurementSet -> xstack zarr store (``xstack convert``).

The MS is read one output chunk (partition x time chunk x baseline chunk) at a time: its rows
are copied by python-casacore (under a process-wide lock) straight into reusable buffers laid
out as the dense (time, baseline_id, frequency, polarization) grid of the xstack schema, and
a writer thread writes them into the zarr store meanwhile. Chunk files are written by
:class:`xstack.io._store.ChunkFiles` - the bytes zarr would write, without zarr's per-chunk
overhead. When a chunk's rows fill its cells in order (a time-ordered MS), the other columns
are read first and compressed while the visibilities are read, and the (uncompressed)
visibilities go to their chunk file batch by batch through a few small buffers. The store is
created and completed by :func:`xstack.io._store.region_store`, which follows the atomic
protocol of :func:`xstack.schema.write_store` (temporary name, completion flag last,
rename). Peak memory is therefore two chunks plus a small per-row index (~50 bytes per MS
row), never the whole MS.

With a ``dask.distributed`` client active, the calling process plans the partitions and
creates the store as above, and the chunks are read and written by tasks in the worker
processes (:func:`_fill_on_cluster`; each a run of whole time chunks, the same streaming),
the completion flag written last once all have finished.

Partitions are one per (spectral window, field) - strictly per DATA_DESC_ID - and one per
scan as well where a single time grid would be irregular: scans with different integration
times, or the same (time, baseline) cell more than once.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import uuid
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from xstack._atomic import check_output
from xstack._cluster import active_client
from xstack.errors import XstackError
from xstack.io import msread
from xstack.io._store import ChunkFiles, region_store
from xstack.msv4 import UNIX_EPOCH_MJD_S
from xstack.schema import DEFAULT_CHUNK_BYTES, new_partition, partition_name, store_encoding

#: Visibility columns accepted by ``datacolumn`` (any other complex array column also works).
DATA_COLUMNS = ("DATA", "CORRECTED_DATA", "MODEL_DATA")


def _encoding() -> dict[str, dict[str, Any]]:
    """zarr codecs of the big arrays (:func:`xstack.schema.store_encoding`)."""
    return store_encoding()


INDEX_COLUMNS = ("TIME", "ANTENNA1", "ANTENNA2", "DATA_DESC_ID", "FIELD_ID", "SCAN_NUMBER",
                  "INTERVAL")


@dataclass
class PartitionPlan:
    """One partition: its rows and the (time, baseline) grid they fall on."""

    name: str
    ddid: int
    field_id: int
    scan: int | None
    rows: np.ndarray  # MS row numbers, sorted by time index
    t_index: np.ndarray
    b_index: np.ndarray
    times: np.ndarray
    scan_of_time: np.ndarray
    antenna1: np.ndarray
    antenna2: np.ndarray
    interval: float


def parse_chunks(text: str | Mapping[str, int] | None) -> dict[str, int]:
    """Parse ``"time=N,baseline_id=M"`` (or a mapping) into validated chunk sizes."""
    if text is None or text == "":
        return {}
    if isinstance(text, str):
        out: dict[str, Any] = {}
        for item in text.split(","):
            key, sep, val = item.partition("=")
            if not sep:
                raise XstackError(f"bad chunk specification {item!r} (expected NAME=N, e.g. time=100)")
            out[key.strip()] = val.strip()
    else:
        out = dict(text)
    chunks: dict[str, int] = {}
    for key, val in out.items():
        if key not in ("time", "baseline_id"):
            raise XstackError(f"cannot chunk dimension {key!r} (only time and baseline_id; "
                              "frequency and polarization stay whole)")
        if isinstance(val, str) and val.strip().isdigit():
            n = int(val.strip())
        elif isinstance(val, (int, np.integer)) and not isinstance(val, bool):
            n = int(val)
        else:
            n = 0
        if n <= 0:
            raise XstackError(f"chunk size for {key} must be a positive integer, got {val!r}")
        chunks[key] = n
    return chunks


def check_datacolumn(path: str, datacolumn: str) -> tuple[str, str]:
    """Validate the data column; return (column name, numpy complex dtype name)."""
    col = str(datacolumn).upper()
    info = msread.column_info(path, col)
    if info is None:
        if col in DATA_COLUMNS:
            raise XstackError(f"{path}: the MS has no {col} column")
        raise XstackError(f"unknown data column {datacolumn!r} (choose DATA, CORRECTED_DATA or MODEL_DATA)")
    vtype = info.get("valueType", "")
    if vtype not in ("complex", "dcomplex") or info.get("ndim", 0) not in (2, -1):
        raise XstackError(f"{datacolumn!r} is not a visibility column ({vtype} array)")
    return col, ("complex128" if vtype == "dcomplex" else "complex64")


def _codes(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(values, return_inverse=True)``, in one pass when ``values`` are sorted.

    The row index of a time-ordered MS is sorted by TIME; sorting it again (and numpy's
    hash-based unique) took a tenth of a 1 GB conversion.
    """
    if values.size > 1 and bool(np.all(values[1:] >= values[:-1])):
        change = np.empty(values.size, dtype=bool)
        change[0] = True
        np.not_equal(values[1:], values[:-1], out=change[1:])
        return values[change], np.cumsum(change) - 1
    uniq, inverse = np.unique(values, return_inverse=True)
    return uniq, inverse.ravel()


def _has_duplicates(cell: np.ndarray, n_cells: int) -> bool:
    """Whether non-negative integers ``cell`` (all below ``n_cells``) repeat a value."""
    if n_cells <= 4 * cell.size + (1 << 20):  # a dense grid: count, no sort
        return bool(np.bincount(cell, minlength=n_cells).max(initial=0) > 1)
    ordered = np.sort(cell)
    return bool(np.any(ordered[1:] == ordered[:-1]))


def plan_partitions(index: dict[str, np.ndarray], meta: msread.MSMeta, where: str) -> list[PartitionPlan]:
    """Group rows into partitions and place every row on its partition's grid."""
    time, a1, a2 = index["TIME"], index["ANTENNA1"], index["ANTENNA2"]
    ddid, fid = index["DATA_DESC_ID"], index["FIELD_ID"]
    nrow = time.size
    scan = index.get("SCAN_NUMBER", np.zeros(nrow, np.int32))
    interval = index.get("INTERVAL", np.zeros(nrow))
    if ddid.size and (ddid.min() < 0 or ddid.max() >= meta.ddid_spw.size):
        raise XstackError(f"{where}: DATA_DESC_ID out of range of the DATA_DESCRIPTION table")
    if fid.size and (fid.min() < 0 or fid.max() >= len(meta.field_names)):
        raise XstackError(f"{where}: FIELD_ID out of range of the FIELD table")
    n_ant = len(meta.antenna_names)
    if max(a1.max(), a2.max()) >= n_ant or min(a1.min(), a2.min()) < 0:
        raise XstackError(f"{where}: ANTENNA1/ANTENNA2 out of range of the ANTENNA table")

    group_key = ddid.astype(np.int64) * (fid.max() + 1) + fid
    order = np.argsort(group_key, kind="stable")
    keys, starts = np.unique(group_key[order], return_index=True)
    bounds = [*starts[1:], nrow]
    plans: list[PartitionPlan] = []
    names: set[str] = set()
    for _key, s0, s1 in zip(keys, starts, bounds):
        grows = np.sort(order[s0:s1])
        d, f = int(ddid[grows[0]]), int(fid[grows[0]])
        gscans = scan[grows]
        groups = [(None, grows)]
        if gscans.size and bool(np.any(gscans != gscans[0])):
            per_scan_interval = {int(s): np.unique(interval[grows[gscans == s]]) for s in np.unique(gscans)}
            distinct = np.unique(np.concatenate(list(per_scan_interval.values())))
            t_uniq, t_inv = _codes(time[grows])
            cell = (t_inv.astype(np.int64) * n_ant + a1[grows]) * n_ant + a2[grows]
            if distinct.size > 1 or _has_duplicates(cell, t_uniq.size * n_ant * n_ant):
                groups = [(int(s), grows[gscans == s]) for s in np.unique(gscans)]
        for s, rows in groups:
            plan = _grid(rows, time, a1, a2, scan, interval, d, f, s, meta, where)
            if plan.name in names:  # two data descriptions of one window (other polarizations)
                plan.name = f"{plan.name}_ddid{d}"
            names.add(plan.name)
            plans.append(plan)
    return plans


def _grid(rows: np.ndarray, time: np.ndarray, a1: np.ndarray, a2: np.ndarray, scan: np.ndarray,
          interval: np.ndarray, ddid: int, field_id: int, scan_id: int | None, meta: msread.MSMeta,
          where: str) -> PartitionPlan:
    times, t_index = _codes(time[rows])
    n_ant = max(len(meta.antenna_names), 1)
    bl = a1[rows].astype(np.int64) * n_ant + a2[rows]
    if n_ant * n_ant <= (1 << 24):  # antenna pairs present, by table look-up rather than sorting
        present = np.zeros(n_ant * n_ant, dtype=bool)
        present[bl] = True
        keys = np.flatnonzero(present)
        lookup = np.zeros(n_ant * n_ant, dtype=np.int64)
        lookup[keys] = np.arange(keys.size)
        b_index = lookup[bl]
    else:
        keys, b_index = _codes(bl)
    pairs = np.column_stack([keys // n_ant, keys % n_ant])
    cell = t_index.astype(np.int64) * pairs.shape[0] + b_index
    if _has_duplicates(cell, times.size * pairs.shape[0]):
        raise XstackError(f"{where}: several rows for one (time, baseline) in DATA_DESC_ID {ddid}, "
                          f"field {field_id}{'' if scan_id is None else f', scan {scan_id}'} "
                          "(several arrays or observations mixed?)")
    if t_index.size > 1 and not bool(np.all(t_index[1:] >= t_index[:-1])):
        order = np.argsort(t_index, kind="stable")  # rows of a time chunk become contiguous
        rows, t_index, b_index = rows[order], t_index[order], b_index[order]
    scan_of_time = np.zeros(times.size, dtype=np.int32)
    scan_of_time[t_index] = scan[rows]
    spw = int(meta.ddid_spw[ddid])
    ivals = interval[rows]
    # int32 where it fits: these row-sized arrays stay in memory for the whole conversion
    small = np.int32 if max(int(rows[-1]) if rows.size else 0, times.size, keys.size) < 2**31 else np.int64
    return PartitionPlan(name=partition_name(spw, field_id, scan_id), ddid=ddid, field_id=field_id,
                 scan=scan_id, rows=rows.astype(small), t_index=t_index.astype(small),
                 b_index=b_index.astype(small), times=times, scan_of_time=scan_of_time,
                 antenna1=pairs[:, 0].astype(np.int32), antenna2=pairs[:, 1].astype(np.int32),
                 interval=float(np.median(ivals)) if ivals.size else 0.0)


def block_spec(path: str, plan: PartitionPlan, meta: msread.MSMeta, column: str,
               vis_dtype: str) -> msread.BlockSpec:
    """How to read one partition's chunks from the MS: its row span, shapes and the optional
    columns (WEIGHT_SPECTRUM, SIGMA...) it has."""
    first, last = int(plan.rows.min()), int(plan.rows.max())

    def defined(col: str) -> bool:
        return msread.cell_defined(path, col, first) and msread.cell_defined(path, col, last)

    if not defined(column):
        raise XstackError(f"{path}: column {column} holds no data for DATA_DESC_ID {plan.ddid}")
    if defined("WEIGHT_SPECTRUM"):
        wsrc = "WEIGHT_SPECTRUM"
    elif defined("WEIGHT"):
        wsrc = "WEIGHT"
    elif defined("SIGMA"):
        wsrc = "SIGMA"
    else:
        wsrc = "NONE"
    spw = int(meta.ddid_spw[plan.ddid])
    return msread.BlockSpec(
        path=path, data_column=column, n_channels=int(meta.spw_freqs[spw].size),
        n_pols=len(meta.pol_names[int(meta.ddid_pol[plan.ddid])]), vis_dtype=vis_dtype,
        weight_source=wsrc, flag_defined=defined("FLAG"),
        has_flag_row=msread.column_info(path, "FLAG_ROW") is not None,
        has_centroid=defined("TIME_CENTROID"), has_exposure=defined("EXPOSURE"),
        time_origin=UNIX_EPOCH_MJD_S)


def chunk_sizes(n_time: int, n_bl: int, n_chan: int, n_pol: int, itemsize: int,
                 chunks: Mapping[str, int]) -> tuple[int, int]:
    """(time, baseline) chunk sizes: the user's, else ~DEFAULT_CHUNK_BYTES of VISIBILITY."""
    per_bl = max(1, n_chan * n_pol * itemsize)
    cb = chunks.get("baseline_id") or min(n_bl, max(1, DEFAULT_CHUNK_BYTES // per_bl))
    ct = chunks.get("time") or max(1, DEFAULT_CHUNK_BYTES // (per_bl * cb))
    return min(max(1, ct), max(n_time, 1)), min(max(1, cb), max(n_bl, 1))


def chunk_blocks(plan: PartitionPlan, ct: int, cb: int, time_chunks: tuple[int, int] | None = None
                 ) -> Iterator[tuple[int, int, int, int, np.ndarray, np.ndarray, np.ndarray]]:
    """(t0, t1, b0, b1, rows, t_index, b_index) of every chunk, rows ascending within a chunk.

    ``time_chunks`` ``(i0, i1)``: only the chunks of time chunks ``i0:i1`` (every baseline
    chunk of them); ``plan`` then needs to hold only their rows (:func:`_restrict`).
    """
    nt, nb = plan.times.size, plan.antenna1.size
    t_edges = [*range(0, nt, ct), nt]
    b_edges = [*range(0, nb, cb), nb]
    # rows are sorted by time index, so a time chunk is a slice of them
    t_starts = np.searchsorted(plan.t_index, t_edges)
    i0, i1 = time_chunks if time_chunks is not None else (0, len(t_edges) - 1)
    for i in range(i0, i1):
        r0, r1 = t_starts[i], t_starts[i + 1]
        rows, ti, bi = plan.rows[r0:r1], plan.t_index[r0:r1] - t_edges[i], plan.b_index[r0:r1]
        for j in range(len(b_edges) - 1):
            sel = (bi >= b_edges[j]) & (bi < b_edges[j + 1]) if len(b_edges) > 2 else slice(None)
            o = np.argsort(rows[sel], kind="stable")  # casacore reads rows in ascending order
            yield (t_edges[i], t_edges[i + 1], b_edges[j], b_edges[j + 1], rows[sel][o], ti[sel][o],
                   bi[sel][o] - b_edges[j])


def _placeholders(plan: PartitionPlan, spec: msread.BlockSpec, ct: int, cb: int) -> dict[str, Any]:
    """Never-computed dask arrays that give the store its array shapes, dtypes and chunks."""
    import dask.array as da

    nt, nb, nc, npol = plan.times.size, plan.antenna1.size, spec.n_channels, spec.n_pols
    layout = {
        "VISIBILITY": ((nt, nb, nc, npol), spec.vis_dtype),
        "WEIGHT": ((nt, nb, nc, npol), np.float32),
        "FLAG": ((nt, nb, nc, npol), bool),
        "UVW": ((nt, nb, 3), np.float64),
        "TIME_CENTROID": ((nt, nb), np.float64),
        "EFFECTIVE_INTEGRATION_TIME": ((nt, nb), np.float64),
    }
    # explicit names spare dask hashing the arguments (a tenth of a small conversion)
    tag = uuid.uuid4().hex
    return {var: da.empty(shape, chunks=(ct, cb, *shape[2:]), dtype=dtype, name=f"xstack-{var}-{tag}")
            for var, (shape, dtype) in layout.items()}


#: Threads writing chunks while the main thread reads the next ones. python-casacore holds
#: the GIL while it copies rows, so writers progress only in GIL-free calls (file writes,
#: blosc, zstd). On a loaded 2-core machine a second writer thread made conversion slower
#: (more contention, no more overlap: benchmarks/bench_convert.py), hence one.
WRITE_THREADS = 1

#: Bytes of fill value written per call when an edge chunk's visibilities are padded.
FILL_PIECE_BYTES = 8 * 1024**2


class _BatchRing:
    """A few batch-sized visibility buffers, each reused once the writes from it are done.

    Streamed visibilities go from casacore to the chunk file through these rather than a
    chunk-sized buffer: the first touch of ~2 x 128 MB of fresh memory per conversion cost
    as much as reading it (page faults), and peak memory is lower.
    """

    def __init__(self, n_slots: int, shape: tuple[int, ...], dtype: str) -> None:
        self.shape, self.dtype = shape, dtype
        self.slots: list[np.ndarray | None] = [None] * n_slots
        self.writes: list[list[Any]] = [[] for _ in range(n_slots)]
        self.turn = 0
        self.current = 0

    def take(self, n: int) -> np.ndarray:
        """The next free buffer's first ``n`` rows (waits for its previous writes)."""
        k = self.current = self.turn % len(self.slots)
        self.turn += 1
        for fut in self.writes[k]:
            fut.result()
        self.writes[k] = []
        if self.slots[k] is None:
            self.slots[k] = np.empty(self.shape, dtype=self.dtype)
        return self.slots[k][:n]


def _chunk_is_direct(rows: np.ndarray, t_index: np.ndarray, b_index: np.ndarray, n_time: int,
                     n_baseline: int) -> bool:
    """Whether consecutive MS rows fill every cell of an (n_time, n_baseline) block in order."""
    n = rows.size
    if n == 0 or n != n_time * n_baseline or int(rows[-1]) - int(rows[0]) + 1 != n:
        return False
    cell = t_index.astype(np.int64) * n_baseline + b_index
    return int(cell[0]) == 0 and bool(np.all(np.diff(cell) == 1))


def _fill(root: Any, plans: list[PartitionPlan], specs: list[msread.BlockSpec], sizes: list[tuple[int, int]],
          progress: bool, description: str, work: list[tuple[int, int, int]] | None = None,
          should_stop: Callable[[], bool] | None = None) -> None:
    """Read every chunk from the MS (or those of ``work``) and write it into the store.

    ``work``: ``(partition index, first time chunk, end time chunk)`` of each range of
    chunks to fill (every baseline chunk of those time chunks), in order; default: every
    chunk of every partition. ``should_stop`` is asked before each chunk is read; when it
    says so the fill ends with :class:`_Stopped` (a cluster's convert failed elsewhere).

    The main thread reads (casacore) while :data:`WRITE_THREADS` threads write what was read
    before. Uncompressed arrays (VISIBILITY) of a chunk whose rows fill its cells in order
    are *streamed*: written batch by batch as they are read, through a :class:`_BatchRing`
    of a few batch-sized buffers, after the other arrays of the chunk were read into a
    chunk-sized buffer set and handed to the writers - so their compression overlaps the
    reading of the visibilities, and the next chunk can reuse the same buffer set (one set
    for a streamed conversion: memory holds one chunk of WEIGHT, FLAG and UVW plus the
    ring, not two chunks of everything). Other chunks alternate between two buffer sets, so
    one is written while the other is read.
    Chunk files are written by :class:`xstack.io._store.ChunkFiles` (the bytes zarr would
    write, without its per-chunk overhead) where the array's codecs allow, else by zarr.
    """
    from collections import deque
    from concurrent.futures import Future, ThreadPoolExecutor
    from functools import partial

    import zarr

    if work is None:
        work = [(k, 0, -(-p.times.size // ct)) for k, (p, (ct, _)) in enumerate(zip(plans, sizes))]
    bar = None
    if progress:  # tqdm takes longer to import than a small MS takes to read
        from xstack._progress import progress_iter

        total = sum((i1 - i0) * -(-plans[k].antenna1.size // sizes[k][1]) for k, i0, i1 in work)
        bar = progress_iter(range(total), description, enabled=True)
    in_use: list[list[Future]] = [[], []]  # the writes still reading each buffer set
    pending: deque[list[Future]] = deque()  # every chunk's writes, oldest chunk first
    open_fds: set[int] = set()

    def free(slot: int) -> None:
        """Wait until no write reads buffer set ``slot`` any more."""
        futures, in_use[slot] = in_use[slot], []
        for fut in futures:
            fut.result()

    def retire(keep: int) -> None:
        """Wait for the writes of all but the ``keep`` newest chunks (and count them done)."""
        while len(pending) > keep:
            for fut in pending.popleft():
                fut.result()
            if bar is not None:
                bar.update(1)

    def finish_raw(files: ChunkFiles, fd: int, batches: list[Future], chunk_shape: tuple[int, ...],
                   n_valid: int, n_streamed: list[int]) -> None:
        for fut in batches:
            fut.result()
        try:
            if n_streamed[0] != n_valid * chunk_shape[1]:  # _chunk_is_direct promised every cell
                raise RuntimeError(f"only {n_streamed[0]} of {n_valid * chunk_shape[1]} cells of a "
                                   "streamed chunk were read")
            if n_valid < chunk_shape[0]:  # edge chunk: zarr pads it with the fill value
                _write_fill(fd, files, chunk_shape[1:], n_valid, chunk_shape[0] - n_valid)
        finally:
            open_fds.discard(fd)
            os.close(fd)

    def write_chunk(files: ChunkFiles, coords: tuple[int, ...], chunk: np.ndarray, n_valid: int) -> None:
        if n_valid < chunk.shape[0]:
            chunk[n_valid:] = files.fill_value
        files.write(coords, chunk)

    def stream_batch(streamed: dict[str, tuple[int, list[Future]]], chunks: dict[str, np.ndarray],
                     n_streamed: list[int], ring: _BatchRing, reading: list[Future],
                     c0: int, c1: int) -> None:
        """Hand cells c0:c1 of the streamed arrays, just read, to the writers."""
        n_streamed[0] += c1 - c0
        for var, (fd, batches) in streamed.items():
            if var == "VISIBILITY":
                cells = ring.slots[ring.current][:c1 - c0]
            else:
                flat = chunks[var]
                cells = flat.reshape(flat.shape[0] * flat.shape[1], -1)[c0:c1]
            fut = pool.submit(ChunkFiles.write_at, fd, cells, c0 * cells[0].nbytes)
            batches.append(fut)
            if var == "VISIBILITY":
                ring.writes[ring.current].append(fut)
            else:  # read from the buffer set
                reading.append(fut)

    def write_others(files: dict[str, ChunkFiles | None], streamed: dict, chunks: dict[str, np.ndarray],
                     coords: dict[str, tuple[int, ...]], n_valid: int, futures: list[Future],
                     early: set[str]) -> None:
        """Hand the chunks of the arrays that are not streamed to the writers."""
        for var, f in files.items():
            if var not in streamed and f is not None:
                futures.append(pool.submit(write_chunk, f, coords[var], chunks[var], n_valid))
                early.add(var)

    def write_zarr(array: Any, values: np.ndarray, t0: int, t1: int, b0: int, b1: int) -> None:
        array[t0:t1, b0:b1] = values

    # every chunk is written exactly once, so zarr need not compare chunks with the fill value
    with zarr.config.set({"array.write_empty_chunks": True}), ThreadPoolExecutor(WRITE_THREADS) as pool:
        try:
            for k, i0, i1 in work:
                plan, spec, (ct, cb) = plans[k], specs[k], sizes[k]
                group = root[plan.name]
                arrays = {var: group[var] for var in msread.BLOCK_VARS}
                files = {var: ChunkFiles.for_array(a) for var, a in arrays.items()}
                for slot in (0, 1):  # the previous partition's buffers are freed first
                    free(slot)
                retire(0)
                buffers: list[dict[str, np.ndarray] | None] = [None, None]  # allocated when first used
                ring = _BatchRing(3, (msread.batch_rows(spec), spec.n_channels, spec.n_pols), spec.vis_dtype)
                slot = 1
                for t0, t1, b0, b1, rows, ti, bi in chunk_blocks(plan, ct, cb, (i0, i1)):
                    if should_stop is not None and should_stop():
                        raise _Stopped("stopped: the conversion failed in another task")
                    whole = (b1 - b0 == cb)
                    streams = whole and any(f is not None and f.raw for f in files.values()) \
                        and _chunk_is_direct(rows, ti, bi, t1 - t0, b1 - b0)
                    # a streamed chunk's buffered arrays are handed to the writers before its
                    # visibilities are read, so the next chunk can take the same set; others alternate
                    slot = 0 if streams else 1 - slot
                    free(slot)
                    retire(2)
                    if buffers[slot] is None:
                        buffers[slot] = msread.block_buffers(spec, ct, cb)
                    buf = buffers[slot]
                    # chunk-shaped views of the buffers; the block is their first t1 - t0 times
                    chunks = {var: buf[var][:ct * cb * int(np.prod(a.shape[2:]))].reshape(
                        (ct, cb, *a.shape[2:])) for var, a in arrays.items()} if whole else {}
                    coords = {var: (t0 // ct, b0 // cb) + (0,) * (a.ndim - 2) for var, a in arrays.items()}
                    streamed: dict[str, tuple[int, list[Future]]] = {}
                    n_streamed = [0]  # cells handed to the writers
                    if streams:
                        for var, f in files.items():
                            if f is not None and f.raw:
                                fd = f.open(coords[var])
                                open_fds.add(fd)
                                streamed[var] = (fd, [])

                    reading = in_use[slot]  # the writes that read this buffer set
                    early: set[str] = set()  # written while the visibilities are still read
                    hooks = {}
                    if streamed:
                        hooks = {"on_batch": partial(stream_batch, streamed, chunks, n_streamed, ring,
                                                     reading),
                                 "on_others": partial(write_others, files, streamed, chunks, coords, t1 - t0,
                                                      reading, early)}
                        if "VISIBILITY" in streamed:
                            hooks["vis_batch"] = lambda c0, c1, ring=ring: ring.take(c1 - c0)
                    block = msread.read_block(spec, rows, ti, bi, t1 - t0, b1 - b0, plan.times[t0:t1],
                                              buffers=buf, **hooks)
                    finishing: list[Future] = []  # the writes that read only the ring
                    for var, a in arrays.items():
                        f = files[var]
                        if var in early:
                            continue
                        if var in streamed:
                            fd, batches = streamed[var]
                            finishing.append(pool.submit(finish_raw, f, fd, batches, (ct, cb, *a.shape[2:]),
                                                         t1 - t0, n_streamed))
                        elif f is not None and whole:
                            reading.append(pool.submit(write_chunk, f, coords[var], chunks[var], t1 - t0))
                        else:
                            reading.append(pool.submit(write_zarr, a, block[var], t0, t1, b0, b1))
                    pending.append([*reading, *finishing])
            for slot in (0, 1):
                free(slot)
            retire(0)
        except BaseException:
            pool.shutdown(wait=True, cancel_futures=True)
            raise
        finally:
            for fd in list(open_fds):
                os.close(fd)
            if bar is not None:
                bar.close()


def _write_fill(fd: int, files: ChunkFiles, row_shape: tuple[int, ...], start_row: int, n_rows: int) -> None:
    """Write ``n_rows`` rows of the fill value from row ``start_row`` of a raw chunk file,
    a few MB at a time (an edge chunk's padding; no chunk-sized buffer)."""
    row = np.full(row_shape, files.fill_value, dtype=files.dtype)
    step = max(1, FILL_PIECE_BYTES // max(1, row.nbytes))
    piece = np.broadcast_to(row, (min(step, n_rows), *row_shape)).copy()
    for r in range(0, n_rows, step):
        n = min(step, n_rows - r)
        ChunkFiles.write_at(fd, piece[:n], (start_row + r) * row.nbytes)


class _Stopped(Exception):
    """A cluster task's fill ended early because the conversion failed elsewhere."""


#: Fill tasks per worker thread of a cluster: a few, so a slow worker (or one that is
#: restarted) delays the end by a fraction of its share, and each task's fixed costs
#: (opening the store and the MS, its buffers' first touch) are paid a few times per thread.
TASKS_PER_THREAD = 3

#: Longest wait, seconds, for the other tasks of a failed conversion to stop (each checks
#: before every chunk) before the store is removed.
STOP_WAIT_S = 60.0

_TABLE_USERS: dict[str, int] = {}
_TABLE_USERS_LOCK = threading.Lock()


@contextlib.contextmanager
def _tables_in_use(path: str) -> Iterator[None]:
    """Keep the MS's cached tables (:mod:`xstack.io.msread`: one per table per process) open
    while any fill task of this process reads them; the last one to end closes them.

    A worker with several threads runs several tasks at once: they share the process's one
    reader (under msread's lock) rather than each closing it under the others. Closing after
    the last task (rather than keeping them for the worker's lifetime) frees the file handles
    and the table caches, and a later convert of a rewritten MS never reads a stale table.
    """
    with _TABLE_USERS_LOCK:
        _TABLE_USERS[path] = _TABLE_USERS.get(path, 0) + 1
    try:
        yield
    finally:
        with _TABLE_USERS_LOCK:
            left = _TABLE_USERS.pop(path) - 1
            if left:
                _TABLE_USERS[path] = left
            else:
                msread.close_tables(path)


def _restrict(plan: PartitionPlan, ct: int, i0: int, i1: int) -> PartitionPlan:
    """``plan`` with only the rows of time chunks ``i0:i1`` (what a fill task is sent)."""
    import dataclasses

    r0, r1 = np.searchsorted(plan.t_index, [i0 * ct, min(i1 * ct, plan.times.size)])
    return dataclasses.replace(plan, rows=plan.rows[r0:r1], t_index=plan.t_index[r0:r1],
                               b_index=plan.b_index[r0:r1])


def task_ranges(plans: list[PartitionPlan], sizes: list[tuple[int, int]], n_tasks: int
                ) -> list[list[tuple[int, int, int]]]:
    """Split the chunks into about ``n_tasks`` tasks of about equal chunk counts.

    Each task is a list of ``(partition index, first time chunk, end time chunk)``: rows of
    whole chunks (every baseline chunk of a time chunk), contiguous, in partition order; a
    task may end one partition and start the next. Never more tasks than time chunks.
    """
    per_row = [-(-p.antenna1.size // cb) for p, (_, cb) in zip(plans, sizes)]
    n_rows = [-(-p.times.size // ct) for p, (ct, _) in zip(plans, sizes)]
    total = sum(r * w for r, w in zip(n_rows, per_row))
    target = max(1, -(-total // max(1, min(int(n_tasks), sum(n_rows)))))
    tasks: list[list[tuple[int, int, int]]] = []
    current: list[tuple[int, int, int]] = []
    filled = 0
    for k, (rows, weight) in enumerate(zip(n_rows, per_row)):
        i = 0
        while i < rows:
            take = min(rows - i, max(1, -(-(target - filled) // weight)))
            current.append((k, i, i + take))
            filled += take * weight
            i += take
            if filled >= target:
                tasks.append(current)
                current, filled = [], 0
    if current:
        tasks.append(current)
    return tasks


def _fill_task(loc: Any, ms_path: str, plans: list[PartitionPlan], specs: list[msread.BlockSpec],
               sizes: list[tuple[int, int]], work: list[tuple[int, int, int]], stop_name: str,
               out_name: str) -> int:
    """One cluster task: open the store and the MS in this process, fill the chunks of
    ``work`` (:func:`_fill`). Returns the number of chunks written."""
    error: XstackError | None = None
    try:
        return _fill_part(loc, ms_path, plans, specs, sizes, work, stop_name, out_name)
    except XstackError as exc:
        error = exc
    # the error goes back to the client pickled, with what it was raised from (zarr's,
    # casacore's exceptions): some of those do not unpickle, and distributed then sends a
    # plain Exception instead - which the command line would print with a traceback
    error.__context__ = error.__cause__ = None
    raise error


def _fill_part(loc: Any, ms_path: str, plans: list[PartitionPlan], specs: list[msread.BlockSpec],
               sizes: list[tuple[int, int]], work: list[tuple[int, int, int]], stop_name: str,
               out_name: str) -> int:
    import zarr

    if not os.path.isdir(ms_path):
        raise XstackError(f"{ms_path}: the MeasurementSet is not visible on a dask worker (workers "
                          "must see the MS path: a shared filesystem)")
    try:
        if loc.local and not os.path.isdir(loc.path):
            raise FileNotFoundError(loc.path)
        root = zarr.open_group(loc.zarr_store(), mode="r+", zarr_format=3)
    except (FileNotFoundError, zarr.errors.GroupNotFoundError):
        raise XstackError(f"{out_name}: the output is not visible on a dask worker (workers must "
                          "see the output location: a shared filesystem or an object store)") from None

    stop = None

    def should_stop() -> bool:
        nonlocal stop
        from distributed import Event

        if stop is None:
            stop = Event(stop_name)
        return bool(stop.is_set())

    with _tables_in_use(ms_path):
        _fill(root, plans, specs, sizes, False, "", work=work, should_stop=should_stop)
    return sum((i1 - i0) * -(-plans[k].antenna1.size // sizes[k][1]) for k, i0, i1 in work)


def _fill_on_cluster(client: Any, loc: Any, ms_path: str, plans: list[PartitionPlan],
                     specs: list[msread.BlockSpec], sizes: list[tuple[int, int]], progress: bool,
                     description: str, out_name: str) -> None:
    """Fill the store's chunks in tasks on the cluster of ``client``; return when all are written.

    Each task gets only its partitions' rows (:func:`_restrict`) and opens the store and the
    MS itself. A worker that dies mid-task has its task rerun elsewhere by the scheduler
    (chunk files are rewritten whole, so a rerun is harmless); a task that raises fails the
    conversion: the others are told to stop (a ``distributed.Event``, checked before every
    chunk) and waited for, so nothing writes into the store after it is removed.
    """
    from distributed import Event, wait

    threads = max(1, sum(client.nthreads().values()))
    tag = uuid.uuid4().hex[:12]
    stop_name = f"xstack-convert-stop-{tag}"
    futures = []
    for i, ranges in enumerate(task_ranges(plans, sizes, TASKS_PER_THREAD * threads)):
        # one restricted plan per range: a task is sent its rows only, never the whole index
        sub = [_restrict(plans[k], sizes[k][0], i0, i1) for k, i0, i1 in ranges]
        sub_work = [(j, i0, i1) for j, (_k, i0, i1) in enumerate(ranges)]
        futures.append(client.submit(
            _fill_task, loc, ms_path, sub, [specs[k] for k, _, _ in ranges],
            [sizes[k] for k, _, _ in ranges], sub_work, stop_name, out_name,
            key=f"xstack-convert-fill-{i}-{tag}", pure=False))
    try:
        _follow(client, futures, progress, description)
        client.gather(futures)
    except BaseException:
        event = Event(stop_name, client=client)
        event.set()
        with contextlib.suppress(Exception):
            wait(futures, timeout=STOP_WAIT_S)
        client.cancel(futures)
        with contextlib.suppress(Exception):
            event.clear()
        raise
    finally:
        del futures


def _follow(client: Any, futures: list[Any], progress: bool, description: str) -> None:
    """A progress bar advanced by the scheduler per finished task (returns when all ended)."""
    from xstack import _progress

    if not (progress and _progress._allowed):
        return
    bar = _progress.tqdm(total=len(futures), desc=description, file=sys.stderr, unit="task",
                         leave=False, dynamic_ncols=True)
    try:
        _progress._distributed_bar_class()(futures, bar, scheduler=client.scheduler.address,
                                           interval="100ms")
    finally:
        bar.close()


def spectral_window_frames(path: str) -> list[str]:
    """The frequency frame of each spectral window (``MEAS_FREQ_REF``, casacore's names;
    TOPO where the column is missing or undefined), as :mod:`xstack.frames` names them."""
    import casacore.tables as pt

    from xstack.frames import frame_from_meas_freq_ref

    with msread.CASACORE_LOCK, pt.table(f"{path}/SPECTRAL_WINDOW", ack=False) as tab:
        if "MEAS_FREQ_REF" not in tab.colnames():
            return ["TOPO"] * tab.nrows()
        return [frame_from_meas_freq_ref(tab.getcell("MEAS_FREQ_REF", k))
                for k in range(tab.nrows())]


def release_free_memory() -> None:
    """Give the C heap's free memory back to the operating system (glibc only; else nothing).

    Planning a large MS makes many row-sized temporaries (a 4 GB MS: ~130 MB); glibc keeps
    such freed memory in the process once its mmap threshold has risen, so without this
    it would sit under the conversion's peak (measured: benchmarks/bench_convert.py).
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if not name:
        return
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):  # not glibc (macOS, musl)
        return
    trim(0)


def convert_ms(
    ms: str | os.PathLike,
    out: str | os.PathLike,
    *,
    datacolumn: str = "DATA",
    chunks: Mapping[str, int] | str | None = None,
    overwrite: bool = False,
    progress: bool = False,
    storage_options: Mapping[str, Any] | None = None,
) -> Path | str:
    """Convert a MeasurementSet into an xstack zarr store (one partition per window x field).

    Parameters
    ----------
    ms
        Path of the MeasurementSet (read only, never modified).
    out
        Output ``.zarr`` directory; written atomically (temporary name, then renamed). Or
        any fsspec URL (``s3://bucket/out.zarr``...): written in place through zarr, the
        completion flag last (an interrupted conversion never opens as a store).
    datacolumn
        Visibility column: ``DATA``, ``CORRECTED_DATA`` or ``MODEL_DATA``.
    chunks
        ``{"time": N, "baseline_id": M}`` (or ``"time=N,baseline_id=M"``); missing sizes are
        chosen so a VISIBILITY chunk holds ~128 MB. Frequency and polarization stay whole.
    overwrite
        Replace an existing ``out``.
    progress
        Progress bar on stderr.
    storage_options
        Options of the output URL's filesystem (:func:`xstack._fs.locate`).

    Returns
    -------
    pathlib.Path or str
        ``out`` (the URL for a remote store). Open it with :func:`xstack.open_store`.

    Notes
    -----
    WEIGHT comes from WEIGHT_SPECTRUM where it holds data, else WEIGHT (broadcast over
    channels), else 1/SIGMA^2; FLAG is FLAG or FLAG_ROW. Missing (time, baseline) cells are
    NaN in VISIBILITY, zero in WEIGHT, flagged, and zero in UVW. Phase centers are
    converted to ICRS (J2000 is taken as ICRS). Visibilities stay complex128 if the column
    is double precision.

    Raises
    ------
    XstackError
        If ``ms`` is not a MeasurementSet, the column does not exist, the MS has no rows,
        or ``out`` exists without ``overwrite``. Nothing is written then.
    """
    from xstack import __version__

    ms_path = msread.check_ms(ms)
    out = check_output(out, overwrite, storage_options)
    requested_chunks = parse_chunks(chunks)
    path = str(ms_path.resolve())
    if isinstance(out, Path) and os.path.abspath(out) == path:
        raise XstackError("the output store must not be the MeasurementSet itself")
    try:
        column, vis_dtype = check_datacolumn(path, datacolumn)
        meta = msread.read_meta(path)
        spw_frames = spectral_window_frames(path)
        index = msread.read_index(path, INDEX_COLUMNS)
        if index["TIME"].size == 0:
            raise XstackError(f"{ms}: the MeasurementSet has no rows")
        plans = plan_partitions(index, meta, str(ms))
        del index
        release_free_memory()
        itemsize = np.dtype(vis_dtype).itemsize
        partitions = {}
        specs: list[msread.BlockSpec] = []
        sizes: list[tuple[int, int]] = []
        for plan in plans:
            spec = block_spec(path, plan, meta, column, vis_dtype)
            ct, cb = chunk_sizes(plan.times.size, plan.antenna1.size, spec.n_channels, spec.n_pols,
                                  itemsize, requested_chunks)
            arrays = _placeholders(plan, spec, ct, cb)
            specs.append(spec)
            sizes.append((ct, cb))
            spw = int(meta.ddid_spw[plan.ddid])
            pols = meta.pol_names[int(meta.ddid_pol[plan.ddid])]
            attrs = {"data_description_id": plan.ddid, "weight_source": spec.weight_source,
                     "spectral_window_name": meta.spw_names[spw],
                     "source_phase_center_frame": meta.phase_center_frame}
            if plan.scan is not None:
                attrs["scan_number"] = plan.scan
            ds = new_partition(
                visibility=arrays["VISIBILITY"], weight=arrays["WEIGHT"], flag=arrays["FLAG"],
                uvw=arrays["UVW"], time=plan.times, antenna1=plan.antenna1, antenna2=plan.antenna2,
                antenna_names=meta.antenna_names, antenna_positions=meta.antenna_positions,
                dish_diameters=meta.dish_diameters, frequency=meta.spw_freqs[spw],
                channel_width=meta.spw_widths[spw], polarization=pols,
                phase_center=tuple(meta.phase_centers[plan.field_id]),
                field_name=meta.field_names[plan.field_id], field_id=plan.field_id,
                spectral_window_id=spw, telescope_name=meta.telescope_name,
                integration_time=plan.interval, attrs=attrs,
                frequency_frame=spw_frames[spw] if spw < len(spw_frames) else "TOPO")
            ds = ds.assign_coords(scan_number=("time", plan.scan_of_time))
            ds = ds.assign(
                TIME_CENTROID=(("time", "baseline_id"), arrays["TIME_CENTROID"],
                               {"units": "s", "scale": "utc", "format": "mjd_seconds"}),
                EFFECTIVE_INTEGRATION_TIME=(("time", "baseline_id"), arrays["EFFECTIVE_INTEGRATION_TIME"],
                                            {"units": "s"}))
            partitions[plan.name] = ds
        root_attrs = {"source_ms": path, "data_column": column, "xstack_version": __version__,
                      "created_by": f"xstack {__version__} convert_ms"}
        client = active_client()
        with region_store(partitions, out, overwrite=overwrite, attrs=root_attrs, encoding=_encoding(),
                          storage_options=storage_options, with_location=True) as (root, loc):
            if client is None:
                _fill(root, plans, specs, sizes, progress, f"convert {ms_path.name}")
            else:  # the client plans and creates the store; the workers read and write the chunks
                _fill_on_cluster(client, loc, path, plans, specs, sizes, progress,
                                 f"convert {ms_path.name}", str(out))
        return out
    finally:
        msread.close_tables(path)
