"""``convert`` on a dask.distributed cluster (issue 14): the chunks are read and written by
tasks in the worker processes, and the store is the single-process convert's, bit for bit.

One ``LocalCluster`` of 2 worker processes with 1 thread each serves the module (the pattern
of tests/test_cluster.py); its scheduler runs in this process, so a scheduler plugin counts
the tasks that finished there - the proof that the reading happened on the workers (none did
before: the MS was read in the calling process). The reference everywhere is the same
conversion without a client (one process), compared file by file and array by array.
"""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zarr

from xstack._cluster import active_client, use_cluster
from xstack.cli import main
from xstack.errors import XstackError
from xstack.io import convert as convert_mod
from xstack.io.convert import chunk_blocks, convert_ms, task_ranges
from xstack.schema import open_store
from xstack.testing import make_test_ms

distributed = pytest.importorskip("distributed")
from _cluster_helpers import TaskCounter, local_cluster  # noqa: E402

FILL_KEY = "xstack-convert-fill"
#: Attributes that hold the time of writing (they differ between any two conversions).
DATES = ("creation_date", "date", "release_date")

VARIANTS = {
    # one partition, time-ordered rows: every chunk streamed, 6 time chunks over the tasks
    "regular": (dict(n_times=11, seed=5), {"time": 2}),
    # 4 partitions (2 windows x 2 fields), missing rows and baselines (padded cells), edge
    # chunks in time and baseline (the latter written through zarr rather than as chunk files)
    "mosaic_irregular": (dict(n_fields=2, n_spws=2, n_channels=[3, 5], n_times=5, n_antennas=7,
                              missing_baselines=3, missing_rows=0.15, flag_row_fraction=0.1,
                              seed=7), {"time": 3, "baseline_id": 12}),
}


class FillCounter(TaskCounter):
    """The scheduler's tasks, and which of them filled chunks."""

    def fills(self, since: int = 0) -> list[str]:
        return [k for k in self.keys[since:] if k.startswith(FILL_KEY)]


@pytest.fixture(scope="module")
def cluster():
    with local_cluster(FillCounter()) as cluster:
        yield cluster


@pytest.fixture(scope="module")
def mss(tmp_path_factory):
    """The test MSs and their single-process conversions (the reference)."""
    tmp = tmp_path_factory.mktemp("convert_dist")
    out = {}
    for name, (kw, chunks) in VARIANTS.items():
        ms = make_test_ms(tmp / f"{name}.ms", **kw)
        assert active_client() is None
        ref = convert_ms(ms, tmp / f"{name}-ref.zarr", chunks=chunks)
        out[name] = (ms, ref, chunks)
    return out


def _strip_dates(doc):
    if isinstance(doc, dict):
        return {k: _strip_dates(v) for k, v in doc.items() if k not in DATES}
    if isinstance(doc, list):
        return [_strip_dates(v) for v in doc]
    return doc


def _arrays(group, prefix=""):
    """{path: zarr array} of every array in the store, at any depth."""
    out = {}
    for name, member in group.members():
        if isinstance(member, zarr.Array):
            out[prefix + name] = member
        else:
            out.update(_arrays(member, f"{prefix}{name}/"))
    return out


def assert_same_store(got, ref) -> None:
    """The same files with the same bytes (metadata: but for the dates of writing), and every
    array of every partition bitwise equal (NaN padding included)."""
    got, ref = Path(got), Path(ref)
    fg = {p.relative_to(got).as_posix(): p for p in got.rglob("*") if p.is_file()}
    fr = {p.relative_to(ref).as_posix(): p for p in ref.rglob("*") if p.is_file()}
    assert sorted(fg) == sorted(fr)
    for rel, path in fr.items():
        if path.name == "zarr.json":
            got_doc, ref_doc = (json.loads(p.read_bytes()) for p in (fg[rel], path))
            assert _strip_dates(got_doc) == _strip_dates(ref_doc), rel
        else:
            assert fg[rel].read_bytes() == path.read_bytes(), rel
    ag = _arrays(zarr.open_group(got, mode="r"))
    ar = _arrays(zarr.open_group(ref, mode="r"))
    assert sorted(ag) == sorted(ar) and any(k.endswith("/VISIBILITY") for k in ar)
    for name, a in ar.items():
        x, y = ag[name][...], a[...]
        assert x.dtype == y.dtype and x.shape == y.shape, name
        if x.dtype.kind in "fcb" or x.dtype.kind in "iu":
            assert x.tobytes() == y.tobytes(), name  # bitwise (NaN patterns too)
        else:
            assert np.array_equal(x, y), name
    assert open_store(got) is not None  # complete: opens as a store


