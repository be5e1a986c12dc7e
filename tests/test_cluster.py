"""Every stage on a dask.distributed cluster (issue 14): same numbers as the threaded run,
the command line reaches the cluster (``--scheduler``, ``--workers``, ``DASK_SCHEDULER_ADDRESS``),
numba threads follow the worker's threads, progress bars follow the scheduler.

One ``LocalCluster`` of 2 worker processes with 1 thread each serves the module. Its
scheduler runs in this process, so a scheduler plugin counts the tasks it saw: the proof that
work went there. The reference everywhere is the same call on dask's threaded scheduler
(no client).
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time

import cloudpickle
import dask
import dask.array as da
import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, make_stack_partition

import xstack
from xstack._cluster import active_client, use_cluster
from xstack.cli import main
from xstack.coords import lm_to_radec
from xstack.errors import OptionError
from xstack.schema import open_store, write_store

distributed = pytest.importorskip("distributed")
from _cluster_helpers import TaskCounter, local_cluster  # noqa: E402

# the small data's warnings (weights vs scatter, few targets) are not what is tested here
pytestmark = pytest.mark.filterwarnings("ignore::xstack.errors.XstackWarning")

# workers are other processes: send this module's functions by value, not by import
cloudpickle.register_pickle_by_value(sys.modules[__name__])


@pytest.fixture(scope="module")
def cluster():
    with local_cluster() as cluster:
        yield cluster


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A small store of 4 VISIBILITY chunks with a 50 mJy source and its catalogue."""
    tmp = tmp_path_factory.mktemp("cluster")
    ra, dec = lm_to_radec(2e-3, -1e-3, *VLA_CENTER)
    ra2, dec2 = lm_to_radec(-1e-3, 2e-3, *VLA_CENTER)
    ds = make_stack_partition(n_time=16, n_ant=7, n_chan=3, sigma=0.01, seed=21,
                              sources=[(ra, dec, 0.05), (ra2, dec2, 0.03)])
    store = tmp / "data.zarr"
    write_store({"spw0_field0": ds.chunk({"time": 4})}, store)
    cat = tmp / "cat.csv"
    cat.write_text("ra,dec\n" + "".join(f"{float(np.degrees(a))!r},{float(np.degrees(d))!r}\n"
                                        for a, d in [(ra, dec), (ra2, dec2)]))
    return store, cat


def _tasks(cluster) -> int:
    return cluster.counter.finished


def _same(got, ref, rel: float = 1e-12) -> None:
    """Equal JSON-like results: floats to ``rel`` (0: bitwise), paths with 'got' for 'ref', the
    rest exactly."""
    if isinstance(ref, dict):
        assert isinstance(got, dict) and set(got) == set(ref), (got, ref)
        for k in ref:
            _same(got[k], ref[k], rel)
    elif isinstance(ref, (list, tuple)):
        assert len(got) == len(ref)
        for g, r in zip(got, ref, strict=True):
            _same(g, r, rel)
    elif isinstance(ref, float):
        assert got == pytest.approx(ref, rel=rel, abs=0, nan_ok=True)
    elif isinstance(ref, str):
        assert got.replace("got", "ref") == ref
    else:
        assert got == ref


# --------------------------------------------------------------------------- Python API
def test_use_cluster_makes_the_client_the_default(cluster):
    assert active_client() is None
    with use_cluster(cluster.scheduler_address) as client:
        assert active_client() is client
        before = _tasks(cluster)
        assert da.ones(10, chunks=2).sum().compute() == 10
        assert _tasks(cluster) > before
    assert active_client() is None  # closed at the end of the block


