"""Image-stacking (paper §3.2): stamps around known positions, stacked pixel by pixel.

The public entry point is :func:`stack_images`, its options an :class:`ImstackOptions`
(validated before any input is read). It runs in phases: ``_load`` (outputs free, positions,
images read) -> ``_plan`` (pixel grid, beams, which image sees which position, the noise mask)
-> ``_compute`` (stamps, weights, the stack) -> ``_assemble`` (the :class:`ImstackResult`)
-> ``_save`` (the outputs). Stamps live in an :class:`xarray.DataArray` cube with dims
``source``, ``y``, ``x`` (coordinates in arcsec offsets from the stacking position); the
numerical work is in :mod:`xstack.imstack.kernels` (plain numpy).
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, fields, is_dataclass
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
from xstack._result import Result, json_ready
from xstack.coords import SPEED_OF_LIGHT, parse_distance
from xstack.errors import NoDataError, OptionError, XstackError, XstackWarning
from xstack.imstack import kernels
from xstack.imstack.io import (
    BeamConvention,
    ImageInfo,
    flat_noise_image,
    image_beam,
    noise_to_corrected,
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
    """Result of :func:`stack_images`.

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
        (see ``pixelisation_factor``); with sub-pixel alignment it is not. With
        ``filter_lowfreq`` and a PSF, the filtered central value divided by
        ``filter_response``, so that it stays a flux density.
    flux_err_jy
        Noise of ``flux_jy`` propagated from the stamps' local noise sigma_k and weights:
        sqrt(sum W_k^2 sigma_k^2) / sum W_k (paper eq. 5 for W_k = 1/sigma_k^2), times
        sqrt(pi/2) for the median. ``stamp_rms_jy`` is the empirical alternative.
    n_positions
        Number of distinct catalog positions stacked.
    noise_estimator, noise_stamp_size
        How sigma_k was measured: the estimator and the side (pixels) of the stamps it was
        measured on (``noise_stamp_size`` as used, the default resolved).
    noise_flattened
        True when sigma_k was measured on a primary-beam corrected image times its beam A
        (where the noise is flat) and divided by A at the position, as it is whenever the
        beam of a corrected image is known; an uncorrected image is measured as it is.
    psf_stamp
        The PSF of the stack (y, x) if a PSF image was found or given, else None: the
        weighted mean of each stamp's PSF, including for nearest-pixel alignment the
        smearing by each position's sub-pixel offset (its central value is then the expected
        pixelisation factor of the dirty beam).
    filter_response
        With ``filter_lowfreq`` and a PSF: the filtered PSF stamp's central value over the
        unfiltered one, the fraction of a point source's peak that the filter keeps (0.62 for
        VLA A at 1.4 GHz with a 5000 m cut); ``flux_jy`` and ``flux_err_jy`` are divided by
        it. None without a filter or a PSF (then ``flux_jy`` is the filtered peak, with a
        warning).
    options
        The options used (:meth:`ImstackOptions.to_dict`), plus ``n_images`` and the
        ``mask_radius_arcsec`` used.
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
    noise_estimator: str = "clipped"
    noise_stamp_size: int = 0
    noise_flattened: bool = False
    pixel_arcsec: tuple[float, float] = (float("nan"), float("nan"))
    pixelisation_factor: float | None = None
    filter_lowfreq: Any = None
    filter_response: float | None = None
    skipped_rows: list[int] = field(default_factory=list)
    outputs: dict[str, str] = field(default_factory=dict)
    primary_beam: list[dict[str, Any]] = field(default_factory=list)
    options: dict[str, Any] = field(default_factory=dict)

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
            "noise_estimator": self.noise_estimator,
            "noise_stamp_size": int(self.noise_stamp_size),
            "noise_flattened": bool(self.noise_flattened),
            "pixelisation_factor": num(self.pixelisation_factor),
            "psf": self.psf_stamp is not None,
            "filter_lowfreq": self.filter_lowfreq,
            "filter_response": num(self.filter_response),
            "skipped_rows": list(self.skipped_rows),
            "outputs": dict(self.outputs),
            "flux_convention": "primary-beam corrected",
            "primary_beam": [dict(p) for p in self.primary_beam],
            "options": dict(self.options),
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
# options
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, kw_only=True)
class ImstackOptions:
    """Every option of :func:`stack_images`, validated on construction.

    The fields are the keyword parameters of :func:`stack_images`, with the same names,
    defaults, units and meanings (see its Parameters); a bad value raises
    :class:`~xstack.errors.OptionError` naming the parameter, before any input is read.
    ``subpixel`` is normalized (``None``, ``"none"``, ``"nearest"`` -> ``False``) and
    ``stamp_size`` made an ``int``.

    Attributes
    ----------
    corrected
        The primary-beam state to assume: ``image_corrected``, or ``False`` with ``pbcor``.
    filter_cells
        ``filter_lowfreq`` as a number of central Fourier cells (odd int), else None.
    filter_uv
        ``filter_lowfreq`` as a uv distance ``(value, unit)``, unit ``"m"`` or ``"lambda"``
        (:func:`xstack.coords.parse_distance`), else None.
    """

    stamp_size: int = 64
    method: str = "mean"
    weighting: str = "sigma2"
    subpixel: str | bool = False
    primary_beam: Any = None
    pbcor: bool = False
    psf: Any = None
    image_corrected: bool | None | Sequence[bool | None] = None
    beam_mask_arcsec: float | None = None
    noise_estimator: str = "clipped"
    noise_stamp_size: int | None = None
    filter_lowfreq: int | str | None = None
    skip_outside: bool = False
    out: str | os.PathLike | None = None
    cube_format: str = "zarr"
    plot: bool = True
    overwrite: bool = False
    progress: bool = False
    # derived in __post_init__ (not constructor arguments)
    filter_cells: int | None = field(init=False, default=None)
    filter_uv: tuple[float, str] | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise OptionError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}",
                              option="method")
        if self.weighting not in WEIGHTINGS:
            raise OptionError(f"weighting must be one of {', '.join(WEIGHTINGS)}, got "
                              f"{self.weighting!r}", option="weighting")
        subpixel = False if self.subpixel in (None, "none", "nearest") else self.subpixel
        if subpixel not in SUBPIXEL:
            raise OptionError(f"subpixel must be fourier or spline (or False), got {subpixel!r}",
                              option="subpixel")
        object.__setattr__(self, "subpixel", subpixel)
        object.__setattr__(self, "stamp_size", _stamp_size(self.stamp_size))
        if self.noise_estimator not in kernels.NOISE_ESTIMATORS:
            raise OptionError(f"noise_estimator must be one of "
                              f"{', '.join(kernels.NOISE_ESTIMATORS)}, got {self.noise_estimator!r}",
                              option="noise_estimator")
        if self.noise_stamp_size is not None:
            object.__setattr__(self, "noise_stamp_size",
                               _stamp_size(self.noise_stamp_size, "noise_stamp_size"))
        if self.cube_format not in _vocabulary.CUBE_FORMATS:
            raise OptionError(f"cube_format must be zarr or fits, got {self.cube_format!r}",
                              option="cube_format")
        if self.pbcor and (self.image_corrected is True or (
                isinstance(self.image_corrected, (list, tuple))
                and any(c is True for c in self.image_corrected))):
            raise OptionError("pbcor=True (divide by the beam) contradicts image_corrected=True",
                              option=("pbcor", "image_corrected"))
        if self.beam_mask_arcsec is not None:
            try:
                radius = float(self.beam_mask_arcsec)
            except (TypeError, ValueError):
                radius = float("nan")
            if not radius > 0:
                raise OptionError(f"beam_mask_arcsec must be a positive radius in arcsec, got "
                                  f"{self.beam_mask_arcsec!r}", option="beam_mask_arcsec")
        self._parse_filter()

    def _parse_filter(self) -> None:
        """Set ``filter_cells`` or ``filter_uv`` from ``filter_lowfreq`` (validated)."""
        spec = self.filter_lowfreq
        if spec is None or spec is False:
            return
        if isinstance(spec, (int, np.integer)) and not isinstance(spec, bool):
            n = int(spec)
            if n < 1 or n % 2 == 0 or n >= self.stamp_size:
                raise OptionError(f"filter_lowfreq={n}: give an odd number of central Fourier "
                                  f"cells smaller than the stamp ({self.stamp_size})",
                                  option="filter_lowfreq")
            object.__setattr__(self, "filter_cells", n)
            return
        try:
            object.__setattr__(self, "filter_uv", parse_distance(spec))
        except XstackError as exc:
            raise OptionError(f"filter_lowfreq: {exc}", option="filter_lowfreq") from None

    @property
    def corrected(self) -> bool | None | Sequence[bool | None]:
        """``image_corrected`` as used: ``False`` (divide by A) when ``pbcor`` is set."""
        return False if self.pbcor else self.image_corrected

    def output_paths(self) -> dict[str, Path] | None:
        """The output names (``fits``, ``cube``, ``png`` unless ``plot`` is off), or None
        without ``out``. Names only: nothing on disk is looked at."""
        if self.out is None:
            return None
        paths = output_paths(self.out, self.cube_format)
        if not self.plot:
            paths.pop("png")
        return paths

    def to_dict(self) -> dict[str, Any]:
        """The options as JSON values (what the result's ``options`` holds): objects such as
        a primary-beam model or an array are described, not serialised."""
        return {f.name: _describe(getattr(self, f.name)) for f in fields(self) if f.init}


