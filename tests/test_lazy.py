"""The lazy API: ``stack_uv(..., compute=False)`` and ``xstack.compute`` (issue 14).

Truth: the eager ``stack_uv`` of the same inputs, and the plain-numpy reference stacker; the
one-pass claim is checked by counting the chunk reads of a shared store."""

from __future__ import annotations

import gc
import shutil
import uuid

import dask
import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, CountVisibilityReads, make_stack_partition
from astropy.table import Table
from dask.callbacks import Callback

import xstack
import xstack.uvstack.stack as stack_module
from xstack._fs import locate
from xstack._lazy import LazyResult
from xstack.coords import lm_to_radec
from xstack.errors import OutputExistsError, SchemaError, XstackError
from xstack.schema import open_store, write_store
from xstack.uvstack.reference import reference_uvstack


def _cat(seed: int, n: int) -> Table:
    rng = np.random.default_rng(seed)
    ra, dec = lm_to_radec(rng.uniform(-3e-3, 3e-3, n), rng.uniform(-3e-3, 3e-3, n), *VLA_CENTER)
    return Table({"ra": np.degrees(ra), "dec": np.degrees(dec)})


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    ds = make_stack_partition(n_time=12, n_ant=7, n_chan=3, sigma=1.0, seed=9, flag_frac=0.1)
    path = tmp_path_factory.mktemp("lazy") / "data.zarr"
    write_store({"p": ds.chunk({"time": 4})}, path)
    return path, ds


def test_lazy_equals_eager_and_reference(store):
    path, ds = store
    cat = _cat(1, 9)
    lazy = xstack.stack_uv(path, cat, compute=False)
    assert isinstance(lazy, LazyResult) and dask.is_dask_collection(lazy)
    eager = xstack.stack_uv(path, cat)
    (res,) = xstack.compute(lazy)
    assert res.flux_jy == eager.flux_jy and res.flux_err_jy == eager.flux_err_jy
    assert res.n_visibilities == eager.n_visibilities
    ref = reference_uvstack([("p", ds)], cat["ra"], cat["dec"], weighting="pb", primary_beam="auto")
    assert res.flux_jy == pytest.approx(ref["flux_jy"], rel=1e-10)
    # .compute() and dask.compute give the same
    assert lazy.compute().flux_jy == res.flux_jy
    assert dask.compute(lazy)[0].flux_jy == res.flux_jy


_CountReads = CountVisibilityReads


def test_two_lazy_stacks_share_one_pass(store):
    path, _ = store
    tree = open_store(path)
    a_cat, b_cat = _cat(2, 5), _cat(3, 7)
    a, b = (xstack.stack_uv(tree, c, compute=False) for c in (a_cat, b_cat))
    ea, eb = xstack.stack_uv(tree, a_cat), xstack.stack_uv(tree, b_cat)
    # the two graphs read the same chunks (same keys), so computed together each chunk is
    # read once: the merged graph has as many distinct VISIBILITY-chunk keys as one stack's
    keys_a = {k for k in dict(a.__dask_graph__()) if "VISIBILITY" in str(k)}
    keys_b = {k for k in dict(b.__dask_graph__()) if "VISIBILITY" in str(k)}
    assert keys_a and keys_a == keys_b
    with dask.config.set(scheduler="sync"):
        with _CountReads() as one:
            xstack.stack_uv(tree, a_cat, compute=False).compute()
        with _CountReads() as both:
            ra, rb = xstack.compute(a, b)
    assert one.reads > 0 and both.reads == one.reads  # each chunk read once for both stacks
    assert (ra.flux_jy, rb.flux_jy) == (ea.flux_jy, eb.flux_jy)
    assert ra.flux_jy != rb.flux_jy  # different positions: two different stacks


# --------------------------------------------------------------------------- lazy + out
def _arrays(tree) -> dict[str, bytes]:
    """Every array (data variables and coordinates) of every partition of a store, as bytes."""
    return {f"{name}/{var}": np.ascontiguousarray(tree[name][var].values).tobytes()
            for name in tree.children for var in tree[name].to_dataset().variables}


