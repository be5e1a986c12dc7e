"""Writing the stack (``out=``) and the flux share one pass: one task per chunk makes both
(issue 14: the written stack costs one output chunk, no chunk-sized phasor)."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import xarray as xr
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.table import Table

from xstack.coords import lm_to_radec
from xstack.schema import open_store
from xstack.uvstack import stack as st
from xstack.uvstack.reference import reference_uvstack


def test_write_pass_evaluates_each_chunk_once_and_matches_flux_only(tmp_path, monkeypatch):
    rng = np.random.default_rng(5)
    ds = make_stack_partition(n_time=12, n_ant=7, n_chan=3, sigma=1.0, seed=4, flag_frac=0.1)
    ra, dec = lm_to_radec(rng.uniform(-3e-3, 3e-3, 8), rng.uniform(-3e-3, 3e-3, 8), *VLA_CENTER)
    cat = Table({"ra": np.degrees(ra), "dec": np.degrees(dec)})
    tree = xr.DataTree.from_dict({"p": ds.chunk({"time": 5, "baseline_id": 11})})
    n_chunks = 3 * 2
    calls = []
    lock = threading.Lock()
    real = st._block_stack_and_sums

    def counted(*args, **kwargs):
        with lock:
            calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(st, "_block_stack_and_sums", counted)
    written = st.stack_uv(tree, cat, out=tmp_path / "s.zarr")
    assert len(calls) == n_chunks  # not once per consumer (the stacked data and the sums)
    flux_only = st.stack_uv(tree, cat)
    # the same row steps in the same order: the same flux to the last bit
    assert written.flux_jy == flux_only.flux_jy
    assert written.flux_err_jy == flux_only.flux_err_jy
    ref = reference_uvstack([("p", ds)], cat["ra"], cat["dec"], weighting="pb", primary_beam="auto")
    assert written.flux_jy == pytest.approx(ref["flux_jy"], rel=1e-10)
    got = open_store(tmp_path / "s.zarr")["p"].ds["VISIBILITY"].values
    ok = np.isfinite(ref["stacked"]["p"])
    np.testing.assert_allclose(got[ok], ref["stacked"]["p"][ok], rtol=0, atol=1e-6)


@pytest.mark.parametrize("bins, uvmin", [(7, None), (np.array([1.0, 3.0, 6.0, 20.0]), "500m")])
def test_profile_made_in_the_same_pass_equals_the_profile_of_the_written_store(
        tmp_path, monkeypatch, bins, uvmin):
    """``profile_bins``: the uv-profile comes from the write pass's own stacked chunks (still
    one evaluation per chunk) and equals ``uv_profile`` of the store read back, to the bit;
    the flux-only and lazy stacks give the same table."""
    import xstack
    from xstack.uvstack.profile import uv_profile

    rng = np.random.default_rng(8)
    ds = make_stack_partition(n_time=12, n_ant=7, n_chan=3, sigma=1.0, seed=6, flag_frac=0.1)
    ra, dec = lm_to_radec(rng.uniform(-3e-3, 3e-3, 8), rng.uniform(-3e-3, 3e-3, 8), *VLA_CENTER)
    cat = Table({"ra": np.degrees(ra), "dec": np.degrees(dec)})
    tree = xr.DataTree.from_dict({"p": ds.chunk({"time": 5, "baseline_id": 11})})
    calls = []
    real = st._block_stack_and_sums

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(st, "_block_stack_and_sums", counted)
    res = st.stack_uv(tree, cat, out=tmp_path / "s.zarr", profile_bins=bins, uvmin=uvmin)
    assert len(calls) == 3 * 2
    ref = uv_profile(tmp_path / "s.zarr", bins=bins, uvmin=uvmin)
    assert res.profile is not None and res.profile.colnames == ref.colnames
    for col in ref.colnames:
        np.testing.assert_array_equal(np.asarray(res.profile[col]), np.asarray(ref[col]), col)
    assert np.count_nonzero(np.asarray(ref["count"])) >= 2  # a profile, not empty bins
    # the written weights are the input's times sum W (float32): only sum_weight scales
    flux_only = st.stack_uv(tree, cat, profile_bins=bins, uvmin=uvmin)
    lazy = xstack.compute(st.stack_uv(tree, cat, profile_bins=bins, uvmin=uvmin,
                                      compute=False))[0]
    for other in (flux_only, lazy):
        for col in ("re_jy", "im_jy", "re_err_jy", "count", "uvdist_klambda"):
            np.testing.assert_allclose(np.asarray(other.profile[col]), np.asarray(ref[col]),
                                       rtol=1e-6, equal_nan=True, err_msg=col)
    assert st.stack_uv(tree, cat).profile is None


def test_profile_bins_is_checked_before_any_data_is_read():
    from xstack.errors import OptionError

    for bad in (0, -2, 1.5, True, [3.0, 1.0], [[1.0, 2.0]]):
        with pytest.raises(OptionError, match="profile_bins"):
            st.UvstackOptions(profile_bins=bad)


def test_stacked_store_codecs_and_phasor_product_bits(tmp_path):
    """The stacked store uses xstack's store codecs (no compression of the noise-like
    VISIBILITY, blosc-lz4 for WEIGHT/FLAG/UVW: zarr's default zstd cost ~0.5 s of CPU on a
    type-6 stack for 10 % less disk), and the in-place phasor product gives the bits of
    (vis * phasor) in complex128 rounded to the input's complex64."""
    import json

    ds = make_stack_partition(n_time=6, n_ant=5, n_chan=3, sigma=1.0, seed=2)
    cat = Table({"ra": [np.degrees(VLA_CENTER[0]) + 0.001], "dec": [np.degrees(VLA_CENTER[1])]})
    st.stack_uv(xr.DataTree.from_dict({"p": ds.chunk({"time": 3})}), cat,
                out=tmp_path / "s.zarr")
    codecs = {}
    for var in ("VISIBILITY", "WEIGHT", "FLAG", "UVW"):
        meta = json.loads((tmp_path / "s.zarr" / "p" / var / "zarr.json").read_text())
        codecs[var] = [c["name"] for c in meta["codecs"]]
    assert codecs["VISIBILITY"] == ["bytes"]
    assert all(codecs[v] == ["bytes", "blosc"] for v in ("WEIGHT", "FLAG", "UVW")), codecs

    rng = np.random.default_rng(0)
    vis = (rng.normal(size=(4, 5, 3, 2)) + 1j * rng.normal(size=(4, 5, 3, 2))).astype(np.complex64)
    ph = np.exp(1j * rng.uniform(0, 2 * np.pi, size=(4, 5, 3)) * 1e4)
    got = st._block_apply_phasor(vis, ph)
    assert got.dtype == np.complex64
    assert got.tobytes() == (vis.astype(np.complex128) * ph[..., None]).astype(np.complex64).tobytes()
    out = np.empty((8, 5, 3, 2), np.complex64)
    st._block_apply_phasor(vis, ph, out=out[2:6])
    assert out[2:6].tobytes() == got.tobytes()
