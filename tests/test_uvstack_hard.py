"""Numerical hard cases of uvstack, each its own test."""

from __future__ import annotations

import dask.array as da
import numpy as np
import pytest
import xarray as xr
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.table import Table

from xstack.beams import standard_beam
from xstack.coords import lm_to_radec
from xstack.errors import XstackError
from xstack.uvstack.reference import reference_uvstack
from xstack.uvstack.stack import stack_uv


def _tree(ds, name="spw0_field0"):
    return xr.DataTree.from_dict({name: ds})


def _cat(ra, dec, **cols):
    t = Table({"ra": np.degrees(np.atleast_1d(ra)), "dec": np.degrees(np.atleast_1d(dec))})
    for k, v in cols.items():
        t[k] = v
    return t


@pytest.mark.parametrize("dec0_deg", [89.9, -89.9])
def test_near_the_poles(dec0_deg):
    """Phase center 0.1 deg from a pole, source on the far side of the pole (RA + 180 deg)."""
    center = (0.3, np.radians(dec0_deg))
    sign = np.sign(dec0_deg)
    src = (0.3 + np.pi, sign * np.radians(89.995))  # 0.105 deg from the center, across the pole
    ds = make_stack_partition(n_time=6, n_ant=6, n_chan=3, phase_center=center,
                              sources=[(*src, 2e-3)], weight_scale=1.0, seed=1)
    res = stack_uv(_tree(ds), _cat(*src), primary_beam="none", weighting="none")
    assert res.flux_jy == pytest.approx(2e-3, rel=1e-9)
    assert abs(res.flux_imag_jy) < 1e-12


def test_across_ra_zero():
    center = (np.radians(359.995), np.radians(-30.0))
    src_ra = np.radians(0.004)  # 32 arcsec east across RA 0/360
    ds = make_stack_partition(n_time=6, n_ant=6, n_chan=3, phase_center=center,
                              sources=[(src_ra, center[1], 1e-3)], weight_scale=1.0)
    for ra_deg in (0.004, 360.004, -359.996):
        cat = Table({"ra": [ra_deg], "dec": [-30.0]})
        res = stack_uv(_tree(ds), cat, primary_beam="none", weighting="none")
        assert res.flux_jy == pytest.approx(1e-3, rel=1e-9)
    # the stacked phase center is the position (wrapped into [0, 360))
    assert res.options["stack_center_deg"][0] == pytest.approx(0.004, abs=1e-9)


def test_at_and_beyond_the_primary_beam_cutoff():
    ds = make_stack_partition(n_time=4, n_ant=5, n_chan=3, sigma=1.0, telescope="ALMA",
                              dish=12.0, freq0=230e9, pols=("XX", "YY"))
    beam = standard_beam("ALMA", 12.0)
    fmax = float(ds["frequency"].max())
    r_cut = beam.radius_at(0.1, fmax)  # the last channel sets the cutoff radius
    ra_in, dec_in = lm_to_radec(r_cut * (1 - 1e-6), 0.0, *VLA_CENTER)
    ra_out, dec_out = lm_to_radec(r_cut * (1 + 1e-6), 0.0, *VLA_CENTER)
    with pytest.warns(UserWarning, match="1 of 2"):
        res = stack_uv(_tree(ds), _cat([ra_in, ra_out], [dec_in, dec_out]), pb_cutoff=0.1)
    assert list(res.positions["used"][:, 0]) == [True, False]
    assert len(res.uncovered) == 1
    assert float(beam(r_cut * (1 - 1e-6), fmax)) >= 0.1
    # a lower cutoff admits it; no cutoff-free position is silently kept
    res2 = stack_uv(_tree(ds), _cat([ra_in, ra_out], [dec_in, dec_out]), pb_cutoff=0.05)
    assert res2.n_positions == 2
    with pytest.raises(XstackError, match="none of the 1"):
        stack_uv(_tree(ds), _cat(ra_out, dec_out))