def _leftovers(directory, name: str) -> list[str]:
    """Temporaries of ``name`` beside it (xstack's hidden ``.NAME.partial-*``)."""
    return [p.name for p in directory.iterdir() if p.name.startswith(f".{name}.")]


@pytest.fixture(scope="module")
def eager_out(store, tmp_path_factory):
    """The reference: the eager stack that writes its store (flux and store in one pass)."""
    path, _ = store
    out = tmp_path_factory.mktemp("eager") / "eager.zarr"
    res = xstack.stack_uv(path, _cat(1, 9), out=out, profile_bins=4)
    return res, out


def test_lazy_with_out_equals_eager_store(store, eager_out, tmp_path):
    path, _ = store
    ref, ref_out = eager_out
    lazy = xstack.stack_uv(path, _cat(1, 9), out=tmp_path / "o.zarr", compute=False,
                           profile_bins=4)
    # planned: the temporary exists (no chunk yet) but nothing opens as a store
    assert _leftovers(tmp_path, "o.zarr") and not (tmp_path / "o.zarr").exists()
    (res,) = xstack.compute(lazy)
    assert res.flux_jy == ref.flux_jy and res.flux_err_jy == ref.flux_err_jy
    assert res.n_visibilities == ref.n_visibilities
    np.testing.assert_array_equal(res.profile["re_jy"], ref.profile["re_jy"])
    got, want = open_store(tmp_path / "o.zarr"), open_store(ref_out)
    assert got.attrs["xstack_complete"] is True and not _leftovers(tmp_path, "o.zarr")
    assert got.attrs["uvstack"] == want.attrs["uvstack"]  # the measured numbers, as eager
    assert got.attrs["uvstack"]["flux_jy"] == res.flux_jy
    a, b = _arrays(got), _arrays(want)
    assert a.keys() == b.keys() and "p/VISIBILITY" in a
    assert all(a[k] == b[k] for k in a), [k for k in a if a[k] != b[k]]


def test_lazy_with_out_and_another_stack_read_each_chunk_once(store, tmp_path, monkeypatch):
    path, _ = store
    tree = open_store(path)
    a_cat, b_cat = _cat(2, 5), _cat(3, 7)
    ea, eb = xstack.stack_uv(tree, a_cat), xstack.stack_uv(tree, b_cat)
    calls = []
    real = stack_module._block_stack_and_sums

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(stack_module, "_block_stack_and_sums", counted)
    with dask.config.set(scheduler="sync"):
        with CountVisibilityReads() as one:
            xstack.stack_uv(tree, a_cat, compute=False).compute()
        a = xstack.stack_uv(tree, a_cat, compute=False, out=tmp_path / "a.zarr")
        b = xstack.stack_uv(tree, b_cat, compute=False)
        with CountVisibilityReads() as both:
            ra, rb = xstack.compute(a, b)
    n_chunks = len(tree["p"]["VISIBILITY"].chunks[0])  # time chunks (one baseline chunk)
    assert one.reads > 0 and both.reads == one.reads  # the store, both fluxes: one read each
    assert len(calls) == n_chunks  # each stacked chunk made once (not again for the sums)
    assert (ra.flux_jy, rb.flux_jy) == (ea.flux_jy, eb.flux_jy)
    stacked = open_store(tmp_path / "a.zarr")
    assert stacked.attrs["uvstack"]["flux_jy"] == ra.flux_jy
    # dask's own compute does the same
    c = xstack.stack_uv(tree, a_cat, compute=False, out=tmp_path / "c.zarr")
    (rc,) = dask.compute(c)
    assert rc.flux_jy == ea.flux_jy
    assert _arrays(open_store(tmp_path / "c.zarr")) == _arrays(stacked)


