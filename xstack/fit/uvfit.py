"""uv-domain model fitting of a stacked data set (paper section 3.4).

The stacked visibilities (Stokes I: every unflagged parallel-hand visibility, each with its
own weight, inside the uv range) are fitted with

* ``point``:    V = S                      (the weighted mean of Re V; exact, linear), or
* ``gaussian``: V = S exp(-pi^2 theta^2 q^2 / (4 ln 2)),  theta = FWHM, q in wavelengths,

by weighted non-linear least squares on the complex visibilities
(:func:`scipy.optimize.least_squares`); the model is real (the source sits at the phase
center), so the imaginary parts enter only chi^2. Initial values come from the linear trick
(ln V is linear in q^2 for a Gaussian, fitted on binned averages). The size is fitted as
``theta^2`` so an unresolved source (theta -> 0) is an interior point of the fit: it gives
``fwhm^2`` consistent with 0 and a 95 % upper limit on the FWHM instead of a blow-up.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from xstack import _options as _opt
from xstack._vocabulary import FIT_MODELS
from xstack.coords import SPEED_OF_LIGHT
from xstack.errors import NoDataError, OptionError, XstackError
from xstack.fit._data import as_partitions, parse_uv_limit, stokes_i_blocks, uv_range_mask
from xstack.fit.models import GAUSS_K, linear_initial_guess, theta_and_error, theta_upper_limit
from xstack.fit.result import FitResult

RAD2ARCSEC = 180.0 / np.pi * 3600.0

#: Above this many visibilities the unbinned fit works on exact sufficient statistics in
#: 20 000 logarithmic q^2 bins (model error O((dq/q)^2) ~ 1e-7, far below any noise).
MAX_UNBINNED = 2_000_000
_FINE_BINS = 20_000


def collect_uv(stacked: Any, *, uvmin: Any = None, uvmax: Any = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, int]:
    """Gather Stokes-I visibilities of a stacked data set inside the uv range.

    Returns
    -------
    q2 : float64, squared uv distance in wavelengths^2
    re : float64, Re V (Jy)
    w : float64, weights (1/Jy^2)
    chi2_im : sum of w (Im V)^2 over the same visibilities
    n_total : usable visibilities before the uv cut
    """
    return _collect(stacked, (parse_uv_limit(uvmin), parse_uv_limit(uvmax)), uvmin, uvmax)


def _collect(stacked: Any, limits: tuple[Any, Any], uvmin: Any, uvmax: Any
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, int]:
    """:func:`collect_uv` with the uv limits already parsed (``uvmin``/``uvmax`` as given,
    for the messages)."""
    lo, hi = limits
    qs, res, ws = [], [], []
    chi2_im, n_total = 0.0, 0
    for name, ds in as_partitions(stacked):
        freq = np.asarray(ds["frequency"].values, dtype=np.float64)
        for uvw, vis, wt in stokes_i_blocks(ds, name):
            n_total += int(np.count_nonzero(wt))
            mask = uv_range_mask(uvw, freq, lo, hi)
            if mask is not None:
                wt = wt * mask[..., None]
            sel = wt > 0
            if not sel.any():
                continue
            q2 = ((uvw[:, 0] ** 2 + uvw[:, 1] ** 2)[:, None]
                  * (freq / SPEED_OF_LIGHT)[None, :] ** 2)
            q2 = np.broadcast_to(q2[..., None], wt.shape)
            qs.append(q2[sel])
            res.append(vis.real[sel])
            ws.append(wt[sel])
            chi2_im += float(np.sum(wt[sel] * vis.imag[sel] ** 2))
    if n_total == 0:
        raise NoDataError("no usable visibilities (all flagged or zero weight)")
    if not ws:
        raise NoDataError(f"no visibilities left in the uv range (uvmin={uvmin}, uvmax={uvmax}); "
                          f"{n_total} usable visibilities lie outside it")
    return (np.concatenate(qs), np.concatenate(res), np.concatenate(ws), chi2_im, n_total)


def _binned_sums(x: np.ndarray, y: np.ndarray, w: np.ndarray, edges: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Exact weighted sums per bin: (x_mean, y_mean, sum_w) and the within-bin chi^2."""
    nb = edges.size - 1
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, nb - 1)
    sw = np.bincount(idx, w, nb)
    swx = np.bincount(idx, w * x, nb)
    swy = np.bincount(idx, w * y, nb)
    swyy = np.bincount(idx, w * y * y, nb)
    ok = sw > 0
    sw, swx, swy, swyy = sw[ok], swx[ok], swy[ok], swyy[ok]
    ybar = swy / sw
    within = float(np.sum(swyy - sw * ybar**2))
    return swx / sw, ybar, sw, max(within, 0.0)


