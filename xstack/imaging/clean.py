"""Deconvolution: Högbom and Clark CLEAN, restoration, and a major-cycle driver.

``clean`` works on a dirty image and its PSF (image plane only). ``clean_data`` runs
major/minor cycles on a store: the minor cycle cleans the residual image with the PSF, the
major cycle recomputes the residual *exactly* as ``dirty - image(predict(model))`` with ducc0
(imaging is linear, so the data are not re-read; only uvw and weights are streamed).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from xstack._result import Result
from xstack.errors import XstackError
from xstack.imaging import kernels


@dataclass(kw_only=True)
class CleanResult(Result):
    """Output of :func:`clean` / :func:`clean_data`.

    Attributes
    ----------
    model
        (ny, nx) CLEAN components, Jy/pixel.
    residual
        (ny, nx) residual image, Jy/beam.
    restored
        model convolved with the restoring beam (peak-normalised Gaussian) + residual, Jy/beam.
    n_components
        Number of minor-cycle iterations (components, counting repeats on one pixel).
    beam_pixels
        Restoring beam (major FWHM, minor FWHM in pixels, PA in degrees east of north).
    peak_residual
        Largest absolute residual inside the mask at the end, Jy/beam.
    converged
        True if the threshold was reached (rather than ``niter`` or the cycle limit).
    n_major
        Major cycles done (0 for image-plane :func:`clean`).
    """

    model: np.ndarray
    residual: np.ndarray
    restored: np.ndarray
    n_components: int
    beam_pixels: tuple[float, float, float]
    peak_residual: float
    converged: bool
    n_major: int = 0
    history: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: components, restoring beam (pixels), peak residual (Jy/beam),
        convergence and the major-cycle history."""
        return {"n_components": int(self.n_components),
                "beam_pixels": [float(b) for b in self.beam_pixels],
                "peak_residual_jy": float(self.peak_residual), "converged": bool(self.converged),
                "n_major": int(self.n_major), "model_flux_jy": float(np.nansum(self.model)),
                "history": list(self.history)}


def restore(model: np.ndarray, residual: np.ndarray, beam_pixels: tuple[float, float, float]
            ) -> np.ndarray:
    """Convolve ``model`` with the peak-1 Gaussian restoring beam and add ``residual``.

    A component of S Jy appears with a peak of S Jy/beam.
    """
    from scipy.signal import fftconvolve

    major, minor, pa = beam_pixels
    half = max(3, int(np.ceil(3.0 * major)))
    kernel = kernels.gaussian_image(2 * half + 1, 2 * half + 1, major, minor, pa, (half, half))
    if not np.any(model):
        return residual.copy()
    return fftconvolve(model, kernel, mode="same") + residual


