"""Pure numpy / numba kernels of the imaging stage (no dask, no xarray).

Image arrays are in FITS order ``image[y, x]`` with x the RA axis (pixel index increasing
towards the *west*, i.e. RA increasing to the left as on the sky) and y the Dec axis
(increasing to the north). The reference pixel (phase center) is ``(y, x) = (ny // 2, nx // 2)``
(0-based), so a pixel's direction cosines are::

    l = -(x - nx // 2) * cell,    m = (y - ny // 2) * cell      (cell in radians)

The visibility convention is the project's (``docs/conventions.md``, paper eq. 1)::

    V = S exp(+2 pi i (u l + v m + w (n - 1)) / lambda)

so the matched (dirty) image is ``I(l, m) = sum_k w_k Re[V_k exp(-2 pi i (...))] / sum_k w_k``.
We do not divide by n anywhere: a pixel value of the model image is the integrated flux
density of a point source at the pixel center.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from xstack.coords import SPEED_OF_LIGHT

FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))


# --------------------------------------------------------------------------- geometry
def pixel_lm(ny: int, nx: int, cell_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Direction cosines (l, m) of every pixel, each of shape (ny, nx)."""
    x = np.arange(nx, dtype=np.float64) - nx // 2
    y = np.arange(ny, dtype=np.float64) - ny // 2
    l = np.broadcast_to(-x[None, :] * cell_rad, (ny, nx))
    m = np.broadcast_to(y[:, None] * cell_rad, (ny, nx))
    return l, m


def n_minus_one(l: np.ndarray, m: np.ndarray) -> np.ndarray:
    """n - 1 = -(l^2 + m^2) / (1 + n), without cancellation."""
    r2 = l * l + m * m
    return -r2 / (1.0 + np.sqrt(np.clip(1.0 - r2, 0.0, None)))


# --------------------------------------------------------------------------- references
def direct_dirty_image(uvw: np.ndarray, frequency: np.ndarray, vis: np.ndarray, weight: np.ndarray,
                       ny: int, nx: int, cell_rad: float, wterm: bool = True) -> np.ndarray:
    """Direct Fourier sum (the slow, independent reference of the gridder), unnormalised.

    Parameters
    ----------
    uvw
        (nrow, 3) baseline coordinates, metres.
    frequency
        (nchan,) Hz.
    vis, weight
        (nrow, nchan) visibilities (Jy) and imaging weights.
    ny, nx, cell_rad
        Image shape and pixel size (radians).

    Returns
    -------
    numpy.ndarray
        ``sum_k w_k Re[V_k exp(-2 pi i (u l + v m + w (n-1)) / lambda)]`` per pixel, (ny, nx).
    """
    l, m = pixel_lm(ny, nx, cell_rad)
    lf, mf = l.ravel(), m.ravel()
    nf = n_minus_one(lf, mf) if wterm else np.zeros_like(lf)
    out = np.zeros(lf.size)
    scale = np.asarray(frequency, dtype=np.float64) / SPEED_OF_LIGHT
    for c, s in enumerate(scale):
        u, v, w = (uvw[:, k] * s for k in range(3))
        phase = -2.0 * np.pi * (np.outer(u, lf) + np.outer(v, mf) + np.outer(w, nf))
        out += np.real((weight[:, c] * vis[:, c]) @ np.exp(1j * phase))
    return out.reshape(ny, nx)


