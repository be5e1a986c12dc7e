"""Local noise sigma_k around stacking positions, measured in a residual image (paper §3.2).

The paper weights image stamps by W_k = 1/sigma_k^2 with sigma_k "the brightness standard
deviation" of a stamp of ~300 beam areas around position k, outside a central circle of
radius BMAJ, and uses "the same local noise estimators" for uv-stacking (§3.3). This module
measures that sigma_k for :func:`xstack.uvstack.stack.stack_uv` (``weighting="sigma2"``,
``noise_image=``). Stamps, the central mask and the paper's plain standard deviation come
from :mod:`xstack.imstack.kernels`; images are read by :func:`xstack.imstack.io.read_image`
(any FITS image with a celestial WCS, an HDU, or an in-memory
:class:`xstack.imaging.image.ImageResult`).

The default estimator is a sigma-clipped standard deviation (see :data:`ESTIMATORS`): on
Gaussian noise it agrees with the paper's standard deviation and is almost as precise,
while a faint source, a clean residual or an artefact that happens to fall in the stamp
does not inflate sigma_k (and so does not down-weight the position for a reason unrelated
to its noise).
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from xstack import _vocabulary
from xstack.errors import XstackError
from xstack.imaging.fitsio import pb_corrected_from_header
from xstack.imstack import kernels
from xstack.imstack.io import ImageInfo, read_image

# the estimators and their constants live with the other stamp kernels (image-stacking
# measures its weights the same way); re-exported here, their long-standing home
ESTIMATORS = kernels.NOISE_ESTIMATORS
CLIP_SIGMA = kernels.CLIP_SIGMA
CLIP_MAXITER = kernels.CLIP_MAXITER
CLIP_CORRECTION = kernels.CLIP_CORRECTION
MAD_TO_SIGMA = _vocabulary.MAD_TO_SIGMA
STAMP_BEAM_AREAS = kernels.STAMP_BEAM_AREAS

#: Default stamp (pixels) and mask radius (pixels) for an image without a restoring beam,
#: the paper's 64 x 64 stamps (made odd, 65) and imstack's 5-pixel fallback mask.
DEFAULT_STAMP_PIXELS = 64
DEFAULT_MASK_PIXELS = 5.0

#: Least fraction of a stamp's pixels outside the mask that must be finite (on the image and
#: not blanked). A position at the very corner of an image keeps about a quarter of its stamp.
MIN_FRACTION = 0.25


@dataclass
class LocalNoise:
    """Local-noise estimates of :func:`measure_local_noise`.

    Attributes
    ----------
    sigma
        float64 (n,): sigma_k in the image unit (``unit``, normally Jy/beam); NaN for the
        rows in ``bad_rows``.
    n_pixels
        int64 (n,): finite stamp pixels outside the central mask that entered sigma_k.
    bad_rows
        0-based rows without a usable estimate; ``reasons`` says why, one entry per row.
    stamp_size
        Stamp side, pixels.
    mask_radius_arcsec
        Radius of the central mask, arcsec.
    min_pixels
        Least finite pixels a stamp needs outside the mask.
    estimator
        One of :data:`ESTIMATORS`.
    unit
        BUNIT of the image ("" if absent).
    name
        The image's label (file name) for messages and provenance.
    pbcor
        ``XSPBCOR`` of an xstack image (True: primary-beam corrected), None if unknown.
    beam
        Where the primary beam A came from when sigma_k were measured where the noise is
        flat and divided by A_k (so that they are the noise of the corrected flux): for an
        image that says it is not corrected, on the image; for a corrected one whose beam
        is known, on the image times A. None when sigma_k are the image's own (no beam).
    """

    sigma: np.ndarray
    n_pixels: np.ndarray
    bad_rows: np.ndarray
    reasons: list[str]
    stamp_size: int
    mask_radius_arcsec: float
    min_pixels: int
    estimator: str
    unit: str
    name: str
    pbcor: bool | None = None
    beam: str | None = None

    def describe_bad(self, rows: np.ndarray | None = None, limit: int = 5) -> str:
        """One-line message naming the (1-based) rows without an estimate, with the reason."""
        rows = self.bad_rows if rows is None else np.asarray(rows, dtype=np.int64)
        why = dict(zip(self.bad_rows.tolist(), self.reasons))
        parts = [f"row {r + 1} {why.get(int(r), 'no estimate')}" for r in rows[:limit]]
        more = f" and {rows.size - limit} more" if rows.size > limit else ""
        return (f"noise image {self.name}: no local-noise estimate for {rows.size} of "
                f"{self.sigma.size} positions: {'; '.join(parts)}{more}")

    def provenance(self) -> dict[str, Any]:
        """JSON-ready record of how sigma_k was measured."""
        return {"image": self.name, "unit": self.unit, "estimator": self.estimator,
                "stamp_size": int(self.stamp_size),
                "mask_radius_arcsec": float(self.mask_radius_arcsec),
                "min_pixels": int(self.min_pixels), "pbcor": self.pbcor,
                "divided_by_beam": self.beam}


def _positions_deg(positions: Any) -> tuple[np.ndarray, np.ndarray]:
    """(ra, dec) in degrees from a catalog path, Table or an (N, 2) array in degrees."""
    from xstack.imstack.stack import _positions  # the catalog rules of image-stacking

    ra, dec, _ = _positions(positions)
    return ra, dec


def _label(image: Any) -> str | None:
    if isinstance(image, (str, os.PathLike)):
        return str(image)
    if isinstance(image, ImageInfo):
        return image.name
    return None


def measure_local_noise(image: Any, positions: Any, *, stamp_size: int | None = None,
                        mask_radius_arcsec: float | None = None, estimator: str = "clipped",
                        min_fraction: float = MIN_FRACTION) -> LocalNoise:
    """Local noise sigma_k of a residual image around each position, with diagnostics.

    Parameters
    ----------
    image
        The residual image: a FITS path, an astropy image HDU, an in-memory
        :class:`xstack.imaging.image.ImageResult` or an :class:`xstack.imstack.io.ImageInfo`.
        Any celestial WCS; degenerate frequency/Stokes axes are dropped.
    positions
        Catalog path or :class:`astropy.table.Table` (``ra``, ``dec`` in degrees), or an
        (N, 2) array of (ra, dec) in degrees.
    stamp_size
        Stamp side in pixels, centered on the pixel nearest to each position. Default: about
        :data:`STAMP_BEAM_AREAS` beam areas (paper §3.2), odd, at least 4 mask radii and at
        most the image; 65 pixels (the paper's 64, made odd so the mask is centered) if the
        image has no beam.
    mask_radius_arcsec
        Radius of the central circle left out of sigma_k (the stacked source and its main
        lobe). Default: the beam's major axis BMAJ (paper §3.2); 5 pixels without a beam.
    estimator
        ``"clipped"`` (default), ``"mad"`` or ``"std"``; see :data:`ESTIMATORS`.
    min_fraction
        A stamp needs finite pixels (on the image, not blanked) in at least this fraction of
        its area outside the mask, and at least ``imstack.kernels.MIN_NOISE_PIXELS``.

    Returns
    -------
    LocalNoise
        ``sigma`` (image unit, Jy/beam for a residual image; NaN where there is no estimate)
        and the rows without one: positions off the image, on a blanked pixel, with too few
        finite pixels, or in a constant (zero-noise) stamp.

    Raises
    ------
    XstackError
        Unreadable image or image without a celestial WCS, a unit that is not per beam,
        bad options or positions.
    """
    if estimator not in ESTIMATORS:
        raise XstackError(f"unknown noise estimator {estimator!r} (use {', '.join(ESTIMATORS)})")
    if not 0.0 < float(min_fraction) <= 1.0:
        raise XstackError(f"min_fraction must be in (0, 1], got {min_fraction}")
    info = read_image(image, name=_label(image) or "<in-memory image>")
    bunit = info.bunit
    if bunit and not bunit.replace(" ", "").lower().endswith("/beam"):
        raise XstackError(f"noise image {info.name}: BUNIT is {bunit!r}; sigma_k needs a residual "
                          "image in Jy/beam (not a model, PSF or primary-beam image)")
    ra, dec = _positions_deg(positions)
    ny, nx = info.shape
    pixm = info.pixel_matrix_deg
    # pixel sizes along the image axes (arcsec); a rotated grid keeps the pixel axes
    pix_x = float(np.hypot(pixm[0, 0], pixm[1, 0]) * 3600.0)
    pix_y = float(np.hypot(pixm[0, 1], pixm[1, 1]) * 3600.0)
    beam = info.beam_arcsec
    if mask_radius_arcsec is None:
        radius = beam[0] if beam else DEFAULT_MASK_PIXELS * max(pix_x, pix_y)
    else:
        radius = float(mask_radius_arcsec)
        if not radius > 0:
            raise XstackError(f"mask radius must be positive, got {mask_radius_arcsec}")
    if stamp_size is None:
        size = kernels.noise_stamp_size(beam, pix_x, pix_y, radius, min(nx, ny),
                                        fallback=DEFAULT_STAMP_PIXELS)
    else:
        if isinstance(stamp_size, bool) or int(stamp_size) != stamp_size or stamp_size < 5:
            raise XstackError(f"stamp size must be an integer >= 5 pixels, got {stamp_size!r}")
        size = int(stamp_size)
        if size > min(nx, ny):
            raise XstackError(f"noise image {info.name}: stamp size {size} is larger than the "
                              f"image ({nx} x {ny} pixels)")
    mask = kernels.central_mask(size, radius / pix_x, radius / pix_y)
    n_outside = int(np.count_nonzero(~mask))
    min_pixels = max(kernels.MIN_NOISE_PIXELS, math.ceil(float(min_fraction) * n_outside))
    if n_outside < min_pixels or n_outside < kernels.MIN_NOISE_PIXELS:
        raise XstackError(f"a stamp of {size} pixels is (almost) inside the central mask of "
                          f"radius {radius:.3g} arcsec: use a larger stamp or a smaller mask")

    n = ra.size
    px, py = info.wcs.world_to_pixel_values(ra, dec)
    px, py = np.asarray(px, np.float64), np.asarray(py, np.float64)
    on_image = np.isfinite(px) & np.isfinite(py) & (px >= -0.5) & (px < nx - 0.5) \
        & (py >= -0.5) & (py < ny - 0.5)
    ix = kernels.nearest_pixel(np.where(on_image, px, 0.0))
    iy = kernels.nearest_pixel(np.where(on_image, py, 0.0))
    blanked = on_image & ~np.isfinite(info.data[iy, ix])

    # sigma_k is measured where the noise is flat, as image-stacking measures it
    # (xstack.imstack.io.flat_noise_image): on the image itself when it says it is NOT
    # primary-beam corrected (e.g. the residual of xstack image), else -- when its beam is
    # known -- on the corrected image times A, whose noise grows as 1/A away from the
    # pointing; then divided by A_k, so that it is the noise of the corrected flux
    from xstack.imstack.io import flat_noise_image, image_beam, noise_to_corrected

    pbcor = pb_corrected_from_header(info.header)
    conv = image_beam(info) if pbcor is False else image_beam(info, image_corrected=True)
    todo = np.flatnonzero(on_image & ~blanked)
    data, flattened = flat_noise_image(info, conv, (px[todo], py[todo], size))
    scaled = conv.values is not None and (pbcor is False or flattened)

    sigma = np.full(n, np.nan)
    npix = np.zeros(n, dtype=np.int64)
    sigma[todo], npix[todo] = kernels.stamp_noise(data, px[todo], py[todo], size, mask,
                                                  estimator, min_pixels)

    beam_from = None
    weak = np.zeros(n, dtype=bool)
    if scaled:
        att = np.asarray(conv.values(ra, dec), dtype=np.float64)
        weak = ~(att >= max(conv.cutoff, 1e-12))
        sigma = np.where(weak, np.nan, noise_to_corrected(sigma, conv, flattened, att))
        beam_from = conv.beam_from

    reasons: dict[int, str] = {}
    for k in np.flatnonzero(weak & on_image):
        reasons[int(k)] = "lies where the image's primary beam is below its cutoff"
    for k in np.flatnonzero(~on_image):
        reasons[int(k)] = f"(ra={ra[k]:.6f}, dec={dec[k]:.6f} deg) is outside the image"
    for k in np.flatnonzero(blanked):
        reasons[int(k)] = f"(ra={ra[k]:.6f}, dec={dec[k]:.6f} deg) is on a blanked pixel"
    for k in todo:
        if npix[k] < min_pixels:
            reasons[int(k)] = (f"has only {npix[k]} finite pixels outside the central mask "
                               f"(need {min_pixels})")
        elif not sigma[k] > 0 and not weak[k]:
            reasons[int(k)] = "has constant pixels around it (zero noise)"
    bad = np.array(sorted(reasons), dtype=np.int64)
    sigma[bad] = np.nan
    return LocalNoise(sigma=sigma, n_pixels=npix, bad_rows=bad, reasons=[reasons[k] for k in bad],
                      stamp_size=size, mask_radius_arcsec=float(radius), min_pixels=min_pixels,
                      estimator=estimator, unit=bunit, name=info.name, pbcor=pbcor,
                      beam=beam_from)


def local_noise(image: Any, positions: Any, *, stamp_size: int | None = None,
                mask_radius_arcsec: float | None = None, estimator: str = "clipped",
                min_fraction: float = MIN_FRACTION, on_bad: str = "raise") -> np.ndarray:
    """Local noise sigma_k (image unit, Jy/beam) of a residual image around each position.

    The rms of the stamp around each position outside a beam-sized central circle, as the
    paper measures image-stacking weights (§3.2); see :func:`measure_local_noise` for the
    parameters and defaults (stamp of ~300 beam areas, mask radius BMAJ, 3-sigma clipped
    std). For uv-stacking only ratios of the weights 1/sigma_k^2 matter, so the absolute
    scale (and unit) of the image cancels.

    Parameters
    ----------
    on_bad
        What to do with positions without an estimate (off the image, on a blanked pixel,
        too few finite pixels around them, zero noise): ``"raise"`` (default) an
        :class:`~xstack.errors.XstackError` naming the rows; ``"nan"`` return NaN for them
        and warn, naming the rows.

    Returns
    -------
    numpy.ndarray
        float64 (n,) sigma_k in the image unit.
    """
    if on_bad not in ("raise", "nan"):
        raise XstackError(f"on_bad must be 'raise' or 'nan', got {on_bad!r}")
    res = measure_local_noise(image, positions, stamp_size=stamp_size,
                              mask_radius_arcsec=mask_radius_arcsec, estimator=estimator,
                              min_fraction=min_fraction)
    if res.bad_rows.size:
        if on_bad == "raise":
            raise XstackError(res.describe_bad())
        warnings.warn(res.describe_bad() + " (NaN returned)", stacklevel=2)
    return res.sigma
