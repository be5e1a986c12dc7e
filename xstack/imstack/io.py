"""Reading FITS images for image-stacking and writing its outputs (all outputs atomic).

Any FITS image with a celestial WCS is accepted: xstack's own images (``xstack image``) and
images from CASA, WSClean, ... Degenerate Stokes and frequency axes are dropped; a Stokes
axis with several planes gives its I plane; other axes must have length 1.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS, FITSFixedWarning

from xstack.errors import XstackError

#: Physical dish diameters (m) of telescopes whose FITS TELESCOP we recognise.
DISH_DIAMETERS = {"ALMA": 12.0, "VLA": 25.0, "EVLA": 25.0, "JVLA": 25.0, "MEERKAT": 13.5,
                  "ATCA": 22.0, "WSRT": 25.0, "GMRT": 45.0, "SMA": 6.0, "NOEMA": 15.0}


@dataclass
class ImageInfo:
    """A 2-D image plane with its celestial WCS and the header facts stacking needs.

    Attributes
    ----------
    data
        float array ``data[y, x]`` (NaN = blanked), native byte order, float32 kept as float32
        (stamps are computed in float64).
    wcs
        2-D celestial :class:`astropy.wcs.WCS` (pixel 0-based via ``world_to_pixel_values``).
    name
        File name (or ``"image[i]"``) used in messages.
    beam_arcsec
        (BMAJ, BMIN) FWHM in arcsec and BPA in degrees, or None.
    frequency_hz
        Frequency of the plane, or None.
    telescope
        TELESCOP, or None.
    pointing_deg
        (ra, dec) of the primary-beam centre: OBSRA/OBSDEC if present, else the reference
        value of the WCS (the phase centre for xstack and CASA images).
    bunit
        BUNIT ("" if absent).
    path
        Path of the file, or None for an in-memory HDU.
    """

    data: np.ndarray
    wcs: WCS
    name: str
    header: fits.Header
    beam_arcsec: tuple[float, float, float] | None = None
    frequency_hz: float | None = None
    telescope: str | None = None
    pointing_deg: tuple[float, float] = (0.0, 0.0)
    bunit: str = ""
    path: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape  # type: ignore[return-value]

    @property
    def pixel_matrix_deg(self) -> np.ndarray:
        """2x2 matrix (deg/pixel) from pixel offsets (x, y) to intermediate world (lon, lat)."""
        return np.asarray(self.wcs.pixel_scale_matrix, dtype=np.float64)


def _hdu_with_image(hdul: fits.HDUList, name: str) -> fits.ImageHDU | fits.PrimaryHDU:
    for hdu in hdul:
        if isinstance(hdu, (fits.PrimaryHDU, fits.ImageHDU)) and hdu.data is not None \
                and hdu.data.ndim >= 2:
            return hdu
    raise XstackError(f"{name}: no image data in any HDU")


def image_from_hdu(hdu: fits.ImageHDU | fits.PrimaryHDU, name: str, path: Path | None = None) -> ImageInfo:
    """Build an :class:`ImageInfo` from an image HDU (see :func:`read_image`)."""
    header = hdu.header
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        try:
            wcs = WCS(header)
        except Exception as exc:  # astropy raises several types for malformed WCS
            raise XstackError(f"{name}: cannot parse the WCS ({exc})") from None
    if not wcs.has_celestial or wcs.wcs.lng < 0 or wcs.wcs.lat < 0:
        raise XstackError(f"{name}: the image has no celestial WCS (need RA/Dec axes, "
                          "e.g. CTYPE1='RA---SIN', CTYPE2='DEC--SIN')")
    data = hdu.data
    naxis = data.ndim
    if wcs.naxis != naxis:
        raise XstackError(f"{name}: WCS has {wcs.naxis} axes but the data has {naxis}")
    lng, lat = wcs.wcs.lng, wcs.wcs.lat
    index: list[Any] = []
    for np_axis in range(naxis):
        wcs_axis = naxis - 1 - np_axis
        if wcs_axis in (lng, lat):
            index.append(slice(None))
            continue
        length = data.shape[np_axis]
        if length == 1:
            index.append(0)
            continue
        ctype = wcs.wcs.ctype[wcs_axis].upper()
        if ctype.startswith("STOKES"):
            sub = wcs.sub([wcs_axis + 1])
            values = sub.wcs_pix2world(np.arange(length)[:, None], 0)[:, 0]
            hits = np.flatnonzero(np.isclose(values, 1.0))
            if hits.size == 0:
                raise XstackError(f"{name}: Stokes axis has no I plane")
            index.append(int(hits[0]))
            continue
        raise XstackError(f"{name}: axis {wcs_axis + 1} ({ctype or 'unnamed'}) has {length} planes; "
                          "image-stacking needs a single 2-D plane (select one first)")
    plane = np.array(data[tuple(index)])  # a copy: the file closes after reading
    if not np.issubdtype(plane.dtype, np.floating):
        plane = plane.astype(np.float64)
    elif not plane.dtype.isnative:
        plane = plane.astype(plane.dtype.newbyteorder("="))  # FITS is big-endian
    # numpy axis order is reversed from FITS: the longitude axis must be the last (x)
    if (naxis - 1 - lng) < (naxis - 1 - lat):
        plane = plane.T
    celestial = wcs.sub([lng + 1, lat + 1])

    beam = None
    if "BMAJ" in header and "BMIN" in header:
        beam = (float(header["BMAJ"]) * 3600.0, float(header["BMIN"]) * 3600.0,
                float(header.get("BPA", 0.0)))
        if not (beam[0] > 0 and beam[1] > 0):
            beam = None
    freq = None
    if wcs.wcs.spec >= 0 and wcs.wcs.ctype[wcs.wcs.spec].upper().startswith("FREQ"):
        spec = wcs.sub([wcs.wcs.spec + 1])
        freq = float(spec.wcs_pix2world([[0.0]], 0)[0, 0])
    elif header.get("RESTFRQ") or header.get("RESTFREQ"):
        freq = float(header.get("RESTFRQ") or header.get("RESTFREQ"))
    if "OBSRA" in header and "OBSDEC" in header:
        pointing = (float(header["OBSRA"]), float(header["OBSDEC"]))
    else:
        pointing = (float(celestial.wcs.crval[0]), float(celestial.wcs.crval[1]))
    telescope = str(header["TELESCOP"]).strip() if "TELESCOP" in header else None
    return ImageInfo(data=plane, wcs=celestial, name=name, header=header.copy(), beam_arcsec=beam,
                     frequency_hz=freq, telescope=telescope or None, pointing_deg=pointing,
                     bunit=str(header.get("BUNIT", "")).strip(), path=path)


def read_image(source: str | os.PathLike | fits.ImageHDU | fits.PrimaryHDU | ImageInfo | Any,
               name: str | None = None) -> ImageInfo:
    """Read one image plane for stacking.

    Parameters
    ----------
    source
        A FITS file path, an astropy image HDU, an in-memory image with ``image`` and
        ``header`` (and optionally ``psf``) attributes such as
        :class:`xstack.imaging.image.ImageResult`, or an :class:`ImageInfo` (returned as is).
    name
        Label for messages (default: the file name).

    Raises
    ------
    XstackError
        Missing or unreadable file, no image data, no celestial WCS, or a non-degenerate
        extra axis.
    """
    if isinstance(source, ImageInfo):
        return source
    if isinstance(source, (fits.ImageHDU, fits.PrimaryHDU)):
        return image_from_hdu(source, name or "image")
    if hasattr(source, "image") and isinstance(getattr(source, "header", None), fits.Header):
        # an in-memory image such as xstack.imaging's ImageResult (image, header[, psf])
        header = source.header
        data = np.asarray(source.image)
        naxis = int(header.get("NAXIS", data.ndim))
        data = data.reshape((1,) * max(naxis - data.ndim, 0) + data.shape)
        info = image_from_hdu(fits.PrimaryHDU(data, header=header), name or "image")
        psf = getattr(source, "psf", None)
        if psf is not None:
            psf = np.asarray(psf)
            psf = psf.reshape((1,) * max(naxis - 2, 0) + psf.shape[-2:])
            info.extra["psf"] = fits.PrimaryHDU(psf, header=header)
        return info
    path = Path(source)
    label = name or str(path)
    if not path.exists():
        raise XstackError(f"{label}: no such image file")
    try:
        with fits.open(path, memmap=True) as hdul:
            return image_from_hdu(_hdu_with_image(hdul, label), label, path)
    except XstackError:
        raise
    except Exception as exc:  # astropy raises OSError/ValueError/... for non-FITS files
        raise XstackError(f"{label}: cannot read as a FITS image ({exc})") from None


def psf_path_for(path: str | os.PathLike) -> Path:
    """The PSF file that ``xstack image`` writes beside ``X.fits``: ``X.psf.fits``."""
    path = Path(path)
    stem = path.name[:-5] if path.name.lower().endswith(".fits") else path.name
    return path.with_name(f"{stem}.psf.fits")


def output_paths(out: str | os.PathLike, cube_format: str = "zarr") -> dict[str, Path]:
    """Names of the outputs for ``OUT.fits``: the stamp, ``OUT.cube.zarr|fits``, ``OUT.png``."""
    out = Path(out)
    stem = out.name[:-5] if out.name.lower().endswith(".fits") else out.name
    return {"fits": out, "cube": out.with_name(f"{stem}.cube.{cube_format}"),
            "png": out.with_name(f"{stem}.png")}


def stamp_header(ra0: float, dec0: float, size: int, pixel_matrix_deg: np.ndarray) -> fits.Header:
    """SIN WCS of a stacked stamp: reference pixel at the stamp centre, at (ra0, dec0) deg.

    The reference position is nominal (the mean stacking position): what matters is that
    offsets from CRPIX are the stacked offsets from the stacking positions, in the pixel
    grid of the input images.
    """
    c = size // 2
    wcs = WCS(naxis=2)
    wcs.wcs.ctype = ["RA---SIN", "DEC--SIN"]
    wcs.wcs.cunit = ["deg", "deg"]
    wcs.wcs.crval = [ra0, dec0]
    wcs.wcs.lonpole = 180.0  # FITS's default flips to 0 at dec0 = +90 exactly
    wcs.wcs.crpix = [c + 1.0, c + 1.0]
    m = np.asarray(pixel_matrix_deg, dtype=np.float64)
    if abs(m[0, 1]) < 1e-12 * abs(m[0, 0]) and abs(m[1, 0]) < 1e-12 * abs(m[1, 1]):
        wcs.wcs.cdelt = [m[0, 0], m[1, 1]]
    else:
        wcs.wcs.cd = m
    wcs.wcs.radesys = "ICRS"
    return wcs.to_header()


def write_fits_atomic(hdul: fits.HDUList, tmp: Path) -> None:
    """Write an HDU list to the temporary path handed out by ``atomic_output``."""
    with open(tmp, "wb") as fh:
        hdul.writeto(fh)


def read_stack_fits(path: str | os.PathLike) -> dict[str, Any]:
    """Read a stacked stamp written by :func:`xstack.imstack.stack.imstack`.

    Returns a dict with ``stamp`` (2-D float64), ``psf`` (2-D or None), ``weights`` (2-D or
    None), ``header`` (primary header), ``pixel_arcsec`` (|x|, |y| pixel sizes) and
    ``centre`` (0-based (y, x) index of the stacking position).
    """
    path = Path(path)
    if not path.exists():
        raise XstackError(f"{path}: no such file")
    with fits.open(path) as hdul:
        header = hdul[0].header.copy()
        stamp = np.asarray(hdul[0].data, dtype=np.float64)
        psf = np.asarray(hdul["PSF"].data, dtype=np.float64) if "PSF" in hdul else None
        wts = np.asarray(hdul["WEIGHTS"].data, dtype=np.float64) if "WEIGHTS" in hdul else None
    wcs = WCS(header)
    scales = np.abs(np.diag(wcs.pixel_scale_matrix)) * 3600.0
    return {"stamp": stamp, "psf": psf, "weights": wts, "header": header,
            "pixel_arcsec": (float(scales[0]), float(scales[1])),
            "centre": (int(round(header["CRPIX2"])) - 1, int(round(header["CRPIX1"])) - 1)}