def test_uvstack_on_cluster_equals_threaded(cluster, data, tmp_path):
    """Flux and weights bitwise equal although the threaded run's kernels use every core and
    the workers' one thread each (the flux sums are fixed-size row blocks added in order:
    tests/test_uvstack_threads_bitwise.py); the stacked visibilities too."""
    store, cat = data
    ref = xstack.stack_uv(store, str(cat), out=tmp_path / "ref.zarr")
    before = _tasks(cluster)
    with use_cluster(cluster.scheduler_address):
        got = xstack.stack_uv(store, str(cat), out=tmp_path / "got.zarr")
    assert _tasks(cluster) > before
    _same(got.to_dict(), ref.to_dict(), rel=0)
    a = open_store(tmp_path / "ref.zarr")["spw0_field0"]["VISIBILITY"].values
    b = open_store(tmp_path / "got.zarr")["spw0_field0"]["VISIBILITY"].values
    np.testing.assert_array_equal(a, b)  # per-row phasors: no reduction, bitwise
    # fit of the same stacked store: bitwise (its reads go to the cluster too)
    fref = xstack.fit_uv(tmp_path / "ref.zarr", model="point")
    with use_cluster(cluster.scheduler_address):
        fgot = xstack.fit_uv(tmp_path / "ref.zarr", model="point")
    assert fgot.to_dict() == fref.to_dict()


def test_make_image_on_cluster_equals_threaded(cluster, data):
    """The chunks are read and gridded by tasks on the workers (one per batch of chunks; more
    in tests/test_imaging_distributed.py), the partial images summed there."""
    store, _ = data
    ref = xstack.make_image(store, size=64, cell_arcsec=2.0)
    before = _tasks(cluster)
    with use_cluster(cluster.scheduler_address):
        got = xstack.make_image(store, size=64, cell_arcsec=2.0)
    # the gridding ran as a task on the cluster (before: read there, gridded in this process)
    grids = [k for k in cluster.counter.keys[before:] if k.startswith("xstack-image-grid")]
    assert len(grids) >= 1, cluster.counter.keys[before:]
    # the same batches, each gridded with one thread, summed in the same order: the same bits
    for a, b in ((got.image, ref.image), (got.psf, ref.psf)):
        np.testing.assert_array_equal(a, b)


def test_noise_on_cluster_equals_threaded(cluster, data):
    """Bitwise: same blocks, same order of the sums."""
    store, cat = data
    kw = dict(method="mc", realizations=4, seed=3)
    ref = xstack.estimate_noise(store, str(cat), **kw)
    with use_cluster(cluster.scheduler_address):
        got = xstack.estimate_noise(store, str(cat), **kw)
    assert got.noise_jy == ref.noise_jy
    np.testing.assert_array_equal(got.values, ref.values)


def test_export_on_cluster_equals_threaded(cluster, data, tmp_path):
    """Bitwise: the blocks are read on the workers (synchronous in-process before), casacore
    writes the same MS."""
    pt = pytest.importorskip("casacore.tables")
    store, _ = data
    ref = xstack.export_ms(store, tmp_path / "ref.ms")
    before = _tasks(cluster)
    with use_cluster(cluster.scheduler_address):
        got = xstack.export_ms(store, tmp_path / "got.ms")
    reads = [k for k in cluster.counter.keys[before:] if "VISIBILITY" in k]
    assert len(reads) >= 4, reads
    with pt.table(str(ref), ack=False) as a, pt.table(str(got), ack=False) as b:
        assert a.nrows() == b.nrows() > 0
        for col in ("DATA", "FLAG", "WEIGHT", "UVW", "TIME"):
            np.testing.assert_array_equal(b.getcol(col), a.getcol(col))


def test_bad_address_is_one_line_error(cluster):
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        t0 = time.perf_counter()
        with pytest.raises(OptionError) as exc, use_cluster("tcp://127.0.0.1:9"):
            pass
    assert time.perf_counter() - t0 < 10
    assert "\n" not in str(exc.value) and "tcp://127.0.0.1:9" in str(exc.value)
    with pytest.raises(OptionError, match="no scheduler file"), use_cluster("/nonexistent.json"):
        pass
    with pytest.raises(OptionError, match="not both"), use_cluster("tcp://x:1", workers=2):
        pass


def test_scheduler_file(cluster, tmp_path):
    path = tmp_path / "sched.json"
    path.write_text(json.dumps({"address": cluster.scheduler_address}))
    with use_cluster(str(path)) as client:
        assert client.scheduler.address == cluster.scheduler_address


def test_distributed_without_address_is_an_error(monkeypatch):
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    with dask.config.set(scheduler="distributed"), pytest.raises(OptionError, match="address"):
        with use_cluster():
            pass