@pytest.mark.parametrize("how", ["xstack.compute", "LazyResult.compute", "dask.compute"])
def test_failed_lazy_write_leaves_nothing(store, tmp_path, monkeypatch, how):
    path, _ = store
    calls = []
    real = stack_module._block_stack_and_sums

    def failing(*args, **kwargs):  # the second chunk fails, the others are written
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("injected chunk failure")
        return real(*args, **kwargs)

    monkeypatch.setattr(stack_module, "_block_stack_and_sums", failing)
    out = tmp_path / "o.zarr"
    lazy = xstack.stack_uv(path, _cat(1, 9), out=out, compute=False)
    with pytest.raises(RuntimeError, match="injected"):
        if how == "xstack.compute":
            xstack.compute(lazy)
        elif how == "LazyResult.compute":
            lazy.compute()
        else:
            dask.compute(lazy)
    assert not out.exists()
    with pytest.raises(XstackError, match="no such store"):
        open_store(out)
    if how == "dask.compute":
        # dask's compute cannot clean up; the temporary never opens as a store, and goes
        # with the lazy result
        for name in _leftovers(tmp_path, "o.zarr"):
            with pytest.raises(SchemaError):
                open_store(tmp_path / name)
        del lazy
        gc.collect()
    else:
        with pytest.raises(XstackError, match="given up after a failed compute"):
            lazy.compute()
    assert not _leftovers(tmp_path, "o.zarr")
    assert list(tmp_path.iterdir()) == []


def test_dropped_lazy_write_leaves_nothing(store, tmp_path):
    path, _ = store
    lazy = xstack.stack_uv(path, _cat(1, 9), out=tmp_path / "o.zarr", compute=False)
    assert _leftovers(tmp_path, "o.zarr")
    del lazy
    gc.collect()
    assert list(tmp_path.iterdir()) == []


def test_lazy_write_happens_once(store, tmp_path):
    path, _ = store
    out = tmp_path / "o.zarr"
    lazy = xstack.stack_uv(path, _cat(1, 9), out=out, compute=False)
    first = lazy.compute()
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    for again in (lambda: lazy.compute(), lambda: dask.compute(lazy), lambda: xstack.compute(lazy)):
        with pytest.raises(XstackError, match="written once"):
            again()
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.zarr"]
    assert open_store(out).attrs["uvstack"]["flux_jy"] == first.flux_jy


