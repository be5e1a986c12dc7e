"""FITS images with a celestial WCS, as CASA lays them out.

Layout written by xstack (``write_image``)::

    NAXIS  = 4      data shape (1, 1, ny, nx), float32
    CTYPE1 = 'RA---SIN'  CDELT1 = -cell/3600 (deg; RA increases to the left / east)
    CTYPE2 = 'DEC--SIN'  CDELT2 = +cell/3600
    CRPIX1 = nx // 2 + 1,  CRPIX2 = ny // 2 + 1   (1-based: the phase center pixel)
    CRVAL1, CRVAL2 = phase center (deg, ICRS; RADESYS = 'ICRS')
    LONPOLE = 180 (the default except at CRVAL2 = +90, where it keeps the orientation)
    CTYPE3 = 'FREQ'   (CRVAL3 = weighted mean frequency, Hz; degenerate)
    CTYPE4 = 'STOKES' (CRVAL4 = 1 = I; degenerate)
    BUNIT  = 'Jy/beam' (image, residual), 'Jy/pixel' (model), '' (PSF)
    BMAJ, BMIN (deg), BPA (deg east of north): Gaussian fit to the PSF main lobe
    XSPBCOR  = T/F  the image IS primary-beam corrected (image) / is not (residual, model)
    XSPBFILE = 'OUT.pb.fits'  the effective primary beam travelling with the image (a name
               beside the image file); XSPBCUT its cutoff (docs/conventions.md)

``read_image`` reads any FITS image with a celestial WCS (2-D, or with degenerate extra axes)
and returns the 2-D plane, its celestial WCS and the header.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS

from xstack._atomic import atomic_output
from xstack.errors import XstackError


def make_header(ny: int, nx: int, cell_arcsec: float, phase_center: tuple[float, float],
                frequency: float | None = None, bandwidth: float | None = None,
                beam: tuple[float, float, float] | None = None, bunit: str = "Jy/beam",
                telescope: str | None = None, extra: dict[str, Any] | None = None) -> fits.Header:
    """The 4-D (RA, Dec, FREQ, STOKES) header of an xstack image.

    Parameters
    ----------
    ny, nx
        Image shape (Dec pixels, RA pixels).
    cell_arcsec
        Pixel size, arcsec.
    phase_center
        (ra, dec) in radians: the reference pixel's world position.
    frequency, bandwidth
        Reference frequency and total bandwidth, Hz (optional).
    beam
        (bmaj_arcsec, bmin_arcsec, bpa_deg) restoring beam (optional).
    bunit
        Brightness unit.
    extra
        Further keywords (8 characters at most each).
    """
    h = fits.Header()
    h["NAXIS"] = 4
    h["NAXIS1"] = int(nx)
    h["NAXIS2"] = int(ny)
    h["NAXIS3"] = 1
    h["NAXIS4"] = 1
    h["CTYPE1"] = "RA---SIN"
    h["CRVAL1"] = float(np.degrees(phase_center[0]) % 360.0)
    h["CDELT1"] = -float(cell_arcsec) / 3600.0
    h["CRPIX1"] = float(nx // 2 + 1)
    h["CUNIT1"] = "deg"
    h["CTYPE2"] = "DEC--SIN"
    h["CRVAL2"] = float(np.degrees(phase_center[1]))
    h["CDELT2"] = float(cell_arcsec) / 3600.0
    h["CRPIX2"] = float(ny // 2 + 1)
    h["CUNIT2"] = "deg"
    # FITS defaults LONPOLE to 0 (not 180) when CRVAL2 is exactly +90, which would flip an
    # image centered on the north pole; 180 keeps the l, m orientation of every other center
    h["LONPOLE"] = 180.0
    h["CTYPE3"] = "FREQ"
    h["CRVAL3"] = float(frequency) if frequency else 1.0
    h["CDELT3"] = float(bandwidth) if bandwidth else 1.0
    h["CRPIX3"] = 1.0
    h["CUNIT3"] = "Hz"
    h["CTYPE4"] = "STOKES"
    h["CRVAL4"] = 1.0
    h["CDELT4"] = 1.0
    h["CRPIX4"] = 1.0
    h["CUNIT4"] = ""
    h["RADESYS"] = "ICRS"
    h["EQUINOX"] = 2000.0
    h["SPECSYS"] = "TOPOCENT"
    if frequency:
        h["RESTFRQ"] = float(frequency)
    h["BUNIT"] = bunit
    if beam is not None:
        h["BMAJ"] = float(beam[0]) / 3600.0
        h["BMIN"] = float(beam[1]) / 3600.0
        h["BPA"] = float(beam[2])
    if telescope:
        h["TELESCOP"] = str(telescope)
    h["ORIGIN"] = "xstack"
    for key, value in (extra or {}).items():
        h[key] = value
    return h


#: Header keyword: True if the image is primary-beam corrected (xstack writes it on every image).
PBCOR_KEY = "XSPBCOR"
#: Header keyword: file name (beside the image) of the primary beam travelling with the image.
PBFILE_KEY = "XSPBFILE"
#: Header keyword: primary-beam cutoff of the image (coverage: beam >= cutoff).
PBCUT_KEY = "XSPBCUT"


def pb_path_for(path: str | os.PathLike) -> Path:
    """The primary-beam file written beside ``X.fits``: ``X.pb.fits`` (like CASA's ``.pb``)."""
    path = Path(path)
    stem = path.name[:-5] if path.name.lower().endswith(".fits") else path.name
    return path.with_name(f"{stem}.pb.fits")


def pb_corrected_from_header(header: fits.Header) -> bool | None:
    """What the header says about primary-beam correction: True, False, or None (nothing)."""
    if PBCOR_KEY not in header:
        return None
    value = header[PBCOR_KEY]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    text = str(value).strip().upper()
    if text in ("T", "TRUE", "1", "YES", "Y"):
        return True
    if text in ("F", "FALSE", "0", "NO", "N"):
        return False
    return None


def pb_file_from_header(header: fits.Header, image_path: str | os.PathLike | None) -> Path | None:
    """The primary-beam file named by ``XSPBFILE`` (relative to the image's folder), or None."""
    name = str(header.get(PBFILE_KEY, "") or "").strip()
    if not name:
        return None
    p = Path(name)
    if not p.is_absolute() and image_path is not None:
        p = Path(image_path).parent / p
    return p


def read_wcs(header: fits.Header, where: str = "") -> WCS:
    """The WCS of a FITS header (astropy, its header-fixing notes silenced), or one clear error
    prefixed with ``where`` (the file's name)."""
    import warnings

    from astropy.wcs import FITSFixedWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FITSFixedWarning)
        try:
            return WCS(header)
        except Exception as exc:  # astropy raises several types for broken headers
            prefix = f"{where}: " if where else ""
            raise XstackError(f"{prefix}cannot read the WCS of the image ({exc})") from None


