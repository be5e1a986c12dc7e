"""Line sources in the simulator (issue 15): channel-averaged profiles against the analytic
erf integral (computed here from scipy, not from xstack), the Doppler track of TOPO channels
against astropy directly, flux conservation, the presets, and continuum scenes unchanged (to
rounding, against references made before line sources)."""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table
from scipy.special import erf

from xstack.frames import frame_ratio, frequency_frame
from xstack.schema import iter_partitions, open_store
from xstack.sim.presets import LINE_PRESETS, preset_scene
from xstack.sim.scene import PAPER_FIELD_CENTER, load_scene
from xstack.sim.simulate import simulate, simulate_partitions

C_KMS = 299_792.458
HI = 1_420_405_751.768
Z = 0.15
NU_C = HI / (1 + Z)
FLUX, FWHM = 0.3, 200.0  # Jy km/s, km/s
SIGMA = FWHM / (2 * np.sqrt(2 * np.log(2)))


def _scene(frame, *, channels=64, width=100e3, days=0, profile="gaussian", line_frame=None):
    """One line source at the phase centre of 5 VLA-C antennas, no noise, no beam.

    ``days``: one 10-minute integration a day on that many days (the annual Doppler drift
    moves the line by channels), else a 6-hour track in 36 integrations.
    """
    obs = ({"date": "2014-01-01", "hour_angle": [-0.1, 0.1], "integration": 600.0,
            "time_per_pointing": 600.0 * days} if days else
           {"date": "2014-01-01", "hour_angle": [-3, 3], "integration": 600.0,
            "time_per_pointing": 21600.0})
    spectral = {"center": NU_C, "bandwidth": channels * width, "channels": channels,
                "polarizations": ["RR", "LL"], "line": "HI", "frame": frame}
    if line_frame:
        spectral["line_frame"] = line_frame
    return {"name": "one-line", "array": {"config": "vla.c", "antennas": [0, 1, 2, 3, 4]},
            "observation": obs, "spectral": spectral,
            "pointings": {"mode": "single", "center": list(PAPER_FIELD_CENTER)},
            "populations": [{"name": "gal", "count": 1, "flux": {"kind": "fixed", "value": 0.0},
                             "positions": {"kind": "list", "ra": [PAPER_FIELD_CENTER[0]],
                                           "dec": [PAPER_FIELD_CENTER[1]]},
                             "line": {"profile": profile, "flux_jy_kms": [FLUX],
                                      "fwhm_kms": [FWHM], "z_values": [Z]}}]}


def _analytic(f_lo, f_hi, centre=NU_C):
    """Channel average of the Gaussian line over [f_lo, f_hi] (Hz), Jy: scipy's erf."""
    v_a = C_KMS * (centre - f_hi) / centre
    v_b = C_KMS * (centre - f_lo) / centre
    k = 1.0 / (SIGMA * np.sqrt(2.0))
    return FLUX * 0.5 * (erf(v_b * k) - erf(v_a * k)) / (v_b - v_a)


def _one(scene):
    parts, cats = simulate_partitions(load_scene(scene))
    (ds,) = parts.values()
    return ds, cats