def fit_uv_arrays(q2: np.ndarray, re: np.ndarray, w: np.ndarray, *, model: str = "gaussian",
                  chi2_extra: float = 0.0, n_vis: int | None = None, n_im: int | None = None,
                  rescale_errors: bool = True) -> FitResult:
    """Fit a point or circular-Gaussian model to (q^2, Re V, weight) samples.

    Parameters
    ----------
    q2, re, w
        Squared uv distance (wavelengths^2), real part (Jy) and weight (1/Jy^2) of each
        sample (a visibility, or a bin average with the bin's summed weight).
    chi2_extra
        chi^2 not represented by the samples (imaginary parts, within-bin scatter).
    n_vis, n_im
        Number of real (resp. imaginary) measurements behind the samples (for the dof).
    rescale_errors
        Multiply the errors by sqrt(chi^2 / dof) (recommended: visibility weights are
        often only relative).
    """
    from scipy.optimize import least_squares

    q2 = np.asarray(q2, dtype=np.float64)
    re = np.asarray(re, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)
    n_vis = int(q2.size if n_vis is None else n_vis)
    n_im = int(n_vis if n_im is None else n_im)
    wsum = float(w.sum())
    if not wsum > 0:
        raise NoDataError("no visibilities with positive weight to fit")
    if model == "point":
        flux = float(np.sum(w * re) / wsum)
        chi2 = float(np.sum(w * (re - flux) ** 2)) + chi2_extra
        dof = max(n_vis + n_im - 1, 1)
        scale = float(np.sqrt(chi2 / dof)) if rescale_errors and chi2 > 0 else 1.0
        err = scale / np.sqrt(wsum)
        return FitResult(model="point", domain="uv", flux_jy=flux, flux_err_jy=float(err),
                         parameters=("flux_jy",), values=np.array([flux]),
                         covariance=np.array([[err**2]]), chi2=chi2, dof=dof,
                         chi2_reduced=chi2 / dof, error_scale=scale, n_data=n_vis)
    if model != "gaussian":
        raise XstackError(f"unknown model {model!r} (use point or gaussian)")

    xmin, xmax = float(q2.min()), float(q2.max())
    if not xmax > 0 or xmax - xmin <= 1e-6 * xmax:
        raise XstackError("gaussian fit ill-conditioned: all visibilities have the same uv "
                          "distance, so flux and size cannot be separated (use the point model "
                          "or a wider uv range)")
    xref = float(np.sum(w * q2) / wsum)
    t = q2 / xref
    sw = np.sqrt(w)
    flux0, theta2_0 = linear_initial_guess(q2, re, w)
    fscale = max(abs(flux0), 1.0 / np.sqrt(wsum))
    # parameters: p0 = S / fscale, p1 = alpha = GAUSS_K theta^2 xref (the exponent at xref)
    alpha_min = -3.0 * xref / xmax  # keep exp() finite on the longest baseline

    def model_fn(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        e = np.exp(-p[1] * t)
        return p[0] * fscale * e, e

    def resid(p: np.ndarray) -> np.ndarray:
        m, _ = model_fn(p)
        return sw * (re - m)

    def jac(p: np.ndarray) -> np.ndarray:
        _, e = model_fn(p)
        return np.column_stack([-sw * fscale * e, sw * p[0] * fscale * t * e])

    p_init = np.array([flux0 / fscale, max(GAUSS_K * theta2_0 * xref, 0.0)])
    sol = least_squares(resid, p_init, jac=jac, bounds=([-np.inf, alpha_min], [np.inf, np.inf]),
                        method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12,
                        max_nfev=200)
    p = sol.x
    J = jac(p)
    JTJ = J.T @ J
    # conversion to physical parameters (flux Jy, theta^2 rad^2)
    D = np.diag([fscale, 1.0 / (GAUSS_K * xref)])
    try:
        eig = np.linalg.eigvalsh(JTJ / np.sqrt(np.outer(np.diag(JTJ), np.diag(JTJ))))
        cond = eig.max() / eig.min() if eig.min() > 0 else np.inf
    except np.linalg.LinAlgError:
        cond = np.inf
    if not np.isfinite(cond) or cond > 1e12:
        raise XstackError(f"gaussian fit ill-conditioned (condition number {cond:.3g}): the "
                          "data do not constrain flux and size separately (too short a uv "
                          "range, or no signal); use the point model or widen the uv range")
    cov_p = np.linalg.inv(JTJ)
    chi2 = float(np.sum(sol.fun**2)) + chi2_extra
    dof = max(n_vis + n_im - 2, 1)
    scale = float(np.sqrt(chi2 / dof)) if rescale_errors and chi2 > 0 else 1.0
    cov = D @ cov_p @ D * scale**2
    flux = float(p[0] * fscale)
    a_hat = float(p[1] / (GAUSS_K * xref))
    sig_s, sig_a = float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1]))
    if not flux > 0:
        raise XstackError(f"gaussian fit ill-conditioned: fitted flux {flux:.3g} Jy is not "
                          f"positive (error {sig_s:.3g} Jy), so the size is undefined; use the "
                          "point model")
    theta, theta_err = theta_and_error(a_hat, sig_a)
    theta_ul = theta_upper_limit(a_hat, sig_a)
    a2 = RAD2ARCSEC**2
    cov_out = cov * np.array([[1.0, a2], [a2, a2 * a2]])
    return FitResult(
        model="gaussian", domain="uv", flux_jy=flux, flux_err_jy=sig_s,
        fwhm_arcsec=theta * RAD2ARCSEC, fwhm_err_arcsec=theta_err * RAD2ARCSEC,
        fwhm_upper_limit_arcsec=theta_ul * RAD2ARCSEC, resolved=bool(a_hat > 3 * sig_a),
        parameters=("flux_jy", "fwhm2_arcsec2"), values=np.array([flux, a_hat * a2]),
        covariance=cov_out, chi2=chi2, dof=dof, chi2_reduced=chi2 / dof, error_scale=scale,
        n_data=n_vis,
        extra={"initial_flux_jy": float(flux0),
               "initial_fwhm_arcsec": float(np.sqrt(theta2_0) * RAD2ARCSEC),
               "condition_number": float(cond), "at_size_bound": bool(p[1] <= alpha_min * 0.999)})


