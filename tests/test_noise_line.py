"""Noise of line stacks (xstack.noise.line): random positions and redshifts, Monte Carlo
injection of lines, bootstrap -- against the stack's own per-bin errors, brute force over
independent noise draws made here, and a Gaussian line's analytic bin averages."""

from __future__ import annotations

import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, antenna_layout, earth_rotation_uvw
from astropy.table import Table
from scipy.special import erf

from xstack.errors import OptionError
from xstack.schema import new_partition
from xstack.spectral import SPEED_OF_LIGHT_KMS

HI = 1_420_405_751.768
ITRF_VLA = np.array([-1601185.4, -5041977.5, 3554875.9])
FREQ0, DFREQ, NCHAN = 1.300e9, 100e3, 48            # 1.3000 - 1.3048 GHz, 23 km/s channels
VRANGE, VRES = (-200.0, 200.0), 40.0                 # 10 bins
STACK = dict(line_frequency="HI", velocity_resolution=VRES, velocity_range=VRANGE,
             frame="lsrk", weighting="none", primary_beam="auto")


def _partition(seed: int, *, frame: str = "LSRK", n_time: int = 6, n_ant: int = 7):
    """Noise only, with known weights: Re and Im of each visibility N(0, 1/w), w the WEIGHT
    (random per visibility, so the weights matter)."""
    rng = np.random.default_rng(1000)  # same array and weights for every noise draw
    enu = antenna_layout(n_ant, 1500.0, rng)
    uvw, a1, a2 = earth_rotation_uvw(enu, n_time, VLA_CENTER[1], hours=4.0)
    freq = FREQ0 + DFREQ * np.arange(NCHAN)
    shape = uvw.shape[:2] + (NCHAN, 2)
    weight = rng.uniform(0.5, 2.0, size=shape)
    noise = np.random.default_rng(seed)
    vis = (noise.normal(size=shape) + 1j * noise.normal(size=shape)) / np.sqrt(weight)
    ds = new_partition(
        visibility=vis, weight=weight.astype(np.float32), flag=np.zeros(shape, bool), uvw=uvw,
        time=5.0e9 + 1200.0 * np.arange(n_time), antenna1=a1, antenna2=a2,
        antenna_names=[f"ea{i:02d}" for i in range(n_ant)], antenna_positions=enu + ITRF_VLA,
        dish_diameters=np.full(n_ant, 25.0), frequency=freq,
        channel_width=np.full(NCHAN, DFREQ), polarization=["RR", "LL"],
        phase_center=VLA_CENTER, telescope_name="VLA", integration_time=1200.0, field_id=0,
        field_name="field0")
    ds["frequency"].attrs["observer"] = frame
    return ds


def _catalog(n: int = 12, seed: int = 3) -> Table:
    """Targets within 6' of the centre, lines well inside the band (+-200 km/s fits)."""
    rng = np.random.default_rng(seed)
    ra0, dec0 = np.degrees(VLA_CENTER)
    t = Table()
    t["ra"] = ra0 + rng.uniform(-0.1, 0.1, n) / np.cos(np.radians(dec0))
    t["dec"] = dec0 + rng.uniform(-0.1, 0.1, n)
    nu_c = rng.uniform(FREQ0 + 1.3e6, FREQ0 + 3.5e6, n)
    t["z"] = HI / nu_c - 1.0
    return t


@pytest.fixture(scope="module")
def noise_data():
    return _partition(seed=1)


@pytest.fixture(scope="module")
def catalog():
    return _catalog()


@pytest.fixture(scope="module")
def brute_force(catalog):
    """The line stack at the targets over independent noise draws (this test's own)."""
    from xstack.uvstack.line import stack_lines

    spectra = [stack_lines(_partition(seed=100 + i), catalog, **STACK).flux_jy
               for i in range(30)]
    return np.std(spectra, axis=0, ddof=1)