def test_lsrk_channels_hold_the_channel_averaged_gaussian():
    ds, cats = _one(_scene("LSRK"))
    assert frequency_frame(ds) == "LSRK"
    f, w = ds.frequency.values, ds.channel_width.values
    expect = _analytic(f - w / 2, f + w / 2)
    vis = ds.VISIBILITY.values
    # every integration, baseline and parallel hand: the same spectrum, real, as computed
    peak = expect.max()
    np.testing.assert_allclose(vis.real, np.broadcast_to(expect[None, None, :, None], vis.shape),
                               rtol=1e-6, atol=1e-9 * peak)
    assert np.abs(vis.imag).max() <= 1e-9 * peak
    # not sampled at the centre: a point-sampled Gaussian differs by far more than 1e-6
    v_mid = C_KMS * (NU_C - f) / NU_C
    sampled = FLUX / (SIGMA * np.sqrt(2 * np.pi)) * np.exp(-0.5 * (v_mid / SIGMA) ** 2)
    assert np.abs(sampled - expect).max() > 1e-4 * peak
    # the integral over the channels (flux density x velocity width) is the line flux
    dv = C_KMS * w / NU_C
    np.testing.assert_allclose(np.sum(vis[0, 0, :, 0].real.astype(np.float64) * dv), FLUX,
                               rtol=1e-6)
    cat = cats["gal"]
    for col in ("z", "freq", "line_flux_jy_kms", "line_fwhm_kms"):
        assert col in cat.colnames
    assert cat["z"][0] == Z and cat["freq"][0] == pytest.approx(NU_C, rel=1e-15)
    assert cat["line_flux_jy_kms"][0] == FLUX and cat["line_fwhm_kms"][0] == FWHM


def test_double_horn_conserves_flux_and_has_two_horns():
    ds, _ = _one(_scene("LSRK", profile="double"))
    f, w = ds.frequency.values, ds.channel_width.values
    spec = ds.VISIBILITY.values[0, 0, :, 0].real.astype(np.float64)
    np.testing.assert_allclose(np.sum(spec * C_KMS * w / NU_C), FLUX, rtol=1e-6)
    # two Gaussians of FLUX/2, FWHM/3 wide, at +-FWHM/3 (as documented), from scipy
    s3, off = SIGMA / 3, FWHM / 3
    v_a = C_KMS * (NU_C - (f + w / 2)) / NU_C
    v_b = C_KMS * (NU_C - (f - w / 2)) / NU_C
    k = 1 / (s3 * np.sqrt(2))
    horns = sum(0.5 * FLUX * 0.5 * (erf((v_b - o) * k) - erf((v_a - o) * k)) / (v_b - v_a)
                for o in (-off, off))
    np.testing.assert_allclose(spec, horns, rtol=1e-6, atol=1e-9 * horns.max())
    mid = np.argmin(np.abs(f - NU_C))
    assert spec[mid] < 0.5 * spec.max()


def _astropy_lsrk_over_topo(times_mjd_s, ra_deg, dec_deg, site_itrf_m):
    """nu_LSRK / nu_TOPO from astropy's SpectralCoord, one integration at a time."""
    import astropy.units as u
    from astropy.coordinates import EarthLocation, SkyCoord, SpectralCoord
    from astropy.time import Time

    site = EarthLocation.from_geocentric(*site_itrf_m, unit=u.m)
    target = SkyCoord(ra_deg * u.deg, dec_deg * u.deg)
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for t in times_mjd_s:
            obs = site.get_gcrs(Time(t / 86400.0, format="mjd", scale="utc"))
            sc = SpectralCoord(1e9 * u.Hz, observer=obs, target=target)
            out.append(sc.with_observer_stationary_relative_to("lsrk").to_value(u.Hz) / 1e9)
    return np.asarray(out)