def point_source_visibilities(uvw: np.ndarray, frequency: np.ndarray, l: np.ndarray, m: np.ndarray,
                              n_minus_1: np.ndarray, flux: np.ndarray,
                              attenuation: np.ndarray | None = None,
                              fwhm: np.ndarray | None = None) -> np.ndarray:
    """Model visibilities of point / circular Gaussian sources, exactly (paper eq. 1).

    ``V = sum_k A_k S_k exp(+2 pi i (u l_k + v m_k + w (n_k - 1)) / lambda)
    exp(-(pi r_k q / lambda)^2)``, q = sqrt(u^2 + v^2), r_k = FWHM_k / (2 sqrt(ln 2)).

    Parameters
    ----------
    uvw
        (nrow, 3) metres.
    frequency
        (nchan,) Hz.
    l, m, n_minus_1, flux
        (nsrc,) direction cosines and integrated flux densities (Jy).
    attenuation
        Optional primary-beam power attenuation, (nsrc,) or (nsrc, nchan).
    fwhm
        Optional Gaussian FWHM per source, radians (0 = point source).

    Returns
    -------
    numpy.ndarray
        (nrow, nchan) complex128.
    """
    uvw = np.asarray(uvw, dtype=np.float64)
    freq = np.asarray(frequency, dtype=np.float64)
    nsrc = np.size(flux)
    amp = np.broadcast_to(np.asarray(flux, dtype=np.float64)[:, None], (nsrc, freq.size)).copy()
    if attenuation is not None:
        att = np.asarray(attenuation, dtype=np.float64)
        amp *= att[:, None] if att.ndim == 1 else att
    out = np.zeros((uvw.shape[0], freq.size), dtype=np.complex128)
    q = np.hypot(uvw[:, 0], uvw[:, 1])
    for c, f in enumerate(freq):
        s = f / SPEED_OF_LIGHT
        # (nrow, nsrc) phases, float64; chunk over sources to bound memory
        for k0 in range(0, nsrc, 256):
            sl = slice(k0, k0 + 256)
            phase = 2.0 * np.pi * s * (np.outer(uvw[:, 0], l[sl]) + np.outer(uvw[:, 1], m[sl])
                                       + np.outer(uvw[:, 2], n_minus_1[sl]))
            term = np.exp(1j * phase) * amp[sl, c][None, :]
            if fwhm is not None:
                r = np.asarray(fwhm, dtype=np.float64)[sl] / (2.0 * math.sqrt(math.log(2.0)))
                term *= np.exp(-(np.pi * np.outer(q * s, r)) ** 2)
            out[:, c] += term.sum(axis=1)
    return out


# --------------------------------------------------------------------------- weighting
def accumulate_weight_grid(grid: np.ndarray, uvw: np.ndarray, frequency: np.ndarray,
                           weight: np.ndarray, cell_rad: float) -> None:
    """Add natural weights to the uv cells of an image's Fourier grid, in place.

    ``grid`` has the image's shape (ny, nx); cell sizes are du = 1/(nx cell),
    dv = 1/(ny cell). Each visibility also counts at (-u, -v) (Hermitian symmetry).
    Visibilities outside the grid (beyond the image's Nyquist limit) are ignored.
    """
    ny, nx = grid.shape
    s = np.asarray(frequency, dtype=np.float64)[None, :] / SPEED_OF_LIGHT
    iu = np.rint(uvw[:, 0:1] * s * (nx * cell_rad)).astype(np.int64)
    iv = np.rint(uvw[:, 1:2] * s * (ny * cell_rad)).astype(np.int64)
    wt = np.asarray(weight, dtype=np.float64)
    for sign in (1, -1):
        x = sign * iu + nx // 2
        y = sign * iv + ny // 2
        ok = (x >= 0) & (x < nx) & (y >= 0) & (y < ny) & (wt > 0)
        np.add.at(grid, (y[ok], x[ok]), wt[ok])


def lookup_weight_grid(grid: np.ndarray, uvw: np.ndarray, frequency: np.ndarray,
                       cell_rad: float) -> np.ndarray:
    """Gridded weight density at each visibility, (nrow, nchan); 0 outside the grid."""
    ny, nx = grid.shape
    s = np.asarray(frequency, dtype=np.float64)[None, :] / SPEED_OF_LIGHT
    x = np.rint(uvw[:, 0:1] * s * (nx * cell_rad)).astype(np.int64) + nx // 2
    y = np.rint(uvw[:, 1:2] * s * (ny * cell_rad)).astype(np.int64) + ny // 2
    ok = (x >= 0) & (x < nx) & (y >= 0) & (y < ny)
    out = np.zeros(x.shape)
    out[ok] = grid[y[ok], x[ok]]
    return out