def celestial_wcs(header: fits.Header) -> WCS:
    """The 2-D celestial WCS of a header (astropy), or a clear error."""
    wcs = read_wcs(header)
    if not wcs.has_celestial:
        raise XstackError("image has no celestial WCS (need RA/Dec axes)")
    return wcs.celestial


def write_image(path: str | os.PathLike, data: np.ndarray, header: fits.Header,
                overwrite: bool = False) -> Path:
    """Write a 2-D image (FITS order [y, x]) as a 4-D float32 FITS file, atomically."""
    data = np.asarray(data)
    if data.ndim != 2:
        raise ValueError("write_image expects a 2-D array")
    h = header.copy()
    ny, nx = data.shape
    if h.get("NAXIS1") != nx or h.get("NAXIS2") != ny:
        raise ValueError("header and data shapes disagree")
    naxis = int(h.get("NAXIS", 2))
    cube = data.astype(np.float32).reshape((1,) * (naxis - 2) + data.shape)
    with atomic_output(path, overwrite=overwrite) as tmp:
        hdu = fits.PrimaryHDU(data=cube, header=h)
        hdu.writeto(tmp, output_verify="exception")
    return Path(path)


def read_image(path: str | os.PathLike) -> tuple[np.ndarray, WCS, fits.Header]:
    """Read the 2-D celestial plane of a FITS image.

    Extra axes (frequency, Stokes) must be degenerate (length 1).

    Returns
    -------
    data : numpy.ndarray
        (ny, nx) float64.
    wcs : astropy.wcs.WCS
        Celestial WCS of the plane.
    header : astropy.io.fits.Header
        The full header.
    """
    path = Path(path)
    if not path.is_file():
        raise XstackError(f"{path}: no such image")
    try:
        with fits.open(path) as hdul:
            hdu = next((h for h in hdul if h.data is not None and getattr(h, "is_image", True)
                        and h.data.ndim >= 2), None)
            if hdu is None:
                raise XstackError(f"{path}: no image data in the FITS file")
            data = np.asarray(hdu.data, dtype=np.float64)
            header = hdu.header.copy()
    except OSError as exc:
        raise XstackError(f"{path}: cannot read as FITS ({exc})") from None
    wcs = celestial_wcs(header)
    extra = [n for n in data.shape[:-2]]
    if any(n != 1 for n in extra):
        raise XstackError(f"{path}: image has non-degenerate extra axes {tuple(data.shape)}")
    return data.reshape(data.shape[-2:]), wcs, header