def psf_sidelobe(psf: np.ndarray) -> float:
    """Largest |PSF| outside the main lobe (connected region above 0.35 around the center)."""
    from scipy import ndimage

    ny, nx = psf.shape
    lobe, _ = ndimage.label(psf > 0.35 * psf[ny // 2, nx // 2])
    outside = lobe != lobe[ny // 2, nx // 2]
    # the main lobe's skirt (below 0.35) is not a sidelobe: grow the lobe a few pixels
    grown = ndimage.binary_dilation(~outside, iterations=3)
    vals = np.abs(psf[~grown])
    return float(vals.max()) if vals.size else 0.0


class PsfConvolver:
    """Sums of PSFs centered on the components of a delta image: what Högbom subtracts,
    done by FFT with the PSF's transform computed once.

    Clark's minor cycles update the residual by convolving each round's new components
    with the PSF. The PSF does not change within a CLEAN, so its transform is kept: every
    round costs one forward and one inverse real FFT (threads: ``workers``) instead of
    three. The PSF is stored wrapped about index 0 in a period of image + half the PSF
    per axis: just enough that no wrapped-around PSF lands on the image (only the image's
    own pixels are returned), a third fewer pixels than the image + PSF of a linear
    convolution.

    Parameters
    ----------
    psf
        PSF, peak at (ny_psf // 2, nx_psf // 2).
    shape
        (ny, nx) of the images it is applied to.
    workers
        FFT threads (``scipy.fft``; -1: all cores).
    """

    def __init__(self, psf: np.ndarray, shape: tuple[int, int], workers: int = -1):
        from scipy import fft

        psf = np.asarray(psf, dtype=np.float64)
        self.shape = (int(shape[0]), int(shape[1]))
        self.workers = workers
        pc = (psf.shape[0] // 2, psf.shape[1] // 2)
        # a component at y' adds the PSF at y' - pc ... y' + p - pc - 1; wrapped with period
        # P, nothing lands on 0 ... n - 1 that does not belong there when
        # P >= n + max(pc, p - pc - 1)
        self.padded = tuple(fft.next_fast_len(n + max(c, p - c - 1), real=True)
                            for n, p, c in zip(self.shape, psf.shape, pc))
        wrapped = np.zeros(self.padded)
        iy = (np.arange(psf.shape[0]) - pc[0]) % self.padded[0]
        ix = (np.arange(psf.shape[1]) - pc[1]) % self.padded[1]
        wrapped[np.ix_(iy, ix)] = psf
        self.psf_ft = fft.rfft2(wrapped, workers=workers)

    def __call__(self, delta: np.ndarray) -> np.ndarray:
        from scipy import fft

        ny, nx = self.shape
        if not np.any(delta):
            return np.zeros_like(delta)
        full = fft.irfft2(fft.rfft2(delta, s=self.padded, workers=self.workers) * self.psf_ft,
                          s=self.padded, workers=self.workers)
        return full[:ny, :nx].copy()


def _convolve_psf(delta: np.ndarray, psf: np.ndarray) -> np.ndarray:
    """Sum of PSFs centered on ``delta``'s components (exactly what Högbom subtracts)."""
    return PsfConvolver(psf, delta.shape)(delta)


def _check(dirty: np.ndarray, psf: np.ndarray, mask: np.ndarray | None, gain: float, niter: int,
           threshold: float) -> np.ndarray:
    if dirty.ndim != 2 or psf.ndim != 2:
        raise XstackError("clean needs 2-D dirty image and PSF")
    if not (0 < gain <= 1):
        raise XstackError(f"CLEAN gain must be in (0, 1], got {gain}")
    if niter < 0 or not np.isfinite(threshold) or threshold < 0:
        raise XstackError("CLEAN needs niter >= 0 and a finite threshold >= 0")
    if not np.all(np.isfinite(dirty)):
        raise XstackError("dirty image has non-finite pixels (primary-beam corrected? clean "
                          "the uncorrected image)")
    if mask is None:
        return np.ones(dirty.shape, dtype=np.bool_)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != dirty.shape:
        raise XstackError(f"mask shape {mask.shape} differs from image shape {dirty.shape}")
    return mask


def _minor(res: np.ndarray, psf: np.ndarray, model: np.ndarray, mask: np.ndarray, gain: float,
           threshold: float, niter: int, algorithm: str, sidelobe: float,
           convolve: PsfConvolver | None = None) -> int:
    """Run up to ``niter`` components on ``res`` / ``model`` in place; return the count.

    ``convolve``: Clark's PSF convolver for ``res``'s shape (made here if not given; a
    CLEAN with several major cycles passes one, so the PSF is transformed once).
    """
    if algorithm == "hogbom":
        return int(kernels.hogbom(res, psf, model, mask, gain, threshold, niter))
    if algorithm != "clark":
        raise XstackError(f"unknown CLEAN algorithm {algorithm!r} (hogbom or clark)")
    if convolve is None:
        convolve = PsfConvolver(psf, res.shape)
    done = 0
    frac = min(max(sidelobe, 0.05), 0.9)
    while done < niter:
        _, _, peak = kernels._abs_peak(res, mask)
        if peak <= threshold:
            break
        limit = max(threshold, frac * peak)
        sel = mask & (np.abs(res) > limit)
        ys, xs = np.nonzero(sel)
        if ys.size > 200_000:  # keep the active list small: raise the limit
            limit = float(np.partition(np.abs(res[ys, xs]), -200_000)[-200_000])
            sel = mask & (np.abs(res) > limit)
            ys, xs = np.nonzero(sel)
        vals = res[ys, xs].copy()
        delta = np.zeros_like(model)
        n = int(kernels.clark_minor(ys.astype(np.int64), xs.astype(np.int64), vals, psf, delta,
                                    gain, limit, niter - done))
        if n == 0:
            n = int(kernels.hogbom(res, psf, delta, mask, gain, threshold, 1))
            model += delta
            done += n
            if n == 0:
                break
            continue
        res -= convolve(delta)
        model += delta
        done += n
    return done


def clean(dirty: np.ndarray, psf: np.ndarray, *, threshold: float, niter: int, gain: float = 0.1,
          mask: np.ndarray | None = None, algorithm: str = "hogbom",
          beam_pixels: tuple[float, float, float] | None = None,
          model: np.ndarray | None = None) -> CleanResult:
    """Image-plane CLEAN of ``dirty`` with ``psf``.

    Parameters
    ----------
    dirty
        (ny, nx) dirty image, Jy/beam.
    psf
        PSF, peak 1 at (ny_psf // 2, nx_psf // 2); any shape (the image's, or larger so that
        every component subtracts a whole PSF).
    threshold
        Stop when the masked peak of the absolute residual is at or below this (Jy/beam).
    niter
        Maximum number of components.
    gain
        Loop gain.
    mask
        Boolean (ny, nx): where components may be placed (default everywhere).
    algorithm
        ``hogbom`` (exact, O(npix) per component) or ``clark`` (minor cycles on the brightest
        pixels with PSF-patch updates, then an exact FFT residual update).
    beam_pixels
        Restoring beam (FWHM major, minor in pixels, PA deg); default: fitted to ``psf``.
    model
        Starting model (Jy/pixel) whose PSF response is already removed from ``dirty``.
    """
    dirty = np.asarray(dirty, dtype=np.float64)
    psf = np.ascontiguousarray(psf, dtype=np.float64)
    mask = _check(dirty, psf, mask, gain, niter, threshold)
    res = dirty.copy()
    mdl = np.zeros_like(res) if model is None else np.array(model, dtype=np.float64)
    n = _minor(res, psf, mdl, mask, gain, threshold, niter, algorithm, psf_sidelobe(psf))
    beam = beam_pixels if beam_pixels is not None else kernels.fit_psf_beam(psf)
    _, _, peak = kernels._abs_peak(res, mask)
    return CleanResult(model=mdl, residual=res, restored=restore(mdl, res, beam), n_components=n,
                       beam_pixels=tuple(float(b) for b in beam), peak_residual=float(peak),
                       converged=bool(peak <= threshold))


def clean_data(data: Any, *, size: int | Sequence[int], cell_arcsec: float, niter: int,
               threshold: float = 0.0, gain: float = 0.1, mask: np.ndarray | None = None,
               algorithm: str = "hogbom", cycle_factor: float = 1.0, max_major: int = 30,
               weighting: str = "natural", robust: float = 0.0, wterm: bool = True,
               pbcor: bool = False, epsilon: float = 1e-6,
               partitions: str | Sequence[str] | None = None, nthreads: int = 0,
               progress: bool = False, autocorrelations: bool = False,
               reproducible: bool = True) -> tuple[Any, CleanResult]:
    """Image a store and CLEAN it with major/minor cycles.

    Each minor cycle cleans the residual image down to
    ``max(threshold, f * peak)``, f = cycle_factor x (largest PSF sidelobe) clipped to
    [0.05, 0.5] (CASA's cyclethreshold with a lower maximum: the image-plane minor cycle is
    exact up to the PSF's truncation at the image edge); each major cycle then recomputes the
    exact residual through ducc0 (predict the model, image it with the same weights, subtract
    from the dirty image).

    CLEAN picks the largest residual pixel at every step, so an image that differs in its
    last bits gives other components: ``reproducible`` (default) grids with one thread per
    image, and the same data then give the same model, whatever the threads (see
    :func:`xstack.imaging.image.make_image`).

    Returns
    -------
    result : ImageResult
        Dirty image/PSF metadata; ``result.image`` is the *restored* image (PB-corrected if
        ``pbcor``), ``result.extra`` holds ``dirty``.
    clean : CleanResult
        Model, residual and restored image (never PB-corrected).
    """
    from xstack.imaging.image import Imager

    imager = Imager(data, size=size, cell_arcsec=cell_arcsec, weighting=weighting, robust=robust,
                    wterm=wterm, epsilon=epsilon, partitions=partitions, nthreads=nthreads,
                    progress=progress, autocorrelations=autocorrelations,
                    reproducible=reproducible)
    stats = imager.dirty_and_psf()
    dirty, psf = stats["dirty"], stats["psf"]
    mask_b = _check(dirty, psf, mask, gain, niter, threshold)
    sidelobe = psf_sidelobe(psf)
    beam = kernels.fit_psf_beam(psf)
    model = np.zeros_like(dirty)
    res = dirty.copy()
    convolve = PsfConvolver(psf, dirty.shape) if algorithm == "clark" else None
    done, n_major, history = 0, 0, []
    _, _, peak = kernels._abs_peak(res, mask_b)
    while done < niter and peak > threshold and n_major < max_major:
        cycle_threshold = max(threshold, float(np.clip(cycle_factor * sidelobe, 0.05, 0.5)) * peak)
        n = _minor(res, psf, model, mask_b, gain, cycle_threshold, niter - done, algorithm,
                   sidelobe, convolve)
        done += n
        # exact residual: imaging is linear, dirty(V - P(model)) = dirty - dirty(P(model))
        res = dirty - imager.image_of_model(model)
        n_major += 1
        _, _, peak = kernels._abs_peak(res, mask_b)
        history.append({"major": n_major, "components": done, "peak_residual": float(peak),
                        "cycle_threshold": float(cycle_threshold)})
        if n == 0:
            break
    restored = restore(model, res, beam)
    cres = CleanResult(model=model, residual=res, restored=restored, n_components=done,
                       beam_pixels=tuple(float(b) for b in beam), peak_residual=float(peak),
                       converged=bool(peak <= threshold), n_major=n_major, history=history)
    result = imager.result(restored, psf, stats, pbcor=pbcor)
    result.extra["dirty"] = dirty
    return result, cres
