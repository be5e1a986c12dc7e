"""Pure-numpy kernels of image-stacking (paper §3.2): no xarray, no dask, no I/O.

Conventions shared by every function here:

* A stamp of ``size`` pixels has its center at index ``c = size // 2`` on both axes (the
  ``numpy.fft.fftshift`` convention), so offsets run from ``-c`` to ``size - 1 - c`` pixels.
* Positions are 0-based pixel coordinates ``(x, y)`` of the image array ``image[y, x]``
  (astropy's ``world_to_pixel`` convention).
* Pixels that lie off the image, or that cannot be computed from finite image pixels, are
  NaN. NaN is never replaced by zero in a stack: every aggregation ignores NaN per pixel.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy import fft as sfft
from scipy import ndimage

from xstack import _vocabulary

#: Pixels around a non-finite input pixel that a spline shift marks as NaN. The cubic
#: spline's prefilter spreads a value with weight ~0.268**k at k pixels, so after 4 pixels
#: the influence of the filled gap is below 0.5 % of the step at its border.
SPLINE_NAN_GUARD = 4

#: Least extra pixels on each side of a stamp that a Fourier shift works on, so that the
#: circular wrap stays outside the stamp (its ringing decays as 1/distance). Measured on
#: band-limited noise: 8 pixels perturb a 64-pixel stamp's center by 0.9 % of the noise rms
#: (random, not a bias) against 0.7 % for 16, at 60 % of the cost.
SHIFT_MARGIN = 8

#: Extra pixels for the spline shift (its boundary influence decays as 0.268**distance).
SPLINE_MARGIN = 8


def padded_size(size: int, margin: int) -> int:
    """Smallest odd 7-smooth length >= (size | 1) + 2 margin.

    Odd, so no Nyquist cell breaks a fractional shift; 7-smooth, so the FFT is fast. An even
    stamp is cut from an odd one of size + 1, which has the same center index size // 2.
    """
    n = (size | 1) + 2 * margin
    while True:
        m = n
        for p in (3, 5, 7):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 2


#: Stamps shifted per batch (bounds the temporary memory of the sub-pixel shifts).
SHIFT_CHUNK = 128

#: Fewest finite pixels outside the central mask for a usable local noise estimate.
MIN_NOISE_PIXELS = 16


def nearest_pixel(coord: np.ndarray) -> np.ndarray:
    """Index of the pixel whose center is nearest to ``coord`` (halves round up), int64."""
    return np.floor(np.asarray(coord, dtype=np.float64) + 0.5).astype(np.int64)


def extract_stamps(image: np.ndarray, x: np.ndarray, y: np.ndarray, size: int,
                   margin: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cut square stamps centered on the pixels nearest to ``(x, y)`` (paper §3.2).

    Parameters
    ----------
    image
        2-D image ``image[y, x]`` (any float dtype; NaN marks blanked pixels).
    x, y
        0-based pixel coordinates of the stacking positions, shape (n,).
    size
        Stamp size in pixels (square).
    margin
        Extra pixels on every side (returned stamps have ``size + 2 * margin`` pixels).

    Returns
    -------
    stamps
        float64 array (n, size + 2 margin, size + 2 margin); NaN where the stamp is off the
        image. The nearest pixel to position k is at ``stamps[k, c + margin, c + margin]``.
    ix, iy
        Nearest-pixel indices, int64 (n,).
    """
    image = np.asarray(image)
    if image.ndim != 2:
        raise ValueError("image must be 2-D")
    ny, nx = image.shape
    ix, iy = nearest_pixel(x), nearest_pixel(y)
    full = size + 2 * margin
    lo = size // 2 + margin
    out = np.full((ix.size, full, full), np.nan, dtype=np.float64)
    for k in range(ix.size):
        x0, y0 = ix[k] - lo, iy[k] - lo
        xs0, xs1 = max(x0, 0), min(x0 + full, nx)
        ys0, ys1 = max(y0, 0), min(y0 + full, ny)
        if xs1 > xs0 and ys1 > ys0:
            out[k, ys0 - y0:ys1 - y0, xs0 - x0:xs1 - x0] = image[ys0:ys1, xs0:xs1]
    return out, ix, iy


