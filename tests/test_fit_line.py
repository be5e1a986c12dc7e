"""The line fit (:func:`xstack.fit.line.fit_line`) and the line integral
(:func:`xstack.fit.line.integrate_line`) against truth made here: Gaussian lines averaged over
each bin analytically (erf, written out in this file), and noise that is correlated between
neighbouring bins exactly as a stack makes it — white noise in channels narrower than the
bins, each bin the overlap-weighted mean of the channels it touches — so the covariance is
known in closed form (channels wider than the bins: neighbouring bins
share them). Brute force over 500 noise realisations: the fitted centre, FWHM and
integral are unbiased within their sampling error, the reported errors match the scatter of
the realisations, and the integral's error needs the covariance (the variances alone are
measurably too small).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import erf

from xstack.errors import OptionError
from xstack.fit.line import LineFit, fit_line, integrate_line

BIN = 20.0  # km/s
EDGES = np.arange(-400.0, 400.0 + BIN / 2, BIN)
CENTRES = 0.5 * (EDGES[1:] + EDGES[:-1])
CHANNEL = 27.0  # km/s: wider than a bin, so neighbouring bins share channels
TRUE = {"peak": 2.0e-3, "centre": 37.0, "fwhm": 180.0}  # Jy, km/s, km/s
SIGMA_CHANNEL = 1.5e-4  # Jy, noise of one channel: the integral at S/N ~ 20
N_REAL = 500
WINDOW = (-200.0, 280.0)  # on bin edges: its true integral is the Gaussian's, analytically


def _bin_average(peak, centre, fwhm, edges):
    """The mean of a Gaussian over each bin: peak sigma sqrt(pi/2) (erf(a) - erf(b)) / width."""
    sigma = fwhm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    a = (edges[1:] - centre) / (math.sqrt(2.0) * sigma)
    b = (edges[:-1] - centre) / (math.sqrt(2.0) * sigma)
    return peak * sigma * math.sqrt(math.pi / 2.0) * (erf(a) - erf(b)) / np.diff(edges)


def _gaussian_integral(peak, centre, fwhm, window):
    sigma = fwhm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    lo, hi = ((w - centre) / (math.sqrt(2.0) * sigma) for w in window)
    return peak * sigma * math.sqrt(2.0 * math.pi) / 2.0 * (erf(hi) - erf(lo))


def _channel_to_bins():
    """M with bins = M @ channels: each bin the overlap-weighted mean of its channels."""
    ch_edges = np.arange(EDGES[0] - 11.0, EDGES[-1] + CHANNEL, CHANNEL)
    lo = np.maximum(ch_edges[None, :-1], EDGES[:-1, None])
    hi = np.minimum(ch_edges[None, 1:], EDGES[1:, None])
    overlap = np.clip(hi - lo, 0.0, None)
    return overlap / overlap.sum(axis=1, keepdims=True)


@pytest.fixture(scope="module")
def realisations():
    m = _channel_to_bins()
    cov = SIGMA_CHANNEL**2 * m @ m.T  # the bins' covariance, exactly
    truth = _bin_average(TRUE["peak"], TRUE["centre"], TRUE["fwhm"], EDGES)
    rng = np.random.default_rng(15)
    noise = rng.normal(0.0, SIGMA_CHANNEL, (N_REAL, m.shape[1])) @ m.T
    fits = [fit_line(CENTRES, truth + n, cov, velocity_edges_kms=EDGES, window_kms=WINDOW)
            for n in noise]
    return {"cov": cov, "truth": truth, "noise": noise, "fits": fits}


def test_neighbouring_bins_are_correlated(realisations):
    cov = realisations["cov"]
    rho = np.diag(cov, 1) / np.sqrt(np.diag(cov)[1:] * np.diag(cov)[:-1])
    assert rho.mean() > 0.3 and (rho > 0.1).mean() > 0.8  # the premise of the tests below


def test_fit_is_unbiased_and_its_errors_match_the_scatter(realisations):
    fits = realisations["fits"]
    assert all(f.converged for f in fits), [f.message for f in fits if not f.converged][:3]
    n = len(fits)
    for name, attr, err in (("centre", "centre_kms", "centre_err_kms"),
                            ("fwhm", "fwhm_kms", "fwhm_err_kms"),
                            ("peak", "peak_jy", "peak_err_jy")):
        values = np.array([getattr(f, attr) for f in fits])
        errors = np.array([getattr(f, err) for f in fits])
        scatter = values.std(ddof=1)
        assert abs(values.mean() - TRUE[name]) < 4.0 * scatter / math.sqrt(n), (
            name, values.mean(), TRUE[name], scatter)
        assert np.median(errors) == pytest.approx(scatter, rel=0.15), name


def test_integral_is_unbiased_and_its_error_uses_the_covariance(realisations):
    fits = realisations["fits"]
    n = len(fits)
    truth = _gaussian_integral(TRUE["peak"], TRUE["centre"], TRUE["fwhm"], WINDOW)
    values = np.array([f.integrated_flux_jy_kms for f in fits])
    errors = np.array([f.integrated_flux_err_jy_kms for f in fits])
    scatter = values.std(ddof=1)
    assert abs(values.mean() - truth) < 4.0 * scatter / math.sqrt(n)
    assert all(f.window_kms == WINDOW for f in fits)
    # linear in the data: the same error for every realisation, equal to the scatter
    assert np.ptp(errors) < 1e-12 * errors[0]
    assert errors[0] == pytest.approx(scatter, rel=0.15)
    # without the covariance (the bins' variances alone) the error is too small: by the
    # factor the closed-form covariance predicts, and beyond the sampling error
    cov = realisations["cov"]
    inside = (EDGES[:-1] >= WINDOW[0]) & (EDGES[1:] <= WINDOW[1])
    a = np.where(inside, BIN, 0.0)
    predicted = math.sqrt((a**2 * np.diag(cov)).sum() / (a @ cov @ a))
    _, diag_only = integrate_line(EDGES, realisations["truth"], np.diag(cov), WINDOW)
    assert diag_only / errors[0] == pytest.approx(predicted, rel=1e-9)
    assert predicted < 0.8  # here: 0.754
    assert diag_only / scatter < 0.85  # too small, beyond the 15 % tolerance above
    assert diag_only / scatter == pytest.approx(predicted, rel=0.1)


def test_default_window_is_the_fitted_centre_plus_minus_fwhm(realisations):
    truth = realisations["truth"]
    fit = fit_line(CENTRES, truth, realisations["cov"], velocity_edges_kms=EDGES)
    assert fit.converged
    # noiseless: the exact parameters back
    assert fit.centre_kms == pytest.approx(TRUE["centre"], abs=1e-6)
    assert fit.fwhm_kms == pytest.approx(TRUE["fwhm"], rel=1e-8)
    assert fit.peak_jy == pytest.approx(TRUE["peak"], rel=1e-8)
    assert fit.window_kms == pytest.approx((TRUE["centre"] - TRUE["fwhm"],
                                            TRUE["centre"] + TRUE["fwhm"]))
    # the window integral over centre +- FWHM holds erf(sqrt(4 ln 2)) = 98.1 % of the line
    total = TRUE["peak"] * TRUE["fwhm"] / (2 * math.sqrt(2 * math.log(2))) * math.sqrt(2 * math.pi)
    assert fit.integrated_flux_jy_kms / total == pytest.approx(
        erf(2 * math.sqrt(math.log(2))), rel=2e-3)


def test_integrate_line_counts_partial_bins_by_overlap():
    edges = np.array([0.0, 10.0, 20.0, 30.0])
    flux = np.array([1.0, 2.0, 4.0])
    cov = np.diag([0.01, 0.04, 0.09])
    value, err = integrate_line(edges, flux, cov, (5.0, 22.0))
    assert value == pytest.approx(5 * 1.0 + 10 * 2.0 + 2 * 4.0)
    assert err == pytest.approx(math.sqrt(25 * 0.01 + 100 * 0.04 + 4 * 0.09))
    # covariance of neighbours enters twice
    cov2 = cov.copy()
    cov2[0, 1] = cov2[1, 0] = 0.005
    _, err2 = integrate_line(edges, flux, cov2, (5.0, 22.0))
    assert err2**2 == pytest.approx(err**2 + 2 * 5 * 10 * 0.005)
    # a bin without data inside the window: no integral; outside: no harm
    flux_nan = np.array([np.nan, 2.0, 4.0])
    assert all(math.isnan(x) for x in integrate_line(edges, flux_nan, cov, (5.0, 22.0)))
    assert integrate_line(edges, flux_nan, cov, (10.0, 30.0))[0] == pytest.approx(60.0)
    with pytest.raises(OptionError):
        integrate_line(edges, flux, cov, (22.0, 5.0))


def test_bins_without_data_are_left_out_of_the_fit():
    truth = _bin_average(*TRUE.values(), EDGES)
    flux = truth.copy()
    flux[:12] = np.nan  # no target covers the low-velocity end
    cov = np.diag(np.full(flux.size, (1e-5) ** 2))
    fit = fit_line(CENTRES, flux, cov, velocity_edges_kms=EDGES)
    assert fit.converged and fit.n_bins == flux.size - 12
    assert fit.fwhm_kms == pytest.approx(TRUE["fwhm"], rel=1e-6)


def test_noise_alone_never_raises():
    """Pure noise: either no line (converged False, NaNs, a reason) or a fit — never an
    exception, and a failed fit still integrates a window it was given."""
    rng = np.random.default_rng(3)
    cov = np.diag(np.full(CENTRES.size, 1e-6))
    failed = 0
    for _ in range(15):
        fit = fit_line(CENTRES, rng.normal(0, 1e-3, CENTRES.size), cov,
                       velocity_edges_kms=EDGES, window_kms=WINDOW)
        assert isinstance(fit, LineFit)
        assert math.isfinite(fit.integrated_flux_jy_kms)
        if not fit.converged:
            failed += 1
            assert fit.message and math.isnan(fit.centre_kms) and math.isnan(fit.fwhm_kms)
            assert fit.to_dict()["centre_kms"] is None
    assert failed > 0  # noise spikes one bin wide are refused as lines
    few = fit_line(CENTRES[:3], np.ones(3), np.ones(3))
    assert not few.converged and "at least 4" in few.message
    flat = fit_line(CENTRES, np.zeros(CENTRES.size), cov)
    assert not flat.converged and flat.message


def test_bad_input_is_an_option_error():
    cov = np.eye(CENTRES.size)
    with pytest.raises(OptionError, match="model"):
        fit_line(CENTRES, np.zeros(CENTRES.size), cov, model="lorentzian")
    with pytest.raises(OptionError, match="flux_cov_jy2"):
        fit_line(CENTRES, np.zeros(CENTRES.size), np.eye(3))
    with pytest.raises(OptionError, match="velocity_edges_kms"):
        fit_line(CENTRES, np.zeros(CENTRES.size), cov, velocity_edges_kms=EDGES[::-1])


def test_bins_narrower_than_channels_singular_covariance():
    """Three 10 km/s bins per 30 km/s channel: the bins of one channel are the same number and
    the covariance has the rank of the channels. The fit uses what it constrains — the
    channels' averages — and gets the line back exactly from noiseless data."""
    edges = np.arange(-300.0, 300.1, 10.0)
    channels = np.arange(-300.0, 300.1, 30.0)
    lo = np.maximum(channels[None, :-1], edges[:-1, None])
    hi = np.minimum(channels[None, 1:], edges[1:, None])
    m = np.clip(hi - lo, 0, None)
    m /= m.sum(axis=1, keepdims=True)
    cov = 1e-8 * m @ m.T
    flux = m @ _bin_average(-2e-3, 20.0, 120.0, channels)  # an absorption line
    fit = fit_line(0.5 * (edges[1:] + edges[:-1]), flux, cov, velocity_edges_kms=edges)
    assert fit.converged, fit.message
    assert fit.dof == channels.size - 1 - 3
    assert fit.values == pytest.approx([-2e-3, 20.0, 120.0], rel=1e-6)