def _stamp_size(value: Any, option: str = "stamp_size") -> int:
    """``stamp_size`` (or another stamp side) as an int >= 5 (OptionError otherwise)."""
    try:
        ok = not isinstance(value, bool) and int(value) == value and value >= 5
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise OptionError(f"{option} must be an integer >= 5 pixels, got {value!r}",
                          option=option)
    return int(value)


def _describe(value: Any) -> Any:
    """A JSON value standing for an option's value (arrays and objects by their kind)."""
    if value is None or isinstance(value, (bool, int, float, str, np.generic, os.PathLike)):
        return json_ready(value)
    if isinstance(value, (list, tuple)):
        return [_describe(v) for v in value]
    if isinstance(value, np.ndarray):
        return f"array {'x'.join(str(n) for n in value.shape)}"
    if is_dataclass(value) and not isinstance(value, type):
        # e.g. a PrimaryBeam: its own fields say what it is
        return {"type": type(value).__name__,
                **{f.name: _describe(getattr(value, f.name)) for f in fields(value)}}
    return type(value).__name__


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


def _filter_mask(options: ImstackOptions, pix_x_arcsec: float, pix_y_arcsec: float,
                 freq_hz: float | None) -> np.ndarray | None:
    """The Fourier cells of a stamp to zero for ``filter_lowfreq`` (None: no filter)."""
    size = options.stamp_size
    if options.filter_cells is not None:
        return kernels.lowfreq_mask((size, size), n_central=options.filter_cells)
    if options.filter_uv is None:
        return None
    value, unit = options.filter_uv
    if unit == "m":
        if freq_hz is None:
            raise XstackError("filter_lowfreq in metres needs the image frequency; give it in "
                              "klambda or as a number of central Fourier cells",
                              option="filter_lowfreq")
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
            beam_mask_arcsec: float | None = None, noise_estimator: str = "clipped",
            noise_stamp_size: int | None = None, filter_lowfreq: int | str | None = None,
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
        ``"sigma2"``: W_k = 1/sigma_k^2 (paper eq. 3), sigma_k the local noise around
        position k: the ``noise_estimator`` of the ``noise_stamp_size`` pixels around it,
        outside a central circle of radius ``beam_mask_arcsec`` (default: the beam's major
        axis BMAJ). ``"pb"``: W_k = A^2 (the inverse variance of the corrected flux, the paper's
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
    noise_estimator
        How sigma_k is measured (the same estimators, and defaults, as the uv stack's
        ``noise_image``, :func:`xstack.uvstack.localnoise.measure_local_noise`):
        ``"clipped"`` (default) the 3-sigma clipped standard deviation, ``"mad"`` 1.4826 x
        the median absolute deviation, ``"std"`` the paper's plain standard deviation. A
        plain std counts what CLEAN left of the bright sources, and any faint source near a
        target, as noise and so down-weights the positions near them: on paper type 6 it
        made the stack 22 % low against the uv stack's 2 % (docs/reproduction.md).
    noise_stamp_size
        Side (pixels) of the square sigma_k is measured on, centered on each position's
        nearest pixel. Default: about 300 beam areas (paper §3.2), odd, at least 4 mask
        radii, at most the image; ``stamp_size`` for an image without a beam. The stamps
        stacked keep ``stamp_size``.
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
    options = ImstackOptions(stamp_size=stamp_size, method=method, weighting=weighting,
                             subpixel=subpixel, primary_beam=primary_beam, pbcor=pbcor, psf=psf,
                             image_corrected=image_corrected, beam_mask_arcsec=beam_mask_arcsec,
                             noise_estimator=noise_estimator, noise_stamp_size=noise_stamp_size,
                             filter_lowfreq=filter_lowfreq, skip_outside=skip_outside, out=out,
                             cube_format=cube_format, plot=plot, overwrite=overwrite,
                             progress=progress)
    inputs = _load(images, positions, options)   # outputs free, positions, images read
    plan = _plan(inputs, options)                # pixel grid, beams, who sees what, noise mask
    measured = _compute(plan, options)           # stamps, weights, the stack (numpy kernels)
    result = _assemble(plan, measured, options)  # xarray objects and the result
    if inputs.paths is not None:
        _save(result, plan, measured, options)
    return result


# ---------------------------------------------------------------------------------------------
# phases of stack_images: load -> plan -> compute -> assemble (-> save)
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Inputs:
    """The normalised inputs of one stack (what :func:`_load` returns)."""

    ra: np.ndarray                   # positions, deg
    dec: np.ndarray
    cat_w: np.ndarray | None         # the catalog's weight column
    infos: list[ImageInfo]           # the images read
    paths: dict[str, Path] | None    # output names (checked free), None without ``out``


@dataclass(frozen=True)
class _Plan:
    """Everything decided before a stamp is cut (what :func:`_plan` returns)."""

    inputs: _Inputs
    pixm: np.ndarray                 # the common pixel matrix, deg per pixel
    pix_x: float                     # pixel sizes along the image x and y axes, arcsec
    pix_y: float
    sx: float                        # the same, signed like CDELT1/CDELT2
    sy: float
    rho: float                       # angle of the y axis east of north, deg
    beam: tuple[float, float, float] | None  # (BMAJ, BMIN, BPA) arcsec, arcsec, deg
    convs: list[BeamConvention]      # primary-beam convention per image
    psfs: list[Any]                  # PSF option per image
    fmask: np.ndarray | None         # Fourier cells the low-frequency filter zeroes
    seen: np.ndarray                 # (n_pos, n_img) bool: position stacked from image
    pix: np.ndarray                  # (n_pos, n_img, 2) pixel x, y of each position
    atten: np.ndarray                # (n_pos, n_img) primary-beam attenuation A, NaN if unused
    unseen: np.ndarray               # rows outside every image
    radius: float                    # central mask radius, arcsec
    mask: np.ndarray                 # (size, size) bool: the central mask
    noise_size: int                  # side of the stamps sigma_k is measured on, pixels
    noise_mask: np.ndarray           # (noise_size, noise_size) bool: their central mask


@dataclass(frozen=True)
class _Measured:
    """The numbers of one stack (what :func:`_compute` returns); per-stamp arrays along
    the stamps in the order cut (image by image)."""

    stamps: np.ndarray               # (n_stamps, size, size), Jy/beam, A-corrected
    rows: np.ndarray                 # catalog row of each stamp
    img_idx: np.ndarray              # image of each stamp
    frac_x: np.ndarray               # sub-pixel offsets, pixels
    frac_y: np.ndarray
    pb_k: np.ndarray                 # A at each stamp's position (NaN if unused)
    sigma: np.ndarray                # local noise, Jy/beam
    w: np.ndarray                    # weights W_k
    stacked: np.ndarray              # (size, size), Jy/beam
    wsum: np.ndarray                 # per-pixel sum of weights (mean) or count (median)
    psf_stack: np.ndarray | None
    flux: float
    flux_err: float
    stamp_rms: float
    peak: float
    pixfac: float | None
    filter_response: float | None = None   # filtered / unfiltered PSF peak (filter_lowfreq)
    noise_flattened: bool = False          # sigma_k measured on a corrected image times A


def _load(images: ImageSource | Sequence[ImageSource], positions: Any,
          options: ImstackOptions) -> _Inputs:
    """Check the outputs are free (before any work), read the positions and the images."""
    paths = options.output_paths()
    if paths is not None:
        for p in paths.values():
            check_output(p, options.overwrite)
    ra, dec, cat_w = _positions(positions)
    if options.weighting == "column" and cat_w is None:
        raise OptionError("weighting 'column' needs a catalog with a weight column",
                          option="weighting")
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
        if options.stamp_size > min(ny, nx):
            raise XstackError(f"{info.name}: stamp size {options.stamp_size} is larger than the "
                              f"image ({nx} x {ny} pixels)")
    return _Inputs(ra=ra, dec=dec, cat_w=cat_w, infos=infos, paths=paths)


def _plan(inputs: _Inputs, options: ImstackOptions) -> _Plan:
    """Pixel grid, beam, primary-beam conventions, which image sees which position, the
    filter and the central mask: everything fixed before a stamp is cut."""
    infos = inputs.infos
    pixm = _check_grids(infos)
    # pixel sizes (arcsec) along the image x and y axes, signed like CDELT1/CDELT2 (for a
    # rotated image the stamp axes stay the pixel axes); rho = angle of the y axis east of north
    pix_x = float(np.hypot(pixm[0, 0], pixm[1, 0]) * 3600)
    pix_y = float(np.hypot(pixm[0, 1], pixm[1, 1]) * 3600)
    sx = pix_x * (-1.0 if pixm[0, 0] < 0 else 1.0)
    sy = pix_y * (-1.0 if pixm[1, 1] < 0 else 1.0)
    rho = float(np.degrees(np.arctan2(pixm[0, 1], pixm[1, 1])))
    beam = next((i.beam_arcsec for i in infos if i.beam_arcsec), None)
    pbs = _as_list(options.primary_beam, len(infos), "primary_beam")
    corr = _as_list(options.corrected, len(infos), "image_corrected")
    convs: list[BeamConvention] = [
        image_beam(info, pbs[i], corr[i], how_to_state="image_corrected=True/False")
        for i, info in enumerate(infos)]
    psfs = _as_list(options.psf, len(infos), "psf")
    fmask = _filter_mask(options, pix_x, pix_y, infos[0].frequency_hz)

    seen, pix, atten = _coverage(inputs, convs, options.weighting)
    n_pos = inputs.ra.size
    unseen = np.flatnonzero(~seen.any(axis=1))
    if unseen.size and not options.skip_outside:
        k = int(unseen[0])
        raise XstackError(f"{unseen.size} of {n_pos} positions are outside every image, e.g. row "
                          f"{k + 1} (ra={inputs.ra[k]:.6f}, dec={inputs.dec[k]:.6f} deg); remove "
                          "them or skip_outside")
    if unseen.size == n_pos:
        raise NoDataError("no position lies inside any image")

    # the central mask of the local noise and the stamp rms
    if options.beam_mask_arcsec is None:
        radius = beam[0] if beam else 5.0 * max(pix_x, pix_y)
    else:
        radius = float(options.beam_mask_arcsec)
    mask = kernels.central_mask(options.stamp_size, radius / pix_x, radius / pix_y)
    if mask.all():
        raise XstackError(f"stamp of {options.stamp_size} pixels is inside the central mask of "
                          f"radius {radius:.3g} arcsec: use a larger stamp")
    # the (larger) stamps sigma_k is measured on: ~300 beam areas as in the paper, so that a
    # CLEAN residual or a neighbour's sidelobe is a small part of them
    limit = min(min(info.shape) for info in infos)
    if options.noise_stamp_size is None:
        noise_size = kernels.noise_stamp_size(beam[:2] if beam else None, pix_x, pix_y, radius,
                                              limit, fallback=options.stamp_size)
    else:
        noise_size = options.noise_stamp_size
        if noise_size > limit:
            raise XstackError(f"noise stamp size {noise_size} is larger than an image "
                              f"({limit} pixels on its short side)", option="noise_stamp_size")
    noise_mask = kernels.central_mask(noise_size, radius / pix_x, radius / pix_y)
    if np.count_nonzero(~noise_mask) < kernels.MIN_NOISE_PIXELS:
        raise XstackError(f"a noise stamp of {noise_size} pixels is (almost) inside the central "
                          f"mask of radius {radius:.3g} arcsec: use a larger noise_stamp_size",
                          option="noise_stamp_size")
    return _Plan(inputs=inputs, pixm=pixm, pix_x=pix_x, pix_y=pix_y, sx=sx, sy=sy, rho=rho,
                 beam=beam, convs=convs, psfs=psfs, fmask=fmask, seen=seen, pix=pix, atten=atten,
                 unseen=unseen, radius=radius, mask=mask, noise_size=noise_size,
                 noise_mask=noise_mask)


def _coverage(inputs: _Inputs, convs: list[BeamConvention], weighting: str
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which image sees which position: (seen (n_pos, n_img) bool, pixel x/y
    (n_pos, n_img, 2), attenuation A (n_pos, n_img), NaN where not needed)."""
    ra, dec, infos = inputs.ra, inputs.dec, inputs.infos
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
    return seen, pix, atten


def _cut_stamps(plan: _Plan, options: ImstackOptions
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every (position, image) stamp, aligned, divided by A for an uncorrected image:
    (stamps, rows, image index, frac_x, frac_y), image by image."""
    infos = plan.inputs.infos
    blocks, meta = [], []
    for i in progress_iter(range(len(infos)), "imstack: stamps", options.progress and len(infos) > 1):
        rows = np.flatnonzero(plan.seen[:, i])
        if rows.size == 0:
            continue
        st, fx, fy = kernels.align_stamps(infos[i].data, plan.pix[rows, i, 0], plan.pix[rows, i, 1],
                                          options.stamp_size, options.subpixel)
        if not plan.convs[i].corrected:
            st /= plan.atten[rows, i][:, None, None]
        blocks.append(st)
        meta.append((rows, np.full(rows.size, i), fx, fy))
    return (np.concatenate(blocks), *(np.concatenate([m[j] for m in meta]) for j in range(4)))


def _local_noise(plan: _Plan, options: ImstackOptions, stamps: np.ndarray, rows: np.ndarray,
                 img_idx: np.ndarray) -> tuple[np.ndarray, bool]:
    """sigma_k of each stamp (Jy/beam of the corrected flux), in the order the stamps were cut,
    and whether it was measured on a primary-beam corrected image times A.

    sigma_k is measured where the noise is flat and then scaled to the position: on nearest-
    pixel stamps of ``plan.noise_size`` (cut in batches, memory bounded for 10^5 positions)
    of the uncorrected image -- the image itself, or a corrected image times its beam A --
    and divided by A at the position. (The noise of a corrected image grows as 1/A away
    from the pointing, so that its spread over a stamp of ~300 beams would count the beam's
    slope as noise: the far side of a stamp dominates the estimate.) On the stamps themselves
    when they have the noise stamp's size and no beam is known for a corrected image.
    """
    infos = plan.inputs.infos
    of_image = {int(i): np.flatnonzero(img_idx == i) for i in np.unique(img_idx)}
    # the noise stamps' centres on each image (a beam model is evaluated only where they read)
    centres = {i: (plan.pix[rows[sel], i, 0], plan.pix[rows[sel], i, 1])
               for i, sel in of_image.items()}
    flat = {i: flat_noise_image(infos[i], plan.convs[i], (*centres[i], plan.noise_size))
            for i in of_image}
    flattened = any(f for _, f in flat.values())
    if plan.noise_size == options.stamp_size and not flattened:
        return kernels.noise_sigma(stamps, plan.mask, options.noise_estimator)[0], False
    sigma = np.full(rows.size, np.nan)
    for i, sel in of_image.items():
        conv, (image, was_flattened) = plan.convs[i], flat[i]
        r = rows[sel]
        sig, _ = kernels.stamp_noise(image, *centres[i], plan.noise_size, plan.noise_mask,
                                     options.noise_estimator)
        a_k = plan.atten[r, i]
        if was_flattened and not np.all(np.isfinite(a_k)):  # A not needed for the weights
            a_k = np.asarray(conv.values(plan.inputs.ra[r], plan.inputs.dec[r]), np.float64)
        sigma[sel] = noise_to_corrected(sig, conv, was_flattened, a_k)
    return sigma, flattened


def _weights(sigma: np.ndarray, pb_k: np.ndarray, rows: np.ndarray, cat_w: np.ndarray | None,
             weighting: str) -> np.ndarray:
    """The weight W_k of each stamp (paper eq. 3 for ``sigma2``)."""
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
    return w


def _compute(plan: _Plan, options: ImstackOptions) -> _Measured:
    """Cut the stamps, weigh them, stack them; the stack's noise, PSF, filter and numbers."""
    stamps, rows, img_idx, frac_x, frac_y = _cut_stamps(plan, options)
    pb_k = plan.atten[rows, img_idx]
    sigma, noise_flattened = _local_noise(plan, options, stamps, rows, img_idx)
    w = _weights(sigma, pb_k, rows, plan.inputs.cat_w, options.weighting)

    if options.method == "mean":
        stacked, wsum = kernels.weighted_nanmean(stamps, w)
    else:
        use = w > 0
        stacked, wsum = kernels.nanmedian_stack(stamps[use])
    c = options.stamp_size // 2
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
    flux_err = kernels.weighted_error(sigma[center_ok], w[center_ok] if options.method == "mean"
                                      else np.ones(int(center_ok.sum())))
    if options.method == "median":
        flux_err *= kernels.MEDIAN_NOISE_FACTOR

    psf_stack = _psf_stack(plan.inputs.infos, plan.psfs, options.stamp_size, img_idx, frac_x,
                           frac_y, w, options.subpixel)
    # the low-spatial-frequency filter (paper §5.3), on the stack and its PSF alike
    response = None
    if plan.fmask is not None:
        stacked = kernels.lowfreq_filter(stacked, plan.fmask)
        if psf_stack is not None:
            unfiltered_peak = float(psf_stack[c, c])
            psf_stack = kernels.lowfreq_filter(psf_stack, plan.fmask)
            # the filter removes the short spacings' share of every point source's peak too
            # (a third of it at 5000 m for VLA A): the filtered PSF's peak relative to the
            # unfiltered one is that share, so the filtered peak divided by it is a flux again
            response = float(psf_stack[c, c]) / unfiltered_peak
        else:
            warnings.warn(XstackWarning(
                "filter_lowfreq without a PSF: flux_jy is the filtered peak, lower than the "
                "sources' flux by the filter's unknown response; give the PSF image (psf=)",
                option="psf"), stacklevel=2)

    flux = float(stacked[c, c])
    if response is not None and response > 0:
        flux /= response
        flux_err /= response
    outside = stacked[~plan.mask]
    stamp_rms = float(np.nanstd(outside)) if np.isfinite(outside).sum() > 1 else float("nan")
    inner = np.where(plan.mask, stacked, np.nan)
    peak = float(np.nanmax(inner)) if np.isfinite(inner).any() else float("nan")
    pixfac = None
    if plan.beam and not options.subpixel:
        beam = plan.beam
        pixfac = kernels.pixelisation_factor(beam[0], beam[1], beam[2] - plan.rho, plan.pix_x,
                                             plan.pix_y)
    return _Measured(stamps=stamps, rows=rows, img_idx=img_idx, frac_x=frac_x, frac_y=frac_y,
                     pb_k=pb_k, sigma=sigma, w=w, stacked=stacked, wsum=wsum, psf_stack=psf_stack,
                     flux=flux, flux_err=flux_err, stamp_rms=stamp_rms, peak=peak, pixfac=pixfac,
                     filter_response=response, noise_flattened=noise_flattened)


def _assemble(plan: _Plan, m: _Measured, options: ImstackOptions) -> ImstackResult:
    """The result: the cube, the stack and its PSF as xarray objects (arcsec offsets), the
    weights table, the numbers and the options used."""
    infos, ra, dec = plan.inputs.infos, plan.inputs.ra, plan.inputs.dec
    off = kernels.offsets_grid(options.stamp_size)
    # x = offset along the image x axis as Delta(RA) cos(dec) (east positive; it decreases with
    # the pixel index for the usual CDELT1 < 0), y = offset north
    xcoord = xr.Variable("x", off * plan.sx + 0.0, attrs={"units": "arcsec",
                         "long_name": "offset east (Delta RA cos Dec) along the image x axis"})
    ycoord = xr.Variable("y", off * plan.sy + 0.0, attrs={"units": "arcsec",
                         "long_name": "offset north along the image y axis"})
    grid = {"x": xcoord, "y": ycoord}
    bunit = infos[0].bunit or "Jy/beam"
    cube = xr.DataArray(
        m.stamps, dims=("source", "y", "x"),
        coords={**grid,
                "position": ("source", m.rows.astype(np.int64)),
                "image": ("source", m.img_idx.astype(np.int64)),
                "ra": ("source", ra[m.rows], {"units": "deg"}),
                "dec": ("source", dec[m.rows], {"units": "deg"}),
                "weight": ("source", m.w),
                "sigma": ("source", m.sigma, {"units": bunit}),
                "pb": ("source", m.pb_k),
                "frac_x": ("source", m.frac_x, {"units": "pixel"}),
                "frac_y": ("source", m.frac_y, {"units": "pixel"})},
        name="stamps", attrs={"units": bunit, "method": options.method,
                              "weighting": options.weighting,
                              "subpixel": str(options.subpixel or "nearest"),
                              "stamp_size": options.stamp_size})
    weights = np.zeros((ra.size, len(infos)))
    weights[m.rows, m.img_idx] = m.w
    stacked_da = xr.DataArray(m.stacked, dims=("y", "x"), coords=grid, name="stacked",
                              attrs={"units": bunit})
    wsum_da = xr.DataArray(m.wsum, dims=("y", "x"), coords=grid,
                           name="weight_sum" if options.method == "mean" else "n_stamps")
    # psf_smeared, as the FITS card PSFSMEAR: fit_image keeps such a PSF's peak (< 1)
    psf_da = None if m.psf_stack is None else xr.DataArray(
        m.psf_stack, dims=("y", "x"), coords=grid, name="psf",
        attrs={"psf_smeared": not options.subpixel})
    used = {**options.to_dict(), "n_images": len(infos), "mask_radius_arcsec": plan.radius}
    return ImstackResult(
        cube=cube, weights=weights, stacked=stacked_da, flux_jy=m.flux, flux_err_jy=m.flux_err,
        n_positions=int(np.unique(m.rows[m.w > 0]).size), psf_stamp=psf_da, weight_sum=wsum_da,
        n_stamps=int(np.sum(m.w > 0)), stamp_rms_jy=m.stamp_rms, peak_jy=m.peak,
        method=options.method, weighting=options.weighting, subpixel=options.subpixel,
        beam_arcsec=plan.beam, mask_radius_arcsec=plan.radius,
        noise_estimator=options.noise_estimator, noise_stamp_size=plan.noise_size,
        noise_flattened=m.noise_flattened, pixel_arcsec=(plan.pix_x, plan.pix_y),
        pixelisation_factor=m.pixfac,
        filter_lowfreq=options.filter_lowfreq, filter_response=m.filter_response,
        skipped_rows=[int(k) + 1 for k in plan.unseen],
        primary_beam=[dict(c.to_dict(), image=info.name) for c, info in zip(plan.convs, infos)],
        options=used)


def _save(result: ImstackResult, plan: _Plan, m: _Measured, options: ImstackOptions) -> None:
    """Write the outputs (atomically); the stamp's nominal center is the weighted mean
    stacking position."""
    ra, dec = plan.inputs.ra[m.rows], plan.inputs.dec[m.rows]
    ra0, dec0 = _mean_position(ra, dec, np.where(m.w > 0, m.w, 0) / np.sum(m.w))
    _write_outputs(result, plan.inputs.paths, plan.pixm, ra0, dec0, options.overwrite)



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
        ("STNOISE", result.noise_estimator, "sigma_k estimator: clipped, mad, std"),
        ("STNOISEN", int(result.noise_stamp_size), "[pixel] side of the sigma_k stamps"),
        ("STNOISEF", bool(result.noise_flattened), "sigma_k measured on image x PB, / PB"),
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