def stamp_footprint(shape: tuple[int, int], x: np.ndarray, y: np.ndarray, size: int
                    ) -> np.ndarray:
    """The pixels of an image that the nearest-pixel stamps of :func:`extract_stamps` read.

    The union of the ``size`` x ``size`` windows centered on the pixels nearest to
    ``(x, y)``, clipped to the image, built with a summed-area table so that it costs
    O(n + pixels) for any number of positions.

    Parameters
    ----------
    shape
        ``(ny, nx)`` of the image.
    x, y
        0-based pixel coordinates, shape (n,) (non-finite ones read nothing).
    size
        Stamp side in pixels.

    Returns
    -------
    footprint
        bool (ny, nx), True where some stamp reads the pixel.
    """
    ny, nx = (int(v) for v in shape)
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    ix, iy = nearest_pixel(x[ok]), nearest_pixel(y[ok])
    lo = size // 2
    x0, y0 = np.clip(ix - lo, 0, nx), np.clip(iy - lo, 0, ny)
    x1, y1 = np.clip(ix - lo + size, 0, nx), np.clip(iy - lo + size, 0, ny)
    keep = (x1 > x0) & (y1 > y0)
    x0, x1, y0, y1 = x0[keep], x1[keep], y0[keep], y1[keep]
    # +1 at each window's first corner, -1 at the two next to it, +1 at the far one: the
    # cumulative sums over both axes count the windows covering each pixel (in place and in
    # int32: numpy's default int64 accumulation of a new array costs 8x the time)
    count = np.zeros((ny + 1, nx + 1), dtype=np.int32)
    np.add.at(count, (y0, x0), 1)
    np.add.at(count, (y0, x1), -1)
    np.add.at(count, (y1, x0), -1)
    np.add.at(count, (y1, x1), 1)
    np.cumsum(count, axis=0, out=count)
    np.cumsum(count, axis=1, out=count)
    return count[:ny, :nx] > 0