def briggs_f2(grid: np.ndarray, robust: float) -> float:
    """Briggs' f^2 = (5 10^-R)^2 / (sum_cells W^2 / sum_vis w) (CASA / Briggs 1995)."""
    sum_w2 = float(np.sum(grid * grid))
    if sum_w2 <= 0:
        return 0.0
    # the grid counts every visibility twice (Hermitian): sum W^2 = 2 sum_i w_i W_i and
    # sum W = 2 sum_i w_i, so their ratio is the weighted mean density, as in Briggs (1995)
    return (5.0 * 10.0 ** (-robust)) ** 2 / (sum_w2 / float(np.sum(grid)))


def imaging_weights(weight: np.ndarray, density: np.ndarray, weighting: str,
                    f2: float = 0.0) -> np.ndarray:
    """Imaging weights from natural weights and the gridded density.

    natural: w; uniform: w / W (0 where W = 0); briggs: w / (1 + W f^2).
    """
    weight = np.asarray(weight, dtype=np.float64)
    if weighting == "natural":
        return weight
    if weighting == "uniform":
        return np.where(density > 0, weight / np.where(density > 0, density, 1.0), 0.0)
    if weighting == "briggs":
        return np.where(density > 0, weight / (1.0 + density * f2), 0.0)
    raise ValueError(f"unknown weighting {weighting!r}")


