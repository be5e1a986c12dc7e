"""Fit of a stacked line spectrum: a Gaussian by generalised least squares, and the line's
integral over a velocity window with its error from the bins' covariance.

A stacked spectrum (:func:`xstack.uvstack.line.stack_lines`) has bins that share channels:
a channel that straddles two bins contributes to both, so the bins' errors are correlated
(``flux_cov_jy2``). Both the fit and the integral use that full covariance:

* :func:`fit_line` minimises r^T C^-1 r (r = data − model, C the bins' covariance), the
  model being a Gaussian averaged over each bin (erf differences, the same average over the
  bin that the stack's overlap weights make of a line), so a line a few bins wide is not
  biased by evaluating it at the bin centres. Parameter errors are those of the linearised
  GLS problem, (J^T C^-1 J)^-1: they assume C is the covariance of the data (not rescaled by
  chi^2; ``chi2`` and ``dof`` are reported to check that).
* :func:`integrate_line` sums ``flux * overlap`` over the bins in a window (a bin partly
  inside counts with the length of its overlap), and its error is sqrt(a^T C a) with ``a``
  those overlap lengths — including the positive covariance of neighbouring bins, which a
  sum of the bins' variances alone would leave out.

Velocities are in km/s, flux densities in Jy, integrals in Jy km/s.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from xstack._json import finite_or_none
from xstack._result import Result
from xstack.errors import OptionError

#: FWHM / sigma of a Gaussian, 2 sqrt(2 ln 2).
FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))

#: The line models :func:`fit_line` knows.
LINE_MODELS = ("gaussian",)

_NAN = float("nan")


@dataclass(kw_only=True)
class LineFit(Result):
    """The fit of a line spectrum (:func:`fit_line`).

    Attributes
    ----------
    model : "gaussian"
    centre_kms, centre_err_kms : fitted line centre on the stack's velocity axis and its
        1-sigma error, km/s
    fwhm_kms, fwhm_err_kms : full width at half maximum of the Gaussian and its error, km/s
    peak_jy, peak_err_jy : the Gaussian's peak flux density (before averaging over a bin) and
        its error, Jy (negative for an absorption line)
    integrated_flux_jy_kms, integrated_flux_err_jy_kms : sum of the bins inside
        ``window_kms`` times their overlap with it, and its error from the bins' covariance
        (:func:`integrate_line`), Jy km/s
    window_kms : (low, high) the window integrated, km/s: the one given, else the fitted
        centre ± FWHM (which holds 98.1 % of a Gaussian line); NaNs when there is none
    converged : True when the fit converged to a line inside the velocity range with finite
        errors; otherwise the fitted numbers are NaN and ``message`` says why
    message : why the fit failed, or ``""``
    chi2, dof : r^T C^-1 r at the best fit and the degrees of freedom (bins used − 3)
    n_bins : number of bins used (finite flux and variance)
    parameters, values, covariance : ("peak_jy", "centre_kms", "fwhm_kms"), their fitted
        values and their covariance
    """

    model: str = "gaussian"
    centre_kms: float = _NAN
    centre_err_kms: float = _NAN
    fwhm_kms: float = _NAN
    fwhm_err_kms: float = _NAN
    peak_jy: float = _NAN
    peak_err_jy: float = _NAN
    integrated_flux_jy_kms: float = _NAN
    integrated_flux_err_jy_kms: float = _NAN
    window_kms: tuple[float, float] = (_NAN, _NAN)
    converged: bool = False
    message: str = ""
    chi2: float = _NAN
    dof: int = 0
    n_bins: int = 0
    parameters: tuple[str, ...] = ("peak_jy", "centre_kms", "fwhm_kms")
    values: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    covariance: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (NaN becomes None)."""
        return {
            "model": self.model,
            "converged": bool(self.converged),
            "message": self.message,
            "centre_kms": finite_or_none(self.centre_kms),
            "centre_err_kms": finite_or_none(self.centre_err_kms),
            "fwhm_kms": finite_or_none(self.fwhm_kms),
            "fwhm_err_kms": finite_or_none(self.fwhm_err_kms),
            "peak_jy": finite_or_none(self.peak_jy),
            "peak_err_jy": finite_or_none(self.peak_err_jy),
            "integrated_flux_jy_kms": finite_or_none(self.integrated_flux_jy_kms),
            "integrated_flux_err_jy_kms": finite_or_none(self.integrated_flux_err_jy_kms),
            "window_kms": [finite_or_none(v) for v in self.window_kms],
            "chi2": finite_or_none(self.chi2),
            "dof": int(self.dof),
            "n_bins": int(self.n_bins),
            "parameters": list(self.parameters),
            "values": [finite_or_none(v) for v in np.ravel(self.values)],
            "covariance": [[finite_or_none(v) for v in row]
                           for row in np.atleast_2d(self.covariance)],
        }