def test_topo_channels_carry_the_doppler_track():
    # 120 days, one integration a day: the line moves by tens of km/s in TOPO
    ds, _ = _one(_scene("TOPO", channels=512, width=10e3, days=120))
    assert frequency_frame(ds) == "TOPO"
    f, w = ds.frequency.values, ds.channel_width.values
    t = ds.time.values
    site = ds.ANTENNA_POSITION.values.mean(axis=0)  # the array centre, as the stacker's
    ra, dec = np.degrees(ds.attrs["phase_center"])
    vis = ds.VISIBILITY.values[:, 0, :, 0].real.astype(np.float64)
    # per integration, the analytic channel average over the channel edges moved to LSRK
    r = frame_ratio(t, ra, dec, site, to_frame="LSRK")
    expect = _analytic(r[:, None] * (f - w / 2), r[:, None] * (f + w / 2))
    np.testing.assert_allclose(vis, expect, rtol=1e-6, atol=1e-9 * expect.max())
    # the track itself, against astropy directly: the line's centroid in TOPO frequency is
    # nu_c / r(t) (the box-averaged Gaussian's centroid is exact to ~exp(-2 pi^2 s^2/dnu^2))
    centroid = (vis * f).sum(axis=1) / vis.sum(axis=1)
    r_astropy = _astropy_lsrk_over_topo(t, ra, dec, site)
    v_track = C_KMS * (1 - NU_C / r_astropy / NU_C)
    v_seen = C_KMS * (1 - centroid / NU_C)
    # SpectralCoord keeps the radial Doppler only: <= 1.5 m/s from the exact factor
    np.testing.assert_allclose(v_seen, v_track, atol=0.01)  # km/s
    # the peak channel moves over the track by the amount the frames say
    peak = vis.argmax(axis=1)
    expected_peak = np.abs((NU_C / r_astropy)[:, None] - f[None, :]).argmin(axis=1)
    assert np.ptp(peak) >= 5
    assert np.abs(peak - expected_peak).max() <= 1
    # every integration still holds the whole line
    np.testing.assert_allclose((vis * C_KMS * w / NU_C * r[:, None]).sum(axis=1), FLUX,
                               rtol=1e-6)


def test_bary_lines_in_lsrk_channels_are_shifted_once():
    """Lines fixed in BARY, channels in LSRK: a constant shift, the LSRK - BARY velocity."""
    ds, _ = _one(_scene("LSRK", line_frame="bary"))
    f, w, t = ds.frequency.values, ds.channel_width.values, ds.time.values
    ra, dec = np.degrees(ds.attrs["phase_center"])
    r = frame_ratio(t, ra, dec, ds.ANTENNA_POSITION.values.mean(axis=0), to_frame="BARY",
                    from_frame="LSRK")
    assert np.ptp(r) < 1e-15  # no time dependence between two sky frames
    vis = ds.VISIBILITY.values[:, 0, :, 0].real
    expect = _analytic(r[:, None] * (f - w / 2), r[:, None] * (f + w / 2))
    np.testing.assert_allclose(vis, expect, rtol=1e-6, atol=1e-9 * expect.max())


def test_line_off_centre_with_beam_matches_a_continuum_source():
    """An off-centre line source with the primary beam and w-term is, channel by channel, a
    continuum source of the channel's line flux density: same kernel path as continuum."""
    scene = _scene("LSRK")
    scene["effects"] = {"primary_beam": "auto", "w_term": True}
    ra0, dec0 = PAPER_FIELD_CENTER
    pos = {"kind": "list", "ra": [ra0 + 0.01], "dec": [dec0 + 0.005]}
    scene["populations"][0]["positions"] = pos
    ds, _ = _one(scene)
    f, w = ds.frequency.values, ds.channel_width.values
    spectrum = _analytic(f - w / 2, f + w / 2)
    peak = int(spectrum.argmax())
    cont = _scene("LSRK")
    cont["effects"] = {"primary_beam": "auto", "w_term": True}
    cont["spectral"] = {k: v for k, v in cont["spectral"].items() if k not in ("line", "frame")}
    cont["populations"] = [{"name": "c", "count": 1, "positions": pos,
                            "flux": {"kind": "fixed", "value": float(spectrum[peak])}}]
    parts, _ = simulate_partitions(load_scene(cont))
    (dc,) = parts.values()
    a = ds.VISIBILITY.values[:, :, peak, 0]
    b = dc.VISIBILITY.values[:, :, peak, 0]
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6 * np.abs(b).max())


#: Continuum presets whose data must stay what they were before line sources existed: noise,
#: primary beam, w-term, extended sources, a mosaic (22 pointings).
CONTINUUM_PRESETS = [("paper-7", 0.01), ("paper-8", 0.02)]
FINGERPRINTS = Path(__file__).parent / "data" / "continuum_fingerprints.json"


