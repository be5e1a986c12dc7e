"""Imaging of xstack stores with ducc0's w-gridder: dirty image, PSF, prediction.

Conventions (``docs/imaging.md``):

* Image arrays are FITS-ordered ``[y, x]``: x is RA (increasing to the *left*), y is Dec; the
  phase center sits at pixel ``(ny // 2, nx // 2)`` (0-based), the WCS reference pixel.
* The visibility sign is the project's (paper eq. 1): V = S exp(+2 pi i (u l + v m + w (n-1))/lambda).
  ducc0's ``wgridder.experimental`` uses the opposite (u, v) orientation: with our sign its
  first image axis is -l and its second is m when ``flip_v=True`` (``flip_w=False``). This is
  pinned by tests against a direct Fourier sum with w-terms.
* No division by n: a model-image pixel is the integrated flux density of a point source at
  its center, so prediction reproduces eq. 1 and imaging is its exact adjoint.
* Stokes I = parallel hands (XX, YY or RR, LL, or I), each visibility with its own weight:
  the dirty image is ``sum_k w_k Re[V_k e^{-i phi_k}] / sum_k w_k`` over every unflagged
  parallel-hand visibility of every channel (multi-frequency synthesis), so the PSF peaks at 1.

Visibilities are read chunk by chunk (the store's time x baseline chunks) and the dirty image
is accumulated: ducc0's ``vis2dirty`` is linear, so nothing larger than one chunk is loaded.
With a ``distributed.Client`` active, each batch of chunks is read and gridded by a task on
the cluster and the partial images are summed there in batch order. Both paths cut the chunks
into the same batches (:class:`_BatchCutter`, by unflagged visibilities; a cluster counts them
first, a task per chunk) and add them in the same order, so a cluster's image is the local
one to the bit (with reproducible gridding, the default).
"""

from __future__ import annotations

import fnmatch
import math
import os
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
from astropy.io import fits
from astropy.wcs import WCS

from xstack import _vocabulary
from xstack._result import Result
from xstack._select import PARALLEL_HANDS, sky_correlations
from xstack.beams import BAND_TOP_KEY
from xstack.coords import angular_separation
from xstack.errors import NoDataError, OptionError, XstackError
from xstack.imaging import kernels
from xstack.imaging.fitsio import (
    PBCOR_KEY,
    PBCUT_KEY,
    PBFILE_KEY,
    celestial_wcs,
    make_header,
    pb_path_for,
    write_image,
)

WEIGHTINGS = _vocabulary.IMAGE_WEIGHTINGS
_ARCSEC = math.pi / (180.0 * 3600.0)


