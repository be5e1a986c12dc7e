"""``estimate_noise`` on a dask.distributed cluster and lazily (``compute=False``), issue 14.

Truth: the same call on dask's threaded scheduler (no client), which runs the block loop in
this process (:func:`xstack.noise.estimate._compute`, reading through
:func:`xstack.fit._data.stokes_i_blocks`). On the cluster each chunk's sums are one task and
the chunks' sums are folded in the data's order, so every number is expected bitwise equal
(the noise kernels' threads split positions, never rows: the thread count changes no sum).

One ``LocalCluster`` of 2 worker processes with 1 thread each serves the module; its scheduler
runs in this process, so a scheduler plugin sees every task: the proof that the blocks ran
there. The data: a two-pointing store (4 VISIBILITY chunks per pointing) with flags and a few
non-finite visibilities, so that the workers' own Stokes-I preparation of a raw chunk is
checked against ``stokes_i_blocks``.
"""

from __future__ import annotations

import json
import pickle
import sys

import cloudpickle
import dask
import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, CountVisibilityReads, make_stack_partition

import xstack
from xstack._cluster import use_cluster
from xstack._lazy import LazyResult
from xstack.cli import main
from xstack.coords import lm_to_radec
from xstack.errors import OptionError
from xstack.schema import open_store, write_store

distributed = pytest.importorskip("distributed")
from _cluster_helpers import local_cluster  # noqa: E402

# the small data's warnings (weights vs scatter, few targets) are not what is tested here
pytestmark = [pytest.mark.filterwarnings("ignore::xstack.errors.XstackWarning"),
              pytest.mark.filterwarnings("ignore:analytic noise from WEIGHT")]

# workers are other processes: send this module's functions by value, not by import
cloudpickle.register_pickle_by_value(sys.modules[__name__])

N_CHUNKS = 8  # 2 pointings x 4 time chunks


@pytest.fixture(scope="module")
def cluster():
    with local_cluster() as cluster:
        yield cluster


def _block_tasks(cluster, since: int) -> int:
    """Tasks since ``since`` that computed one chunk's noise sums."""
    return sum("noise-chunk-sums" in k for k in cluster.counter.keys[since:])


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Two pointings (4 chunks each, flags, NaNs), a 40 mJy source, a catalogue of 3."""
    tmp = tmp_path_factory.mktemp("noise_dist")
    ra, dec = lm_to_radec(np.array([2e-3, -1e-3, 1e-3]), np.array([-1e-3, 2e-3, 1e-3]),
                          *VLA_CENTER)
    parts = {}
    for i, dl in enumerate((0.0, 1.5e-3)):
        center = lm_to_radec(dl, 0.0, *VLA_CENTER)
        ds = make_stack_partition(n_time=16, n_ant=7, n_chan=3, sigma=0.01, seed=21 + i,
                                  flag_frac=0.1, phase_center=tuple(map(float, center)),
                                  field_id=i, sources=[(ra[0], dec[0], 0.04)])
        vis = ds["VISIBILITY"].values.copy()
        vis[3, 2, 1, 0] = np.nan  # unflagged but not finite: weight 0 in both passes
        parts[f"spw0_field{i}"] = ds.assign(VISIBILITY=(ds["VISIBILITY"].dims, vis,
                                                        ds["VISIBILITY"].attrs)).chunk({"time": 4})
    store = tmp / "data.zarr"
    write_store(parts, store)
    cat = tmp / "cat.csv"
    cat.write_text("ra,dec\n" + "".join(f"{float(np.degrees(a))!r},{float(np.degrees(d))!r}\n"
                                        for a, d in zip(ra, dec)))
    return store, cat


def _assert_same(got, ref) -> None:
    """Bitwise equal noise results: the JSON and every array."""
    assert got.to_dict() == ref.to_dict()
    np.testing.assert_array_equal(got.values, ref.values)
    for name in ("injected", "positions_deg", "injected_flux_jy"):
        a, b = getattr(got, name), getattr(ref, name)
        assert (a is None) == (b is None), name
        if b is not None:
            np.testing.assert_array_equal(a, b)
    assert (got.profile is None) == (ref.profile is None)
    if ref.profile is not None:
        for key, value in ref.profile.items():
            np.testing.assert_array_equal(got.profile[key], value)


CASES = {"mc": dict(method="mc", realizations=6, seed=3, profile_bins=3),
         "analytic": dict(method="analytic"),
         "bootstrap": dict(method="bootstrap", realizations=6, seed=4),
         "random-row-engine": dict(method="random", realizations=5, seed=5, engine="numba")}


@pytest.mark.parametrize("case", list(CASES))
def test_cluster_equals_threaded(cluster, data, case):
    store, cat = data
    kw = CASES[case]
    ref = xstack.estimate_noise(store, str(cat), **kw)
    before = len(cluster.counter.keys)
    with use_cluster(cluster.scheduler_address):
        got = xstack.estimate_noise(store, str(cat), **kw)
    # every chunk's sums ran as a task on the cluster (none before: the blocks were looped
    # over in this process and only their reads went to the cluster)
    assert _block_tasks(cluster, before) == N_CHUNKS
    # the positions' plan: one task per pointing, its result fetched by the workers that need it
    assert sum("noise-block-plan" in k for k in cluster.counter.keys[before:]) == 2
    _assert_same(got, ref)
    assert got.extra["n_pointings"] == 2


def test_lazy_equals_eager(data):
    store, cat = data
    for kw in (CASES["mc"], CASES["analytic"]):
        lazy = xstack.estimate_noise(store, str(cat), compute=False, **kw)
        assert isinstance(lazy, LazyResult) and dask.is_dask_collection(lazy)
        eager = xstack.estimate_noise(store, str(cat), **kw)
        _assert_same(lazy.compute(), eager)
        _assert_same(xstack.compute(lazy)[0], eager)
        with dask.config.set(scheduler="sync"):
            _assert_same(dask.compute(lazy)[0], eager)


def test_lazy_on_cluster(cluster, data):
    store, cat = data
    eager = xstack.estimate_noise(store, str(cat), **CASES["mc"])
    lazy = xstack.estimate_noise(store, str(cat), compute=False, **CASES["mc"])
    before = len(cluster.counter.keys)
    with use_cluster(cluster.scheduler_address):
        (got,) = xstack.compute(lazy)
    assert _block_tasks(cluster, before) == N_CHUNKS
    _assert_same(got, eager)


def test_lazy_with_other_chunkings(data):
    """In-memory partitions and chunks split along baselines: the tasks see the local loop's
    blocks (whole along baselines, channels, correlations), same results bitwise."""
    store, cat = data
    tree = open_store(store)
    kw = CASES["mc"]
    for name in ("numpy", "baseline-chunks"):
        parts = {}
        for key in sorted(tree.children):
            ds = tree[key].to_dataset()
            parts[key] = ds.load() if name == "numpy" else ds.chunk({"time": 3, "baseline_id": 5})
        eager = xstack.estimate_noise(parts, str(cat), **kw)
        _assert_same(xstack.estimate_noise(parts, str(cat), compute=False, **kw).compute(), eager)
        # other blocks than the store's chunks: the same sums in another order
        np.testing.assert_allclose(eager.values, xstack.estimate_noise(store, str(cat), **kw).values,
                                   rtol=1e-12, atol=0)


def test_graph_is_linear_in_the_chunks():
    """One layer per pointing, written out: a graph built from dask.delayed calls (one layer
    and one graph merge per chunk) took 3.6 s for 2000 chunks, growing quadratically. Checked
    by the graph's structure, not a clock (timings belong in benchmarks): 20 000 chunks give
    one new layer of 2 keys per chunk (+ the plan and the first fold) over the inputs' layer."""
    import dask.array as da

    from xstack.noise.estimate import _pointing_graph

    x = da.zeros((20_000, 4), chunks=(1, 4))
    hlg = _pointing_graph([x, x, x, x], "plan").__dask_graph__()
    new = [name for name in hlg.layers if name not in x.__dask_graph__().layers]
    assert len(new) == 1
    assert len(hlg.layers[new[0]]) == 2 * 20_000 + 2
    graph = dict(hlg)
    assert sum("noise-chunk-sums" in str(k) for k in graph) == 20_000