# --------------------------------------------------------------------------- splitting
def test_task_ranges_cover_every_chunk_once(tmp_path):
    """Plain bookkeeping: the tasks' ranges cover each (partition, time chunk) exactly once, in
    order, never a partial time chunk, about the asked-for number of tasks."""
    from xstack.io import msread

    ms = make_test_ms(tmp_path / "in.ms", **VARIANTS["mosaic_irregular"][0])
    index = msread.read_index(str(ms), convert_mod.INDEX_COLUMNS)
    plans = convert_mod.plan_partitions(index, msread.read_meta(str(ms)), "test")
    msread.close_tables(str(ms))
    sizes = [(2, 6)] * len(plans)  # 3 time chunks x 3 baseline chunks per partition
    n_rows = [-(-p.times.size // 2) for p in plans]
    for n_tasks in (1, 2, 5, 6, 12, 1000):
        tasks = task_ranges(plans, sizes, n_tasks)
        assert 1 <= len(tasks) <= max(n_tasks, 1) + 1 and len(tasks) <= sum(n_rows)
        if n_tasks <= sum(n_rows):
            assert len(tasks) >= n_tasks // 2, (n_tasks, len(tasks))
        flat = [(k, i) for task in tasks for k, i0, i1 in task for i in range(i0, i1)]
        assert flat == [(k, i) for k, n in enumerate(n_rows) for i in range(n)], n_tasks
        # a task's restricted plan yields the same blocks as the whole plan does for its range
        for task in tasks:
            for k, i0, i1 in task:
                whole = [b for b in chunk_blocks(plans[k], 2, 6) if i0 * 2 <= b[0] < i1 * 2]
                part = list(chunk_blocks(convert_mod._restrict(plans[k], 2, i0, i1), 2, 6, (i0, i1)))
                assert len(whole) == len(part)
                for a, b in zip(whole, part):
                    assert a[:4] == b[:4] and all(np.array_equal(x, y) for x, y in zip(a[4:], b[4:]))


# ------------------------------------------------------------- two threads in one process
def test_threads_of_one_worker_share_one_reader(mss, tmp_path, monkeypatch):
    """A worker with 2 threads (in-process here, so the reads can be watched): its fill tasks
    run at once, never more than one casacore table object of the MS is open in the process,
    and the last task to end closes it. Runs before the module's cluster is started."""
    import casacore.tables as pt

    from xstack.io import msread

    ms, ref, chunks = mss["regular"]
    path = str(Path(ms).resolve())
    live, peak, readers = [0], [0], set()
    real_table, real_cached = pt.table, msread._table

    class Counted:
        """A casacore table of the MS, counted while open."""

        def __init__(self, name, *args, **kwargs):
            self._tab = real_table(name, *args, **kwargs)
            live[0] += 1
            peak[0] = max(peak[0], live[0])

        def __getattr__(self, attr):
            return getattr(self._tab, attr)

        def close(self):
            live[0] -= 1
            self._tab.close()

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.close()

    def table(name, *args, **kwargs):
        if str(name) == path:
            return Counted(name, *args, **kwargs)
        return real_table(name, *args, **kwargs)

    def cached(p):
        if p == path:
            readers.add(threading.get_ident())
            time.sleep(0.002)  # let the other thread's task interleave
        return real_cached(p)

    monkeypatch.setattr(pt, "table", table)
    monkeypatch.setattr(msread, "_table", cached)
    monkeypatch.setattr(msread, "READ_BATCH_BYTES", 2000)  # several reads per chunk
    main_thread = threading.get_ident()
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=":0") as lc, use_cluster(lc.scheduler_address):
        out = convert_ms(ms, tmp_path / "got.zarr", chunks=chunks)
    assert len(readers - {main_thread}) == 2, "the fill tasks did not run in two worker threads"
    assert peak[0] == 1 and live[0] == 0  # one reader at a time, closed at the end
    assert path not in msread._OPEN_TABLES and not convert_mod._TABLE_USERS
    assert_same_store(out, ref)


def test_failed_task_fails_the_convert_and_leaves_nothing(mss, tmp_path, monkeypatch):
    """A task that raises (in-process workers, so the failure can be injected): the convert
    raises that error, the other task stops before its next chunk, and nothing is left - no
    store, no temporary."""
    from xstack.io import msread

    ms, _, chunks = mss["regular"]
    calls = []
    real = msread.read_block

    def failing(*args, **kwargs):
        calls.append(threading.get_ident())
        if len(calls) == 3:
            raise XstackError("injected read failure")
        # a read already under way when the failure happens takes long enough for the client
        # to hear of it and set the stop flag before any later task starts (no race)
        time.sleep(0.05 if len(calls) < 3 else 1.0)
        return real(*args, **kwargs)

    monkeypatch.setattr(msread, "read_block", failing)
    work = tmp_path / "out"
    work.mkdir()
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=":0") as lc, use_cluster(lc.scheduler_address):
        with pytest.raises(XstackError, match="injected read failure"):
            convert_ms(ms, work / "got.zarr", chunks=chunks)
        time.sleep(0.3)  # anything still writing would show now
    assert list(work.iterdir()) == []
    assert len(calls) < 6  # stopped: not every chunk was read


