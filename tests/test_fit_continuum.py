"""Continuum subtraction of a stacked spectrum (:func:`xstack.fit.line.subtract_continuum`).

Truth from outside the code: a generalised least-squares fit written here in plain numpy with
the polynomial's bin averages integrated numerically (not the closed form the code uses),
polynomials that must vanish exactly, the covariance against brute force over independent
noise draws, and the command line (``xstack linestack`` / ``xstack imstack``) against the
library and the injected truth.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.special import erf

from xstack.errors import OptionError
from xstack.fit.line import subtract_continuum

EDGES = np.arange(-600.0, 600.1, 20.0)  # km/s, 60 bins
CENTRES = 0.5 * (EDGES[1:] + EDGES[:-1])
N = CENTRES.size
FREE = ((-600.0, -300.0), (300.0, 600.0))
LINE_PEAK, LINE_FWHM = 2e-3, 100.0  # Jy, km/s


def _line(edges=EDGES, peak=LINE_PEAK, fwhm=LINE_FWHM):
    s = fwhm / (2 * math.sqrt(2 * math.log(2)))
    a, b = erf(edges[1:] / (math.sqrt(2) * s)), erf(edges[:-1] / (math.sqrt(2) * s))
    return peak * s * math.sqrt(math.pi / 2) * (a - b) / np.diff(edges)


def _cov(sigma=3e-4, rho=0.35):
    return sigma**2 * (np.eye(N) + rho * (np.eye(N, k=1) + np.eye(N, k=-1)))


def _numeric_bin_averages(order, edges=EDGES, samples=2001):
    """(nbin, order + 1) the average of v^k over each bin by Simpson-like dense sampling."""
    out = np.empty((edges.size - 1, order + 1))
    for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        v = np.linspace(lo, hi, samples)
        for k in range(order + 1):
            out[i, k] = np.trapezoid(v**k, v) / (hi - lo)
    return out


def _poly(coef, edges=EDGES):
    return _numeric_bin_averages(len(coef) - 1, edges) @ np.asarray(coef)


@pytest.mark.parametrize("order", [0, 1, 2])
def test_matches_plain_numpy_gls(order):
    """Coefficients, subtracted spectrum, baseline and chi2 as a plain-numpy GLS."""
    rng = np.random.default_rng(order)
    cov = _cov()
    coef = [5e-3, -4e-6, 3e-9][: order + 1]
    y = _poly(coef) + _line() + np.linalg.cholesky(cov) @ rng.normal(size=N)
    sub, sub_cov, base = subtract_continuum(EDGES, y, cov, order=order, line_free_kms=FREE)

    a = _numeric_bin_averages(order)
    free = np.zeros(N, bool)
    for lo, hi in FREE:
        free |= (EDGES[:-1] >= lo) & (EDGES[1:] <= hi)
    ci = np.linalg.inv(cov[np.ix_(free, free)])
    x = a[free]
    beta = np.linalg.solve(x.T @ ci @ x, x.T @ ci @ y[free])
    np.testing.assert_allclose(base.coefficients_jy, beta, rtol=1e-7)
    np.testing.assert_allclose(sub, y - a @ beta, rtol=0, atol=1e-12)
    np.testing.assert_allclose(base.flux_jy, a @ beta, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(base.fit_bins, free)
    r = y[free] - x @ beta
    assert base.chi2 == pytest.approx(r @ ci @ r, rel=1e-8)
    assert base.dof == free.sum() - (order + 1)
    # covariance: M C M^T with M = I - A G P
    g = np.linalg.solve(x.T @ ci @ x, x.T @ ci)
    m = np.eye(N)
    m[:, free] -= a @ g
    np.testing.assert_allclose(sub_cov, m @ cov @ m.T, rtol=1e-7, atol=1e-20)
    np.testing.assert_allclose(base.coefficient_errors,
                               np.sqrt(np.diag(np.linalg.inv(x.T @ ci @ x))), rtol=1e-7)


@pytest.mark.parametrize("order", [0, 1, 3])
def test_polynomial_of_the_order_vanishes_and_the_line_stays(order):
    """Noiseless: a continuum of the fitted order is removed exactly; the line, which is ~0 in
    the line-free bins (300 km/s is 7 sigma), is left untouched."""
    coef = [4e-3, 2e-6, -1e-9, 5e-13][: order + 1]
    line = _line()
    sub, _, base = subtract_continuum(EDGES, _poly(coef) + line, _cov(), order=order,
                                      line_free_kms=FREE)
    np.testing.assert_allclose(sub, line, rtol=0, atol=1e-10 * LINE_PEAK)
    np.testing.assert_allclose(base.coefficients_jy, coef, rtol=1e-6)
    # a lower order leaves a residual that the fit's chi2 sees (order 1 on a parabola)
    if order >= 2:
        _, _, low = subtract_continuum(EDGES, _poly(coef) + line, _cov(), order=1,
                                       line_free_kms=FREE)
        assert low.chi2 > 100 * max(base.chi2, 1e-12)


def test_covariance_against_brute_force():
    """The scatter of the subtracted spectrum over 4000 independent noise draws matches the
    returned covariance (variances within 9 %, 4 sigma of a variance from 4000 draws;
    correlations within 0.07), and the baseline's own error matches the baselines' scatter."""
    rng = np.random.default_rng(7)
    cov = _cov()
    chol = np.linalg.cholesky(cov)
    truth = _poly([3e-3, 1e-6]) + _line()
    subs, bases = [], []
    for _ in range(4000):
        s, c, b = subtract_continuum(EDGES, truth + chol @ rng.normal(size=N), cov, order=1,
                                     line_free_kms=FREE)
        subs.append(s)
        bases.append(b.flux_jy)
    subs, bases = np.array(subs), np.array(bases)
    emp = np.cov(subs.T)
    np.testing.assert_allclose(np.diag(emp), np.diag(c), rtol=0.09)
    corr_emp = emp / np.sqrt(np.outer(np.diag(emp), np.diag(emp)))
    corr = c / np.sqrt(np.outer(np.diag(c), np.diag(c)))
    assert np.max(np.abs(corr_emp - corr)) < 0.07  # 4.4 sigma of a correlation from 4000
    np.testing.assert_allclose(bases.std(axis=0, ddof=1), b.flux_err_jy, rtol=0.05)
    # unbiased: the mean subtracted spectrum is the line
    np.testing.assert_allclose(subs.mean(axis=0), _line(), atol=4 * np.sqrt(np.diag(c)).max()
                               / np.sqrt(4000))


def test_empty_bins_stay_nan_and_are_left_out():
    y = _poly([2e-3]) + _line()
    y[:3] = np.nan
    cov = _cov()
    cov[:3, :] = np.nan
    cov[:, :3] = np.nan
    sub, c, base = subtract_continuum(EDGES, y, cov, order=0, line_free_kms=FREE)
    assert np.all(np.isnan(sub[:3])) and np.all(np.isnan(c[:3, :]))
    assert not base.fit_bins[:3].any()
    np.testing.assert_allclose(sub[3:], _line()[3:], atol=1e-10 * LINE_PEAK)


def test_a_bin_only_partly_line_free_is_not_fitted():
    _, _, base = subtract_continuum(EDGES, _poly([1e-3]), _cov(), order=0,
                                    line_free_kms=((-595.0, -245.0),))
    used = np.flatnonzero(base.fit_bins)
    assert EDGES[used[0]] >= -595.0 and EDGES[used[-1] + 1] <= -245.0
    assert used.size == 16  # -580..-260: the bins at -600 and -260..-240 are only partly inside


@pytest.mark.parametrize("kw, words", [
    (dict(order=-1), "degree"),
    (dict(order=1.5), "degree"),
    (dict(line_free_kms=((10.0, -10.0),)), "low < high"),
    (dict(line_free_kms="left"), "velocity ranges"),
    (dict(line_free_kms=((-600.0, -570.0),), order=1), "needs at least 3"),
    (dict(line_window_kms=(-350.0, 350.0)), "overlaps the line window"),
])
def test_bad_input_is_an_option_error(kw, words):
    args = dict(order=0, line_free_kms=FREE)
    args.update(kw)
    with pytest.raises(OptionError, match=words):
        subtract_continuum(EDGES, _poly([1e-3]), _cov(), **args)


# --- the command line ---------------------------------------------------------------------

def _fake_result(flux, cov):
    from astropy.table import Table

    from xstack.spectral import LINES
    from xstack.uvstack.line import LineStackResult

    return LineStackResult(
        velocity_edges_kms=EDGES, velocity_kms=CENTRES, flux_jy=flux,
        flux_err_jy=np.sqrt(np.diag(cov)), flux_cov_jy2=cov, n_targets_per_bin=np.full(N, 4),
        n_positions=4, n_visibilities=1000, positions=Table({"ra": [1.0], "dec": [2.0]}),
        rest_frequency_hz=LINES["HI"], frame="lsrk", options={"weighting": "pb"}, out=None)


def test_linestack_cli_subtracts_and_reports(tmp_path, monkeypatch, capsys):
    """``--continuum-subtract 1 --line-free``: the JSON's spectrum and integral are those of the
    library's subtracted spectrum; the continuum's coefficients are reported; the ECSV carries
    the baseline so flux + baseline is the spectrum as stacked; without the option the
    integral is biased by the continuum."""
    from astropy.table import Table

    import xstack.uvstack.line as line
    from xstack.cli import main
    from xstack.fit.line import fit_line

    rng = np.random.default_rng(3)
    cov = _cov(sigma=1e-4)
    stacked = _poly([4e-3, 3e-6]) + _line() + np.linalg.cholesky(cov) @ rng.normal(size=N)
    monkeypatch.setattr(line, "stack_lines", lambda *a, **k: _fake_result(stacked, cov))
    (tmp_path / "d.zarr").mkdir()
    (tmp_path / "c.csv").write_text("ra,dec,z\n150,2,0.1\n")
    argv = ["linestack", str(tmp_path / "d.zarr"), str(tmp_path / "c.csv"),
            str(tmp_path / "o.zarr"), "--line-frequency", "HI", "--line-window=-200,200",
            "--json", "--no-png"]
    assert main([*argv, "--continuum-subtract", "1", "--line-free=-600,-300;300,600km/s"]) == 0
    got = json.loads(capsys.readouterr()[0])
    sub, sub_cov, base = subtract_continuum(EDGES, stacked, cov, order=1, line_free_kms=FREE)
    fit = fit_line(CENTRES, sub, sub_cov, velocity_edges_kms=EDGES, window_kms=(-200, 200))
    np.testing.assert_allclose(got["flux_jy"], sub, rtol=1e-12, atol=1e-15)
    assert got["integrated_flux_jy_kms"] == pytest.approx(fit.integrated_flux_jy_kms, rel=1e-9)
    assert got["integrated_flux_err_jy_kms"] == pytest.approx(fit.integrated_flux_err_jy_kms,
                                                              rel=1e-9)
    cont = got["continuum_subtracted"]
    assert cont["order"] == 1 and cont["line_free_kms"] == [[-600, -300], [300, 600]]
    np.testing.assert_allclose(cont["coefficients_jy"], base.coefficients_jy, rtol=1e-9)
    truth = LINE_PEAK * LINE_FWHM / (2 * math.sqrt(2 * math.log(2))) * math.sqrt(2 * math.pi)
    # the whole line lies in +-200 km/s to 0.3 %; the subtracted integral finds it
    assert abs(got["integrated_flux_jy_kms"] - truth) < 4 * got["integrated_flux_err_jy_kms"]
    tab = Table.read(tmp_path / "o_spectrum.ecsv")
    np.testing.assert_allclose(np.asarray(tab["flux_jy"]) + np.asarray(tab["baseline_jy"]),
                               stacked, rtol=1e-12, atol=1e-15)
    assert tab.meta["continuum_subtracted"]["order"] == 1

    # without subtraction the 4 mJy continuum adds 1.6 Jy km/s to the +-200 km/s integral
    assert main([*argv, "--overwrite"]) == 0
    plain = json.loads(capsys.readouterr()[0])
    assert plain["continuum_subtracted"] is None
    assert plain["integrated_flux_jy_kms"] - truth > 20 * plain["integrated_flux_err_jy_kms"]


@pytest.mark.parametrize("extra, words", [
    (["--continuum-subtract", "1"], "needs --line-free"),
    (["--line-free=-600,-300"], "needs --continuum-subtract"),
    (["--continuum-subtract", "-1", "--line-free=-600,-300"], "degree >= 0"),
    (["--continuum-subtract", "0", "--line-free=-600,-100", "--line-window=-200,200"],
     "overlaps --line-window"),
    (["--continuum-subtract", "2", "--line-free=-600,-560"], "needs at least 4"),
])
def test_linestack_cli_bad_continuum_options(tmp_path, monkeypatch, capsys, extra, words):
    import xstack.uvstack.line as line
    from xstack.cli import main

    cov = _cov()
    monkeypatch.setattr(line, "stack_lines", lambda *a, **k: _fake_result(_line(), cov))
    (tmp_path / "d.zarr").mkdir()
    (tmp_path / "c.csv").write_text("ra,dec,z\n150,2,0.1\n")
    rc = main(["linestack", str(tmp_path / "d.zarr"), str(tmp_path / "c.csv"),
               str(tmp_path / "o.zarr"), "--line-frequency", "HI", "--no-png", *extra])
    err = capsys.readouterr()[1].strip().splitlines()
    assert rc != 0 and len(err) == 1 and words in err[0], err
    assert not (tmp_path / "o_spectrum.ecsv").exists()


def test_imstack_cube_continuum_removed_from_spectrum_and_moment0(tmp_path, capsys):
    """A cube whose targets have a continuum (flat in frequency, a point source at each) as
    well as a line: ``imstack --line-frequency --continuum-subtract 0`` recovers the line's
    integral to 0.1 %, where without it the continuum adds its flux times the window."""
    from astropy.io import fits
    from test_imstack_line import BEAM_FWHM_PIX, TARGETS, make_cube

    from xstack.cli import main

    line_only = make_cube(tmp_path / "line.fits", TARGETS, nchan=60)
    make_cube(tmp_path / "both.fits", TARGETS, nchan=60)
    with fits.open(tmp_path / "both.fits", mode="update") as hdul:
        n = hdul[0].data.shape[-1]
        yy, xx = np.mgrid[0:n, 0:n]
        s = BEAM_FWHM_PIX / (2 * np.sqrt(2 * np.log(2)))
        cont = sum(np.exp(-((xx - t[0]) ** 2 + (yy - t[1]) ** 2) / (2 * s * s)) for t in TARGETS)
        hdul[0].data = (hdul[0].data + 0.01 * cont[None, None]).astype(np.float32)
    line_only.write(tmp_path / "cat.csv", format="ascii.csv")
    common = ["--line-frequency", "HI", "--velocity-resolution", "20km/s",
              "--velocity-range=-300,300km/s", "--line-window=-150,150km/s", "--json",
              # equal weights: sigma2 weights come from each cube's own scatter, which the
              # continuum changes in a noiseless cube
              "--weighting", "none"]
    runs = {}
    for name, cube, extra in (("line", "line.fits", []), ("both", "both.fits", []),
                              ("sub", "both.fits", ["--continuum-subtract", "0",
                                                    "--line-free=-300,-180;180,300km/s"])):
        assert main(["imstack", str(tmp_path / cube), str(tmp_path / "cat.csv"),
                     str(tmp_path / f"out_{name}.fits"), *common, *extra]) == 0
        runs[name] = json.loads(capsys.readouterr()[0])
    truth = runs["line"]["integrated_flux_jy_kms"]
    # 10 mJy over 300 km/s = 3 Jy km/s of continuum in the window without subtraction
    assert runs["both"]["integrated_flux_jy_kms"] == pytest.approx(truth + 3.0, rel=0.01)
    assert runs["sub"]["integrated_flux_jy_kms"] == pytest.approx(truth, rel=1e-3)
    assert runs["sub"]["continuum_subtracted"]["coefficients_jy"][0] == pytest.approx(0.01,
                                                                                     rel=1e-3)
