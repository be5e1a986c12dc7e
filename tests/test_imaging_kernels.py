"""Imaging kernels: gridder vs direct Fourier sum, eq. 1, weighting, beam fit, CLEAN."""

from __future__ import annotations

import math

import numpy as np
import pytest

from xstack.coords import SPEED_OF_LIGHT
from xstack.imaging import kernels
from xstack.imaging.clean import clean, restore
from xstack.imaging.image import grid_visibilities, predict

ARCSEC = math.pi / 180 / 3600


def _random_uvw(rng, nrow, scale=2000.0):
    uvw = rng.normal(scale=scale, size=(nrow, 3))
    uvw[:, 2] *= 0.7
    return uvw


@pytest.mark.parametrize("cell_arcsec", [1.0, 60.0])  # narrow field and a wide (w-term) one
def test_gridder_equals_direct_fourier_sum(rng, cell_arcsec):
    n = 48
    cell = cell_arcsec * ARCSEC
    uvw = _random_uvw(rng, 40)
    freq = np.array([1.3e9, 1.45e9, 1.6e9])
    vis = rng.normal(size=(40, 3)) + 1j * rng.normal(size=(40, 3))
    wgt = rng.uniform(0.2, 2.0, size=(40, 3))
    ref = kernels.direct_dirty_image(uvw, freq, vis, wgt, n, n, cell)
    got = grid_visibilities(uvw, freq, vis, wgt, n, n, cell, epsilon=1e-9, wterm=True)
    assert np.max(np.abs(got - ref)) < 1e-5 * np.max(np.abs(ref))
    if cell_arcsec == 60.0:  # the w-term matters here: without it the sum differs
        flat = grid_visibilities(uvw, freq, vis, wgt, n, n, cell, epsilon=1e-9, wterm=False)
        assert np.max(np.abs(flat - ref)) > 1e-2 * np.max(np.abs(ref))