def _unflagged(scene):
    """The preset as it was before the presets flagged like CASA's simulator (elevation limit,
    shadowing): the references below were made without flags."""
    return dataclasses.replace(scene, effects=dataclasses.replace(scene.effects, flagging=None))


def _arrays(store, catalog_paths):
    """Every array of a simulated store and its catalogs, by name."""
    arrays = {}
    for name, ds in iter_partitions(open_store(store)):
        for var in ("VISIBILITY", "WEIGHT", "FLAG", "UVW", "time", "frequency", "channel_width"):
            arrays[f"{name}/{var}"] = ds[var].values
    for pop in sorted(catalog_paths):
        t = Table.read(catalog_paths[pop], format="ascii.ecsv")
        for col in t.colnames:
            arrays[f"catalog/{pop}/{col}"] = np.asarray(t[col])
    return arrays


def _fingerprint(arrays):
    """Numbers that pin every array to rounding.

    A sha256 of the bytes is not portable: numpy's and numba's sin/cos/exp take different
    SIMD paths on different CPUs (AVX2 here, AVX-512 elsewhere) and their last bits differ,
    so the data of one code version hash differently on two machines (the sha256 this test
    held failed in CI for that reason). Instead each float array is reduced, in float64, to
    its L2 norm, its sum and 4 projections on fixed random +-1 vectors (numpy's PCG64 with a
    fixed seed: the same signs on every machine); any change larger than rounding -- a
    different seed, a missing effect, a permuted row -- moves them. Integer and boolean arrays
    are compared exactly.
    """
    out = {}
    for key, values in arrays.items():
        x = np.asarray(values)
        if np.iscomplexobj(x):
            x = np.stack([x.real, x.imag], axis=-1)
        exact = x.dtype.kind in "biu"
        # rounding allowed, as a fraction of the norm: float32 rounding is 6e-8 of each
        # element and float64's 1e-16; projections of n elements' rounding add up to about
        # that fraction of the norm, so these leave room for another CPU's last bits and
        # still see one element of 1e5 changed by a few per mille of the typical value
        rtol = 0.0 if exact else (1e-5 if x.dtype.itemsize <= 4 else 1e-10)
        x = x.astype(np.float64).ravel()
        signs = np.random.default_rng(20261202).choice([-1.0, 1.0], size=(4, x.size))
        out[key] = {"exact": exact, "rtol": rtol, "norm": float(np.sqrt(np.sum(x * x))),
                    "sum": float(x.sum()), "proj": [float(v) for v in signs @ x]}
    return out


def _assert_same_fingerprint(got, ref):
    assert sorted(got) == sorted(ref)
    for key, r in ref.items():
        g = got[key]
        if r["exact"]:
            assert g == r, key
            continue
        tol = r["rtol"] * r["norm"] + 1e-300
        np.testing.assert_allclose(g["norm"], r["norm"], rtol=r["rtol"], err_msg=key)
        np.testing.assert_allclose(g["sum"], r["sum"], rtol=0, atol=tol, err_msg=key)
        np.testing.assert_allclose(g["proj"], r["proj"], rtol=0, atol=tol, err_msg=key)


@pytest.mark.parametrize("name, scale", CONTINUUM_PRESETS)
def test_continuum_presets_unchanged(name, scale, tmp_path):
    """References made by the simulator before line sources (git 28699e2, by
    ``tests/data/make_continuum_fingerprints.py``), which on the
    machine that made them gives bit for bit the same data as the current simulator."""
    res = simulate(_unflagged(preset_scene(name)), tmp_path / "p.zarr", seed=3, scale=scale)
    assert "line" not in res.steps_run
    ref = json.loads(FINGERPRINTS.read_text())[f"{name}@{scale}"]
    _assert_same_fingerprint(_fingerprint(_arrays(res.store, res.catalog_paths)), ref)
    for _, ds in iter_partitions(open_store(res.store)):
        assert frequency_frame(ds) == "TOPO"