# --------------------------------------------------------------------------- numba threads
def _threads_in_kernels() -> dict[str, int]:
    """In a task: numba's threads after each of xstack's kernel wrappers ran (reset before)."""
    import numba

    from xstack._scatter import pair_variance
    from xstack.noise import kernels as nk
    from xstack.uvstack import kernels as uk

    rng = np.random.default_rng(0)
    uvw = rng.normal(0, 100, (50, 3))
    freq = np.array([1.4e9, 1.5e9])
    l, m = np.array([1e-3, -1e-3]), np.array([0.0, 1e-3])
    n1 = np.sqrt(1 - l**2 - m**2) - 1
    vis = rng.normal(size=(50, 2, 1)) + 0j
    w = np.ones((50, 2, 1))
    f = np.zeros((50, 2, 1), bool)
    out = {}
    calls = {
        "uvstack.phasor": lambda: uk.phasor_from_coefficients(uvw, freq, l, m, n1,
                                                              np.ones((2, 2)) / 2),
        "uvstack.sums": lambda: uk.stack_sums(vis, w, f, np.ones((50, 2), complex)),
        "noise.positions": lambda: nk.position_sums(uvw, freq, vis[..., 0], w[..., 0], l, m, n1,
                                                    np.ones((2, 2))),
        "scatter": lambda: pair_variance(vis.reshape(5, 10, 2, 1), w.reshape(5, 10, 2, 1),
                                         f.reshape(5, 10, 2, 1)),
    }
    for name, call in calls.items():
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        call()
        out[name] = numba.get_num_threads()
    return out


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="needs 2 cores to tell 1 thread from all")
def test_numba_threads_follow_the_worker_threads(cluster):
    with distributed.Client(cluster, set_as_default=False) as client:
        futures = [client.submit(_threads_in_kernels, pure=False, workers=[a])
                   for a in client.scheduler_info()["workers"]]
        results = client.gather(futures)
    assert len(results) == 2
    for res in results:
        assert res == dict.fromkeys(res, 1), res  # 1 thread per worker, not every core
    # outside a worker the kernels keep every core
    import numba

    assert _threads_in_kernels()["uvstack.sums"] == numba.config.NUMBA_NUM_THREADS


# --------------------------------------------------------------------------- progress
def test_progress_bar_follows_the_scheduler(cluster, monkeypatch):
    from xstack import _progress

    bars = []

    class Recorder:
        def __init__(self, total=None, **kwargs):
            self.total, self.n, self.closed = total, 0, False
            bars.append(self)

        def update(self, n=1):
            self.n += n

        def close(self):
            self.closed = True

    monkeypatch.setattr(_progress, "tqdm", Recorder)
    previous = _progress.set_allowed(True)
    try:
        x = da.arange(40, chunks=4)
        with use_cluster(cluster.scheduler_address), _progress.dask_progress("sum"):
            total = (x * 2).sum().compute()
    finally:
        _progress.set_allowed(previous)
    assert total == 2 * sum(range(40))
    assert len(bars) == 1
    bar = bars[0]
    assert bar.total >= 10 and bar.n == bar.total and bar.closed  # every task, not 1 future


# --------------------------------------------------------------------------- command line
def _uvstack_cli(data, out, *extra):
    store, cat = data
    return ["uvstack", str(store), str(cat), str(out), "--json", "--no-progress", *extra]


def _json(capsys) -> dict:
    doc = json.loads(capsys.readouterr().out)
    for k in ("seconds", "elapsed_s", "output", "out"):
        doc.pop(k, None)
    return doc


def test_cli_scheduler_runs_on_the_cluster(cluster, data, tmp_path, capsys):
    assert main(_uvstack_cli(data, tmp_path / "ref.zarr")) == 0
    ref = _json(capsys)
    before = _tasks(cluster)
    assert main(_uvstack_cli(data, tmp_path / "got.zarr", "--scheduler",
                             cluster.scheduler_address)) == 0
    got = _json(capsys)
    assert _tasks(cluster) - before > 0
    _same(got, ref, rel=0)
    assert active_client() is None  # the command's connection is closed


