"""Bandwidth and time-average smearing: simulated on request, predicted and corrected by uvstack.

Truth from outside the code under test: finite differences of the simulator's own UVW (the
Earth-rotation rates), numerical channel averages, plain-numpy equation 1 on k-times finer
channels and integrations averaged to the coarse grid (``_sim_helpers.direct_eq1``), plain
numpy means of sinc factors over all visibilities (the analytic loss), injected fluxes.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import xarray as xr
from _sim_helpers import direct_eq1

from xstack.errors import XstackError
from xstack.schema import baseline_pairs
from xstack.sim import arrays as arr
from xstack.sim.kernels import record_steps
from xstack.sim.scene import load_scene, scene_to_toml
from xstack.sim.simulate import simulate_partitions
from xstack.smearing import EARTH_ROTATION_RATE, delay_rates, smearing_factors
from xstack.uvstack import smearing as usm
from xstack.uvstack.stack import stack_uv

C = 299_792_458.0
ARCMIN = math.pi / (180 * 60)
RA0, DEC0 = math.radians(57.2957916666667), math.radians(-30.0)


def _lmn(ra, dec, ra0=RA0, dec0=DEC0):
    """Direction cosines, plain numpy (conventions.md)."""
    ra, dec = np.radians(np.asarray(ra, float)), np.radians(np.asarray(dec, float))
    da_ = ra - ra0
    l = np.cos(dec) * np.sin(da_)
    m = np.sin(dec) * np.cos(dec0) - np.cos(dec) * np.sin(dec0) * np.cos(da_)
    n = np.sqrt(1 - l**2 - m**2)
    return l, m, -(l**2 + m**2) / (1 + n)


def _offsets_deg(offsets_arcmin):
    """(ra, dec) degrees of tangent-plane offsets (arcmin) from the field center."""
    from xstack.coords import lm_to_radec

    x = np.array([o[0] for o in offsets_arcmin]) * ARCMIN
    y = np.array([o[1] for o in offsets_arcmin]) * ARCMIN
    ra, dec = lm_to_radec(x, y, RA0, DEC0)
    return list(np.degrees(ra)), list(np.degrees(dec))


# ------------------------------------------------------------------ the factors themselves

def test_delay_rate_matches_finite_differences_of_simulator_uvw():
    """du/dt, dv/dt, dw/dt of the docstring against central differences of the simulator's
    own UVW (ERFA geometry): equal to 2e-3 (the residue is precession of the pole since
    J2000, which tilts the rotation axis by 0.19 degrees), and the sign right."""
    a = arr.packaged_array("vla.a")
    a1, a2 = baseline_pairs(a.n_antennas)
    t = 56658 * 86400.0 + 5 * 3600.0
    h = 1.0

    def uvw_at(tt):
        return arr.baseline_uvw(a.positions, a1, a2, np.array([tt]), RA0, DEC0)[0]

    uvw = uvw_at(t)
    fd = (uvw_at(t + h) - uvw_at(t - h)) / (2 * h)
    # delay rate of unit directions picks out du/dt (l), dv/dt (m), dw/dt (n - 1)
    rates = delay_rates(uvw, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], DEC0)
    scale = np.abs(fd).max()
    assert scale > 1.0  # VLA A: metres per second
    assert np.abs(rates - fd).max() / scale < 2e-3
    # and the opposite sign is far off
    assert np.abs(-rates - fd).max() / scale > 1.0


def test_bandwidth_factor_is_the_channel_average():
    """sinc(pi d dnu / c) against a fine numerical average of exp(2 pi i d nu / c) over the
    channel; the time factor against a numerical average over the integration of the phase
    with the rate of the finite-difference test."""
    rng = np.random.default_rng(3)
    uvw = rng.normal(scale=15e3, size=(50, 3))
    l, m, nm1 = _lmn(np.degrees(RA0) + 0.2, -29.9)
    freq, width, dt = np.array([1.4e9, 1.5e9]), np.array([2e6, 3e6]), 20.0
    f_b = smearing_factors(uvw, freq, width, dt, l, m, nm1, DEC0, time=False)[:, 0, :]
    d = uvw @ np.array([l[()], m[()], nm1[()]])
    x = (np.arange(4000) + 0.5) / 4000 - 0.5  # midpoints across the channel
    for c in range(2):
        nu = freq[c] + width[c] * x
        avg = np.exp(2j * np.pi * d[:, None] * nu[None, :] / C).mean(axis=1)
        ref = avg * np.exp(-2j * np.pi * d * freq[c] / C)  # the phase at the center removed
        assert np.abs(ref.imag).max() < 1e-6
        np.testing.assert_allclose(f_b[:, c], ref.real, atol=1e-6)
    assert f_b.min() < 0.9  # a real effect
    f_t = smearing_factors(uvw, freq, width, dt, l, m, nm1, DEC0, bandwidth=False)[:, 0, :]
    s, co = math.sin(DEC0), math.cos(DEC0)
    u, v, w = uvw.T
    rate = EARTH_ROTATION_RATE * ((w * co - v * s) * l + u * s * m - u * co * nm1)
    for c in range(2):
        ph = 2 * np.pi * freq[c] / C * rate[:, None] * (dt * x)[None, :]
        np.testing.assert_allclose(f_t[:, c], np.exp(1j * ph).mean(axis=1).real, atol=1e-6)
    assert f_t.min() < 0.9


# ------------------------------------------------------------------ the simulator

def _bf_scene(kt: int, kf: int, bandwidth: bool, time: bool) -> dict:
    ra, dec = _offsets_deg([(14, 0), (0, 12), (-7, -9)])
    return {
        "name": "bf", "visibility_dtype": "complex128",
        "array": {"config": "vla.a", "antennas": ["W72", "E72", "N72", "W16", "E40"]},
        "observation": {"integration": 6.0 / kt, "time_per_pointing": 12.0,
                        "hour_angle": [-4, 4]},
        "spectral": {"center": 1.4e9, "bandwidth": 2e6, "channels": 2 * kf,
                     "polarizations": ["RR", "LL"]},
        "effects": {"primary_beam": "none", "w_term": True, "bandwidth_smearing": bandwidth,
                    "time_smearing": time},
        "populations": [
            {"name": "points", "count": 2, "flux": {"kind": "fixed", "value": 1.0},
             "positions": {"kind": "list", "ra": ra[:2], "dec": dec[:2]}},
            {"name": "blob", "count": 1, "flux": {"kind": "fixed", "value": 1.0},
             "shape": {"kind": "gaussian", "fwhm_arcsec": [2.0]},
             "positions": {"kind": "list", "ra": ra[2:], "dec": dec[2:]}}],
    }


def _only(parts: dict) -> xr.Dataset:
    (ds,) = parts.values()
    return ds.compute()


@pytest.mark.parametrize("bandwidth,time", [(True, False), (False, True), (True, True)])
def test_smeared_simulation_equals_brute_force_average(bandwidth, time):
    """The smeared simulation equals plain-numpy equation 1 at 16x finer channels and/or
    integrations (on the fine simulation's own UVW) averaged to the coarse grid, per
    visibility; without smearing the simulator is far from that average."""
    k = 16
    kt, kf = (k if time else 1), (k if bandwidth else 1)
    with record_steps() as steps:
        parts, cats = simulate_partitions(_bf_scene(1, 1, bandwidth, time))
        coarse = _only(parts)
    assert ("smear_bandwidth" in steps) == bandwidth and ("smear_time" in steps) == time
    assert coarse.attrs["smearing"] == {"bandwidth": bandwidth, "time": time}
    fine = _only(simulate_partitions(_bf_scene(kt, kf, False, False))[0])
    plain = _only(simulate_partitions(_bf_scene(1, 1, False, False))[0])
    # truth: plain numpy equation 1 on the fine grid, averaged
    ra = np.concatenate([cats["points"]["ra"], cats["blob"]["ra"]])
    dec = np.concatenate([cats["points"]["dec"], cats["blob"]["dec"]])
    l, m, nm1 = _lmn(ra, dec)
    fwhm = np.radians(np.array([0.0, 0.0, 2.0]) / 3600)
    uvw_f = fine["UVW"].values
    ntf, nb = uvw_f.shape[:2]
    freq_f = fine["frequency"].values
    vf = direct_eq1(uvw_f.reshape(-1, 3), freq_f, l, m, nm1, np.ones(3), fwhm=fwhm)
    np.testing.assert_allclose(fine["VISIBILITY"].values[..., 0].reshape(-1, freq_f.size), vf,
                               atol=1e-9)  # the fine grid itself is equation 1
    nt, nc = coarse.sizes["time"], coarse.sizes["frequency"]
    truth = vf.reshape(nt, kt, nb, nc, kf).mean(axis=(1, 4))
    sim = coarse["VISIBILITY"].values[..., 0]
    # midpoint-rule error of 16 samples is (x/16)^2/6 of the factor: < 1e-3 here
    assert np.abs(sim - truth).max() < 1.5e-3
    assert np.abs(plain["VISIBILITY"].values[..., 0] - truth).max() > 0.02
    # the fine and coarse grids cover the same times and channels
    np.testing.assert_allclose(fine["frequency"].values.reshape(nc, kf).mean(axis=1),
                               coarse["frequency"].values)
    np.testing.assert_allclose(fine["time"].values.reshape(nt, kt).mean(axis=1),
                               coarse["time"].values)


def test_smearing_is_opt_in_and_costs_nothing_otherwise():
    """Without the flags no smearing step runs (kernel counters, steps_run) and the data
    are the unsmeared equation 1; the partition records that it carries no smearing."""
    with record_steps() as steps:
        parts, cats = simulate_partitions(_bf_scene(1, 1, False, False))
        ds = _only(parts)
    assert "smear_bandwidth" not in steps and "smear_time" not in steps
    assert ds.attrs["smearing"] == {"bandwidth": False, "time": False}
    ra = np.concatenate([cats["points"]["ra"], cats["blob"]["ra"]])
    dec = np.concatenate([cats["points"]["dec"], cats["blob"]["dec"]])
    l, m, nm1 = _lmn(ra, dec)
    ref = direct_eq1(ds["UVW"].values.reshape(-1, 3), ds["frequency"].values, l, m, nm1,
                     np.ones(3), fwhm=np.radians(np.array([0.0, 0.0, 2.0]) / 3600))
    np.testing.assert_allclose(ds["VISIBILITY"].values[..., 0].reshape(ref.shape), ref,
                               atol=1e-9)
    from xstack.sim.simulate import _plan

    plan = _plan(load_scene(_bf_scene(1, 1, True, True)), 0, 1.0)
    assert {"bandwidth_smearing", "time_smearing"} <= plan.steps
    assert not {"bandwidth_smearing", "time_smearing"} & _plan(
        load_scene(_bf_scene(1, 1, False, False)), 0, 1.0).steps


def test_scene_flags_round_trip_and_are_validated():
    scene = load_scene(_bf_scene(1, 1, True, False))
    assert scene.effects.bandwidth_smearing and not scene.effects.time_smearing
    text = scene_to_toml(scene)
    assert "bandwidth_smearing = true" in text and "time_smearing = false" in text
    import tomllib

    again = load_scene(tomllib.loads(text))
    assert again.to_dict() == scene.to_dict()
    bad = _bf_scene(1, 1, True, False)
    bad["effects"]["time_smearing"] = "yes"
    with pytest.raises(XstackError, match="effects.time_smearing"):
        load_scene(bad)


# ------------------------------------------------------------------ uv-stacking

def _wide_scene(smear: bool) -> dict:
    """VLA A (27 antennas), 1.4 GHz, 4 x 2 MHz channels, 15 s integrations, 15 min; four
    1 Jy point sources 10-13' off axis: ~5-12 % smearing loss."""
    ra, dec = _offsets_deg([(12, 0), (-9, 8), (3, -13), (-10, -7)])
    return {
        "name": "wide", "visibility_dtype": "complex128",
        "array": {"config": "vla.a"},
        "observation": {"integration": 15.0, "time_per_pointing": 900.0,
                        "hour_angle": [-4, 4]},
        "spectral": {"center": 1.4e9, "bandwidth": 8e6, "channels": 4,
                     "polarizations": ["RR", "LL"]},
        "effects": {"primary_beam": "auto", "w_term": True, "bandwidth_smearing": smear,
                    "time_smearing": smear},
        "populations": [{"name": "t", "count": 4, "flux": {"kind": "fixed", "value": 1.0},
                         "positions": {"kind": "list", "ra": ra, "dec": dec}}],
    }


@pytest.fixture(scope="module")
def wide():
    out = {}
    for smear in (True, False):
        parts, cats = simulate_partitions(_wide_scene(smear))
        tree = xr.DataTree.from_dict({k: v.compute() for k, v in parts.items()})
        out[smear] = (tree, cats["t"])
    return out


def _plain_loss(ds: xr.Dataset, cat) -> np.ndarray:
    """Mean smearing factor of each position over every visibility (plain numpy)."""
    uvw = ds["UVW"].values.reshape(-1, 3)
    freq = ds["frequency"].values
    width = ds["channel_width"].values
    dt = float(ds["time"].attrs["integration_time"])
    ra0, dec0 = ds.attrs["phase_center"]
    l, m, nm1 = _lmn(cat["ra"], cat["dec"], ra0, dec0)
    u, v, w = (uvw[:, i][:, None] for i in range(3))
    d = u * l + v * m + w * nm1
    s, c = math.sin(dec0), math.cos(dec0)
    rate = 7.2921150e-5 * ((w * c - v * s) * l + u * s * m - u * c * nm1)
    f = np.sinc(d[..., None] * width / C) * np.sinc(rate[..., None] * freq * dt / C)
    return f.mean(axis=(0, 2))  # equal weights (noise-free simulation)


def _stack(tree, cat, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = stack_uv(tree, cat, weighting="none", **kw)
    return res, [str(w.message) for w in caught]


def test_uvstack_corrects_smearing_of_a_wide_field(wide):
    """Noise-free smeared wide field: uncorrected, the stack is low by the analytic loss
    (plain numpy over all visibilities); corrected (auto), it recovers the injected 1 Jy to
    < 0.5 %; the same scene without smearing is not corrected under auto."""
    tree, cat = wide[True]
    (ds,) = (tree[k].to_dataset() for k in tree.children)
    L = _plain_loss(ds, cat)
    assert 0.03 < 1 - L.mean() and (1 - L).max() < 0.2  # several %
    raw, _ = _stack(tree, cat, smearing="none")
    assert raw.options["smearing_corrected"] == []
    assert raw.flux_jy == pytest.approx(L.mean(), abs=3e-3)  # weighting none: mean of L_k
    assert raw.flux_jy < 0.95
    fixed, msgs = _stack(tree, cat, smearing="auto")
    assert fixed.options["smearing"] == "auto"
    assert fixed.options["smearing_corrected"] == ["bandwidth", "time"]
    assert fixed.flux_jy == pytest.approx(1.0, rel=5e-3)
    np.testing.assert_allclose(fixed.positions["smearing_loss"][:, 0], 1 - L, atol=2e-3)
    assert any("smearing='none'" in m for m in msgs)  # some position loses > 10 %
    forced, _ = _stack(tree, cat, smearing="correct")
    assert forced.flux_jy == pytest.approx(fixed.flux_jy, rel=1e-12)
    # the same field simulated without smearing: auto leaves it alone
    tree0, cat0 = wide[False]
    auto0, msgs0 = _stack(tree0, cat0, smearing="auto")
    none0, _ = _stack(tree0, cat0, smearing="none")
    assert auto0.options["smearing_corrected"] == []
    assert auto0.flux_jy == none0.flux_jy
    assert auto0.flux_jy == pytest.approx(1.0, rel=5e-3)
    assert np.all(auto0.positions["smearing_loss"] == 0)
    assert not any("--smearing" in m for m in msgs0)
    # forcing the correction on unsmeared data over-corrects by about the loss
    over, _ = _stack(tree0, cat0, smearing="correct")
    assert over.flux_jy > 1.03


def test_loss_subsample_against_all_rows(wide):
    """The subsampled loss against all rows and against plain numpy over all visibilities."""
    tree, cat = wide[True]
    (ds,) = (tree[k].to_dataset() for k in tree.children)
    ra0, dec0 = ds.attrs["phase_center"]
    l, m, nm1 = _lmn(cat["ra"], cat["dec"], ra0, dec0)
    pm = np.array([True, True])
    full, full_ref = usm.loss_factors(ds, l, m, nm1, bandwidth=True, time=True, pol_mask=pm,
                                      max_rows=10**9)
    np.testing.assert_allclose(full.mean(axis=1), _plain_loss(ds, cat), atol=1e-12)
    for rows, tol in ((2000, 5e-3), (8000, 2e-3)):
        sub, _ = usm.loss_factors(ds, l, m, nm1, bandwidth=True, time=True, pol_mask=pm,
                                  max_rows=rows)
        assert np.abs(sub - full).max() < tol, rows
    # flagged rows carry no weight: flag everything but one baseline, then L is that row's
    flag = ds["FLAG"].values.copy()
    flag[:, 1:] = True
    one = ds.assign(FLAG=(ds["FLAG"].dims, flag))
    got, _ = usm.loss_factors(one, l, m, nm1, bandwidth=True, time=True, pol_mask=pm,
                              max_rows=10**9)
    sub = one.isel(baseline_id=[0])
    np.testing.assert_allclose(got.mean(axis=1), _plain_loss(sub, cat), atol=1e-12)


def test_sample_rows_spread_over_track_and_baselines():
    t, b = usm.sample_rows(1000, 351, 20_000)
    assert t.size == 20_000 and t.min() == 0 and t.max() == 999
    assert np.unique(b).size == 351  # every baseline
    assert np.ptp(np.bincount(t)) <= 1  # evenly over the track
    t, b = usm.sample_rows(3, 4, 20_000)
    assert t.size == 12  # all rows when fewer


def test_auto_treats_real_and_old_simulated_data_right():
    from conftest import make_partition

    real = make_partition()
    real.attrs.pop("smearing")      # make_partition says "not smeared"; real data say nothing
    assert usm.data_effects(real, "auto") == (True, True)  # no attribute: real data
    old_sim = real.assign_attrs(source="xstack simulate")
    assert usm.data_effects(old_sim, "auto") == (False, False)
    sim_bw = real.assign_attrs(source="xstack simulate",
                               smearing={"bandwidth": True, "time": False})
    assert usm.data_effects(sim_bw, "auto") == (True, False)
    assert usm.data_effects(old_sim, "correct") == (True, True)
    assert usm.data_effects(real, "none") == (False, False)
    with pytest.raises(XstackError, match="smearing"):
        usm.check_mode("yes")


def test_uvstack_rejects_bad_smearing_option(wide):
    tree, cat = wide[False]
    with pytest.raises(XstackError, match="unknown smearing 'bogus'"):
        stack_uv(tree, cat, smearing="bogus")


def test_cli_smearing_option(tmp_path, capsys):
    """--smearing reaches uvstack (JSON options) and bad values are refused by argparse."""
    import json

    from xstack.cli import main
    from xstack.sim.simulate import simulate

    sim = simulate(_bf_scene(1, 1, True, True), tmp_path / "bf.zarr")
    catalog = tmp_path / "cat.ecsv"
    sim.catalogs["points"].write(catalog, format="ascii.ecsv")
    for mode, corrected in (("none", []), ("auto", ["bandwidth", "time"])):
        rc = main(["uvstack", str(sim.store), str(catalog), str(tmp_path / f"{mode}.zarr"),
                   "--smearing", mode, "--json", "--no-progress", "--primary-beam", "none"])
        assert rc == 0
        doc = json.loads(capsys.readouterr().out)
        assert doc["options"]["smearing"] == mode
        assert doc["options"]["smearing_corrected"] == corrected
    with pytest.raises(SystemExit):
        main(["uvstack", str(sim.store), str(catalog), str(tmp_path / "o2.zarr"), "--smearing",
              "maybe"])


def test_real_ms_records_integration_time(tmp_path):
    """A converted real MS carries its INTERVAL as integration_time (read with casacore)
    and counts as smeared under auto."""
    from casacore.tables import table

    from xstack.io.convert import convert_ms
    from xstack.schema import iter_partitions, open_store
    from xstack.testing import require_real_ms

    ms = require_real_ms("evla", tmp_path / "src")
    with table(str(ms), ack=False) as t:
        interval = float(np.median(t.getcol("INTERVAL")))
    store = convert_ms(ms, tmp_path / "evla.zarr")
    for _name, ds in iter_partitions(open_store(store)):
        assert ds["time"].attrs["integration_time"] == pytest.approx(interval)
        assert usm.data_effects(ds, "auto") == (True, True)
        l, m, nm1 = _lmn([np.degrees(ds.attrs["phase_center"][0]) + 0.1],
                         [np.degrees(ds.attrs["phase_center"][1])],
                         *ds.attrs["phase_center"])
        pm = np.array([str(p) in ("RR", "LL") for p in ds["polarization"].values])
        L, ref = usm.loss_factors(ds, l, m, nm1, bandwidth=True, time=True, pol_mask=pm)
        assert np.all((L > 0) & (L <= 1)) and 0 < ref[0] <= 1