def test_lazy_in_image_domain_is_refused(tmp_path):
    with pytest.raises(OptionError, match="compute=False") as exc:
        xstack.estimate_noise(tmp_path / "x.fits", ([0.0], [0.0]), domain="image",
                              compute=False)
    assert exc.value.option == "compute"


def test_block_plan_is_one_key_per_pointing(data):
    """The positions' coefficient arrays are in the graph once per pointing (one key every
    chunk task depends on, sent once to each worker), not copied into each chunk's task."""
    store, cat = data
    lazy = xstack.estimate_noise(store, str(cat), compute=False, method="mc", realizations=100)
    graph = dict(lazy.__dask_graph__())
    plans = [k for k in graph if "noise-block-plan" in str(k)]
    chunk_tasks = [k for k in graph if "noise-chunk-sums" in str(k)]
    assert len(plans) == 2 and len(chunk_tasks) == N_CHUNKS
    plan_bytes = min(len(pickle.dumps(graph[k])) for k in plans)
    assert plan_bytes > 20_000  # 101 groups x 3 positions: (3, 303) coef and b, l, m, n ...
    for key in chunk_tasks:
        assert len(pickle.dumps(graph[key])) < plan_bytes / 10


_CountReads = CountVisibilityReads


def test_stack_and_noise_in_one_pass(data):
    """A uv stack and its noise computed together read each VISIBILITY chunk once."""
    store, cat = data
    tree = open_store(store)
    kw = CASES["mc"]
    eager_stack = xstack.stack_uv(tree, str(cat))
    eager_noise = xstack.estimate_noise(tree, str(cat), **kw)
    stack = xstack.stack_uv(tree, str(cat), compute=False)
    noise = xstack.estimate_noise(tree, str(cat), compute=False, **kw)
    with dask.config.set(scheduler="sync"):
        with _CountReads() as alone:
            xstack.estimate_noise(tree, str(cat), compute=False, **kw).compute()
        with _CountReads() as both:
            got_stack, got_noise = xstack.compute(stack, noise)
    assert alone.reads == N_CHUNKS
    assert both.reads == N_CHUNKS  # not 2 x: the two graphs share the chunks' keys
    assert got_stack.flux_jy == eager_stack.flux_jy
    _assert_same(got_noise, eager_noise)
    # the same target flux by both stages' estimator (different code, same definition)
    assert got_noise.target_flux_jy == pytest.approx(got_stack.flux_jy, rel=1e-9)


def _noise_json(capsys) -> dict:
    doc = json.loads(capsys.readouterr().out)
    for k in ("seconds", "elapsed_s"):
        doc.pop(k, None)
    return doc


def test_cli_scheduler_runs_the_blocks_on_the_cluster(cluster, data, capsys):
    store, cat = data
    argv = ["noise", str(store), str(cat), "--realizations", "4", "--seed", "2", "--json",
            "--no-progress"]
    assert main(argv) == 0
    ref = _noise_json(capsys)
    before = len(cluster.counter.keys)
    assert main([*argv, "--scheduler", cluster.scheduler_address]) == 0
    got = _noise_json(capsys)
    assert _block_tasks(cluster, before) == N_CHUNKS
    assert got == ref  # the same JSON, to the last bit
