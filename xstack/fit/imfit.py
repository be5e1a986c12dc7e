"""Image-domain PSF fitting of a stacked stamp (paper section 3.4).

The model is a circular Gaussian (integrated flux S, FWHM theta) convolved with the dirty
beam, plus a constant::

    M(x) = S (G_theta * PSF)(x - x0) + c

fitted to the stacked stamp by least squares (:func:`scipy.optimize.least_squares`, the
successor of the ``leastsq`` the paper used). The convolution is done in Fourier space with
the analytic transform of the Gaussian, exp(-pi^2 theta^2 f^2 / (4 ln 2)), so theta -> 0 is
smooth (the model becomes S PSF + c) and the size is fitted as theta^2 like in the uv fit.
With the PSF normalised to a peak of 1 and the stamp in Jy/beam, S is in Jy.

Errors. Pixels of a dirty image are not independent: for natural weighting the noise
covariance between two pixels is sigma^2 PSF(x_i - x_j) exactly (the noise autocorrelation
*is* the dirty beam). The unweighted least-squares estimate is kept (as in the paper) and
its covariance is the sandwich (J^T J)^-1 J^T C J (J^T J)^-1 with C = sigma^2 R, R the
correlation (``noise_correlation="psf"``: R from the PSF; ``"residual"``: from the
autocorrelation of the fit residuals; ``"none"``: white noise, which underestimates the
errors by roughly the square root of the number of pixels per beam). sigma^2 is estimated
from the residuals, unbiased for correlated noise: r^T r / (N - tr(H R)).

The model at a pixel needs the PSF out to that pixel's offset plus the Gaussian's extent. A
PSF no larger than the stamp (as ``xstack imstack`` writes it) lacks the sidelobes the
Gaussian spreads in from beyond its edge, so without a fit radius the Gaussian fit is made
again without the stamp's border, 3 sigma of the first fit's Gaussian (and a pixel) wide,
where the PSF does not cover the model (for a 1.5" source in 0.5" pixels the border held
0.3 % of the flux and 1 % of the size).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from xstack import _options as _opt
from xstack._vocabulary import FIT_MODELS, NOISE_CORRELATIONS
from xstack.errors import OptionError, XstackError
from xstack.fit.models import GAUSS_K, theta_and_error, theta_upper_limit
from xstack.fit.result import FitResult


def read_stamp_fits(path: str | os.PathLike) -> dict[str, Any]:
    """Read a stacked stamp FITS (primary image, optional ``PSF`` extension).

    Returns ``stamp``, ``psf`` (or None), ``pixel_arcsec`` (|dx|, |dy|), ``center``
    (0-based (y, x) of the reference pixel = the stacking position) and ``pbcor`` (the
    stamp's ``STPBCOR``: True if its flux is primary-beam corrected, None if it says nothing).
    """
    from astropy.io import fits
    from astropy.wcs import WCS

    path = Path(path)
    if not path.exists():
        raise XstackError(f"{path}: no such file")
    try:
        with fits.open(path) as hdul:
            header = hdul[0].header.copy()
            stamp = np.asarray(hdul[0].data, dtype=np.float64)
            psf = np.asarray(hdul["PSF"].data, dtype=np.float64) if "PSF" in hdul else None
            smeared = bool(hdul["PSF"].header.get("PSFSMEAR", False)) if "PSF" in hdul else False
    except (OSError, ValueError) as exc:
        raise XstackError(f"{path}: cannot read as FITS ({exc})") from None
    stamp = np.squeeze(stamp)
    if stamp.ndim != 2:
        raise XstackError(f"{path}: the primary HDU is not a 2-D image (shape {stamp.shape})")
    wcs = WCS(header).celestial
    scales = np.abs(np.diag(wcs.pixel_scale_matrix)) * 3600.0
    center = (int(round(header.get("CRPIX2", stamp.shape[0] // 2 + 1))) - 1,
              int(round(header.get("CRPIX1", stamp.shape[1] // 2 + 1))) - 1)
    pbcor = header.get("STPBCOR")
    return {"stamp": stamp, "psf": None if psf is None else np.squeeze(psf),
            "psf_smeared": smeared, "pbcor": None if pbcor is None else bool(pbcor),
            "pixel_arcsec": (float(scales[0]), float(scales[1])), "center": center}


def read_psf(psf: Any, with_flag: bool = False) -> Any:
    """The PSF array (and whether it is an imstack PSF with pixelisation smear)."""
    smeared = False
    if isinstance(psf, (str, os.PathLike)):
        from astropy.io import fits

        p = Path(psf)
        if not p.exists():
            raise XstackError(f"{p}: no such PSF file")
        with fits.open(p) as hdul:
            hdu = hdul["PSF"] if "PSF" in hdul else hdul[0]
            smeared = bool(hdu.header.get("PSFSMEAR", False))
            arr = np.squeeze(np.asarray(hdu.data, dtype=np.float64))
    else:
        # an ImstackResult.psf_stamp says so in its attrs, as the FITS PSF extension does
        smeared = bool(getattr(psf, "attrs", {}).get("psf_smeared", False))
        arr = np.asarray(psf, dtype=np.float64)
    return (arr, smeared) if with_flag else arr


class PsfConvolver:
    """Convolutions with the PSF on a padded grid aligned with the stamp."""

    def __init__(self, psf: np.ndarray, shape: tuple[int, int], center: tuple[int, int],
                 pixel_arcsec: tuple[float, float], normalize: bool = True):
        if psf.ndim != 2 or not np.all(np.isfinite(psf)):
            raise XstackError("the PSF must be a finite 2-D image")
        peak = np.unravel_index(np.argmax(psf), psf.shape)
        pmax = psf[peak]
        if not pmax > 0:
            raise XstackError("the PSF has no positive peak")
        self.peak = float(pmax)
        if normalize:
            psf = psf / pmax
        ny, nx = shape
        # padded FFT grid: the PSF wholly, plus the stamp, without wrap-around
        Ny = int(2 ** np.ceil(np.log2(psf.shape[0] + ny)))
        Nx = int(2 ** np.ceil(np.log2(psf.shape[1] + nx)))
        grid = np.zeros((Ny, Nx))
        # place the PSF so that its peak sits at pixel (0, 0) (periodic)
        iy = (np.arange(psf.shape[0]) - peak[0]) % Ny
        ix = (np.arange(psf.shape[1]) - peak[1]) % Nx
        grid[np.ix_(iy, ix)] = psf
        self.psf_ft = np.fft.rfft2(grid)
        fy = np.fft.fftfreq(Ny) / pixel_arcsec[1]
        fx = np.fft.rfftfreq(Nx) / pixel_arcsec[0]
        self.f2 = fy[:, None] ** 2 + fx[None, :] ** 2   # (cycles/arcsec)^2
        self.N = (Ny, Nx)
        self.shape = shape
        self.center = center
        # stamp pixel (y, x) <-> offset (y - cy, x - cx) from the source
        self.oy = (np.arange(ny) - center[0]) % Ny
        self.ox = (np.arange(nx) - center[1]) % Nx

    def model(self, a_arcsec2: float) -> tuple[np.ndarray, np.ndarray]:
        """(G*PSF) and d(G*PSF)/da on the stamp, for theta^2 = a (arcsec^2)."""
        g = np.exp(-GAUSS_K * a_arcsec2 * self.f2)
        img = np.fft.irfft2(self.psf_ft * g, s=self.N)
        dimg = np.fft.irfft2(self.psf_ft * g * (-GAUSS_K * self.f2), s=self.N)
        sel = np.ix_(self.oy, self.ox)
        return img[sel], dimg[sel]

    def correlate(self, img: np.ndarray, rho_ft: np.ndarray | None = None) -> np.ndarray:
        """R img: the stamp-sized image convolved with the noise correlation (PSF default)."""
        grid = np.zeros(self.N)
        grid[np.ix_(self.oy, self.ox)] = img
        ft = self.psf_ft if rho_ft is None else rho_ft
        out = np.fft.irfft2(np.fft.rfft2(grid) * ft, s=self.N)
        return out[np.ix_(self.oy, self.ox)]


@dataclass(frozen=True, kw_only=True)
class ImageFitOptions:
    """Every option of :func:`fit_image`, validated when built (before any data is read).

    The fields are the keyword arguments of :func:`fit_image` (see there for their meaning);
    the stamp and the PSF are inputs, not options. ``pixel_arcsec`` is stored as the pair
    (|dx|, |dy|) in arcsec and ``center`` as a pair of ints; each bad value raises an
    :class:`~xstack.errors.OptionError` naming the parameter.
    """

    pixel_arcsec: float | tuple[float, float] | None = None
    center: tuple[int, int] | None = None
    model: str = "gaussian"
    fit_radius_arcsec: float | None = None
    background: bool = True
    noise_correlation: str = "psf"
    sigma_jy: float | None = None
    normalize_psf: bool | None = None

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: normalised values are set once, here
        set_(self, "model", _opt.choice("model", self.model, FIT_MODELS))
        set_(self, "noise_correlation",
             _opt.choice("noise_correlation", self.noise_correlation, NOISE_CORRELATIONS))
        pix = self.pixel_arcsec
        if pix is not None:
            pair = (pix, pix) if np.isscalar(pix) else tuple(pix)
            if len(pair) != 2:
                raise OptionError(f"pixel_arcsec must be one value or a pair (|dx|, |dy|), "
                                  f"got {pix!r}", option="pixel_arcsec")
            set_(self, "pixel_arcsec", tuple(_opt.positive("pixel_arcsec", p, optional=False)
                                             for p in pair))
        if self.center is not None:
            c = tuple(self.center) if not np.isscalar(self.center) else (self.center,)
            if len(c) != 2:
                raise OptionError(f"center must be a (y, x) pixel pair, got {self.center!r}",
                                  option="center")
            set_(self, "center", tuple(_opt.integer("center", v) for v in c))
        set_(self, "fit_radius_arcsec", _opt.positive("fit_radius_arcsec", self.fit_radius_arcsec))
        set_(self, "background", _opt.flag("background", self.background))
        set_(self, "sigma_jy", _opt.positive("sigma_jy", self.sigma_jy))
        set_(self, "normalize_psf", _opt.flag("normalize_psf", self.normalize_psf, optional=True))

    @property
    def n_parameters(self) -> int:
        """Number of fitted parameters: S, theta^2 (gaussian) and c (background)."""
        return (2 if self.model == "gaussian" else 1) + int(self.background)

    def to_dict(self) -> dict[str, Any]:
        """The options as a JSON-ready dict (tuples as lists)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        return {k: list(v) if isinstance(v, tuple) else v for k, v in out.items()}


@dataclass(frozen=True)
class _Inputs:
    """The normalised inputs of an image fit: stamp, PSF and their geometry."""

    img: np.ndarray              # the stamp, Jy/beam
    psf: np.ndarray              # the dirty beam on the stamp's pixel grid
    pix: tuple[float, float]     # (|dx|, |dy|), arcsec
    center: tuple[int, int]      # 0-based (y, x) of the stacking position
    normalize: bool              # divide the PSF by its peak
    pb_convention: str           # "corrected", "not corrected" or "not stated"


@dataclass(frozen=True)
class _Plan:
    """What the fit works on: the pixels used, the PSF convolver, scales and start values."""

    conv: PsfConvolver
    use: np.ndarray              # pixels entering the fit
    data: np.ndarray             # img[use]
    amp_scale: float             # flux scale (Jy) making S and c of order 1
    s2: float                    # size scale (arcsec^2): theta^2 = alpha s2
    model: str
    background: bool
    psf_normalized: bool         # the PSF was divided by its peak
    p0: np.ndarray               # initial parameters (scaled)
    lower: list[float]           # lower bounds (scaled)

    @property
    def npix(self) -> int:
        return int(self.data.size)

    def unpack(self, p: np.ndarray) -> tuple[float, float, float]:
        """(S Jy, theta^2 arcsec^2, c Jy/beam) from the scaled parameters."""
        S = p[0] * self.amp_scale
        a = p[1] * self.s2 if self.model == "gaussian" else 0.0
        c = p[-1] * self.amp_scale if self.background else 0.0
        return S, a, c

    def model_and_jac(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The model on the used pixels and its Jacobian in the scaled parameters."""
        S, a, c = self.unpack(p)
        base, dbase = self.conv.model(a)
        cols = [base[self.use] * self.amp_scale]
        if self.model == "gaussian":
            cols.append(S * dbase[self.use] * self.s2)
        if self.background:
            cols.append(np.full(self.npix, self.amp_scale))
        return S * base[self.use] + c, np.column_stack(cols)

    def resid(self, p: np.ndarray) -> np.ndarray:
        return self.model_and_jac(p)[0] - self.data

    def jac(self, p: np.ndarray) -> np.ndarray:
        return self.model_and_jac(p)[1]


@dataclass(frozen=True)
class _Measured:
    """The solved fit: scaled parameters, residuals and the covariance pieces."""

    p: np.ndarray
    fun: np.ndarray              # residuals on the used pixels
    JTJ_inv: np.ndarray
    JRJ: np.ndarray
    cond: float
    dof_eff: float               # N - tr(H R)
    rss: float
    sigma2: float


def fit_image(stamp: Any, *, psf: Any = None, pixel_arcsec: float | tuple[float, float] | None = None,
              center: tuple[int, int] | None = None, model: str = "gaussian",
              fit_radius_arcsec: float | None = None, background: bool = True,
              noise_correlation: str = "psf", sigma_jy: float | None = None,
              normalize_psf: bool | None = None) -> FitResult:
    """Fit a circular Gaussian convolved with the dirty beam (plus a constant) to a stamp.

    Parameters
    ----------
    stamp
        A stacked-stamp FITS path (as written by ``xstack imstack``: primary image in
        Jy/beam, ``PSF`` extension), or a 2-D array (then give ``psf`` and ``pixel_arcsec``).
    psf
        Dirty beam: FITS path or 2-D array on the stamp's pixel grid (any size; its peak is
        taken as its center). Default: the stamp file's ``PSF`` extension.
    pixel_arcsec
        Pixel size (|dx|, |dy|) or a single value, arcsec (arrays only).
    center
        0-based (y, x) pixel of the stacking position; default: the reference pixel of a
        FITS stamp, else ``(ny // 2, nx // 2)``.
    model
        ``"gaussian"`` (flux, FWHM) or ``"point"`` (flux only: S PSF + c).
    fit_radius_arcsec
        Fit only pixels within this distance of the center, arcsec (default: the stamp,
        less any border where the Gaussian model reaches past the PSF; module notes).
    background
        Fit the constant c (the paper's model); False fixes c = 0.
    noise_correlation
        ``"psf"`` (default), ``"residual"`` or ``"none"``; see the module notes.
    sigma_jy
        Pixel noise rms (Jy/beam) if known; default: estimated from the residuals.
    normalize_psf
        Divide the PSF by its peak. Default: yes, except for an imstack PSF with nearest-pixel
        smear (``PSFSMEAR = T``, or ``psf_stamp.attrs["psf_smeared"]``; peak < 1), kept so
        that S is the true mean flux (docs/imstack.md); a plain array is divided. The noise correlation
        always uses the PSF scaled to a peak of 1.

    Returns
    -------
    FitResult
        ``domain="image"``; ``extra`` holds ``background_jy_per_beam`` and its error,
        ``noise_correlation``, ``sigma_jy_per_beam``, ``effective_dof`` and
        ``primary_beam`` (the stamp's convention: ``"corrected"`` for an ``xstack imstack``
        stamp, whose ``STPBCOR = T`` says its flux is primary-beam corrected; ``"not stated"``
        for an array or a FITS stamp without it, which is fitted as is with a warning).

    Raises
    ------
    OptionError
        A bad option (before the stamp is read).
    XstackError
        An unreadable stamp or PSF, too few pixels, or an ill-conditioned fit.
    """
    options = ImageFitOptions(pixel_arcsec=pixel_arcsec, center=center, model=model,
                              fit_radius_arcsec=fit_radius_arcsec, background=background,
                              noise_correlation=noise_correlation, sigma_jy=sigma_jy,
                              normalize_psf=normalize_psf)
    inputs = _load(stamp, psf, options)
    plan, measured = _solve(inputs, options)
    return _assemble(inputs, plan, measured, options)


def _solve(inputs: _Inputs, options: ImageFitOptions) -> tuple[_Plan, _Measured]:
    """Plan and solve the fit; for the Gaussian model with no fit radius, again without the
    pixels whose model reaches past the PSF given (:func:`_uncovered`)."""
    plan = _plan(inputs, options)
    measured = _compute(plan, options)
    if options.fit_radius_arcsec is None and options.model == "gaussian":
        # the model at a pixel near the PSF's edge lacks the PSF beyond it, convolved with the
        # Gaussian (a stamp-sized PSF, as xstack imstack writes: 0.3 % of the flux and 1 % of
        # the size of a 1.5" source in 0.5" pixels)
        _, a_hat, _ = plan.unpack(measured.p)
        outside = _uncovered(inputs, float(np.sqrt(max(a_hat, 0.0))))
        if (plan.use & outside).any() and (plan.use & ~outside).sum() > 4 * options.n_parameters:
            plan = _plan(inputs, options, exclude=outside, conv=plan.conv)
            measured = _compute(plan, options)
    return plan, measured


def _uncovered(inputs: _Inputs, fwhm_arcsec: float) -> np.ndarray:
    """Stamp pixels whose model (a Gaussian of ``fwhm_arcsec`` convolved with the PSF) reaches
    past the PSF given: those within 3 sigma of the Gaussian (and one pixel) of its edge."""
    ny, nx = inputs.img.shape
    peak = np.unravel_index(np.argmax(inputs.psf), inputs.psf.shape)
    sigma = fwhm_arcsec / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    ky = int(np.ceil(3.0 * sigma / inputs.pix[1])) + 1
    kx = int(np.ceil(3.0 * sigma / inputs.pix[0])) + 1
    # offsets from the center the PSF covers: -peak ... size - 1 - peak
    oy = np.arange(ny) - inputs.center[0]
    ox = np.arange(nx) - inputs.center[1]
    in_y = (oy - ky >= -peak[0]) & (oy + ky <= inputs.psf.shape[0] - 1 - peak[0])
    in_x = (ox - kx >= -peak[1]) & (ox + kx <= inputs.psf.shape[1] - 1 - peak[1])
    return ~(in_y[:, None] & in_x[None, :])


def _load(stamp: Any, psf: Any, options: ImageFitOptions) -> _Inputs:
    """Read the stamp and the PSF (FITS paths or arrays) and settle pixel size, center, PSF
    normalisation and primary-beam convention; warns when a FITS stamp does not state the
    latter."""
    smeared = False
    pb_convention = "not stated"
    center = options.center
    if isinstance(stamp, (str, os.PathLike)):
        info = read_stamp_fits(stamp)
        if info["pbcor"] is None:
            # stacklevel 3: the warning points at the caller of fit_image
            warnings.warn(f"{stamp}: the stamp does not say whether its flux is primary-beam "
                          "corrected (no STPBCOR): fitted as is; stack with xstack imstack, "
                          "which measures corrected fluxes and records it", stacklevel=3)
        else:
            pb_convention = "corrected" if info["pbcor"] else "not corrected"
        img = info["stamp"]
        pix = info["pixel_arcsec"]
        center = info["center"] if center is None else center
        if psf is None:
            psf = info["psf"]
            smeared = info["psf_smeared"]
            if psf is None:
                raise XstackError(f"{stamp}: no PSF extension; give the dirty beam with psf=",
                                  option="psf")
    else:
        img = np.asarray(stamp, dtype=np.float64)
        if options.pixel_arcsec is None:
            raise OptionError("pixel_arcsec is needed when the stamp is an array",
                              option="pixel_arcsec")
        pix = options.pixel_arcsec
    if psf is None:
        raise XstackError("a PSF (dirty beam) is needed for the image fit", option="psf")
    img = np.squeeze(img)
    if img.ndim != 2:
        raise XstackError(f"the stamp must be a 2-D image, got shape {img.shape}")
    ny, nx = img.shape
    center = (ny // 2, nx // 2) if center is None else (int(center[0]), int(center[1]))
    psf_arr, smeared_file = read_psf(psf, with_flag=True)
    smeared = smeared or smeared_file
    normalize = (not smeared) if options.normalize_psf is None else options.normalize_psf
    return _Inputs(img=img, psf=psf_arr, pix=pix, center=center, normalize=normalize,
                   pb_convention=pb_convention)


def _plan(inputs: _Inputs, options: ImageFitOptions, exclude: np.ndarray | None = None,
          conv: PsfConvolver | None = None) -> _Plan:
    """The pixels to fit (less ``exclude``), the PSF convolver (``conv``, made if not given),
    the parameter scales and the start values (a linear fit of the point model S PSF + c,
    size 0)."""
    img, pix, center = inputs.img, inputs.pix, inputs.center
    ny, nx = img.shape
    if conv is None:
        conv = PsfConvolver(inputs.psf, img.shape, center, pix, normalize=inputs.normalize)
    yy, xx = np.mgrid[0:ny, 0:nx]
    r = np.hypot((yy - center[0]) * pix[1], (xx - center[1]) * pix[0])
    use = np.isfinite(img)
    if options.fit_radius_arcsec is not None:
        use &= r <= options.fit_radius_arcsec
    if exclude is not None:
        use &= ~exclude
    npix = int(use.sum())
    if npix <= options.n_parameters + 1:
        raise XstackError(f"only {npix} usable pixels to fit (fit radius too small?)")
    data = img[use]
    psf0, _ = conv.model(0.0)
    amp_scale = max(float(np.max(np.abs(data))), 1e-30)
    # size parameter: alpha = theta^2 / s2 with s2 = beam area in arcsec^2 (order 1)
    s2 = float(max(pix[0] * pix[1] * max(np.sum(psf0 > 0.5 * psf0.max()), 1), pix[0] * pix[1]))
    gaussian, background = options.model == "gaussian", options.background
    A0 = np.column_stack([psf0[use]] + ([np.ones(npix)] if background else []))
    lin, *_ = np.linalg.lstsq(A0, data, rcond=None)
    p0 = [lin[0] / amp_scale] + ([0.1] if gaussian else []) + \
         ([lin[-1] / amp_scale] if background else [])
    # theta^2 may go below 0 (noise) but not so far that exp(+...) explodes at Nyquist
    a_min = -2.0 / (GAUSS_K * float(conv.f2.max()))
    lower = [-np.inf] + ([a_min / s2] if gaussian else []) + ([-np.inf] if background else [])
    return _Plan(conv=conv, use=use, data=data, amp_scale=amp_scale, s2=s2,
                 model=options.model, background=background, psf_normalized=inputs.normalize,
                 p0=np.array(p0), lower=lower)


def _compute(plan: _Plan, options: ImageFitOptions) -> _Measured:
    """Solve the least-squares problem, check its conditioning and compute the pieces of the
    sandwich covariance and the noise level (see the module notes)."""
    from scipy.optimize import least_squares

    # residuals in units of the stamp's peak (amp_scale): least_squares' gtol is absolute on
    # J^T r, which in Jy/beam starts below it for a µJy stack; the fit then stopped after two
    # evaluations near its start (a noiseless point source of 3 µJy fitted 0.41" wide, a
    # 1.5" Gaussian 1.47", flux 1.6 % high), where a 1 Jy source converged
    unit = plan.amp_scale
    sol = least_squares(lambda p: plan.resid(p) / unit, plan.p0,
                        jac=lambda p: plan.jac(p) / unit, method="trf", x_scale="jac",
                        bounds=(plan.lower, [np.inf] * len(plan.p0)), xtol=1e-12, ftol=1e-12,
                        gtol=1e-12, max_nfev=500)
    fun = sol.fun * unit
    J = plan.jac(sol.x)
    JTJ = J.T @ J
    try:
        JTJ_inv = np.linalg.inv(JTJ)
        d = np.sqrt(np.diag(JTJ))
        cond = np.linalg.cond(JTJ / np.outer(d, d))
    except np.linalg.LinAlgError:
        cond = np.inf
    if not np.isfinite(cond) or cond > 1e12:
        raise XstackError(f"image fit ill-conditioned (condition number {cond:.3g}): the stamp does "
                          "not constrain the parameters (stamp too small for the beam?)")
    JRJ = J.T @ _correlated_jacobian(plan, J, fun, options.noise_correlation)
    trHR = float(np.trace(JTJ_inv @ JRJ))
    rss = float(np.sum(fun**2))
    dof_eff = plan.npix - trHR
    if options.sigma_jy is not None:
        sigma2 = options.sigma_jy ** 2
    else:
        if dof_eff <= 0:
            raise XstackError("too few independent pixels to estimate the noise; give sigma_jy",
                              option="sigma_jy")
        sigma2 = rss / dof_eff
    return _Measured(p=sol.x, fun=fun, JTJ_inv=JTJ_inv, JRJ=JRJ, cond=float(cond),
                     dof_eff=dof_eff, rss=rss, sigma2=sigma2)


def _correlated_jacobian(plan: _Plan, J: np.ndarray, fun: np.ndarray,
                         noise_correlation: str) -> np.ndarray:
    """R J: each Jacobian column convolved with the noise correlation R (peak 1): the PSF,
    the autocorrelation of the residuals ``fun``, or the identity."""
    conv, use = plan.conv, plan.use
    if noise_correlation == "none":
        return J.copy()
    rho_ft = None
    if noise_correlation == "residual":
        res_full = np.zeros(conv.shape)
        res_full[use] = fun
        grid = np.zeros(conv.N)
        grid[np.ix_(conv.oy, conv.ox)] = res_full
        ft = np.fft.rfft2(grid)
        acf = np.fft.irfft2(np.abs(ft) ** 2, s=conv.N)
        rho_ft = np.fft.rfft2(acf / acf[0, 0])
    RJ = np.empty_like(J)
    # the noise correlation is the dirty beam with peak 1 (whatever the PSF's scale)
    rho = conv.psf_ft / conv.peak if (rho_ft is None and not plan.psf_normalized) else rho_ft
    for i in range(J.shape[1]):
        col = np.zeros(conv.shape)
        col[use] = J[:, i]
        RJ[:, i] = conv.correlate(col, rho)[use]
    return RJ


def _assemble(inputs: _Inputs, plan: _Plan, measured: _Measured,
              options: ImageFitOptions) -> FitResult:
    """The :class:`FitResult`: physical parameters and covariance, goodness of fit, the
    extras (options as used, noise, PSF) and, for the Gaussian model, the size."""
    gaussian, background = options.model == "gaussian", options.background
    sigma2, rss, dof_eff = measured.sigma2, measured.rss, measured.dof_eff
    cov_p = sigma2 * measured.JTJ_inv @ measured.JRJ @ measured.JTJ_inv
    # physical parameters: (S Jy, theta^2 arcsec^2, c Jy/beam)
    scales = [plan.amp_scale] + ([plan.s2] if gaussian else []) + \
             ([plan.amp_scale] if background else [])
    D = np.diag(scales)
    cov = D @ cov_p @ D
    S, a_hat, c = plan.unpack(measured.p)
    names = ["flux_jy"] + (["fwhm2_arcsec2"] if gaussian else []) + \
            (["background_jy_per_beam"] if background else [])
    values = [S] + ([a_hat] if gaussian else []) + ([c] if background else [])
    extra = {"noise_correlation": options.noise_correlation,
             "sigma_jy_per_beam": float(np.sqrt(sigma2)), "primary_beam": inputs.pb_convention,
             "psf_peak": plan.conv.peak, "psf_normalized": inputs.normalize,
             "effective_dof": float(dof_eff), "condition_number": measured.cond,
             "pixel_arcsec": list(inputs.pix), "center_pixel": list(inputs.center)}
    if background:
        extra["background_jy_per_beam"] = float(c)
        extra["background_err_jy_per_beam"] = float(np.sqrt(cov[-1, -1]))
    result = FitResult(model=options.model, domain="image", flux_jy=float(S),
                       flux_err_jy=float(np.sqrt(cov[0, 0])), parameters=tuple(names),
                       values=np.array(values), covariance=cov, chi2=rss / sigma2,
                       dof=int(round(dof_eff)), chi2_reduced=rss / sigma2 / max(dof_eff, 1),
                       error_scale=1.0, n_data=plan.npix, extra=extra,
                       options=options.to_dict())
    if gaussian:
        if not S > 0:
            raise XstackError(f"gaussian fit ill-conditioned: fitted flux {S:.3g} Jy is not "
                              f"positive (error {np.sqrt(cov[0, 0]):.3g} Jy), so the size is "
                              "undefined; use the point model")
        sig_a = float(np.sqrt(cov[1, 1]))
        theta, theta_err = theta_and_error(a_hat, sig_a)
        result.fwhm_arcsec = theta
        result.fwhm_err_arcsec = theta_err
        result.fwhm_upper_limit_arcsec = theta_upper_limit(a_hat, sig_a)
        result.resolved = bool(a_hat > 3 * sig_a)
    return result