def test_point_source_lands_on_its_pixel_with_right_orientation():
    """A source east (+l) appears left of center (smaller x); north (+m) above (larger y)."""
    n, cell = 64, 10 * ARCSEC
    rng = np.random.default_rng(3)
    uvw = _random_uvw(rng, 300, 800.0)
    freq = np.array([1.4e9])
    for dx, dy in [(7, 0), (0, 5), (-4, -9)]:
        l, m = -dx * cell, dy * cell  # pixel offset (x right, y up) -> direction cosines
        n1 = np.array([-(l * l + m * m) / (1 + math.sqrt(1 - l * l - m * m))])
        vis = kernels.point_source_visibilities(uvw, freq, np.array([l]), np.array([m]), n1,
                                                np.array([2.5]))
        img = grid_visibilities(uvw, freq, vis, np.ones((300, 1)), n, n, cell) / 300
        y, x = np.unravel_index(np.argmax(img), img.shape)
        assert (y - n // 2, x - n // 2) == (dy, dx)
        assert img[y, x] == pytest.approx(2.5, rel=1e-6)


def test_eq1_kernel_analytic_and_gaussian():
    uvw = np.array([[100.0, -250.0, 30.0], [0.0, 0.0, 0.0]])
    freq = np.array([1e9, 2e9])
    l, m = 1e-3, -2e-3
    n1 = -(l * l + m * m) / (1 + math.sqrt(1 - l * l - m * m))
    fwhm = 3.0 * ARCSEC
    got = kernels.point_source_visibilities(uvw, freq, np.array([l]), np.array([m]), np.array([n1]),
                                            np.array([0.7]), attenuation=np.array([0.5]),
                                            fwhm=np.array([fwhm]))
    for c, f in enumerate(freq):
        u, v, w = uvw[0] * f / SPEED_OF_LIGHT
        q = math.hypot(u, v)
        expect = 0.35 * np.exp(2j * np.pi * (u * l + v * m + w * n1)) * \
            math.exp(-(math.pi * q * fwhm) ** 2 / (4 * math.log(2)))
        assert got[0, c] == pytest.approx(expect, rel=1e-12)
    assert np.allclose(got[1], 0.35)


def test_eq1_kernel_agrees_with_simulation_kernel(rng):
    sim = pytest.importorskip("xstack.sim.kernels")
    uvw = _random_uvw(rng, 50)
    freq = np.linspace(1.3e9, 1.5e9, 5)
    l, m = rng.normal(scale=1e-3, size=(2, 7))
    n1 = -(l * l + m * m) / (1 + np.sqrt(1 - l * l - m * m))
    flux = rng.uniform(0.1, 1, 7)
    fwhm = rng.uniform(0, 5, 7) * ARCSEC
    ours = kernels.point_source_visibilities(uvw, freq, l, m, n1, flux, fwhm=fwhm)
    theirs = sim.model_visibilities(uvw, freq, l, m, n1, flux, fwhm=fwhm)
    assert np.allclose(ours, theirs, rtol=1e-9, atol=1e-12)


def test_adjoint_random(rng):
    n, cell = 64, 2 * ARCSEC
    uvw = _random_uvw(rng, 200, 5000.0)
    freq = np.array([1.0e9, 1.2e9])
    x = rng.normal(size=(n, n))
    y = rng.normal(size=(200, 2)) + 1j * rng.normal(size=(200, 2))
    lhs = np.sum(grid_visibilities(uvw, freq, y, np.ones((200, 2)), n, n, cell, epsilon=1e-10) * x)
    rhs = np.real(np.vdot(predict(x, 2.0, uvw, freq, epsilon=1e-10), y))
    assert abs(lhs - rhs) < 1e-6 * abs(lhs)


def test_weighting_limits(rng):
    """Briggs robust=+5 is natural, robust=-5 is uniform (up to a constant)."""
    n, cell = 32, 5 * ARCSEC
    uvw = _random_uvw(rng, 500, 300.0)
    freq = np.array([1.4e9])
    w = rng.uniform(0.5, 2, size=(500, 1))
    grid = np.zeros((n, n))
    kernels.accumulate_weight_grid(grid, uvw, freq, w, cell)
    # everything inside: the grid holds each weight twice (Hermitian)
    assert grid.sum() == pytest.approx(2 * w.sum())
    dens = kernels.lookup_weight_grid(grid, uvw, freq, cell)
    assert np.all(dens >= w - 1e-12)
    nat = kernels.imaging_weights(w, dens, "briggs", kernels.briggs_f2(grid, 5.0))
    uni = kernels.imaging_weights(w, dens, "briggs", kernels.briggs_f2(grid, -5.0))
    ref_uni = kernels.imaging_weights(w, dens, "uniform")
    assert np.allclose(nat / nat.sum(), w / w.sum(), rtol=1e-3)
    assert np.allclose(uni / uni.sum(), ref_uni / ref_uni.sum(), rtol=1e-3)


@pytest.mark.parametrize("pa", [0.0, 30.0, -60.0, 90.0])
def test_beam_fit_recovers_gaussian(pa):
    g = kernels.gaussian_image(96, 96, 9.0, 5.0, pa)
    major, minor, pa_fit = kernels.fit_psf_beam(g)
    assert major == pytest.approx(9.0, rel=1e-3)
    assert minor == pytest.approx(5.0, rel=1e-3)
    assert (pa_fit - pa + 90) % 180 - 90 == pytest.approx(0.0, abs=0.1)


def test_gaussian_orientation():
    """PA 0: elongated north-south (along y); PA 90: east-west (along x)."""
    g0 = kernels.gaussian_image(64, 64, 10.0, 3.0, 0.0)
    g90 = kernels.gaussian_image(64, 64, 10.0, 3.0, 90.0)
    assert g0[32 + 5, 32] == pytest.approx(0.5) and g0[32, 32 + 5] < 0.01
    assert g90[32, 32 + 5] == pytest.approx(0.5) and g90[32 + 5, 32] < 0.01
    g45 = kernels.gaussian_image(64, 64, 10.0, 3.0, 45.0)  # towards north-east = up-left
    assert g45[35, 29] > 0.5 and g45[35, 35] < 0.01


@pytest.mark.parametrize("algorithm", ["hogbom", "clark"])
def test_clean_recovers_components(algorithm):
    rng = np.random.default_rng(5)
    n = 96
    psf_big = kernels.gaussian_image(2 * n, 2 * n, 4.0, 3.0, 20.0)
    # add sidelobes so CLEAN has work to do
    yy, xx = np.mgrid[:2 * n, :2 * n] - n
    psf_big = psf_big + 0.2 * np.cos(xx / 3.0) * np.exp(-(xx**2 + yy**2) / 800.0) * (xx**2 + yy**2 > 25)
    psf_big[n, n] = 1.0
    truth = np.zeros((n, n))
    pos = [(20, 30), (50, 70), (70, 15)]
    for (y, x), s in zip(pos, [1.0, -0.4, 0.6]):
        truth[y, x] = s
    from scipy.signal import fftconvolve

    dirty = fftconvolve(truth, psf_big, mode="full")[n:2 * n, n:2 * n]
    noise = 1e-4 * rng.normal(size=dirty.shape)
    res = clean(dirty + noise, psf_big, threshold=5e-4, niter=5000, gain=0.2, algorithm=algorithm)
    assert res.converged
    for (y, x), s in zip(pos, [1.0, -0.4, 0.6]):
        assert res.model[y - 1:y + 2, x - 1:x + 2].sum() == pytest.approx(s, abs=3e-3)
    assert res.peak_residual <= 5e-4
    assert np.std(res.residual) < 3e-4
    # restored peak = component flux (peak-1 restoring beam)
    assert res.restored[20, 30] == pytest.approx(1.0, abs=0.01)


def test_clean_mask_and_errors():
    psf = kernels.gaussian_image(64, 64, 3.0, 3.0, 0.0)
    dirty = np.roll(psf, (5, 5), axis=(0, 1)) + 0.5 * np.roll(psf, (-10, 3), axis=(0, 1))
    mask = np.zeros((64, 64), bool)
    mask[32 - 10 - 3:32 - 10 + 4, 32 + 3 - 3:32 + 3 + 4] = True
    res = clean(dirty, psf, threshold=1e-3, niter=500, mask=mask)
    assert res.model[~mask].sum() == 0 and res.model[mask].sum() == pytest.approx(0.5, abs=1e-2)
    from xstack.errors import XstackError

    with pytest.raises(XstackError, match="mask shape"):
        clean(dirty, psf, threshold=0, niter=1, mask=np.ones((3, 3), bool))
    with pytest.raises(XstackError, match="gain"):
        clean(dirty, psf, threshold=0, niter=1, gain=0)
    bad = dirty.copy()
    bad[0, 0] = np.nan
    with pytest.raises(XstackError, match="non-finite"):
        clean(bad, psf, threshold=0, niter=1)


def test_restore_flux_scale():
    model = np.zeros((64, 64))
    model[30, 40] = 2.0
    out = restore(model, np.zeros_like(model), (5.0, 3.0, 10.0))
    assert out.max() == pytest.approx(2.0)
    assert out[30, 40] == pytest.approx(2.0)


@pytest.mark.parametrize("image_shape, psf_shape", [((64, 80), (64, 80)), ((50, 41), (101, 83)),
                                                     ((33, 32), (16, 17)), ((20, 21), (61, 60))])
def test_psf_convolver_is_the_sum_of_shifted_psfs(rng, image_shape, psf_shape):
    """Clark's residual update (FFT with the PSF's transform kept) against plain numpy: a PSF
    added at every component, cut at the image edge; components on the edges and corners,
    PSFs larger (up to three times) and smaller than the image, odd and even sizes."""
    from xstack.imaging.clean import PsfConvolver

    ny, nx = image_shape
    psf = rng.normal(size=psf_shape)
    delta = np.zeros(image_shape)
    for y, x in [(0, 0), (ny - 1, nx - 1), (0, nx - 1), (ny // 2, nx // 3)]:
        delta[y, x] = rng.normal()
    expected = np.zeros(image_shape)
    pcy, pcx = psf_shape[0] // 2, psf_shape[1] // 2
    for y, x in zip(*np.nonzero(delta)):
        for py in range(psf_shape[0]):
            for px in range(psf_shape[1]):
                yy, xx = y + py - pcy, x + px - pcx
                if 0 <= yy < ny and 0 <= xx < nx:
                    expected[yy, xx] += delta[y, x] * psf[py, px]
    conv = PsfConvolver(psf, image_shape)
    assert np.allclose(conv(delta), expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    # the transform is reused: a second delta through the same convolver
    assert np.allclose(conv(2.0 * delta), 2.0 * expected, rtol=0,
                       atol=1e-12 * np.abs(expected).max())
    assert not np.any(conv(np.zeros(image_shape)))