def test_fingerprint_sees_a_small_change(tmp_path):
    """The comparison can fail: one visibility of 22 x 99 200 changed by 1 % of the largest,
    and one target moved by 0.1 arcsec, are each seen; the unchanged data pass."""
    res = simulate(_unflagged(preset_scene("paper-8")), tmp_path / "p.zarr", seed=3, scale=0.02)
    arrays = _arrays(res.store, res.catalog_paths)
    ref = _fingerprint(arrays)
    _assert_same_fingerprint(_fingerprint(arrays), ref)
    vis = arrays["spw0_field7/VISIBILITY"].copy()
    vis[0, 100, 50, 0] += 0.01 * np.abs(vis).max()
    with pytest.raises(AssertionError, match="VISIBILITY"):
        _assert_same_fingerprint(_fingerprint({**arrays, "spw0_field7/VISIBILITY": vis}), ref)
    dec = arrays["catalog/targets/dec"].copy()
    dec[3] += 0.1 / 3600
    with pytest.raises(AssertionError, match="dec"):
        _assert_same_fingerprint(_fingerprint({**arrays, "catalog/targets/dec": dec}), ref)


@pytest.mark.parametrize("name", LINE_PRESETS)
def test_line_preset_tiny_scale_runs_and_writes_truth(name, tmp_path):
    import tomllib

    from xstack.sim.scene import scene_to_toml

    scene = preset_scene(name)
    assert load_scene(tomllib.loads(scene_to_toml(scene))) == scene  # --print-scene round trip
    res = simulate(scene, tmp_path / "l.zarr", seed=1, scale=0.01)
    assert "line" in res.steps_run
    (pop,) = [q.name for q in scene.populations if q.line is not None]
    cat = Table.read(res.catalog_paths[pop], format="ascii.ecsv")
    for col in ("ra", "dec", "z", "freq", "line_flux_jy_kms", "line_fwhm_kms"):
        assert col in cat.colnames
    assert 10 <= len(cat) < next(q.count for q in scene.populations if q.line is not None)
    # every line centre inside the band, and frequencies consistent with the redshifts
    parts = list(iter_partitions(open_store(res.store)))
    f = parts[0][1].frequency.values
    assert np.all((cat["freq"] > f.min()) & (cat["freq"] < f.max()))
    from xstack.spectral import rest_frequency

    rest = rest_frequency(scene.spectral.line)
    np.testing.assert_allclose(cat["freq"], rest / (1 + cat["z"]), rtol=1e-14)
    vis = parts[0][1].VISIBILITY.values
    assert np.isfinite(vis).all() and np.abs(vis).max() > 0


def test_line_settings_are_checked():
    from xstack.errors import XstackError

    bad = _scene("LSRK")
    del bad["spectral"]["line"]
    with pytest.raises(XstackError, match="spectral.line"):
        load_scene(bad)
    bad = _scene("LSRK", line_frame="galactic")
    with pytest.raises(XstackError, match="line_frame"):
        load_scene(bad)
    bad = _scene("LSRK")
    bad["populations"][0]["line"]["profile"] = "boxcar"
    with pytest.raises(XstackError, match="profile"):
        load_scene(bad)
    bad = _scene("LSRK")
    bad["populations"][0]["line"]["z"] = [0.1]
    with pytest.raises(XstackError, match="exactly one of"):
        load_scene(bad)


def test_lines_do_not_depend_on_the_chunking():
    scene = _scene("TOPO", channels=128, width=50e3)
    scene["effects"] = {"primary_beam": "auto", "w_term": True}
    ra0, dec0 = PAPER_FIELD_CENTER
    scene["populations"][0]["positions"] = {"kind": "list", "ra": [ra0 + 0.01],
                                            "dec": [dec0 - 0.01]}
    a, _ = _one(scene)
    scene.update(time_chunk=5, baseline_chunk=3)
    b, _ = _one(scene)
    assert b.VISIBILITY.data.numblocks[:2] != a.VISIBILITY.data.numblocks[:2]
    np.testing.assert_array_equal(a.VISIBILITY.values, b.VISIBILITY.values)
