"""Spectral-line stacking in the image domain: 3-D stamps of a cube aligned in velocity.

For each target k its stamp cube s_ki(y, x) (channel i; nearest pixel, as the continuum
image stack) is cut from the cube. Its channel i covers the velocity interval between the
velocities v = c (nu_c,k - nu) / nu_c,k of the channel's frequency edges about the target's
own observed line centre nu_c,k (catalog ``z``: nu_rest / (1 + z), or ``freq``), and
o_kij is the length of that interval inside bin j of the common grid
(:func:`xstack.spectral.overlap_lengths`: channels are never assigned to the nearest bin).
With channel weights w_ki (W_k times 1/sigma_ki^2, A_ki^2, the catalog weight, or 1)::

    S_j(y, x) = sum_k sum_i w_ki o_kij s_ki(y, x) / sum_k sum_i w_ki o_kij

both sums over the voxels with data, so a target contributes only to the bins its channels
cover and a bin no target covers is NaN -- the estimator of the uv-domain line stack
(``xstack.uvstack.line``) with stamps in place of visibilities. The median is taken per voxel
over the targets' regridded stamps R_kj = sum_i o_kij s_ki / sum_i o_kij.

Errors: the channels' noise sigma_ki is the stamp plane's own (std outside the beam, as the
continuum stack), independent between channels and targets; S_j is linear in the s_ki, so
Cov(S_j, S_j') = sum_ki a_kij a_kij' sigma_ki^2 with a_kij = w_ki o_kij / sum w o: neighbouring
bins that share a channel are correlated. The median's errors are those of the equally
weighted mean times sqrt(pi / 2) (large-N Gaussian noise).
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS

from xstack import _vocabulary
from xstack._result import Result, json_ready
from xstack.errors import NoDataError, OptionError, XstackError, XstackWarning
from xstack.imstack import kernels

METHODS = _vocabulary.IMSTACK_METHODS
WEIGHTINGS = _vocabulary.IMSTACK_WEIGHTINGS
#: FITS SPECSYS -> the frame name the line stacks report.
_FRAMES = {"TOPOCENT": "topo", "GEOCENTR": "geo", "BARYCENT": "bary", "LSRK": "lsrk",
           "LSRD": "lsrd", "SOURCE": "rest"}


@dataclass(kw_only=True)
class ImLineStackResult(Result):
    """The result of :func:`stack_line_cube` (attributes as
    :class:`xstack.uvstack.line.LineStackResult`, plus the stacked cube).

    Attributes
    ----------
    velocity_edges_kms, velocity_kms
        Bin edges (nbin + 1) and centres, km/s about each target's line centre.
    flux_jy, flux_err_jy, flux_cov_jy2
        The stacked cube at its centre pixel per bin (Jy/beam: the flux density of a point
        source), its error and the bins' covariance (Jy^2).
    n_targets_per_bin
        Targets whose channels cover the bin at the centre pixel with weight > 0.
    n_positions
        Targets that enter some bin.
    n_visibilities
        0: an image-domain stack uses no visibilities (the key is kept for the JSON of
        ``xstack linestack``).
    stacked
        (nbin, ny, nx) the stacked cube, Jy/beam; NaN where no target has data.
    weight_sum
        (nbin, ny, nx) sum_k sum_i w_ki o_kij per voxel (mean) or targets per voxel (median).
    positions
        The catalog with ``used``, ``line_centre_hz``, ``n_bins``, ``x_pix``, ``y_pix``.
    header
        Celestial FITS header of the stamps (reference pixel at the centre).
    """

    velocity_edges_kms: np.ndarray
    velocity_kms: np.ndarray
    flux_jy: np.ndarray
    flux_err_jy: np.ndarray
    flux_cov_jy2: np.ndarray
    n_targets_per_bin: np.ndarray
    n_positions: int
    n_visibilities: int
    positions: Table
    rest_frequency_hz: float
    frame: str
    stacked: np.ndarray
    weight_sum: np.ndarray
    header: fits.Header
    options: dict[str, Any] = field(default_factory=dict)
    out: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary, the keys of :meth:`LineStackResult.to_dict`."""
        return json_ready({
            "velocity_kms": self.velocity_kms, "velocity_edges_kms": self.velocity_edges_kms,
            "flux_jy": self.flux_jy, "flux_err_jy": self.flux_err_jy,
            "n_targets_per_bin": self.n_targets_per_bin, "n_positions": self.n_positions,
            "n_visibilities": self.n_visibilities, "rest_frequency_hz": self.rest_frequency_hz,
            "frame": self.frame, "options": self.options, "out": self.out})

    def table(self) -> Table:
        """One row per catalog position (see ``positions``)."""
        return Table(self.positions, copy=True)

    def moment0(self, window_kms: tuple[float, float]) -> np.ndarray:
        """The stacked cube integrated over ``window_kms`` (bins weighted by their overlap
        with the window), Jy/beam km/s; NaN bins count as 0."""
        edges = self.velocity_edges_kms
        lo, hi = float(window_kms[0]), float(window_kms[1])
        dv = np.clip(np.minimum(edges[1:], hi) - np.maximum(edges[:-1], lo), 0.0, None)
        return np.tensordot(dv, np.nan_to_num(self.stacked, nan=0.0), axes=(0, 0))

    def write(self, path: str | os.PathLike, overwrite: bool = False) -> Path:
        """The stacked cube as FITS: (VRAD, Dec, RA) float32, velocity in km/s about each
        target's line centre (radio convention), plus a ``WEIGHTS`` extension."""
        from xstack._atomic import atomic_output

        h = self.header.copy()
        h["NAXIS"] = 3
        h["CTYPE3"] = "VRAD"
        h["CUNIT3"] = "km/s"
        h["CRPIX3"] = 1.0
        h["CRVAL3"] = float(self.velocity_kms[0])
        h["CDELT3"] = float(self.velocity_edges_kms[1] - self.velocity_edges_kms[0])
        h["SPECSYS"] = {v: k for k, v in _FRAMES.items()}.get(self.frame, self.frame.upper())
        h["RESTFRQ"] = (float(self.rest_frequency_hz), "[Hz] rest frequency of the line")
        h["BUNIT"] = "Jy/beam"
        h["XSVELDEF"] = ("v=c(nu_c-nu)/nu_c", "about each target's own line centre")
        h["XSNPOS"] = (int(self.n_positions), "targets stacked")
        h["XSMETHOD"] = str(self.options.get("method", ""))
        with atomic_output(path, overwrite=overwrite) as tmp:
            fits.HDUList([fits.PrimaryHDU(self.stacked.astype(np.float32), header=h),
                          fits.ImageHDU(self.weight_sum.astype(np.float32), name="WEIGHTS")]
                         ).writeto(tmp, output_verify="fix")
        return Path(path)


