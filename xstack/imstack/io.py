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
from astropy.wcs import WCS

from xstack.beams import BAND_TOP_KEY, TELESCOPE_DISH_DIAMETERS
from xstack.errors import XstackError, XstackWarning
from xstack.imaging.fitsio import read_wcs
from xstack.imstack import kernels

#: Physical dish diameters (m) of telescopes whose FITS TELESCOP we recognise (one home:
#: :data:`xstack.beams.TELESCOPE_DISH_DIAMETERS`).
DISH_DIAMETERS = TELESCOPE_DISH_DIAMETERS


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
        (ra, dec) of the primary-beam center: OBSRA/OBSDEC if present, else the reference
        value of the WCS (the phase center for xstack and CASA images).
    bunit
        BUNIT ("" if absent).
    path
        Path of the file, or None for an in-memory HDU.
    band_top_hz
        Highest frequency of the data the image was made from, Hz: the band edge at which
        "inside the field" is decided (:func:`xstack.beams.inside_field`). ``XSFRQHI`` if
        the header has it (xstack images), else the upper edge of the frequency plane
        (CRVAL3 + |CDELT3|/2, as CASA and WSClean record a multi-frequency image), else
        ``frequency_hz``.
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
    band_top_hz: float | None = None

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
    wcs = read_wcs(header, name)
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
    freq = top = None
    if wcs.wcs.spec >= 0 and wcs.wcs.ctype[wcs.wcs.spec].upper().startswith("FREQ"):
        spec = wcs.sub([wcs.wcs.spec + 1])
        freq = float(spec.wcs_pix2world([[0.0]], 0)[0, 0])
        top = freq + abs(float(spec.wcs_pix2world([[0.5]], 0)[0, 0]) - freq)
    elif header.get("RESTFRQ") or header.get("RESTFREQ"):
        freq = float(header.get("RESTFRQ") or header.get("RESTFREQ"))
    if header.get(BAND_TOP_KEY):
        top = float(header[BAND_TOP_KEY])
    if top is None or not np.isfinite(top) or top <= 0:
        top = freq
    if "OBSRA" in header and "OBSDEC" in header:
        pointing = (float(header["OBSRA"]), float(header["OBSDEC"]))
    else:
        pointing = (float(celestial.wcs.crval[0]), float(celestial.wcs.crval[1]))
    telescope = str(header["TELESCOP"]).strip() if "TELESCOP" in header else None
    return ImageInfo(data=plane, wcs=celestial, name=name, header=header.copy(), beam_arcsec=beam,
                     frequency_hz=freq, telescope=telescope or None, pointing_deg=pointing,
                     bunit=str(header.get("BUNIT", "")).strip(), path=path, band_top_hz=top)


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
        pb = getattr(source, "pb", None)
        if pb is not None and np.shape(pb) == info.shape:
            info.extra["pb"] = np.asarray(pb, dtype=np.float64)  # the beam travels with it
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
    """SIN WCS of a stacked stamp: reference pixel at the stamp center, at (ra0, dec0) deg.

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
    """Read a stacked stamp written by :func:`xstack.imstack.stack.stack_images`.

    Returns a dict with ``stamp`` (2-D float64), ``psf`` (2-D or None), ``weights`` (2-D or
    None), ``header`` (primary header), ``pixel_arcsec`` (|x|, |y| pixel sizes) and
    ``center`` (0-based (y, x) index of the stacking position).
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
            "center": (int(round(header["CRPIX2"])) - 1, int(round(header["CRPIX1"])) - 1)}


# ---------------------------------------------------------------------------------------------
# the primary-beam convention of an image (docs/conventions.md, "Primary beams and images")
# ---------------------------------------------------------------------------------------------

