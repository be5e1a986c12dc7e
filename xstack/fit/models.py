"""Source models for fitting (pure numpy, no dask/xarray).

A circular Gaussian of integrated flux density S and full width at half maximum theta
(radians) has the visibility

    V(q) = S exp(-pi^2 theta^2 q^2 / (4 ln 2)),   q = sqrt(u^2 + v^2) in wavelengths,

i.e. the paper's equation 1 with r_k = theta / (2 sqrt(ln 2)). We parametrise the size by
``a = theta^2`` so that the unresolved limit theta -> 0 is an ordinary interior point of the
fit (the model is analytic and linear in ``a`` there) instead of a singular boundary.
"""

from __future__ import annotations

import numpy as np

#: V = S exp(-GAUSS_K * theta^2 * q^2) with q in wavelengths, theta in radians.
GAUSS_K = np.pi**2 / (4.0 * np.log(2.0))


def gaussian_vis(q2: np.ndarray, flux: float, theta2: float) -> np.ndarray:
    """Visibility of a circular Gaussian at q^2 (wavelengths^2); ``theta2`` = FWHM^2 (rad^2)."""
    return flux * np.exp(-GAUSS_K * theta2 * np.asarray(q2, dtype=np.float64))


def gaussian_image_ft(f2: np.ndarray, theta2_pix: float) -> np.ndarray:
    """Fourier transform of a unit-integral circular Gaussian of FWHM^2 ``theta2_pix``
    (pixels^2) at squared spatial frequency ``f2`` (cycles/pixel)^2."""
    return np.exp(-GAUSS_K * theta2_pix * f2)


def linear_initial_guess(q2: np.ndarray, re: np.ndarray, w: np.ndarray, nbins: int = 20
                         ) -> tuple[float, float]:
    """Initial (flux, theta^2) from the linear trick: ln V = ln S - GAUSS_K theta^2 q^2.

    The visibilities are averaged in bins of q^2 first (the log of single noisy visibilities
    is meaningless); bins whose mean is positive at > 2 sigma enter a weighted straight-line
    fit of ln(mean) against q^2, weights (mean/sigma)^2. Falls back to (weighted mean, 0).
    """
    q2 = np.asarray(q2, dtype=np.float64)
    wsum = float(np.sum(w))
    mean = float(np.sum(w * re) / wsum) if wsum > 0 else 0.0
    if q2.size < 3 or wsum <= 0:
        return mean, 0.0
    edges = np.unique(np.quantile(q2, np.linspace(0, 1, nbins + 1)))
    if edges.size < 3:
        return mean, 0.0
    idx = np.clip(np.searchsorted(edges, q2, side="right") - 1, 0, edges.size - 2)
    sw = np.bincount(idx, w, edges.size - 1)
    swy = np.bincount(idx, w * re, edges.size - 1)
    swx = np.bincount(idx, w * q2, edges.size - 1)
    ok = sw > 0
    ybar = np.where(ok, swy / np.where(ok, sw, 1), 0.0)
    xbar = np.where(ok, swx / np.where(ok, sw, 1), 0.0)
    sig = np.where(ok, 1.0 / np.sqrt(np.where(ok, sw, 1)), np.inf)
    good = ok & (ybar > 2 * sig)
    if good.sum() < 2:
        return mean, 0.0
    x, y = xbar[good], np.log(ybar[good])
    wt = (ybar[good] / sig[good]) ** 2
    A = np.vstack([np.ones_like(x), x]).T * np.sqrt(wt)[:, None]
    coef, *_ = np.linalg.lstsq(A, y * np.sqrt(wt), rcond=None)
    flux0 = float(np.exp(coef[0]))
    theta2 = float(-coef[1] / GAUSS_K)
    if not np.isfinite(flux0) or not np.isfinite(theta2):
        return mean, 0.0
    return flux0, max(theta2, 0.0)


def theta_upper_limit(a_hat: float, sigma_a: float, level: float = 0.95) -> float:
    """Upper limit on theta = sqrt(a) from a Gaussian likelihood for a = theta^2.

    With a flat prior on a >= 0 the posterior is the likelihood N(a_hat, sigma_a) truncated
    at 0; the limit is its ``level`` quantile (well defined also when a_hat < 0).
    """
    from scipy.stats import norm

    if not (np.isfinite(sigma_a) and sigma_a > 0):
        return float(np.sqrt(max(a_hat, 0.0)))
    p0 = norm.cdf(0.0, a_hat, sigma_a)
    q = p0 + level * (1.0 - p0)
    if q >= 1.0 - 1e-15:  # a_hat far below zero: use the tail asymptotics
        return float(np.sqrt(sigma_a**2 / max(-a_hat, sigma_a) * -np.log(1.0 - level)))
    a_ul = float(norm.ppf(q, a_hat, sigma_a))
    return float(np.sqrt(max(a_ul, 0.0)))


def theta_and_error(a_hat: float, sigma_a: float) -> tuple[float, float]:
    """theta = sqrt(max(a, 0)) and a 1-sigma error: half the width of the image of the
    interval [a - sigma_a, a + sigma_a] under sqrt (-> sigma_a / (2 theta) when resolved)."""
    theta = float(np.sqrt(max(a_hat, 0.0)))
    hi = np.sqrt(max(a_hat + sigma_a, 0.0))
    lo = np.sqrt(max(a_hat - sigma_a, 0.0))
    return theta, float(0.5 * (hi - lo))