@dataclass
class _Cube:
    data: np.ndarray  # (nchan, ny, nx), memory-mapped where possible
    freq_edges_hz: np.ndarray  # (nchan + 1,)
    celestial: WCS
    header: fits.Header
    frame: str
    name: str
    hdul: Any = None  # the open (memory-mapped) file: close() when done

    def close(self) -> None:
        if self.hdul is not None:
            self.hdul.close()


def read_cube(source: str | os.PathLike) -> _Cube:
    """A FITS image cube with a frequency axis: its planes, channel edges (Hz) and WCS.

    Raises
    ------
    XstackError
        Not a cube: no FREQ axis with more than one plane (a continuum image), or
        non-degenerate axes besides RA, Dec and FREQ.
    """
    path = Path(source)
    if not path.is_file():
        raise XstackError(f"{path}: no such image cube")
    try:
        hdul = fits.open(path, memmap=True)
    except OSError as exc:
        raise XstackError(f"{path}: cannot read as FITS ({exc})") from None
    try:
        return _open_cube(hdul, path)
    except BaseException:
        hdul.close()
        raise


def _open_cube(hdul: fits.HDUList, path: Path) -> _Cube:
    hdu = next((h for h in hdul if getattr(h, "is_image", False) and h.data is not None
                and h.data.ndim >= 2), None)
    if hdu is None:
        raise XstackError(f"{path}: no image data in the FITS file")
    header = hdu.header.copy()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        wcs = WCS(header)
    spec = int(wcs.wcs.spec)
    ctype = str(wcs.wcs.ctype[spec]) if spec >= 0 else ""
    nspec = int(header.get(f"NAXIS{spec + 1}", 1)) if spec >= 0 else 1
    if spec < 0 or nspec < 2:
        raise XstackError(f"{path}: a line stack needs an image cube with a frequency axis of "
                          f"more than one plane; this image has shape {tuple(hdu.data.shape)}"
                          " (a continuum image: stack it without a line frequency)")
    if not ctype.startswith("FREQ"):
        raise XstackError(f"{path}: the spectral axis is {ctype!r}; a FREQ axis is needed")
    data = hdu.data
    axis = data.ndim - 1 - spec  # numpy order is the reverse of FITS's
    data = np.moveaxis(data, axis, 0)
    while data.ndim > 3:
        if data.shape[1] != 1:
            raise XstackError(f"{path}: non-degenerate axes besides RA, Dec and FREQ "
                              f"{tuple(hdu.data.shape)}")
        data = data[:, 0]
    pix = np.arange(nspec + 1, dtype=np.float64) - 0.5
    spectral = wcs.sub([spec + 1])
    edges = np.asarray(spectral.pixel_to_world_values(pix), dtype=np.float64).ravel()
    unit = str(spectral.wcs.cunit[0]) or "Hz"
    if unit != "Hz":
        import astropy.units as u

        edges = (edges * u.Unit(unit)).to_value(u.Hz)
    frame = _FRAMES.get(str(header.get("SPECSYS", "TOPOCENT")).strip().upper(),
                        str(header.get("SPECSYS", "topo")).strip().lower())
    return _Cube(data=data, freq_edges_hz=edges, celestial=wcs.celestial, header=header,
                 frame=frame, name=path.name, hdul=hdul)