def fourier_shift(stamps: np.ndarray, dy: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """Shift each stamp by (dy, dx) pixels with the Fourier shift theorem: out(r) = in(r - d).

    Exact for band-limited images (an interferometric image sampled finer than Nyquist) up
    to the circular wrap at the stamp border; call it on stamps with a margin and crop.
    Stamps must be finite. Works on the whole batch at once (float64).
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    n, ny, nx = stamps.shape
    ky = sfft.fftfreq(ny)[None, :, None]
    kx = sfft.rfftfreq(nx)[None, None, :]
    dy = np.asarray(dy, dtype=np.float64).reshape(n, 1, 1)
    dx = np.asarray(dx, dtype=np.float64).reshape(n, 1, 1)
    spec = sfft.rfft2(stamps, axes=(1, 2), workers=-1)
    # the phase ramp is separable: two small exponentials instead of one per Fourier cell
    spec *= np.exp(-2j * np.pi * ky * dy)
    spec *= np.exp(-2j * np.pi * kx * dx)
    # (an even length's Nyquist cell cannot carry a fractional shift of a real signal;
    # align_stamps always passes odd sizes)
    return sfft.irfft2(spec, s=(ny, nx), axes=(1, 2), workers=-1)


def _cubic_bspline_1d(c: np.ndarray, d: np.ndarray, axis: int) -> np.ndarray:
    """Evaluate prefiltered cubic B-spline coefficients ``c`` (n, ny, nx) at r - d along ``axis``.

    A pure translation samples every pixel at the same fractional phase, so the spline is a
    4-tap filter per stamp: out[i] = sum_j w_j(t) c[i + f + j], j = -1..2, with f = floor(-d)
    and t = -d - f. Indices beyond the border are clamped (the margin is cropped later).
    """
    length = c.shape[axis]
    f = np.floor(-d).astype(np.int64)
    t = -d - f
    w = np.stack([(1 - t) ** 3 / 6, (3 * t**3 - 6 * t**2 + 4) / 6,
                  (-3 * t**3 + 3 * t**2 + 3 * t + 1) / 6, t**3 / 6])  # (4, n)
    pad = [(0, 0), (0, 0), (0, 0)]
    pad[axis] = (3, 3)
    cp = np.pad(c, pad, mode="edge")
    out = np.zeros_like(c)
    for fv in np.unique(f):  # |d| <= 1/2 gives at most two groups
        sel = np.flatnonzero(f == fv)
        cs = cp[sel]
        part = np.zeros((sel.size, *c.shape[1:]))
        for j in range(4):
            start = 3 + fv + j - 1
            sl = [slice(None)] * 3
            sl[axis] = slice(start, start + length)
            part += w[j, sel].reshape(-1, 1, 1) * cs[tuple(sl)]
        out[sel] = part
    return out


def spline_shift(stamps: np.ndarray, dy: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """Shift each stamp by (dy, dx) pixels with cubic B-spline interpolation: out(r) = in(r - d).

    The same interpolant as ``scipy.ndimage.shift(order=3)`` (prefilter along each image axis,
    then a separable 4-tap filter), vectorised over the stamps. Non-finite pixels are filled
    with the nearest finite value for the interpolation and the result is NaN within
    ``SPLINE_NAN_GUARD`` pixels of them, so no filled value reaches the stack (beyond the
    guard its influence is below 0.5 % of the local step).
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    dy = np.asarray(dy, dtype=np.float64).reshape(-1)
    dx = np.asarray(dx, dtype=np.float64).reshape(-1)
    finite = np.isfinite(stamps).all(axis=(1, 2))
    out = np.empty_like(stamps)

    def run(a: np.ndarray, sy: np.ndarray, sx: np.ndarray) -> np.ndarray:
        c = ndimage.spline_filter1d(a, 3, axis=1, mode="mirror")
        c = ndimage.spline_filter1d(c, 3, axis=2, mode="mirror")
        return _cubic_bspline_1d(_cubic_bspline_1d(c, sy, 1), sx, 2)

    if finite.any():
        out[finite] = run(stamps[finite], dy[finite], dx[finite])
    for k in np.flatnonzero(~finite):
        out[k] = _guarded(stamps[k], lambda a, k=k: run(a[None], dy[k:k + 1], dx[k:k + 1])[0])
    return out


def _guarded(stamp: np.ndarray, shift: Any) -> np.ndarray:
    """Apply ``shift`` to a stamp with non-finite pixels without letting a fill reach the result.

    The gap is filled with the nearest finite value (continuous at its border, so the
    interpolant barely rings), shifted, and every pixel within ``SPLINE_NAN_GUARD`` of the gap
    is set to NaN.
    """
    bad = ~np.isfinite(stamp)
    if not bad.any():
        return shift(stamp)
    if bad.all():
        return np.full_like(stamp, np.nan)
    idx = ndimage.distance_transform_edt(bad, return_distances=False, return_indices=True)
    out = shift(stamp[tuple(idx)])
    out[ndimage.binary_dilation(bad, iterations=SPLINE_NAN_GUARD)] = np.nan
    return out


def align_stamps(image: np.ndarray, x: np.ndarray, y: np.ndarray, size: int,
                 subpixel: str | bool | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps of ``size`` pixels with each stacking position at the stamp center.

    ``subpixel`` selects the alignment:

    ``False``/``None``
        nearest pixel, as in the paper: the position lies within half a pixel of the center
        and the stack loses peak brightness (see :func:`pixelisation_factor`).
    ``"fourier"``
        Fourier shift by the fractional offset (exact for band-limited images). A stamp with
        non-finite pixels in its margin (image edge, blanking) has the gap filled with the
        nearest finite values for the transform, and pixels within ``SPLINE_NAN_GUARD`` of
        the gap are NaN afterwards.
    ``"spline"``
        cubic B-spline interpolation (``scipy.ndimage.shift``).

    Returns
    -------
    stamps
        float64 (n, size, size), NaN where not computable.
    frac_x, frac_y
        The source's offset from the nearest pixel center, ``x - round(x)``, in pixels
        (what nearest-pixel alignment leaves uncorrected).
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if subpixel in (False, None, "none", "nearest"):
        stamps, ix, iy = extract_stamps(image, x, y, size)
        return stamps, x - ix, y - iy
    if subpixel not in ("fourier", "spline"):
        raise ValueError(f"unknown sub-pixel method {subpixel!r}")
    odd = size | 1  # an even stamp is the first `size` pixels of an odd one, same center
    if subpixel == "fourier":
        margin = (padded_size(size, SHIFT_MARGIN) - odd) // 2
    else:
        margin = SPLINE_MARGIN
    padded, ix, iy = extract_stamps(image, x, y, odd, margin)
    fx, fy = x - ix, y - iy
    # the source sits at +f from the center: move it by -f onto the center pixel
    dx, dy = -fx, -fy
    result = np.empty((x.size, size, size))
    for s in range(0, x.size, SHIFT_CHUNK):  # chunks bound the temporaries' memory
        sl = slice(s, s + SHIFT_CHUNK)
        pad, sy, sx = padded[sl], dy[sl], dx[sl]
        if subpixel == "fourier":
            out = np.empty_like(pad)
            finite = np.isfinite(pad).all(axis=(1, 2))
            if finite.any():
                out[finite] = fourier_shift(pad[finite], sy[finite], sx[finite])
            for k in np.flatnonzero(~finite):
                out[k] = _guarded(pad[k], lambda a, yk=sy[k:k + 1], xk=sx[k:k + 1]:
                                  fourier_shift(a[None], yk, xk)[0])
        else:
            out = spline_shift(pad, sy, sx)
        # a pixel whose nearest-pixel value is off the image stays NaN whatever the method
        out[~np.isfinite(pad)] = np.nan
        result[sl] = out[:, margin:margin + size, margin:margin + size]
    return result, fx, fy


def offsets_grid(size: int) -> np.ndarray:
    """Pixel offsets of a stamp's pixels from its center: ``arange(size) - size // 2``."""
    return np.arange(size, dtype=np.float64) - size // 2


def central_mask(size: int, radius_x_pix: float, radius_y_pix: float | None = None) -> np.ndarray:
    """Boolean (size, size) mask, True inside the ellipse of the given radii (pixels).

    With equal radii this is the paper's circle "with a radius equal to the major axis of
    the beam", measured in pixels of each axis (so non-square pixels still give a circle
    on the sky).
    """
    ry = radius_x_pix if radius_y_pix is None else radius_y_pix
    off = offsets_grid(size)
    return (off[None, :] / radius_x_pix) ** 2 + (off[:, None] / ry) ** 2 <= 1.0


def local_sigma(stamps: np.ndarray, mask: np.ndarray, min_pixels: int = MIN_NOISE_PIXELS) -> np.ndarray:
    """Local noise sigma_k of each stamp: std of its finite pixels outside ``mask`` (paper §3.2).

    Returns NaN for stamps with fewer than ``min_pixels`` usable pixels (ddof = 1).
    """
    stamps = np.asarray(stamps)
    n = stamps.shape[0]
    flat = stamps.reshape(n, -1)
    idx = np.flatnonzero(~np.asarray(mask).ravel())
    need = max(min_pixels, 2)
    sigma = np.full(n, np.nan)
    if idx.size < need:
        return sigma
    for s in range(0, n, SHIFT_CHUNK):  # chunks bound the temporaries' memory
        outside = flat[s:s + SHIFT_CHUNK, idx].astype(np.float64, copy=False)
        finite = np.isfinite(outside)
        full = finite.all(axis=1)
        if full.all():  # the common case (stamps inside the image): no nan-function copies
            sigma[s:s + SHIFT_CHUNK] = outside.std(axis=1, ddof=1)
            continue
        for k in range(outside.shape[0]):
            vals = outside[k] if full[k] else outside[k][finite[k]]
            if vals.size >= need:
                sigma[s + k] = vals.std(ddof=1)
    return sigma


#: Local-noise estimators (:func:`noise_sigma`). ``clipped``: iterative 3-sigma clipping
#: about the median, the std of what remains, corrected for the truncation (the default of
#: both stacks). ``mad``: 1.4826 x the median absolute deviation (breakdown point 50 %, but
#: ~1.6x the scatter of the std on Gaussian noise). ``std``: the plain standard deviation of
#: the paper, which also counts any source, CLEAN residual or artefact in the stamp as noise.
NOISE_ESTIMATORS = _vocabulary.LOCAL_NOISE_ESTIMATORS

#: Clipping threshold (in units of the current std about the median) of ``clipped``.
CLIP_SIGMA = 3.0

#: Most clipping iterations. The window only shrinks, so it converges: in 3-5 iterations on
#: Gaussian noise, in ~15 where a stamp straddles two noise levels (a mosaic's edge, say),
#: so the bound is generous -- an iteration is one comparison pass over the sorted stamps.
CLIP_MAXITER = 100

#: A noise stamp covers about this many beam areas by default (paper §3.2: "approximately 300").
STAMP_BEAM_AREAS = 300.0


def clip_correction(k: float) -> float:
    """std of N(0, 1) restricted to |x| < c, at the fixed point c = k std(c).

    Converged k-sigma clipping of Gaussian noise stops where the threshold is k times the std
    of the values it keeps; that std underestimates sigma by this factor (0.9848 for k = 3).
    """
    c = k
    s = 1.0
    for _ in range(100):
        s = math.sqrt(1.0 - 2.0 * c * math.exp(-0.5 * c * c) / math.sqrt(2.0 * math.pi)
                      / math.erf(c / math.sqrt(2.0)))
        c_new = k * s
        if abs(c_new - c) < 1e-14:
            break
        c = c_new
    return s


#: Bias factor of the converged 3-sigma clipped std on Gaussian noise (divided out).
CLIP_CORRECTION = clip_correction(CLIP_SIGMA)


def clipped_sigma(vals: np.ndarray, min_pixels: int = MIN_NOISE_PIXELS
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Converged 3-sigma clipped std (truncation corrected) of each row of ``vals``.

    Parameters
    ----------
    vals
        (n, p) values (NaN = unusable pixel).
    min_pixels
        Rows with fewer finite values give NaN.

    Returns
    -------
    sigma, n_finite
        float64 (n,) and int64 (n,).

    Notes
    -----
    Each row is sorted once; a clipping window is then an index range of the sorted row, its
    sums come from cumulative sums (relative to the row's median, so the variance does not
    cancel) and every iteration costs one comparison pass instead of a median.
    """
    vals = np.asarray(vals, dtype=np.float64)
    n, p = vals.shape
    if p == 0:  # the mask covers the whole stamp: nothing to measure on
        return np.full(n, np.nan), np.zeros(n, dtype=np.int64)
    srt = np.sort(vals, axis=1)  # NaN sort last
    nf = np.isfinite(srt).sum(axis=1)
    rows = np.arange(n)
    lo = np.zeros(n, dtype=np.int64)
    hi = nf.astype(np.int64)

    def window_median(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        m = np.maximum(hi - lo, 1)
        a = srt[rows, np.minimum(lo + (m - 1) // 2, p - 1)]
        b = srt[rows, np.minimum(lo + m // 2, p - 1)]
        return 0.5 * (a + b)

    shift = np.where(nf > 0, window_median(lo, hi), 0.0)
    d = np.where(np.isfinite(srt), srt - shift[:, None], 0.0)
    c1 = np.zeros((n, p + 1))
    c2 = np.zeros((n, p + 1))
    np.cumsum(d, axis=1, out=c1[:, 1:])
    np.cumsum(d * d, axis=1, out=c2[:, 1:])

    def window_std(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        m = (hi - lo).astype(np.float64)
        s1 = c1[rows, hi] - c1[rows, lo]
        s2 = c2[rows, hi] - c2[rows, lo]
        with np.errstate(invalid="ignore", divide="ignore"):
            var = (s2 - s1 * s1 / m) / (m - 1.0)
        return np.sqrt(np.clip(var, 0.0, None))

    for _ in range(CLIP_MAXITER):
        med = window_median(lo, hi)
        std = window_std(lo, hi)
        # comparisons with NaN are False, so blanked pixels never enter a window
        new_lo = np.maximum(lo, (srt < (med - CLIP_SIGMA * std)[:, None]).sum(axis=1))
        new_hi = np.minimum(hi, (srt <= (med + CLIP_SIGMA * std)[:, None]).sum(axis=1))
        new_hi = np.maximum(new_hi, new_lo)
        if np.array_equal(new_lo, lo) and np.array_equal(new_hi, hi):
            break
        lo, hi = new_lo, new_hi
    sigma = window_std(lo, hi) / CLIP_CORRECTION
    sigma[nf < max(min_pixels, 2)] = np.nan
    return sigma, nf


def mad_sigma(vals: np.ndarray, min_pixels: int = MIN_NOISE_PIXELS
              ) -> tuple[np.ndarray, np.ndarray]:
    """1.4826 x the median absolute deviation of each row (NaN ignored): (sigma, n_finite)."""
    vals = np.asarray(vals, dtype=np.float64)
    nf = np.isfinite(vals).sum(axis=1)
    sigma = np.full(vals.shape[0], np.nan)
    ok = nf >= max(min_pixels, 2)
    if ok.any():
        v = vals[ok]
        med = np.nanmedian(v, axis=1)
        sigma[ok] = _vocabulary.MAD_TO_SIGMA * np.nanmedian(np.abs(v - med[:, None]), axis=1)
    return sigma, nf


def noise_sigma(stamps: np.ndarray, mask: np.ndarray, estimator: str = "clipped",
                min_pixels: int = MIN_NOISE_PIXELS) -> tuple[np.ndarray, np.ndarray]:
    """Local noise sigma_k of each stamp outside ``mask`` with one of :data:`NOISE_ESTIMATORS`.

    Parameters
    ----------
    stamps
        (n, size, size) stamps (NaN = off the image or blanked).
    mask
        (size, size) bool, True for the central pixels left out (the source and its lobe).
    estimator
        ``"clipped"``, ``"mad"`` or ``"std"``.
    min_pixels
        Stamps with fewer finite pixels outside the mask give NaN.

    Returns
    -------
    sigma, n_finite
        float64 (n,) sigma_k in the stamps' unit; int64 (n,) finite pixels outside the mask.
    """
    if estimator not in NOISE_ESTIMATORS:
        raise ValueError(f"unknown noise estimator {estimator!r} "
                         f"(use {', '.join(NOISE_ESTIMATORS)})")
    stamps = np.asarray(stamps)
    vals = stamps.reshape(stamps.shape[0], -1)[:, np.flatnonzero(~np.asarray(mask).ravel())]
    if estimator == "std":
        return (local_sigma(stamps, mask, min_pixels=min_pixels),
                np.isfinite(vals).sum(axis=1))
    return (clipped_sigma if estimator == "clipped" else mad_sigma)(vals, min_pixels)


def stamp_noise(image: np.ndarray, x: np.ndarray, y: np.ndarray, size: int, mask: np.ndarray,
                estimator: str = "clipped", min_pixels: int = MIN_NOISE_PIXELS
                ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`noise_sigma` of the nearest-pixel stamps of ``image`` centered on ``(x, y)``.

    The stamps are cut :data:`SHIFT_CHUNK` at a time, so that the memory stays bounded for
    10^5 positions and stamps of ~300 beams.

    Parameters
    ----------
    image
        2-D image ``image[y, x]`` (NaN = blanked).
    x, y
        0-based pixel coordinates, shape (n,).
    size, mask, estimator, min_pixels
        As :func:`extract_stamps` and :func:`noise_sigma`.

    Returns
    -------
    sigma, n_finite
        float64 (n,) sigma_k in the image's unit; int64 (n,) finite pixels outside the mask.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    sigma = np.full(x.size, np.nan)
    n_finite = np.zeros(x.size, dtype=np.int64)
    for s in range(0, x.size, SHIFT_CHUNK):
        stamps, _, _ = extract_stamps(image, x[s:s + SHIFT_CHUNK], y[s:s + SHIFT_CHUNK], size)
        sigma[s:s + SHIFT_CHUNK], n_finite[s:s + SHIFT_CHUNK] = noise_sigma(
            stamps, mask, estimator, min_pixels)
    return sigma, n_finite


def noise_stamp_size(beam_arcsec: tuple[float, float] | None, pix_x: float, pix_y: float,
                     mask_radius_arcsec: float, limit: int, *,
                     beam_areas: float = STAMP_BEAM_AREAS, fallback: int = 65) -> int:
    """Default side (pixels, odd) of the stamp the local noise is measured on.

    About ``beam_areas`` beam areas (paper §3.2: ~300), at least 4 mask radii, made odd so
    the mask is centered, at most ``limit`` (the image); ``fallback`` without a beam.

    Parameters
    ----------
    beam_arcsec
        (BMAJ, BMIN) FWHM in arcsec, or None.
    pix_x, pix_y
        Pixel sizes along the image axes, arcsec.
    mask_radius_arcsec
        Radius of the central mask, arcsec.
    limit
        Largest side allowed (the smaller image dimension), pixels.
    """
    if beam_arcsec:
        beam_area_pix = math.pi / (4.0 * math.log(2.0)) * beam_arcsec[0] * beam_arcsec[1] \
            / (pix_x * pix_y)
        size = math.ceil(math.sqrt(beam_areas * beam_area_pix))
        size = max(size, math.ceil(4.0 * mask_radius_arcsec / min(pix_x, pix_y)))
    else:
        size = int(fallback)
    return min(size | 1, int(limit))


def weighted_nanmean(stamps: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel weighted mean over the stamp axis, ignoring NaN pixels.

    stacked(y, x) = sum_k W_k s_k(y, x) / sum_k W_k, both sums over the stamps k whose pixel
    (y, x) is finite -- an edge stamp contributes only where it has data.

    Returns
    -------
    stacked
        float64 (ny, nx); NaN where no stamp has data or the weights sum to 0.
    wsum
        float64 (ny, nx): sum of the weights that contributed to each pixel.
    """
    stamps = np.asarray(stamps, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    finite = np.isfinite(stamps)
    if finite.all():  # no stamp off the image: a plain weighted sum
        wsum = np.full(stamps.shape[1:], w.sum())
        num = np.tensordot(w, stamps, axes=(0, 0))
    else:
        wk = np.where(finite, w[:, None, None], 0.0)
        wsum = wk.sum(axis=0)
        num = np.einsum("kyx,kyx->yx", wk, np.where(finite, stamps, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        stacked = np.where(wsum > 0, num / wsum, np.nan)
    return stacked, wsum


def weighted_error(sigma: np.ndarray, weights: np.ndarray) -> float:
    """Noise of a weighted mean of independent values with noise ``sigma`` and weights W.

    sigma_stack = sqrt(sum W_k^2 sigma_k^2) / sum W_k. With W_k = 1/sigma_k^2 this is the
    paper's equation 5, sigma^2 = 1 / sum(1/sigma_k^2); with equal weights and equal sigma
    it is equation 6, sigma_map / sqrt(N).
    """
    sigma = np.asarray(sigma, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    ok = np.isfinite(sigma) & (w > 0)
    if not ok.any():
        return float("nan")
    return float(np.sqrt(np.sum(w[ok] ** 2 * sigma[ok] ** 2)) / np.sum(w[ok]))


def nanmedian_stack(stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel median over the stamp axis ignoring NaN; also the count of stamps per pixel."""
    stamps = np.asarray(stamps, dtype=np.float64)
    count = np.isfinite(stamps).sum(axis=0).astype(np.float64)
    out = np.full(stamps.shape[1:], np.nan)
    ok = count > 0
    if ok.any():
        out[ok] = np.nanmedian(stamps[:, ok], axis=0)
    return out, count


#: Noise of the median of N Gaussian values relative to that of their mean, for large N.
MEDIAN_NOISE_FACTOR = float(np.sqrt(np.pi / 2.0))


def lowfreq_mask(shape: tuple[int, int], n_central: int | None = None,
                 q_min_cells: float | None = None) -> np.ndarray:
    """Boolean mask (unshifted FFT order) of the Fourier cells the §5.3 filter sets to zero.

    ``n_central``: the central n x n cells of the centered Fourier image (paper: 3 x 3 for a
    256 x 256 stamp). ``q_min_cells``: every cell with radius sqrt(ky^2 + kx^2) < q_min,
    in units of Fourier cells (one cell is 1 / (stamp size x pixel) wavelengths).
    """
    ny, nx = shape
    ky = sfft.fftfreq(ny) * ny
    kx = sfft.fftfreq(nx) * nx
    if n_central is not None:
        half = (int(n_central) - 1) / 2.0
        return (np.abs(ky)[:, None] <= half) & (np.abs(kx)[None, :] <= half)
    if q_min_cells is not None:
        return np.hypot(ky[:, None], kx[None, :]) < q_min_cells
    raise ValueError("give n_central or q_min_cells")


def lowfreq_filter(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The low-spatial-frequency FFT filter of paper §5.3 applied to a 2-D stamp.

    FFT the stamp, set the masked (low-frequency) cells to zero, inverse FFT. Non-finite
    pixels are zero-filled for the transform and NaN again afterwards.
    """
    image = np.asarray(image, dtype=np.float64)
    bad = ~np.isfinite(image)
    spec = sfft.fft2(np.where(bad, 0.0, image))
    spec[mask] = 0.0
    out = sfft.ifft2(spec).real
    out[bad] = np.nan
    return out


def pixelisation_factor(bmaj: float, bmin: float, bpa_deg: float, pix_x: float, pix_y: float,
                        n: int = 64) -> float:
    """Expected peak of a nearest-pixel stack of a Gaussian beam, relative to perfect alignment.

    With nearest-pixel alignment the source lies at an offset (u, v) uniformly distributed in
    the pixel, [-p_x/2, p_x/2] x [-p_y/2, p_y/2], so the stacked central pixel is

        F = < exp(-4 ln2 [ (u cos + v sin)^2/bmin^2 ... ]) >   (the beam's quadratic form)

    averaged over the pixel, computed by Gauss-Legendre quadrature (exact to ~1e-12).
    For small pixels F ~ 1 - (ln 2 / 3)(p_x^2 + p_y^2)/2 (1/bmaj^2 + 1/bmin^2) for square
    pixels p. ``bmaj``, ``bmin``, ``pix_*`` in the same angular unit; ``bpa_deg`` east of
    north (the FITS BPA); pixel axes x (east-west) and y (north-south).
    """
    t, wt = np.polynomial.legendre.leggauss(n)
    u = 0.5 * pix_x * t  # east-west offset
    v = 0.5 * pix_y * t  # north-south offset
    pa = np.radians(bpa_deg)
    # major axis along position angle pa (from north towards east)
    a = u[None, :] * np.sin(pa) + v[:, None] * np.cos(pa)
    b = u[None, :] * np.cos(pa) - v[:, None] * np.sin(pa)
    g = np.exp(-4.0 * np.log(2.0) * ((a / bmaj) ** 2 + (b / bmin) ** 2))
    return float(0.25 * np.einsum("i,j,ij->", wt, wt, g))
