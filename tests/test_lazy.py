"""The lazy API: ``stack_uv(..., compute=False)`` and ``xstack.compute`` (issue 14).

Truth: the eager ``stack_uv`` of the same inputs, and the plain-numpy reference stacker; the
one-pass claim is checked by counting the chunk reads of a shared store."""

from __future__ import annotations

import dask
import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, CountVisibilityReads, make_stack_partition
from astropy.table import Table
from dask.callbacks import Callback

import xstack
from xstack._lazy import LazyResult
from xstack.coords import lm_to_radec
from xstack.errors import OptionError
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


def test_lazy_with_out_is_refused(store, tmp_path):
    path, _ = store
    with pytest.raises(OptionError, match="compute=False"):
        xstack.stack_uv(path, _cat(1, 3), compute=False, out=tmp_path / "o.zarr")


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