def cube_frame_ratio(c: _Cube, frame: str) -> tuple[float, str]:
    """(r, the frame the stack is in) with nu_frame = r nu_cube for the cube's channels.

    ``frame="cube"`` or a cube already in ``frame``: r = 1. Otherwise the Doppler factor of
    :func:`xstack.frames.frame_ratio` at the cube's mean time (MJD-AVG, else MJD-OBS, else
    DATE-OBS) for its array centre (OBSGEO-X/Y/Z, ITRF metres) towards its pointing centre
    (OBSRA/OBSDEC, else the reference pixel): one factor for the cube, as one cube holds
    the whole track (over an 8-hour track r varies by ~1e-7, 0.04 km/s at 21 cm, which the
    cube averages over).
    """
    from xstack.frames import frame_name, frame_ratio

    if frame == "cube" or c.frame == frame:
        return 1.0, c.frame
    h = c.header
    if c.frame == "rest":
        raise OptionError(f"{c.name}: SPECSYS {h.get('SPECSYS')!r} (rest frame) cannot be "
                          f"converted to {frame}; give frame 'cube'", option="frame")
    mjd = None
    for key in ("MJD-AVG", "MJD-OBS"):
        if key in h:
            mjd = float(h[key])
            break
    if mjd is None and "DATE-OBS" in h:
        from astropy.time import Time

        mjd = float(Time(str(h["DATE-OBS"]), scale="utc").mjd)
    geo = [h.get(f"OBSGEO-{a}") for a in "XYZ"]
    if mjd is None or any(g is None for g in geo):
        missing = ", ".join(k for k, ok in (("MJD-AVG/MJD-OBS/DATE-OBS", mjd is not None),
                                             ("OBSGEO-X/Y/Z", all(g is not None for g in geo)))
                            if not ok)
        raise OptionError(f"{c.name} is in frame {frame_name(c.frame)} and its header has no "
                          f"{missing} to convert it to {frame_name(frame)}; frame 'cube' "
                          "stacks it in its own frame (the catalog's redshifts taken as "
                          f"{frame_name(c.frame)})", option="frame")
    if "OBSRA" in h and "OBSDEC" in h:
        ra0, dec0 = float(h["OBSRA"]), float(h["OBSDEC"])
    else:
        ra0, dec0 = (float(x) for x in c.celestial.wcs.crval[:2])
    r = frame_ratio(mjd * 86400.0, ra0, dec0, np.asarray(geo, dtype=np.float64),
                    to_frame=frame, from_frame=c.frame)
    return float(np.asarray(r).ravel()[0]), frame


