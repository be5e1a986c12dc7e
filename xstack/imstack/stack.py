"""Image-stacking (paper §3.2): stamps around known positions, stacked pixel by pixel.

The public entry point is :func:`imstack`. Stamps live in an :class:`xarray.DataArray` cube
with dims ``source``, ``y``, ``x`` (coordinates in arcsec offsets from the stacking
position); the numerical work is in :mod:`xstack.imstack.kernels` (plain numpy).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
from astropy.io import fits
from astropy.table import Table

from xstack import __version__, _vocabulary
from xstack._atomic import atomic_output, check_output
from xstack._inputs import Positions
from xstack._progress import progress_iter
from xstack._result import Result
from xstack.coords import SPEED_OF_LIGHT, parse_distance
from xstack.errors import NoDataError, OptionError, XstackError
from xstack.imstack import kernels
from xstack.imstack.io import (
    BeamConvention,
    ImageInfo,
    image_beam,
    output_paths,
    psf_path_for,
    read_image,
    stamp_header,
    write_fits_atomic,
)

METHODS = _vocabulary.IMSTACK_METHODS
WEIGHTINGS = _vocabulary.IMSTACK_WEIGHTINGS
SUBPIXEL = (False, "fourier", "spline")

ImageSource = str | os.PathLike | fits.ImageHDU | fits.PrimaryHDU | ImageInfo


@dataclass(kw_only=True)
class ImstackResult(Result):
    """Result of :func:`imstack`.

    Attributes
    ----------
    cube
        Stamps, ``xr.DataArray`` (source, y, x) in the image unit (Jy/beam), NaN where the
        stamp is off its image. One entry per (position, image) pair used; the coordinates
        ``position`` (catalog row), ``image`` (index into ``images``), ``ra``, ``dec``
        (deg), ``weight``, ``sigma`` (local noise, Jy/beam), ``pb`` (attenuation or NaN),
        ``frac_x``, ``frac_y`` (offset of the position from the nearest pixel center, pixels)
        run along ``source``; ``x``, ``y`` are offsets in arcsec (x positive to the east for
        a standard image with negative CDELT1, y to the north).
    weights
        float64 (n_catalog_rows, n_images): the weight W_k of each position's stamp in each
        image, 0 where the position was not stacked from that image.
    stacked
        The stacked stamp, ``xr.DataArray`` (y, x), Jy/beam.
    primary_beam
        Per image: the convention used (``image_corrected``, ``corrected_from`` header /
        option / assumed), where the beam came from (``beam``) and its ``cutoff``. The stack
        always measures primary-beam corrected fluxes (docs/conventions.md).
    flux_jy
        Value of the stacked stamp at its central pixel (the stacking position) -- the paper's
        "peak" for point sources, without the upward bias of taking a noisy maximum. With
        nearest-pixel alignment the stack is smeared by the pixelisation
        (see ``pixelisation_factor``); with sub-pixel alignment it is not.
    flux_err_jy
        Noise of ``flux_jy`` propagated from the stamps' local noise sigma_k and weights:
        sqrt(sum W_k^2 sigma_k^2) / sum W_k (paper eq. 5 for W_k = 1/sigma_k^2), times
        sqrt(pi/2) for the median. ``stamp_rms_jy`` is the empirical alternative.
    n_positions
        Number of distinct catalog positions stacked.
    psf_stamp
        The PSF of the stack (y, x) if a PSF image was found or given, else None: the
        weighted mean of each stamp's PSF, including for nearest-pixel alignment the
        smearing by each position's sub-pixel offset (its central value is then the expected
        pixelisation factor of the dirty beam).
    """

    cube: xr.DataArray
    weights: np.ndarray
    stacked: xr.DataArray
    flux_jy: float
    flux_err_jy: float
    n_positions: int
    psf_stamp: xr.DataArray | None = None
    weight_sum: xr.DataArray | None = None
    n_stamps: int = 0
    stamp_rms_jy: float = float("nan")
    peak_jy: float = float("nan")
    method: str = "mean"
    weighting: str = "sigma2"
    subpixel: str | bool = False
    beam_arcsec: tuple[float, float, float] | None = None
    mask_radius_arcsec: float = float("nan")
    pixel_arcsec: tuple[float, float] = (float("nan"), float("nan"))
    pixelisation_factor: float | None = None
    filter_lowfreq: Any = None
    skipped_rows: list[int] = field(default_factory=list)
    outputs: dict[str, str] = field(default_factory=dict)
    primary_beam: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly summary (what ``xstack imstack --json`` prints)."""
        def num(v: Any) -> float | None:
            return None if v is None or not np.isfinite(v) else float(v)

        return {
            "flux_jy": num(self.flux_jy),
            "flux_err_jy": num(self.flux_err_jy),
            "n_positions": int(self.n_positions),
            "n_stamps": int(self.n_stamps),
            "method": self.method,
            "weighting": self.weighting,
            "subpixel": self.subpixel or "nearest",
            "stamp_rms_jy": num(self.stamp_rms_jy),
            "peak_jy": num(self.peak_jy),
            "stamp_size": int(self.stacked.shape[0]),
            "pixel_arcsec": [num(p) for p in self.pixel_arcsec],
            "beam_arcsec": list(self.beam_arcsec) if self.beam_arcsec else None,
            "mask_radius_arcsec": num(self.mask_radius_arcsec),
            "pixelisation_factor": num(self.pixelisation_factor),
            "psf": self.psf_stamp is not None,
            "filter_lowfreq": self.filter_lowfreq,
            "skipped_rows": list(self.skipped_rows),
            "outputs": dict(self.outputs),
            "flux_convention": "primary-beam corrected",
            "primary_beam": [dict(p) for p in self.primary_beam],
        }

    def table(self) -> Table:
        """One row per stamp stacked: the cube's ``source`` coordinates (``position`` row,
        ``image``, ``ra``/``dec`` in deg, ``weight``, ``sigma`` in Jy/beam, ``pb``, sub-pixel
        offsets) and the stamp's central value ``center_jy``."""
        t = Table()
        for name, coord in self.cube.coords.items():
            if coord.dims == ("source",):
                t[str(name)] = np.asarray(coord.values)
        ny, nx = self.cube.shape[1:]
        t["center_jy"] = np.asarray(self.cube.values[:, ny // 2, nx // 2], dtype=np.float64)
        for name, unit in (("ra", "deg"), ("dec", "deg"), ("sigma", "Jy/beam"),
                           ("center_jy", "Jy/beam")):
            if name in t.colnames:
                t[name].unit = unit
        return t


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------

def _positions(positions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(ra, dec) in degrees and the optional catalog weight column (:class:`~xstack._inputs.Positions`)."""
    pos = Positions.from_any(positions)
    return pos.ra_deg, pos.dec_deg, pos.weight


def _as_list(value: Any, n: int, what: str) -> list[Any]:
    if isinstance(value, (list, tuple)):
        if len(value) != n:
            raise XstackError(f"{what}: got {len(value)} entries for {n} images")
        return list(value)
    return [value] * n


def _check_grids(infos: list[ImageInfo]) -> np.ndarray:
    """All images must share one pixel grid orientation and scale so stamps line up."""
    ref = infos[0].pixel_matrix_deg
    for info in infos[1:]:
        if not np.allclose(info.pixel_matrix_deg, ref, rtol=1e-6, atol=1e-12 * np.abs(ref).max()):
            raise XstackError(f"{info.name}: pixel scale/orientation differs from {infos[0].name}; "
                              "stack images with the same cell size and orientation")
    return ref


def _filter_mask(filter_lowfreq: Any, size: int, pix_x_arcsec: float, pix_y_arcsec: float,
                 freq_hz: float | None) -> np.ndarray | None:
    """The Fourier cells to zero for ``filter_lowfreq`` (None: no filter)."""
    if filter_lowfreq is None or filter_lowfreq is False:
        return None
    if isinstance(filter_lowfreq, (int, np.integer)) and not isinstance(filter_lowfreq, bool):
        n = int(filter_lowfreq)
        if n < 1 or n % 2 == 0 or n >= size:
            raise XstackError(f"filter_lowfreq={n}: give an odd number of central Fourier cells "
                              f"smaller than the stamp ({size})")
        return kernels.lowfreq_mask((size, size), n_central=n)
    value, unit = parse_distance(filter_lowfreq)
    if unit == "m":
        if freq_hz is None:
            raise XstackError("filter_lowfreq in metres needs the image frequency; give it in "
                              "klambda or as a number of central Fourier cells")
        value = value * freq_hz / SPEED_OF_LIGHT
    # one Fourier cell of a stamp is 1 / (size * pixel) wavelengths (pixel in radians)
    cell = 1.0 / (size * np.radians(max(pix_x_arcsec, pix_y_arcsec) / 3600.0))
    return kernels.lowfreq_mask((size, size), q_min_cells=value / cell)


def _mean_position(ra: np.ndarray, dec: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """Weighted mean direction (deg) of the positions (unit-vector average)."""
    r, d = np.radians(ra), np.radians(dec)
    v = np.stack([np.cos(d) * np.cos(r), np.cos(d) * np.sin(r), np.sin(d)]) @ w
    return float(np.degrees(np.arctan2(v[1], v[0])) % 360.0), float(np.degrees(np.arctan2(
        v[2], np.hypot(v[0], v[1]))))


# ---------------------------------------------------------------------------------------------
# public API
# ---------------------------------------------------------------------------------------------

def stack_images(images: ImageSource | Sequence[ImageSource], positions: Any, *, stamp_size: int = 64,
            method: str = "mean", weighting: str = "sigma2", subpixel: str | bool = False,
            primary_beam: Any = None, pbcor: bool = False, psf: Any = None,
            image_corrected: bool | None | Sequence[bool | None] = None,
            beam_mask_arcsec: float | None = None, filter_lowfreq: int | str | None = None,
            skip_outside: bool = False, out: str | os.PathLike | None = None,
            cube_format: str = "zarr", plot: bool = True, overwrite: bool = False,
            progress: bool = False) -> ImstackResult:
    """Stack image stamps at known positions (Lindroos et al. 2015, §3.2).

    Parameters
    ----------
    images
        One image or a sequence (e.g. mosaic pointings): FITS paths, astropy image HDUs,
        in-memory images (:class:`xstack.imaging.image.ImageResult`: image, header and PSF)
        or :class:`~xstack.imstack.io.ImageInfo`. Any celestial WCS; degenerate Stokes/frequency
        axes are dropped. All images must share cell size and orientation.
    positions
        Catalog path or :class:`~astropy.table.Table` (columns ``ra``, ``dec`` in degrees,
        optional ``weight``), or an (N, 2) array of (ra, dec) in degrees.
    stamp_size
        Stamp side in pixels; the stacking position is at index ``stamp_size // 2``.
    method
        ``"mean"`` (weighted mean per pixel, NaN ignored) or ``"median"`` (per-pixel median
        of all stamps, unweighted).
    weighting
        ``"sigma2"``: W_k = 1/sigma_k^2, sigma_k the std of the stamp outside a central
        circle of radius ``beam_mask_arcsec`` (default: the beam's major axis BMAJ), paper
        eq. 3. ``"pb"``: W_k = A^2 (the inverse variance of the corrected flux, the paper's
        ALMA weights), for corrected and uncorrected images alike.
        ``"none"``: W_k = 1. ``"column"``: the catalog's ``weight`` column.
    subpixel
        ``False`` (nearest pixel, as in the paper), ``"fourier"`` or ``"spline"`` (shift each
        stamp so the position is exactly at the center; removes the pixelisation loss).
    primary_beam
        Primary beam A: a :class:`~xstack.beams.PrimaryBeam`, a model name, a PB FITS image,
        an array on the image grid, or a list with one per image. It wins over the image's
        own beam. Default: the beam file named by the header (``XSPBFILE``, written by
        ``xstack image`` as ``X.pb.fits``; a mosaic's effective beam), else the telescope's
        standard beam from TELESCOP and the image frequency, centered on OBSRA/OBSDEC or the
        WCS reference position (never for a mosaic). Positions outside the field are not
        stacked from that image: the one rule of every stage
        (:func:`xstack.beams.inside_field`: A >= the cutoff -- the header's ``XSPBCUT``, the
        PrimaryBeam's, else 0.1 -- at the highest frequency of the image's band, inside the
        main lobe; docs/conventions.md "Inside the field").
    image_corrected
        Whether the image is primary-beam corrected (one, or one per image); default: the
        header's ``XSPBCOR``; an image that says nothing is used as is, with a warning. The
        stack always measures corrected fluxes: an uncorrected image's stamps are divided by
        A(position), a corrected image is used as is (docs/conventions.md).
    pbcor
        ``True`` is the older spelling of ``image_corrected=False`` (divide each stamp by A).
    psf
        PSF image(s) (FITS path/HDU, one or one per image). Default: ``X.psf.fits`` beside
        ``X.fits`` where it exists.
    beam_mask_arcsec
        Radius of the central mask for sigma_k and the stamp rms (default BMAJ; 5 pixels if
        the image has no beam).
    filter_lowfreq
        The §5.3 low-spatial-frequency FFT filter of the stacked stamp (and its PSF): an odd
        int n zeroes the central n x n Fourier cells (paper: 3); a distance ("4500m",
        "20klambda") zeroes every cell with uv distance below it.
    skip_outside
        Skip positions outside every image instead of raising (their rows are reported).
    out
        ``OUT.fits``: also write the stacked stamp (FITS, with ``PSF`` and ``WEIGHTS``
        extensions), the cube (``OUT.cube.zarr`` or ``OUT.cube.fits``) and ``OUT.png``.
        All atomic; nothing is written if anything fails.
    cube_format
        ``"zarr"`` or ``"fits"``.
    plot
        Write ``OUT.png`` (with ``out``).
    overwrite
        Replace existing outputs.
    progress
        Progress bar on stderr.

    Returns
    -------
    ImstackResult

    Raises
    ------
    XstackError
        Bad option, image without celestial WCS, stamp larger than an image, positions
        outside every image or on blanked pixels (unless ``skip_outside``), no finite stamp
        value at the stacking position, existing outputs.
    """
    # ---- options (before any work) ----------------------------------------------------------
    if method not in METHODS:
        raise OptionError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    if weighting not in WEIGHTINGS:
        raise OptionError(f"weighting must be one of {', '.join(WEIGHTINGS)}, got {weighting!r}")
    if subpixel in (None, "none", "nearest"):
        subpixel = False
    if subpixel not in SUBPIXEL:
        raise OptionError(f"subpixel must be fourier or spline (or False), got {subpixel!r}")
    if isinstance(stamp_size, bool) or int(stamp_size) != stamp_size or stamp_size < 5:
        raise OptionError(f"stamp size must be an integer >= 5 pixels, got {stamp_size!r}")
    stamp_size = int(stamp_size)
    if cube_format not in _vocabulary.CUBE_FORMATS:
        raise OptionError(f"cube format must be zarr or fits, got {cube_format!r}")
    paths = None
    if out is not None:
        paths = output_paths(out, cube_format)
        if not plot:
            paths.pop("png")
        for p in paths.values():
            check_output(p, overwrite)

    if pbcor:
        if image_corrected is True or (isinstance(image_corrected, (list, tuple))
                                       and any(c is True for c in image_corrected)):
            raise XstackError("pbcor=True (divide by the beam) contradicts image_corrected=True")
        image_corrected = False

    # ---- inputs -----------------------------------------------------------------------------
    ra, dec, cat_w = _positions(positions)
    if weighting == "column" and cat_w is None:
        raise XstackError("weighting 'column' needs a catalog with a weight column")
    if isinstance(images, (str, os.PathLike, fits.ImageHDU, fits.PrimaryHDU, ImageInfo)) or (
            hasattr(images, "image") and hasattr(images, "header")):
        images = [images]
    images = list(images)
    if not images:
        raise XstackError("no images given")
    infos = [read_image(img, name=None if isinstance(img, (str, os.PathLike)) else f"image[{i}]")
             for i, img in enumerate(images)]
    for info in infos:
        ny, nx = info.shape
        if stamp_size > min(ny, nx):
            raise XstackError(f"{info.name}: stamp size {stamp_size} is larger than the image "
                              f"({nx} x {ny} pixels)")
    pixm = _check_grids(infos)
    # pixel sizes (arcsec) along the image x and y axes, signed like CDELT1/CDELT2 (for a
    # rotated image the stamp axes stay the pixel axes); rho = angle of the y axis east of north
    pix_x = float(np.hypot(pixm[0, 0], pixm[1, 0]) * 3600)
    pix_y = float(np.hypot(pixm[0, 1], pixm[1, 1]) * 3600)
    sx = pix_x * (-1.0 if pixm[0, 0] < 0 else 1.0)
    sy = pix_y * (-1.0 if pixm[1, 1] < 0 else 1.0)
    rho = float(np.degrees(np.arctan2(pixm[0, 1], pixm[1, 1])))
    beam = next((i.beam_arcsec for i in infos if i.beam_arcsec), None)
    pbs = _as_list(primary_beam, len(infos), "primary_beam")
    corr = _as_list(image_corrected, len(infos), "image_corrected")
    convs: list[BeamConvention] = [
        image_beam(info, pbs[i], corr[i],
                   how_to_state="image_corrected=True/False")
        for i, info in enumerate(infos)]
    psfs = _as_list(psf, len(infos), "psf")
    fmask = _filter_mask(filter_lowfreq, stamp_size, pix_x, pix_y, infos[0].frequency_hz)

    # ---- which positions each image sees ----------------------------------------------------
    n_pos = ra.size
    seen = np.zeros((n_pos, len(infos)), dtype=bool)
    pix = np.full((n_pos, len(infos), 2), np.nan)
    atten = np.full((n_pos, len(infos)), np.nan)
    for i, info in enumerate(infos):
        px, py = info.wcs.world_to_pixel_values(ra, dec)
        px, py = np.asarray(px, np.float64), np.asarray(py, np.float64)
        ny, nx = info.shape
        inside = np.isfinite(px) & np.isfinite(py) & (px >= -0.5) & (px < nx - 0.5) \
            & (py >= -0.5) & (py < ny - 0.5)
        ix, iy = kernels.nearest_pixel(np.where(inside, px, 0)), kernels.nearest_pixel(
            np.where(inside, py, 0))
        inside &= np.isfinite(info.data[iy, ix])  # blanked center: not covered by this image
        conv = convs[i]
        # A is needed for pb weights and to correct an uncorrected image (and recorded when
        # the beam travels with the image)
        if weighting == "pb" or not conv.corrected or conv.from_image:
            if conv.values is None:
                raise XstackError(conv.missing or f"{info.name}: no primary beam known; give primary_beam=",
                                  option="primary_beam")
            atten[:, i] = np.asarray(conv.values(ra, dec), dtype=np.float64)
        # whenever a beam is known, the one rule of every stage decides "inside the field"
        # (xstack.beams.inside_field at the image's band edge, docs/conventions.md)
        if conv.inside is not None:
            inside &= np.asarray(conv.inside(ra, dec), dtype=bool)
        seen[:, i] = inside
        pix[:, i, 0], pix[:, i, 1] = px, py
    unseen = np.flatnonzero(~seen.any(axis=1))
    if unseen.size and not skip_outside:
        k = int(unseen[0])
        raise XstackError(f"{unseen.size} of {n_pos} positions are outside every image, e.g. row "
                          f"{k + 1} (ra={ra[k]:.6f}, dec={dec[k]:.6f} deg); remove them or skip_outside")
    if unseen.size == n_pos:
        raise NoDataError("no position lies inside any image")

    # ---- stamps -----------------------------------------------------------------------------
    blocks, meta = [], []
    for i in progress_iter(range(len(infos)), "imstack: stamps", progress and len(infos) > 1):
        rows = np.flatnonzero(seen[:, i])
        if rows.size == 0:
            continue
        st, fx, fy = kernels.align_stamps(infos[i].data, pix[rows, i, 0], pix[rows, i, 1],
                                          stamp_size, subpixel)
        if not convs[i].corrected:
            st /= atten[rows, i][:, None, None]
        blocks.append(st)
        meta.append((rows, np.full(rows.size, i), fx, fy))
    stamps = np.concatenate(blocks)
    rows = np.concatenate([m[0] for m in meta])
    img_idx = np.concatenate([m[1] for m in meta])
    frac_x = np.concatenate([m[2] for m in meta])
    frac_y = np.concatenate([m[3] for m in meta])
    pb_k = atten[rows, img_idx]

    # ---- local noise and weights ------------------------------------------------------------
    if beam_mask_arcsec is None:
        radius = beam[0] if beam else 5.0 * max(pix_x, pix_y)
    else:
        radius = float(beam_mask_arcsec)
        if not radius > 0:
            raise XstackError(f"beam mask radius must be positive, got {beam_mask_arcsec}")
    mask = kernels.central_mask(stamp_size, radius / pix_x, radius / pix_y)
    if mask.all():
        raise XstackError(f"stamp of {stamp_size} pixels is inside the central mask of radius "
                          f"{radius:.3g} arcsec: use a larger stamp")
    sigma = kernels.local_sigma(stamps, mask)
    if weighting == "sigma2":
        with np.errstate(divide="ignore"):
            w = np.where(np.isfinite(sigma) & (sigma > 0), 1.0 / sigma**2, 0.0)
    elif weighting == "pb":
        w = np.nan_to_num(pb_k, nan=0.0) ** 2
    elif weighting == "column":
        w = cat_w[rows]
    else:
        w = np.ones(rows.size)
    if not np.any(w > 0):
        raise NoDataError("every stamp has zero weight (no usable noise estimate?)")

    # ---- aggregation ------------------------------------------------------------------------
    if method == "mean":
        stacked, wsum = kernels.weighted_nanmean(stamps, w)
    else:
        use = w > 0
        stacked, wsum = kernels.nanmedian_stack(stamps[use])
    c = stamp_size // 2
    center_ok = np.isfinite(stamps[:, c, c]) & (w > 0)
    if not center_ok.any():
        # the nearest pixels are finite (or the position would count as uncovered), but a
        # sub-pixel shift blanks pixels near a NaN: without this the flux is silently NaN
        raise XstackError(
            "no stamp has a finite value at the stacking position: blanked (NaN) pixels "
            f"within {kernels.SPLINE_NAN_GUARD} pixels of every position spoil the sub-pixel "
            "shift; use subpixel=False or images without blanking near the positions")
    # the stacked value's noise from the stamps' local noise (eq. 5 / 6)
    # (the median is unweighted: its error is that of the equal-weight mean times sqrt(pi/2))
    flux_err = kernels.weighted_error(sigma[center_ok], w[center_ok] if method == "mean"
                                      else np.ones(int(center_ok.sum())))
    if method == "median":
        flux_err *= kernels.MEDIAN_NOISE_FACTOR

    # ---- PSF of the stack -------------------------------------------------------------------
    psf_stack = _psf_stack(infos, psfs, stamp_size, img_idx, frac_x, frac_y, w, subpixel)

    # ---- low-spatial-frequency filter (paper §5.3) ------------------------------------------
    if fmask is not None:
        stacked = kernels.lowfreq_filter(stacked, fmask)
        if psf_stack is not None:
            psf_stack = kernels.lowfreq_filter(psf_stack, fmask)

    flux = float(stacked[c, c])
    outside = stacked[~mask]
    stamp_rms = float(np.nanstd(outside)) if np.isfinite(outside).sum() > 1 else float("nan")
    inner = np.where(mask, stacked, np.nan)
    peak = float(np.nanmax(inner)) if np.isfinite(inner).any() else float("nan")
    pixfac = None
    if beam and not subpixel:
        pixfac = kernels.pixelisation_factor(beam[0], beam[1], beam[2] - rho, pix_x, pix_y)

    # ---- xarray objects ---------------------------------------------------------------------
    off = kernels.offsets_grid(stamp_size)
    # x = offset along the image x axis as Delta(RA) cos(dec) (east positive; it decreases with
    # the pixel index for the usual CDELT1 < 0), y = offset north
    xcoord = xr.Variable("x", off * sx + 0.0, attrs={"units": "arcsec",
                         "long_name": "offset east (Delta RA cos Dec) along the image x axis"})
    ycoord = xr.Variable("y", off * sy + 0.0, attrs={"units": "arcsec",
                         "long_name": "offset north along the image y axis"})
    bunit = infos[0].bunit or "Jy/beam"
    cube = xr.DataArray(
        stamps, dims=("source", "y", "x"),
        coords={"x": xcoord, "y": ycoord,
                "position": ("source", rows.astype(np.int64)),
                "image": ("source", img_idx.astype(np.int64)),
                "ra": ("source", ra[rows], {"units": "deg"}),
                "dec": ("source", dec[rows], {"units": "deg"}),
                "weight": ("source", w),
                "sigma": ("source", sigma, {"units": bunit}),
                "pb": ("source", pb_k),
                "frac_x": ("source", frac_x, {"units": "pixel"}),
                "frac_y": ("source", frac_y, {"units": "pixel"})},
        name="stamps", attrs={"units": bunit, "method": method, "weighting": weighting,
                              "subpixel": str(subpixel or "nearest"), "stamp_size": stamp_size})
    weights = np.zeros((n_pos, len(infos)))
    weights[rows, img_idx] = w
    stacked_da = xr.DataArray(stacked, dims=("y", "x"), coords={"x": xcoord, "y": ycoord},
                              name="stacked", attrs={"units": bunit})
    wsum_da = xr.DataArray(wsum, dims=("y", "x"), coords={"x": xcoord, "y": ycoord},
                           name="weight_sum" if method == "mean" else "n_stamps")
    psf_da = None if psf_stack is None else xr.DataArray(
        psf_stack, dims=("y", "x"), coords={"x": xcoord, "y": ycoord}, name="psf")
    n_positions = int(np.unique(rows[w > 0]).size)
    result = ImstackResult(
        cube=cube, weights=weights, stacked=stacked_da, flux_jy=flux, flux_err_jy=flux_err,
        n_positions=n_positions, psf_stamp=psf_da, weight_sum=wsum_da, n_stamps=int(np.sum(w > 0)),
        stamp_rms_jy=stamp_rms, peak_jy=peak, method=method, weighting=weighting,
        subpixel=subpixel, beam_arcsec=beam, mask_radius_arcsec=radius, pixel_arcsec=(pix_x, pix_y),
        pixelisation_factor=pixfac, filter_lowfreq=filter_lowfreq,
        skipped_rows=[int(k) + 1 for k in unseen],
        primary_beam=[dict(c.to_dict(), image=info.name) for c, info in zip(convs, infos)])
    if paths is not None:
        ra0, dec0 = _mean_position(ra[rows], dec[rows], np.where(w > 0, w, 0) / np.sum(w))
        _write_outputs(result, paths, pixm, ra0, dec0, overwrite)
    return result


def _psf_stamp_for(info: ImageInfo, psf: Any, stamp_size: int) -> np.ndarray | None:
    """A finite PSF stamp with margin (odd size) centered on the PSF peak, or None."""
    if psf is None and "psf" in info.extra:
        psf = info.extra["psf"]
    if psf is None:
        if info.path is None:
            return None
        candidate = psf_path_for(info.path)
        if not candidate.exists():
            return None
        psf = candidate
    pinfo = read_image(psf, name=f"PSF {psf}")
    if not np.allclose(pinfo.pixel_matrix_deg, info.pixel_matrix_deg, rtol=1e-6,
                       atol=1e-12 * np.abs(info.pixel_matrix_deg).max()):
        raise XstackError(f"{pinfo.name}: PSF pixel grid differs from the image {info.name}")
    data = np.nan_to_num(pinfo.data, nan=0.0)
    py, px = np.unravel_index(np.argmax(data), data.shape)
    odd = stamp_size | 1
    margin = (kernels.padded_size(stamp_size, kernels.SHIFT_MARGIN) - odd) // 2
    st, _, _ = kernels.extract_stamps(data, np.array([px]), np.array([py]), odd, margin)
    return np.nan_to_num(st[0], nan=0.0)


def _psf_stack(infos: list[ImageInfo], psfs: list[Any], stamp_size: int, img_idx: np.ndarray,
               frac_x: np.ndarray, frac_y: np.ndarray, w: np.ndarray, subpixel: Any) -> np.ndarray | None:
    """Weighted-mean PSF of the stamps (with each stamp's sub-pixel smear if nearest-pixel)."""
    padded = {}
    for i, info in enumerate(infos):
        if np.any(img_idx == i):
            p = _psf_stamp_for(info, psfs[i], stamp_size)
            if p is None:
                return None  # some stamps have no PSF: the stack's PSF is unknown
            padded[i] = p
    if not padded:
        return None
    margin = (next(iter(padded.values())).shape[0] - (stamp_size | 1)) // 2
    total = np.zeros((stamp_size, stamp_size))
    wtot = 0.0
    for i, p in padded.items():
        sel = (img_idx == i) & (w > 0)
        if not sel.any():
            continue
        if subpixel:
            shifted = p[None] * 1.0
            wi = np.array([w[sel].sum()])
        else:
            # the stacked source is the PSF displaced by each position's offset from its pixel:
            # average in chunks to bound memory
            acc = np.zeros_like(p)
            idx = np.flatnonzero(sel)
            for s in range(0, idx.size, 256):
                part = idx[s:s + 256]
                sh = kernels.fourier_shift(np.broadcast_to(p, (part.size, *p.shape)),
                                           frac_y[part], frac_x[part])
                acc += np.einsum("k,kyx->yx", w[part], sh)
            shifted = acc[None]
            wi = np.array([1.0])
        total += (shifted * wi[:, None, None]).sum(axis=0)[margin:margin + stamp_size,
                                                             margin:margin + stamp_size]
        wtot += float(w[sel].sum())
    return total / wtot if wtot > 0 else None


def _header_cards(result: ImstackResult) -> list[tuple[str, Any, str]]:
    def f(v: Any) -> Any:
        return float(v) if v is not None and np.isfinite(v) else "NaN"

    return [
        ("BUNIT", str(result.stacked.attrs.get("units", "Jy/beam")), "unit of the stacked stamp"),
        ("NSTACK", result.n_positions, "number of stacked positions"),
        ("NSTAMP", result.n_stamps, "number of stamps (position x image)"),
        ("STMETHOD", result.method, "stacking: mean (weighted) or median"),
        ("STWEIGHT", result.weighting, "stamp weights: sigma2, pb, none, column"),
        ("STSUBPIX", str(result.subpixel or "nearest"), "alignment: nearest, fourier, spline"),
        ("STFLUX", f(result.flux_jy), "[Jy/beam] stacked value at the center pixel"),
        ("STFLUXER", f(result.flux_err_jy), "[Jy/beam] noise of STFLUX from sigma_k (eq. 5)"),
        ("STRMS", f(result.stamp_rms_jy), "[Jy/beam] rms of the stack outside the mask"),
        ("STPEAK", f(result.peak_jy), "[Jy/beam] maximum inside the central mask"),
        ("STMASKR", f(result.mask_radius_arcsec), "[arcsec] radius of the central mask"),
        ("STPIXFAC", f(result.pixelisation_factor), "expected nearest-pixel peak factor (Gauss)"),
        ("STFILTER", str(result.filter_lowfreq), "low-spatial-frequency FFT filter"),
        ("STPBCOR", True, "stacked flux is primary-beam corrected"),
        ("STPBFROM", ",".join(sorted({str(p.get("corrected_from")) for p in result.primary_beam}))
         or "none", "convention from: header, option, assumed"),
        ("ORIGIN", f"xstack {__version__}", ""),
    ]


def _write_outputs(result: ImstackResult, paths: dict[str, Path], pixm: np.ndarray, ra0: float,
                   dec0: float, overwrite: bool) -> None:
    size = result.stacked.shape[0]
    header = stamp_header(ra0, dec0, size, pixm / 1.0)
    if result.beam_arcsec:
        header["BMAJ"] = result.beam_arcsec[0] / 3600.0
        header["BMIN"] = result.beam_arcsec[1] / 3600.0
        header["BPA"] = result.beam_arcsec[2]
    for key, value, comment in _header_cards(result):
        header[key] = (value, comment)
    header["HISTORY"] = "xstack imstack: reference pixel = the stacking position; CRVAL is the"
    header["HISTORY"] = "mean stacking position (nominal). Offsets are in the input pixel grid."
    hdus = [fits.PrimaryHDU(result.stacked.values.astype(np.float64), header=header)]
    if result.psf_stamp is not None:
        ph = header.copy()
        for key in ("BUNIT", "STFLUX", "STFLUXER", "STRMS", "STPEAK"):
            ph.remove(key, ignore_missing=True)
        ph["EXTNAME"] = "PSF"
        ph["PSFSMEAR"] = (not result.subpixel, "includes the nearest-pixel smear of the stack")
        c = size // 2
        ph["PSFPEAK"] = (float(result.psf_stamp.values[c, c]), "center value: keep, do not renormalise")
        ph["HISTORY"] = "PSF of the stack: mean of the dirty beam displaced by every position's"
        ph["HISTORY"] = "sub-pixel offset (PSFSMEAR = T). Its center value PSFPEAK < 1 is the"
        ph["HISTORY"] = "pixelisation loss; fitting with it unnormalised gives the true flux."
        hdus.append(fits.ImageHDU(result.psf_stamp.values.astype(np.float64), header=ph, name="PSF"))
    wh = fits.Header()
    wh["EXTNAME"] = "WEIGHTS"
    wh["CONTENT"] = ("sum of weights" if result.method == "mean" else "number of stamps",
                     "per-pixel coverage of the stack")
    hdus.append(fits.ImageHDU(result.weight_sum.values.astype(np.float64), header=wh, name="WEIGHTS"))
    hdul = fits.HDUList(hdus)

    with contextlib.ExitStack() as stack:
        tmp_fits = stack.enter_context(atomic_output(paths["fits"], overwrite))
        tmp_cube = stack.enter_context(atomic_output(paths["cube"], overwrite))
        tmp_png = stack.enter_context(atomic_output(paths["png"], overwrite)) if "png" in paths else None
        write_fits_atomic(hdul, tmp_fits)
        _write_cube(result, tmp_cube, paths["cube"].suffix == ".zarr", header)
        if tmp_png is not None:
            from xstack.imstack.plot import plot_stack

            plot_stack(result, tmp_png)
    result.outputs = {k: str(v) for k, v in paths.items()}


def _write_cube(result: ImstackResult, tmp: Path, as_zarr: bool, header: fits.Header) -> None:
    cube = result.cube
    if as_zarr:
        ds = xr.Dataset({"stamps": cube, "stacked": result.stacked})
        ds.attrs.update({k: (v if isinstance(v, (int, float, str)) else str(v))
                         for k, v, _ in _header_cards(result)})
        ds.to_zarr(tmp, mode="w", consolidated=False)
        return
    h = header.copy()
    h["CTYPE3"] = ("STAMP", "stamp index (see the STAMPS table)")
    h["CRPIX3"], h["CRVAL3"], h["CDELT3"] = 1.0, 0.0, 1.0
    cols = Table({name: np.asarray(cube.coords[name].values) for name in
                  ("position", "image", "ra", "dec", "weight", "sigma", "pb", "frac_x", "frac_y")})
    cols["position"] += 1  # 1-based catalog rows in the file
    hdul = fits.HDUList([fits.PrimaryHDU(cube.values.astype(np.float32), header=h),
                         fits.table_to_hdu(cols)])
    hdul[1].name = "STAMPS"
    write_fits_atomic(hdul, tmp)