# --- the model ----------------------------------------------------------------------------

def _erf_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """erf(a) − erf(b) for a >= b, without cancellation in the tails (erfc there)."""
    from scipy.special import erf, erfc

    out = erf(a) - erf(b)
    right = b > 0  # both in the right tail: erfc(b) − erfc(a)
    out[right] = erfc(b[right]) - erfc(a[right])
    left = a < 0  # both in the left tail
    out[left] = erfc(-a[left]) - erfc(-b[left])
    return out


def gaussian_bins(params: Any, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """A Gaussian line (peak, centre, FWHM) averaged over the bins [lo, hi] (km/s), Jy.

    ``peak * sigma sqrt(pi/2) / (hi − lo) * (erf(a) − erf(b))`` with
    a = (hi − centre) / (sqrt 2 sigma), b = (lo − centre) / (sqrt 2 sigma): the exact bin
    average, whose sum times the widths is the line's integral peak sigma sqrt(2 pi).
    """
    peak, centre, fwhm = (float(p) for p in params)
    sigma = fwhm / FWHM_PER_SIGMA
    s2 = math.sqrt(2.0) * sigma
    a, b = (hi - centre) / s2, (lo - centre) / s2
    return peak * sigma * math.sqrt(math.pi / 2.0) / (hi - lo) * _erf_difference(a, b)


def _gaussian_jacobian(params: Any, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """d(bin averages)/d(peak, centre, FWHM), shape (nbin, 3)."""
    peak, centre, fwhm = (float(p) for p in params)
    sigma = fwhm / FWHM_PER_SIGMA
    s2 = math.sqrt(2.0) * sigma
    w = hi - lo
    a, b = (hi - centre) / s2, (lo - centre) / s2
    ea, eb = np.exp(-a * a), np.exp(-b * b)
    e = _erf_difference(a, b)
    k = sigma * math.sqrt(math.pi / 2.0) / w
    d_peak = k * e
    d_centre = peak * (eb - ea) / w
    d_sigma = peak * math.sqrt(math.pi / 2.0) / w * (e - 2.0 / math.sqrt(math.pi)
                                                     * (a * ea - b * eb))
    return np.stack([d_peak, d_centre, d_sigma / FWHM_PER_SIGMA], axis=1)


# --- helpers ------------------------------------------------------------------------------

def edges_from_centres(velocity_kms: Any) -> np.ndarray:
    """Bin edges halfway between increasing bin centres (the outer ones mirrored), km/s."""
    v = np.asarray(velocity_kms, dtype=np.float64)
    if v.size < 2:
        raise OptionError("need at least two bins to tell their edges", option="velocity_kms")
    mid = 0.5 * (v[1:] + v[:-1])
    return np.concatenate([[v[0] - (mid[0] - v[0])], mid, [v[-1] + (v[-1] - mid[-1])]])


def _check_spectrum(velocity_kms: Any, flux_jy: Any, flux_cov_jy2: Any,
                    velocity_edges_kms: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                      np.ndarray]:
    """(centres, flux, covariance (n, n), edges (n+1)) as float64, shapes checked; a 1-D
    ``flux_cov_jy2`` is the bins' variances (no covariance between bins)."""
    v = np.asarray(velocity_kms, dtype=np.float64).ravel()
    s = np.asarray(flux_jy, dtype=np.float64).ravel()
    c = np.asarray(flux_cov_jy2, dtype=np.float64)
    n = v.size
    if s.size != n:
        raise OptionError(f"flux_jy has {s.size} bins, velocity_kms {n}", option="flux_jy")
    if c.ndim == 1:
        c = np.diag(c)
    if c.shape != (n, n):
        raise OptionError(f"flux_cov_jy2 must be ({n}, {n}) (or {n} variances), got "
                          f"{c.shape}", option="flux_cov_jy2")
    edges = (edges_from_centres(v) if velocity_edges_kms is None
             else np.asarray(velocity_edges_kms, dtype=np.float64).ravel())
    if edges.size != n + 1:
        raise OptionError(f"velocity_edges_kms must have {n + 1} values, got {edges.size}",
                          option="velocity_edges_kms")
    if not np.all(np.diff(edges) > 0):
        raise OptionError("velocity_edges_kms must increase", option="velocity_edges_kms")
    return v, s, c, edges


def _window(window_kms: Any) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in window_kms)
    except (TypeError, ValueError):
        raise OptionError(f"window_kms must be two velocities (low, high), got {window_kms!r}",
                          option="window_kms") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise OptionError(f"window_kms must be finite with low < high, got ({lo}, {hi})",
                          option="window_kms")
    return lo, hi


def overlap_in_window(velocity_edges_kms: Any, window_kms: Any) -> np.ndarray:
    """Length (km/s) of each bin [edge_j, edge_j+1] inside the window (low, high)."""
    edges = np.asarray(velocity_edges_kms, dtype=np.float64)
    lo, hi = _window(window_kms)
    return np.clip(np.minimum(edges[1:], hi) - np.maximum(edges[:-1], lo), 0.0, None)


def integrate_line(velocity_edges_kms: Any, flux_jy: Any, flux_cov_jy2: Any,
                   window_kms: Any) -> tuple[float, float]:
    """The integral of a binned spectrum over a velocity window, and its 1-sigma error.

    Parameters
    ----------
    velocity_edges_kms
        Bin edges, km/s, increasing (nbin + 1).
    flux_jy
        Flux density per bin, Jy (the mean over the bin).
    flux_cov_jy2
        Covariance of the bins, Jy^2, (nbin, nbin); a 1-D array is the bins' variances
        (independent bins).
    window_kms
        (low, high), km/s. A bin partly inside counts with its overlap fraction.

    Returns
    -------
    (float, float)
        sum_j a_j S_j in Jy km/s, with a_j the length of bin j inside the window, and
        sqrt(a^T C a). NaN (both) when a bin with a_j > 0 has no flux (NaN: no target
        covered it) or when no bin overlaps the window.
    """
    edges = np.asarray(velocity_edges_kms, dtype=np.float64).ravel()
    _, s, c, _ = _check_spectrum(0.5 * (edges[1:] + edges[:-1]), flux_jy, flux_cov_jy2, edges)
    a = overlap_in_window(edges, window_kms)
    inside = a > 0
    if not inside.any():
        return _NAN, _NAN
    if not (np.all(np.isfinite(s[inside]))
            and np.all(np.isfinite(c[np.ix_(inside, inside)]))):
        return _NAN, _NAN
    ai = a[inside]
    value = float(ai @ s[inside])
    var = float(ai @ c[np.ix_(inside, inside)] @ ai)
    return value, math.sqrt(var) if var >= 0 else _NAN


# --- the fit ------------------------------------------------------------------------------

def _whitener(cov: np.ndarray) -> tuple[Any, int]:
    """A function x -> W x with W^T W = C^-1 (Cholesky, else the eigenvectors of the
    non-zero eigenvalues: a singular C — bins that are sums of the same channels — constrains
    only the combinations it has), and the rank."""
    from scipy.linalg import cholesky, solve_triangular

    try:
        low = cholesky(cov, lower=True)
        if np.min(np.diag(low)) ** 2 < 1e-12 * np.max(np.diag(cov)):
            # numerically singular: the factor would amplify rounding into fake information
            raise np.linalg.LinAlgError("near-singular covariance")
        # the explicit inverse factor, once: the fit whitens dozens of vectors
        w = solve_triangular(low, np.eye(cov.shape[0]), lower=True)
        rank = cov.shape[0]
    except np.linalg.LinAlgError:
        vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
        keep = vals > vals.max() * 1e-12
        w = vecs[:, keep].T / np.sqrt(vals[keep])[:, None]
        rank = int(keep.sum())
    return (lambda x: w @ x), rank


def _start(whiten: Any, s_w: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Start values by a matched filter: the (centre, FWHM) on a grid whose best-amplitude
    Gaussian lowers chi^2 most; robust to noise spikes one bin wide and to the line's sign."""
    centres = 0.5 * (lo + hi)
    width = float(np.median(hi - lo))
    span = float(hi.max() - lo.min())
    fwhms = np.geomspace(width, max(span / 2.0, 2.0 * width), 10)
    grid_c = np.linspace(lo.min(), hi.max(), 2 * centres.size + 1)
    best = (-np.inf, np.array([0.0, float(centres.mean()), 3.0 * width]))
    for fwhm in fwhms:
        sigma2 = math.sqrt(2.0) * fwhm / FWHM_PER_SIGMA
        a = (hi[:, None] - grid_c[None, :]) / sigma2
        b = (lo[:, None] - grid_c[None, :]) / sigma2
        # bin averages of unit-peak Gaussians at every grid centre (as gaussian_bins)
        shapes = (sigma2 * math.sqrt(math.pi) / 2.0 / (hi - lo)[:, None]
                  * _erf_difference(a, b))
        g_w = whiten(shapes)
        gg = np.einsum("ij,ij->j", g_w, g_w)
        gs = s_w @ g_w
        ok = gg > 0
        gain = np.where(ok, gs * gs / np.where(ok, gg, 1.0), -np.inf)
        j = int(np.argmax(gain))
        if gain[j] > best[0]:
            best = (gain[j], np.array([gs[j] / gg[j], grid_c[j], fwhm]))
    return best[1]


def fit_line(velocity_kms: Any, flux_jy: Any, flux_cov_jy2: Any, *,
             velocity_edges_kms: Any = None, window_kms: Any = None,
             model: str = "gaussian") -> LineFit:
    """Fit a Gaussian line to a stacked spectrum with the bins' full covariance.

    Parameters
    ----------
    velocity_kms
        Bin centres, km/s, increasing.
    flux_jy
        Flux density per bin, Jy. NaN bins (no target covered them) are left out.
    flux_cov_jy2
        Covariance of the bins, Jy^2, (nbin, nbin) (a 1-D array: the variances of independent
        bins).
    velocity_edges_kms
        Bin edges, km/s (nbin + 1); default halfway between the centres. The model is the
        Gaussian averaged over each bin.
    window_kms
        (low, high), km/s, the window of the integrated flux; default the fitted centre ±
        FWHM.
    model
        ``"gaussian"``.

    Returns
    -------
    LineFit
        ``converged=False`` with NaN numbers and a ``message`` when the data do not
        constrain a line (too few bins, the width or centre ran to the edge of the range,
        singular errors); the integral over a given ``window_kms`` is computed either way.
        Noisy data never raise.

    Raises
    ------
    OptionError
        Inconsistent shapes, edges that do not increase, a bad window or an unknown model.
    """
    from scipy.optimize import least_squares

    if model not in LINE_MODELS:
        raise OptionError(f"model={model!r}: known line models are {', '.join(LINE_MODELS)}",
                          option="model")
    v, s, c, edges = _check_spectrum(velocity_kms, flux_jy, flux_cov_jy2, velocity_edges_kms)
    given_window = _window(window_kms) if window_kms is not None else None
    lo_all, hi_all = edges[:-1], edges[1:]
    var = np.diag(c)
    use = np.isfinite(s) & np.isfinite(var) & (var > 0)
    use &= np.all(np.isfinite(c[:, use]), axis=1) if use.any() else use
    n = int(use.sum())

    def failed(message: str, **extra: Any) -> LineFit:
        integral = (integrate_line(edges, s, c, given_window) if given_window is not None
                    else (_NAN, _NAN))
        return LineFit(model=model, integrated_flux_jy_kms=integral[0],
                       integrated_flux_err_jy_kms=integral[1],
                       window_kms=given_window or (_NAN, _NAN), converged=False,
                       message=message, n_bins=n, **extra)

    if n < 4:
        return failed(f"{n} bins with data: a Gaussian (3 parameters) needs at least 4")
    lo, hi, su = lo_all[use], hi_all[use], s[use]
    whiten, rank = _whitener(c[np.ix_(use, use)])
    if rank < 4:
        return failed(f"the covariance of the bins has rank {rank}: too few independent bins")
    s_w = whiten(su)
    x0 = _start(whiten, s_w, lo, hi)
    width = float(np.min(hi - lo))
    vmin, vmax = float(lo.min()), float(hi.max())
    span = vmax - vmin
    bounds = ([-np.inf, vmin, 0.05 * width], [np.inf, vmax, 2.0 * span])
    x0 = np.clip(x0, [-np.inf, vmin, 0.05 * width * 1.01], [np.inf, vmax, 2.0 * span * 0.99])

    def residual(p: np.ndarray) -> np.ndarray:
        return whiten(su - gaussian_bins(p, lo, hi))

    def jacobian(p: np.ndarray) -> np.ndarray:
        return -whiten(_gaussian_jacobian(p, lo, hi))

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            sol = least_squares(residual, x0, jac=jacobian, bounds=bounds, method="trf",
                                x_scale="jac", xtol=1e-10, ftol=1e-10, gtol=1e-10,
                                max_nfev=300)
    except (ValueError, np.linalg.LinAlgError) as exc:  # e.g. non-finite residuals
        return failed(f"the fit failed ({exc})")
    p = sol.x
    chi2 = float(sol.fun @ sol.fun)
    dof = rank - 3
    if not sol.success:
        return failed(f"the fit did not converge ({sol.message})", chi2=chi2, dof=dof)
    at_edge = []
    if p[1] - vmin < 1e-6 * span or vmax - p[1] < 1e-6 * span:
        at_edge.append("its centre at the edge of the velocity range")
    if p[2] >= 2.0 * span * 0.999:
        at_edge.append("its width twice the velocity range")
    if at_edge:
        return failed("no line found: the best Gaussian has " + " and ".join(at_edge),
                      chi2=chi2, dof=dof)
    if p[2] < width:
        # below a bin only peak x width is measured (a noise spike fits so too)
        return failed(f"the best Gaussian is narrower than one bin (FWHM {p[2]:.3g} km/s < "
                      f"{width:.3g} km/s): its width and centre are not resolved; use finer "
                      "bins, or give window_kms for the integral", chi2=chi2, dof=dof)
    j_w = sol.jac
    try:
        cov = np.linalg.inv(j_w.T @ j_w)
    except np.linalg.LinAlgError:
        return failed("the parameters' errors are singular (a line with zero peak?)",
                      chi2=chi2, dof=dof)
    errs = np.sqrt(np.diag(cov))
    if not np.all(np.isfinite(errs)) or p[0] == 0:
        return failed("the parameters' errors are not finite", chi2=chi2, dof=dof)
    window = given_window or (float(p[1] - p[2]), float(p[1] + p[2]))
    integral, integral_err = integrate_line(edges, s, c, window)
    return LineFit(model=model, centre_kms=float(p[1]), centre_err_kms=float(errs[1]),
                   fwhm_kms=float(p[2]), fwhm_err_kms=float(errs[2]), peak_jy=float(p[0]),
                   peak_err_jy=float(errs[0]), integrated_flux_jy_kms=integral,
                   integrated_flux_err_jy_kms=integral_err, window_kms=window,
                   converged=True, chi2=chi2, dof=dof, n_bins=n, values=np.asarray(p, float),
                   covariance=cov)


# --- continuum subtraction ------------------------------------------------------------------

@dataclass(kw_only=True)
class ContinuumBaseline(Result):
    """The polynomial continuum :func:`subtract_continuum` fitted and removed.

    Attributes
    ----------
    order : degree of the polynomial in velocity (0: a constant)
    line_free_kms : the line-free ranges ((low, high), ...), km/s
    coefficients_jy, coefficient_errors : c_0 ... c_order of
        sum_k c_k v^k (v in km/s, c_k in Jy (km/s)^-k) and their 1-sigma errors
    coefficient_covariance : (order + 1, order + 1) covariance of the coefficients
    flux_jy, flux_err_jy : the baseline averaged over each bin (every bin, also those with no
        data) and its 1-sigma error, Jy
    fit_bins : bool mask of the bins the fit used (wholly inside a line-free range, with data)
    chi2, dof : r^T C^-1 r of the fit over ``fit_bins`` and its degrees of freedom
    matrix : (nbin, nbin) the linear map M of the subtraction, S' = M S on the bins with data
        (the identity on bins without): apply it to any spectrum on the same bins, e.g. each
        pixel of a stacked cube
    """

    order: int
    line_free_kms: tuple[tuple[float, float], ...]
    coefficients_jy: np.ndarray
    coefficient_errors: np.ndarray
    coefficient_covariance: np.ndarray
    flux_jy: np.ndarray
    flux_err_jy: np.ndarray
    fit_bins: np.ndarray
    chi2: float = _NAN
    dof: int = 0
    matrix: np.ndarray | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (NaN becomes None)."""
        return {
            "order": int(self.order),
            "line_free_kms": [[float(a), float(b)] for a, b in self.line_free_kms],
            "coefficients_jy": [finite_or_none(v) for v in self.coefficients_jy],
            "coefficient_errors": [finite_or_none(v) for v in self.coefficient_errors],
            "coefficient_units": ["Jy" if k == 0 else f"Jy (km/s)^-{k}"
                                  for k in range(self.order + 1)],
            "n_bins_fitted": int(np.count_nonzero(self.fit_bins)),
            "chi2": finite_or_none(self.chi2),
            "dof": int(self.dof),
        }


def _ranges(line_free_kms: Any) -> tuple[tuple[float, float], ...]:
    """((low, high), ...) from one pair or a sequence of pairs, each checked."""
    try:
        arr = np.asarray(line_free_kms, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.empty((0, 3))
    if arr.ndim == 1 and arr.size == 2:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != 2 or arr.shape[0] == 0:
        raise OptionError(f"line_free_kms must be velocity ranges ((low, high), ...) in km/s, "
                          f"got {line_free_kms!r}", option="line_free_kms")
    out = []
    for lo, hi in arr:
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise OptionError(f"line_free_kms: each range needs finite low < high, got "
                              f"({lo:g}, {hi:g})", option="line_free_kms")
        out.append((float(lo), float(hi)))
    return tuple(out)


def polynomial_bin_averages(velocity_edges_kms: Any, order: int,
                            scale_kms: float = 1.0) -> np.ndarray:
    """(nbin, order + 1): the average over each bin [lo, hi] of (v / scale)^k, k = 0..order,
    exactly: ((hi/s)^(k+1) − (lo/s)^(k+1)) / ((k + 1) (hi − lo)/s)."""
    edges = np.asarray(velocity_edges_kms, dtype=np.float64) / float(scale_kms)
    lo, hi = edges[:-1], edges[1:]
    k = np.arange(order + 1)
    return ((hi[:, None] ** (k + 1) - lo[:, None] ** (k + 1))
            / ((k + 1) * (hi - lo)[:, None]))


def subtract_continuum(velocity_edges_kms: Any, flux_jy: Any, flux_cov_jy2: Any, *,
                       order: int, line_free_kms: Any, line_window_kms: Any = None
                       ) -> tuple[np.ndarray, np.ndarray, ContinuumBaseline]:
    """Fit a polynomial continuum to line-free bins and subtract it from the whole spectrum.

    The polynomial sum_k c_k v^k is fitted by generalised least squares with the bins'
    covariance C over the bins lying *wholly* inside one of the line-free ranges (a bin only
    partly inside is left out of the fit: it may hold some line), as the polynomial's exact
    average over each bin (its integral over the bin divided by the width: no error from
    evaluating at bin centres). The baseline's bin averages are subtracted from every bin.
    The result is linear in the spectrum, S' = M S with
    M = I − A (X^T C^-1 X)^-1 X^T C^-1 P (A: the polynomial's bin averages on all bins, X those
    on the fitted bins, P selects them), so its covariance is exactly C' = M C M^T — the
    baseline's own error and its correlation with every bin included.

    Parameters
    ----------
    velocity_edges_kms
        Bin edges, km/s, increasing (nbin + 1).
    flux_jy
        Flux density per bin, Jy. NaN bins (no target covered them) stay NaN and are left
        out of the fit.
    flux_cov_jy2
        Covariance of the bins, Jy^2, (nbin, nbin); a 1-D array is the bins' variances.
    order
        Degree of the polynomial, >= 0 (0: a constant, 1: a straight line).
    line_free_kms
        The velocity ranges free of line emission, km/s: one (low, high) or a sequence of
        them.
    line_window_kms
        (low, high), km/s, the line's window, or None; a line-free range overlapping it is an
        error.

    Returns
    -------
    (flux_jy, flux_cov_jy2, baseline)
        The subtracted spectrum (Jy; NaN where the input is), its covariance (Jy^2,
        (nbin, nbin); NaN rows and columns for NaN bins) and the :class:`ContinuumBaseline`.

    Raises
    ------
    OptionError
        A negative or non-integer order, bad ranges, a range overlapping the line window,
        fewer than order + 2 usable bins wholly inside the line-free ranges (at least one
        more than the polynomial's parameters, so the fit is checked by one degree of
        freedom), or a covariance that does not constrain the polynomial.
    """
    if isinstance(order, bool) or not float(order).is_integer() or int(order) < 0:
        raise OptionError(f"order={order!r}: the polynomial's degree must be an integer >= 0",
                          option="order")
    order = int(order)
    ranges = _ranges(line_free_kms)
    edges = np.asarray(velocity_edges_kms, dtype=np.float64).ravel()
    _, s, c, edges = _check_spectrum(0.5 * (edges[1:] + edges[:-1]), flux_jy, flux_cov_jy2,
                                     edges)
    if line_window_kms is not None:
        w_lo, w_hi = _window(line_window_kms)
        for lo, hi in ranges:
            if lo < w_hi and hi > w_lo:
                raise OptionError(f"line_free_kms range ({lo:g}, {hi:g}) km/s overlaps the line "
                                  f"window ({w_lo:g}, {w_hi:g}) km/s: the continuum fit would "
                                  "remove line flux", option="line_free_kms")
    n = s.size
    var = np.diag(c)
    ok = np.isfinite(s) & np.isfinite(var) & (var > 0)
    if ok.any():
        ok &= np.all(np.isfinite(c[:, ok]), axis=1)
    inside = np.zeros(n, dtype=bool)
    for lo, hi in ranges:
        inside |= (edges[:-1] >= lo) & (edges[1:] <= hi)
    free = inside & ok
    nfree = int(free.sum())
    if nfree < order + 2:
        raise OptionError(f"line_free_kms holds {nfree} bins with data wholly inside its "
                          f"ranges; a polynomial of order={order} needs at least {order + 2}",
                          option="line_free_kms")
    # the polynomial in v / scale: well conditioned for any order on a +-1000 km/s axis
    scale = float(np.max(np.abs(edges))) or 1.0
    a_all = polynomial_bin_averages(edges, order, scale)
    x = a_all[free]
    whiten, rank = _whitener(c[np.ix_(free, free)])
    if rank < order + 2:
        raise OptionError(f"the covariance of the {nfree} line-free bins has rank {rank}: too "
                          f"few independent bins for order={order}", option="line_free_kms")
    w = whiten(np.eye(nfree))  # W with W^T W = C^-1 (on the constrained subspace)
    xw = w @ x
    normal = xw.T @ xw
    try:
        cov_scaled = np.linalg.inv(normal)
    except np.linalg.LinAlgError:
        raise OptionError(f"the line-free bins do not constrain a polynomial of order={order}",
                          option="line_free_kms") from None
    gain = cov_scaled @ xw.T @ w  # (X^T C^-1 X)^-1 X^T C^-1, (order + 1, nfree)
    beta_scaled = gain @ s[free]
    resid = w @ (s[free] - x @ beta_scaled)
    # M on the bins with data; the rows and columns of NaN bins stay NaN
    idx = np.flatnonzero(ok)
    m = np.eye(idx.size)
    cols = np.searchsorted(idx, np.flatnonzero(free))
    m[:, cols] -= a_all[ok] @ gain
    s_out = np.full(n, np.nan)
    s_out[ok] = m @ s[ok]
    c_out = np.full((n, n), np.nan)
    c_out[np.ix_(ok, ok)] = m @ c[np.ix_(ok, ok)] @ m.T
    base = a_all @ beta_scaled
    base_var = np.einsum("ij,jk,ik->i", a_all, cov_scaled, a_all)
    powers = scale ** -np.arange(order + 1, dtype=np.float64)
    coef_cov = cov_scaled * np.outer(powers, powers)
    m_full = np.eye(n)
    m_full[np.ix_(ok, ok)] = m
    baseline = ContinuumBaseline(
        order=order, line_free_kms=ranges, coefficients_jy=beta_scaled * powers,
        coefficient_errors=np.sqrt(np.diag(coef_cov)), coefficient_covariance=coef_cov,
        flux_jy=base, flux_err_jy=np.sqrt(np.clip(base_var, 0.0, None)), fit_bins=free,
        chi2=float(resid @ resid), dof=rank - (order + 1), matrix=m_full)
    return s_out, c_out, baseline


# --- the spectrum as a table and a picture ---------------------------------------------------

def spectrum_table(result: Any, fit: LineFit | None = None,
                   baseline: ContinuumBaseline | None = None) -> Any:
    """A line stack's spectrum as an :class:`astropy.table.Table` with units, one row a bin.

    Columns ``velocity_kms`` (centre), ``velocity_lo_kms``, ``velocity_hi_kms``, ``flux_jy``,
    ``flux_err_jy``, ``n_targets``, ``flux_cov_jy2`` (the bin's row of the covariance, so the
    table alone can be refitted) and, with a converged ``fit``, ``model_jy`` (the fitted
    Gaussian averaged over the bin). ``meta`` holds the fit (:meth:`LineFit.to_dict`), the rest
    frequency, frame, ``n_positions`` and ``n_visibilities``. With a ``baseline``
    (:func:`subtract_continuum`; ``result`` then holds the subtracted spectrum) also
    ``baseline_jy`` and ``baseline_err_jy`` (the continuum removed, per bin: ``flux_jy +
    baseline_jy`` is the spectrum before subtraction) and ``meta["continuum_subtracted"]``.

    Parameters
    ----------
    result
        A :class:`~xstack.uvstack.line.LineStackResult` (or anything with its spectrum
        attributes).
    fit
        The :func:`fit_line` of the spectrum, or None.
    baseline
        The continuum subtracted from ``result``'s spectrum, or None.
    """
    import astropy.units as u
    from astropy.table import Table

    from xstack._result import json_ready

    edges = np.asarray(result.velocity_edges_kms, dtype=np.float64)
    t = Table()
    t["velocity_kms"] = np.asarray(result.velocity_kms, dtype=np.float64) * u.km / u.s
    t["velocity_lo_kms"] = edges[:-1] * u.km / u.s
    t["velocity_hi_kms"] = edges[1:] * u.km / u.s
    t["flux_jy"] = np.asarray(result.flux_jy, dtype=np.float64) * u.Jy
    t["flux_err_jy"] = np.asarray(result.flux_err_jy, dtype=np.float64) * u.Jy
    t["n_targets"] = np.asarray(result.n_targets_per_bin, dtype=np.int64)
    t["flux_cov_jy2"] = np.asarray(result.flux_cov_jy2, dtype=np.float64) * u.Jy**2
    if fit is not None and fit.converged:
        t["model_jy"] = gaussian_bins(fit.values, edges[:-1], edges[1:]) * u.Jy
    if baseline is not None:
        t["baseline_jy"] = np.asarray(baseline.flux_jy, dtype=np.float64) * u.Jy
        t["baseline_err_jy"] = np.asarray(baseline.flux_err_jy, dtype=np.float64) * u.Jy
    t.meta.update(json_ready({
        "rest_frequency_hz": float(result.rest_frequency_hz), "frame": result.frame,
        "n_positions": int(result.n_positions), "n_visibilities": int(result.n_visibilities),
        "velocity_convention": "v = c (nu_c - nu) / nu_c about each target's line centre",
        "fit": fit.to_dict() if fit is not None else None,
        "continuum_subtracted": baseline.to_dict() if baseline is not None else None}))
    return t


def line_spectrum_figure(table: Any, *, title: str | None = None) -> Any:
    """A matplotlib Figure (Agg) of a :func:`spectrum_table`: the spectrum as steps with its
    1-sigma band, the fitted Gaussian (``meta["fit"]``), the integration window shaded, and
    below it the number of targets per bin.

    Artists carry ``gid``: ``"spectrum"``, ``"error"``, ``"model"``, ``"window"``,
    ``"n_targets"``; with a ``baseline_jy`` column (continuum subtracted) also
    ``"unsubtracted"`` (the spectrum before subtraction), ``"baseline"`` (the continuum
    removed) and ``"line_free"`` (the ranges it was fitted on).
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    edges = np.append(np.asarray(table["velocity_lo_kms"], dtype=np.float64),
                      float(table["velocity_hi_kms"][-1]))
    flux = np.asarray(table["flux_jy"], dtype=np.float64)
    err = np.asarray(table["flux_err_jy"], dtype=np.float64)
    fit = table.meta.get("fit") or {}
    peak = fit.get("peak_jy") if fit.get("converged") else None
    big = np.nanmax(np.abs(np.concatenate([flux, err, [abs(peak or 0.0)], [0.0]])))
    scale, unit = ((1e3, "mJy") if big > 1e-3 else (1e6, "µJy")) if np.isfinite(big) \
        else (1e6, "µJy")
    fig = Figure(figsize=(6.4, 5.0), dpi=110)
    top, bottom = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": (3, 1)})
    band = top.stairs((flux + err) * scale, edges, baseline=(flux - err) * scale, fill=True,
                      color="C0", alpha=0.25, label="±1σ")
    band.set_gid("error")
    steps = top.stairs(flux * scale, edges, baseline=None, color="C0", lw=1.2,
                       label="stacked spectrum")
    steps.set_gid("spectrum")
    top.axhline(0.0, color="0.5", lw=0.8)
    if "baseline_jy" in table.colnames:
        base = np.asarray(table["baseline_jy"], dtype=np.float64)
        cont = table.meta.get("continuum_subtracted") or {}
        before = top.stairs((flux + base) * scale, edges, baseline=None, color="0.55", lw=0.8,
                            label="before continuum subtraction")
        before.set_gid("unsubtracted")
        removed = top.stairs(base * scale, edges, baseline=None, color="C3", lw=1.0,
                             ls="--", label=f"continuum (order {cont.get('order', '?')})")
        removed.set_gid("baseline")
        for i, (lo, hi) in enumerate(cont.get("line_free_kms") or []):
            free = top.axvspan(lo, hi, ymin=0.0, ymax=0.04, color="C2", alpha=0.5,
                               label="line-free" if i == 0 else None)
            free.set_gid("line_free")
    window = fit.get("window_kms") or [None, None]
    if all(w is not None for w in window):
        span = top.axvspan(window[0], window[1], color="0.85", zorder=0,
                           label="integration window")
        span.set_gid("window")
    if peak is not None:
        v = np.linspace(edges[0], edges[-1], 600)
        sigma = fit["fwhm_kms"] / FWHM_PER_SIGMA
        model = peak * np.exp(-0.5 * ((v - fit["centre_kms"]) / sigma) ** 2)
        label = (f"Gaussian: centre {fit['centre_kms']:.4g} ± {fit['centre_err_kms']:.2g},\n"
                 f"FWHM {fit['fwhm_kms']:.4g} ± {fit['fwhm_err_kms']:.2g} km/s")
        (line,) = top.plot(v, model * scale, color="k", lw=1.2, label=label)
        line.set_gid("model")
    integral = fit.get("integrated_flux_jy_kms")
    if integral is not None and fit.get("integrated_flux_err_jy_kms") is not None:
        top.text(0.02, 0.97, f"∫ = {integral:.4g} ± {fit['integrated_flux_err_jy_kms']:.2g} "
                 "Jy km/s", transform=top.transAxes, va="top", fontsize=8)
    top.set_ylabel(f"flux density [{unit}]")
    # room above the data for the legend and the integral, so they hide no bin
    low, high = top.get_ylim()
    top.set_ylim(low, high + 0.45 * (high - low))
    top.legend(frameon=False, fontsize=7, loc="upper right", ncol=2)
    if title:
        top.set_title(title, fontsize=9)
    counts = bottom.stairs(np.asarray(table["n_targets"], dtype=np.float64), edges, color="C2")
    counts.set_gid("n_targets")
    bottom.set_ylabel("targets")
    bottom.set_xlabel("velocity [km/s]")
    bottom.set_ylim(bottom=0)
    fig.tight_layout()
    return fig


def plot_line_spectrum(table: Any, path: Any, *, title: str | None = None,
                       overwrite: bool = False) -> str:
    """Write :func:`line_spectrum_figure` of ``table`` to the PNG ``path`` atomically;
    returns ``path`` as str (an existing file is an error without ``overwrite``)."""
    import os

    from xstack._atomic import atomic_output

    fig = line_spectrum_figure(table, title=title)
    path = os.fspath(path)
    with atomic_output(path, overwrite=overwrite) as tmp:
        fig.savefig(str(tmp), format="png")
    return path