def _stamp_cube(cube: np.ndarray, ix: int, iy: int, size: int) -> np.ndarray:
    """(nchan, size, size) stamp centred on pixel (ix, iy), NaN off the cube: the layout of
    :func:`xstack.imstack.kernels.extract_stamps` for every plane at once."""
    nchan, ny, nx = cube.shape
    out = np.full((nchan, size, size), np.nan)
    x0, y0 = ix - size // 2, iy - size // 2
    xs0, xs1 = max(x0, 0), min(x0 + size, nx)
    ys0, ys1 = max(y0, 0), min(y0 + size, ny)
    if xs1 > xs0 and ys1 > ys0:
        out[:, ys0 - y0:ys1 - y0, xs0 - x0:xs1 - x0] = cube[:, ys0:ys1, xs0:xs1]
    return out


def _attenuation(cube: _Cube, ra_deg: float, dec_deg: float, freq_hz: np.ndarray,
                 primary_beam: str) -> np.ndarray | None:
    """A_k(nu_i) of the telescope's standard beam at a target, or None if none is known."""
    if primary_beam == "none":
        return None
    from xstack.beams import TELESCOPE_DISH_DIAMETERS, standard_beam
    from xstack.coords import angular_separation

    tel = str(cube.header.get("TELESCOP", "")).upper()
    if tel not in TELESCOPE_DISH_DIAMETERS:
        return None
    beam = standard_beam(tel, TELESCOPE_DISH_DIAMETERS[tel],
                         model=None if primary_beam == "auto" else primary_beam)
    ra0 = float(cube.header.get("OBSRA", cube.header.get("CRVAL1", 0.0)))
    dec0 = float(cube.header.get("OBSDEC", cube.header.get("CRVAL2", 0.0)))
    theta = angular_separation(math.radians(ra_deg), math.radians(dec_deg),
                               math.radians(ra0), math.radians(dec0))
    return np.asarray(beam.main_lobe(theta, freq_hz), dtype=np.float64)