def test_random_noise_matches_stack_error_and_brute_force(noise_data, catalog, brute_force):
    from xstack.noise.line import estimate_line_noise
    from xstack.uvstack.line import stack_lines

    R = 30
    res = estimate_line_noise(noise_data, catalog, method="random", realizations=R, seed=2,
                              **STACK)
    analytic = stack_lines(noise_data, catalog, **STACK).flux_err_jy
    assert res.values.shape == (R, 10) and res.noise_jy.shape == (10,)
    np.testing.assert_allclose(res.target_flux_err_jy, analytic, rtol=1e-12)
    assert np.all(np.isfinite(res.noise_jy))
    # per bin: a std of R = 30 draws is within ~3 x 13 % of the truth
    for other in (analytic, brute_force):
        assert np.all(np.abs(res.noise_jy / other - 1) < 0.45), res.noise_jy / other
    # pooled over the 10 bins (about independent): within 3 x 4.2 %
    pooled = np.sqrt(np.mean(res.noise_jy**2) / np.mean(analytic**2))
    assert abs(pooled - 1) < 0.13, pooled
    pooled_bf = np.sqrt(np.mean(brute_force**2) / np.mean(analytic**2))
    assert abs(pooled_bf - 1) < 0.13, pooled_bf
    # noise data: no bias beyond the sampling error of the mean
    assert np.all(np.abs(res.bias_jy) < 4 * res.noise_jy / np.sqrt(R))
    # random targets are in the field, away from the targets, with the targets' redshifts
    assert res.positions_deg.shape == (R, len(catalog), 2)
    assert res.extra["min_separation_arcsec"] > 0
    for r in range(3):
        assert sorted(res.redshift_index[r]) == list(range(len(catalog)))
    assert res.covariance_jy2.shape == (10, 10)
    np.testing.assert_allclose(np.sqrt(np.diag(res.covariance_jy2)), res.noise_jy, rtol=1e-12)
    d = res.to_dict()
    for key in ("velocity_kms", "noise_jy", "bias_jy", "realizations"):
        assert key in d
    assert len(d["noise_jy"]) == 10 and d["realizations"] == R


def _expected_stack(flux, fwhm, catalog, edges):
    """The stack of noiseless Gaussian lines of the catalog's redshifts (Jy per bin), plain
    numpy: per target the channels' averages of the line weighted by their overlap with
    each bin (equal weights per channel), then the mean over the targets."""
    sigma = fwhm / (2 * np.sqrt(2 * np.log(2)))
    nu = FREQ0 + DFREQ * np.arange(NCHAN)
    out = []
    for z in np.asarray(catalog["z"], dtype=float):
        nu_c = HI / (1 + z)
        v_lo = SPEED_OF_LIGHT_KMS * (1 - (nu + DFREQ / 2) / nu_c)
        v_hi = SPEED_OF_LIGHT_KMS * (1 - (nu - DFREQ / 2) / nu_c)
        cdf = 0.5 * (erf(v_hi / (np.sqrt(2) * sigma)) - erf(v_lo / (np.sqrt(2) * sigma)))
        s = flux * cdf / (v_hi - v_lo)
        o = np.clip(np.minimum(v_hi[:, None], edges[None, 1:])
                    - np.maximum(v_lo[:, None], edges[None, :-1]), 0, None)
        out.append((o * s[:, None]).sum(axis=0) / o.sum(axis=0))
    return np.mean(out, axis=0)


@pytest.mark.parametrize("frame", ["LSRK", "TOPO"])
def test_mc_recovers_injected_lines_without_bias(noise_data, catalog, frame):
    from xstack.noise.line import estimate_line_noise

    R, F, FWHM = 12, 20.0, 120.0
    data = noise_data if frame == "LSRK" else _partition(seed=1, frame="TOPO")
    res = estimate_line_noise(data, catalog, method="mc", realizations=R, seed=5,
                              line_flux_jy_kms=F, line_fwhm_kms=FWHM, **STACK)
    truth = _expected_stack(F, FWHM, catalog, res.velocity_edges_kms)
    # the stack of the injected lines alone (no noise) is the lines' expected stack up to
    # the other injected lines' sidelobes, which average out over random placements: the
    # injection (channel averages, beam, Doppler track) checked against plain numpy
    inj_err = res.injected.std(axis=0, ddof=1) / np.sqrt(R)
    assert np.all(np.abs(res.injected.mean(axis=0) - truth) < 4 * inj_err + 0.005 * truth.max())
    assert np.all(np.abs(res.injected - truth) < 0.1 * truth.max())
    # recovered = injected + noise: no bias within the sampling error of the mean
    err = res.noise_jy / np.sqrt(R)
    assert np.all(np.abs(res.bias_jy) < 4 * err), res.bias_jy / err
    assert np.all(np.abs(res.values.mean(axis=0) - truth)
                  < 4 * np.hypot(err, inj_err) + 0.005 * truth.max())
    # the line is seen: the peak bins are many sigma above the noise
    assert truth.max() / res.noise_jy.max() > 5
    assert res.extra["passes"] == 1 + 2 * R


