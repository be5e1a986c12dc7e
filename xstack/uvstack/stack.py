"""uv-stacking (paper section 3.3) as a lazy dask/xarray pipeline: the public API.

``stack_uv(data, positions, ...)`` phase-rotates every visibility of every partition by the
normalised phasor of equation 4 (:mod:`xstack.uvstack.kernels`), multiplies the visibility
weights of each pointing by the sum of its position weights (section 3.3.2), and estimates
the point-source flux of the stack as the weighted mean of Re V over the unflagged parallel
hands in the uv range (section 3.3.1). The stacked data stay lazy (dask) until written or
computed; the flux needs one pass over the data, and writing ``out=`` happens in that same
pass (the written stack and the flux sums share each chunk's phasor).

See ``docs/uvstack.md`` for the user documentation and the choices made where the paper is
silent.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import dask
import dask.array as da
import numpy as np
import xarray as xr
from astropy.table import Table

from xstack import _options as _opt
from xstack import _vocabulary
from xstack._antenna import ANTENNA_TOL_RAD, MIN_ROWS_PER_ANTENNA
from xstack._inputs import Positions, grouped_partitions
from xstack._lazy import LazyResult
from xstack._result import Result
from xstack._scatter import EMPIRICAL_TOLERANCE
from xstack._select import (
    UVLimit,
    parallel_hand_mask,
    parse_uv_limit,
    sky_correlations,
    uv_limits,
    uv_range_mask,
)
from xstack.beams import DEFAULT_PB_CUTOFF, dish_diameter, inside_field, standard_beam
from xstack.coords import (
    angular_separation,
    mean_direction,
    radec_to_lmn,
)
from xstack.errors import NoDataError, OptionError, WeightsWarning, XstackError, XstackWarning
from xstack.schema import default_time_chunk
from xstack.uvstack import kernels
from xstack.uvstack import smearing as _smearing
from xstack.uvstack.profile import plot_uv_profile, uv_profile  # noqa: F401  (public re-export)

WEIGHTINGS = _vocabulary.UVSTACK_WEIGHTINGS
ENGINES = _vocabulary.UVSTACK_ENGINES
ERRORS = _vocabulary.UVSTACK_ERRORS
#: Engines that evaluate a block of rows, in the order of their row counters in the sums
#: (after the _NSUMS flux sums of :func:`kernels.stack_sums`) and their codes in the trailing
#: column of a chunk's shared phasor.
_ROW_ENGINES = ("numba", "antenna", "numpy", "nufft")
#: Flux sums per chunk (:func:`kernels.stack_sums`: flux, weights, variance from the weights,
#: imaginary part, count, variance from the measured noise, counts of its two fallbacks)
_NSUMS = kernels.NSUMS
#: Measure the visibility noise per block for ``flux_err_empirical_jy`` (benchmarks switch
#: it off to time what it costs; the error is then NaN)
_EMPIRICAL_SUMS = True


@dataclass(kw_only=True)
class StackResult(Result):
    """The result of :func:`stack_uv`.

    Attributes
    ----------
    stacked
        Partition name -> lazy stacked :class:`xarray.Dataset` in the xstack schema.
    flux_jy, flux_err_jy
        Weighted mean of Re V of the stack (Jy) and its 1-sigma uncertainty from the weights
        (WEIGHT taken as 1/sigma^2 per real/imaginary part).
    flux_err_empirical_jy
        The same uncertainty with the noise measured from the visibilities (scatter of
        neighbouring channels, or integrations for one channel; :mod:`xstack._scatter`) in
        place of 1/WEIGHT: right whatever the weights' scale. NaN if not measured.
    weight_scale
        ``(flux_err_empirical_jy / flux_err_jy)^2``: the measured variance over the variance
        the weights claim, averaged as the error bar weighs it (1 for honest weights).
    noise_estimate
        Where the measured noise came from: ``pairs`` (``channels``, ``integrations`` or
        ``mixed``), and the visibilities of the flux whose variance is ``own`` (their
        baseline's and correlation's estimate in their block), ``pooled`` (too few pairs:
        their weights rescaled by one measured factor for the block) or ``weights`` (too few
        pairs in the whole block: 1/WEIGHT as it is).
    flux_imag_jy
        The same mean of Im V (zero within errors for a real stacked source).
    n_positions
        Catalog positions that entered at least one pointing (duplicates count).
    n_visibilities
        Visibilities (unflagged, selected polarizations, in uv range, weight > 0) in the flux.
    positions
        The catalog with per-partition columns: ``used`` (n_partitions bool), ``weight_used``
        (W_k per partition), ``attenuation`` (A_k at the partition's mean frequency),
        ``n_pointings``; ``meta["partitions"]`` names the partitions in column order.
    uncovered
        Catalog rows covered by no pointing (not used).
    options
        The options used (JSON-ready).
    profile
        With ``profile_bins``: the uv-profile of the stacked visibilities
        (:func:`~xstack.uvstack.profile.uv_profile`'s table), made in the stack's own pass over
        the data; else None.
    """

    stacked: dict[str, xr.Dataset]
    flux_jy: float
    flux_err_jy: float
    n_positions: int
    n_visibilities: int
    positions: Table
    options: dict[str, Any]
    uncovered: Table
    flux_imag_jy: float = 0.0
    partition_sums: dict[str, list[float]] = field(default_factory=dict)
    flux_err_empirical_jy: float = float("nan")
    weight_scale: float = float("nan")
    noise_estimate: dict[str, Any] = field(default_factory=dict)
    profile: Table | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: flux_jy, flux_err_jy, flux_err_empirical_jy, weight_scale,
        noise_estimate, n_positions, n_visibilities, options (NaN as None)."""
        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {
            "flux_jy": float(self.flux_jy),
            "flux_err_jy": float(self.flux_err_jy),
            "flux_err_empirical_jy": num(self.flux_err_empirical_jy),
            "weight_scale": num(self.weight_scale),
            "noise_estimate": dict(self.noise_estimate),
            "flux_imag_jy": float(self.flux_imag_jy),
            "n_positions": int(self.n_positions),
            "n_visibilities": int(self.n_visibilities),
            "n_uncovered": len(self.uncovered),
            "partitions": sorted(self.stacked),
            "options": self.options,
        }

    def table(self) -> Table:
        """One row per catalog position: the catalog with ``used``, ``weight_used``,
        ``attenuation``, ``smearing_loss`` (one column per partition) and ``n_pointings``."""
        return Table(self.positions, copy=True)


# --- options ------------------------------------------------------------------------------

#: Model primary beams by name (:func:`xstack.beams.standard_beam`); anything else must be a
#: FITS image path
_BEAM_MODELS = ("auto", "airy", "gaussian", "none")
_FITS_SUFFIXES = (".fits", ".fit", ".fits.gz")


def _is_fits_path(primary_beam: Any) -> bool:
    return isinstance(primary_beam, (str, os.PathLike)) and \
        str(primary_beam).lower().endswith(_FITS_SUFFIXES)


def _option_error(name: str, message: str) -> OptionError:
    return OptionError(message, option=name)


@dataclass(frozen=True, kw_only=True)
class UvstackOptions:
    """Every option of :func:`stack_uv`, validated when constructed (before any data is read).

    The fields, their defaults and their meaning are the keyword arguments of
    :func:`stack_uv`. A bad value raises :class:`~xstack.errors.OptionError` (a
    :class:`ValueError`) naming the parameter, also in its ``option`` attribute.
    ``polarizations`` is kept as ``"parallel"``, ``"all"`` or a tuple of correlation names
    (a string other than the first two is a comma-separated list; None is ``"parallel"``).

    Attributes
    ----------
    uv_lo, uv_hi
        Derived: ``uvmin`` and ``uvmax`` parsed to ``(value, "m" | "lambda")`` (metres or
        wavelengths, :func:`xstack._select.parse_uv_limit`), or None for no limit.
    """

    weighting: str = "pb"
    primary_beam: Any = "auto"
    pb_cutoff: float = DEFAULT_PB_CUTOFF
    uvmin: Any = None
    uvmax: Any = None
    # arrays: not compared (their == is elementwise)
    sigma: Any = field(default=None, compare=False)
    noise_image: Any = field(default=None, compare=False)
    polarizations: Any = "parallel"
    engine: str = "auto"
    out: str | os.PathLike | None = None
    overwrite: bool = False
    progress: bool = False
    antenna_tol_rad: float = ANTENNA_TOL_RAD
    autocorrelations: bool = False
    smearing: str = "auto"
    profile_bins: Any = field(default=None, compare=False)
    uv_lo: UVLimit | None = field(init=False, default=None)
    uv_hi: UVLimit | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        _opt.choice("weighting", self.weighting, WEIGHTINGS)
        _opt.choice("engine", self.engine, ENGINES)
        _opt.choice("smearing", self.smearing, _smearing.MODES)
        try:
            cutoff = float(self.pb_cutoff)
        except (TypeError, ValueError):
            cutoff = float("nan")
        if not 0 <= cutoff < 1:
            raise _option_error("pb_cutoff", f"pb_cutoff must be in [0, 1), got {self.pb_cutoff}")
        self._check_primary_beam()
        self._set_uv_limits()
        self._check_sigma()
        self._set_polarizations()
        self._check_profile_bins()
        try:
            tol = float(self.antenna_tol_rad)
        except (TypeError, ValueError):
            tol = float("nan")
        if not (np.isfinite(tol) and tol >= 0):
            raise _option_error("antenna_tol_rad", "antenna_tol_rad must be a finite angle >= 0 "
                                f"(radians), got {self.antenna_tol_rad!r}")

    def _check_profile_bins(self) -> None:
        bins = self.profile_bins
        if bins is None:
            return
        if np.ndim(bins) == 0:
            if isinstance(bins, bool) or not isinstance(bins, (int, np.integer)) or bins < 1:
                raise _option_error("profile_bins", "profile_bins must be a number of bins >= 1 "
                                    f"or increasing bin edges in kilo-wavelengths, got {bins!r}")
            return
        edges = np.asarray(bins, dtype=np.float64)
        if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
            raise _option_error("profile_bins", "profile_bins edges must be increasing "
                                "(kilo-wavelengths)")

    def _check_primary_beam(self) -> None:
        beam = self.primary_beam
        if not _is_fits_path(beam) and str(beam).lower() not in _BEAM_MODELS:
            raise _option_error("primary_beam", f"unknown primary beam {beam!r} (primary_beam: "
                                f"{', '.join(_BEAM_MODELS)} or a FITS file)")

    def _set_uv_limits(self) -> None:
        for name in ("uvmin", "uvmax"):
            try:
                parse_uv_limit(getattr(self, name))
            except XstackError as exc:
                raise _option_error(name, f"{name}: {exc}") from None
        lo, hi = uv_limits(self.uvmin, self.uvmax)
        # frozen: derived fields are set once, here
        object.__setattr__(self, "uv_lo", lo)
        object.__setattr__(self, "uv_hi", hi)

    def _check_sigma(self) -> None:
        if self.noise_image is not None:
            if self.weighting != "sigma2":
                raise _option_error("noise_image", "noise_image is used only with "
                                    f"weighting='sigma2' (got {self.weighting!r})")
            if self.sigma is not None:
                raise _option_error(("sigma", "noise_image"), "give sigma= or noise_image=, "
                                    "not both")
        if self.sigma is not None:
            try:
                np.asarray(self.sigma, dtype=np.float64)
            except (TypeError, ValueError):
                raise _option_error("sigma", "sigma must be one number or one per position "
                                    "(Jy)") from None

    def _set_polarizations(self) -> None:
        pols = self.polarizations
        if pols is None:
            pols = "parallel"
        elif isinstance(pols, str) and pols not in ("parallel", "all"):
            pols = tuple(p.strip() for p in pols.split(",") if p.strip())
        elif not isinstance(pols, str):
            try:
                pols = tuple(str(p) for p in pols)
            except TypeError:
                raise _option_error("polarizations", "polarizations must be 'parallel', 'all' "
                                    f"or a list of correlation names, got {pols!r}") from None
        if not pols:
            raise _option_error("polarizations", "polarizations: no correlation name given")
        object.__setattr__(self, "polarizations", pols)

    def to_dict(self) -> dict[str, Any]:
        """The options recorded in :attr:`StackResult.options` (JSON-ready, in this order).

        ``sigma``, ``noise_image``, ``out``, ``overwrite``, ``progress``,
        ``antenna_tol_rad`` and ``profile_bins`` are not recorded (the result records what sigma_k were used);
        the stacking adds ``smearing_corrected``, ``sigma``, ``stack_center_deg``,
        ``local_noise`` and ``engine_rows``, and replaces ``engine`` by the engine that ran.
        """
        pols = self.polarizations
        return {
            "weighting": self.weighting,
            "primary_beam": (str(Path(self.primary_beam)) if _is_fits_path(self.primary_beam)
                             else str(self.primary_beam)),
            "pb_cutoff": float(self.pb_cutoff),
            "uvmin": None if self.uvmin is None else str(self.uvmin),
            "uvmax": None if self.uvmax is None else str(self.uvmax),
            "polarizations": pols if isinstance(pols, str) else list(pols),
            "autocorrelations": bool(self.autocorrelations),
            "smearing": self.smearing,
            "engine": self.engine,
        }


# --- inputs -------------------------------------------------------------------------------

def _load_datasets(data: Any) -> list[tuple[str, list[tuple[str, xr.Dataset]]]]:
    """Normalise ``data`` to [(label, [(partition name, Dataset), ...]), ...].

    See :func:`xstack._inputs.grouped_partitions` (MeasurementSets converted lazily).
    """
    # in-memory partitions may lack baseline antenna ids (the numba engine does not need them)
    return grouped_partitions(data, prefix="xstack-uvstack-", validate=False)


def _positions_table(positions: Any) -> Table:
    return Positions.from_any(positions).as_table()


class FitsBeam:
    """A primary-beam image (FITS, CASA ``.pb`` style) used as A(offset, frequency).

    The image is taken to describe the beam of *any* pointing: a position's offset (l, m)
    from the pointing center is looked up at the same offset from the image's reference
    direction (CRVAL). With a spectral axis the plane nearest in frequency is used per
    channel; without one the single plane is used for every channel. Bilinear interpolation;
    zero outside the image and where the image is blank (NaN).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        from astropy.io import fits
        from astropy.wcs import WCS

        path = Path(path)
        if not path.is_file():
            raise XstackError(f"{path}: no such primary-beam FITS file")
        try:
            with fits.open(path) as hdul:
                hdu = next(h for h in hdul if h.data is not None and h.data.ndim >= 2)
                data = np.asarray(hdu.data, dtype=np.float64)
                header = hdu.header
        except StopIteration:
            raise XstackError(f"{path}: no image in the FITS file") from None
        except OSError as exc:
            raise XstackError(f"{path}: cannot read FITS ({exc})") from None
        wcs = WCS(header)
        self.celestial = wcs.celestial
        self.ra0, self.dec0 = np.radians(self.celestial.wcs.crval[:2])
        self.freqs = None
        naxis = wcs.naxis
        # numpy axes are reversed FITS axes; keep the two celestial and the spectral axis
        spec_axis = wcs.wcs.spec if wcs.wcs.spec >= 0 else None
        planes = np.moveaxis(data, [naxis - 1 - a for a in range(naxis)], list(range(naxis)))
        # planes now indexed [x, y, axis3, axis4...] in FITS order
        index = [slice(None)] * naxis
        for a in range(2, naxis):
            if a != spec_axis:
                index[a] = 0
        planes = planes[tuple(index)]
        if spec_axis is not None and spec_axis >= 2:
            nspec = data.shape[naxis - 1 - spec_axis]
            pix = np.zeros((nspec, naxis))
            pix[:, spec_axis] = np.arange(nspec)
            world = wcs.wcs_pix2world(pix, 0)
            spec = wcs.wcs.ctype[spec_axis].upper()
            if not spec.startswith("FREQ"):
                raise XstackError(f"{path}: spectral axis {spec} is not frequency")
            self.freqs = world[:, spec_axis] * (1.0 if wcs.wcs.cunit[spec_axis] == "Hz" else 1.0)
            self.planes = np.moveaxis(planes, -1, 0)  # (nspec, x, y)
        else:
            self.planes = planes[None]  # (1, x, y)
        self.path = str(path)

    def attenuation(self, l: np.ndarray, m: np.ndarray, frequency: np.ndarray) -> np.ndarray:
        """A(l, m, nu) -> (npos, nchan) for offsets (l, m) from the pointing center."""
        from scipy.ndimage import map_coordinates

        from xstack.coords import lm_to_radec

        ra, dec = lm_to_radec(l, m, self.ra0, self.dec0)
        x, y = self.celestial.wcs_world2pix(np.degrees(ra), np.degrees(dec), 0)
        if self.freqs is None:
            which = np.zeros(len(frequency), dtype=int)
        else:
            which = np.abs(self.freqs[:, None] - np.asarray(frequency)[None, :]).argmin(axis=0)
        out = np.empty((len(l), len(frequency)))
        cache: dict[int, np.ndarray] = {}
        for c, p in enumerate(which):
            if p not in cache:
                plane = np.nan_to_num(self.planes[p], nan=0.0)
                cache[p] = map_coordinates(plane, [x, y], order=1, mode="constant", cval=0.0)
            out[:, c] = cache[p]
        return np.clip(out, 0.0, None)


def _beam_for(primary_beam: Any, ds: xr.Dataset, cutoff: float):
    """Return a function (theta, l, m, freq) -> A (npos, nchan) for one partition."""
    if isinstance(primary_beam, FitsBeam):
        return lambda theta, l, m, f: primary_beam.attenuation(l, m, f)
    name = str(primary_beam).lower()
    telescope = str(ds.attrs.get("telescope_name", "unknown"))
    dish = dish_diameter(ds)
    if name == "auto":
        beam = standard_beam(telescope, dish, cutoff=cutoff)
    elif name in ("airy", "gaussian", "none"):
        beam = standard_beam(telescope, dish, model=name, cutoff=cutoff)
    else:
        raise XstackError(f"unknown primary beam {primary_beam!r} (use auto, airy, gaussian, none "
                          "or a FITS file)")
    return lambda theta, l, m, f: beam.main_lobe(theta[:, None], np.asarray(f)[None, :])


def _pol_mask(ds: xr.Dataset, polarizations: Any, where: str) -> np.ndarray:
    pols = [str(p).upper() for p in ds["polarization"].values]
    if polarizations in ("parallel", None):
        mask = parallel_hand_mask(pols)
    elif polarizations == "all":
        mask = np.ones(len(pols), dtype=bool)
    else:
        want = {str(p).upper() for p in polarizations}
        mask = np.array([p in want for p in pols])
    if not mask.any():
        raise XstackError(f"{where}: no selected polarization among {pols}")
    return mask


# --- block functions (top level: picklable for dask.distributed) ---------------------------

def _block_phasor(uvw_block, params, frequency, engine, antennas=None, rows=None,
                  tol_rad=ANTENNA_TOL_RAD):
    """Phasor of one (time, baseline) block and the engine that computed it.

    params = [l, m, n-1, coef_0..coef_{nchan-1}]; ``antennas`` = (antenna1, antenna2) ids of
    the block's baselines. ``auto`` takes the per-antenna kernel when the block's baseline UVW
    factorise to ``tol_rad`` (and it saves work), else the per-row ``numba`` kernel;
    ``antenna`` raises :class:`XstackError` where it does not apply. ``rows`` (nt * nb bool):
    the rows whose phasor is needed (the antenna path returns 0 for the others).
    """
    nt, nb = uvw_block.shape[:2]
    uvw = uvw_block.reshape(nt * nb, 3)
    l, m, n1 = params[:, 0], params[:, 1], params[:, 2]
    coef = params[:, 3:]
    if engine in ("auto", "antenna"):
        try:
            if antennas is None:
                raise kernels.FactorisationError("no baseline antenna ids in the data")
            ph, _ = kernels.phasor_antenna(
                uvw, frequency, l, m, n1, coef, *antennas, rows=rows, tol_rad=tol_rad,
                min_rows_per_antenna=MIN_ROWS_PER_ANTENNA if engine == "auto" else 0.0)
            return ph.reshape(nt, nb, len(frequency)), "antenna"
        except kernels.FactorisationError as exc:
            if engine == "antenna":
                raise XstackError(f"engine='antenna' is not valid for these data: {exc}") from exc
        engine = "numba"
    ph = kernels.phasor_from_coefficients(uvw, frequency, l, m, n1, coef, engine=engine)
    return ph.reshape(nt, nb, len(frequency)), engine


#: Bytes of phasor (complex128 per row and channel) evaluated at a time inside a chunk: the
#: phasor's temporaries stay a few steps of this size whatever the chunk and the number of
#: channels (a fixed row count made a whole 256-channel chunk's phasor at once: 1x the chunk)
_STEP_BYTES = 8 * 2**20


def _rows_per_step(nchan: int) -> int:
    return max(1, _STEP_BYTES // (16 * max(int(nchan), 1)))


def _steps(nt, nb, nchan):
    """(time slice, baseline slice) sub-blocks whose phasor holds about ``_STEP_BYTES``.

    Whole integrations when they fit (the antenna path factorises per integration), else
    baseline ranges of one integration (a subset of baselines factorises as well).
    """
    rows = _rows_per_step(nchan)
    if nb <= rows:
        tstep = max(1, rows // max(nb, 1))
        for t0 in range(0, nt, tstep):
            yield slice(t0, t0 + tstep), slice(None)
    else:
        for t0 in range(nt):
            for b0 in range(0, nb, rows):
                yield slice(t0, t0 + 1), slice(b0, b0 + rows)


def _antennas(a1, a2, bsl):
    return None if a1 is None else (a1[bsl], a2[bsl])


def _block_phasor_chunk(uvw, params, a1, a2, frequency, engine, tol_rad):
    """The whole chunk's phasor, shared by stack and sums: (nt, nb, nchan + 1) complex128.

    The trailing column holds the index in ``_ROW_ENGINES`` of the engine that computed the
    row (a dask task returns one array, and the sums count rows per engine).
    """
    nt, nb = uvw.shape[:2]
    nchan = len(frequency)
    ph = np.empty((nt, nb, nchan + 1), dtype=np.complex128)
    for tsl, bsl in _steps(nt, nb, nchan):
        ph[tsl, bsl, :nchan], used = _block_phasor(uvw[tsl, bsl], params, frequency, engine,
                                                   _antennas(a1, a2, bsl), tol_rad=tol_rad)
        ph[tsl, bsl, nchan] = _ROW_ENGINES.index(used)
    return ph


def _block_apply_phasor(vis, ph, out=None):
    # NaN under flags stays NaN (flagged); the output keeps the input precision. Multiplied
    # into ``out`` (numpy casts per buffer): no whole-chunk complex128 temporary, the same
    # bits as (vis * ph).astype(vis.dtype), 4x faster on a 128 MB chunk
    if out is None:
        out = np.empty_like(vis)
    return np.multiply(vis, ph[..., None], out=out, casting="same_kind")


def _engine_rows(counts):
    return np.array([counts.get(e, 0) for e in _ROW_ENGINES], dtype=np.float64)


def _block_noise(vis, weight, flag, pol_mask):
    """The block's measured noise model per (baseline, correlation) (:mod:`xstack._scatter`),
    or None when switched off. Estimated from this block alone (its times, all channels):
    the data are read once, for the flux and the noise together."""
    if not _EMPIRICAL_SUMS:
        return None
    from xstack._scatter import noise_model

    return noise_model(vis, weight, flag, pol_mask=np.asarray(pol_mask, dtype=bool))


def _finish_empirical(total):
    if not _EMPIRICAL_SUMS:
        total[5] = np.nan
    return total


def _block_sums(vis, weight, flag, uvw, params, a1, a2, frequency, engine, tol_rad, pol_mask,
                lo, hi, stacked=None):
    """The flux sums of one chunk (1, 1, NSUMS + engines), the phasor evaluated per row step
    (:func:`_steps`). With ``stacked`` (an array like ``vis``) the stacked visibilities are
    written into it from the same phasor; without, the phasor is evaluated only for the rows
    that carry weight in the selected polarizations."""
    total = np.zeros(_NSUMS)
    counts: dict[str, int] = {}
    pm = np.asarray(pol_mask, dtype=bool)
    noise = _block_noise(vis, weight, flag, pm)
    for tsl, bsl in _steps(*vis.shape[:3]):
        v, w, f, x = (a[tsl, bsl] for a in (vis, weight, flag, uvw))
        nt, nb, nc, npol = v.shape
        n = nt * nb
        v, w, f = v.reshape(n, nc, npol), w.reshape(n, nc, npol), f.reshape(n, nc, npol)
        # the flux needs the phasor only where some selected visibility carries weight
        rows = None if stacked is not None else np.any(~f[:, :, pm] & (w[:, :, pm] > 0), axis=(1, 2))
        ph, used = _block_phasor(x, params, frequency, engine, _antennas(a1, a2, bsl), rows=rows,
                                 tol_rad=tol_rad)
        counts[used] = counts.get(used, 0) + n
        if stacked is not None:
            _block_apply_phasor(v.reshape(nt, nb, nc, npol), ph, out=stacked[tsl, bsl])
        mask = uv_range_mask(x.reshape(n, 3), frequency, lo, hi)
        total += kernels.stack_sums(v, w, f, ph.reshape(n, nc), pol_mask, mask,
                                    None if noise is None else noise[bsl])
    return np.concatenate([_finish_empirical(total), _engine_rows(counts)])[None, None, :]


def _block_stack_and_sums(vis, weight, flag, uvw, params, a1, a2, frequency, engine, tol_rad,
                          pol_mask, lo, hi):
    """The stacked visibilities and the flux sums of one chunk, from one phasor evaluation
    per row step: the chunk's phasor is never held whole, so writing the stack costs one
    output chunk beside the input, and the sums add in the same order as the flux-only pass
    (:func:`_block_sums`), so both give the same flux to the last bit.

    Returns ``(stacked, sums)``: stacked (nt, nb, nchan, npol) in the input's precision, sums
    (1, 1, NSUMS + engines) as :func:`_block_sums`.
    """
    stacked = np.empty_like(vis)
    sums = _block_sums(vis, weight, flag, uvw, params, a1, a2, frequency, engine, tol_rad,
                       pol_mask, lo, hi, stacked=stacked)
    return stacked, sums


def _first(pair):
    return pair[0]


def _second(pair):
    return pair[1]


# --- planning -----------------------------------------------------------------------------

@dataclass
class _Plan:
    name: str
    ds: xr.Dataset
    used: np.ndarray  # (npos,) bool
    weight: np.ndarray  # (npos,) W_k (0 where unused)
    attenuation: np.ndarray  # (npos,) A at the mean frequency
    sum_weight: float
    params: np.ndarray  # (nused, 3 + nchan)
    pol_mask: np.ndarray
    #: (npos,) 1 - L_k at the mean frequency (0 where unused or not corrected), and the
    #: smearing effects corrected (xstack.uvstack.smearing)
    smearing_loss: np.ndarray | None = None
    smearing_effects: tuple[bool, bool] = (False, False)


def _geometry(ds, ra, dec, beam_spec, cutoff):
    """Positions in one pointing: (l, m, n - 1, A (npos, nchan), A at the mean frequency,
    used = inside the primary beam)."""
    ra0, dec0 = (float(x) for x in ds.attrs["phase_center"])
    freq = np.asarray(ds["frequency"].values, dtype=np.float64)
    l, m, n, n1 = radec_to_lmn(ra, dec, ra0, dec0)
    theta = angular_separation(ra0, dec0, ra, dec)
    beam = _beam_for(beam_spec, ds, cutoff)
    att = np.asarray(beam(theta, l, m, freq), dtype=np.float64)  # (npos, nchan)
    att_ref = np.asarray(beam(theta, l, m, np.array([freq.mean()])), dtype=np.float64)[:, 0]
    is_none = isinstance(beam_spec, str) and beam_spec.lower() == "none"
    used = n > 0
    if not is_none:
        # the one rule (xstack.beams.inside_field): A >= cutoff at the highest channel
        used &= inside_field(lambda t, f: beam(t, l, m, np.array([f]))[:, 0], theta, freq, cutoff)
    return l, m, n1, att, att_ref, used


def _block_weight_total(weight, flag, uvw, frequency, pol_mask, lo, hi):
    """Sum of the visibility weights of one block that enter the flux (unflagged, selected
    correlations, weight > 0, uv range)."""
    nt, nb, nc, npol = weight.shape
    w = np.where(flag | ~(weight > 0), 0.0, weight.astype(np.float64))[..., pol_mask]
    mask = uv_range_mask(uvw.reshape(nt * nb, 3), frequency, lo, hi)
    if mask is not None:
        w = w * mask.reshape(nt, nb, nc)[..., None]
    return np.array([[[np.nansum(w)]]])


def _weight_total(ds, pol_mask, lo, hi):
    """Lazy total visibility weight of a partition (reads WEIGHT, FLAG and UVW only)."""
    ds = _as_dask(ds)
    freq = np.asarray(ds["frequency"].values, dtype=np.float64)
    return da.blockwise(_block_weight_total, "tbs", ds["WEIGHT"].data, "tbcp", ds["FLAG"].data,
                        "tbcp", ds["UVW"].data, "tbx", dtype=np.float64, concatenate=True,
                        new_axes={"s": 1}, adjust_chunks={"t": 1, "b": 1}, frequency=freq,
                        pol_mask=np.asarray(pol_mask, bool), lo=lo, hi=hi).sum()


def _sigma2_pointing_weights(parts, geometries, sigma, polarizations, lo, hi, progress=False):
    """Per-(pointing, position) weights of ``sigma2`` on several pointings (paper §3.3.2).

    sigma_k is the noise of position k's primary-beam corrected flux in the whole data (a
    catalog ``sigma`` or a local-noise image of the mosaic). Pointing p sees position k with
    noise proportional to 1/(A_pk sqrt(W_p)) (W_p: the pointing's total visibility weight),
    so it holds the fraction f_pk = A_pk^2 W_p / sum_q A_qk^2 W_q of the position's
    information. The weights w_pk = A_pk^2 / (sigma_k^2 sum_q A_qk^2 W_q) give each pointing's
    estimate of position k the effective weight w_pk W_p = f_pk / sigma_k^2: a position near
    a pointing's edge enters that pointing with its small share, not with full weight.

    ``geometries``: :func:`_geometry` of every partition, in ``parts`` order.

    Returns
    -------
    list of (npos,) arrays, one per partition in ``parts`` order.
    """
    from xstack._progress import dask_progress

    totals = [_weight_total(ds, _pol_mask(ds, polarizations, name), lo, hi)
              for name, ds in parts]
    with dask_progress("uvstack: pointing weights", enabled=progress):
        wtot = np.array(dask.compute(*totals), dtype=np.float64)
    a2 = np.array([np.where(g[5], g[4], 0.0) ** 2 for g in geometries])  # (npart, npos)
    info = (a2 * wtot[:, None]).sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(info > 0, a2 / (sigma[None, :] ** 2 * info[None, :]), 0.0)
    # only ratios matter: scale to ~1 so that no weight under- or overflows downstream
    peak = float(np.max(w)) if w.size else 0.0
    return list(w / peak) if peak > 0 else list(w)


# --- phase 1: inputs ----------------------------------------------------------------------

@dataclass
class _Inputs:
    """Normalised inputs of one stack: nothing of the visibilities is read yet."""

    table: Table  # the catalog
    ra: np.ndarray  # (npos,) radians
    dec: np.ndarray  # (npos,) radians
    sigma: np.ndarray | None  # (npos,) sigma_k for weighting="sigma2" (inf: no estimate)
    noise: Any  # the local-noise measurement (xstack.uvstack.localnoise) or None
    col_weight: np.ndarray | None  # (npos,) the catalog's weight column for "column"
    beam: Any  # a FitsBeam or a model beam's name
    parts: list[tuple[str, xr.Dataset]]  # (unique name, lazy partition) to stack


def _load(data: Any, positions: Any, options: UvstackOptions) -> _Inputs:
    """Read the catalog, the per-position sigma/weights and a FITS beam; open the data lazily.

    Checks ``out`` before the data are opened. No visibility is read.
    """
    from xstack._atomic import check_output

    table = _positions_table(positions)
    ra = np.radians(np.asarray(table["ra"], dtype=np.float64))
    dec = np.radians(np.asarray(table["dec"], dtype=np.float64))
    sig, noise = _position_sigma(table, options)
    col_weight = None
    if options.weighting == "column":
        if "weight" not in table.colnames:
            raise XstackError("weighting='column' needs a 'weight' column in the catalog")
        col_weight = np.asarray(table["weight"], dtype=np.float64)
    beam = FitsBeam(options.primary_beam) if _is_fits_path(options.primary_beam) \
        else options.primary_beam
    if options.out is not None:
        check_output(options.out, options.overwrite)
    datasets = _load_datasets(data)
    multi = len(datasets) > 1
    parts = [(f"{name}_ds{i}" if multi else name, sky_correlations(ds, options.autocorrelations))
             for i, (_label, group) in enumerate(datasets) for name, ds in group]
    return _Inputs(table, ra, dec, sig, noise, col_weight, beam, parts)


def _position_sigma(table: Table, options: UvstackOptions) -> tuple[np.ndarray | None, Any]:
    """sigma_k (Jy, one per catalog row) of ``weighting="sigma2"`` and the local-noise
    measurement they came from: ``sigma=``, else measured in ``noise_image``, else the
    catalog's ``sigma`` column; (None, None) for the analytic sigma_k or another weighting."""
    npos = len(table)
    sig = None
    noise = None
    if options.weighting != "sigma2":
        return None, None
    if options.sigma is not None:
        try:
            sig = np.broadcast_to(np.asarray(options.sigma, dtype=np.float64), (npos,)).copy()
        except (TypeError, ValueError):
            raise OptionError(f"sigma must be one number or one per position ({npos})",
                              option="sigma") from None
    elif options.noise_image is not None:
        from xstack.uvstack.localnoise import measure_local_noise

        # stacklevel 4: the caller of stack_uv (stack_uv -> _load -> here)
        if "sigma" in table.colnames:
            warnings.warn(XstackWarning("the catalog's sigma column is ignored: sigma_k "
                                        "are measured in noise_image",
                                        option="noise_image"), stacklevel=4)
        noise = measure_local_noise(options.noise_image, table)
        # rows without an estimate get weight 0 here; a used one is an error in _plan
        sig = np.where(np.isfinite(noise.sigma), noise.sigma, np.inf)
        if noise.pbcor is False and noise.beam is None and \
                str(options.primary_beam).lower() != "none":
            warnings.warn(f"noise image {noise.name} is not primary-beam corrected "
                          "(XSPBCOR = F) and names no primary beam (XSPBFILE): its sigma_k "
                          "miss the 1/A_k rise of the noise of the corrected flux; give "
                          "the residual of xstack image (it carries OUT.pb.fits) or a "
                          "corrected image", stacklevel=4)
    elif "sigma" in table.colnames:
        sig = np.asarray(table["sigma"], dtype=np.float64)
    if noise is None and sig is not None and not np.all(np.isfinite(sig) & (sig > 0)):
        bad = int(np.argmax(~(np.isfinite(sig) & (sig > 0))))
        raise XstackError(f"positions row {bad + 1}: sigma must be positive and finite")
    return sig, noise


# --- phase 2: plan ------------------------------------------------------------------------

@dataclass
class _StackPlan:
    """What enters the stack: per-partition plans, the stack's phase center, the options
    record of the result (JSON; ``engine`` and ``engine_rows`` set by the flux pass)."""

    inputs: _Inputs
    partitions: list[_Plan]  # every partition, in input order
    active: list[_Plan]  # those with a positive total position weight
    covered: np.ndarray  # (npos,) bool: inside some pointing
    used: np.ndarray  # (npos,) bool: with a positive weight in some active pointing
    center: tuple[float, float]  # radians
    record: dict[str, Any]


def _plan(inputs: _Inputs, options: UvstackOptions) -> _StackPlan:
    """Positions per pointing, their weights and coefficients, the stack center.

    Reads no visibility; ``sigma2`` on several pointings sums each pointing's WEIGHT and
    the smearing correction subsamples UVW/WEIGHT/FLAG rows (both small passes).
    """
    ra, dec, npos = inputs.ra, inputs.dec, len(inputs.table)
    parts = inputs.parts
    # each pointing's view of the positions, computed once (sigma2 weights and plans use it)
    geometries = [_geometry(ds, ra, dec, inputs.beam, float(options.pb_cutoff))
                  for _, ds in parts]
    position_weights: list[Any] = [None] * len(parts)
    if options.weighting == "sigma2" and inputs.sigma is not None and len(parts) > 1:
        position_weights = _sigma2_pointing_weights(
            parts, geometries, inputs.sigma, options.polarizations, options.uv_lo,
            options.uv_hi, options.progress)
    plans = [_plan_partition(pname, ds, inputs, options, pw, geo)
             for (pname, ds), pw, geo in zip(parts, position_weights, geometries)]
    covered = np.zeros(npos, dtype=bool)
    for p in plans:
        covered |= p.used
    if not covered.any():
        raise NoDataError(f"none of the {npos} positions lies inside a pointing "
                          f"(primary-beam cutoff {options.pb_cutoff})")
    if inputs.noise is not None:
        missing = np.flatnonzero(covered & ~np.isfinite(inputs.noise.sigma))
        if missing.size:
            raise XstackError(inputs.noise.describe_bad(missing))
    n_uncovered = int(np.count_nonzero(~covered))
    if n_uncovered:
        # stacklevel 3: the caller of stack_uv
        warnings.warn(f"{n_uncovered} of {npos} positions lie in no pointing and are not "
                      "stacked (see StackResult.uncovered)", stacklevel=3)
    active = [p for p in plans if p.sum_weight > 0]
    if not active:
        raise NoDataError("all position weights are zero: nothing to stack")
    used = np.zeros(npos, dtype=bool)
    for p in active:
        used |= p.used & (p.weight > 0)
    # the stacked dataset's phase center: the positions' mean direction (the first position
    # if they cancel)
    center = mean_direction(ra[used], dec[used]) or (float(ra[used][0]), float(dec[used][0]))
    worst = max(float(p.smearing_loss.max(initial=0.0)) for p in active)
    if worst > _smearing.WARN_LOSS:
        warnings.warn(XstackWarning(f"smearing costs up to {100 * worst:.0f}% of a position's "
                                    "flux (corrected to first order; smearing='none' to leave "
                                    "it)", option="smearing"), stacklevel=3)
    record = _options_record(options, inputs, active, center)
    return _StackPlan(inputs, plans, active, covered, used, center, record)


def _options_record(options: UvstackOptions, inputs: _Inputs, active: list[_Plan],
                    center: tuple[float, float]) -> dict[str, Any]:
    """The result's ``options``: :meth:`UvstackOptions.to_dict` with what the plan found
    (smearing corrected, where sigma_k came from, the stack center), in the documented order."""
    given = options.to_dict()
    record = {k: v for k, v in given.items() if k != "engine"}
    record["smearing_corrected"] = [e for i, e in enumerate(("bandwidth", "time"))
                                    if any(p.smearing_effects[i] for p in active)]
    record["engine"] = given["engine"]
    noise, sig = inputs.noise, inputs.sigma
    record["sigma"] = (f"local-noise:{noise.name}" if noise is not None else "given"
                       if sig is not None else "analytic" if options.weighting == "sigma2"
                       else None)
    record["stack_center_deg"] = [float(np.degrees(center[0])), float(np.degrees(center[1]))]
    if noise is not None:
        record["local_noise"] = noise.provenance()
    return record


def _plan_partition(name: str, ds: xr.Dataset, inputs: _Inputs, options: UvstackOptions,
                    position_weight: np.ndarray | None = None, geometry: Any = None) -> _Plan:
    """One partition's plan: position weights W_k (0 outside the pointing), their total, and
    the phasor parameters [l, m, n - 1, W_k / (A_k(nu) L_k(nu) sum W)] of the used positions.

    ``position_weight``: per-pointing weights of ``sigma2`` on a mosaic (else from
    ``options.weighting``); ``geometry``: :func:`_geometry` of the partition if known.
    """
    ra, weighting, sigma = inputs.ra, options.weighting, inputs.sigma
    freq = np.asarray(ds["frequency"].values, dtype=np.float64)
    l, m, n1, att, att_ref, used = (geometry if geometry is not None else _geometry(
        ds, ra, inputs.dec, inputs.beam, float(options.pb_cutoff)))
    if position_weight is not None:
        w = position_weight
    elif weighting == "none":
        w = np.ones(ra.size)
    elif weighting == "pb":
        w = att_ref**2
    elif weighting == "sigma2":
        w = 1.0 / sigma**2 if sigma is not None else att_ref**2
    else:
        w = inputs.col_weight
    w = np.where(used, w, 0.0)
    total = float(w.sum())
    sel = used & (w > 0)
    pol_mask = _pol_mask(ds, options.polarizations, name)
    smear_loss, effects = np.zeros(ra.size), (False, False)
    if total > 0:
        # smearing loss L_k(nu), corrected as the primary beam is (xstack.uvstack.smearing)
        effects = _smearing.data_effects(ds, options.smearing)
        L, L_ref = _smearing.loss_factors(
            ds, l[sel], m[sel], n1[sel], bandwidth=effects[0], time=effects[1],
            pol_mask=pol_mask,
            uv_select=lambda x, f: uv_range_mask(x, f, options.uv_lo, options.uv_hi))
        smear_loss[sel] = 1.0 - L_ref
        coef = w[sel, None] / (att[sel] * L) / total
        params = np.column_stack([l[sel], m[sel], n1[sel], coef])
    else:
        params = np.zeros((0, 3 + freq.size))
    return _Plan(name, ds, used, w, att_ref, total, params, pol_mask, smear_loss, effects)


def _as_dask(ds: xr.Dataset) -> xr.Dataset:
    """Chunk a numpy-backed partition (time x baseline, full spectra) and align UVW chunks."""
    vis = ds["VISIBILITY"]
    if not isinstance(vis.data, da.Array):
        nt = default_time_chunk(ds.sizes["baseline_id"], ds.sizes["frequency"],
                                ds.sizes["polarization"], vis.dtype.itemsize)
        ds = ds.chunk({"time": nt, "baseline_id": -1, "frequency": -1, "polarization": -1})
    vchunks = ds["VISIBILITY"].data.chunks
    if len(vchunks[2]) > 1 or len(vchunks[3]) > 1:
        ds = ds.chunk({"frequency": -1, "polarization": -1})
        vchunks = ds["VISIBILITY"].data.chunks
    updates = {}
    for var in ("WEIGHT", "FLAG", "UVW"):
        arr = ds[var].data
        want = vchunks if var != "UVW" else (vchunks[0], vchunks[1], (3,))
        if not isinstance(arr, da.Array):
            arr = da.from_array(arr, chunks=want)
        elif arr.chunks != want:
            arr = arr.rechunk(want)
        else:
            continue
        updates[var] = (ds[var].dims, arr, ds[var].attrs)
    return ds.assign(updates) if updates else ds


# --- phase 3: compute ---------------------------------------------------------------------

def _stacked_dataset(plan: _Plan, options: UvstackOptions, stack_center, record, ra, dec,
                     shared_phasor: bool = False) -> tuple[xr.Dataset, Any]:
    """The lazy stacked partition and the lazy flux sums of ``plan``.

    The stacked visibilities come from one phasor per chunk; with ``shared_phasor`` (used
    when the stack is written) the sums use that phasor too, so a write plus the flux costs
    one phasor evaluation instead of two; otherwise the sums evaluate the phasor in small row
    steps themselves, only for rows that carry weight (less memory for a flux alone).
    ``record``: the options record, copied into the partition's ``uvstack_options``.
    """
    ds = _as_dask(plan.ds)
    engine = options.engine
    freq = np.asarray(ds["frequency"].values, dtype=np.float64)
    vis = ds["VISIBILITY"].data
    uvw = ds["UVW"].data
    params = da.from_array(plan.params, chunks=plan.params.shape, name=False)
    # antenna ids per baseline chunk: the antenna engine factorises each block's baselines
    ants: list[Any] = [None, None, None, None]
    if "baseline_antenna1_id" in ds and "baseline_antenna2_id" in ds:
        bchunks = (vis.chunks[1],)
        ants = [da.from_array(np.asarray(ds[f"baseline_antenna{i}_id"].values), chunks=bchunks,
                              name=False) if j == 0 else "b" for i in (1, 2) for j in (0, 1)]
    nsums = _NSUMS + len(_ROW_ENGINES)
    tol = float(options.antenna_tol_rad)
    sum_kwargs = dict(dtype=np.float64, concatenate=True, new_axes={"s": nsums},
                      adjust_chunks={"t": 1, "b": 1}, frequency=freq, pol_mask=plan.pol_mask,
                      lo=options.uv_lo, hi=options.uv_hi)
    if shared_phasor:
        # one task per chunk makes both (a tuple), two getters split it: the phasor is
        # evaluated once per row and never held for a whole chunk (bench_uvstack_memory.py)
        pair = da.blockwise(_block_stack_and_sums, "tb", vis, "tbcp", ds["WEIGHT"].data, "tbcp",
                            ds["FLAG"].data, "tbcp", uvw, "tbx", params, "kz", *ants,
                            dtype=object, meta=np.empty((0, 0), dtype=object), concatenate=True,
                            frequency=freq, engine=engine, tol_rad=tol, pol_mask=plan.pol_mask,
                            lo=options.uv_lo, hi=options.uv_hi)
        stacked = da.blockwise(_first, "tbcp", pair, "tb", dtype=vis.dtype,
                               new_axes={"c": vis.shape[2], "p": vis.shape[3]},
                               meta=np.empty((0, 0, 0, 0), dtype=vis.dtype))
        sums = da.blockwise(_second, "tbs", pair, "tb", dtype=np.float64, new_axes={"s": nsums},
                            adjust_chunks={"t": 1, "b": 1},
                            meta=np.empty((0, 0, 0), dtype=np.float64)).sum(axis=(0, 1))
    else:
        # "e": the channels plus the engine column (one chunk). Computed only when the stacked
        # visibilities are (the caller's own compute of a flux-only stack)
        ph = da.blockwise(_block_phasor_chunk, "tbe", uvw, "tbx", params, "kz", *ants,
                          dtype=np.complex128, concatenate=True, new_axes={"e": freq.size + 1},
                          frequency=freq, engine=engine, tol_rad=tol)
        # a sliced view (not a contracted index): keeps dask's chunk-by-chunk order
        stacked = da.blockwise(_block_apply_phasor, "tbcp", vis, "tbcp", ph[..., :-1], "tbc",
                               dtype=vis.dtype)
        sums = da.blockwise(_block_sums, "tbs", vis, "tbcp", ds["WEIGHT"].data, "tbcp",
                            ds["FLAG"].data, "tbcp", uvw, "tbx", params, "kz", *ants,
                            engine=engine, tol_rad=tol, **sum_kwargs).sum(axis=(0, 1))
    out = ds.drop_encoding().copy()
    out["VISIBILITY"] = (ds["VISIBILITY"].dims, stacked, ds["VISIBILITY"].attrs)
    weight = ds["WEIGHT"].data * np.float32(plan.sum_weight)
    out["WEIGHT"] = (ds["WEIGHT"].dims, weight.astype(np.float32), ds["WEIGHT"].attrs)
    sel = plan.used & (plan.weight > 0)
    idx = np.flatnonzero(sel)
    out = out.assign(
        STACK_POSITION_RA=("stack_position", np.degrees(ra[idx]), {"units": "deg"}),
        STACK_POSITION_DEC=("stack_position", np.degrees(dec[idx]), {"units": "deg"}),
        STACK_POSITION_INDEX=("stack_position", idx.astype(np.int64)),
        STACK_WEIGHT=("stack_position", plan.weight[idx]),
        STACK_ATTENUATION=("stack_position", plan.attenuation[idx]),
    )
    out.attrs.update({
        "phase_center": [float(stack_center[0]), float(stack_center[1])],
        "original_phase_center": [float(x) for x in plan.ds.attrs["phase_center"]],
        "uvstack_sum_weight": float(plan.sum_weight),
        "uvstack_n_positions": int(idx.size),
        # a copy: the record's engine is the requested one until the flux pass has run
        "uvstack_options": dict(record),
        "data_kind": "stacked",
    })
    return out, sums


@dataclass
class _Measured:
    """What the flux pass measured (:func:`_measure`) and the lazy stacked partitions."""

    stacked: dict[str, xr.Dataset]
    sums: list[np.ndarray]  # per active partition: the flux sums, then rows per engine
    flux_jy: float
    flux_err_jy: float
    flux_err_empirical_jy: float
    weight_scale: float
    noise_estimate: dict[str, Any]
    flux_imag_jy: float
    n_visibilities: int
    profile: Table | None = None


def _profile_graphs(stacked: dict[str, xr.Dataset], options: UvstackOptions
                    ) -> tuple[list[Any], Callable[[tuple[Any, ...]], Table | None]]:
    """The lazy uv-profile sums of the stacked partitions (none without ``profile_bins``) and
    the function that makes the table from their computed values."""
    if options.profile_bins is None:
        return [], lambda results: None
    from xstack.uvstack.profile import profile_edges, profile_graph, profile_table

    pols = options.polarizations if isinstance(options.polarizations, str) \
        else list(options.polarizations)
    parts = list(stacked.values())
    edges, fmean = profile_edges(parts, options.profile_bins, options.uvmin, options.uvmax)
    graphs = [profile_graph(ds, edges, pols) for ds in parts]
    return graphs, lambda results: profile_table(np.sum(results, axis=0), edges, fmean)


def _compute(plan: _StackPlan, options: UvstackOptions) -> _Measured:
    """Build the lazy stack and run the one pass over the data: the flux sums, and the
    written store when ``options.out`` is set (sharing each chunk's phasor)."""
    from xstack._progress import dask_progress

    stacked: dict[str, xr.Dataset] = {}
    sums_graph = []
    for p in plan.active:
        ds_out, sums = _stacked_dataset(p, options, plan.center, plan.record, plan.inputs.ra,
                                        plan.inputs.dec, shared_phasor=options.out is not None)
        stacked[p.name] = ds_out
        sums_graph.append(sums)
    done: list[_Measured] = []
    # the uv-profile's sums read the stacked chunks of the same pass (no second pass)
    profile_graphs, make_profile = _profile_graphs(stacked, options)
    n_sums = len(sums_graph)

    def measure(results: tuple[Any, ...]) -> dict[str, Any]:
        done.append(_measure(results[:n_sums], plan, options, stacked))
        done[-1].profile = make_profile(results[n_sums:])
        return _store_attrs(done[-1], plan)

    try:
        if options.out is None:
            with dask_progress("uvstack: flux", enabled=options.progress):
                measure(dask.compute(*sums_graph, *profile_graphs))
        else:
            from xstack.schema import write_store

            # one pass: one task per chunk makes the stacked chunk and its flux sums. xarray's
            # write optimises its sources on their own (da.store); low-level fusion would fold
            # that task into the write's chain and again into the sums', computing it twice
            with dask.config.set({"optimization.fuse.active": False}):
                write_store(stacked, options.out, kind="stacked", overwrite=options.overwrite,
                            progress=options.progress, description="uvstack",
                            compute_with=[*sums_graph, *profile_graphs], final_attrs=measure)
    except MemoryError as exc:
        if options.engine != "nufft":
            raise
        raise XstackError(f"engine 'nufft': {exc}") from None
    return done[-1]


def _store_attrs(m: _Measured, plan: _StackPlan) -> dict[str, Any]:
    """The root attributes of the written stack: what the flux pass measured."""
    emp = m.flux_err_empirical_jy
    return {"uvstack": {"flux_jy": m.flux_jy, "flux_err_jy": m.flux_err_jy,
                        "flux_err_empirical_jy": emp if np.isfinite(emp) else None,
                        "n_positions": int(np.count_nonzero(plan.used)),
                        "n_visibilities": m.n_visibilities, "options": plan.record}}


def _measure(results: tuple[Any, ...], plan: _StackPlan, options: UvstackOptions,
             stacked: dict[str, xr.Dataset]) -> _Measured:
    """Combine the partitions' flux sums (section 3.3.1); record the engines that ran in
    ``plan.record``. NoDataError when no visibility entered the flux."""
    scale = np.array([p.sum_weight for p in plan.active])
    sums = [np.asarray(r, dtype=np.float64) for r in results]
    den = sum(s_p * s[1] for s_p, s in zip(scale, sums))
    nvis = int(round(sum(s[4] for s in sums)))
    if not den > 0 or nvis == 0:
        raise NoDataError("no unflagged visibility with positive weight in the selected "
                          "polarizations and uv range")
    var_w = sum(s_p**2 * s[2] for s_p, s in zip(scale, sums))
    # the same variance with the noise measured per block in place of 1/WEIGHT
    var_e = sum(s_p**2 * s[5] for s_p, s in zip(scale, sums))
    n_pooled = int(round(sum(s[6] for s in sums)))
    n_weights = int(round(sum(s[7] for s in sums)))
    multichan = {int(p.ds.sizes["frequency"]) > 1 for p in plan.active}
    rows = np.sum([s[_NSUMS:] for s in sums], axis=0)
    ran = {e: int(r) for e, r in zip(_ROW_ENGINES, rows) if r > 0}
    plan.record["engine"] = next(iter(ran)) if len(ran) == 1 else "mixed" if ran \
        else options.engine
    plan.record["engine_rows"] = ran
    return _Measured(
        stacked=stacked, sums=sums, n_visibilities=nvis,
        flux_jy=float(sum(s_p * s[0] for s_p, s in zip(scale, sums)) / den),
        flux_err_jy=float(np.sqrt(var_w) / den),
        flux_err_empirical_jy=float(np.sqrt(var_e) / den),
        weight_scale=float(var_e / var_w) if var_w > 0 else float("nan"),
        noise_estimate={
            "pairs": ("mixed" if len(multichan) > 1 else "channels" if True in multichan
                      else "integrations"),
            "own": nvis - n_pooled - n_weights, "pooled": n_pooled, "weights": n_weights},
        flux_imag_jy=float(sum(s_p * s[3] for s_p, s in zip(scale, sums)) / den))


# --- phase 4: assemble --------------------------------------------------------------------

def _assemble(plan: _StackPlan, measured: _Measured, options: UvstackOptions) -> StackResult:
    """The :class:`StackResult`: the catalog with per-partition columns, and a warning when
    the weights' and the measured error disagree."""
    inputs, plans = plan.inputs, plan.partitions
    pos = Table(inputs.table, copy=True)
    pos["used"] = np.stack([p.used & (p.weight > 0) for p in plans], axis=1)
    pos["weight_used"] = np.stack([p.weight for p in plans], axis=1)
    pos["attenuation"] = np.stack([p.attenuation for p in plans], axis=1)
    pos["smearing_loss"] = np.stack([p.smearing_loss for p in plans], axis=1)
    pos["n_pointings"] = pos["used"].sum(axis=1)
    if inputs.noise is not None:
        pos["sigma_local"] = inputs.noise.sigma
    pos.meta["partitions"] = [p.name for p in plans]
    err_w, err_e = measured.flux_err_jy, measured.flux_err_empirical_jy
    ratio = err_e / err_w
    if np.isfinite(ratio) and abs(ratio - 1) > EMPIRICAL_TOLERANCE:
        warnings.warn(WeightsWarning(
            f"uv-stack flux error from WEIGHT ({err_w:.3g} Jy) and from the "
            f"visibility scatter ({err_e:.3g} Jy) differ by "
            f"{ratio:.3g}x: the weights are mis-scaled"
            + ("" if ratio < 1 else ", or sky signal changes across channels (bright sources "
               "far from the phase center: subtract them first)")
            + "; choose the error printed first with errors='weights' (flux_err_jy) or "
            "errors='empirical' (flux_err_empirical_jy)",
            option="errors"),
            stacklevel=3)
    return StackResult(stacked=measured.stacked, flux_jy=measured.flux_jy, flux_err_jy=err_w,
                       n_positions=int(np.count_nonzero(plan.used)),
                       n_visibilities=measured.n_visibilities, positions=pos,
                       options=plan.record, uncovered=inputs.table[~plan.covered],
                       flux_imag_jy=measured.flux_imag_jy,
                       partition_sums={p.name: s[:_NSUMS].tolist()
                                       for p, s in zip(plan.active, measured.sums)},
                       flux_err_empirical_jy=err_e, weight_scale=measured.weight_scale,
                       noise_estimate=measured.noise_estimate, profile=measured.profile)


# --- public API ---------------------------------------------------------------------------

def stack_uv(data: Any, positions: Any, *, weighting: str = "pb", primary_beam: Any = "auto",
            pb_cutoff: float = DEFAULT_PB_CUTOFF, uvmin: Any = None, uvmax: Any = None, sigma: Any = None,
            noise_image: Any = None, polarizations: Any = "parallel", engine: str = "auto",
            out: str | os.PathLike | None = None, overwrite: bool = False,
            progress: bool = False, antenna_tol_rad: float = ANTENNA_TOL_RAD,
            autocorrelations: bool = False, smearing: str = "auto",
            profile_bins: Any = None, compute: bool = True) -> StackResult | LazyResult:
    """Stack visibilities at catalog positions (paper eq. 4) and estimate the stacked flux.

    Parameters
    ----------
    data
        An :class:`xarray.DataTree` (e.g. from :func:`xstack.open_store`), a store path, a
        MeasurementSet path (converted to a temporary store), a Dataset, a dict of Datasets
        (any input of :func:`xstack._inputs.partitions`), or a list of these: several
        datasets are stacked together, every partition (pointing x window) about its own
        phase center.
    positions
        :class:`astropy.table.Table` or catalog path with ``ra``, ``dec`` in degrees, or
        coordinates (:meth:`xstack._inputs.Positions.from_any`); optional ``weight`` for
        ``weighting="column"``, ``sigma`` in Jy for ``"sigma2"``.
    weighting
        Position weights W_k: ``none`` (1), ``pb`` (A_k^2 at the partition's mean frequency:
        the inverse variance of the primary-beam corrected flux), ``sigma2`` (1/sigma_k^2
        from ``sigma=``, else measured in ``noise_image``, else the catalog's ``sigma``
        column; without any of them the analytic sigma_k proportional to 1/A_k of the
        paper's ALMA case, i.e. the same as ``pb``), ``column`` (the catalog's ``weight``
        column).
    primary_beam
        ``auto`` (the telescope's standard beam, :func:`xstack.beams.standard_beam`),
        ``airy``, ``gaussian``, ``none``, or the path of a FITS primary-beam image.
    pb_cutoff
        A position enters a pointing only if A >= pb_cutoff in every channel and it lies
        inside the main lobe of a model beam (never beyond its first null, whatever the
        cutoff: a sidelobe cannot be primary-beam corrected).
    uvmin, uvmax
        uv-distance range of the flux estimate (``"5000m"``, ``"23.8klambda"``; numbers
        are metres). The stacked data themselves keep every visibility.
    sigma
        Per-position noise (Jy), for ``weighting="sigma2"``.
    noise_image
        For ``weighting="sigma2"`` without ``sigma=``: a residual image of the same data in
        Jy/beam (FITS path, HDU or :class:`xstack.imaging.image.ImageResult`), primary-beam
        corrected so that its noise grows as 1/A. sigma_k is the 3-sigma clipped rms of a
        stamp of ~300 beam areas around each position outside a circle of radius BMAJ
        (paper §3.2, :func:`xstack.uvstack.localnoise.measure_local_noise`); it takes
        precedence over a catalog ``sigma`` column. Only ratios of the weights matter, so
        the image's absolute scale cancels. Every position that enters a pointing needs an
        estimate (on the image, enough finite pixels around it), otherwise XstackError
        naming the rows; positions in no pointing need none.
    polarizations
        ``parallel`` (Stokes I: XX/YY or RR/LL), ``all`` or a list of names, for the flux.
    engine
        ``auto`` (default: per block of rows ``antenna`` where it applies, else ``numba``),
        ``antenna`` (per-antenna phasors, sine/cosine per antenna instead of per baseline;
        needs ``baseline_antenna1_id``/``baseline_antenna2_id`` and baseline UVW that are
        differences of per-antenna UVW to ``antenna_tol_rad``, XstackError otherwise),
        ``numba`` (per-row kernel), ``numpy`` (plain reference evaluation, slow) or ``nufft``
        (ducc0 type-3 NUFFT, accuracy 1e-12; compact fields only). The engine that ran is
        ``options["engine"]`` (``antenna``, ``numba`` or ``mixed``; ``engine_rows`` counts
        the rows per engine) after the flux pass.
    out
        Write the stacked store here (kind ``stacked``), atomically.
    overwrite
        Replace an existing ``out``.
    progress
        Progress bars on stderr.
    antenna_tol_rad
        Largest accepted bound (radians, at any position and channel) of the phase error of
        the per-antenna factorisation (:meth:`xstack._antenna.AntennaLayout.phase_error`).
    autocorrelations
        Include autocorrelation baselines (antenna1 == antenna2). Off by default: they measure
        an antenna's system power, not the sky, and are flagged in the flux and in the
        written stack (as CASA and WSClean leave them out).
    smearing
        Bandwidth and time-average smearing (:mod:`xstack.uvstack.smearing`): ``auto``
        corrects the data that carry it (real data; simulations whose scene asked for it,
        partition attribute ``smearing``), ``correct`` always, ``none`` never. The loss
        L_k(nu) of each position (weighted mean smearing factor over its pointing's
        visibilities, from a subsample of rows) divides its coefficient like A_k;
        ``positions["smearing_loss"]`` holds 1 - L_k at the mean frequency.
    profile_bins
        Also make the uv-profile of the stacked visibilities (``result.profile``) in the
        same pass over the data: a number of equal bins over the data's uv range (measured
        from UVW first, a pass over UVW only) or the stack's ``uvmin``/``uvmax``, or bin edges
        in kilo-wavelengths; equal to :func:`~xstack.uvstack.profile.uv_profile` of the
        written store with the same bins, range and polarizations. None: no profile.
    compute
        ``False``: plan the stack (catalog, weights, beams; no visibility is read) and return
        a :class:`xstack._lazy.LazyResult` whose flux pass runs later, together with other
        lazy results in one pass over shared data: ``xstack.compute(a, b)`` or
        ``dask.compute(a, b)`` (on the active distributed Client, if any). With ``out`` the
        store is created now (an existing ``out`` without ``overwrite`` is an error here)
        and written in that pass, each VISIBILITY chunk read once for the store and the
        flux; it becomes a store only when the result is finished, in the calling process.
        A failed :func:`xstack.compute`, or dropping the lazy result uncomputed, removes
        what was written; a second compute of the same result is an error (a store is
        written once).

    Returns
    -------
    StackResult
        Or, with ``compute=False``, a lazy result that computes to it.

    Raises
    ------
    OptionError
        A bad option value (:class:`UvstackOptions`), before the catalog or data are read;
        ``sigma`` of the wrong length for the catalog.
    XstackError
        An unreadable catalog or FITS beam, a catalog entirely outside the pointings, zero
        total weight, no usable visibility, an existing ``out`` without ``overwrite``, a
        ``noise_image`` without celestial WCS or without an estimate for a used position.
    """
    options = UvstackOptions(
        weighting=weighting, primary_beam=primary_beam, pb_cutoff=pb_cutoff, uvmin=uvmin,
        uvmax=uvmax, sigma=sigma, noise_image=noise_image, polarizations=polarizations,
        engine=engine, out=out, overwrite=overwrite, progress=progress,
        antenna_tol_rad=antenna_tol_rad, autocorrelations=autocorrelations, smearing=smearing,
        profile_bins=profile_bins)
    inputs = _load(data, positions, options)  # the catalog; the data opened lazily
    plan = _plan(inputs, options)  # what enters, with which weight (no visibility read)
    if not compute:
        return _lazy(plan, options)
    measured = _compute(plan, options)  # the one pass over the data (and the write)
    return _assemble(plan, measured, options)


def _optimised_now(x: da.Array) -> Any:
    """A one-chunk ``Delayed`` of the dask array ``x`` with its graph optimised now (under
    the caller's configuration), not at compute time."""
    if x.npartitions > 1:
        x = x.rechunk(x.shape)
    return x.to_delayed(optimize_graph=True).ravel()[0]


def _lazy(plan: _StackPlan, options: UvstackOptions) -> LazyResult:
    """The flux pass of ``plan`` as a dask collection that finishes into a StackResult.

    With ``options.out`` the store is begun now (:class:`xstack.schema.StoreWrite`: the
    temporary with every group, no chunk) and the collection holds its chunk writes beside
    the flux sums, made by the same task per chunk as the eager write; its finishing, in the
    calling process, completes the store with the measured numbers."""
    stacked: dict[str, xr.Dataset] = {}
    sums_graph = []
    for p in plan.active:
        ds_out, sums = _stacked_dataset(p, options, plan.center, plan.record, plan.inputs.ra,
                                        plan.inputs.dec, shared_phasor=options.out is not None)
        stacked[p.name] = ds_out
        sums_graph.append(sums)

    profile_graphs, make_profile = _profile_graphs(stacked, options)
    n_sums = len(sums_graph)
    write = None
    writes: list[Any] = []
    if options.out is not None:
        from xstack.schema import StoreWrite

        # as the eager write (_compute): no low-level fusion, or the task making a stacked
        # chunk and its sums is folded into both chains and runs twice. xarray's write
        # optimises its sources now; the sums are optimised now too (to_delayed), so that
        # the caller's configuration at compute time cannot fuse them
        with dask.config.set({"optimization.fuse.active": False}):
            write = StoreWrite(stacked, options.out, kind="stacked", overwrite=options.overwrite)
            sums_graph = [_optimised_now(x) for x in sums_graph]
            profile_graphs = [_optimised_now(x) for x in profile_graphs]
        writes = write.graphs

    def finish(results: list[Any]) -> StackResult:
        results = results[len(writes):]
        try:
            measured = _measure(tuple(results[:n_sums]), plan, options, stacked)
            measured.profile = make_profile(tuple(results[n_sums:]))
            if write is not None:
                write.finish(_store_attrs(measured, plan))
        except BaseException:
            if write is not None:  # every task has run: nothing writes into it any more
                write.abort()
            raise
        return _assemble(plan, measured, options)

    return LazyResult([*writes, *sums_graph, *profile_graphs], finish, "stack_uv", write=write)