@pytest.mark.parametrize("weighting", ["none", "pb"])
def test_near_the_primary_beam_null_and_in_the_sidelobes(weighting):
    # with no cutoff at all, a position just inside the first null is stacked (tiny A,
    # finite A^-1), one in the first sidelobe (A ~ 0.018 > 0 for the Airy model) is not
    ds = make_stack_partition(n_time=4, n_ant=5, n_chan=3, sigma=1.0, telescope="ALMA",
                              dish=12.0, freq0=230e9, pols=("XX", "YY"))
    beam = standard_beam("ALMA", 12.0)
    freq = ds["frequency"].values
    r_null = float(beam.first_null(freq.max()))  # the highest channel's null is innermost
    assert float(beam(1.3 * r_null, freq.max())) > 0.01  # a sidelobe above a low cutoff
    radii = [0.5 * r_null, 0.98 * r_null, 1.3 * r_null, 1.6 * r_null]
    ra, dec = lm_to_radec(np.array(radii), np.zeros(4), *VLA_CENTER)
    with pytest.warns(UserWarning, match="2 of 4"):
        res = stack_uv(_tree(ds), _cat(ra, dec), pb_cutoff=0.0, weighting=weighting)
    assert list(res.positions["used"][:, 0]) == [True, True, False, False]
    assert np.isfinite(res.flux_jy) and np.isfinite(res.flux_err_jy)
    # a 1 % cutoff drops the one next to the null too, and still not the sidelobe ones
    assert float(beam(0.98 * r_null, freq.max())) < 0.01
    with pytest.warns(UserWarning, match="3 of 4"):
        res01 = stack_uv(_tree(ds), _cat(ra, dec), pb_cutoff=0.01, weighting=weighting)
    assert list(res01.positions["used"][:, 0]) == [True, False, False, False]


@pytest.mark.parametrize("weighting", ["none", "pb"])
def test_duplicate_positions(weighting, rng):
    ds = make_stack_partition(n_time=6, n_ant=6, n_chan=3, sigma=1.0, seed=3)
    ra, dec = lm_to_radec(rng.uniform(-3e-3, 3e-3, 5), rng.uniform(-3e-3, 3e-3, 5), *VLA_CENTER)
    once = stack_uv(_tree(ds), _cat(ra, dec), weighting=weighting)
    twice = stack_uv(_tree(ds), _cat(np.repeat(ra, 2), np.repeat(dec, 2)), weighting=weighting)
    assert twice.flux_jy == pytest.approx(once.flux_jy, rel=1e-12)
    assert twice.n_positions == 10
    np.testing.assert_allclose(twice.stacked["spw0_field0"]["VISIBILITY"].values,
                               once.stacked["spw0_field0"]["VISIBILITY"].values, atol=1e-13)
    # visibility weights scale with the sum of position weights (duplicates count)
    np.testing.assert_allclose(twice.stacked["spw0_field0"]["WEIGHT"].values,
                               2 * once.stacked["spw0_field0"]["WEIGHT"].values, rtol=1e-6)


def test_hundred_thousand_positions(rng):
    ds = make_stack_partition(n_time=2, n_ant=4, n_chan=3, sigma=1.0, seed=4)
    n = 100_000
    ra, dec = lm_to_radec(rng.uniform(-5e-3, 5e-3, n), rng.uniform(-5e-3, 5e-3, n), *VLA_CENTER)
    cat = _cat(ra, dec)
    fast = stack_uv(_tree(ds), cat, weighting="pb")
    slow = stack_uv(_tree(ds), cat, weighting="pb", engine="numpy")
    assert fast.n_positions == n
    assert fast.flux_jy == pytest.approx(slow.flux_jy, rel=1e-9, abs=1e-12)
    np.testing.assert_allclose(fast.stacked["spw0_field0"]["VISIBILITY"].values,
                               slow.stacked["spw0_field0"]["VISIBILITY"].values, atol=1e-10)


def test_fully_flagged_chunks_and_nan_under_flags(rng):
    ds = make_stack_partition(n_time=8, n_ant=6, n_chan=3, sigma=1.0, seed=5, flag_frac=0.2)
    vis = ds["VISIBILITY"].values.copy()
    flag = ds["FLAG"].values.copy()
    flag[:2] = True  # the whole first time chunk
    vis[:2] = np.nan
    vis[flag & (rng.uniform(size=flag.shape) < 0.5)] = np.nan + 1j * np.inf
    ds["VISIBILITY"] = (ds["VISIBILITY"].dims, vis)
    ds["FLAG"] = (ds["FLAG"].dims, flag)
    chunked = ds.chunk({"time": 2})
    ra, dec = lm_to_radec([1e-3, -2e-3], [5e-4, 1e-3], *VLA_CENTER)
    res = stack_uv(_tree(chunked), _cat(ra, dec))
    ref = reference_uvstack([("p", ds)], np.degrees(ra), np.degrees(dec), weighting="pb",
                            primary_beam="auto")
    assert np.isfinite(res.flux_jy) and np.isfinite(res.flux_err_jy)
    assert res.flux_jy == pytest.approx(ref["flux_jy"], rel=1e-9)
    assert res.n_visibilities == ref["n_visibilities"] == np.count_nonzero(~flag)