def stack_line_cube(cube: str | os.PathLike, positions: Any, *, line_frequency: Any,
                    velocity_resolution: float = 20.0,
                    velocity_range: tuple[float, float] = (-600.0, 600.0),
                    method: str = "mean", weighting: str = "sigma2", stamp_size: int = 32,
                    beam_mask_arcsec: float | None = None, primary_beam: str = "auto",
                    pb_cutoff: float | None = None, frame: str = "lsrk",
                    noise_estimator: str = "clipped",
                    out: str | os.PathLike | None = None,
                    overwrite: bool = False) -> ImLineStackResult:
    """Stack the spectral lines of catalog targets in an image cube, aligned in velocity.

    Parameters
    ----------
    cube
        FITS image cube (RA, Dec, FREQ[, STOKES]) in Jy/beam, e.g. from ``xstack image --cube``.
    positions
        Catalog (path or table) with ``ra``, ``dec`` and ``z`` or ``freq`` (observed line
        centre; Hz without a unit); optional ``weight``.
    line_frequency
        Rest frequency (Hz) or a line name (:func:`xstack.spectral.rest_frequency`).
    velocity_resolution, velocity_range
        The common grid, km/s (:func:`xstack.spectral.velocity_edges`).
    method
        ``mean`` (weighted) or ``median`` per voxel.
    weighting
        ``sigma2`` (1/sigma_ki^2 from each stamp plane's noise outside the beam), ``pb``
        (A_ki^2), ``none`` or ``column`` (the catalog's weight).
    stamp_size
        Stamp size, pixels (>= 8).
    beam_mask_arcsec
        Radius of the central mask for the noise (default the header's BMAJ).
    noise_estimator
        How each stamp plane's noise sigma_ki is measured outside the mask: ``"clipped"``
        (default, the 3-sigma clipped standard deviation, as the continuum stacks),
        ``"mad"`` or ``"std"`` (the plain standard deviation, which counts a bright
        neighbour or CLEAN's residual in the stamp as noise; the default before
        2026-12-06). Used for the sigma2 weights and the errors.
    primary_beam
        ``auto`` (the telescope's standard beam from TELESCOP), a model name, or ``none``.
        A cube whose header says it is not corrected (``XSPBCOR = F``) is divided by it.
    pb_cutoff
        Channels of a target where the beam is below this are left out (default the
        header's XSPBCUT, else 0.1).
    frame
        Frame of the catalog's redshifts: ``lsrk`` (default) or ``bary``; a cube in another
        frame (``xstack image --cube`` of topocentric data: SPECSYS TOPOCENT) is converted
        by the Doppler factor at its mean time (MJD-AVG, else MJD-OBS or DATE-OBS) for its
        array centre (OBSGEO-X/Y/Z) towards its pointing centre, as the uv line stack
        converts topocentric data; ``cube``: the redshifts are in the cube's own frame, no
        conversion.
    out
        FITS file for the stacked cube (:meth:`ImLineStackResult.write`).

    Raises
    ------
    OptionError
        An unknown frame, or a cube in another frame whose header lacks the time or the
        array position to convert it (``frame="cube"`` stacks it as it is).
    """
    from xstack.spectral import rest_frequency, velocity_edges

    if method not in METHODS:
        raise OptionError(f"unknown method {method!r} (use {', '.join(METHODS)})",
                          option="method")
    if weighting not in WEIGHTINGS:
        raise OptionError(f"unknown weighting {weighting!r} (use {', '.join(WEIGHTINGS)})",
                          option="weighting")
    if int(stamp_size) < 8:
        raise OptionError(f"stamp size must be >= 8 pixels, got {stamp_size}",
                          option="stamp_size")
    if noise_estimator not in kernels.NOISE_ESTIMATORS:
        raise OptionError(f"unknown noise estimator {noise_estimator!r} (use "
                          f"{', '.join(kernels.NOISE_ESTIMATORS)})", option="noise_estimator")
    if frame not in _vocabulary.CUBE_LINE_FRAMES:
        raise OptionError(f"unknown frame {frame!r} (use "
                          f"{', '.join(_vocabulary.CUBE_LINE_FRAMES)})", option="frame")
    size = int(stamp_size)
    grid = velocity_edges(velocity_resolution, velocity_range)
    if out is not None:
        from xstack._atomic import check_output

        check_output(out, overwrite)
    rest_hz = float(rest_frequency(line_frequency))
    c = read_cube(cube)
    try:
        return _stack(c, cube, positions, rest_hz=rest_hz, grid=grid, method=method,
                      weighting=weighting, size=size, beam_mask_arcsec=beam_mask_arcsec,
                      primary_beam=primary_beam, pb_cutoff=pb_cutoff,
                      velocity_resolution=velocity_resolution, velocity_range=velocity_range,
                      frame=frame, noise_estimator=noise_estimator, out=out,
                      overwrite=overwrite)
    finally:
        c.close()