def beam_from_header(header: fits.Header) -> tuple[float, float, float] | None:
    """(bmaj_arcsec, bmin_arcsec, bpa_deg) from BMAJ/BMIN/BPA, or None."""
    if "BMAJ" not in header or "BMIN" not in header:
        return None
    return (float(header["BMAJ"]) * 3600.0, float(header["BMIN"]) * 3600.0,
            float(header.get("BPA", 0.0)))


def grid_of(header: fits.Header) -> dict[str, Any]:
    """Geometry of an xstack-style SIN image: shape, cell (arcsec), center (rad), ref pixel.

    Raises
    ------
    XstackError
        If the image is not a SIN projection with square pixels and RA increasing left.
    """
    c1, c2 = str(header.get("CTYPE1", "")), str(header.get("CTYPE2", ""))
    if not (c1.startswith("RA") and c1.endswith("SIN") and c2.startswith("DEC") and c2.endswith("SIN")):
        raise XstackError(f"image projection is {c1!r}/{c2!r}; a RA---SIN/DEC--SIN image is needed")
    for key in ("PC1_2", "PC2_1", "CD1_2", "CD2_1", "CROTA2"):
        if abs(float(header.get(key, 0.0))) > 1e-12:
            raise XstackError("rotated image grids are not supported")
    # FITS's default LONPOLE is 0 at CRVAL2 = +90 (180 elsewhere): a grid turned by 180 deg
    lonpole = float(header.get("LONPOLE", 0.0 if float(header.get("CRVAL2", 0.0)) == 90.0
                               else 180.0))
    if abs(lonpole % 360.0 - 180.0) > 1e-9:
        raise XstackError(f"rotated image grids are not supported (LONPOLE = {lonpole:g})")
    cd1 = float(header.get("CDELT1", 0.0))
    cd2 = float(header.get("CDELT2", 0.0))
    if not (cd1 < 0 < cd2) or not math.isclose(-cd1, cd2, rel_tol=1e-9):
        raise XstackError(f"image pixels must be square with RA increasing to the left "
                          f"(CDELT1={cd1}, CDELT2={cd2})")
    return {
        "nx": int(header["NAXIS1"]), "ny": int(header["NAXIS2"]),
        "cell_arcsec": cd2 * 3600.0,
        "center": (math.radians(float(header["CRVAL1"])), math.radians(float(header["CRVAL2"]))),
        "crpix": (float(header["CRPIX1"]), float(header["CRPIX2"])),
    }