# --------------------------------------------------------------------------- results
@dataclass(kw_only=True)
class ImageResult(Result):
    """A dirty (or restored) image with its PSF and metadata.

    Attributes
    ----------
    image
        (ny, nx) float64, Jy/beam, FITS order [y, x] (RA increasing to the left). Primary-beam
        corrected (NaN below the beam cutoff) when ``pbcor`` was asked for, and always for a
        mosaic; the header's ``XSPBCOR`` says which.
    psf
        (ny, nx) float64, peak 1 at (ny // 2, nx // 2).
    wcs
        2-D celestial :class:`astropy.wcs.WCS` of ``image`` (SIN projection).
    beam
        (bmaj_arcsec, bmin_arcsec, bpa_deg): Gaussian fit to the PSF main lobe.
    header
        4-D FITS header (RA, Dec, FREQ, STOKES) used for the image file.
    sum_weights
        Sum of imaging weights over every gridded visibility (normalisation).
    frequency
        Weighted mean frequency, Hz (the FREQ axis value).
    primary_beam
        (ny, nx) the image's primary beam A (peak 1, dimensionless): the model beam's main
        lobe at ``frequency`` (single pointing) or the normalised effective beam of a linear
        mosaic. It travels with the image as ``X.pb.fits`` (:meth:`write_with_pb`), named in
        the header (``XSPBFILE``); corrected image = uncorrected image / pb.
    """

    image: np.ndarray
    psf: np.ndarray
    wcs: WCS
    beam: tuple[float, float, float]
    header: fits.Header
    sum_weights: float
    frequency: float
    phase_center: tuple[float, float] = (0.0, 0.0)
    cell_arcsec: float = 0.0
    weighting: str = "natural"
    robust: float = 0.0
    primary_beam: np.ndarray | None = None
    n_visibilities: int = 0
    partitions: tuple[str, ...] = ()
    telescope: str = ""
    bandwidth: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: shape, cell (arcsec), beam (arcsec, deg), frequency (Hz),
        phase center (deg), weighting, visibilities, primary-beam state, image rms and peak
        (Jy/beam, finite pixels)."""
        finite = self.image[np.isfinite(self.image)]
        return {"shape": list(self.image.shape), "cell_arcsec": float(self.cell_arcsec),
                "beam_arcsec": [float(self.beam[0]), float(self.beam[1])],
                "beam_pa_deg": float(self.beam[2]), "frequency_hz": float(self.frequency),
                "bandwidth_hz": float(self.bandwidth),
                "phase_center_deg": [math.degrees(float(x)) for x in self.phase_center],
                "weighting": self.weighting, "robust": float(self.robust),
                "n_visibilities": int(self.n_visibilities), "partitions": list(self.partitions),
                "telescope": self.telescope,
                "pbcor": bool(self.header.get(PBCOR_KEY, False)),
                "rms_jy": float(np.std(finite)) if finite.size else None,
                "peak_jy": float(np.max(finite)) if finite.size else None}

    def header_for(self, kind: str = "image") -> fits.Header:
        """FITS header for ``kind`` in image | residual | psf | model | pb.

        ``XSPBCOR`` is the image's own statement: as imaged for ``image``, False for the
        residual and the CLEAN model (never corrected); absent for the PSF and the beam.
        """
        h = self.header.copy()
        h["BUNIT"] = {"image": "Jy/beam", "residual": "Jy/beam", "psf": "", "model": "Jy/pixel",
                      "pb": ""}[kind]
        h["XSIMTYPE"] = kind
        if kind in ("residual", "model"):
            h[PBCOR_KEY] = False
        elif kind in ("psf", "pb"):
            h.remove(PBCOR_KEY, ignore_missing=True)
            h.remove(PBFILE_KEY, ignore_missing=True)
        return h

    def write(self, path: str | os.PathLike, data: np.ndarray | None = None, kind: str = "image",
              overwrite: bool = False, pb_file: str | None = None) -> Path:
        """Write ``data`` (default: the image) as a FITS file with this result's header.

        ``pb_file``: name (beside ``path``) of the primary-beam file to record as ``XSPBFILE``.
        """
        h = self.header_for(kind)
        if pb_file:
            h[PBFILE_KEY] = (str(pb_file), "primary beam of this image (beside it)")
        return write_image(path, self.image if data is None else data, h, overwrite=overwrite)

    def write_with_pb(self, path: str | os.PathLike, data: np.ndarray | None = None,
                      kind: str = "image", overwrite: bool = False) -> dict[str, Path]:
        """Write the image and, beside it, its primary beam ``X.pb.fits`` (named in the header).

        The beam is written first, the image last (each atomically), so an image never names
        a beam file that is not there. Returns ``{"image": path, "pb": pb_path}``.
        """
        from xstack._atomic import check_output

        if self.primary_beam is None:
            raise XstackError("this image has no primary beam to write")
        pb_path = pb_path_for(path)
        for p in (pb_path, Path(path)):  # refuse before writing either
            check_output(p, overwrite)
        self.write(pb_path, self.primary_beam, kind="pb", overwrite=overwrite)
        out = self.write(path, data, kind=kind, overwrite=overwrite, pb_file=pb_path.name)
        return {"image": out, "pb": pb_path}


# --------------------------------------------------------------------------- selection
def select_partitions(data: Any, partitions: str | Sequence[str] | None = None, *,
                      allow_mosaic: bool = False) -> list[tuple[str, xr.Dataset]]:
    """Partitions of ``data`` whose names match ``partitions`` (names or glob patterns).

    Unless ``allow_mosaic``, all selected partitions must share one phase center (one
    pointing): CLEAN's major cycles work on a single pointing.
    """
    from xstack._inputs import partitions as as_partitions

    parts = as_partitions(data)
    if partitions is not None:
        pats = [partitions] if isinstance(partitions, str) else list(partitions)
        chosen = [(n, d) for n, d in parts if any(fnmatch.fnmatchcase(n, p) for p in pats)]
        if not chosen:
            raise XstackError(f"no partition matches {pats} (available: "
                              f"{', '.join(n for n, _ in parts)})")
        parts = chosen
    if not allow_mosaic and len(group_pointings(parts)) > 1:
        raise XstackError(
            f"the selected partitions have {len(group_pointings(parts))} different phase centers "
            "(a mosaic): CLEAN works on one pointing at a time (choose one with partitions=); "
            "a dirty linear mosaic of all pointings is made without niter=",
            option=("partitions", "niter"))
    return parts


def group_pointings(parts: Sequence[tuple[str, xr.Dataset]]
                    ) -> list[tuple[tuple[float, float], list[tuple[str, xr.Dataset]]]]:
    """Partitions grouped by phase center (within 1 mas), in order of first appearance.

    Returns
    -------
    list of ((ra, dec) radians, [(name, Dataset), ...])
    """
    groups: list[tuple[tuple[float, float], list[tuple[str, xr.Dataset]]]] = []
    for name, ds in parts:
        ra, dec = (float(x) for x in ds.attrs["phase_center"])
        for center, members in groups:
            if angular_separation(center[0], center[1], ra, dec) <= 1e-3 * _ARCSEC:
                members.append((name, ds))
                break
        else:
            groups.append(((ra, dec), [(name, ds)]))
    return groups


def uvw_rotation(from_center: tuple[float, float], to_center: tuple[float, float]) -> np.ndarray:
    """3x3 matrix taking (u, v, w) referred to ``from_center`` to ``to_center`` (radians).

    The rows of R(c) are the unit vectors u (east), v (north), w (towards c) in equatorial
    (x, y, z), so that u l + v m + w n = b . s for any direction s (docs/conventions.md).
    """
    def frame(ra: float, dec: float) -> np.ndarray:
        sa, ca, sd, cd = math.sin(ra), math.cos(ra), math.sin(dec), math.cos(dec)
        return np.array([[-sa, ca, 0.0], [-sd * ca, -sd * sa, cd], [cd * ca, cd * sa, sd]])

    return frame(*to_center) @ frame(*from_center).T


def rephase(uvw: np.ndarray, vis: np.ndarray | None, frequency: np.ndarray,
            from_center: tuple[float, float], to_center: tuple[float, float]
            ) -> tuple[np.ndarray, np.ndarray | None]:
    """Refer (R, 3) uvw and (R, nchan) visibilities to a new phase center, exactly.

    V' = V exp(+2 pi i (w - w') / lambda), uvw' = R uvw: a source then appears as
    S exp(+2 pi i (u' l' + v' m' + w' (n' - 1)) / lambda) with (l', m', n') relative to the
    new center, so the gridder images directly on the new center's SIN grid.
    """
    from xstack.coords import SPEED_OF_LIGHT

    new = uvw @ uvw_rotation(from_center, to_center).T
    if vis is None:
        return np.ascontiguousarray(new), None
    dw = (uvw[:, 2] - new[:, 2])[:, None] * (np.asarray(frequency)[None, :] / SPEED_OF_LIGHT)
    return np.ascontiguousarray(new), vis * np.exp(2j * np.pi * dw)


def _parallel_hands(ds: xr.Dataset, name: str) -> list[int]:
    pols = [str(p).upper() for p in ds["polarization"].values]
    idx = [i for i, p in enumerate(pols) if p in PARALLEL_HANDS]
    if not idx:
        raise XstackError(f"{name}: no parallel-hand polarization (have {pols}); Stokes I needs "
                          "XX/YY or RR/LL")
    return idx


def _check_grid(size: int | Sequence[int], cell_arcsec: float) -> tuple[int, int, float]:
    if isinstance(size, (int, np.integer)):
        nx = ny = int(size)
    else:
        nx, ny = (int(s) for s in size)
    for n in (nx, ny):
        if n < 32 or n % 2:
            raise XstackError(f"image size must be even and at least 32 pixels, got {n}")
    if not (np.isfinite(cell_arcsec) and cell_arcsec > 0):
        raise XstackError(f"cell size must be positive, got {cell_arcsec}")
    if max(nx, ny) * cell_arcsec * _ARCSEC / 2 >= 1.0:
        raise XstackError("image does not fit in the sky hemisphere (size x cell too large)")
    return ny, nx, float(cell_arcsec) * _ARCSEC


# --------------------------------------------------------------------------- chunk reading
def _blocks(ds: xr.Dataset) -> list[tuple[slice, slice]]:
    """(time, baseline) slices following the store's chunks (or ~128 MB for numpy data)."""
    from xstack.schema import default_time_chunk

    vis = ds["VISIBILITY"]
    if vis.chunks is not None:
        tch, bch = vis.chunks[0], vis.chunks[1]
    else:
        nt, nb, nf, npol = vis.shape
        step = default_time_chunk(nb, nf, npol, vis.dtype.itemsize)
        tch = [min(step, nt - t) for t in range(0, nt, step)] or [0]
        bch = [nb]
    tb = np.concatenate([[0], np.cumsum(tch)]).astype(int)
    bb = np.concatenate([[0], np.cumsum(bch)]).astype(int)
    return [(slice(tb[i], tb[i + 1]), slice(bb[j], bb[j + 1]))
            for i in range(len(tch)) for j in range(len(bch))]


def _read(ds: xr.Dataset, ts: slice, bs: slice, names: Sequence[str]) -> list[np.ndarray]:
    import dask

    from xstack._cluster import local_scheduler

    arrays = [ds[n].data[ts, bs] for n in names]
    # threads measured best in one process; an active distributed client wins (reads there)
    return [np.asarray(a) for a in dask.compute(*arrays, scheduler=local_scheduler("threads"))]


def rows_of_block(uvw: np.ndarray, weight: np.ndarray, flag: np.ndarray, pols: Sequence[int],
                  vis: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Flatten a (time, baseline, chan, pol) block to Stokes-I rows for the gridder.

    Each parallel hand becomes its own set of rows (same uvw), so every visibility keeps its
    own weight. Flagged, non-finite, negative-weight and bad-uvw samples get weight 0; rows
    without any positive weight are dropped.

    Returns
    -------
    uvw_rows : (R, 3) float64; weight_rows : (R, nchan) float64; vis_rows : (R, nchan) complex128
    """
    nf = weight.shape[2]
    uvw2 = np.ascontiguousarray(uvw.reshape(-1, 3), dtype=np.float64)
    good_uvw = np.all(np.isfinite(uvw2), axis=1)
    ws, vs = [], []
    for p in pols:
        w = weight[..., p].reshape(-1, nf).astype(np.float64)
        bad = flag[..., p].reshape(-1, nf) | ~np.isfinite(w) | (w < 0) | ~good_uvw[:, None]
        if vis is not None:
            v = vis[..., p].reshape(-1, nf).astype(np.complex128)
            finite = np.isfinite(v)
            bad |= ~finite
            vs.append(np.where(bad, 0.0, v))
        ws.append(np.where(bad, 0.0, w))
    w_all = np.concatenate(ws)
    keep = np.any(w_all > 0, axis=1)
    uvw_all = np.concatenate([uvw2] * len(pols))[keep]
    uvw_all[~np.isfinite(uvw_all)] = 0.0
    v_all = np.concatenate(vs)[keep] if vis is not None else None
    return np.ascontiguousarray(uvw_all), np.ascontiguousarray(w_all[keep]), v_all


def count_rows_of_block(uvw: np.ndarray, weight: np.ndarray, flag: np.ndarray,
                        pols: Sequence[int]) -> int:
    """Visibilities (rows x channels) :func:`rows_of_block` gives the gridder for this block
    without visibilities (a row is kept if any channel is unflagged with a finite positive
    weight and finite uvw): what a batch of chunks is measured in (:class:`_BatchCutter`)."""
    nf = weight.shape[2]
    good_uvw = np.all(np.isfinite(uvw.reshape(-1, 3)), axis=1)
    kept = 0
    for p in pols:
        w = weight[..., p].reshape(-1, nf)
        ok = ~flag[..., p].reshape(-1, nf) & (w > 0) & np.isfinite(w) & good_uvw[:, None]
        kept += int(np.count_nonzero(np.any(ok, axis=1)))
    return kept * nf


# --------------------------------------------------------------------------- ducc0 wrappers
def _precision(epsilon: float) -> tuple[type, type]:
    # single precision is ~2x faster and good to ~1e-5; below that, double
    return (np.complex64, np.float32) if epsilon >= 1e-4 else (np.complex128, np.float64)


def grid_visibilities(uvw: np.ndarray, frequency: np.ndarray, vis: np.ndarray, weight: np.ndarray,
                      ny: int, nx: int, cell_rad: float, *, epsilon: float = 1e-6, wterm: bool = True,
                      nthreads: int = 0) -> np.ndarray:
    """``sum_k w_k Re[V_k exp(-2 pi i (u l + v m + w (n-1)) / lambda)]`` on the pixel grid.

    Unnormalised dirty image (ducc0 ``vis2dirty``), FITS order (ny, nx), float64.
    """
    import ducc0.wgridder.experimental as wg

    if uvw.shape[0] == 0:
        return np.zeros((ny, nx))
    cdt, fdt = _precision(epsilon)
    dirty = wg.vis2dirty(
        uvw=uvw, freq=np.asarray(frequency, dtype=np.float64), vis=vis.astype(cdt, copy=False),
        wgt=weight.astype(fdt, copy=False), mask=(weight > 0).astype(np.uint8),
        npix_x=nx, npix_y=ny, pixsize_x=cell_rad, pixsize_y=cell_rad, epsilon=epsilon,
        do_wgridding=wterm, nthreads=nthreads, flip_v=True, divide_by_n=False)
    return dirty.T.astype(np.float64)


def predict(model_image: np.ndarray, wcs_or_cell: WCS | float, uvw: np.ndarray, frequency: Any, *,
            epsilon: float = 1e-6, wterm: bool = True, nthreads: int = 0) -> np.ndarray:
    """Visibilities of a model image (ducc0 ``dirty2vis``): the adjoint of imaging.

    ``V(u, v, w) = sum_pix M[y, x] exp(+2 pi i (u l + v m + w (n-1)) / lambda)`` (eq. 1 with
    each pixel a point source of integrated flux M at the pixel center; no 1/n).

    Parameters
    ----------
    model_image
        (ny, nx) Jy/pixel, FITS order, phase center at pixel (ny // 2, nx // 2).
    wcs_or_cell
        Pixel size in arcsec, or the image's WCS (SIN, square pixels, reference pixel at the
        image center).
    uvw
        (..., 3) metres, relative to the image's phase center.
    frequency
        (nchan,) Hz.

    Returns
    -------
    numpy.ndarray
        (..., nchan) complex128.
    """
    import ducc0.wgridder.experimental as wg

    model = np.asarray(model_image, dtype=np.float64)
    ny, nx = model.shape
    if isinstance(wcs_or_cell, WCS):
        cell_arcsec = _cell_from_wcs(wcs_or_cell, ny, nx)
    else:
        cell_arcsec = float(wcs_or_cell)
    _check_grid((nx, ny), cell_arcsec)
    freq = np.atleast_1d(np.asarray(frequency, dtype=np.float64))
    uvw = np.asarray(uvw, dtype=np.float64)
    lead = uvw.shape[:-1]
    uvw2 = np.ascontiguousarray(uvw.reshape(-1, 3))
    good = np.all(np.isfinite(uvw2), axis=1)
    out = np.zeros((uvw2.shape[0], freq.size), dtype=np.complex128)
    if good.any():
        cdt, _ = _precision(epsilon)
        fdt = np.float32 if cdt is np.complex64 else np.float64
        vis = wg.dirty2vis(
            uvw=np.ascontiguousarray(uvw2[good]), freq=freq,
            dirty=np.ascontiguousarray(model.T.astype(fdt)),
            pixsize_x=cell_arcsec * _ARCSEC, pixsize_y=cell_arcsec * _ARCSEC, epsilon=epsilon,
            do_wgridding=wterm, nthreads=nthreads, flip_v=True, divide_by_n=False)
        out[good] = vis
    return out.reshape(*lead, freq.size)


def _cell_from_wcs(wcs: WCS, ny: int, nx: int) -> float:
    w = wcs.celestial
    if not all(c.endswith("SIN") for c in w.wcs.ctype):
        raise XstackError(f"model image projection {list(w.wcs.ctype)} is not SIN")
    scale = w.proj_plane_pixel_scales()
    cell = abs(float(scale[1].to_value("arcsec")))
    if not math.isclose(abs(float(scale[0].to_value("arcsec"))), cell, rel_tol=1e-9):
        raise XstackError("model image pixels are not square")
    crpix = w.wcs.crpix
    if abs(crpix[0] - (nx // 2 + 1)) > 1e-6 or abs(crpix[1] - (ny // 2 + 1)) > 1e-6:
        raise XstackError(f"model image reference pixel {tuple(crpix)} is not its center "
                          f"({nx // 2 + 1}, {ny // 2 + 1}); the grid does not match")
    return cell


# --------------------------------------------------------------------------- uv coverage
#: Header keyword: dimension of the uv coverage at the image's scale. 2 = a 2-D synthesized
#: beam; 1 = every visibility on (or so near) one line through the uv origin that the beam
#: is longer than the image: BMAJ/BMIN then describe no beam.
UVDIM_KEY = "XSUVDIM"
#: uv coverage whose second-moment axis ratio (minor / major, the square root of the
#: eigenvalue ratio) is below this is collinear (to rounding): one baseline in one
#: integration, or a snapshot of collinear baselines.
COLLINEAR_RATIO = 1e-6


def uv_moments(uvw: np.ndarray, frequency: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Weighted second moments of the uv coverage: [sum w u^2, sum w v^2, sum w u v].

    Parameters
    ----------
    uvw : (R, 3) float64
        Baseline coordinates, metres.
    frequency : (C,) float64
        Channel frequencies, Hz.
    weight : (R, C) float64
        Imaging weights (0 for samples that do not enter the image).

    Returns
    -------
    numpy.ndarray
        (3,) float64, wavelengths^2 times the weight unit.
    """
    from xstack.coords import SPEED_OF_LIGHT

    k2 = (np.asarray(frequency, dtype=np.float64) / SPEED_OF_LIGHT) ** 2
    wk = np.asarray(weight, dtype=np.float64) @ k2  # (R,): sum over channels of w (f/c)^2
    u, v = uvw[:, 0], uvw[:, 1]
    return np.array([wk @ (u * u), wk @ (v * v), wk @ (u * v)])


def check_uv_coverage(moments: np.ndarray, parts: Sequence[tuple[str, xr.Dataset]], ny: int,
                      nx: int, cell_arcsec: float) -> tuple[int, str | None]:
    """Is there a 2-D synthesized beam? The dimension of the uv coverage and a message.

    The PSF near its peak is ``1 - 2 pi^2 x^T M x`` (x the direction offset in radians, M the
    weighted mean of (u, v)(u, v)^T in wavelengths, ``moments`` normalised by the sum of the
    weights), i.e. a Gaussian of sigma = 1 / (2 pi sqrt(eigenvalue)) along each eigenvector.

    * Both eigenvalues 0 (every visibility at u = v = 0): no beam at all, an
      :class:`~xstack.errors.XstackError`.
    * Axis ratio sqrt(min / max eigenvalue) below :data:`COLLINEAR_RATIO` (one baseline in
      one integration, collinear baselines in a snapshot), or a beam major axis so
      estimated longer than the image: dimension 1 and a one-line message (the image is
      still the correct dirty image - fringes - but its BMAJ/BMIN describe no beam).

    Returns
    -------
    (dimension, message)
        2 and None for a 2-D beam; 1 and the warning text otherwise.
    """
    from xstack.imaging.kernels import FWHM_PER_SIGMA

    m = np.asarray(moments, dtype=np.float64)
    cov = np.array([[m[0], m[2]], [m[2], m[1]]])
    evals, evecs = np.linalg.eigh(cov)
    n_bl = sum(int(np.count_nonzero(np.asarray(ds["baseline_antenna1_id"].values)
                                    != np.asarray(ds["baseline_antenna2_id"].values)))
               if "baseline_antenna1_id" in ds.coords else int(ds.sizes.get("baseline_id", 0))
               for _, ds in parts)
    n_t = sum(int(ds.sizes.get("time", 0)) for _, ds in parts)
    n_c = sum(int(ds.sizes.get("frequency", 0)) for _, ds in parts)
    what = (f"{n_bl} baseline{'' if n_bl == 1 else 's'}, {n_t} integration{'' if n_t == 1 else 's'}, "
            f"{n_c} channel{'' if n_c == 1 else 's'}")
    if not (np.all(np.isfinite(evals)) and evals[1] > 0):
        raise XstackError(f"uv coverage has zero extent ({what}: every visibility at u = v = 0): "
                          "there is no synthesized beam and nothing to image")
    ratio = math.sqrt(max(float(evals[0]), 0.0) / float(evals[1]))
    # position angle (east of north) of the line the uv points lie on
    eu, ev = evecs[0, 1], evecs[1, 1]
    pa = (math.degrees(math.atan2(eu, ev)) + 90.0) % 180.0 - 90.0
    if ratio < COLLINEAR_RATIO:
        return 1, (f"uv coverage is one-dimensional ({what}, every visibility on one line "
                   f"through the uv origin at position angle {pa:.1f} deg): the synthesized beam "
                   "is not 2-D (stripes across the image), so BMAJ/BMIN mean nothing and "
                   "image-domain stacking or fitting cannot work; stack in the uv-domain")
    fwhm_major = FWHM_PER_SIGMA / (2 * math.pi * math.sqrt(float(evals[0]))) * 180 / math.pi * 3600
    extent = max(nx, ny) * float(cell_arcsec)
    if fwhm_major > extent:
        fwhm_minor = FWHM_PER_SIGMA / (2 * math.pi * math.sqrt(float(evals[1]))) * 180 / math.pi \
            * 3600
        return 1, (f"uv coverage is nearly one-dimensional ({what}, axis ratio {ratio:.2g}, "
                   f"uv points along position angle {pa:.1f} deg): the synthesized beam "
                   f"(~{fwhm_major:.3g}\" x {fwhm_minor:.3g}\") is longer than the image "
                   f"({extent:.3g}\"), so BMAJ/BMIN mean nothing and image-domain stacking or "
                   "fitting cannot work; stack in the uv-domain")
    return 2, None


# --------------------------------------------------------------------------- per-batch work
#: Visibilities (rows x channels) gathered per ducc0 call: every call pays for the FFTs of
#: the whole oversampled grid, so fewer, larger calls are faster; on a cluster, one task's work.
BATCH_VISIBILITIES = 1 << 24
#: Batches gridded at once by a reproducible local pass (one thread each; memory grows with
#: them: a batch's rows and its images).
MAX_BATCHES_IN_FLIGHT = 4
#: Threads of a reproducible batch's dirty pass: its dirty image and PSF, side by side.
_DIRTY_PASS_THREADS = 2
#: Key prefix of the gridding tasks on a cluster (one per batch of store chunks).
GRID_TASK = "xstack-image-grid"
#: Key prefix of the planning tasks on a cluster (a chunk's count of gridder visibilities).
COUNT_TASK = "xstack-image-count"
#: Key prefix of the tasks that sum the gridding tasks' partial images (a chain).
SUM_TASK = "xstack-image-sum"
#: Gridding tasks' partial results each summing task adds to the running sum.
_SUM_FAN_IN = 4
#: Arrays each pass reads per store chunk.
_PASS_COLUMNS = {"density": ("UVW", "WEIGHT", "FLAG"), "model": ("UVW", "WEIGHT", "FLAG"),
                 "dirty": ("UVW", "WEIGHT", "FLAG", "VISIBILITY")}


@dataclass(frozen=True)
class _GridSpec:
    """What a gridding task needs of the :class:`Imager` (small, picklable)."""

    ny: int
    nx: int
    cell: float
    cell_arcsec: float
    epsilon: float
    wterm: bool
    nthreads: int
    weighting: str
    f2: float
    shift: bool
    data_center: tuple[float, ...]
    phase_center: tuple[float, ...]

    reproducible: bool = True

    def kw(self, nthreads: int) -> dict[str, Any]:
        """ducc0 keywords of a gridding (``vis2dirty``) or a prediction (``dirty2vis``).

        Threaded gridding adds the threads' partial uv grids in the order they finish, so the
        image differs in its last bits from run to run (1e-6 of the peak in single
        precision, measured); a threaded prediction differs between thread counts. CLEAN,
        taking the largest residual pixel at every step, turns either into other components.
        One thread when ``reproducible``: the same data give the same bits whatever the
        threads (on a cluster too, whatever the workers' threads: batches and their sums are
        the local path's, see :class:`_BatchCutter`).
        """
        return {"epsilon": self.epsilon, "wterm": self.wterm,
                "nthreads": 1 if self.reproducible else nthreads}


class _Read:
    """One array's (time, baseline) slice, read where :meth:`read` runs (in the task).

    For a dask array: the graph of just the blocks that cover the slice (their dependency
    closure, a few tasks) and the slice within them; for numpy data: the slice itself.
    """

    __slots__ = ("array", "graph", "keys", "index")

    def __init__(self, array: np.ndarray | None = None, graph: dict | None = None,
                 keys: list | None = None, index: tuple[slice, ...] = ()) -> None:
        self.array, self.graph, self.keys, self.index = array, graph, keys, index

    def read(self) -> np.ndarray:
        if self.graph is None:
            return np.asarray(self.array)
        from dask.array.core import concatenate3
        from dask.core import flatten
        from dask.local import get_sync

        flat = list(flatten(self.keys))
        values = dict(zip(flat, get_sync(self.graph, flat), strict=True))

        def nest(k: Any) -> Any:
            return [nest(x) for x in k] if isinstance(k, list) else values[k]

        return np.asarray(concatenate3(nest(self.keys)))[self.index]


class _Batch:
    """The store chunks one gridding task reads itself: ``[(reads, pols, freq), ...]``.

    A plain class on purpose: ``dask.delayed`` looks into lists, dicts and dataclasses and
    would turn dask collections into task inputs (each chunk read on some worker, then moved
    to the gridding task's worker); here the task reads its chunks where it runs.
    """

    __slots__ = ("chunks",)

    def __init__(self, chunks: list[tuple[list[_Read], list[int], np.ndarray]]) -> None:
        self.chunks = chunks


class _BatchCutter:
    """Cuts a sequence of store chunks into batches: a batch is closed once it holds
    ``size`` gridder visibilities (:func:`count_rows_of_block`: after flagging, so a batch
    is a full ducc0 call however much is flagged; each call pays for the FFTs of the whole
    oversampled grid) and before a chunk of another frequency axis.

    The one rule of both paths: the local path feeds it chunk by chunk as it reads them, a
    cluster's plan with counts measured beforehand, so that both make the same batches and
    add their sums in the same order (the same bits).
    """

    def __init__(self, size: int) -> None:
        self.size, self.n, self.freq = int(size), 0, None

    def before(self, freq: np.ndarray) -> bool:
        """Whether a batch ends before a chunk of frequency axis ``freq``."""
        cut = self.freq is not None and (self.freq.shape != freq.shape
                                          or not np.array_equal(self.freq, freq))
        if cut:
            self.n = 0
        self.freq = freq
        return cut

    def after(self, count: int) -> bool:
        """Whether the batch ends after a chunk of ``count`` visibilities."""
        self.n += int(count)
        if self.n >= self.size:
            self.n = 0
            return True
        return False


def _count_task(reads: list[_Read], pols: list[int]) -> int:
    """One cluster task of the planning pass: a chunk's :func:`count_rows_of_block`."""
    uvw, weight, flag = (r.read() for r in reads)
    return count_rows_of_block(uvw, weight, flag, pols)


class _Columns:
    """Makes :class:`_Read` s of a partition's arrays; each array's graph is materialised once
    (culling it per slice costs O(all chunks) per slice: minutes for 10^4 chunks)."""

    def __init__(self) -> None:
        self._arrays: dict[tuple[int, str], tuple[dict, str, list[np.ndarray]]] = {}

    def read(self, ds: xr.Dataset, column: str, ts: slice, bs: slice) -> _Read:
        import dask.array as da
        from dask.core import get_dependencies

        a = ds[column].data
        if not isinstance(a, da.Array) or ts.stop <= ts.start or bs.stop <= bs.start:
            return _Read(array=np.asarray(a[ts, bs]))
        ident = (id(ds), column)
        if ident not in self._arrays:
            bounds = [np.concatenate([[0], np.cumsum(c)]).astype(int) for c in a.chunks]
            self._arrays[ident] = (dict(a.__dask_graph__()), a.name, bounds)
        dsk, name, bounds = self._arrays[ident]
        tb, bb = bounds[0], bounds[1]
        i0, i1 = np.searchsorted(tb, ts.start, "right") - 1, np.searchsorted(tb, ts.stop, "left")
        j0, j1 = np.searchsorted(bb, bs.start, "right") - 1, np.searchsorted(bb, bs.stop, "left")
        ranges = [range(i0, i1), range(j0, j1)] + [range(len(b) - 1) for b in bounds[2:]]

        def keys(prefix: tuple[int, ...], dims: list[range]) -> Any:
            if not dims:
                return (name, *prefix)
            return [keys((*prefix, i), dims[1:]) for i in dims[0]]

        nested = keys((), ranges)
        graph: dict = {}
        todo = [(name, i, j, *rest) for i in ranges[0] for j in ranges[1]
                for rest in np.ndindex(*(len(r) for r in ranges[2:]))]
        while todo:
            k = todo.pop()
            if k in graph:
                continue
            graph[k] = dsk[k]
            todo.extend(get_dependencies(dsk, k))
        index = (slice(ts.start - tb[i0], ts.stop - tb[i0]), slice(bs.start - bb[j0], bs.stop - bb[j0]))
        return _Read(graph=graph, keys=nested, index=index)


def _chunk_rows(spec: _GridSpec, arrays: Sequence[np.ndarray], pols: Sequence[int],
                freq: np.ndarray, density: np.ndarray | None, need_vis: bool
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray] | None:
    """One chunk's gridder rows: (uvw, imaging weight, vis, data weight), None if empty."""
    uvw, w, v = rows_of_block(arrays[0], arrays[1], arrays[2], pols,
                              arrays[3] if need_vis else None)
    if uvw.shape[0] == 0:
        return None
    if spec.shift:
        uvw, v = rephase(uvw, v, freq, spec.data_center, spec.phase_center)
    raw = w
    if density is not None:
        dens = kernels.lookup_weight_grid(density, uvw, freq, spec.cell)
        w = kernels.imaging_weights(w, dens, spec.weighting, spec.f2)
    return uvw, w, v, raw


def _density_chunk(spec: _GridSpec, grid: np.ndarray, arrays: Sequence[np.ndarray],
                   pols: Sequence[int], freq: np.ndarray) -> None:
    """Add one chunk's natural weights to the uv density ``grid`` (in place)."""
    u, w, _ = rows_of_block(arrays[0], arrays[1], arrays[2], pols)
    if spec.shift:
        u, _ = rephase(u, None, freq, spec.data_center, spec.phase_center)
    kernels.accumulate_weight_grid(grid, u, freq, w, spec.cell)


def _threads(nthreads: int) -> int:
    """``nthreads``, or every core for 0."""
    return nthreads if nthreads > 0 else (os.cpu_count() or 1)


def _grid_pair(spec: _GridSpec, uvw: np.ndarray, freq: np.ndarray,
               pair: tuple[np.ndarray, np.ndarray], w: np.ndarray, nthreads: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """Grid two sets of visibilities on the same rows (the dirty image and the PSF).

    Single-threaded reproducible gridding runs the two at once (ducc0 releases the GIL), so
    two cores stay busy; each image is still made by one thread, in a fixed order.
    """
    kw = spec.kw(nthreads)

    def one(v: np.ndarray) -> np.ndarray:
        return grid_visibilities(uvw, freq, v, w, spec.ny, spec.nx, spec.cell, **kw)

    if spec.reproducible and _threads(nthreads) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(_DIRTY_PASS_THREADS) as pool:
            first, second = pool.map(one, pair)
        return first, second
    return one(pair[0]), one(pair[1])


def _dirty_sums(spec: _GridSpec, uvw: np.ndarray, freq: np.ndarray, w: np.ndarray,
                v: np.ndarray, raw: np.ndarray, nthreads: int) -> dict[str, Any]:
    """One batch's unnormalised dirty image and PSF and its weight sums."""
    used = freq[np.any(w > 0, axis=0)]
    dirty, psf = _grid_pair(spec, uvw, freq, (v, np.ones_like(v)), w, nthreads)
    return {
        "dirty": dirty,
        "psf": psf,
        "sum_w": float(w.sum()),
        # data weights are 1/sigma^2: the image noise is sum w_img^2 sigma^2 / (sum w_img)^2
        "var_num": float(np.sum(np.where(raw > 0, w * w / np.where(raw > 0, raw, 1.0), 0.0))),
        "sum_wf": float((w.sum(axis=0) * freq).sum()),
        "nvis": int(np.count_nonzero(w)),
        "fmin": float(used.min()) if used.size else np.inf,
        "fmax": float(used.max()) if used.size else -np.inf,
        "moments": uv_moments(uvw, freq, w),
    }


def _model_sums(spec: _GridSpec, uvw: np.ndarray, freq: np.ndarray, w: np.ndarray,
                model: np.ndarray, nthreads: int) -> dict[str, Any]:
    """One batch's unnormalised dirty image of the model's predicted visibilities."""
    kw = spec.kw(nthreads)
    vis = predict(model, spec.cell_arcsec, uvw, freq, **kw)
    return {"image": grid_visibilities(uvw, freq, vis, w, spec.ny, spec.nx, spec.cell, **kw)}


def _empty_sums(spec: _GridSpec, kind: str) -> dict[str, Any]:
    zeros = np.zeros((spec.ny, spec.nx))
    if kind == "density":
        return {"grid": zeros}
    if kind == "model":
        return {"image": zeros}
    return {"dirty": zeros, "psf": zeros.copy(), "sum_w": 0.0, "var_num": 0.0, "sum_wf": 0.0,
            "nvis": 0, "fmin": np.inf, "fmax": -np.inf, "moments": np.zeros(3)}


def _add_sums(acc: dict[str, Any] | None, part: dict[str, Any]) -> dict[str, Any]:
    """``acc + part`` key by key (min/max for the frequency range), updating ``acc``."""
    if acc is None:
        return part
    for k, v in part.items():
        if k == "fmin":
            acc[k] = min(acc[k], v)
        elif k == "fmax":
            acc[k] = max(acc[k], v)
        elif isinstance(v, np.ndarray):
            acc[k] += v
        else:
            acc[k] = acc[k] + v
    return acc


def _sum_task(*parts: dict[str, Any] | None) -> dict[str, Any] | None:
    """A link of the cluster's summing chain: its inputs added left to right (the running sum
    first, then the next batches), as the local path adds batch after batch, so the
    floating-point sum is the same. Empty batches (None) are skipped; the inputs are left
    untouched (a rerun task must find them as they were)."""
    acc = None
    for p in parts:
        if p is None:
            continue
        if acc is None:
            acc = {k: v.copy() if isinstance(v, np.ndarray) else v for k, v in p.items()}
        else:
            acc = _add_sums(acc, p)
    return acc


def _task_threads(requested: int) -> int:
    """Gridder threads in a task: the worker's threads (at most ``requested`` if > 0)."""
    import sys

    dist = sys.modules.get("distributed")
    if dist is None:
        return requested
    try:
        have = int(dist.get_worker().state.nthreads)
    except ValueError:  # not on a worker
        return requested
    return have if requested <= 0 else max(1, min(requested, have))


def _grid_task(spec: _GridSpec, kind: str, batch: _Batch, density: np.ndarray | None,
               model: np.ndarray | None) -> dict[str, Any] | None:
    """One cluster task: read a batch of store chunks here, grid them, return partial sums
    (None if no visibility of the batch is unflagged).

    ``kind``: ``density`` (uniform/Briggs uv density grid), ``dirty`` (dirty image, PSF and
    weight sums) or ``model`` (dirty image of ``model``'s predicted visibilities).
    """
    nthreads = _task_threads(spec.nthreads)
    grid = np.zeros((spec.ny, spec.nx)) if kind == "density" else None
    rows = []
    for reads, pols, freq in batch.chunks:
        # chunk by chunk, so a task holds one chunk's raw arrays at a time (as the local path)
        got = [r.read() for r in reads]
        if grid is not None:
            _density_chunk(spec, grid, got, pols, freq)
            continue
        r = _chunk_rows(spec, got, pols, freq, density, need_vis=kind == "dirty")
        if r is not None:
            rows.append(r)
    if grid is not None:
        return {"grid": grid}
    if not rows:
        return None  # as the local path, which skips a batch with nothing to grid
    freq = batch.chunks[0][2]
    uvw = np.concatenate([r[0] for r in rows])
    w = np.concatenate([r[1] for r in rows])
    if kind == "model":
        return _model_sums(spec, uvw, freq, w, model, nthreads)
    v = np.concatenate([r[2] for r in rows])
    raw = np.concatenate([r[3] for r in rows])
    return _dirty_sums(spec, uvw, freq, w, v, raw, nthreads)


# --------------------------------------------------------------------------- the imager
class Imager:
    """Streams a selection of partitions through ducc0 with fixed imaging weights.

    Holding the weighting (the uniform/Briggs density grid) fixed lets CLEAN's major cycles
    image the model's predicted visibilities with exactly the weights of the dirty image.
    ``reproducible`` (default) grids each image with one thread, so a CLEAN run again on the
    same data finds the same components (:func:`make_image`).
    """

    def __init__(self, data: Any, *, size: int | Sequence[int], cell_arcsec: float,
                 weighting: str = "natural", robust: float = 0.0, wterm: bool = True,
                 epsilon: float = 1e-6, partitions: str | Sequence[str] | None = None,
                 nthreads: int = 0, progress: bool = False,
                 image_center: tuple[float, float] | None = None,
                 autocorrelations: bool = False, reproducible: bool = True) -> None:
        if weighting not in WEIGHTINGS:
            raise OptionError(f"unknown weighting {weighting!r} (use {', '.join(WEIGHTINGS)})")
        if not (1e-12 < epsilon < 0.1):
            raise OptionError(f"gridder epsilon must be in (1e-12, 0.1), got {epsilon}")
        self.ny, self.nx, self.cell = _check_grid(size, cell_arcsec)
        self.cell_arcsec = float(cell_arcsec)
        # autocorrelations measure system power, not the sky: flagged unless asked for
        self.parts = [(name, sky_correlations(ds, autocorrelations))
                      for name, ds in select_partitions(data, partitions)]
        self.pols = {name: _parallel_hands(ds, name) for name, ds in self.parts}
        self.weighting, self.robust = weighting, float(robust)
        self.wterm, self.epsilon, self.nthreads = bool(wterm), float(epsilon), int(nthreads)
        self.progress = progress
        #: grid with one thread per image, so the same data make the same bits (see
        #: :meth:`_GridSpec.kw`)
        self.reproducible = bool(reproducible)
        #: the data's phase center (the pointing: primary-beam center)
        self.data_center = tuple(float(x) for x in self.parts[0][1].attrs["phase_center"])
        #: the image's center (reference pixel); visibilities are rephased to it if it differs
        self.phase_center = self.data_center if image_center is None else \
            (float(image_center[0]), float(image_center[1]))
        self._shift = angular_separation(*self.data_center, *self.phase_center) > 1e-3 * _ARCSEC
        self.density: np.ndarray | None = None
        self.f2 = 0.0
        #: visibilities (rows x channels) gathered per ducc0 call
        self.batch_visibilities = BATCH_VISIBILITIES
        #: cluster passes' batch plans by the columns they read (see :meth:`_plan`), and
        #: the batches of store chunks they share (:meth:`_cluster_jobs`)
        self._plans: dict[tuple[str, ...], list[_Batch]] = {}
        self._cluster_plan: list[list[tuple[str, xr.Dataset, slice, slice]]] | None = None
        if weighting != "natural":
            self._density_pass()

    # -- iteration
    def _spec(self) -> _GridSpec:
        return _GridSpec(ny=self.ny, nx=self.nx, cell=self.cell, cell_arcsec=self.cell_arcsec,
                         epsilon=self.epsilon, wterm=self.wterm, nthreads=self.nthreads,
                         weighting=self.weighting, f2=self.f2, shift=self._shift,
                         data_center=self.data_center, phase_center=self.phase_center,
                         reproducible=self.reproducible)

    def _chunks(self) -> list[tuple[str, xr.Dataset, slice, slice, np.ndarray]]:
        """Every store chunk of the selection, in order: (partition, dataset, time slice,
        baseline slice, frequencies in Hz)."""
        out = []
        for name, ds in self.parts:
            freq = np.asarray(ds["frequency"].values, dtype=np.float64)
            out.extend((name, ds, ts, bs, freq) for ts, bs in _blocks(ds))
        return out

    def _local_batches(self, names: Sequence[str], description: str
                       ) -> Iterator[list[tuple[str, np.ndarray, list[np.ndarray]]]]:
        """The chunks read in this process, grouped into :class:`_BatchCutter`'s batches:
        each a list of (partition, frequencies, arrays of ``names``; the first three UVW,
        WEIGHT, FLAG)."""
        from xstack._progress import progress_iter

        chunks = self._chunks()
        cutter = _BatchCutter(self.batch_visibilities)
        batch: list[tuple[str, np.ndarray, list[np.ndarray]]] = []
        for name, ds, ts, bs, freq in progress_iter(chunks, description, self.progress,
                                                     total=len(chunks)):
            if cutter.before(freq) and batch:
                yield batch
                batch = []
            arrays = _read(ds, ts, bs, names)
            batch.append((name, freq, arrays))
            if cutter.after(count_rows_of_block(*arrays[:3], self.pols[name])):
                yield batch
                batch = []
        if batch:
            yield batch

    def _iter(self, need_vis: bool, description: str) -> Iterator[tuple[np.ndarray, ...]]:
        """Yield the (uvw, freq, imaging weight, vis, data weight) rows of each batch with
        anything unflagged, read chunk by chunk in this process.

        Small store chunks are gathered into batches (:class:`_BatchCutter`): every ducc0
        call pays for the FFTs of the whole (oversampled) grid, so fewer, larger calls are
        much faster.
        """
        spec = self._spec()
        names = ["UVW", "WEIGHT", "FLAG"] + (["VISIBILITY"] if need_vis else [])
        for batch in self._local_batches(names, description):
            rows = [r for name, freq, arrays in batch
                    if (r := _chunk_rows(spec, arrays, self.pols[name], freq, self.density,
                                         need_vis)) is not None]
            if not rows:
                continue
            uvw = np.concatenate([r[0] for r in rows])
            w = np.concatenate([r[1] for r in rows])
            v = np.concatenate([r[2] for r in rows]) if need_vis else None
            raw = np.concatenate([r[3] for r in rows])
            yield uvw, batch[0][1], w, v, raw

    def _cluster_jobs(self) -> list[list[tuple[str, xr.Dataset, slice, slice]]]:
        """The local path's batches (:class:`_BatchCutter`) for a cluster's tasks, from each
        chunk's count of gridder visibilities, measured once by a task per chunk on the
        cluster (reads UVW, WEIGHT and FLAG; the density pass and every major cycle share it).
        """
        if self._cluster_plan is not None:
            return self._cluster_plan
        import uuid

        import dask

        from xstack._progress import dask_progress

        tag = uuid.uuid4().hex[:12]
        chunks = self._chunks()
        columns = _Columns()
        tasks = [dask.delayed(_count_task, pure=False)(
                     [columns.read(ds, c, ts, bs) for c in ("UVW", "WEIGHT", "FLAG")],
                     self.pols[name], dask_key_name=f"{COUNT_TASK}-{tag}-{i}")
                 for i, (name, ds, ts, bs, _) in enumerate(chunks)]
        with dask_progress("planning", enabled=self.progress):
            counts = dask.compute(*tasks) if tasks else ()
        plan: list[list[tuple[str, xr.Dataset, slice, slice]]] = []
        cur: list[tuple[str, xr.Dataset, slice, slice]] = []
        cutter = _BatchCutter(self.batch_visibilities)
        for (name, ds, ts, bs, freq), n in zip(chunks, counts, strict=True):
            if cutter.before(freq) and cur:
                plan.append(cur)
                cur = []
            cur.append((name, ds, ts, bs))
            if cutter.after(n):
                plan.append(cur)
                cur = []
        if cur:
            plan.append(cur)
        self._cluster_plan = plan
        return plan

    def _plan(self, kind: str) -> list[_Batch]:
        """The cluster tasks' batches (:meth:`_cluster_jobs`) as reads of their store chunks.

        A task carries only the graph of its own chunks. Made once per set of columns (the
        density pass and CLEAN's major cycles share one).
        """
        names = _PASS_COLUMNS[kind]
        if names in self._plans:
            return self._plans[names]
        columns = _Columns()
        batches = [_Batch([([columns.read(ds, c, ts, bs) for c in names], self.pols[name],
                            np.asarray(ds["frequency"].values, dtype=np.float64))
                           for name, ds, ts, bs in jobs]) for jobs in self._cluster_jobs()]
        self._plans[names] = batches
        return batches

    def _on_cluster(self, client: Any, kind: str, description: str,
                    model: np.ndarray | None = None) -> dict[str, Any]:
        """One pass as cluster tasks: a gridding task per batch (reading its own chunks),
        the partial sums added in batch order by a chain of tasks, each adding up to
        ``_SUM_FAN_IN`` batches to the running sum (the local path's order, so the same
        bits); only the total comes back.

        The density grid and the model image go to the cluster once (scattered), not with
        every task.
        """
        import uuid

        import dask

        from xstack._progress import dask_progress

        tag = uuid.uuid4().hex[:12]
        density = None
        if kind != "density" and self.density is not None:
            density = client.scatter(self.density, hash=False)
        shipped = None if model is None else client.scatter(np.asarray(model, dtype=np.float64),
                                                            hash=False)
        spec = self._spec()
        level = [dask.delayed(_grid_task, pure=False)(
                     spec, kind, batch, density, shipped,
                     dask_key_name=f"{GRID_TASK}-{kind}-{tag}-{i}")
                 for i, batch in enumerate(self._plan(kind))]
        if not level:
            return _empty_sums(spec, kind)
        # the first link sums batches 0..K-1, each next one the running sum and K more
        total = dask.delayed(_sum_task, pure=False)(
            *level[:_SUM_FAN_IN], dask_key_name=f"{SUM_TASK}-{kind}-{tag}-0")
        for i in range(_SUM_FAN_IN, len(level), _SUM_FAN_IN):
            total = dask.delayed(_sum_task, pure=False)(
                total, *level[i:i + _SUM_FAN_IN], dask_key_name=f"{SUM_TASK}-{kind}-{tag}-{i}")
        with dask_progress(description, enabled=self.progress):
            (total,) = dask.compute(total)
        return _empty_sums(spec, kind) if total is None else total

    def _density_pass(self) -> None:
        from xstack._cluster import active_client

        client = active_client()
        if client is not None:
            grid = self._on_cluster(client, "density", "weights")["grid"]
        else:
            # a grid per batch, added in batch order: a cluster's sum, to the bit
            grid, spec = None, self._spec()
            for batch in self._local_batches(["UVW", "WEIGHT", "FLAG"], "weights"):
                part = np.zeros((self.ny, self.nx))
                for name, freq, arrays in batch:
                    _density_chunk(spec, part, arrays, self.pols[name], freq)
                grid = part if grid is None else grid + part
            if grid is None:
                grid = np.zeros((self.ny, self.nx))
        self.density = grid
        self.f2 = kernels.briggs_f2(grid, self.robust) if self.weighting == "briggs" else 0.0

    # -- products
    def dirty_and_psf(self) -> dict[str, Any]:
        """Normalised dirty image and PSF plus weight statistics.

        With a ``distributed.Client`` active, each batch of store chunks is read and gridded
        by a task on the cluster and the partial images are summed there; else in this
        process (threads).
        """
        from xstack._cluster import active_client

        client = active_client()
        if client is not None:
            acc: dict[str, Any] | None = self._on_cluster(client, "dirty", "imaging")
        else:
            spec = self._spec()
            acc = self._sum_batches(self._iter(True, "imaging"), _DIRTY_PASS_THREADS,
                                    lambda uvw, freq, w, v, raw: _dirty_sums(
                                        spec, uvw, freq, w, v, raw, self.nthreads))
        if acc is None or not acc["sum_w"] > 0:
            raise NoDataError("no unflagged parallel-hand visibilities with positive weight to image")
        sum_w = acc["sum_w"]
        fmin, fmax = acc["fmin"], acc["fmax"]
        self.sum_weights = sum_w
        return {"dirty": acc["dirty"] / sum_w, "psf": acc["psf"] / sum_w, "sum_weights": sum_w,
                "noise_variance": acc["var_num"] / sum_w**2,
                "frequency": acc["sum_wf"] / sum_w, "n_visibilities": acc["nvis"],
                "bandwidth": float(fmax - fmin) if np.isfinite(fmax) else 0.0,
                "fmin": float(fmin), "fmax": float(fmax), "uv_moments": acc["moments"] / sum_w}

    def image_of_model(self, model: np.ndarray) -> np.ndarray:
        """Dirty image of a model image's predicted visibilities (same weights), normalised.

        ``residual = dirty - image_of_model(model)`` is the exact residual image (linearity).
        On a cluster (an active ``distributed.Client``) each batch is predicted and gridded by
        a task, the model sent to the cluster once per call.
        """
        from xstack._cluster import active_client

        client = active_client()
        if client is not None:
            return self._on_cluster(client, "model", "major cycle", model=model)["image"] \
                / self.sum_weights
        spec = self._spec()
        acc = self._sum_batches(self._iter(False, "major cycle"), 1,
                                lambda uvw, freq, w, _v, _raw: _model_sums(
                                    spec, uvw, freq, w, model, self.nthreads))
        if acc is None:
            return np.zeros((self.ny, self.nx))
        return acc["image"] / self.sum_weights

    def _sum_batches(self, batches: Iterator[tuple[np.ndarray, ...]], threads_per_batch: int,
                     work: Callable[..., dict[str, Any]]) -> dict[str, Any] | None:
        """``work(*batch)`` of every batch, the partial sums added in batch order.

        Threaded gridding runs the batches one after the other, each on ``nthreads``. When
        reproducible (a batch on ``threads_per_batch`` threads), as many batches as the
        threads allow are in flight at once (each holds its rows and images: memory grows
        with them) and their sums are still added in batch order, so the image is the
        same bits as one batch at a time.
        """
        window = min(_threads(self.nthreads) // threads_per_batch, MAX_BATCHES_IN_FLIGHT) \
            if self.reproducible else 1
        acc = None
        if window <= 1:
            for batch in batches:
                acc = _add_sums(acc, work(*batch))
            return acc
        from collections import deque
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(window) as pool:
            pending: deque = deque()
            for batch in batches:
                pending.append(pool.submit(work, *batch))
                if len(pending) >= window:
                    acc = _add_sums(acc, pending.popleft().result())
            while pending:
                acc = _add_sums(acc, pending.popleft().result())
        return acc

    def primary_beam(self, frequency: float, main_lobe: bool = False) -> tuple[np.ndarray, float]:
        """Primary-beam power pattern on the image grid at ``frequency`` and its cutoff.

        ``main_lobe``: 0 beyond the first null (the attenuation a correction divides by).
        """
        from xstack.beams import dish_diameter, standard_beam

        ds = self.parts[0][1]
        dish = dish_diameter(ds)
        beam = standard_beam(str(ds.attrs.get("telescope_name", "")), dish)
        l, m = kernels.pixel_lm(self.ny, self.nx, self.cell)
        if self._shift:
            from xstack.coords import lm_to_radec

            ra, dec = lm_to_radec(l, m, *self.phase_center)
            theta = angular_separation(ra, dec, *self.data_center)
        else:
            theta = np.arcsin(np.clip(np.hypot(l, m), 0.0, 1.0))
        if main_lobe:
            return beam.main_lobe(theta, frequency), beam.cutoff
        return beam(theta, frequency), beam.cutoff

    def result(self, image: np.ndarray, psf: np.ndarray, stats: dict[str, Any],
               pbcor: bool = False) -> ImageResult:
        """Wrap arrays into an :class:`ImageResult` (beam fit, WCS, header, PB correction).

        The uv coverage is checked first (:func:`check_uv_coverage`): zero extent is an error,
        a one-dimensional coverage (no 2-D beam within the image) a warning, and the header's
        ``XSUVDIM`` records which (2 or 1).
        """
        uv_dim = 2
        if "uv_moments" in stats:
            uv_dim, message = check_uv_coverage(stats["uv_moments"], self.parts, self.ny,
                                                self.nx, self.cell_arcsec)
            if message:
                warnings.warn(message, stacklevel=3)
        major, minor, pa = kernels.fit_psf_beam(psf)
        beam = (float(major * self.cell_arcsec), float(minor * self.cell_arcsec), float(pa))
        ds = self.parts[0][1]
        telescope = str(ds.attrs.get("telescope_name", ""))
        header = make_header(self.ny, self.nx, self.cell_arcsec, self.phase_center,
                             stats["frequency"], stats.get("bandwidth") or None, beam,
                             telescope=telescope,
                             extra={"XSWEIGHT": self.weighting, "XSROBUST": self.robust,
                                    "XSSUMW": stats["sum_weights"], "XSWTERM": self.wterm,
                                    "XSEPSIL": self.epsilon, PBCOR_KEY: bool(pbcor),
                                    UVDIM_KEY: (uv_dim, "uv coverage dimension (1: no 2-D beam)")})
        extra: dict[str, Any] = {}
        # the beam travels with every image (OUT.pb.fits), corrected or not
        pb, cutoff = self.primary_beam(stats["frequency"], main_lobe=True)
        header[PBCUT_KEY] = (float(cutoff), "primary-beam cutoff (coverage: pb >= cutoff)")
        # the band edge at which every stage decides "inside the field" (xstack.beams)
        top = max(float(np.max(np.asarray(d["frequency"].values))) for _, d in self.parts)
        header[BAND_TOP_KEY] = (top, "[Hz] highest channel frequency of the data")
        if pbcor:
            extra["uncorrected"] = image
            image = np.where(pb >= max(cutoff, 1e-6), image / np.where(pb > 0, pb, 1.0), np.nan)
        return ImageResult(
            image=image, psf=psf, wcs=celestial_wcs(header), beam=beam, header=header,
            sum_weights=stats["sum_weights"], frequency=stats["frequency"],
            phase_center=self.phase_center, cell_arcsec=self.cell_arcsec,
            weighting=self.weighting, robust=self.robust, primary_beam=pb,
            n_visibilities=stats["n_visibilities"], partitions=tuple(n for n, _ in self.parts),
            telescope=telescope, bandwidth=stats.get("bandwidth", 0.0), extra=extra)


def make_image(data: Any, *, size: int | Sequence[int], cell_arcsec: float, weighting: str = "natural",
               robust: float = 0.0, wterm: bool = True, pbcor: bool = False, epsilon: float = 1e-6,
               partitions: str | Sequence[str] | None = None, nthreads: int = 0,
               progress: bool = False, mosaic_center: tuple[float, float] | None = None,
               pb_cutoff: float | None = None,
               autocorrelations: bool = False, cube: bool = False,
               channels: int = 1, reproducible: bool = True) -> ImageResult | Any:
    """Dirty image and PSF (Stokes I, multi-frequency synthesis) of a store.

    With ``cube=True``: a dirty image cube instead, one plane per ``channels`` channels
    (:func:`xstack.imaging.cube.make_cube`, returning a ``CubeResult``; one pointing).

    Partitions that share a phase center (e.g. several spectral windows of one pointing) are
    imaged jointly. Partitions with different phase centers (a mosaic) give a linear mosaic
    (:func:`make_mosaic`).

    Parameters
    ----------
    data
        Store path, :class:`xarray.DataTree` from :func:`xstack.open_store`, or one partition
        Dataset.
    size
        Image size in pixels: N (square) or (nx, ny); even, >= 32.
    cell_arcsec
        Pixel size, arcsec.
    weighting
        ``natural``, ``uniform`` or ``briggs`` (with ``robust``, CASA's definition). Uniform and
        Briggs densities are counted on the image's uv grid; visibilities outside it (beyond
        the image's Nyquist limit) then get weight 0.
    robust
        Briggs robustness R (-2 ~ uniform, +2 ~ natural).
    wterm
        Correct the w-term exactly (ducc0 w-gridding). Needed for wide fields.
    pbcor
        Divide the image by the primary beam (the telescope's standard beam at the weighted
        mean frequency); pixels below the beam cutoff become NaN. The PSF is never corrected.
        A mosaic is always primary-beam corrected.
    epsilon
        ducc0 gridder accuracy (relative). >= 1e-4 runs in single precision.
    partitions
        Partition names or glob patterns to image (default: all).
    nthreads
        Threads (0 = all cores): ducc0's with ``reproducible=False``; else how many batches
        of visibilities (a batch's dirty image and PSF) are gridded at once, one thread each.
    progress
        Progress bar on stderr.
    reproducible
        Grid and predict with one thread (the dirty image and the PSF side by side), so the
        same data give the same image, and CLEAN the same components, to the last bit
        whatever the threads; False uses ``nthreads``: faster (``benchmarks/bench_imaging.py --only
        reproducible``), but the last bits vary from run to run and between thread counts.
    mosaic_center
        (ra, dec) radians of a mosaic's image center (default: the mean direction of the
        pointings). Ignored for a single pointing.
    pb_cutoff
        Mosaic only: pixels where no pointing's primary beam reaches this power are NaN
        (default: the telescope beam's cutoff, 0.1).
    autocorrelations
        Image autocorrelation baselines too (default: left out, they do not measure the sky).

    Returns
    -------
    ImageResult
    """
    if cube:
        from xstack.imaging.cube import make_cube

        return make_cube(data, size=size, cell_arcsec=cell_arcsec, channels=channels,
                         weighting=weighting, robust=robust, wterm=wterm, pbcor=pbcor,
                         epsilon=epsilon, partitions=partitions, nthreads=nthreads,
                         progress=progress, autocorrelations=autocorrelations,
                         reproducible=reproducible)
    parts = select_partitions(data, partitions, allow_mosaic=True)
    if len(group_pointings(parts)) > 1:
        return make_mosaic(parts, size=size, cell_arcsec=cell_arcsec, weighting=weighting,
                           robust=robust, wterm=wterm, epsilon=epsilon, nthreads=nthreads,
                           progress=progress, center=mosaic_center, pb_cutoff=pb_cutoff,
                           autocorrelations=autocorrelations, reproducible=reproducible)
    imager = Imager(dict(parts), size=size, cell_arcsec=cell_arcsec, weighting=weighting,
                    robust=robust, wterm=wterm, epsilon=epsilon, nthreads=nthreads,
                    progress=progress, autocorrelations=autocorrelations,
                    reproducible=reproducible)
    stats = imager.dirty_and_psf()
    return imager.result(stats["dirty"], stats["psf"], stats, pbcor=pbcor)


def mean_direction(centers: Sequence[tuple[float, float]]) -> tuple[float, float]:
    """(ra, dec) radians of the normalised mean unit vector of ``centers`` (radians)."""
    from xstack.coords import mean_direction as _mean

    c = np.asarray(centers, dtype=np.float64)
    out = _mean(c[:, 0], c[:, 1])
    if out is None:
        raise XstackError("the pointings have no mean direction; give mosaic_center")
    return out


def make_mosaic(data: Any, *, size: int | Sequence[int], cell_arcsec: float,
                weighting: str = "natural", robust: float = 0.0, wterm: bool = True,
                epsilon: float = 1e-6, partitions: str | Sequence[str] | None = None,
                nthreads: int = 0, progress: bool = False,
                center: tuple[float, float] | None = None,
                pb_cutoff: float | None = None,
                autocorrelations: bool = False, reproducible: bool = True) -> ImageResult:
    """Linear mosaic of the pointings of a store on one SIN grid (primary-beam corrected).

    Each pointing p (the partitions sharing a phase center) is imaged on the common grid,
    its visibilities rephased to the mosaic center with rotated uvw (exact, so the grid is a
    true SIN projection about the center for any mosaic size). With D_p its normalised dirty
    image, A_p its primary-beam power at the pixel and W_p = 1 / sigma_p^2 its image noise
    weight::

        I = sum_p W_p A_p D_p / sum_p W_p A_p^2

    (the minimum-variance combination; W_p is equal for equal pointings, giving
    sum A_p D_p / sum A_p^2). Its variance is 1 / sum W_p A_p^2 and a source of flux S shows
    S (sum W_p A_p A_p S / sum W_p A_p^2 = S). The **effective beam** is

        pb = sqrt(sum_p W_p A_p^2) / max_pixels sqrt(sum_p W_p A_p^2)      (peak 1)

    so the noise of the corrected mosaic is sigma_flat / pb, with sigma_flat = the noise of
    the flat-noise (uncorrected) image I * pb, uniform over the mosaic, and pb^2 is the
    inverse-variance weight of the corrected flux. Pixels where pb < ``pb_cutoff`` are NaN
    (the coverage every stage uses: a position is inside the mosaic where pb >= cutoff).

    Returns
    -------
    ImageResult
        ``image``: the mosaic, Jy/beam, PB-corrected (``XSPBCOR = T``). ``pb``: the effective
        beam above (``XSPBNORM`` in the header is its normalisation: the absolute effective
        beam sqrt(sum W_p A_p^2 / sum W_p) is pb * XSPBNORM). ``psf``: the noise-weighted
        mean of the pointings' PSFs (all pointings of one observation share nearly the same
        uv coverage). ``extra``: ``uncorrected`` (the flat-noise image ``image * pb``, 0 where
        no pointing contributes), ``pointings``.
    """
    parts = select_partitions(data, partitions, allow_mosaic=True)
    groups = group_pointings(parts)
    if center is None:
        center = mean_direction([c for c, _ in groups])
    center = (float(center[0]), float(center[1]))
    num = den = psf = None
    total_w = sum_w = sum_wf = 0.0
    nvis = 0
    fmin, fmax = np.inf, -np.inf
    cutoff = pb_cutoff
    pointings = []
    imager = None
    moments = np.zeros(3)
    for pc, members in groups:
        imager = Imager(dict(members), size=size, cell_arcsec=cell_arcsec, weighting=weighting,
                        robust=robust, wterm=wterm, epsilon=epsilon, nthreads=nthreads,
                        progress=progress, image_center=center,
                        autocorrelations=autocorrelations, reproducible=reproducible)
        try:
            st = imager.dirty_and_psf()
        except NoDataError:  # a fully flagged pointing adds nothing
            continue
        a_p, beam_cut = imager.primary_beam(st["frequency"])
        cutoff = beam_cut if pb_cutoff is None else cutoff
        w_p = 1.0 / st["noise_variance"] if st["noise_variance"] > 0 else st["sum_weights"]
        if num is None:
            num, den, psf = np.zeros_like(a_p), np.zeros_like(a_p), np.zeros_like(a_p)
        num += w_p * a_p * st["dirty"]
        den += w_p * a_p * a_p
        psf += w_p * st["psf"]
        moments += w_p * st["uv_moments"]
        total_w += w_p
        sum_w += st["sum_weights"]
        sum_wf += st["frequency"] * st["sum_weights"]
        nvis += st["n_visibilities"]
        fmin, fmax = min(fmin, st["fmin"]), max(fmax, st["fmax"])
        pointings.append({"phase_center": pc, "partitions": [n for n, _ in members],
                          "noise_weight": w_p, "sum_weights": st["sum_weights"]})
    if num is None or imager is None:
        raise NoDataError("no unflagged parallel-hand visibilities with positive weight to image")
    cutoff = max(float(cutoff), 1e-6)
    pb_abs = np.sqrt(den / total_w)
    pb_norm = float(pb_abs.max())
    if not pb_norm > 0:
        raise XstackError("no pointing's primary beam covers the mosaic grid")
    pb = pb_abs / pb_norm
    good = (pb >= cutoff) & (den > 0)
    image = np.where(good, num / np.where(den > 0, den, 1.0), np.nan)
    # the flat-noise image: corrected mosaic times the effective beam (uniform noise)
    flat = np.where(den > 0, num / np.where(den > 0, den, 1.0) * pb, 0.0)
    stats = {"frequency": sum_wf / sum_w, "sum_weights": sum_w, "n_visibilities": nvis,
             "bandwidth": float(fmax - fmin) if np.isfinite(fmax) else 0.0,
             "uv_moments": moments / total_w}
    psf = psf / total_w
    # the header and beam come from the last imager (same grid and center for every pointing)
    imager.parts = parts
    res = imager.result(image, psf, stats, pbcor=False)
    res.header[PBCOR_KEY] = True
    res.header["XSMOSAIC"] = (len(pointings), "linear mosaic of this many pointings")
    res.header[PBCUT_KEY] = (cutoff, "primary-beam cutoff (coverage: pb >= cutoff)")
    res.header["XSPBNORM"] = (pb_norm, "absolute effective beam = pb * XSPBNORM")
    res.primary_beam = pb
    res.partitions = tuple(n for n, _ in parts)
    res.extra.update({"uncorrected": flat, "pointings": pointings, "pb_cutoff": cutoff})
    return res
