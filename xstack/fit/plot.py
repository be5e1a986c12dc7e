"""Pictures of a fit (matplotlib, Agg backend): the data with the fitted model over them.

* :func:`plot_uv_fit`: the binned uv-profile of the stacked visibilities (Re V, Im V, 1σ
  errors, as :func:`xstack.uvstack.profile.uv_profile` makes it) with the fitted model curve,
  like the paper's Figs. 5–7.
* :func:`plot_image_fit`: stacked stamp, fitted model (Gaussian ⊗ dirty beam + constant) and
  residual, side by side.

Both curves/images are the fitted model evaluated with the parameters in the
:class:`~xstack.fit.result.FitResult` (θ² as fitted, possibly slightly negative), not a
re-derived approximation, so what is drawn is what was fitted.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from xstack.errors import XstackError
from xstack.fit.result import FitResult

RAD2ARCSEC = 180.0 / np.pi * 3600.0


def _figure_class() -> Any:
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    return Figure


def _fit_text(result: FitResult, scale: float, unit: str) -> str:
    """'S = 3.1 ± 0.4 µJy, FWHM = 1.5 ± 0.2″' (or FWHM < limit when unresolved); ``scale``
    is units per Jy (1e6 for µJy)."""
    text = f"S = {result.flux_jy * scale:.4g} ± {result.flux_err_jy * scale:.2g} {unit}"
    if result.model == "gaussian" and result.fwhm_arcsec is not None:
        if result.resolved:
            text += f", FWHM = {result.fwhm_arcsec:.3g} ± {result.fwhm_err_arcsec:.2g}″"
        else:
            text += f", FWHM < {result.fwhm_upper_limit_arcsec:.3g}″ (95 %)"
    return text


def uv_model(result: FitResult, q_klambda: np.ndarray) -> np.ndarray:
    """The fitted uv model (Jy) at uv distances ``q_klambda`` (kλ).

    Point: S everywhere; Gaussian: S exp(−π² θ² q² / (4 ln 2)) with the fitted θ²
    (``result.values[1]``, arcsec², used as fitted even if slightly negative).
    """
    from xstack.fit.models import gaussian_vis

    q = np.asarray(q_klambda, dtype=np.float64) * 1e3
    if result.model == "point":
        return np.full(q.shape, float(result.flux_jy))
    if result.model == "gaussian":
        theta2_rad2 = float(result.values[1]) / RAD2ARCSEC**2
        return gaussian_vis(q * q, float(result.flux_jy), theta2_rad2)
    raise XstackError(f"cannot draw the uv model of a {result.model!r} fit")


def _uv_fit_figure(table: Any, result: FitResult, *, title: str | None = None
                   ) -> tuple[Any, Any, float]:
    """Figure of a uv-profile table with the fitted model; returns (figure, axes, scale).

    ``scale`` converts Jy to the plotted unit; the model curve has ``gid="model"``.
    """
    from xstack.uvstack.profile import draw_uv_profile, profile_scale

    if result.domain != "uv":
        raise XstackError(f"plot_uv_fit needs a uv-domain fit, got {result.domain!r}")
    Figure = _figure_class()
    fig = Figure(figsize=(6.4, 4.4), dpi=110)
    ax = fig.add_subplot(111)
    scale, unit = profile_scale(table)
    # the model at q -> 0 can exceed every binned point (a resolved source), so it decides too
    if abs(result.flux_jy) > 1e-3:
        scale, unit = 1e3, "mJy"
    draw_uv_profile(ax, table, scale=scale, unit=unit)
    lo = float(np.nanmin(np.asarray(table["bin_lo_klambda"])))
    hi = float(np.nanmax(np.asarray(table["bin_hi_klambda"])))
    q = np.linspace(lo, hi, 256)
    name = "point" if result.model == "point" else "Gaussian"
    (line,) = ax.plot(q, uv_model(result, q) * scale, color="k", lw=1.5,
                      label=f"{name}: {_fit_text(result, scale, unit)}")
    line.set_gid("model")
    chi = f"χ²/dof = {result.chi2_reduced:.3g}, {result.n_data} visibilities"
    ax.set_title(f"{title}\n{chi}" if title else f"uv-domain {result.model} fit ({chi})",
                 fontsize=9)
    ax.legend(frameon=False, fontsize=8)
    fig.tight_layout()
    return fig, ax, scale


def plot_uv_fit(stacked: Any, result: FitResult, path: str | os.PathLike, *, bins: int = 30,
                uvmin: Any = None, uvmax: Any = None, title: str | None = None,
                overwrite: bool = False, table: Any = None) -> str:
    """Write a PNG of the binned uv-profile of ``stacked`` with the fitted model over it.

    Parameters
    ----------
    stacked
        What was fitted: a stacked store path, DataTree, Dataset, dict of partitions or a
        ``StackResult`` (anything :func:`~xstack.uvstack.profile.uv_profile` takes).
    result
        The uv-domain :class:`~xstack.fit.result.FitResult` of :func:`~xstack.fit.fit_uv`.
    path
        Output PNG; written atomically.
    bins
        Number of uv-distance bins of the profile (equal width in kλ).
    uvmin, uvmax
        uv range of the profile (``"20klambda"``, ``"5000m"``); give the fit's range.
    title
        First title line (default: the fit's domain and model).
    overwrite
        Replace an existing ``path``; otherwise an existing file is an error, left untouched.
    table
        A precomputed :func:`~xstack.uvstack.profile.uv_profile` table (then ``stacked``,
        ``bins``, ``uvmin`` and ``uvmax`` are not used).

    Returns
    -------
    str
        ``path``.

    Raises
    ------
    XstackError
        ``path`` exists without ``overwrite``, its directory does not exist, or ``result``
        is not a uv fit.
    """
    from xstack._atomic import check_output
    from xstack.uvstack.profile import save_png, uv_profile

    check_output(path, overwrite)  # before the (possibly long) profile pass
    if table is None:
        table = uv_profile(stacked, bins=bins, uvmin=uvmin, uvmax=uvmax)
    fig, _, _ = _uv_fit_figure(table, result, title=title)
    return save_png(fig, path, overwrite=overwrite)


def image_model(stamp_shape: tuple[int, int], psf: Any, result: FitResult) -> np.ndarray:
    """The fitted image model S (G_θ ⊗ PSF) + c (Jy/beam) on a stamp of ``stamp_shape``.

    Uses the pixel size, center and PSF normalisation recorded by
    :func:`~xstack.fit.imfit.fit_image` in ``result.extra`` and the fitted θ² as fitted.
    """
    from xstack.fit.imfit import PsfConvolver, read_psf

    if result.domain != "image":
        raise XstackError(f"need an image-domain fit, got {result.domain!r}")
    ex = result.extra
    pix = (float(ex["pixel_arcsec"][0]), float(ex["pixel_arcsec"][1]))
    center = (int(ex["center_pixel"][0]), int(ex["center_pixel"][1]))
    conv = PsfConvolver(read_psf(psf), tuple(stamp_shape), center, pix,
                      normalize=bool(ex.get("psf_normalized", True)))
    a = float(result.values[1]) if result.model == "gaussian" else 0.0
    base, _ = conv.model(a)
    return float(result.flux_jy) * base + float(ex.get("background_jy_per_beam", 0.0))


def _image_fit_figure(stamp: np.ndarray, model: np.ndarray, result: FitResult, *,
                      east_left: bool = False, fit_radius_arcsec: float | None = None,
                      title: str | None = None) -> tuple[Any, Any]:
    """Three-panel figure (stamp, model, residual); returns (figure, axes array).

    Each panel's image has ``gid`` ``"stamp"``, ``"model"`` or ``"residual"``; the first
    two share one colour scale.
    """
    from xstack.imstack.plot import unit_scale

    Figure = _figure_class()
    ny, nx = stamp.shape
    pix = result.extra["pixel_arcsec"]
    cy, cx = result.extra["center_pixel"]
    sx = -1.0 if east_left else 1.0
    # pixel edges in arcsec offsets from the stacking position; east to the left for sky images
    extent = (sx * (-cx - 0.5) * pix[0], sx * (nx - cx - 0.5) * pix[0],
              (-cy - 0.5) * pix[1], (ny - cy - 0.5) * pix[1])
    scale, unit = unit_scale(np.concatenate([stamp.ravel(), model.ravel()]))
    resid = stamp - model
    vmin = float(np.nanmin([np.nanmin(stamp), np.nanmin(model)])) / scale
    vmax = float(np.nanmax([np.nanmax(stamp), np.nanmax(model)])) / scale
    rmax = float(np.nanmax(np.abs(resid))) / scale if np.isfinite(resid).any() else 1.0
    rmax = rmax if rmax > 0 else 1.0
    fig = Figure(figsize=(13, 4.6), dpi=100)
    axes = fig.subplots(1, 3)
    panels = (("stamp", "stacked stamp", stamp, "viridis", vmin, vmax),
              ("model", "fitted model", model, "viridis", vmin, vmax),
              ("residual", "residual (stamp − model)", resid, "RdBu_r", -rmax, rmax))
    for ax, (gid, name, img, cmap, lo, hi) in zip(axes, panels):
        im = ax.imshow(img / scale, origin="lower", extent=extent, cmap=cmap, vmin=lo, vmax=hi,
                       interpolation="nearest")
        im.set_gid(gid)
        if fit_radius_arcsec is not None:
            from matplotlib.patches import Circle

            ax.add_patch(Circle((0.0, 0.0), float(fit_radius_arcsec), fill=False, ls="--",
                                edgecolor="white" if gid != "residual" else "k", lw=0.8))
        ax.set_xlabel("offset east (arcsec)" if east_left else "x offset (arcsec)")
        ax.set_ylabel("offset north (arcsec)" if east_left else "y offset (arcsec)")
        ax.set_title(name)
        fig.colorbar(im, ax=ax, label=f"{unit}/beam", shrink=0.85)
    text = _fit_text(result, 1.0 / scale, unit)  # unit_scale gives Jy per unit, not units per Jy
    if "background_jy_per_beam" in result.extra:
        text += (f", c = {result.extra['background_jy_per_beam'] / scale:.3g} ± "
                 f"{result.extra['background_err_jy_per_beam'] / scale:.2g} {unit}/beam")
    head = title or f"image-domain {result.model} fit (Gaussian ⊗ dirty beam + constant)"
    fig.suptitle(f"{head}\n{text}; χ²/dof = {result.chi2_reduced:.3g}", fontsize=10)
    fig.tight_layout()
    return fig, axes


def plot_image_fit(stamp: Any, result: FitResult, path: str | os.PathLike, *, psf: Any = None,
                   fit_radius_arcsec: float | None = None, title: str | None = None,
                   overwrite: bool = False) -> str:
    """Write a PNG of a stacked stamp, its fitted model and the residual.

    Parameters
    ----------
    stamp
        What was fitted: a stacked-stamp FITS path (primary image in Jy/beam, optional
        ``PSF`` extension) or a 2-D array (Jy/beam; then give ``psf``).
    result
        The image-domain :class:`~xstack.fit.result.FitResult` of
        :func:`~xstack.fit.fit_image` (its ``extra`` holds pixel size, center and PSF
        normalisation).
    path
        Output PNG; written atomically.
    psf
        The dirty beam used in the fit (FITS path or array); default: the stamp's ``PSF``
        extension.
    fit_radius_arcsec
        The fit radius (arcsec) used in the fit, drawn as a dashed circle.
    title
        First title line (default: the fit's domain and model).
    overwrite
        Replace an existing ``path``; otherwise an existing file is an error, left untouched.

    Returns
    -------
    str
        ``path``.

    Raises
    ------
    XstackError
        ``path`` exists without ``overwrite``, no PSF, or ``result`` is not an image fit.
    """
    from xstack._atomic import check_output
    from xstack.uvstack.profile import save_png

    check_output(path, overwrite)
    east_left = False
    if isinstance(stamp, (str, os.PathLike)):
        from astropy.io import fits
        from astropy.wcs import WCS

        from xstack.fit.imfit import read_stamp_fits

        info = read_stamp_fits(stamp)
        img = info["stamp"]
        if psf is None:
            psf = info["psf"]
        try:
            wcs = WCS(fits.getheader(Path(stamp))).celestial
            east_left = bool(wcs.has_celestial and wcs.pixel_scale_matrix[0, 0] < 0)
        except Exception:  # a header without a usable WCS still plots, in pixel-aligned axes
            east_left = False
    else:
        img = np.squeeze(np.asarray(stamp, dtype=np.float64))
    if psf is None:
        raise XstackError("a PSF (dirty beam) is needed to draw the image-fit model")
    model = image_model(img.shape, psf, result)
    fig, _ = _image_fit_figure(img, model, result, east_left=east_left,
                               fit_radius_arcsec=fit_radius_arcsec, title=title)
    return save_png(fig, path, overwrite=overwrite)