def test_lazy_existing_out_fails_at_plan_time(store, tmp_path):
    path, _ = store
    out = tmp_path / "o.zarr"
    out.mkdir()
    with pytest.raises(OutputExistsError):
        xstack.stack_uv(path, _cat(1, 9), out=out, compute=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.zarr"]
    lazy = xstack.stack_uv(path, _cat(1, 9), out=out, compute=False, overwrite=True)
    assert lazy.compute().flux_jy == xstack.stack_uv(path, _cat(1, 9)).flux_jy
    assert open_store(out).attrs["xstack_complete"] is True


def test_lazy_write_at_memory_url(store, eager_out):
    path, _ = store
    ref, ref_out = eager_out
    url = f"memory://xstack-lazy/{uuid.uuid4().hex[:8]}/o.zarr"
    lazy = xstack.stack_uv(path, _cat(1, 9), out=url, compute=False, profile_bins=4)
    with pytest.raises(SchemaError):  # written in place there: incomplete until finished
        open_store(url)
    (res,) = xstack.compute(lazy)
    assert res.flux_jy == ref.flux_jy
    got = open_store(url)
    assert got.attrs["xstack_complete"] is True
    assert _arrays(got) == _arrays(open_store(ref_out))
    dropped = xstack.stack_uv(path, _cat(1, 9), out=url + "2", compute=False)
    del dropped
    gc.collect()
    assert not locate(url + "2").exists()


def test_lazy_write_on_a_local_cluster(store, eager_out, tmp_path):
    """On 2 worker processes: the same store, bitwise, and the same flux as threaded."""
    pytest.importorskip("distributed")
    from _cluster_helpers import local_cluster

    from xstack._cluster import use_cluster

    path, _ = store
    ref, ref_out = eager_out
    with local_cluster() as cluster, use_cluster(cluster.scheduler_address):
        lazy = xstack.stack_uv(path, _cat(1, 9), out=tmp_path / "o.zarr", compute=False,
                               profile_bins=4)
        before = cluster.counter.finished
        (res,) = xstack.compute(lazy)
        assert cluster.counter.finished > before  # the chunk writes ran on the workers
        # dask's compute would finish the store on a worker: refused there, nothing kept
        other = xstack.stack_uv(path, _cat(1, 9), out=tmp_path / "d.zarr", compute=False)
        with pytest.raises(XstackError, match="only in the process"):
            dask.compute(other)
        del other  # (the client holds the failure's traceback, and so the result, until closed)
        # a chunk task failing on a worker (a damaged input chunk): xstack.compute removes
        # the temporary once the tasks still running on the workers have ended
        damaged = tmp_path / "damaged.zarr"
        shutil.copytree(path, damaged)
        chunk = next(p for p in sorted((damaged / "p" / "VISIBILITY").rglob("*"))
                     if p.is_file() and p.name != "zarr.json")
        chunk.write_bytes(b"not a chunk")
        bad = xstack.stack_uv(damaged, _cat(1, 9), out=tmp_path / "b.zarr", compute=False)
        with pytest.raises(XstackError, match="damaged|VISIBILITY"):
            xstack.compute(bad)
        assert not _leftovers(tmp_path, "b.zarr") and not (tmp_path / "b.zarr").exists()
        shutil.rmtree(damaged)
    gc.collect()
    assert res.flux_jy == ref.flux_jy and res.flux_err_jy == ref.flux_err_jy
    assert _arrays(open_store(tmp_path / "o.zarr")) == _arrays(open_store(ref_out))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.zarr"]


def test_lazy_plans_without_reading_visibilities(store):
    path, _ = store
    tree = open_store(path)
    executed = []

    class Spy(Callback):
        def _posttask(self, key, result, dsk, state, id):
            executed.append(key)

    with Spy():
        lazy = xstack.stack_uv(tree, _cat(4, 6), compute=False)
    assert not any("VISIBILITY" in str(k) for k in executed)
    assert np.isfinite(lazy.compute().flux_jy)


def test_compute_passes_other_values_through():
    arr = dask.array.arange(4)
    got = xstack.compute(arr, 5)
    np.testing.assert_array_equal(got[0], np.arange(4))
    assert got[1] == 5


def test_lazy_with_out_at_a_url_makes_each_chunk_once(store, monkeypatch):
    """On a store written in place (an object store; memory:// here) the lazy write is one
    task per chunk of its own: the stacked chunk and its flux sums are made once, not once
    for the store and once for the sums (dask's store(compute=False) gives arrays, which a
    compute fuses with the other results' arrays)."""
    path, _ = store
    tree = open_store(path)
    calls = []
    real = stack_module._block_stack_and_sums

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(stack_module, "_block_stack_and_sums", counted)
    n_chunks = len(tree["p"]["VISIBILITY"].chunks[0])
    with dask.config.set(scheduler="sync"):
        eager = xstack.stack_uv(tree, _cat(2, 5), out="memory://lazy-url/e.zarr")
        assert len(calls) == n_chunks
        calls.clear()
        a = xstack.stack_uv(tree, _cat(2, 5), compute=False, out="memory://lazy-url/a.zarr")
        b = xstack.stack_uv(tree, _cat(3, 7), compute=False)
        ra, _rb = xstack.compute(a, b)
    assert len(calls) == n_chunks
    assert ra.flux_jy == eager.flux_jy
    got = open_store("memory://lazy-url/a.zarr")["p"]["VISIBILITY"].values
    ref = open_store("memory://lazy-url/e.zarr")["p"]["VISIBILITY"].values
    np.testing.assert_array_equal(got, ref)