@dataclass
class BeamConvention:
    """What an image says about its primary beam, and where the beam comes from.

    Attributes
    ----------
    corrected
        The image is primary-beam corrected (used as is); False: divide by A.
    corrected_from
        ``"header"`` (``XSPBCOR``), ``"option"`` (the caller said so) or ``"assumed"`` (the
        image says nothing: used as is).
    beam_from
        Where A comes from: ``"option: ..."``, ``"beam file ..."``, ``"in-memory beam"``,
        ``"model ... centered on (ra, dec)"``, ``"none (A = 1)"`` or ``"unknown"``.
    cutoff
        Positions with A < cutoff (or A = 0) are outside the image.
    values
        ``values(ra_deg, dec_deg) -> A`` (dimensionless, 0 off the beam image), or None if no
        beam is known (then ``missing`` says why).
    inside
        ``inside(ra_deg, dec_deg) -> bool``: the positions inside the image's field by the one
        rule of every stage (:func:`xstack.beams.inside_field`, at the band edge
        ``ImageInfo.band_top_hz``), or None if no beam is known.
    grid
        A on the image's own pixel grid when the beam came as an array on that grid (a beam
        file beside the image, an in-memory beam), else None (:func:`beam_on_grid` then
        evaluates ``values`` on the pixel centres).
    unit
        The beam is A = 1 everywhere (``primary_beam="none"``).
    """

    corrected: bool
    corrected_from: str
    beam_from: str
    cutoff: float
    values: Any = None
    missing: str = ""
    from_image: bool = False
    inside: Any = None
    grid: np.ndarray | None = None
    unit: bool = False

    @property
    def model_on_grid(self) -> bool:
        """Whether :func:`beam_on_grid` has to evaluate a model (no array on the grid)."""
        return self.values is not None and not self.unit and self.grid is None

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly summary (what the results record)."""
        return {"image_corrected": bool(self.corrected), "corrected_from": self.corrected_from,
                "beam": self.beam_from, "cutoff": float(self.cutoff)}


#: Image rows per block when a beam model is evaluated on every pixel of an image (bounds the
#: memory of the pixel-to-sky transform to ~20 float64 arrays of this many rows).
GRID_ROWS = 256


def beam_on_grid(conv: BeamConvention, info: ImageInfo,
                 footprint: np.ndarray | None = None) -> np.ndarray | None:
    """The primary beam A on the pixels of ``info`` (float64, same shape), NaN where A is
    below the convention's cutoff or 0 (outside the field); None if no beam is known or it is
    A = 1 everywhere (nothing to flatten).

    Used to measure an image's noise where it is flat: the noise of a primary-beam corrected
    image grows as 1/A away from the pointing, and that of ``image * A`` does not.

    Parameters
    ----------
    conv, info
        The image's beam convention (:func:`image_beam`) and the image.
    footprint
        Optional bool mask of the image's shape (e.g. :func:`xstack.imstack.kernels.
        stamp_footprint`): a beam model is then evaluated only there, NaN elsewhere -- the
        pixel-to-sky transform is most of the cost, and a few stamps read a small part of a
        large image. A beam given on the grid is used whole.
    """
    if conv.values is None or conv.unit:
        return None
    if not conv.model_on_grid:
        beam = np.array(conv.grid, dtype=np.float64)
    else:
        ny, nx = info.shape
        if footprint is not None and np.shape(footprint) != (ny, nx):
            raise ValueError(f"footprint has shape {np.shape(footprint)}, the image {(ny, nx)}")
        beam = np.full((ny, nx), np.nan, dtype=np.float64)
        xs = np.arange(nx, dtype=np.float64)
        for y0 in range(0, ny, GRID_ROWS):
            y1 = min(ny, y0 + GRID_ROWS)
            px, py = np.meshgrid(xs, np.arange(y0, y1, dtype=np.float64))
            if footprint is not None:
                use = np.asarray(footprint[y0:y1], dtype=bool)
                if not use.any():
                    continue
                px, py = px[use], py[use]
            ra, dec = info.wcs.pixel_to_world_values(px, py)
            a = np.asarray(conv.values(np.asarray(ra), np.asarray(dec)), np.float64)
            if footprint is None:
                beam[y0:y1] = a
            else:
                beam[y0:y1][use] = a
    with np.errstate(invalid="ignore"):
        beam[~(np.isfinite(beam) & (beam > 0) & (beam >= conv.cutoff))] = np.nan
    return beam


def flat_noise_image(info: ImageInfo, conv: BeamConvention,
                     stamps: tuple[np.ndarray, np.ndarray, int] | None = None
                     ) -> tuple[np.ndarray, bool]:
    """The image on which to measure the local noise sigma_k, where that noise is flat.

    An image that is not primary-beam corrected is its own (its noise is the same over the
    field); a corrected image whose beam is known becomes ``image * A`` (NaN below the
    cutoff), as its noise grows as 1/A away from the pointing; a corrected image without a
    known beam stays as it is. A sigma_k measured on the returned image is that of the
    corrected flux once divided by A at the position -- except for the last case, where it
    already is (:func:`noise_to_corrected`).

    ``stamps`` = ``(x, y, size)``, the noise stamps' centres (0-based pixels) and side,
    limits a beam model's evaluation to the pixels they read (:func:`beam_on_grid` on their
    :func:`~xstack.imstack.kernels.stamp_footprint`, made only when a model is evaluated);
    the flattened image is NaN elsewhere.

    Returns
    -------
    image, flattened
        The 2-D image (the input's own array when not flattened; never modified), and
        whether it is the corrected image times A.
    """
    if not conv.corrected:
        return info.data, False
    footprint = None
    if stamps is not None and conv.model_on_grid:
        footprint = kernels.stamp_footprint(info.shape, *stamps)
    beam = beam_on_grid(conv, info, footprint)
    if beam is None:
        return info.data, False
    return np.asarray(info.data, dtype=np.float64) * beam, True


def noise_to_corrected(sigma: np.ndarray, conv: BeamConvention, flattened: bool,
                       atten: np.ndarray) -> np.ndarray:
    """sigma_k measured on :func:`flat_noise_image` as the noise of the corrected flux.

    Divided by the attenuation ``atten`` (A at each position) for an uncorrected image or a
    flattened one, NaN where A is not positive (outside the beam); unchanged otherwise.
    """
    sigma = np.asarray(sigma, dtype=np.float64)
    if (conv.corrected and not flattened) or conv.values is None or conv.unit:
        return sigma
    atten = np.asarray(atten, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(atten > 0, sigma / atten, np.nan)


def beam_image_values(beam: np.ndarray, wcs: WCS, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
    """A primary-beam image sampled at the nearest pixel of each (ra, dec) deg; 0 off the image."""
    px, py = wcs.world_to_pixel_values(np.asarray(ra, np.float64), np.asarray(dec, np.float64))
    px = np.nan_to_num(np.asarray(px, np.float64), nan=-1e9)
    py = np.nan_to_num(np.asarray(py, np.float64), nan=-1e9)
    ix, iy = np.floor(px + 0.5).astype(np.int64), np.floor(py + 0.5).astype(np.int64)
    ny, nx = beam.shape
    ok = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
    out = np.zeros(np.shape(ra), dtype=np.float64)
    out[ok] = beam[iy[ok], ix[ok]]
    return np.nan_to_num(out, nan=0.0)


def _model_beam(info: ImageInfo, pb: Any) -> tuple[Any, str]:
    """(PrimaryBeam or None, why not) for a model name / PrimaryBeam / None (TELESCOP default)."""
    from xstack.beams import PrimaryBeam, standard_beam

    tel = (info.telescope or "").upper()
    if isinstance(pb, PrimaryBeam):
        return pb, ""
    if pb is None:
        if tel not in DISH_DIAMETERS:
            return None, (f"{info.name}: no primary beam known (TELESCOP {info.telescope!r}, "
                          f"frequency {info.frequency_hz}); give primary_beam=")
        return standard_beam(tel, DISH_DIAMETERS[tel]), ""
    if tel not in DISH_DIAMETERS:
        raise XstackError(f"{info.name}: primary beam {pb!r} needs a known TELESCOP "
                          f"(got {info.telescope!r}); give a PB FITS image instead")
    return standard_beam(tel, DISH_DIAMETERS[tel], model=pb), ""


def image_beam(info: ImageInfo, pb: Any = None, image_corrected: bool | None = None, *,
               cutoff: float | None = None,
               how_to_state: str = "image_corrected=True/False") -> BeamConvention:
    """The primary-beam convention of ``info`` and the beam A to use with it.

    The convention is the image's own statement (``XSPBCOR``) unless ``image_corrected``
    says otherwise (it wins; a disagreement is warned about). An image that says nothing is
    used as is (as if corrected), with a one-line warning naming ``how_to_state``.

    The beam, in order: ``pb`` (a :class:`~xstack.beams.PrimaryBeam`, a model name ``airy``,
    ``gaussian``, ``vla``, ``none``, a PB FITS image, or an array on the image grid) wins;
    else the beam file named by ``XSPBFILE`` beside the image; else the beam of an in-memory
    ``ImageResult``; else the telescope's standard beam (TELESCOP, the image frequency)
    centered on the pointing (OBSRA/OBSDEC or the reference position) -- except for a mosaic
    (``XSMOSAIC`` > 1), whose beam is not that of one pointing.

    ``inside`` of the result decides which positions are inside the field by the one rule of
    every stage (:func:`xstack.beams.inside_field` at ``info.band_top_hz``; for a mosaic's
    effective beam, the beam file itself; docs/conventions.md "Inside the field").
    """
    from xstack.beams import DEFAULT_PB_CUTOFF, PrimaryBeam, inside_field
    from xstack.coords import angular_separation
    from xstack.imaging.fitsio import PBCUT_KEY, pb_corrected_from_header, pb_file_from_header

    header = info.header
    said = pb_corrected_from_header(header)
    if isinstance(pb, str) and pb == "none":
        pb_none = True
    else:
        pb_none = isinstance(pb, PrimaryBeam) and pb.model == "none"
    if image_corrected is not None:
        corrected, corrected_from = bool(image_corrected), "option"
        if said is not None and said != corrected:
            warnings.warn(XstackWarning(
                f"{info.name}: its header says XSPBCOR = {'T' if said else 'F'} but it is "
                f"treated as {'' if corrected else 'not '}primary-beam corrected as asked "
                "(image_corrected)", option="image_corrected"), stacklevel=3)
    elif said is not None:
        corrected, corrected_from = said, "header"
    else:
        corrected, corrected_from = True, "assumed"
        if not pb_none:
            warnings.warn(XstackWarning(
                f"{info.name}: the header does not say whether the image is primary-beam "
                "corrected (no XSPBCOR): used as is, as if corrected; if it is not, state it "
                f"with {how_to_state}", option="image_corrected"), stacklevel=3)
    if cutoff is None:
        cutoff = float(header.get(PBCUT_KEY, DEFAULT_PB_CUTOFF))
    conv = BeamConvention(corrected, corrected_from, "unknown", float(cutoff))

    def from_array(beam: np.ndarray, wcs: WCS, label: str, beam_freq: float | None = None) -> None:
        beam = np.asarray(beam, dtype=np.float64)
        conv.values = lambda ra, dec: beam_image_values(beam, wcs, ra, dec)
        conv.beam_from, conv.from_image = label, True
        if beam.shape == info.shape and (wcs is info.wcs or wcs.wcs.compare(info.wcs.wcs,
                                                                            tolerance=1e-9)):
            conv.grid = beam
        conv.inside = _sampled_inside(beam, wcs, info, beam_freq or info.frequency_hz, conv)

    def from_model(model: PrimaryBeam, label: str) -> None:
        if info.frequency_hz is None:
            conv.missing = (f"{info.name}: no frequency in the header for the primary beam; "
                            "give a PB FITS image instead")
            return
        r0, d0 = np.radians(info.pointing_deg[0]), np.radians(info.pointing_deg[1])
        freq = float(info.frequency_hz)
        conv.values = lambda ra, dec: np.asarray(model.main_lobe(angular_separation(
            np.radians(ra), np.radians(dec), r0, d0), freq), dtype=np.float64)
        top = info.band_top_hz or freq
        conv.inside = lambda ra, dec: inside_field(model, angular_separation(
            np.radians(ra), np.radians(dec), r0, d0), top, conv.cutoff)
        conv.beam_from = (f"{label}: {model.model} beam ({model.dish_diameter:g} m) at "
                          f"{freq / 1e9:.6g} GHz centered on ({info.pointing_deg[0]:.6f}, "
                          f"{info.pointing_deg[1]:.6f}) deg")

    if pb_none:
        conv.values = lambda ra, dec: np.ones(np.shape(ra))
        conv.inside = lambda ra, dec: np.ones(np.shape(ra), dtype=bool)
        conv.beam_from, conv.unit = "none (A = 1)", True
        return conv
    if pb is not None:
        if isinstance(pb, (str, os.PathLike)) and not (isinstance(pb, str) and pb in (
                "airy", "gaussian", "vla")):
            pbimg = read_image(pb, name=f"primary beam {pb}")
            from_array(pbimg.data, pbimg.wcs, f"option: beam image {pb}", pbimg.frequency_hz)
        elif isinstance(pb, np.ndarray):
            if pb.shape != info.shape:
                raise XstackError(f"{info.name}: the primary-beam array has shape {pb.shape}, "
                                  f"the image {info.shape}")
            from_array(pb, info.wcs, "option: beam array on the image grid")
        else:
            model, why = _model_beam(info, pb)
            if isinstance(pb, PrimaryBeam):
                conv.cutoff = float(pb.cutoff)
            from_model(model, "option")
        return conv
    pb_file = pb_file_from_header(header, info.path)
    if pb_file is not None and info.path is not None:
        if not pb_file.exists():
            conv.missing = (f"{info.name}: its primary beam {pb_file} (XSPBFILE) is missing; keep "
                            "it beside the image or give the beam with primary_beam=")
            return conv
        pbimg = read_image(pb_file, name=f"primary beam {pb_file}")
        if pbimg.shape != info.shape:
            raise XstackError(f"{pb_file}: primary beam of shape {pbimg.shape} for an image of "
                              f"shape {info.shape}")
        from_array(pbimg.data, pbimg.wcs, f"beam file {pb_file.name}", pbimg.frequency_hz)
        return conv
    if "pb" in info.extra:
        from_array(info.extra["pb"], info.wcs, "in-memory beam of the image")
        return conv
    if int(header.get("XSMOSAIC", 1) or 1) > 1:
        conv.missing = (f"{info.name}: a mosaic whose effective primary beam is not given (no "
                        "XSPBFILE); give its beam image (OUT.pb.fits) with primary_beam=")
        return conv
    model, why = _model_beam(info, None)
    if model is None:
        conv.missing = why
        return conv
    from_model(model, "model")
    return conv


def _sampled_inside(beam: np.ndarray, wcs: WCS, info: ImageInfo, beam_freq: float | None,
                    conv: BeamConvention) -> Any:
    """``inside(ra_deg, dec_deg)`` for a beam known as an image (file, array) on ``wcs``.

    The rule is :func:`xstack.beams.inside_field` at the image's band edge
    (``info.band_top_hz``). A single pointing's beam image holds A at ``beam_freq``; a
    circular beam depends on theta * nu, so A(theta, nu) is read at the radius
    theta * nu / beam_freq from the pointing center (bilinear) -- the same positions as the
    model beam of uvstack. A mosaic's effective beam (``XSMOSAIC`` > 1) has no one center to
    scale about: it is read where the position is (nearest pixel, as the mosaic is blanked),
    i.e. its own coverage at the image's reference frequency (docs/conventions.md).
    """
    from scipy.ndimage import map_coordinates

    from xstack.beams import inside_field
    from xstack.coords import angular_separation, lm_to_radec

    mosaic = int(info.header.get("XSMOSAIC", 1) or 1) > 1
    top = info.band_top_hz
    if mosaic or not top or not beam_freq:
        return lambda ra, dec: inside_field(
            lambda t, f: beam_image_values(beam, wcs, ra, dec), np.zeros(np.shape(ra)),
            top or 1.0, conv.cutoff)
    r0, d0 = np.radians(info.pointing_deg[0]), np.radians(info.pointing_deg[1])
    plane = np.nan_to_num(beam, nan=0.0)

    def inside(ra: Any, dec: Any) -> np.ndarray:
        ra_r, dec_r = np.radians(np.asarray(ra, np.float64)), np.radians(np.asarray(dec, np.float64))
        theta = angular_separation(ra_r, dec_r, r0, d0)
        # position angle of each position about the pointing center (east of north)
        pa = np.arctan2(np.sin(ra_r - r0) * np.cos(dec_r),
                        np.cos(d0) * np.sin(dec_r) - np.sin(d0) * np.cos(dec_r) * np.cos(ra_r - r0))

        def attenuation(t: np.ndarray, f: float) -> np.ndarray:
            s = np.minimum(np.sin(t) * (f / beam_freq), 1.0)  # A depends on sin(theta) nu
            ra_s, dec_s = lm_to_radec(s * np.sin(pa), s * np.cos(pa), r0, d0)
            x, y = wcs.world_to_pixel_values(np.degrees(ra_s), np.degrees(dec_s))
            x = np.nan_to_num(np.asarray(x, np.float64), nan=-1e9)
            y = np.nan_to_num(np.asarray(y, np.float64), nan=-1e9)
            return map_coordinates(plane, [np.atleast_1d(y), np.atleast_1d(x)], order=1,
                                   mode="constant", cval=0.0).reshape(np.shape(t))

        return inside_field(attenuation, theta, top, conv.cutoff)

    return inside