def test_cli_image_and_noise_on_the_cluster(cluster, data, tmp_path, capsys):
    store, cat = data
    for argv in (["image", str(store), str(tmp_path / "{}.fits"), "--size", "64",
                  "--cell", "2arcsec", "--json", "--no-progress"],
                 ["noise", str(store), str(cat), "--realizations", "4", "--json",
                  "--no-progress"]):
        assert main([a.format("ref") for a in argv]) == 0
        ref = _json(capsys)
        before = _tasks(cluster)
        assert main([a.format("got") for a in argv]
                    + ["--scheduler", cluster.scheduler_address]) == 0
        got = _json(capsys)
        assert _tasks(cluster) - before > 0, argv[0]
        if argv[0] == "image":
            # the gridder's threads add in the order they finish (the images agree to rounding),
            # and the beam is a least-squares fit to the PSF: a rounding-level change of the PSF
            # moves the fitted beam by up to the fit's tolerance
            _same(got, ref, rel=1e-6)
        else:
            _same(got, ref, rel=0)


def test_cli_honours_dask_scheduler_address(cluster, data, tmp_path, capsys, monkeypatch):
    assert main(_uvstack_cli(data, tmp_path / "ref.zarr")) == 0
    ref = _json(capsys)
    monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", cluster.scheduler_address)
    before = _tasks(cluster)
    assert main(_uvstack_cli(data, tmp_path / "got.zarr")) == 0
    assert _tasks(cluster) - before > 0
    _same(_json(capsys), ref, rel=0)


def test_cli_bad_address_is_one_line(data, tmp_path, capsys):
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        rc = main(_uvstack_cli(data, tmp_path / "x.zarr", "--scheduler", "tcp://127.0.0.1:9"))
    err = capsys.readouterr().err.strip()
    assert rc == 1
    assert err.startswith("error: ") and "\n" not in err, err
    assert "--scheduler tcp://127.0.0.1:9" in err and "Traceback" not in err
    assert not (tmp_path / "x.zarr").exists()


