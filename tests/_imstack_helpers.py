"""Synthetic FITS images for the image-stacking tests: analytic Gaussian-beam point sources
on a SIN grid plus Gaussian noise. Everything here is independent of xstack.imstack."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS

#: Field center of the paper's data sets: RA 3h49m10.99s, Dec -30 deg.
RA0, DEC0 = 57.2957917, -30.0
LN2 = np.log(2.0)


def sin_wcs(n: int, cell_arcsec: float, ra0: float = RA0, dec0: float = DEC0,
            crpix: tuple[float, float] | None = None) -> WCS:
    """A standard SIN celestial WCS (CDELT1 < 0), reference pixel at the image center."""
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---SIN", "DEC--SIN"]
    w.wcs.cunit = ["deg", "deg"]
    w.wcs.crval = [ra0, dec0]
    w.wcs.crpix = list(crpix) if crpix else [n // 2 + 1.0, n // 2 + 1.0]
    w.wcs.cdelt = [-cell_arcsec / 3600.0, cell_arcsec / 3600.0]
    w.wcs.radesys = "ICRS"
    return w


def gauss_beam(east: np.ndarray, north: np.ndarray, bmaj: float, bmin: float, bpa: float) -> np.ndarray:
    """Gaussian beam of peak 1: FWHM bmaj x bmin (arcsec), position angle bpa (deg E of N)."""
    pa = np.radians(bpa)
    a = east * np.sin(pa) + north * np.cos(pa)
    b = east * np.cos(pa) - north * np.sin(pa)
    return np.exp(-4.0 * LN2 * ((a / bmaj) ** 2 + (b / bmin) ** 2))


def render(n: int, cell: float, px: np.ndarray, py: np.ndarray, flux: np.ndarray,
           beam: tuple[float, float, float], background: np.ndarray | float = 0.0) -> np.ndarray:
    """Image n x n of point sources at pixel positions (px, py) convolved with the beam.

    Uses the local tangent-plane offsets east = -(x - px) cell, north = (y - py) cell (exact
    to < 1e-6 for the small fields used here).
    """
    img = np.zeros((n, n)) + background
    half = int(np.ceil(4.0 * beam[0] / cell))
    for x0, y0, s in zip(px, py, flux):
        i0, j0 = int(round(x0)), int(round(y0))
        xs = np.arange(max(i0 - half, 0), min(i0 + half + 1, n))
        ys = np.arange(max(j0 - half, 0), min(j0 + half + 1, n))
        if xs.size == 0 or ys.size == 0:
            continue
        east = -(xs[None, :] - x0) * cell
        north = (ys[:, None] - y0) * cell
        img[ys[0]:ys[-1] + 1, xs[0]:xs[-1] + 1] += s * gauss_beam(east, north, *beam)
    return img


def grid_positions(n_side: int, spacing: int, margin: int,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Pixel positions on a jittered grid: uniform sub-pixel offsets, sources well separated."""
    base = margin + spacing * np.arange(n_side, dtype=np.float64)
    gx, gy = np.meshgrid(base, base)
    gx = gx.ravel() + rng.uniform(-0.5, 0.5, gx.size)
    gy = gy.ravel() + rng.uniform(-0.5, 0.5, gy.size)
    return gx, gy


def header_for(w: WCS, beam: tuple[float, float, float] | None, extra: dict | None = None) -> fits.Header:
    h = w.to_header()
    if beam is not None:
        h["BMAJ"], h["BMIN"], h["BPA"] = beam[0] / 3600.0, beam[1] / 3600.0, beam[2]
    h["BUNIT"] = "Jy/beam"
    for k, v in (extra or {}).items():
        h[k] = v
    return h


def write_image(path: Path, data: np.ndarray, w: WCS, beam: tuple[float, float, float] | None = None,
                psf: bool = False, extra: dict | None = None, four_d: bool = False,
                freq_hz: float = 1.4e9) -> Path:
    """Write ``data`` as a FITS image (optionally 4-D RA/DEC/FREQ/STOKES) and ``X.psf.fits``."""
    h = header_for(w, beam, extra)
    arr = data.astype(np.float32)
    if four_d:
        h["NAXIS"] = 4
        h["CTYPE3"], h["CRVAL3"], h["CDELT3"], h["CRPIX3"], h["CUNIT3"] = "FREQ", freq_hz, 1e6, 1.0, "Hz"
        h["CTYPE4"], h["CRVAL4"], h["CDELT4"], h["CRPIX4"] = "STOKES", 1.0, 1.0, 1.0
        arr = arr[None, None]
    fits.PrimaryHDU(arr, header=h).writeto(path)
    if psf:
        n = data.shape[0]
        cell = abs(w.wcs.cdelt[1]) * 3600.0
        off = (np.arange(n) - n // 2) * cell
        p = gauss_beam(-off[None, :], off[:, None], *beam)
        fits.PrimaryHDU(p.astype(np.float32), header=header_for(w, beam)).writeto(
            path.with_name(path.name[:-5] + ".psf.fits"))
    return path


def expected_nearest(frac_x: np.ndarray, frac_y: np.ndarray, cell: float,
                     beam: tuple[float, float, float]) -> float:
    """Exact expectation of a nearest-pixel stack's center for given sub-pixel offsets."""
    # a source at +f pixels from the stamp center is seen at the center at offset -f
    return float(np.mean(gauss_beam(frac_x * cell, -frac_y * cell, *beam)))


def make_field(tmp: Path, rng: np.random.Generator, cell: float, beam=(3.2, 1.6, 0.0), n_side: int = 20,
               flux: float = 1.0, noise: float = 0.01, name: str = "img.fits", psf: bool = False,
               spacing: int | None = None, ra0: float = RA0, dec0: float = DEC0, **kw):
    """Image with n_side^2 sources of equal flux on a jittered grid; returns (path, ra, dec, px, py)."""
    spacing = spacing or int(np.ceil(2.2 * beam[0] / cell)) + 4
    margin = spacing
    n = 2 * margin + spacing * (n_side - 1) + 1
    w = sin_wcs(n, cell, ra0, dec0)
    px, py = grid_positions(n_side, spacing, margin, rng)
    img = render(n, cell, px, py, np.full(px.size, flux), beam)
    img += rng.normal(0.0, noise, img.shape)
    sky = w.pixel_to_world_values(px, py)
    path = write_image(tmp / name, img, w, beam, psf=psf, **kw)
    return path, np.asarray(sky[0]), np.asarray(sky[1]), px, py