def test_memory_url_with_in_process_workers(mss):
    """Threads-only workers share the client's process, so a ``memory://`` output works: the
    chunks go through zarr (no chunk files there) and equal the local reference's."""
    ms, ref, chunks = mss["mosaic_irregular"]
    url = "memory://convert-dist-threads/got.zarr"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=":0") as lc, use_cluster(lc.scheduler_address):
        assert convert_ms(ms, url, chunks=chunks) == url
    fills = [k for k in lc.scheduler.task_prefixes if k.startswith(FILL_KEY)]
    assert fills, "no fill task ran"
    got = _arrays(zarr.open_group(zarr.storage.FsspecStore.from_url(url), mode="r"))
    want = _arrays(zarr.open_group(ref, mode="r"))
    assert sorted(got) == sorted(want)
    for name, a in want.items():
        assert got[name][...].tobytes() == a[...].tobytes(), name
    assert open_store(url) is not None


# --------------------------------------------------------------------------- the cluster
@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_convert_on_cluster_equals_single_process(cluster, mss, tmp_path, variant):
    ms, ref, chunks = mss[variant]
    since = len(cluster.counter.keys)
    with use_cluster(cluster.scheduler_address):
        out = convert_ms(ms, tmp_path / "got.zarr", chunks=chunks)
    fills = cluster.counter.fills(since)
    # 2 workers x 1 thread x TASKS_PER_THREAD tasks (fewer only if there are fewer time chunks)
    assert len(fills) >= 2, fills
    assert set(cluster.counter.workers[since:]) <= set(cluster.scheduler.workers)
    assert_same_store(out, ref)


def test_convert_on_cluster_to_a_memory_url_is_refused_by_the_workers(cluster, mss):
    """memory:// lives in one process: worker processes cannot see it - one clear error,
    nothing that opens."""
    ms, _, chunks = mss["regular"]
    url = "memory://convert-dist/got.zarr"
    with use_cluster(cluster.scheduler_address), \
            pytest.raises(XstackError, match="not visible on a dask worker"):
        convert_ms(ms, url, chunks=chunks)
    with pytest.raises(XstackError):
        open_store(url)