def _stack(c: _Cube, cube: Any, positions: Any, *, rest_hz: float, grid: np.ndarray,
           method: str, weighting: str, size: int, beam_mask_arcsec: float | None,
           primary_beam: str, pb_cutoff: float | None, velocity_resolution: float,
           velocity_range: tuple[float, float], frame: str, noise_estimator: str, out: Any,
           overwrite: bool) -> ImLineStackResult:
    """The stack of :func:`stack_line_cube` on an opened cube."""
    from xstack._inputs import Positions
    from xstack.beams import DEFAULT_PB_CUTOFF
    from xstack.spectral import line_centres_hz, overlap_lengths, velocity_kms

    nbin = grid.size - 1
    pos = Positions.from_any(positions)
    table = Table(pos.as_table(), copy=True)
    centres = line_centres_hz(table, rest_hz)
    # the catalog's line centres in the cube's frame: nu_frame = r nu_cube
    ratio, frame_out = cube_frame_ratio(c, frame)
    centres_cube = centres / ratio
    cat_w = pos.weight
    if weighting == "column" and cat_w is None:
        raise XstackError("weighting column needs a catalog column weight")
    px, py = c.celestial.world_to_pixel_values(pos.ra_deg, pos.dec_deg)
    ix = kernels.nearest_pixel(np.nan_to_num(np.asarray(px, float), nan=-1e9))
    iy = kernels.nearest_pixel(np.nan_to_num(np.asarray(py, float), nan=-1e9))
    nchan, ny, nx = c.data.shape
    inside = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    if not inside.all():
        rows = ", ".join(str(i + 1) for i in np.flatnonzero(~inside)[:10])
        warnings.warn(XstackWarning(f"catalog rows {rows}: outside the cube, left out"),
                      stacklevel=2)
    freq_mid = 0.5 * (c.freq_edges_hz[1:] + c.freq_edges_hz[:-1])
    # the noise mask: the beam's major axis, in pixels of each axis (as the continuum stack)
    pixm = np.abs(np.asarray(c.celestial.pixel_scale_matrix)) * 3600.0
    bmaj = beam_mask_arcsec if beam_mask_arcsec is not None else \
        (float(c.header["BMAJ"]) * 3600.0 if "BMAJ" in c.header else None)
    if bmaj is None:
        mask = kernels.central_mask(size, max(size / 8.0, 1.0))
    else:
        mask = kernels.central_mask(size, float(bmaj) / pixm[0, 0], float(bmaj) / pixm[1, 1])
    said = c.header.get("XSPBCOR")
    correct = said is not None and not bool(said)
    cutoff = float(pb_cutoff if pb_cutoff is not None else
                   c.header.get("XSPBCUT", DEFAULT_PB_CUTOFF))
    if weighting == "pb" and primary_beam == "none":
        raise OptionError("weighting pb needs a primary beam", option="weighting")

    centre = size // 2
    num = np.zeros((nbin, size, size))
    den = np.zeros((nbin, size, size))
    regridded: list[np.ndarray] = []  # median: each target's stamp on the grid
    coef: list[np.ndarray] = []  # (nchan, nbin) weights into the centre pixel's sums
    sig2: list[np.ndarray] = []
    used = np.zeros(len(table), dtype=bool)
    n_bins = np.zeros(len(table), dtype=np.int64)
    for k in np.flatnonzero(inside):
        v = velocity_kms(c.freq_edges_hz, centres_cube[k])
        o = overlap_lengths(v, grid)  # (nchan, nbin) km/s
        if not np.any(o > 0):
            continue
        stamp = _stamp_cube(c.data, int(ix[k]), int(iy[k]), size)
        a = _attenuation(c, pos.ra_deg[k], pos.dec_deg[k], freq_mid, primary_beam)
        if a is None and (weighting == "pb" or correct):
            raise XstackError(f"{c.name}: no primary beam known (TELESCOP "
                              f"{c.header.get('TELESCOP', '')!r}) for "
                              f"{'the pb weighting' if weighting == 'pb' else 'the correction'}")
        if a is not None:
            off = ~(a >= max(cutoff, 1e-6))
            stamp[off] = np.nan
            if correct:
                with np.errstate(divide="ignore", invalid="ignore"):
                    stamp /= np.where(off, 1.0, a)[:, None, None]
        sigma = kernels.noise_sigma(stamp, mask, noise_estimator)[0]
        if weighting == "sigma2":
            with np.errstate(divide="ignore"):
                w = np.where(np.isfinite(sigma) & (sigma > 0), 1.0 / sigma**2, 0.0)
        elif weighting == "pb":
            w = np.nan_to_num(a, nan=0.0) ** 2
        elif weighting == "column":
            w = np.full(nchan, float(cat_w[k]))
        else:
            w = np.ones(nchan)
        if method == "median":
            w = np.ones(nchan)  # the median's error: that of the equally weighted mean
        finite = np.isfinite(stamp)
        s0 = np.where(finite, stamp, 0.0)
        wo = w[:, None] * o  # (nchan, nbin)
        fin = finite.astype(np.float64)
        if method == "mean":
            num += np.einsum("ij,iyx->jyx", wo, s0)
            den += np.einsum("ij,iyx->jyx", wo, fin)
        else:
            cnt = np.einsum("ij,iyx->jyx", o, fin)
            with np.errstate(invalid="ignore", divide="ignore"):
                regridded.append(np.where(cnt > 0, np.einsum("ij,iyx->jyx", o, s0) / cnt,
                                          np.nan))
        ck = wo * fin[:, centre, centre][:, None]
        good_sigma = np.isfinite(sigma)
        covered = ck.sum(axis=0) > 0
        if not covered.any():
            continue
        used[k] = True
        n_bins[k] = int(covered.sum())
        coef.append(ck)
        sig2.append(np.where(good_sigma, sigma, np.nan) ** 2)
    if not used.any():
        raise NoDataError("no target's line falls in the cube's channels within the velocity "
                          "range (or every stamp has zero weight)")
    C = np.stack(coef)  # (ntarget, nchan, nbin)
    S2 = np.stack(sig2)  # (ntarget, nchan)
    dsum = C.sum(axis=(0, 1))  # (nbin,)
    n_per_bin = (C.sum(axis=1) > 0).sum(axis=0).astype(np.int64)
    with np.errstate(invalid="ignore", divide="ignore"):
        if method == "mean":
            stacked = np.where(den > 0, num / den, np.nan)
            weight_sum = den
        else:
            R = np.stack(regridded)
            weight_sum = np.isfinite(R).sum(axis=0).astype(np.float64)
            stacked = np.full(R.shape[1:], np.nan)
            ok = weight_sum > 0
            stacked[ok] = np.nanmedian(R[:, ok], axis=0)
        A = C / np.where(dsum > 0, dsum, np.inf)[None, None, :]
        cov = np.einsum("kij,kil,ki->jl", A, A, np.nan_to_num(S2, nan=0.0))
    if method == "median":
        cov = cov * kernels.MEDIAN_NOISE_FACTOR**2
    empty = dsum <= 0
    cov[empty, :] = np.nan
    cov[:, empty] = np.nan
    flux = stacked[:, centre, centre].copy()
    flux[empty] = np.nan
    err = np.sqrt(np.diag(cov))
    from xstack.imstack.io import stamp_header
    from xstack.imstack.stack import _mean_position

    ra0, dec0 = _mean_position(pos.ra_deg[used], pos.dec_deg[used], np.ones(int(used.sum())))
    header = stamp_header(ra0, dec0, size, c.celestial.pixel_scale_matrix)
    for key in ("BMAJ", "BMIN", "BPA", "TELESCOP"):
        if key in c.header:
            header[key] = c.header[key]
    table["used"] = used
    table["line_centre_hz"] = centres
    table["n_bins"] = n_bins
    table["x_pix"] = np.asarray(px, dtype=np.float64)
    table["y_pix"] = np.asarray(py, dtype=np.float64)
    options = json_ready({
        "cube": str(cube), "line_frequency_hz": rest_hz,
        "velocity_resolution_kms": float(velocity_resolution),
        "velocity_range_kms": [float(x) for x in velocity_range], "method": method,
        "weighting": weighting, "stamp_size": size, "primary_beam": primary_beam,
        "pb_corrected_here": bool(correct), "pb_cutoff": cutoff,
        "beam_mask_arcsec": None if bmaj is None else float(bmaj),
        "noise_estimator": noise_estimator, "frame": frame_out, "cube_frame": c.frame,
        "frame_ratio": float(ratio)})
    res = ImLineStackResult(
        velocity_edges_kms=grid, velocity_kms=0.5 * (grid[1:] + grid[:-1]), flux_jy=flux,
        flux_err_jy=err, flux_cov_jy2=cov, n_targets_per_bin=n_per_bin,
        n_positions=int(used.sum()), n_visibilities=0, positions=table,
        rest_frequency_hz=rest_hz, frame=frame_out, stacked=stacked, weight_sum=weight_sum,
        header=header, options=options, out=None if out is None else str(out))
    if out is not None:
        res.write(out, overwrite=overwrite)
    return res