# --------------------------------------------------------------------------- beams
def gaussian_image(ny: int, nx: int, major_pix: float, minor_pix: float, pa_deg: float,
                   center: tuple[float, float] | None = None) -> np.ndarray:
    """Peak-1 elliptical Gaussian (FWHM in pixels, PA east of north) in FITS pixel order.

    North is +y and east is -x (RA increases to the left), so the major axis points along
    (dx, dy) = (-sin PA, cos PA).
    """
    cy, cx = center if center is not None else (ny // 2, nx // 2)
    y = np.arange(ny, dtype=np.float64)[:, None] - cy
    x = np.arange(nx, dtype=np.float64)[None, :] - cx
    pa = math.radians(pa_deg)
    a = -x * math.sin(pa) + y * math.cos(pa)  # along the major axis
    b = x * math.cos(pa) + y * math.sin(pa)   # along the minor axis
    return np.exp(-4.0 * math.log(2.0) * ((a / major_pix) ** 2 + (b / minor_pix) ** 2))


def fit_psf_beam(psf: np.ndarray) -> tuple[float, float, float]:
    """Fit an elliptical Gaussian to the PSF main lobe.

    The main lobe is the connected region above 35 % of the peak around the center pixel.

    Returns
    -------
    major, minor : float
        FWHM in pixels.
    pa : float
        Position angle of the major axis, degrees east of north, in (-90, 90].
    """
    from scipy import ndimage, optimize

    ny, nx = psf.shape
    cy, cx = ny // 2, nx // 2
    peak = psf[cy, cx]
    if not np.isfinite(peak) or peak <= 0:
        raise ValueError("PSF has no positive peak at the center")
    lobe, _ = ndimage.label(psf / peak > 0.35)
    sel = lobe == lobe[cy, cx]
    ys, xs = np.nonzero(sel)
    vals = psf[ys, xs] / peak
    dy = ys - cy
    dx = xs - cx
    if ys.size < 5:
        # undersampled PSF: the lobe is (nearly) one pixel; report a pixel-sized beam
        return 1.0, 1.0, 0.0
    # start from second moments
    wsum = vals.sum()
    cxx = float((vals * dx * dx).sum() / wsum)
    cyy = float((vals * dy * dy).sum() / wsum)
    cxy = float((vals * dx * dy).sum() / wsum)
    evals, evecs = np.linalg.eigh(np.array([[cxx, cxy], [cxy, cyy]]))
    s_major = math.sqrt(max(evals[1], 0.25)) * 1.3
    s_minor = math.sqrt(max(evals[0], 0.25)) * 1.3
    vx, vy = evecs[:, 1]
    pa0 = math.atan2(-vx, vy)

    def resid(p: np.ndarray) -> np.ndarray:
        smaj, smin, pa = p
        a = -dx * math.sin(pa) + dy * math.cos(pa)
        b = dx * math.cos(pa) + dy * math.sin(pa)
        return np.exp(-0.5 * ((a / smaj) ** 2 + (b / smin) ** 2)) - vals

    sol = optimize.least_squares(resid, [s_major, s_minor, pa0], method="lm")
    smaj, smin, pa = sol.x
    smaj, smin = abs(smaj), abs(smin)
    if smin > smaj:
        smaj, smin = smin, smaj
        pa += math.pi / 2
    pa_deg = math.degrees(pa)
    pa_deg = (pa_deg + 90.0) % 180.0 - 90.0
    if pa_deg == -90.0:
        pa_deg = 90.0
    return smaj * FWHM_PER_SIGMA, smin * FWHM_PER_SIGMA, pa_deg


# --------------------------------------------------------------------------- CLEAN
@njit(cache=True)
def _abs_peak(res: np.ndarray, mask: np.ndarray) -> tuple[int, int, float]:
    ny, nx = res.shape
    best = -1.0
    by = -1
    bx = -1
    for y in range(ny):
        for x in range(nx):
            if mask[y, x]:
                a = abs(res[y, x])
                if a > best:
                    best = a
                    by = y
                    bx = x
    return by, bx, best


@njit(cache=True)
def hogbom(res: np.ndarray, psf: np.ndarray, model: np.ndarray, mask: np.ndarray,
           gain: float, threshold: float, niter: int) -> int:
    """Högbom CLEAN in place: ``res`` and ``model`` are updated; returns the iterations done.

    The PSF center ``(ny_psf // 2, nx_psf // 2)`` is shifted onto each component; the part
    of the shifted PSF that falls outside the residual is dropped. Stops after ``niter``
    components or when the masked |residual| peak is below ``threshold``.
    """
    ny, nx = res.shape
    py, px = psf.shape
    pcy = py // 2
    pcx = px // 2
    n = 0
    while n < niter:
        by, bx, best = _abs_peak(res, mask)
        if by < 0 or best <= threshold:
            break
        val = gain * res[by, bx]
        model[by, bx] += val
        y0 = max(0, by - pcy)
        y1 = min(ny, by - pcy + py)
        x0 = max(0, bx - pcx)
        x1 = min(nx, bx - pcx + px)
        for y in range(y0, y1):
            for x in range(x0, x1):
                res[y, x] -= val * psf[y - by + pcy, x - bx + pcx]
        n += 1
    return n


@njit(cache=True)
def clark_minor(ys: np.ndarray, xs: np.ndarray, vals: np.ndarray, psf: np.ndarray,
                model: np.ndarray, gain: float, threshold: float, niter: int) -> int:
    """Clark minor cycle on an active pixel list (in place on ``vals`` and ``model``).

    Only the listed pixels (the brightest residual pixels) are searched and updated; the
    caller recomputes the full residual afterwards (the major step). Returns iterations.
    """
    k = vals.size
    py, px = psf.shape
    pcy = py // 2
    pcx = px // 2
    n = 0
    while n < niter:
        best = -1.0
        bi = -1
        for i in range(k):
            a = abs(vals[i])
            if a > best:
                best = a
                bi = i
        if bi < 0 or best <= threshold:
            break
        val = gain * vals[bi]
        by = ys[bi]
        bx = xs[bi]
        model[by, bx] += val
        for i in range(k):
            dy = ys[i] - by + pcy
            dx = xs[i] - bx + pcx
            if 0 <= dy < py and 0 <= dx < px:
                vals[i] -= val * psf[dy, dx]
        n += 1
    return n