def test_mc_line_parameters_from_catalog_columns(noise_data, catalog):
    from xstack.noise.line import estimate_line_noise

    cat = Table(catalog, copy=True)
    cat["line_flux_jy_kms"] = np.full(len(cat), 1.0)
    cat["line_fwhm_kms"] = np.full(len(cat), 100.0)
    a = estimate_line_noise(noise_data, cat, method="mc", realizations=2, seed=1, **STACK)
    b = estimate_line_noise(noise_data, catalog, method="mc", realizations=2, seed=1,
                            line_flux_jy_kms=1.0, line_fwhm_kms=100.0, **STACK)
    np.testing.assert_allclose(a.values, b.values, rtol=1e-12, atol=1e-15)


def test_bootstrap_scatter_matches_analytic_error(noise_data):
    from xstack.noise.line import estimate_line_noise

    cat = _catalog(n=24, seed=7)
    R = 40
    res = estimate_line_noise(noise_data, cat, method="bootstrap", realizations=R, seed=4,
                              **STACK)
    ratio = res.noise_jy / res.target_flux_err_jy
    # bootstrap of N targets: sqrt((N-1)/N) x the sample scatter / sqrt(N); pooled over the
    # bins (the N targets' own scatter varies by ~1/sqrt(2N) = 14 % per bin)
    pooled = np.sqrt(np.mean(ratio**2))
    assert abs(pooled - 1) < 0.2, ratio
    assert np.all((ratio > 0.4) & (ratio < 1.7)), ratio
    assert np.all(np.abs(res.bias_jy) < 4 * res.noise_jy / np.sqrt(R))
    assert res.redshift_index.shape == (R, len(cat))


@pytest.mark.parametrize("kw, name", [
    (dict(method="analytic"), "method"),
    (dict(realizations=1), "realizations"),
    (dict(redshifts="shuffle"), "redshifts"),
    (dict(method="mc"), "line_flux_jy_kms"),
    (dict(method="mc", line_flux_jy_kms=1.0, line_fwhm_kms=-5.0), "line_fwhm_kms"),
    (dict(frame="topo"), "frame"),
])
def test_bad_input_one_line_errors(noise_data, catalog, kw, name):
    from xstack.noise.line import estimate_line_noise

    args = dict(STACK, realizations=2) | kw
    with pytest.raises(OptionError) as info:
        estimate_line_noise(noise_data, catalog, **args)
    assert info.value.option == name
    assert "\n" not in str(info.value)


def test_velocity_of_bins_is_the_stack_grid(noise_data, catalog):
    from xstack.noise.line import estimate_line_noise

    res = estimate_line_noise(noise_data, catalog, method="random", realizations=2, **STACK)
    np.testing.assert_allclose(res.velocity_edges_kms, np.arange(-200, 201, 40.0))
    assert SPEED_OF_LIGHT_KMS > 0 and res.table()["noise_jy"].unit == "Jy"


def test_cli_line_noise(tmp_path, noise_data, catalog, capsys):
    import json

    from xstack.cli import main
    from xstack.noise.line import estimate_line_noise
    from xstack.schema import write_store

    store = write_store({"spw0_field0": noise_data}, tmp_path / "d.zarr")
    cat = tmp_path / "cat.ecsv"
    catalog.write(cat, format="ascii.ecsv")
    png, table = tmp_path / "noise.png", tmp_path / "noise.ecsv"
    status = main(["noise", str(store), str(cat), "--line-frequency", "HI", "--method",
                   "random", "--realizations", "4", "--velocity-resolution", "40km/s",
                   "--velocity-range=-200,200km/s", "--weighting", "none", "--png", str(png),
                   "--table", str(table), "--json"])
    assert status == 0
    out = json.loads(capsys.readouterr().out)
    ref = estimate_line_noise(noise_data, catalog, method="random", realizations=4, seed=0,
                              **STACK)
    np.testing.assert_allclose(out["velocity_kms"], ref.velocity_kms)
    np.testing.assert_allclose(out["noise_jy"], ref.noise_jy, rtol=1e-6)
    np.testing.assert_allclose(out["bias_jy"], ref.bias_jy, rtol=1e-6, atol=1e-12)
    assert out["realizations"] == 4
    assert png.read_bytes()[:4] == b"\x89PNG" and Table.read(table).colnames[0] == "velocity_kms"
    # library parameter names come back as the command line's flags, on one line
    assert main(["noise", str(store), str(cat), "--line-frequency", "HI", "--method", "mc",
                 "--realizations", "2"]) != 0
    err = capsys.readouterr().err
    assert "--line-flux" in err and len(err.strip().splitlines()) == 1