def test_progress_bar_counts_the_fill_tasks(cluster, mss, tmp_path, monkeypatch):
    from xstack import _progress

    bars = []

    class Recorder:
        def __init__(self, *args, total=None, **kwargs):
            self.total, self.n, self.closed = total, 0, False
            bars.append(self)

        def update(self, n=1):
            self.n += n

        def close(self):
            self.closed = True

    monkeypatch.setattr(_progress, "tqdm", Recorder)
    previous = _progress.set_allowed(True)
    ms, ref, chunks = mss["regular"]
    since = len(cluster.counter.keys)
    try:
        with use_cluster(cluster.scheduler_address):
            out = convert_ms(ms, tmp_path / "got.zarr", chunks=chunks, progress=True)
    finally:
        _progress.set_allowed(previous)
    n_fills = len(cluster.counter.fills(since))
    assert len(bars) == 1 and n_fills >= 2
    assert bars[0].total == n_fills and bars[0].n == n_fills and bars[0].closed
    assert_same_store(out, ref)


def test_cli_scheduler_converts_on_the_cluster(cluster, mss, tmp_path, capsys):
    ms, ref, _ = mss["mosaic_irregular"]
    argv = ["convert", str(ms), "{}", "--chunks", "time=3,baseline_id=12", "--json", "--no-progress"]
    since = len(cluster.counter.keys)
    assert main([a.format(tmp_path / "got.zarr") for a in argv]
                + ["--scheduler", cluster.scheduler_address]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert len(cluster.counter.fills(since)) >= 2
    assert active_client() is None  # the command's connection is closed
    assert len(doc["partitions"]) == 4
    assert_same_store(tmp_path / "got.zarr", ref)


# --------------------------------------------------------------------------- a killed worker
@pytest.mark.slow
def test_killed_worker_mid_convert(tmp_path):
    """SIGKILL one of 2 workers as soon as it starts a fill task: the nanny restarts it and
    the scheduler reruns its tasks (chunk files are rewritten whole), so the store is the
    single-process one bit for bit - or, if the scheduler gave up, a one-line error and
    nothing that opens."""
    import signal

    ms = make_test_ms(tmp_path / "in.ms", n_antennas=12, n_times=24, n_channels=32,
                      pols=("XX", "XY", "YX", "YY"), seed=3)
    chunks = {"time": 1}
    ref = convert_ms(ms, tmp_path / "ref.zarr", chunks=chunks)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0") as lc:
        counter = FillCounter()
        lc.scheduler.add_plugin(counter)
        killed = []

        def kill_one() -> None:
            """Kill the worker that runs a fill task, once it has run it for a moment."""
            with distributed.Client(lc, set_as_default=False) as c:
                pids = c.run(os.getpid)
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                running = [ts for ts in list(lc.scheduler.tasks.values())
                           if str(ts.key).startswith(FILL_KEY) and ts.state == "processing"
                           and ts.processing_on is not None]
                if running:
                    time.sleep(0.05)  # mid-task: reading the MS, writing chunks
                    os.kill(pids[running[0].processing_on.address], signal.SIGKILL)
                    killed.append(len(counter.fills()))
                    return
                time.sleep(0.002)

        killer = threading.Thread(target=kill_one, daemon=True)
        error = None
        with use_cluster(lc.scheduler_address):
            killer.start()
            try:
                out = convert_ms(ms, tmp_path / "got.zarr", chunks=chunks)
            except XstackError as exc:  # pragma: no cover - the scheduler gave up
                error = exc
            except Exception as exc:  # noqa: BLE001  # pragma: no cover
                error = exc
        killer.join(5)
    assert killed, "no worker was killed"
    n_fills = len(counter.fills())
    print("killed a worker after", killed[0], "fill tasks finished; fill tasks finished:", n_fills)
    if error is None:
        assert n_fills > killed[0]  # the conversion went on after the kill
        # the killed worker's task(s) were sent to a worker again
        starts = [k for k in counter.processing if k.startswith(FILL_KEY)]
        assert len(starts) > len(set(starts)), "no fill task was rerun"
        assert_same_store(out, ref)
    else:
        assert "\n" not in str(error).strip()
        assert not (tmp_path / "got.zarr").exists()
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".got.zarr")]