@dataclass(frozen=True, kw_only=True)
class UvFitOptions:
    """Every option of :func:`fit_uv`, validated when built (before any data is read).

    The fields are the keyword arguments of :func:`fit_uv` (see there); ``uv_limits`` (not
    an argument) holds ``uvmin``/``uvmax`` parsed to ``(value, "m" | "lambda")`` or None.
    Each bad value raises an :class:`~xstack.errors.OptionError` naming the parameter.
    """

    model: str = "point"
    uvmin: Any = None
    uvmax: Any = None
    binned: bool = False
    nbins: int = 30
    rescale_errors: bool = True
    uv_limits: tuple[Any, Any] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: normalised values are set once, here
        set_(self, "model", _opt.choice("model", self.model, FIT_MODELS))
        set_(self, "binned", _opt.flag("binned", self.binned))
        set_(self, "rescale_errors", _opt.flag("rescale_errors", self.rescale_errors))
        set_(self, "nbins", _opt.integer("nbins", self.nbins))
        if self.binned and self.nbins < 3:
            raise OptionError(f"nbins must be at least 3 for a binned fit, got {self.nbins}",
                              option="nbins")
        limits = []
        for name in ("uvmin", "uvmax"):
            try:
                limits.append(parse_uv_limit(getattr(self, name)))
            except OptionError:
                raise
            except XstackError as exc:
                raise OptionError(f"{name}: {exc}", option=name) from None
        set_(self, "uv_limits", tuple(limits))

    def to_dict(self) -> dict[str, Any]:
        """The options as given, JSON-ready (uv limits as strings, like the result's)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.init}
        for name in ("uvmin", "uvmax"):
            out[name] = None if out[name] is None else str(out[name])
        return out


def fit_uv(stacked: Any, *, model: str = "point", uvmin: Any = None, uvmax: Any = None,
           binned: bool = False, nbins: int = 30, rescale_errors: bool = True) -> FitResult:
    """Fit a point or circular Gaussian model to stacked visibilities.

    Parameters
    ----------
    stacked
        A stacked store (path), :class:`xarray.DataTree`, Dataset, mapping of Datasets, or an
        object with a ``stacked`` attribute (a ``StackResult``). The source is taken to be at
        the phase center.
    model
        ``"point"`` (flux only) or ``"gaussian"`` (flux and FWHM).
    uvmin, uvmax
        uv-distance limits: a number (metres) or a string with units (``5000m``,
        ``23.8klambda``).
    binned
        Fit the binned uv-profile (``nbins`` bins linear in q) instead of the visibilities.
    nbins
        Number of bins of the binned fit (>= 3).
    rescale_errors
        Scale errors by sqrt(reduced chi^2) of the real and imaginary residuals.

    Returns
    -------
    FitResult
        ``flux_jy``, ``flux_err_jy``, ``fwhm_arcsec``, ``fwhm_err_arcsec``,
        ``fwhm_upper_limit_arcsec``, ``covariance`` (flux Jy, fwhm^2 arcsec^2), chi^2 ...

    Raises
    ------
    OptionError
        A bad option (before the data are read).
    NoDataError
        No usable visibilities, or none left in the uv range.
    XstackError
        An ill-conditioned fit.
    """
    options = UvFitOptions(model=model, uvmin=uvmin, uvmax=uvmax, binned=binned, nbins=nbins,
                           rescale_errors=rescale_errors)
    q2, re, w, chi2_im, n_total = _collect(stacked, options.uv_limits, uvmin, uvmax)
    res, extra = _compute(q2, re, w, chi2_im, options)
    return _assemble(res, extra, q2, n_total, options)


def _compute(q2: np.ndarray, re: np.ndarray, w: np.ndarray, chi2_im: float,
             options: UvFitOptions) -> tuple[FitResult, dict[str, Any]]:
    """The fit of the visibilities, of their binned uv-profile (``binned``), or of exact
    sufficient statistics in fine q^2 bins (more than :data:`MAX_UNBINNED` visibilities);
    returns the fit and the extras saying which."""
    n = q2.size
    model, rescale = options.model, options.rescale_errors
    if options.binned:
        q = np.sqrt(q2)
        edges = np.linspace(q.min(), q.max() * (1 + 1e-12), options.nbins + 1) ** 2
        xb, yb, wb, within = _binned_sums(q2, re, w, edges)
        res = fit_uv_arrays(xb, yb, wb, model=model, chi2_extra=chi2_im + within, n_vis=n,
                            rescale_errors=rescale)
        return res, {"profile": {"q_klambda": (np.sqrt(xb) / 1e3).tolist(),
                                 "re_jy": yb.tolist(), "err_jy": (1 / np.sqrt(wb)).tolist()}}
    if n > MAX_UNBINNED:
        lq = np.log(q2 + 1e-300)
        edges = np.exp(np.linspace(lq.min(), lq.max() + 1e-9, _FINE_BINS + 1))
        xb, yb, wb, within = _binned_sums(q2, re, w, edges)
        res = fit_uv_arrays(xb, yb, wb, model=model, chi2_extra=chi2_im + within, n_vis=n,
                            rescale_errors=rescale)
        return res, {"compressed_bins": int(xb.size)}
    return fit_uv_arrays(q2, re, w, model=model, chi2_extra=chi2_im,
                         rescale_errors=rescale), {}


def _assemble(res: FitResult, extra: dict[str, Any], q2: np.ndarray, n_total: int,
              options: UvFitOptions) -> FitResult:
    """The fit with its extras: how it was computed, the options as used (``binned``,
    ``uvmin``, ``uvmax``) and the uv range of the data."""
    res.extra.update(extra)
    opts = options.to_dict()
    res.options = opts
    res.extra.update({"binned": opts["binned"], "n_vis_before_uv_cut": int(n_total),
                      "uvmin": opts["uvmin"], "uvmax": opts["uvmax"],
                      "q_range_klambda": [float(np.sqrt(q2.min()) / 1e3),
                                          float(np.sqrt(q2.max()) / 1e3)]})
    return res