def test_cli_distributed_without_address(data, tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    monkeypatch.setenv("DASK_SCHEDULER", "distributed")
    rc = main(_uvstack_cli(data, tmp_path / "x.zarr"))
    err = capsys.readouterr().err.strip()
    assert rc == 1 and err.startswith("error: ") and "\n" not in err, err
    assert "--scheduler ADDRESS" in err and "DASK_SCHEDULER_ADDRESS" in err


def test_every_long_command_has_the_options():
    from xstack.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    for name in ("convert", "simulate", "subtract", "image", "uvstack", "imstack", "fit",
                 "noise", "export", "reproduce"):
        flags = sub.choices[name]._option_string_actions
        assert "--scheduler" in flags and "--workers" in flags, name


@pytest.mark.slow
def test_cli_workers_starts_and_closes_a_local_cluster(data, tmp_path, capsys):
    assert main(_uvstack_cli(data, tmp_path / "ref.zarr")) == 0
    ref = _json(capsys)
    assert main(_uvstack_cli(data, tmp_path / "got.zarr", "--workers", "2")) == 0
    _same(_json(capsys), ref, rel=0)
    assert active_client() is None


@pytest.mark.slow
def test_cli_reproduce_realisations_run_as_tasks(cluster, tmp_path, capsys):
    """reproduce's --scheduler (now the shared option): one task per realisation, same numbers."""
    argv = ["reproduce", "--type", "2", "--realizations", "2", "--scale", "0.005", "-q",
            "--no-progress", "--json"]
    assert main([*argv, "--outdir", str(tmp_path / "ref")]) == 0
    ref = json.loads(capsys.readouterr().out)["types"][0]
    before = _tasks(cluster)
    assert main([*argv, "--outdir", str(tmp_path / "got"), "--scheduler",
                 cluster.scheduler_address]) == 0
    got = json.loads(capsys.readouterr().out)["types"][0]
    assert [k for k in cluster.counter.keys[before:] if "run_realization" in k]
    for key in ("uv_flux_mean_jy", "uv_flux_scatter_jy", "image_flux_mean_jy"):
        assert got[key] == pytest.approx(ref[key], rel=1e-12), key


# --------------------------------------------------------------------------- a killed worker
@pytest.mark.slow
def test_killed_worker_mid_stack_same_answer(data, tmp_path):
    """SIGKILL one of 2 workers while the stack runs: the nanny restarts it, the scheduler
    reruns its tasks: flux and output bitwise equal to the threaded run's."""
    import signal

    ds = make_stack_partition(n_time=64, n_ant=10, n_chan=8, sigma=0.01, seed=5)
    store = tmp_path / "big.zarr"
    write_store({"p": ds.chunk({"time": 1})}, store)  # 64 chunks: time to kill mid-run
    _, cat = data
    ref = xstack.stack_uv(store, str(cat), out=tmp_path / "ref.zarr")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as lc:
        counter = TaskCounter()
        lc.scheduler.add_plugin(counter)
        killed = []

        def kill_one() -> None:
            while counter.finished < 20:
                time.sleep(0.01)
            with distributed.Client(lc, set_as_default=False) as c:
                pids = c.run(os.getpid)
            os.kill(next(iter(pids.values())), signal.SIGKILL)
            killed.append(counter.finished)

        killer = threading.Thread(target=kill_one, daemon=True)
        with use_cluster(lc.scheduler_address):
            killer.start()
            got = xstack.stack_uv(store, str(cat), out=tmp_path / "got.zarr")
        killer.join(5)
    assert killed, "no worker was killed"
    print("killed a worker after", killed[0], "finished tasks of", counter.finished)
    assert counter.finished > killed[0]  # the stack went on after the kill
    _same(got.to_dict(), ref.to_dict(), rel=0)
    np.testing.assert_array_equal(open_store(tmp_path / "got.zarr")["p"]["VISIBILITY"].values,
                                  open_store(tmp_path / "ref.zarr")["p"]["VISIBILITY"].values)


def test_local_cluster_holds_one_queued_read_per_thread():
    """``--workers N`` starts its cluster with worker-saturation 1.0 (distributed's 1.1 rounds
    up to two queued chunk reads per thread: 5.3-7.7 instead of 3.5-4.0 chunks per worker in
    benchmarks/bench_scale.py) and the workers' bounded heap."""
    import os

    with use_cluster(workers=1) as client:
        saturation = client.run_on_scheduler(lambda dask_scheduler: dask_scheduler.WORKER_SATURATION)
        env = client.run(lambda: os.environ.get("MALLOC_MMAP_THRESHOLD_"))
    assert saturation == 1.0
    assert set(env.values()) == {"1048576"}


_ENV_PROBE = r"""
import json, os, sys
from xstack._cluster import use_cluster

names = ["OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MALLOC_MMAP_THRESHOLD_"]
out = {}
with use_cluster(workers=1) as client:
    out["inside"] = {n: os.environ.get(n) for n in names}
    out["workers"] = list(client.run(lambda: os.environ.get("OMP_NUM_THREADS")).values())
    import ducc0  # first imported here, with the cluster running
    out["ducc0_pool"] = ducc0.misc.thread_pool_size()
out["after"] = {n: os.environ.get(n) for n in names}
print(json.dumps(out))
"""


def test_local_cluster_leaves_this_process_environment():
    """distributed's nanny sets OMP_NUM_THREADS=1 (and MKL/OpenBLAS) in the parent process
    before it spawns a worker and leaves them: ducc0 imported afterwards sized its pool to one
    thread (``--threaded-gridding`` single-threaded), and a program started later (CASA)
    inherited them. The workers keep them; this process gets its own values back. Run in a
    fresh interpreter, whose environment and ducc0 import this test controls."""
    import subprocess

    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                        "MALLOC_MMAP_THRESHOLD_", "DASK_SCHEDULER_ADDRESS")}
    env["MKL_NUM_THREADS"] = "3"  # a value of the user's own comes back unchanged
    done = subprocess.run([sys.executable, "-c", _ENV_PROBE], env=env, capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["workers"] == ["1"]
    want = {"OMP_NUM_THREADS": None, "MKL_NUM_THREADS": "3", "OPENBLAS_NUM_THREADS": None,
            "MALLOC_MMAP_THRESHOLD_": None}
    assert out["inside"] == want
    assert out["after"] == want
    # ducc0's pool as a plain interpreter of the same environment sizes it
    plain = subprocess.run([sys.executable, "-c", "import ducc0; "
                            "print(ducc0.misc.thread_pool_size())"], env=env,
                           capture_output=True, text=True, timeout=120)
    assert out["ducc0_pool"] == int(plain.stdout.strip())
