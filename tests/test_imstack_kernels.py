"""Kernels of image-stacking, each against an analytic answer or an independent plain loop."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import erf

from xstack.imstack import kernels


def _gauss(shape, x0, y0, sx, sy):
    y, x = np.indices(shape, dtype=np.float64)
    return np.exp(-0.5 * (((x - x0) / sx) ** 2 + ((y - y0) / sy) ** 2))


def test_extract_stamps_matches_slicing_and_nan_off_edge():
    rng = np.random.default_rng(0)
    img = rng.normal(size=(50, 60))
    x = np.array([30.4, 0.2, 59.49, 10.5])
    y = np.array([25.0, 3.6, 49.2, -0.4])
    st, ix, iy = kernels.extract_stamps(img, x, y, 8)
    assert ix.tolist() == [30, 0, 59, 11] and iy.tolist() == [25, 4, 49, 0]
    np.testing.assert_array_equal(st[0], img[21:29, 26:34])
    for k in range(4):  # independent per-pixel check, NaN off the image
        for a in range(8):
            for b in range(8):
                yy, xx = iy[k] - 4 + a, ix[k] - 4 + b
                inside = 0 <= yy < 50 and 0 <= xx < 60
                if inside:
                    assert st[k, a, b] == img[yy, xx]
                else:
                    assert np.isnan(st[k, a, b])


@pytest.mark.parametrize("d", [(0.3, -0.45), (-0.5, 0.5), (0.0, 0.17)])
def test_fourier_shift_moves_a_band_limited_gaussian_exactly(d):
    dy, dx = d
    shape = (41, 41)
    # well sampled (sigma 3 x 2.5 pixels): exact to rounding
    src = _gauss(shape, 20.0, 20.0, 3.0, 2.5)
    out = kernels.fourier_shift(src[None], np.array([dy]), np.array([dx]))[0]
    np.testing.assert_allclose(out, _gauss(shape, 20.0 + dx, 20.0 + dy, 3.0, 2.5), atol=1e-10)
    # 3 pixels across the FWHM (the paper's type-2 minor axis): aliasing at the 1e-5 level
    src = _gauss(shape, 20.0, 20.0, 2.2, 1.36)
    out = kernels.fourier_shift(src[None], np.array([dy]), np.array([dx]))[0]
    np.testing.assert_allclose(out, _gauss(shape, 20.0 + dx, 20.0 + dy, 2.2, 1.36), atol=3e-5)


def test_fourier_integer_shift_is_a_roll():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(2, 15, 17))
    out = kernels.fourier_shift(a, np.array([2.0, -1.0]), np.array([-3.0, 4.0]))
    np.testing.assert_allclose(out[0], np.roll(a[0], (2, -3), axis=(0, 1)), atol=1e-12)
    np.testing.assert_allclose(out[1], np.roll(a[1], (-1, 4), axis=(0, 1)), atol=1e-12)


def test_spline_shift_accuracy_and_nan_guard():
    shape = (41, 41)
    src = _gauss(shape, 20.0, 20.0, 2.2, 1.4)
    out = kernels.spline_shift(src[None], np.array([0.4]), np.array([-0.3]))[0]
    truth = _gauss(shape, 19.7, 20.4, 2.2, 1.4)
    assert np.abs(out - truth).max() < 5e-3
    holed = src.copy()
    holed[:, :5] = np.nan
    out2 = kernels.spline_shift(holed[None], np.array([0.4]), np.array([-0.3]))[0]
    guard = kernels.SPLINE_NAN_GUARD
    assert np.isnan(out2[:, :5 + guard]).all()
    # far from the gap the zero fill does not matter
    np.testing.assert_allclose(out2[:, 5 + guard + 4:], out[:, 5 + guard + 4:], atol=1e-3)


@pytest.mark.parametrize("method", ["fourier", "spline"])
def test_align_stamps_centers_the_source(method):
    shape = (80, 90)
    x0, y0 = 41.37, 36.62
    img = _gauss(shape, x0, y0, 2.0, 3.0)
    st, fx, fy = kernels.align_stamps(img, np.array([x0]), np.array([y0]), 16, method)
    assert st.shape == (1, 16, 16)
    np.testing.assert_allclose([fx[0], fy[0]], [0.37, -0.38], atol=1e-12)
    truth = _gauss((16, 16), 8.0, 8.0, 2.0, 3.0)
    tol = 1e-6 if method == "fourier" else 5e-3
    np.testing.assert_allclose(st[0], truth, atol=tol)


def test_align_fourier_falls_back_at_edges_without_zero_fill():
    img = _gauss((60, 60), 3.2, 30.0, 2.0, 2.0) + 5.0  # constant background of 5
    st, _, _ = kernels.align_stamps(img, np.array([3.2]), np.array([30.0]), 16, "fourier")
    finite = np.isfinite(st[0])
    # image column 0 is stamp column 5; the spline fallback blanks SPLINE_NAN_GUARD more
    first = 5 + kernels.SPLINE_NAN_GUARD
    assert not finite[:, :first].any() and finite[:, first:].all()
    # zero-filled values would pull pixels near the edge towards 0, well below the background
    assert np.nanmin(st[0]) > 4.99


def test_local_sigma_against_numpy():
    rng = np.random.default_rng(2)
    st = rng.normal(0, 1, (5, 20, 20)) * np.arange(1, 6)[:, None, None]
    st[1, :3] = np.nan
    mask = kernels.central_mask(20, 4.0)
    sig = kernels.local_sigma(st, mask)
    for k in range(5):
        vals = st[k][~mask]
        vals = vals[np.isfinite(vals)]
        assert sig[k] == pytest.approx(np.std(vals, ddof=1), rel=1e-12)
    assert mask.sum() == sum(1 for a in range(20) for b in range(20)
                             if (a - 10) ** 2 + (b - 10) ** 2 <= 16)
    # too few pixels outside the mask: no estimate
    assert np.isnan(kernels.local_sigma(st[:1], kernels.central_mask(20, 30.0))).all()


def test_weighted_nanmean_and_median_ignore_nan_per_pixel():
    rng = np.random.default_rng(3)
    st = rng.normal(size=(7, 6, 5))
    st[rng.random(st.shape) < 0.3] = np.nan
    w = rng.uniform(0.5, 2.0, 7)
    mean, wsum = kernels.weighted_nanmean(st, w)
    med, count = kernels.nanmedian_stack(st)
    for a in range(6):
        for b in range(5):
            vals = st[:, a, b]
            ok = np.isfinite(vals)
            if ok.any():
                assert mean[a, b] == pytest.approx(np.sum(w[ok] * vals[ok]) / np.sum(w[ok]))
                assert wsum[a, b] == pytest.approx(np.sum(w[ok]))
                assert med[a, b] == pytest.approx(np.median(vals[ok]))
                assert count[a, b] == ok.sum()
            else:
                assert np.isnan(mean[a, b]) and np.isnan(med[a, b])


def test_weighted_error_is_eq5_and_eq6():
    sig = np.array([1.0, 2.0, 0.5, 3.0])
    # eq. 5: sigma^2 = 1 / sum(1/sigma_k^2) for W_k = 1/sigma_k^2
    assert kernels.weighted_error(sig, 1 / sig**2) == pytest.approx(1 / np.sqrt(np.sum(1 / sig**2)))
    # eq. 6: sigma_map / sqrt(N) for equal noise
    assert kernels.weighted_error(np.full(25, 2.0), np.ones(25)) == pytest.approx(2.0 / 5.0)


def test_lowfreq_filter_removes_large_scales_only():
    n = 64
    y, x = np.indices((n, n))
    small = np.cos(2 * np.pi * 10 * x / n)               # 10 cycles per stamp: kept
    large = 3.0 + np.cos(2 * np.pi * (x + y) / n)         # offset and 1 cycle: removed by 3 x 3
    out = kernels.lowfreq_filter(small + large, kernels.lowfreq_mask((n, n), n_central=3))
    np.testing.assert_allclose(out, small, atol=1e-12)
    assert kernels.lowfreq_mask((n, n), n_central=3).sum() == 9
    assert kernels.lowfreq_mask((n, n), q_min_cells=1.5).sum() == 9  # radius < 1.5: 3x3 cells
    nan_in = small.copy()
    nan_in[0, 0] = np.nan
    assert np.isnan(kernels.lowfreq_filter(nan_in, kernels.lowfreq_mask((n, n), n_central=1))[0, 0])


def test_pixelisation_factor_closed_form_and_monte_carlo():
    ln2 = np.log(2.0)

    def axis(theta, p):  # mean of exp(-4 ln2 u^2/theta^2) for u uniform in [-p/2, p/2]
        a = 4 * ln2 / theta**2
        return np.sqrt(np.pi / a) * erf(np.sqrt(a) * p / 2) / p

    for p in (0.25, 0.5, 1.0):
        exact = axis(3.2, p) * axis(1.6, p)  # BPA = 0: major axis north-south (y)
        assert kernels.pixelisation_factor(3.2, 1.6, 0.0, p, p) == pytest.approx(exact, rel=1e-12)
    # the paper's cases (3.2" x 1.6" beam): 0.7 % loss at 0.25", 2.8 % at 0.5"
    assert 1 - kernels.pixelisation_factor(3.2, 1.6, 0.0, 0.25, 0.25) == pytest.approx(0.0070, abs=2e-4)
    assert 1 - kernels.pixelisation_factor(3.2, 1.6, 0.0, 0.5, 0.5) == pytest.approx(0.0276, abs=5e-4)
    # rotated beam, non-square pixels: Monte Carlo over the pixel
    rng = np.random.default_rng(4)
    u = rng.uniform(-0.3, 0.3, 400_000)
    v = rng.uniform(-0.2, 0.2, 400_000)
    pa = np.radians(35.0)
    a = u * np.sin(pa) + v * np.cos(pa)
    b = u * np.cos(pa) - v * np.sin(pa)
    mc = np.mean(np.exp(-4 * ln2 * ((a / 1.5) ** 2 + (b / 0.9) ** 2)))
    assert kernels.pixelisation_factor(1.5, 0.9, 35.0, 0.6, 0.4) == pytest.approx(mc, abs=3e-4)


def test_vectorised_spline_equals_scipy_ndimage_shift():
    from scipy import ndimage

    rng = np.random.default_rng(5)
    a = ndimage.gaussian_filter(rng.normal(size=(6, 50, 44)), (0, 2, 2))
    dy = rng.uniform(-0.5, 0.5, 6)
    dx = rng.uniform(-0.5, 0.5, 6)
    out = kernels.spline_shift(a, dy, dx)
    for k in range(6):
        ref = ndimage.shift(a[k], (dy[k], dx[k]), order=3, mode="mirror")
        # identical interpolant; the boundary handling differs only near the border
        np.testing.assert_allclose(out[k][10:-10, 10:-10], ref[10:-10, 10:-10], atol=1e-12)


@pytest.mark.parametrize("estimator", ["clipped", "mad", "std"])
def test_noise_sigma_when_the_mask_covers_the_stamp(estimator):
    """A central mask as large as the stamp (a small stamp, a large beam) leaves no pixel:
    sigma_k is NaN for every estimator (the position then gets weight 0), not an error."""
    stamps = np.random.default_rng(0).normal(size=(3, 5, 5))
    mask = np.ones((5, 5), dtype=bool)
    sigma, n_finite = kernels.noise_sigma(stamps, mask, estimator)
    assert sigma.shape == (3,) and np.all(np.isnan(sigma))
    assert np.all(n_finite == 0)
    # and all-NaN stamps with pixels outside the mask
    sigma, n_finite = kernels.noise_sigma(np.full((2, 9, 9), np.nan),
                                          kernels.central_mask(9, 1.0), estimator)
    assert np.all(np.isnan(sigma)) and np.all(n_finite == 0)
