"""Dirty image cubes: one Stokes I dirty image per channel (or per group of channels).

Each plane is exactly the continuum image (:func:`xstack.imaging.image.make_image`) of the
store's channels of that plane alone: the same ducc0 gridder, sign convention, weighting and
primary-beam handling, run on the store with its frequency axis cut to the plane's channels.
Only one plane is held at a time when the cube is streamed to a FITS file (``out=``).

FITS layout (``write`` / ``out=``): a 4-D primary HDU (RA, Dec, FREQ, STOKES) like the
continuum images (``docs/imaging.md``), with a linear FREQ axis (Hz, CRVAL3 the first plane's
centre frequency, CDELT3 the plane spacing; ``SPECSYS`` from the store's frequency frame,
:func:`xstack.frames.frequency_frame`), and the restoring beam of every plane in a CASA-style
``BEAMS`` binary-table extension (columns BMAJ, BMIN [arcsec], BPA [deg], CHAN, POL;
``CASAMBM = T`` in the primary header): the CASA convention, also read by spectral-cube and
radio-beam (the tests check it with astropy only). The
primary header's BMAJ/BMIN/BPA are the median plane's beam. Cubes are dirty (no CLEAN).
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
from astropy.io import fits

from xstack._result import Result
from xstack.errors import NoDataError, OptionError, XstackError

#: FITS SPECSYS of each casacore frequency frame (FITS WCS paper III, table 8).
SPECSYS = {"TOPO": "TOPOCENT", "GEO": "GEOCENTR", "BARY": "BARYCENT", "LSRK": "LSRK",
           "LSRD": "LSRD", "GALACTO": "GALACTOC", "LGROUP": "LOCALGRP", "CMB": "CMBDIPOL",
           "REST": "SOURCE"}


@dataclass(kw_only=True)
class CubeResult(Result):
    """A dirty image cube (:func:`make_cube`).

    Attributes
    ----------
    image
        (nplane, ny, nx) float64, Jy/beam (None when streamed to ``out`` with ``keep=False``).
    frequency_hz
        (nplane,) centre frequency of each plane (the mean of its channels' frequencies), Hz.
    channel_width_hz
        (nplane,) total width of each plane's channels, Hz.
    beams
        (nplane, 3) restoring beam (bmaj, bmin arcsec; bpa deg) of each plane; NaN for a plane
        with no data.
    header
        The cube's 4-D FITS header (spectral WCS, SPECSYS, median beam).
    n_visibilities, sum_weights
        (nplane,) per plane.
    """

    image: np.ndarray | None
    frequency_hz: np.ndarray
    channel_width_hz: np.ndarray
    beams: np.ndarray
    header: fits.Header
    n_visibilities: np.ndarray
    sum_weights: np.ndarray
    channels: int = 1
    frame: str = "TOPO"
    out: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: planes, frequencies (Hz), beams, visibilities, frame."""
        return {"n_planes": int(self.frequency_hz.size), "channels_per_plane": self.channels,
                "frequency_hz": [float(f) for f in self.frequency_hz],
                "channel_width_hz": [float(f) for f in self.channel_width_hz],
                "beams_arcsec_deg": [[float(x) for x in b] for b in self.beams],
                "n_visibilities": [int(n) for n in self.n_visibilities],
                "frame": self.frame, "out": None if self.out is None else str(self.out)}

    def write(self, path: str | os.PathLike, overwrite: bool = False) -> Path:
        """Write the in-memory cube as FITS (float32, BEAMS table)."""
        if self.image is None:
            raise XstackError("this cube was streamed to a file and not kept in memory")
        from xstack._atomic import atomic_output

        with atomic_output(path, overwrite=overwrite) as tmp:
            data = self.image.astype(np.float32)[None]
            hdul = fits.HDUList([fits.PrimaryHDU(data=data, header=self.header),
                                 beams_table(self.beams)])
            hdul.writeto(tmp, output_verify="exception")
        return Path(path)


def beams_table(beams: np.ndarray) -> fits.BinTableHDU:
    """The CASA-style ``BEAMS`` extension of a cube: one row per plane (Stokes I)."""
    beams = np.asarray(beams, dtype=np.float64).reshape(-1, 3)
    n = beams.shape[0]
    cols = [fits.Column(name="BMAJ", format="E", unit="arcsec", array=beams[:, 0]),
            fits.Column(name="BMIN", format="E", unit="arcsec", array=beams[:, 1]),
            fits.Column(name="BPA", format="E", unit="deg", array=beams[:, 2]),
            fits.Column(name="CHAN", format="J", array=np.arange(n, dtype=np.int32)),
            fits.Column(name="POL", format="J", array=np.zeros(n, dtype=np.int32))]
    hdu = fits.BinTableHDU.from_columns(cols, name="BEAMS")
    hdu.header["EXTVER"] = 1
    hdu.header["NCHAN"] = n
    hdu.header["NPOL"] = 1
    return hdu


def _plane_groups(freq: np.ndarray, width: np.ndarray, channels: int
                  ) -> list[tuple[slice, float, float]]:
    """(channel slice, centre frequency, total width) of each plane of ``channels`` channels;
    a last incomplete group is left out (it would break the linear spectral axis)."""
    n = freq.size // channels
    return [(slice(g * channels, (g + 1) * channels),
             float(np.mean(freq[g * channels:(g + 1) * channels])),
             float(np.sum(np.abs(width[g * channels:(g + 1) * channels])))) for g in range(n)]


def observation_keywords(parts: Sequence[Any]) -> dict[str, Any]:
    """FITS keywords of when and where the data were taken (FITS WCS paper III, section 4.1):
    DATE-OBS, MJD-OBS (the first integration), MJD-AVG (the mean of the integrations' times),
    TIMESYS, and OBSGEO-X/Y/Z (the array centre, ITRF metres: the mean antenna position).

    With them a reader converts the cube's topocentric frequencies to another frame (as
    ``xstack imstack --line-frequency`` does: :func:`xstack.frames.frame_ratio` at MJD-AVG);
    keywords whose data are missing are left out."""
    from astropy.time import Time

    times = [np.asarray(ds["time"].values, dtype=np.float64).ravel() for ds in parts
             if "time" in ds.coords or "time" in ds]
    t = np.concatenate(times) if times else np.empty(0)
    t = t[np.isfinite(t)]
    out: dict[str, Any] = {}
    if t.size:
        first = float(t.min()) / 86400.0
        out["DATE-OBS"] = (Time(first, format="mjd", scale="utc").isot, "first integration (UTC)")
        out["MJD-OBS"] = (first, "[d] first integration")
        out["MJD-AVG"] = (float(np.mean(t)) / 86400.0, "[d] mean time of the integrations")
        out["TIMESYS"] = "UTC"
    pos = [np.asarray(ds["ANTENNA_POSITION"].values, dtype=np.float64).reshape(-1, 3)
           for ds in parts if "ANTENNA_POSITION" in ds]
    if pos and np.all(np.isfinite(pos[0])) and np.any(pos[0] != 0):
        centre = pos[0].mean(axis=0)
        for axis, value in zip("XYZ", centre):
            out[f"OBSGEO-{axis}"] = (float(value), "[m] array centre, ITRF")
    return out


def _cube_header(plane_header: fits.Header, freqs: np.ndarray, beams: np.ndarray,
                 frame: str, channels: int, observed: dict[str, Any] | None = None
                 ) -> fits.Header:
    h = plane_header.copy()
    for key, value in (observed or {}).items():
        h[key] = value
    h["NAXIS3"] = int(freqs.size)
    h["CTYPE3"] = "FREQ"
    h["CRVAL3"] = float(freqs[0])
    h["CDELT3"] = float(freqs[1] - freqs[0]) if freqs.size > 1 else float(h.get("CDELT3", 1.0))
    h["CRPIX3"] = 1.0
    h["CUNIT3"] = "Hz"
    h["SPECSYS"] = SPECSYS.get(frame, frame)
    if "RESTFRQ" not in (observed or {}):
        h.remove("RESTFRQ", ignore_missing=True)  # a plane's frequency, not a line's
    good = np.isfinite(beams[:, 0])
    if good.any():
        mid = np.flatnonzero(good)[np.argsort(beams[good, 0])[good.sum() // 2]]
        h["BMAJ"], h["BMIN"], h["BPA"] = (float(beams[mid, 0]) / 3600.0,
                                          float(beams[mid, 1]) / 3600.0, float(beams[mid, 2]))
    h["CASAMBM"] = (True, "one restoring beam per plane: BEAMS table")
    h["XSCUBE"] = (True, "dirty image cube (xstack image --cube)")
    h["XSCHANS"] = (int(channels), "store channels averaged per plane")
    for key in ("XSSUMW",):  # per plane: not one number for the cube
        h.remove(key, ignore_missing=True)
    return h


@dataclass
class VelocityGrid:
    """Planes of equal width in radio velocity about a rest frequency, in a frame.

    Radio velocity v = c (nu_0 - nu) / nu_0 is linear in frequency, so the planes are equal in
    frequency too: width nu_0 dv / c, edges at nu_0 (1 - k dv / c) for integer k (plane
    centres at velocities (k + 1/2) dv).
    """

    rest_hz: float
    resolution_kms: float
    frame: str = "lsrk"


def _velocity_planes(parts: Sequence[tuple[str, Any]], grid: VelocityGrid
                     ) -> list[tuple[np.ndarray, float, float, dict[str, np.ndarray]]]:
    """(channel indices, centre Hz, width Hz, {partition: (ntime, nidx) weight factors}) of
    each plane of ``grid`` lying wholly inside the band at every integration.

    A channel enters a plane with the fraction of its width (in the frame: its edges times
    the integration's r(t), :func:`xstack.frames.partition_frame_ratios`) inside the plane, so
    a plane is the overlap-weighted mean of the channels it covers and moves with the
    Doppler track of topocentric data.
    """
    from xstack.frames import partition_frame_ratios
    from xstack.spectral import SPEED_OF_LIGHT_KMS

    ds0 = parts[0][1]
    freq = np.asarray(ds0["frequency"].values, dtype=np.float64)
    width = (np.abs(np.asarray(ds0["channel_width"].values, dtype=np.float64))
             if "channel_width" in ds0 else None)
    if width is None or not np.all(np.isfinite(width)) or np.any(width <= 0):
        if freq.size < 2:
            raise XstackError("a velocity-grid cube needs the channels' widths")
        width = np.full(freq.size, abs(float(np.median(np.diff(freq)))))
    lo, hi = freq - width / 2, freq + width / 2
    ratios = {name: partition_frame_ratios(ds, grid.frame) for name, ds in parts}
    r_all = np.concatenate(list(ratios.values()))
    band_lo = float(np.max(r_all) * lo.min())
    band_hi = float(np.min(r_all) * hi.max())
    dnu = grid.rest_hz * grid.resolution_kms / SPEED_OF_LIGHT_KMS
    # plane k: [nu_0 - (k + 1) dnu, nu_0 - k dnu]; wholly inside [band_lo, band_hi]
    k_lo = math.ceil((grid.rest_hz - band_hi) / dnu - 1e-9)
    k_hi = math.floor((grid.rest_hz - band_lo) / dnu + 1e-9) - 1
    if k_hi < k_lo:
        raise OptionError(f"no plane of {grid.resolution_kms:g} km/s lies wholly inside the "
                          f"band ({band_lo / 1e6:.6f}-{band_hi / 1e6:.6f} MHz in "
                          f"{grid.frame.upper()})", option="velocity_resolution")
    planes = []
    for k in range(k_hi, k_lo - 1, -1):  # increasing frequency
        p_lo, p_hi = grid.rest_hz - (k + 1) * dnu, grid.rest_hz - k * dnu
        factors: dict[str, np.ndarray] = {}
        touched = np.zeros(freq.size, dtype=bool)
        for name, r in ratios.items():
            a, b = r[:, None] * lo[None, :], r[:, None] * hi[None, :]
            overlap = np.clip(np.minimum(b, p_hi) - np.maximum(a, p_lo), 0.0, None)
            factors[name] = overlap / (b - a)
            touched |= np.any(overlap > 0, axis=0)
        idx = np.flatnonzero(touched)
        planes.append((idx, 0.5 * (p_lo + p_hi), dnu,
                       {n: f[:, idx] for n, f in factors.items()}))
    return planes


def iter_planes(data: Any, *, channels: int = 1, partitions: str | Sequence[str] | None = None,
                velocity_grid: VelocityGrid | None = None,
                **image_kw: Any) -> Iterator[tuple[int, float, float, Any]]:
    """Yield ``(plane, centre_hz, width_hz, ImageResult or None)`` one plane at a time.

    Each plane is :func:`~xstack.imaging.image.make_image` of the selected partitions with
    their frequency axis cut to the plane's channels (None when the plane has no unflagged
    data). Partitions must share one pointing and one frequency axis. With ``velocity_grid``
    the planes are those of :func:`_velocity_planes` (each channel's WEIGHT times the fraction
    of it inside the plane) and ``channels`` must be 1.
    """
    from xstack.imaging.image import group_pointings, select_partitions

    if isinstance(channels, bool) or not isinstance(channels, (int, np.integer)) or channels < 1:
        raise OptionError(f"channels per plane must be an integer >= 1, got {channels!r}",
                          option="channels")
    parts = select_partitions(data, partitions, allow_mosaic=True)
    if len(group_pointings(parts)) > 1:
        raise XstackError("a cube is made of one pointing; the selected partitions have "
                          f"{len(group_pointings(parts))} phase centers (choose one with "
                          "partitions=)", option="partitions")
    freq = np.asarray(parts[0][1]["frequency"].values, dtype=np.float64)
    for name, ds in parts[1:]:
        other = np.asarray(ds["frequency"].values, dtype=np.float64)
        if other.shape != freq.shape or not np.allclose(other, freq, rtol=1e-12, atol=0.0):
            raise XstackError(f"a cube needs partitions with one frequency axis; {name} differs "
                              f"from {parts[0][0]} (choose one spectral window with "
                              "partitions=)", option="partitions")
    if velocity_grid is not None:
        if channels != 1:
            raise OptionError("channels per plane and a velocity grid do not go together",
                              option="channels")
        for i, (idx, centre, w, factors) in enumerate(_velocity_planes(parts, velocity_grid)):
            sub = {}
            for name, ds in parts:
                part = ds.isel(frequency=idx)
                fac = xr.DataArray(factors[name].astype(np.float32), dims=("time", "frequency"))
                sub[name] = part.assign(WEIGHT=part["WEIGHT"] * fac)
            yield i, centre, w, _plane_image(sub, image_kw)
        return
    ds0 = parts[0][1]
    width = (np.asarray(ds0["channel_width"].values, dtype=np.float64)
             if "channel_width" in ds0 else np.full(freq.size, np.nan))
    if freq.size < channels:
        raise OptionError(f"{channels} channels per plane, but the data have {freq.size}",
                          option="channels")
    if freq.size % channels:
        warnings.warn(f"{freq.size} channels are not a whole number of planes of {channels}: "
                      f"the last {freq.size % channels} are left out", stacklevel=3)
    groups = _plane_groups(freq, width, channels)
    centres = np.array([g[1] for g in groups])
    if centres.size > 2:
        step = np.diff(centres)
        if not np.allclose(step, step[0], rtol=1e-6, atol=0.0):
            raise XstackError("the planes' frequencies are not evenly spaced: a FITS cube "
                              "needs a linear spectral axis (image each regular stretch of "
                              "channels with partitions=)")
    for i, (sl, centre, w) in enumerate(groups):
        sub = {name: ds.isel(frequency=sl) for name, ds in parts}
        yield i, centre, w, _plane_image(sub, image_kw)


def _plane_image(sub: dict[str, Any], image_kw: dict[str, Any]) -> Any:
    """make_image of one plane's data, or None when it has no unflagged data."""
    from xstack.imaging.image import make_image

    try:
        with warnings.catch_warnings():
            # the uv-coverage warnings of a plane repeat those of every other plane
            warnings.simplefilter("ignore", UserWarning)
            return make_image(sub, **image_kw)
    except NoDataError:
        return None


def make_cube(data: Any, *, size: int | Sequence[int], cell_arcsec: float, channels: int = 1,
              weighting: str = "natural", robust: float = 0.0, wterm: bool = True,
              pbcor: bool = False, epsilon: float = 1e-6,
              partitions: str | Sequence[str] | None = None, nthreads: int = 0,
              progress: bool = False, autocorrelations: bool = False,
              out: str | os.PathLike | None = None, overwrite: bool = False,
              keep: bool | None = None, velocity_resolution: float | None = None,
              line_frequency: Any = None, frame: str = "lsrk",
              reproducible: bool = True) -> CubeResult:
    """Dirty Stokes I image cube of a store: one plane per ``channels`` channels, or per
    ``velocity_resolution`` km/s of radio velocity about ``line_frequency`` in ``frame``.

    Parameters
    ----------
    data
        Store path, DataTree or partition Dataset (one pointing, one frequency axis).
    size, cell_arcsec, weighting, robust, wterm, pbcor, epsilon, partitions, nthreads,
    progress, autocorrelations, reproducible
        As :func:`xstack.imaging.image.make_image`, per plane.
    channels
        Consecutive channels averaged (imaged together) per plane, >= 1.
    velocity_resolution, line_frequency, frame
        A velocity grid instead of channels: planes ``velocity_resolution`` km/s wide in
        radio velocity about the rest frequency ``line_frequency`` (Hz or a line name), edges
        at multiples of the resolution, in ``frame`` (``lsrk`` or ``bary``; topocentric data
        are converted per integration). Each plane is the overlap-weighted mean of the
        channels it covers (each channel's WEIGHT times the fraction of its width inside the
        plane); only planes wholly inside the band at every integration are made. The FITS
        axis is FREQ (linear in radio velocity) with RESTFRQ and SPECSYS of the frame.
    out
        FITS file to stream the cube to (one plane in memory at a time), written atomically.
    keep
        Keep the planes in memory in ``CubeResult.image`` (default: when ``out`` is None).

    Returns
    -------
    CubeResult
        Planes of frequency ``frequency_hz`` (Hz) with per-plane beams.
    """
    from xstack._atomic import atomic_output, check_output
    from xstack._inputs import partitions as as_partitions
    from xstack.frames import frequency_frame

    if out is not None:
        check_output(out, overwrite)
    keep = out is None if keep is None else bool(keep)
    parts = [ds for _, ds in as_partitions(data)]
    grid = None
    if velocity_resolution is not None or line_frequency is not None:
        from xstack import _vocabulary
        from xstack.frames import frame_name
        from xstack.spectral import rest_frequency

        if velocity_resolution is None or line_frequency is None:
            raise OptionError("a velocity-grid cube needs both velocity_resolution and "
                              "line_frequency", option="velocity_resolution")
        if not float(velocity_resolution) > 0:
            raise OptionError(f"velocity_resolution must be > 0 km/s, got {velocity_resolution}",
                              option="velocity_resolution")
        if frame not in _vocabulary.LINE_FRAMES:
            raise OptionError(f"unknown frame {frame!r} (use "
                              f"{', '.join(_vocabulary.LINE_FRAMES)})", option="frame")
        grid = VelocityGrid(float(rest_frequency(line_frequency)), float(velocity_resolution),
                            frame)
        cube_frame = frame_name(frame)
    else:
        cube_frame = frequency_frame(parts[0])
    frame = cube_frame
    observed = observation_keywords(parts)
    if grid is not None:
        observed["RESTFRQ"] = (grid.rest_hz, "[Hz] rest frequency of the velocity grid")
        observed["XSVRES"] = (grid.resolution_kms, "[km/s] radio velocity per plane")
    planes = iter_planes(data, channels=channels, partitions=partitions, velocity_grid=grid,
                         size=size,
                         cell_arcsec=cell_arcsec, weighting=weighting, robust=robust,
                         wterm=wterm, pbcor=pbcor, epsilon=epsilon, nthreads=nthreads,
                         progress=progress, autocorrelations=autocorrelations,
                         reproducible=reproducible)
    freqs: list[float] = []
    widths: list[float] = []
    beams: list[tuple[float, float, float]] = []
    nvis: list[int] = []
    sumw: list[float] = []
    stack: list[np.ndarray] = []
    template: fits.Header | None = None
    pending: list[int] = []  # planes with no data before the first imaged one
    stream: Any = None

    def plane_data(res: Any, shape: tuple[int, int]) -> np.ndarray:
        return np.full(shape, np.nan) if res is None else res.image

    with (atomic_output(out, overwrite=overwrite) if out is not None
          else _null_path()) as tmp:
        for i, centre, w, res in planes:
            freqs.append(centre)
            widths.append(w)
            beams.append((math.nan,) * 3 if res is None else res.beam)
            nvis.append(0 if res is None else res.n_visibilities)
            sumw.append(0.0 if res is None else res.sum_weights)
            if res is None and template is None:
                pending.append(i)
                continue
            if template is None:
                template = res.header
                shape = res.image.shape
                if tmp is not None:
                    n = _count_planes(data, channels, partitions, grid)
                    # the axis length is fixed up front; CRVAL3/CDELT3 and the beams at the end
                    hdr = _cube_header(template, np.full(n, centre), np.array([res.beam]),
                                       frame, channels, observed)
                    stream = fits.StreamingHDU(tmp, _primary(hdr))
                for _ in pending:
                    blank = np.full(shape, np.nan)
                    if stream is not None:
                        stream.write(blank.astype(np.float32)[None, None])
                    if keep:
                        stack.append(blank)
            img = plane_data(res, shape)
            if stream is not None:
                stream.write(img.astype(np.float32)[None, None])
            if keep:
                stack.append(np.asarray(img, dtype=np.float64))
        if template is None:
            raise NoDataError("no unflagged parallel-hand visibilities with positive weight "
                              "in any plane")
        fr = np.asarray(freqs)
        bm = np.asarray(beams, dtype=np.float64)
        header = _cube_header(template, fr, bm, frame, channels, observed)
        if stream is not None:
            stream.close()
            # the beams are known only now: the final header and the BEAMS table
            with fits.open(tmp, mode="update") as hdul:
                for key in ("BMAJ", "BMIN", "BPA", "CRVAL3", "CDELT3"):
                    if key in header:
                        hdul[0].header[key] = header[key]
                hdul.append(beams_table(bm))
    return CubeResult(image=np.stack(stack) if keep else None, frequency_hz=fr,
                      channel_width_hz=np.asarray(widths), beams=bm, header=header,
                      n_visibilities=np.asarray(nvis, dtype=np.int64),
                      sum_weights=np.asarray(sumw), channels=int(channels), frame=frame,
                      out=None if out is None else Path(out))


def _primary(h: fits.Header) -> fits.Header:
    """``h`` with the mandatory primary keywords first (float32 data), for streaming."""
    mandatory = ("SIMPLE", "BITPIX", "NAXIS", "NAXIS1", "NAXIS2", "NAXIS3", "NAXIS4", "EXTEND")
    out = fits.Header([("SIMPLE", True), ("BITPIX", -32), ("NAXIS", 4),
                       ("NAXIS1", h["NAXIS1"]), ("NAXIS2", h["NAXIS2"]),
                       ("NAXIS3", h["NAXIS3"]), ("NAXIS4", 1), ("EXTEND", True)])
    for card in h.cards:
        if card.keyword not in mandatory:
            out.append(card)
    return out


def _count_planes(data: Any, channels: int, partitions: Any,
                  grid: VelocityGrid | None = None) -> int:
    from xstack.imaging.image import select_partitions

    parts = select_partitions(data, partitions, allow_mosaic=True)
    if grid is not None:
        return len(_velocity_planes(parts, grid))
    return int(parts[0][1].sizes["frequency"]) // int(channels)


class _null_path:
    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: Any) -> None:
        return None
