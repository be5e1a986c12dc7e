"""stack_uv(): exactness against analytic truth and the plain-numpy reference, outputs, errors."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.table import Table

from xstack.beams import standard_beam
from xstack.coords import SPEED_OF_LIGHT, lm_to_radec, radec_to_lmn
from xstack.errors import XstackError
from xstack.schema import open_store
from xstack.uvstack.reference import reference_uvstack
from xstack.uvstack.stack import stack_uv


def _tree(**parts):
    return xr.DataTree.from_dict(parts)


def _cat(ra, dec, **cols):
    t = Table({"ra": np.degrees(np.atleast_1d(ra)), "dec": np.degrees(np.atleast_1d(dec))})
    for k, v in cols.items():
        t[k] = v
    return t


def _offsets(center, rng, n, radius):
    l = rng.uniform(-radius, radius, n)
    m = rng.uniform(-radius, radius, n)
    return lm_to_radec(l, m, *center)


@pytest.mark.parametrize("weighting,beam", [("none", "none"), ("pb", "auto"), ("pb", "gaussian"),
                                            ("column", "airy"), ("sigma2", "auto")])
def test_equals_numpy_reference_on_random_data(rng, weighting, beam):
    ds = make_stack_partition(n_time=8, n_ant=6, n_chan=5, sigma=0.3, seed=3, flag_frac=0.1)
    ra, dec = _offsets(VLA_CENTER, rng, 17, 0.004)
    cat = _cat(ra, dec, weight=rng.uniform(0.2, 2.0, 17))
    sigma = rng.uniform(0.5, 2.0, 17) if weighting == "sigma2" else None
    res = stack_uv(_tree(p=ds), cat, weighting=weighting, primary_beam=beam, sigma=sigma)
    ref = reference_uvstack([("p", ds)], cat["ra"], cat["dec"], weighting=weighting,
                            primary_beam=beam, column_weight=cat["weight"], sigma=sigma)
    assert res.flux_jy == pytest.approx(ref["flux_jy"], rel=1e-9, abs=1e-12)
    assert res.flux_err_jy == pytest.approx(ref["flux_err_jy"], rel=1e-9)
    assert res.n_visibilities == ref["n_visibilities"]
    got = res.stacked["p"]["VISIBILITY"].values
    want = ref["stacked"]["p"]
    ok = np.isfinite(want)
    np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-9 * np.abs(want[ok]).max())


def test_single_position_is_plain_phase_shift():
    ds = make_stack_partition(n_time=6, n_ant=5, n_chan=3, sigma=1.0, seed=5)
    ra, dec = VLA_CENTER[0] + 0.003, VLA_CENTER[1] - 0.002
    res = stack_uv(_tree(p=ds), _cat(ra, dec), primary_beam="none", weighting="none")
    l, m, n, n1 = radec_to_lmn(ra, dec, *VLA_CENTER)
    uvw = ds["UVW"].values
    d = uvw[..., 0] * l + uvw[..., 1] * m + uvw[..., 2] * n1
    ph = np.exp(-2j * np.pi * d[..., None] * ds["frequency"].values / SPEED_OF_LIGHT)
    want = ds["VISIBILITY"].values * ph[..., None]
    np.testing.assert_allclose(res.stacked["p"]["VISIBILITY"].values, want, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(res.stacked["p"]["UVW"].values, uvw)
    np.testing.assert_array_equal(res.stacked["p"]["WEIGHT"].values, ds["WEIGHT"].values)


def _isolated_pointings(fluxes, separation=0.02, telescope="ALMA", dish=12.0, freq0=230e9):
    """One pointing per source, far apart (beyond the PB cutoff of the others); the data hold
    the primary-beam attenuated source (A S), noiseless."""
    beam = standard_beam(telescope, dish)
    parts, ras, decs = {}, [], []
    for i, s in enumerate(fluxes):
        center = (VLA_CENTER[0] + i * separation, VLA_CENTER[1])
        ra, dec = lm_to_radec(2e-5 * (i + 1), -1.5e-5 * i, *center)
        theta = np.arccos(np.sin(dec) * np.sin(center[1])
                          + np.cos(dec) * np.cos(center[1]) * np.cos(ra - center[0]))
        freqs = freq0 + 25e6 * np.arange(3)
        # attenuated flux per channel: build per channel by summing channel-specific sources
        ds = make_stack_partition(n_time=6, n_ant=6, n_chan=3, freq0=freq0, extent_m=150.0,
                                  phase_center=center, sources=[(ra, dec, 1.0)], seed=10 + i,
                                  telescope=telescope, dish=dish, weight_scale=1.0, field_id=i,
                                  pols=("XX", "YY"))
        att = beam(theta, freqs)
        ds["VISIBILITY"] = ds["VISIBILITY"] * (s * att)[None, None, :, None]
        parts[f"spw0_field{i}"] = ds
        ras.append(ra)
        decs.append(dec)
    return parts, np.array(ras), np.array(decs)


def test_flux_equals_mean_input_flux_mosaic():
    fluxes = [1e-3, 2.5e-3, 0.4e-3]
    parts, ra, dec = _isolated_pointings(fluxes)
    res = stack_uv(xr.DataTree.from_dict(parts), _cat(ra, dec), weighting="none")
    assert res.flux_jy == pytest.approx(np.mean(fluxes), rel=1e-6)
    assert res.n_positions == 3
    assert list(res.positions["n_pointings"]) == [1, 1, 1]
    # the same sources as separate datasets stacked together
    trees = [xr.DataTree.from_dict({k: v}) for k, v in parts.items()]
    res2 = stack_uv(trees, _cat(ra, dec), weighting="none")
    assert res2.flux_jy == pytest.approx(np.mean(fluxes), rel=1e-6)
    assert len(res2.stacked) == 3


def test_mosaic_weights_corrected_by_sum_of_position_weights():
    """Pointing 0 holds 3 positions, pointing 1 one: visibilities of 0 weigh 3x (none)."""
    parts, ra, dec = _isolated_pointings([1e-3, 2e-3])
    c0 = parts["spw0_field0"].attrs["phase_center"]
    # two more positions in pointing 0, at the source (exact duplicates of position 0)
    ra3 = np.concatenate([ra, [ra[0], ra[0]]])
    dec3 = np.concatenate([dec, [dec[0], dec[0]]])
    res = stack_uv(xr.DataTree.from_dict(parts), _cat(ra3, dec3), weighting="none")
    assert res.stacked["spw0_field0"].attrs["uvstack_sum_weight"] == 3.0
    np.testing.assert_allclose(res.stacked["spw0_field0"]["WEIGHT"].values,
                               3.0 * parts["spw0_field0"]["WEIGHT"].values)
    assert res.flux_jy == pytest.approx((3 * 1e-3 + 2e-3) / 4, rel=1e-6)
    assert c0 == parts["spw0_field0"].attrs["phase_center"]


def test_output_store(tmp_path, rng):
    ds = make_stack_partition(n_time=6, n_ant=5, n_chan=3, sigma=1.0, seed=2)
    ra, dec = _offsets(VLA_CENTER, rng, 4, 0.003)
    out = tmp_path / "stacked.zarr"
    res = stack_uv(_tree(spw0_field0=ds), _cat(ra, dec), out=out)
    tree = open_store(out)
    st = tree["spw0_field0"].to_dataset()
    assert tree.attrs["xstack_kind"] == "stacked"
    np.testing.assert_array_equal(st["UVW"].values, ds["UVW"].values)
    np.testing.assert_allclose(st["VISIBILITY"].values, res.stacked["spw0_field0"]["VISIBILITY"].values)
    pc = st.attrs["phase_center"]
    assert np.degrees(pc) == pytest.approx(res.options["stack_center_deg"])
    assert st.attrs["original_phase_center"] == list(VLA_CENTER)
    np.testing.assert_allclose(st["STACK_POSITION_RA"].values, np.degrees(ra))
    assert tree.attrs["uvstack"]["flux_jy"] == pytest.approx(res.flux_jy)
    with pytest.raises(XstackError, match="exists"):
        stack_uv(_tree(spw0_field0=ds), _cat(ra, dec), out=out)
    # restacking the written store at its own phase center gives the same flux
    res2 = stack_uv(out, _cat(*pc), primary_beam="none", weighting="none")
    assert res2.flux_jy == pytest.approx(res.flux_jy, rel=1e-6)


def test_written_stack_and_flux_in_one_pass_equal_the_flux_only_pass(tmp_path, rng):
    # with out= the flux sums share each chunk's phasor with the written stack; the result
    # must be the flux-only pass's, and the written data the reference's
    ds = make_stack_partition(n_time=12, n_ant=6, n_chan=4, sigma=0.5, seed=8, flag_frac=0.1)
    ds = ds.chunk({"time": 5, "baseline_id": 7})
    ra, dec = _offsets(VLA_CENTER, rng, 9, 0.003)
    alone = stack_uv(_tree(spw0_field0=ds), _cat(ra, dec))
    written = stack_uv(_tree(spw0_field0=ds), _cat(ra, dec), out=tmp_path / "s.zarr")
    for key in ("flux_jy", "flux_err_jy", "flux_imag_jy", "n_visibilities"):
        assert getattr(written, key) == pytest.approx(getattr(alone, key), rel=1e-12, abs=0)
    ref = reference_uvstack([("spw0_field0", ds.compute())], np.degrees(ra), np.degrees(dec),
                            weighting="pb", primary_beam="auto")
    assert written.flux_jy == pytest.approx(ref["flux_jy"], rel=1e-9)
    st = open_store(tmp_path / "s.zarr")["spw0_field0"].to_dataset()
    # stored at the input precision (complex64)
    np.testing.assert_allclose(st["VISIBILITY"].values, ref["stacked"]["spw0_field0"], rtol=1e-5,
                               atol=1e-6)
    assert open_store(tmp_path / "s.zarr").attrs["uvstack"]["flux_jy"] == written.flux_jy


def test_uncovered_positions_reported_and_all_outside_rejected():
    ds = make_stack_partition(n_time=4, n_ant=5, n_chan=2, sigma=1.0)
    far = (VLA_CENTER[0] + 0.2, VLA_CENTER[1])
    with pytest.warns(UserWarning, match="1 of 2 positions"):
        res = stack_uv(_tree(p=ds), _cat([VLA_CENTER[0], far[0]], [VLA_CENTER[1], far[1]]))
    assert len(res.uncovered) == 1 and res.n_positions == 1
    assert res.uncovered["ra"][0] == pytest.approx(np.degrees(far[0]))
    with pytest.raises(XstackError, match="none of the 1 positions"):
        stack_uv(_tree(p=ds), _cat(*far))


def test_bad_options():
    ds = make_stack_partition(n_time=4, n_ant=5, n_chan=2, sigma=1.0)
    cat = _cat(*VLA_CENTER)
    for kwargs, msg in [({"weighting": "bogus"}, "weighting"), ({"engine": "gpu"}, "engine"),
                        ({"primary_beam": "square"}, "primary beam"),
                        ({"weighting": "column"}, "weight"), ({"uvmin": "3parsec"}, "unit"),
                        ({"pb_cutoff": 1.5}, "pb_cutoff"),
                        ({"weighting": "sigma2", "sigma": [1.0, 2.0]}, "one per position"),
                        ({"weighting": "sigma2", "sigma": -1.0}, "positive"),
                        ({"uvmin": "5km", "uvmax": "1km"}, "smaller"),
                        ({"primary_beam": "/nonexistent/pb.fits"}, "no such")]:
        with pytest.raises(XstackError, match=msg):
            stack_uv(_tree(p=ds), cat, **kwargs)


def test_uv_range_selects_visibilities():
    ds = make_stack_partition(n_time=6, n_ant=6, n_chan=3, sigma=1.0, seed=4)
    cat = _cat(*VLA_CENTER)
    full = stack_uv(_tree(p=ds), cat, primary_beam="none")
    for lo, hi in [("500m", "2000m"), ("3klambda", "10klambda"), (None, "1.5km")]:
        res = stack_uv(_tree(p=ds), cat, primary_beam="none", uvmin=lo, uvmax=hi)
        ref = reference_uvstack([("p", ds)], cat["ra"], cat["dec"], uvmin=lo, uvmax=hi)
        assert 0 < res.n_visibilities < full.n_visibilities
        assert res.n_visibilities == ref["n_visibilities"]
        assert res.flux_jy == pytest.approx(ref["flux_jy"], rel=1e-9)


@pytest.mark.parametrize("spectral", [False, True])
def test_fits_primary_beam_matches_model(tmp_path, rng, spectral):
    """A FITS beam image sampled from the Gaussian model gives the same stack as the model."""
    from astropy.io import fits
    from astropy.wcs import WCS

    # 3 channels: the mean frequency (where the attenuation column is reported) is a plane
    ds = make_stack_partition(n_time=6, n_ant=6, n_chan=3, sigma=1.0, seed=13, dfreq=200e6)
    freq = ds["frequency"].values
    model = standard_beam("VLA", 25.0, model="gaussian")
    npix, cell = 257, np.radians(10 / 3600)
    w = WCS(naxis=4 if spectral else 2)
    w.wcs.ctype = ["RA---SIN", "DEC--SIN"] + (["FREQ", "STOKES"] if spectral else [])
    w.wcs.crval = [10.0, 40.0] + ([freq[0], 1.0] if spectral else [])
    w.wcs.crpix = [129, 129] + ([1, 1] if spectral else [])
    w.wcs.cdelt = [-np.degrees(cell), np.degrees(cell)] + ([freq[1] - freq[0], 1] if spectral else [])
    w.wcs.cunit = ["deg", "deg"] + (["Hz", ""] if spectral else [])
    y, x = np.mgrid[:npix, :npix]
    lpix = -(x - 128) * cell
    mpix = (y - 128) * cell
    theta = np.arcsin(np.hypot(lpix, mpix))
    planes = [model(theta, f) for f in (freq if spectral else freq[:1])]
    data = np.array(planes)[None] if spectral else planes[0]
    path = tmp_path / "pb.fits"
    fits.PrimaryHDU(data=data.astype(np.float32), header=w.to_header()).writeto(path)
    ra, dec = lm_to_radec(rng.uniform(-4e-3, 4e-3, 6), rng.uniform(-4e-3, 4e-3, 6), *VLA_CENTER)
    got = stack_uv(_tree(p=ds), _cat(ra, dec), primary_beam=str(path))
    if spectral:
        want = stack_uv(_tree(p=ds), _cat(ra, dec), primary_beam="gaussian")
    else:  # one plane at the first channel used for every channel
        one = ds.isel(frequency=[0])
        got = stack_uv(_tree(p=one), _cat(ra, dec), primary_beam=str(path))
        want = stack_uv(_tree(p=one), _cat(ra, dec), primary_beam="gaussian")
    att_got = np.asarray(got.positions["attenuation"])
    att_want = np.asarray(want.positions["attenuation"])
    np.testing.assert_allclose(att_got, att_want, rtol=2e-3, atol=1e-4)
    assert got.flux_jy == pytest.approx(want.flux_jy, rel=5e-3, abs=1e-3 * want.flux_err_jy)


def test_simulated_point_source_through_the_sim_stage():
    """Cross-stage conventions: xstack.sim (eq. 1, standard VLA beam, w-term) and uvstack
    agree exactly on an off-center noiseless point source (primary-beam corrected)."""
    from xstack.sim.simulate import simulate_partitions

    scene = {
        "array": {"config": "vla.d"},
        "observation": {"date": "2014-01-01", "hour_angle": [-1.0, 1.0], "integration": 60.0,
                        "time_per_pointing": 1200.0},
        "spectral": {"center": 1.4e9, "bandwidth": 100e6, "channels": 4,
                     "polarizations": ["RR", "LL"]},
        "pointings": {"mode": "single", "center": ["3h49m10.99s", "-30d00m00s"]},
        "effects": {"primary_beam": "auto", "w_term": True},
        "populations": [{"name": "targets", "count": 1, "flux": {"kind": "fixed", "value": "1mJy"},
                         "positions": {"kind": "box", "size_arcsec": [1200, 1200]},
                         "shape": {"kind": "point"}}],
    }
    parts, cats = simulate_partitions(scene, seed=3)
    res = stack_uv(xr.DataTree.from_dict(parts), cats["targets"])
    assert res.positions["attenuation"][0, 0] < 0.99  # really attenuated
    assert res.flux_jy == pytest.approx(1e-3, rel=1e-6)


def test_nufft_engine_end_to_end(rng):
    """Compact array, compact field: the NUFFT engine equals numba; huge grids are refused."""
    ds = make_stack_partition(n_time=6, n_ant=6, n_chan=3, sigma=1.0, seed=14, extent_m=100.0,
                              telescope="ALMA", dish=12.0, freq0=100e9, pols=("XX", "YY"))
    ra, dec = lm_to_radec(rng.uniform(-1e-4, 1e-4, 30), rng.uniform(-1e-4, 1e-4, 30), *VLA_CENTER)
    a = stack_uv(_tree(p=ds), _cat(ra, dec), engine="nufft")
    b = stack_uv(_tree(p=ds), _cat(ra, dec), engine="numba")
    assert a.flux_jy == pytest.approx(b.flux_jy, rel=1e-9, abs=1e-9 * b.flux_err_jy)
    big = make_stack_partition(n_time=4, n_ant=6, n_chan=2, sigma=1.0, extent_m=30000.0)
    ra2, dec2 = lm_to_radec([-4e-3, 4e-3], [4e-3, -4e-3], *VLA_CENTER)
    with pytest.raises(XstackError, match="nufft"):
        stack_uv(_tree(p=big), _cat(ra2, dec2), engine="nufft", primary_beam="none")