def test_all_zero_weights_are_an_error_not_nan():
    ds = make_stack_partition(n_time=4, n_ant=5, n_chan=2, sigma=1.0)
    cat = _cat([VLA_CENTER[0]] * 2, [VLA_CENTER[1]] * 2, weight=[0.0, 0.0])
    with pytest.raises(XstackError, match="weights are zero"):
        stack_uv(_tree(ds), cat, weighting="column")
    zero = ds.copy()
    zero["WEIGHT"] = zero["WEIGHT"] * 0
    with pytest.raises(XstackError, match="no unflagged visibility"):
        stack_uv(_tree(zero), _cat(*VLA_CENTER))
    flagged = ds.copy()
    flagged["FLAG"] = flagged["FLAG"] | True
    with pytest.raises(XstackError, match="no unflagged visibility"):
        stack_uv(_tree(flagged), _cat(*VLA_CENTER))


def test_float32_input(rng):
    ds = make_stack_partition(n_time=6, n_ant=6, n_chan=3, sigma=1.0, seed=6, dtype=np.complex64)
    ra, dec = lm_to_radec(rng.uniform(-3e-3, 3e-3, 7), rng.uniform(-3e-3, 3e-3, 7), *VLA_CENTER)
    res = stack_uv(_tree(ds), _cat(ra, dec))
    ref = reference_uvstack([("p", ds)], np.degrees(ra), np.degrees(dec), weighting="pb",
                            primary_beam="auto")
    st = res.stacked["spw0_field0"]["VISIBILITY"]
    assert st.dtype == np.complex64  # output keeps the input precision...
    # ...but phases and the flux are computed in float64 from the same input values
    assert res.flux_jy == pytest.approx(ref["flux_jy"], rel=1e-9)
    np.testing.assert_allclose(st.values, ref["stacked"]["p"], rtol=0, atol=1e-6)


def test_long_baselines_high_frequency_float64_phases():
    """16 km baselines at 900 GHz, a point source 2' off: phases ~1e5 rad; float64 keeps the
    stacked flux exact (a float32 phase would scramble it, see test_uvstack_kernels)."""
    center = VLA_CENTER
    src = lm_to_radec(5.8e-4, -2.0e-4, *center)
    ds = make_stack_partition(n_time=6, n_ant=8, n_chan=4, freq0=900e9, dfreq=2e9,
                              extent_m=8000.0, phase_center=center, sources=[(*src, 1.0)],
                              weight_scale=1.0, telescope="ALMA", dish=12.0,
                              pols=("XX", "YY"), dtype=np.complex128)
    assert float(np.abs(ds["UVW"]).max()) > 1e4
    res = stack_uv(_tree(ds), _cat(*src), primary_beam="none", weighting="none")
    assert res.flux_jy == pytest.approx(1.0, rel=1e-6)
    v = res.stacked["spw0_field0"]["VISIBILITY"].values
    assert np.max(np.abs(np.angle(v))) < 1e-6  # phase error of every stacked visibility


def test_dask_backed_store_with_awkward_chunks(rng):
    """Frequency split over chunks and UVW chunked differently: rechunked, same result."""
    ds = make_stack_partition(n_time=9, n_ant=6, n_chan=4, sigma=1.0, seed=8)
    ra, dec = lm_to_radec(rng.uniform(-3e-3, 3e-3, 5), rng.uniform(-3e-3, 3e-3, 5), *VLA_CENTER)
    want = stack_uv(_tree(ds), _cat(ra, dec))
    odd = ds.copy()
    for var in ("VISIBILITY", "WEIGHT", "FLAG"):
        odd[var] = (ds[var].dims, da.from_array(ds[var].values, chunks=(4, 5, 1, 2)))
    odd["UVW"] = (ds["UVW"].dims, da.from_array(ds["UVW"].values, chunks=(3, 7, 3)))
    got = stack_uv(_tree(odd), _cat(ra, dec))
    assert got.flux_jy == pytest.approx(want.flux_jy, rel=1e-12)
