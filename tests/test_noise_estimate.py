"""Noise and bias estimates against the true scatter of noise-only simulations."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _fit_helpers import C, noise_field, point_sources_vis, stack_flux

from xstack.beams import standard_beam
from xstack.coords import angular_separation
from xstack.errors import XstackError
from xstack.noise.estimate import estimate_noise
from xstack.noise.positions import random_positions

CENTER = (1.0, -0.5236)
BEAM = standard_beam("VLA", 25.0)
FIELD = dict(n_ant=20, extent_m=20e3)


def _targets(n=60, seed=0, radius_arcmin=10.0, sep_arcsec=60.0):
    ra, dec = random_positions(n, 1, np.array([CENTER]), np.array([np.radians(radius_arcmin / 60)]),
                               avoid_ra=np.zeros(0), avoid_dec=np.zeros(0),
                               min_separation=np.radians(sep_arcsec / 3600),
                               rng=np.random.default_rng(seed))
    return ra[0], dec[0]


def _true_scatter(ra, dec, uvw, freq):
    """Exact std of the stacked flux over independent noise (sigma = 1, W = 1, 2 hands)."""
    A = BEAM(angular_separation(ra, dec, *CENTER)[:, None], freq[None, :])
    from _fit_helpers import lmn

    l, m, n1 = lmn(ra, dec, *CENTER)
    P = np.zeros(uvw.shape[:2] + (freq.size,), complex)
    for k in range(ra.size):
        d = uvw[..., 0] * l[k] + uvw[..., 1] * m[k] + uvw[..., 2] * n1[k]
        P += np.exp(-2j * np.pi * d[..., None] * freq / C) / A[k]
    P /= ra.size
    return float(np.sqrt(2 * np.sum(np.abs(P) ** 2)) / (2 * P.size)), A


def test_estimates_match_true_scatter():
    ra, dec = _targets()
    pos = (np.degrees(ra), np.degrees(dec))
    ds0, uvw, freq = noise_field(0, **FIELD)
    truth, A = _true_scatter(ra, dec, uvw, freq)
    # the exact formula agrees with the scatter over independent simulations
    sims = [stack_flux(ds.VISIBILITY.values, ds.WEIGHT.values, uvw, freq, ra, dec, CENTER, 1 / A)
            for ds in (noise_field(s, **FIELD)[0] for s in range(100, 160))]
    assert np.std(sims, ddof=1) == pytest.approx(truth, rel=0.25)
    for seed in (1, 2):
        ds, _, _ = noise_field(seed, **FIELD)
        for method in ("mc", "random", "bootstrap"):
            res = estimate_noise(ds, pos, method=method, realizations=200, seed=seed,
                                 weighting="none", flux=1e-3 if method == "mc" else None)
            assert res.realizations == 200 and res.values.size == 200
            assert res.noise_jy == pytest.approx(truth, rel=0.15), (method, seed)
            # the targets' own stacked flux is the reference implementation's
            ref = stack_flux(ds.VISIBILITY.values, ds.WEIGHT.values, uvw, freq, ra, dec, CENTER,
                             1 / A)
            assert res.target_flux_jy == pytest.approx(ref, rel=1e-9, abs=1e-12)
        ana = estimate_noise(ds, pos, method="analytic", weighting="none")
        assert ana.noise_jy == pytest.approx(truth, rel=0.15)
        assert ana.realizations == 0 and ana.bias_jy is None


def test_mc_injection_equals_injecting_into_the_data():
    """Stacking is linear: the analytic injection equals writing the fakes into the data."""
    ra, dec = _targets(n=8)
    ds, uvw, freq = noise_field(3, n_ant=8, n_time=6, extent_m=20e3)
    res = estimate_noise(ds, (np.degrees(ra), np.degrees(dec)), method="mc", realizations=3,
                         flux=np.linspace(1, 2, 8), seed=5, weighting="none")
    vis = ds.VISIBILITY.values
    for r in range(3):
        fra, fdec = np.radians(res.positions_deg[r]).T
        A = BEAM(angular_separation(fra, fdec, *CENTER)[:, None], freq[None, :])
        fake = np.zeros(vis.shape[:3], complex)
        for c in range(freq.size):
            fake[..., c] = point_sources_vis(uvw, freq[c:c + 1], fra, fdec,
                                             res.injected_flux_jy[r] * A[:, c], CENTER)[..., 0]
        ref = stack_flux(vis + fake[..., None], ds.WEIGHT.values, uvw, freq, fra, fdec, CENTER,
                         1 / A)
        assert res.values[r] == pytest.approx(ref, rel=1e-9)
        # separations are respected
        min_sep = np.radians(res.extra["min_separation_arcsec"] / 3600) * 0.999
        sep = angular_separation(fra[:, None], fdec[:, None], fra[None], fdec[None])
        assert np.all(sep[~np.eye(8, dtype=bool)] >= min_sep)
        tsep = angular_separation(fra[:, None], fdec[:, None], ra[None], dec[None])
        assert tsep.min() >= min_sep
    assert np.allclose(np.sort(res.injected_flux_jy[0]), np.linspace(1, 2, 8))
    # this data's UVW are antenna differences: the check above ran the antenna path
    assert res.extra["engine"] == "antenna" and res.extra["antenna_phase_error_rad"] < 1e-11


def test_engines_agree_and_fallback_is_recorded():
    """Antenna and per-row kernels agree (flags, NaN UVW, uv cut, profiles); inconsistent
    UVW make ``auto`` fall back per block, observably."""
    ra, dec = _targets(n=12)
    pos = (np.degrees(ra), np.degrees(dec))
    ds, _, _ = noise_field(3, n_ant=8, n_time=6, extent_m=20e3)
    ds = ds.copy(deep=True)
    rng = np.random.default_rng(2)
    ds["FLAG"].values[rng.uniform(size=ds["FLAG"].shape) < 0.1] = True
    ds["FLAG"].values[1, 4] = True
    ds["UVW"].values[1, 4] = np.nan  # a flagged row without coordinates
    ds["FLAG"].values[3] = True  # a whole integration
    # 1 cm on one baseline of one integration: inconsistent with any antenna UVW
    bad = ds.copy(deep=True)
    bad["UVW"].values[4, 27, 0] += 0.01
    ds, bad = ds.chunk({"time": 2}), bad.chunk({"time": 2})  # three blocks
    kw = dict(method="mc", realizations=6, flux=1e-3, seed=1, profile_bins=4, uvmin="300m")
    row = estimate_noise(ds, pos, engine="numba", **kw)
    ant = estimate_noise(ds, pos, **kw)
    assert row.extra["engine"] == "numba" and "antenna_phase_error_rad" not in row.extra
    assert ant.extra["engine"] == "antenna" and ant.extra["engine_blocks"] == {"antenna": 3,
                                                                               "numba": 0}
    scale = np.abs(row.values).max()
    np.testing.assert_allclose(ant.values, row.values, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(ant.injected, row.injected, rtol=1e-12)
    np.testing.assert_allclose(ant.profile["values"], row.profile["values"], rtol=1e-9,
                               atol=1e-9 * np.nanmax(np.abs(row.profile["values"])))
    rnd = estimate_noise(ds, pos, method="random", realizations=6, seed=1, engine="antenna")
    rnd_row = estimate_noise(ds, pos, method="random", realizations=6, seed=1, engine="numba")
    np.testing.assert_allclose(rnd.values, rnd_row.values, rtol=1e-9,
                               atol=1e-9 * np.abs(rnd_row.values).max())
    # that block falls back to the per-row kernel
    mixed = estimate_noise(bad, pos, **kw)
    assert mixed.extra["engine"] == "mixed"
    assert mixed.extra["engine_blocks"] == {"antenna": 2, "numba": 1}
    assert "phase error" in mixed.extra["engine_fallback"]
    np.testing.assert_allclose(mixed.values, estimate_noise(bad, pos, engine="numba", **kw).values,
                               rtol=1e-9, atol=1e-9 * scale)
    with pytest.raises(XstackError, match="engine='antenna' is not valid"):
        estimate_noise(bad, pos, engine="antenna", **kw)
    with pytest.raises(XstackError, match="unknown engine"):
        estimate_noise(ds, pos, engine="gpu", **kw)


def test_mc_finds_bias_from_bright_residual():
    """An unsubtracted extended residual (short baselines only) biases the stack; mc sees it."""
    flux = 2e-2
    res_vis_args = dict(fwhm_arcsec=240.0)
    ra, dec = _targets(n=40, seed=4)
    pos = (np.degrees(ra), np.degrees(dec))
    _, uvw, freq = noise_field(0, **FIELD)
    resid = point_sources_vis(uvw, freq, np.array([CENTER[0] + 1e-4]), np.array([CENTER[1]]),
                              np.array([200.0]), CENTER, **res_vis_args)
    clean, _, _ = noise_field(7, **FIELD)
    dirty, _, _ = noise_field(7, extra_vis=resid, **FIELD)
    r0 = estimate_noise(clean, pos, method="mc", realizations=100, flux=flux, seed=1,
                        weighting="none")
    r1 = estimate_noise(dirty, pos, method="mc", realizations=100, flux=flux, seed=1,
                        weighting="none")
    # same noise and same seed: identical positions, so the difference is the residual alone
    np.testing.assert_allclose(r1.positions_deg, r0.positions_deg)
    diff = r1.values - r0.values
    for r in range(2):
        pra, pdec = np.radians(r1.positions_deg[r]).T
        A = BEAM(angular_separation(pra, pdec, *CENTER)[:, None], freq[None, :])
        ref_r = stack_flux(resid[..., None] * np.ones(2), np.ones(resid.shape + (2,)), uvw, freq,
                           pra, pdec, CENTER, 1 / A)
        assert diff[r] == pytest.approx(ref_r, rel=1e-8)
    # truth: mean over independent random position sets of the residual alone, stacked
    ref = []
    rng = np.random.default_rng(99)
    radius = angular_separation(ra, dec, *CENTER).max() * 1.02
    sep = np.radians(r1.extra["min_separation_arcsec"] / 3600)
    for _ in range(20):
        pra, pdec = random_positions(40, 1, np.array([CENTER]), np.array([radius]), avoid_ra=ra,
                                     avoid_dec=dec, min_separation=sep, rng=rng)
        A = BEAM(angular_separation(pra[0], pdec[0], *CENTER)[:, None], freq[None, :])
        ref.append(stack_flux(resid[..., None] * np.ones(2), np.ones(resid.shape + (2,)), uvw, freq,
                              pra[0], pdec[0], CENTER, 1 / A))
    true_bias = float(np.mean(ref))
    shift = r1.bias_jy - r0.bias_jy
    tol = 4 * (np.std(diff) / np.sqrt(diff.size) + np.std(ref) / np.sqrt(len(ref)))
    assert shift == pytest.approx(true_bias, abs=tol)
    # the bias is large compared with the noise-only bias and with the noise of the stack
    assert abs(r1.bias_jy) > 3 * abs(r0.bias_jy) and abs(r1.bias_jy) > r0.noise_jy
    # the uv-profile shows where: the offset sits on the short baselines
    r2 = estimate_noise(dirty, pos, method="mc", realizations=30, flux=flux, seed=1,
                        profile_bins=8, weighting="none")
    off = np.nanmean(r2.profile["values"] - r2.profile["injected"][:, None], axis=0)
    assert abs(off[0]) > 3 * np.nanmax(np.abs(off[4:]))


def test_bad_inputs(tmp_path):
    ds, _, _ = noise_field(0, n_ant=6, n_time=4)
    ra, dec = _targets(n=5)
    pos = (np.degrees(ra), np.degrees(dec))
    with pytest.raises(XstackError, match="at least 2 realisations"):
        estimate_noise(ds, pos, method="mc", realizations=1)
    with pytest.raises(XstackError, match="unknown noise method"):
        estimate_noise(ds, pos, method="jackknife")
    with pytest.raises(XstackError, match="too dense"):
        estimate_noise(ds, pos, method="random", realizations=3, min_separation_arcsec=600)
    with pytest.raises(XstackError, match="no visibilities left"):
        estimate_noise(ds, pos, method="random", realizations=3, uvmin="1e9lambda")
    with pytest.raises(XstackError, match="inside a primary beam"):
        estimate_noise(ds, ([0.0], [10.0]), method="analytic")


def test_result_outputs(tmp_path):
    ds, _, _ = noise_field(0, n_ant=6, n_time=4)
    ra, dec = _targets(n=5)
    res = estimate_noise(ds, (np.degrees(ra), np.degrees(dec)), method="mc", realizations=5,
                         flux="1mJy")
    d = res.to_dict()
    assert {"noise_jy", "bias_jy", "realizations"} <= set(d)
    assert len(d["values_jy"]) == 5 and d["realizations"] == 5
    path = res.write_json(tmp_path / "n.json")
    assert json.loads(path.read_text())["noise_jy"] == pytest.approx(res.noise_jy)
    t = res.table()
    assert len(t) == 5 and np.allclose(t["offset_jy"], res.values - res.injected)
    np.testing.assert_allclose(res.injected, 1e-3, rtol=0.05)


@pytest.mark.parametrize("weighting", ["pb", "none"])
def test_target_flux_matches_uvstack_on_a_mosaic(weighting):
    """Same estimator as xstack.uvstack, also for two overlapping pointings."""
    stack_uv = pytest.importorskip("xstack.uvstack.stack").stack_uv
    ra, dec = _targets(n=12, radius_arcmin=12.0, sep_arcsec=30.0)
    parts = {}
    for i, dra in enumerate((0.0, np.radians(8 / 60))):
        center = (CENTER[0] + dra, CENTER[1])
        ds, uvw, freq = noise_field(10 + i, n_ant=8, n_time=6, extent_m=20e3)
        src = point_sources_vis(uvw, freq, ra, dec, 1.0, center,
                                atten=BEAM(angular_separation(ra, dec, *center), 1.4e9))
        ds["VISIBILITY"] = ds["VISIBILITY"] + src[..., None]
        ds.attrs["phase_center"] = [float(center[0]), float(center[1])]
        ds.attrs["field_id"] = i
        parts[f"spw0_field{i}"] = ds
    from astropy.table import Table

    pos = Table({"ra": np.degrees(ra), "dec": np.degrees(dec)})
    import xarray as xr

    # the noise stage evaluates equation 4 at channel centers: compare without uvstack's
    # smearing correction (these data are unsmeared channel-center visibilities)
    ref = stack_uv(xr.DataTree.from_dict(parts), pos, weighting=weighting, smearing="none")
    for method in ("analytic", "random", "bootstrap"):
        res = estimate_noise(parts, pos, method=method, realizations=4, weighting=weighting)
        assert res.target_flux_jy == pytest.approx(ref.flux_jy, rel=1e-9), method
    ana = estimate_noise(parts, pos, method="analytic", weighting=weighting)
    assert ana.noise_jy == pytest.approx(ref.flux_err_jy, rel=0.3)


def test_random_positions_avoid_bright_sources_and_stay_in_field():
    ds, _, _ = noise_field(0, n_ant=6, n_time=4, extent_m=20e3)
    ra, dec = _targets(n=10)
    bright = _targets(n=15, seed=9)
    res = estimate_noise(ds, (np.degrees(ra), np.degrees(dec)), method="random", realizations=10,
                         avoid=(np.degrees(bright[0]), np.degrees(bright[1])),
                         min_separation_arcsec=45.0, weighting="none")
    pra, pdec = np.radians(res.positions_deg[..., 0]).ravel(), np.radians(res.positions_deg[..., 1]).ravel()
    sep_b = angular_separation(pra[:, None], pdec[:, None], bright[0][None], bright[1][None])
    assert sep_b.min() >= np.radians(45 / 3600) * 0.999
    # inside the targets' footprint (their hull, grown by its margin; 10 targets: a warning)
    assert "convex hull of 10 targets" in res.extra["region"]
    margin = float(res.extra["region"].split("grown by ")[1].split(" arcsec")[0]) * np.pi / 648000
    rmax = angular_separation(ra, dec, *CENTER).max()
    assert angular_separation(pra, pdec, *CENTER).max() <= rmax + margin * 1.001
    # --region beam: the whole beam (out to the cutoff), roughly uniform in area
    res_b = estimate_noise(ds, (np.degrees(ra), np.degrees(dec)), method="random",
                           realizations=10, region="beam", weighting="none")
    bra, bdec = np.radians(res_b.positions_deg.reshape(-1, 2)).T
    r_cut = float(BEAM.radius_at(0.1, 1.45e9))
    assert angular_separation(bra, bdec, *CENTER).max() <= r_cut * (1 + 1e-9)
    frac = np.mean(angular_separation(bra, bdec, *CENTER) < r_cut / np.sqrt(2))
    assert 0.35 < frac < 0.65


def test_targets_beyond_the_first_null_never_enter_a_pointing():
    # with no cutoff, an Airy sidelobe (A ~ 0.018) must still not count as inside the beam
    ds, _, _ = noise_field(3)
    beam = standard_beam("VLA", 25.0, model="airy")
    center = tuple(float(x) for x in ds.attrs["phase_center"])
    r_null = float(beam.first_null(float(ds["frequency"].max())))
    assert float(beam(1.3 * r_null, float(ds["frequency"].max()))) > 0.01
    ra = np.full(3, center[0])
    dec = center[1] + np.array([0.3, 1.3, 1.6]) * r_null
    with_sidelobes = estimate_noise(ds, (np.degrees(ra), np.degrees(dec)), method="analytic",
                                    primary_beam="airy", pb_cutoff=0.0)
    alone = estimate_noise(ds, (np.degrees(ra[:1]), np.degrees(dec[:1])), method="analytic",
                           primary_beam="airy", pb_cutoff=0.0)
    assert with_sidelobes.noise_jy == pytest.approx(alone.noise_jy, rel=1e-12)


def test_every_method_counts_the_positions_uvstack_uses():
    """One rule for 'inside the field' (issue 11, item 8): a target outside every pointing
    is left out by bootstrap as by the other methods and by uvstack (bootstrap used to
    resample it and report it among its positions)."""
    import xarray as xr
    from astropy.table import Table

    from xstack.uvstack.stack import stack_uv

    ds, _, _ = noise_field(5)
    ra, dec = _targets(n=20, seed=2)
    far_ra, far_dec = np.append(ra, CENTER[0]), np.append(dec, CENTER[1] + np.radians(3.0))
    pos_all = (np.degrees(far_ra), np.degrees(far_dec))
    counts = {m: estimate_noise(ds, pos_all, method=m, realizations=20).n_positions
              for m in ("analytic", "random", "bootstrap")}
    with pytest.warns(UserWarning, match="lie in no pointing"):
        ref = stack_uv(xr.DataTree.from_dict({"/p": ds}),
                      Table({"ra": pos_all[0], "dec": pos_all[1]}), smearing="none")
    assert counts == {"analytic": 20, "random": 20, "bootstrap": 20} and ref.n_positions == 20
    # and the bootstrap resamples exactly the targets inside: as without the far one
    a = estimate_noise(ds, pos_all, method="bootstrap", realizations=30, seed=4)
    b = estimate_noise(ds, (np.degrees(ra), np.degrees(dec)), method="bootstrap",
                       realizations=30, seed=4)
    np.testing.assert_allclose(a.values, b.values, rtol=1e-12)
