"""Image-stacking end to end on synthetic FITS images with known injected fluxes."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr
from _imstack_helpers import (
    expected_nearest,
    make_field,
    render,
    sin_wcs,
    write_image,
)
from astropy.io import fits

from xstack.beams import standard_beam
from xstack.coords import angular_separation
from xstack.errors import XstackError, XstackWarning
from xstack.imstack import kernels
from xstack.imstack.io import read_stack_fits
from xstack.imstack.stack import stack_images

BEAM = (3.2, 1.6, 0.0)  # the paper's VLA A-array beam at 1.4 GHz, arcsec


@pytest.fixture(scope="module")
def fields(tmp_path_factory):
    """One 400-source field at 0.25" and one at 0.5" pixels (the paper's types 1 and 2)."""
    out = {}
    d = tmp_path_factory.mktemp("fields")
    for cell, seed in ((0.25, 11), (0.5, 12)):
        rng = np.random.default_rng(seed)
        out[cell] = make_field(d, rng, cell, beam=BEAM, name=f"f{cell}.fits", psf=True)
    return out


@pytest.mark.parametrize("cell", [0.25, 0.5])
def test_nearest_pixel_loses_exactly_the_pixelisation_factor(fields, cell):
    path, ra, dec, _, _ = fields[cell]
    res = stack_images(path, np.c_[ra, dec], stamp_size=32, weighting="none")
    assert res.n_positions == 400
    # exact expectation for these positions: the beam at each one's sub-pixel offset
    exact = expected_nearest(res.cube.frac_x.values, res.cube.frac_y.values, cell, BEAM)
    assert abs(res.flux_jy - exact) < 4 * res.flux_err_jy
    # the analytic average over a uniform offset (kernels.pixelisation_factor) agrees to the
    # sampling scatter of 400 offsets
    assert res.pixelisation_factor == pytest.approx(exact, abs=3e-3)
    loss = 1 - res.flux_jy
    if cell == 0.25:  # paper: ~1 % (Gaussian-beam prediction 0.7 %)
        assert 0.002 < loss < 0.015
    else:             # paper: ~5 % (Gaussian-beam prediction 2.8 %)
        assert 0.018 < loss < 0.05
    # the stack's PSF carries the same smear: its center is the expected factor
    assert res.psf_stamp is not None
    assert float(res.psf_stamp.values[16, 16]) == pytest.approx(exact, abs=1e-4)


@pytest.mark.parametrize("cell,method", [(0.25, "fourier"), (0.5, "fourier"), (0.5, "spline")])
def test_subpixel_alignment_recovers_flux_within_one_percent(fields, cell, method):
    path, ra, dec, _, _ = fields[cell]
    res = stack_images(path, np.c_[ra, dec], stamp_size=32, weighting="none", subpixel=method)
    assert abs(res.flux_jy - 1.0) < 0.01
    assert abs(res.flux_jy - 1.0) < 4 * res.flux_err_jy + (1e-3 if method == "fourier" else 3e-3)
    assert float(res.psf_stamp.values[16, 16]) == pytest.approx(1.0, abs=1e-9)
    assert res.pixelisation_factor is None


def test_median_and_mean_agree_on_gaussian_noise(tmp_path):
    rng = np.random.default_rng(5)
    sigma, n = 1.0, 400
    path, ra, dec, _, _ = make_field(tmp_path, rng, 0.5, beam=BEAM, noise=sigma, spacing=40)
    pos = np.c_[ra, dec]
    mean = stack_images(path, pos, stamp_size=32, weighting="none", subpixel="fourier")
    med = stack_images(path, pos, stamp_size=32, method="median", weighting="none", subpixel="fourier")
    # median - mean of N Gaussian values: zero mean, std sqrt(pi/2 - 1) sigma / sqrt(N)
    sd = np.sqrt(np.pi / 2 - 1) * sigma / np.sqrt(n)
    assert abs(med.flux_jy - mean.flux_jy) < 4 * sd
    diff = (med.stacked - mean.stacked).values
    assert abs(np.mean(diff)) < 4 * sd / np.sqrt(diff.size / 4)
    assert 0.8 * sd < np.std(diff) < 1.2 * sd
    assert abs(mean.flux_jy - 1.0) < 4 * mean.flux_err_jy
    assert abs(med.flux_jy - 1.0) < 4 * med.flux_err_jy
    assert med.flux_err_jy / mean.flux_err_jy == pytest.approx(np.sqrt(np.pi / 2), rel=0.05)
    # the propagated error is the real scatter of the stacked pixels (white noise)
    assert mean.stamp_rms_jy == pytest.approx(mean.flux_err_jy, rel=0.12)


def test_sigma2_weights_follow_eq3_and_eq5(tmp_path):
    rng = np.random.default_rng(6)
    cell, n_side, spacing = 0.5, 12, 40
    n = 2 * spacing + spacing * (n_side - 1) + 1
    w = sin_wcs(n, cell)
    base = spacing + spacing * np.arange(n_side, dtype=np.float64)
    gx, gy = np.meshgrid(base, base)
    px = gx.ravel() + rng.uniform(-0.5, 0.5, gx.size)
    py = gy.ravel() + rng.uniform(-0.5, 0.5, gy.size)
    img = render(n, cell, px, py, np.full(px.size, 1.0), BEAM)
    noise_map = np.where(np.arange(n)[None, :] < n // 2, 0.05, 0.2) * np.ones((n, 1))
    img += rng.normal(size=img.shape) * noise_map
    path = write_image(tmp_path / "noisy.fits", img, w, BEAM)
    ra, dec = w.pixel_to_world_values(px, py)
    # the paper's sigma_k: the plain std on the stamp itself (the default is checked below)
    res = stack_images(path, np.c_[ra, dec], stamp_size=32, weighting="sigma2", subpixel="fourier",
                       noise_estimator="std", noise_stamp_size=32)
    cube = res.cube
    # independent sigma_k: std (ddof 1) outside a circle of radius BMAJ in arcsec offsets
    r = np.hypot(cube.x.values[None, :], cube.y.values[:, None])
    outside = r > BEAM[0]
    sig = np.array([np.std(s[outside][np.isfinite(s[outside])], ddof=1) for s in cube.values])
    np.testing.assert_allclose(cube.sigma.values, sig, rtol=1e-10)
    np.testing.assert_allclose(cube.weight.values, 1 / sig**2, rtol=1e-10)
    left = px < n // 2
    assert np.median(sig[left]) == pytest.approx(0.05, rel=0.05)
    assert np.median(sig[~left]) == pytest.approx(0.2, rel=0.05)
    wk = 1 / sig**2
    manual = np.einsum("k,kyx->yx", wk, cube.values) / wk.sum()
    np.testing.assert_allclose(res.stacked.values, manual, rtol=1e-10)
    assert res.flux_err_jy == pytest.approx(1 / np.sqrt(wk.sum()), rel=1e-10)  # eq. 5
    np.testing.assert_allclose(res.weights[:, 0], wk)
    unweighted = stack_images(path, np.c_[ra, dec], stamp_size=32, weighting="none", subpixel="fourier",
                              noise_estimator="std", noise_stamp_size=32)
    assert res.flux_err_jy < 0.75 * unweighted.flux_err_jy
    assert abs(res.flux_jy - 1.0) < 4 * res.flux_err_jy
    assert res.stamp_rms_jy == pytest.approx(res.flux_err_jy, rel=0.15)


def _clipped_std_numpy(v: np.ndarray, k: float = 3.0) -> float:
    """Plain-numpy 3-sigma clipping about the median, iterated to convergence, divided by the
    std of a unit Gaussian truncated where the clipping of pure noise converges."""
    from scipy import optimize, stats

    v = v[np.isfinite(v)]
    while True:
        med, sd = np.median(v), np.std(v, ddof=1)
        keep = v[(v >= med - k * sd) & (v <= med + k * sd)]
        if keep.size == v.size:
            break
        v = keep
    # truncated-Gaussian std at the fixed point c = k * std(c), from scipy, not from xstack
    def trunc_std(c):
        return np.sqrt(stats.truncnorm(-c, c).var())
    c = optimize.brentq(lambda c: c - k * trunc_std(c), 1.0, 10.0)
    return float(np.std(v, ddof=1) / trunc_std(c))


def _two_noise_field(tmp_path, rng, artefacts=False, flux=1.0):
    """12 x 12 sources of ``flux`` Jy 40 pixels apart on noise 0.05 (left half) and 0.2 Jy/beam
    (right half); with ``artefacts`` a 3 Jy/beam point 12 pixels east of every other source
    (a CLEAN residual; 28 pixels from the next)."""
    cell, n_side, spacing = 0.5, 12, 40
    n = 2 * spacing + spacing * (n_side - 1) + 1
    w = sin_wcs(n, cell)
    base = spacing + spacing * np.arange(n_side, dtype=np.float64)
    gx, gy = np.meshgrid(base, base)
    px = gx.ravel() + rng.uniform(-0.5, 0.5, gx.size)
    py = gy.ravel() + rng.uniform(-0.5, 0.5, gy.size)
    img = render(n, cell, px, py, np.full(px.size, flux), BEAM)
    near = np.arange(px.size) % 2 == 0
    if artefacts:
        img += render(n, cell, np.round(px[near]) + 12, np.round(py[near]),
                      np.full(near.sum(), 3.0), BEAM)
    noise_map = np.where(np.arange(n)[None, :] < n // 2, 0.05, 0.2) * np.ones((n, 1))
    img += rng.normal(size=img.shape) * noise_map
    path = write_image(tmp_path / "noisy.fits", img, w, BEAM)
    ra, dec = w.pixel_to_world_values(px, py)
    return path, img, np.c_[ra, dec], px, py, near, cell, n


def test_default_sigma_k_is_the_clipped_std_on_300_beams_like_the_uv_stack(tmp_path):
    from xstack.uvstack.localnoise import measure_local_noise

    # targets below the noise, as stacking's are: the ~4 neighbours in each noise stamp then
    # do not raise it (at 0.1 Jy, 2 sigma on the quiet half, they add 1.4 %; at 1 Jy, 3 %)
    path, img, pos, px, py, _, cell, n = _two_noise_field(tmp_path, np.random.default_rng(6),
                                                          flux=0.02)
    res = stack_images(path, pos, stamp_size=32, subpixel="fourier")
    # the paper's ~300 beam areas: 300 x (pi / 4 ln 2) BMAJ BMIN / cell^2 pixels, side made odd
    side = int(np.ceil(np.sqrt(300 * np.pi / (4 * np.log(2)) * BEAM[0] * BEAM[1] / cell**2))) | 1
    assert res.noise_stamp_size == side == 85
    assert res.noise_estimator == "clipped"
    # independent: cut each noise stamp from the image array at the nearest pixel, leave out
    # the circle of radius BMAJ, clip in plain numpy
    h = side // 2
    off = np.arange(side) - h
    outside = np.hypot(off[None, :], off[:, None]) * cell > BEAM[0]
    want = []
    for x, y in zip(np.floor(px + 0.5).astype(int), np.floor(py + 0.5).astype(int)):
        st = np.full((side, side), np.nan)
        y0, x0 = y - h, x - h
        ys, xs = slice(max(y0, 0), min(y0 + side, n)), slice(max(x0, 0), min(x0 + side, n))
        st[ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0] = img[ys, xs]
        want.append(_clipped_std_numpy(st[outside]))
    # (the kernel's running sums agree with numpy's std to ~1e-8)
    np.testing.assert_allclose(res.cube.sigma.values, want, rtol=1e-7)
    np.testing.assert_allclose(res.cube.weight.values, 1 / np.asarray(want) ** 2, rtol=2e-7)
    # the uv stack's noise_image weights are the same numbers (paper §3.3: "the same local
    # noise estimators")
    uv = measure_local_noise(path, pos)
    np.testing.assert_allclose(res.cube.sigma.values, uv.sigma, rtol=1e-12)
    # and the noise levels are the truth's
    left = px < n // 2
    assert np.median(res.cube.sigma.values[left]) == pytest.approx(0.05, rel=0.02)
    assert np.median(res.cube.sigma.values[~left]) == pytest.approx(0.2, rel=0.02)
    assert res.flux_err_jy == pytest.approx(1 / np.sqrt(np.sum(1 / np.asarray(want) ** 2)), rel=1e-7)
    assert abs(res.flux_jy - 0.02) < 4 * res.flux_err_jy


def test_clipped_sigma_k_ignores_a_clean_residual_the_plain_std_counts(tmp_path):
    # half the targets have a 3 Jy/beam residual 6" away, inside their 40-pixel stamps (and
    # outside their neighbours'): the paper's plain std on the stamp calls it noise and
    # down-weights them; the clipped std on ~300 beams still sees the noise
    path, _, pos, px, _, near, _, n = _two_noise_field(tmp_path, np.random.default_rng(11),
                                                       artefacts=True)
    truth = np.where(px < n // 2, 0.05, 0.2)
    plain = stack_images(path, pos, stamp_size=40, noise_estimator="std", noise_stamp_size=40)
    clipped = stack_images(path, pos, stamp_size=40)
    # away from the step in the noise (a noise stamp of 85 pixels across it measures a mix:
    # the price of the larger stamp, where the noise varies on scales below ~17 beams)
    away = np.abs(px - n // 2) > 45
    ratio_plain = (plain.cube.sigma.values / truth)[away]
    ratio_clip = (clipped.cube.sigma.values / truth)[away]
    near = near[away]
    assert np.median(ratio_plain[near]) > 1.5             # the residual counted as noise
    assert np.median(ratio_plain[~near]) == pytest.approx(1.0, abs=0.05)
    # the 1 Jy targets' wings lift it by ~3 % (see above); ~0.01 scatter from ~7000 pixels
    assert np.all(np.abs(ratio_clip - 1.03) < 0.06)
    assert np.median(ratio_clip[near]) == pytest.approx(np.median(ratio_clip[~near]), abs=0.02)
    # so the weights stop depending on the residual: the down-weighting it caused is gone
    # (weights relative to the truth's 1/sigma^2)
    w_plain = plain.cube.weight.values[away] * truth[away] ** 2
    w_clip = clipped.cube.weight.values[away] * truth[away] ** 2
    assert np.median(w_plain[near]) / np.median(w_plain[~near]) < 0.5
    assert np.median(w_clip[near]) / np.median(w_clip[~near]) == pytest.approx(1.0, abs=0.05)


def test_noise_options_are_checked(tmp_path):
    path, _, pos, *_ = _two_noise_field(tmp_path, np.random.default_rng(1))
    with pytest.raises(XstackError, match="noise_estimator must be one of clipped, mad, std"):
        stack_images(path, pos, noise_estimator="rms")
    with pytest.raises(XstackError, match="noise_stamp_size must be an integer >= 5"):
        stack_images(path, pos, noise_stamp_size=3)
    with pytest.raises(XstackError, match="noise stamp size 9999 is larger than an image"):
        stack_images(path, pos, noise_stamp_size=9999)
    with pytest.raises(XstackError, match="inside the central mask"):
        stack_images(path, pos, stamp_size=64, noise_stamp_size=7)
    mad = stack_images(path, pos, stamp_size=32, noise_estimator="mad", noise_stamp_size=65)
    assert mad.noise_stamp_size == 65 and mad.to_dict()["noise_estimator"] == "mad"


@pytest.mark.parametrize("subpixel", [False, "fourier"])
def test_edge_stamps_do_not_bias_the_stack(tmp_path, subpixel):
    rng = np.random.default_rng(7)
    cell, n, bg = 0.5, 120, 0.5
    w = sin_wcs(n, cell)
    # positions 2-5 pixels from every edge and corner, and some inside, >= 27 pixels apart
    xy = np.array([(2.3, 30.4), (3.7, 60.1), (4.6, 90.8), (115.4, 30.4), (116.8, 60.1),
                   (117.2, 90.8), (30.2, 2.6), (60.6, 3.3), (90.4, 4.1), (30.2, 117.1),
                   (60.6, 116.4), (90.4, 115.6), (2.8, 3.1), (116.9, 2.2), (3.4, 116.6),
                   (117.3, 117.4), (60.3, 60.2), (35.1, 40.7), (85.6, 80.3)])
    px, py = xy[:, 0], xy[:, 1]
    img = render(n, cell, px, py, np.ones(px.size), BEAM, background=bg)
    img += rng.normal(0, 1e-3, img.shape)
    path = write_image(tmp_path / "edge.fits", img, w, BEAM)
    ra, dec = w.pixel_to_world_values(px, py)
    res = stack_images(path, np.c_[ra, dec], stamp_size=40, weighting="none", subpixel=subpixel)
    cube = res.cube.values
    assert np.isnan(cube).any()  # stamps do run off the image
    truth = bg + (1.0 if subpixel else expected_nearest(res.cube.frac_x.values,
                                                        res.cube.frac_y.values, cell, BEAM))
    assert res.flux_jy == pytest.approx(truth, abs=3e-3)
    # far from the source the stack is the background everywhere, including where only a
    # few stamps have data; zero-filling would drag those pixels towards 0
    far = np.hypot(res.stacked.x.values[None, :], res.stacked.y.values[:, None]) > 2.2 * BEAM[0]
    far &= np.isfinite(res.stacked.values)
    assert np.abs(res.stacked.values[far] - bg).max() < 0.02
    zero_filled = np.nan_to_num(cube, nan=0.0).mean(axis=0)
    assert np.abs(zero_filled[far] - bg).max() > 0.2  # the test would catch a zero fill
    assert res.weight_sum.values.min() < res.weight_sum.values.max()


def test_mosaic_pointings_with_pb_weights_and_4d_axes(tmp_path):
    rng = np.random.default_rng(8)
    cell, n, beam, freq = 0.2, 256, (1.0, 0.8, 30.0), 230e9
    pb = standard_beam("ALMA", 12.0)
    centers = [(57.30, -30.0), (57.30 + 20 / 3600 / np.cos(np.radians(30)), -30.0)]
    mid_ra = 0.5 * (centers[0][0] + centers[1][0])
    ra = mid_ra + (np.arange(25) % 5 - 2) * 3.0 / 3600 / np.cos(np.radians(30)) \
        + rng.uniform(-0.1, 0.1, 25) / 3600
    dec = -30.0 + (np.arange(25) // 5 - 2) * 3.0 / 3600 + rng.uniform(-0.1, 0.1, 25) / 3600
    ra = np.append(ra, centers[0][0] - 9 / 3600)  # seen by pointing 0 only (A1 < 0.1)
    dec = np.append(dec, -30.0)
    paths, atten = [], []
    for i, (r0, d0) in enumerate(centers):
        w = sin_wcs(n, cell, r0, d0)
        a = pb(angular_separation(np.radians(ra), np.radians(dec), np.radians(r0), np.radians(d0)), freq)
        px, py = w.world_to_pixel_values(ra, dec)
        img = render(n, cell, px, py, 1.0 * a, beam) + rng.normal(0, 2e-3, (n, n))
        paths.append(write_image(tmp_path / f"p{i}.fits", img, w, beam, four_d=True, freq_hz=freq,
                                 extra={"TELESCOP": "ALMA"}))
        atten.append(a)
    atten = np.array(atten).T
    assert atten[-1, 1] < 0.1 < atten[-1, 0]
    res = stack_images(paths, np.c_[ra, dec], stamp_size=40, weighting="pb", pbcor=True, subpixel="fourier")
    seen = atten >= 0.1
    np.testing.assert_allclose(res.weights, np.where(seen, atten**2, 0.0), rtol=1e-9)
    assert res.n_positions == 26 and res.n_stamps == int(seen.sum()) == 51
    assert abs(res.flux_jy - 1.0) < 0.01
    assert set(np.unique(res.cube.image.values)) == {0, 1}


def test_no_primary_beam_correction_beyond_the_first_null(tmp_path):
    # cutoff 0: positions inside the main lobe are corrected, one in the Airy sidelobe
    # (A ~ 0.018 > 0) and one beyond are not stacked at all
    from xstack.beams import PrimaryBeam

    rng = np.random.default_rng(10)
    cell, n, beam, freq = 0.5, 240, (1.0, 0.8, 0.0), 230e9
    pb0 = standard_beam("ALMA", 12.0)
    pb = PrimaryBeam(pb0.model, pb0.dish_diameter, pb0.blockage_diameter, cutoff=0.0)
    r_null = float(np.degrees(pb.first_null(freq))) * 3600  # arcsec
    offsets = np.array([0.3, 0.6, 1.3, 1.5]) * r_null
    ra = 57.30 + offsets / 3600 / np.cos(np.radians(30))
    dec = np.full(4, -30.0)
    w = sin_wcs(n, cell, 57.30, -30.0)
    img = rng.normal(0, 1e-3, (n, n))
    path = write_image(tmp_path / "a.fits", img, w, beam, four_d=True, freq_hz=freq,
                       extra={"TELESCOP": "ALMA"})
    assert pb(np.radians(1.3 * r_null / 3600), freq) > 0.01
    res = stack_images(path, np.c_[ra, dec], stamp_size=16, weighting="pb", pbcor=True,
                  primary_beam=pb, skip_outside=True)
    assert list(res.weights[:, 0] > 0) == [True, True, False, False]
    assert np.isfinite(res.flux_jy)


def test_four_d_image_equals_two_d(tmp_path):
    rng = np.random.default_rng(9)
    w = sin_wcs(100, 0.5)
    img = rng.normal(size=(100, 100))
    p2 = write_image(tmp_path / "a.fits", img, w, BEAM)
    p4 = write_image(tmp_path / "b.fits", img, w, BEAM, four_d=True)
    ra, dec = w.pixel_to_world_values([30.3, 60.7], [40.2, 55.5])
    pos = np.c_[ra, dec]
    r2 = stack_images(p2, pos, stamp_size=24)
    r4 = stack_images(p4, pos, stamp_size=24)
    np.testing.assert_array_equal(r2.stacked.values, r4.stacked.values)


def test_lowfreq_filter_removes_a_background_offset(fields, tmp_path):
    rng = np.random.default_rng(10)
    cell = 0.5
    path, ra, dec, px, py = make_field(tmp_path, rng, cell, beam=BEAM, noise=1e-3, psf=True,
                                       n_side=8, spacing=70)
    with fits.open(path) as h:
        data = h[0].data + 0.3  # a background the filter must remove
        fits.PrimaryHDU(data, header=h[0].header).writeto(tmp_path / "bg.fits")
    (tmp_path / "bg.psf.fits").write_bytes((tmp_path / "img.psf.fits").read_bytes())
    pos = np.c_[ra, dec]
    raw = stack_images(tmp_path / "bg.fits", pos, stamp_size=64, weighting="none", subpixel="fourier")
    assert raw.flux_jy == pytest.approx(1.3, abs=5e-3)
    filt = stack_images(tmp_path / "bg.fits", pos, stamp_size=64, weighting="none", subpixel="fourier",
                   filter_lowfreq=1)
    # zeroing the DC cell subtracts the stamp mean: background + the source's mean over the
    # stamp; the source's share is the PSF's mean, which the filter response gives back
    response = 1 - np.mean(raw.psf_stamp.values) / float(raw.psf_stamp.values[32, 32])
    assert filt.filter_response == pytest.approx(response, rel=1e-12)
    assert float(filt.psf_stamp.values[32, 32]) == pytest.approx(1 - np.mean(raw.psf_stamp.values))
    expected = raw.flux_jy - np.mean(raw.stacked.values)
    assert filt.flux_jy * filt.filter_response == pytest.approx(expected, abs=1e-9)
    assert filt.flux_jy == pytest.approx(1.0, abs=0.02)      # the background gone, the flux kept
    assert filt.to_dict()["filter_response"] == pytest.approx(response, rel=1e-12)
    # a uv distance: one Fourier cell of a 64 x 0.5" stamp is 6446 lambda
    by_q = stack_images(tmp_path / "bg.fits", pos, stamp_size=64, weighting="none", subpixel="fourier",
                   filter_lowfreq="1klambda")
    assert by_q.flux_jy == pytest.approx(filt.flux_jy, abs=1e-12)


@pytest.mark.parametrize("spec", ["20klambda", 5])
def test_lowfreq_filter_keeps_a_point_source_flux(tmp_path, spec):
    """A filter that removes a large share of the peak (here 10-40 %) must not bias the flux:
    noiseless isolated sources of 1 Jy (stamps free of neighbours) come back at 1 Jy, through
    the filter response of the stacked PSF; the filtered peak alone is lower by that share."""
    rng = np.random.default_rng(12)
    cell = 0.5
    path, ra, dec, _, _ = make_field(tmp_path, rng, cell, beam=BEAM, noise=0.0, psf=True,
                                     n_side=6, spacing=80)
    pos = np.c_[ra, dec]
    for subpixel in (False, "fourier"):
        raw = stack_images(path, pos, stamp_size=64, weighting="none", subpixel=subpixel)
        filt = stack_images(path, pos, stamp_size=64, weighting="none", subpixel=subpixel,
                            filter_lowfreq=spec)
        assert 0.5 < filt.filter_response < 0.95
        assert filt.flux_jy == pytest.approx(raw.flux_jy, rel=1e-4)   # 10-40 % without the response
        peak = float(filt.stacked.values[32, 32])
        assert peak == pytest.approx(filt.flux_jy * filt.filter_response, rel=1e-12)
        assert peak == pytest.approx(raw.flux_jy * filt.filter_response, rel=1e-4)
        assert filt.flux_err_jy == pytest.approx(raw.flux_err_jy / filt.filter_response, rel=1e-9)
    assert raw.filter_response is None


def test_lowfreq_filter_without_psf_warns(tmp_path):
    rng = np.random.default_rng(13)
    path, ra, dec, _, _ = make_field(tmp_path, rng, 0.5, beam=BEAM, noise=0.0, psf=False,
                                     n_side=4, spacing=80)
    with pytest.warns(XstackWarning, match="filter_lowfreq without a PSF") as rec:
        res = stack_images(path, np.c_[ra, dec], stamp_size=64, weighting="none",
                           filter_lowfreq=5)
    assert any(getattr(r.message, "option", None) == "psf" for r in rec)
    assert res.filter_response is None and res.flux_jy < 0.95     # the bare filtered peak


def test_outputs_layout_and_roundtrip(fields, tmp_path):
    path, ra, dec, _, _ = fields[0.5]
    out = tmp_path / "stack.fits"
    res = stack_images(path, np.c_[ra, dec], stamp_size=32, subpixel="fourier", out=out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stack.cube.zarr", "stack.fits", "stack.png"]
    with fits.open(out) as hdul:
        assert [h.name for h in hdul] == ["PRIMARY", "PSF", "WEIGHTS"]
        h = hdul[0].header
        assert h["CTYPE1"] == "RA---SIN" and h["CRPIX1"] == 17 and h["CRPIX2"] == 17
        assert h["BMAJ"] * 3600 == pytest.approx(3.2) and h["BUNIT"] == "Jy/beam"
        assert h["STFLUX"] == pytest.approx(res.flux_jy) and h["NSTACK"] == 400
        assert hdul[0].data[16, 16] == pytest.approx(res.flux_jy)
        assert hdul["PSF"].data.max() == pytest.approx(1.0)
    back = read_stack_fits(out)
    assert back["center"] == (16, 16) and back["pixel_arcsec"][0] == pytest.approx(0.5)
    cube = xr.open_zarr(tmp_path / "stack.cube.zarr", consolidated=False)
    np.testing.assert_array_equal(cube["stamps"].values, res.cube.values)
    np.testing.assert_array_equal(cube["stamps"].position.values, np.arange(400))
    json.dumps(res.to_dict())
    with pytest.raises(XstackError, match="exists"):
        stack_images(path, np.c_[ra, dec], stamp_size=32, out=out)
    res2 = stack_images(path, np.c_[ra, dec], stamp_size=32, out=out, overwrite=True, cube_format="fits",
                   plot=False)
    with fits.open(tmp_path / "stack.cube.fits") as hdul:
        assert hdul[0].data.shape == (400, 32, 32)
        assert hdul["STAMPS"].data["position"][0] == 1
    assert res2.flux_jy < res.flux_jy  # nearest pixel loses the pixelisation factor
    with fits.open(out) as hdul:
        ph = hdul["PSF"].header
        assert ph["PSFSMEAR"] and ph["PSFPEAK"] == pytest.approx(hdul["PSF"].data[16, 16])
        assert ph["PSFPEAK"] < 0.99


def _no_celestial(tmp_path):
    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = "LINEAR", "LINEAR"
    p = tmp_path / "lin.fits"
    fits.PrimaryHDU(np.zeros((50, 50), np.float32), header=h).writeto(p)
    return p


def test_bad_input_raises_and_writes_nothing(fields, tmp_path):
    path, ra, dec, _, _ = fields[0.5]
    outdir = tmp_path / "out"
    outdir.mkdir()
    out = outdir / "s.fits"
    pos = np.c_[ra, dec]
    with pytest.raises(XstackError, match="celestial"):
        stack_images(_no_celestial(tmp_path), pos, out=out)
    with pytest.raises(XstackError, match="outside every image.*row 401"):
        stack_images(path, np.vstack([pos, [[ra[0] + 1.0, dec[0]]]]), stamp_size=32, out=out)
    with pytest.raises(XstackError, match="larger than the image"):
        stack_images(path, pos, stamp_size=1000, out=out)
    with pytest.raises(XstackError, match="method"):
        stack_images(path, pos, method="mode", out=out)
    with pytest.raises(XstackError, match="no such image"):
        stack_images(tmp_path / "missing.fits", pos, out=out)
    w = sin_wcs(60, 0.5)
    cube_like = fits.Header(w.to_header())
    cube_like["NAXIS"] = 3
    cube_like["CTYPE3"], cube_like["CRVAL3"], cube_like["CDELT3"], cube_like["CRPIX3"] = \
        "FREQ", 1e9, 1e6, 1
    p3 = tmp_path / "cube3.fits"
    fits.PrimaryHDU(np.zeros((4, 60, 60), np.float32), header=cube_like).writeto(p3)
    with pytest.raises(XstackError, match="4 planes"):
        stack_images(p3, pos, out=out)
    coarse = write_image(tmp_path / "coarse.fits", np.zeros((100, 100)), sin_wcs(100, 1.0), BEAM)
    with pytest.raises(XstackError, match="pixel scale"):
        stack_images([path, coarse], pos, stamp_size=32, out=out)
    assert list(outdir.iterdir()) == []
    # skipping works when asked and reports the row
    res = stack_images(path, np.vstack([pos, [[ra[0] + 1.0, dec[0]]]]), stamp_size=32, skip_outside=True)
    assert res.skipped_rows == [401] and res.n_positions == 400


def test_blanked_pixels_are_excluded_per_pixel(tmp_path):
    rng = np.random.default_rng(13)
    path, ra, dec, px, py = make_field(tmp_path, rng, 0.5, beam=BEAM, noise=1e-3, n_side=6)
    with fits.open(path) as h:
        data = h[0].data.copy()
        hdr = h[0].header
    data[:, : int(px[0]) + 3] = np.nan  # a blanked strip through the first column of sources
    fits.PrimaryHDU(data, header=hdr).writeto(tmp_path / "blank.fits")
    res = stack_images(tmp_path / "blank.fits", np.c_[ra, dec], stamp_size=32, weighting="none",
                  subpixel="fourier", skip_outside=True)
    # positions whose center pixel is blanked are not covered; the rest still give the flux
    assert res.n_positions == 30 and res.skipped_rows == [1 + 6 * k for k in range(6)]
    assert res.flux_jy == pytest.approx(1.0, abs=5e-3)
    assert kernels.SPLINE_NAN_GUARD > 0


def test_public_api_name_is_callable(fields):
    import xstack

    path, ra, dec, _, _ = fields[0.5]
    # the package xstack.imstack is already imported here and shadows the lazy API name
    res = xstack.stack_images(path, np.c_[ra[:10], dec[:10]], stamp_size=32)
    assert isinstance(res, xstack.imstack.ImstackResult) and res.n_positions == 10


@pytest.mark.parametrize("ra0,dec0", [(0.0, 10.0), (180.0, 89.98), (359.9999, -89.5)])
def test_ra_wrap_and_poles(tmp_path, ra0, dec0):
    rng = np.random.default_rng(14)
    path, ra, dec, _, _ = make_field(tmp_path, rng, 0.5, beam=BEAM, n_side=6, noise=1e-3,
                                     ra0=ra0, dec0=dec0)
    if ra0 == 0.0:
        assert (ra > 359).any() and (ra < 1).any()  # positions on both sides of RA = 0
    res = stack_images(path, np.c_[ra, dec], stamp_size=32, weighting="none", subpixel="fourier")
    assert res.n_positions == 36
    assert res.flux_jy == pytest.approx(1.0, abs=5e-3)


def test_pb_weights_from_a_pb_fits_image(fields, tmp_path):
    path, ra, dec, px, py = fields[0.5]
    with fits.open(path) as h:
        hdr = h[0].header
        ny, nx = h[0].data.shape
    yy, xx = np.indices((ny, nx))
    pbimg = np.exp(-((xx - nx / 2) ** 2 + (yy - ny / 2) ** 2) / (2 * (nx / 3) ** 2))
    fits.PrimaryHDU(pbimg.astype(np.float32), header=hdr).writeto(tmp_path / "pb.fits")
    res = stack_images(path, np.c_[ra, dec], stamp_size=32, weighting="pb", primary_beam=tmp_path / "pb.fits")
    a = pbimg[np.floor(py + 0.5).astype(int), np.floor(px + 0.5).astype(int)].astype(np.float32)
    np.testing.assert_allclose(res.weights[:, 0], a.astype(np.float64) ** 2, rtol=1e-6)
    with pytest.raises(XstackError, match="primary beam"):
        stack_images(path, np.c_[ra, dec], stamp_size=32, weighting="pb")  # no TELESCOP, no primary_beam=


def test_rotated_wcs_and_rotated_beam(tmp_path):
    from _imstack_helpers import gauss_beam

    rng = np.random.default_rng(15)
    cell, n, beam = 0.5, 400, (3.2, 1.6, 20.0)
    w = sin_wcs(n, cell)
    rho = np.radians(30.0)  # pixel axes rotated by 30 deg
    w.wcs.pc = [[np.cos(rho), -np.sin(rho)], [np.sin(rho), np.cos(rho)]]
    m = w.pixel_scale_matrix * 3600.0  # pixel offsets -> (east, north) arcsec
    base = 30 + 34 * np.arange(11, dtype=np.float64)
    gx, gy = np.meshgrid(base, base)
    px = gx.ravel() + rng.uniform(-0.5, 0.5, gx.size)
    py = gy.ravel() + rng.uniform(-0.5, 0.5, gy.size)
    yy, xx = np.indices((n, n), dtype=np.float64)
    img = np.zeros((n, n))
    for x0, y0 in zip(px, py):
        sl = (slice(int(y0) - 15, int(y0) + 16), slice(int(x0) - 15, int(x0) + 16))
        dx, dy = xx[sl] - x0, yy[sl] - y0
        img[sl] += gauss_beam(m[0, 0] * dx + m[0, 1] * dy, m[1, 0] * dx + m[1, 1] * dy, *beam)
    img += rng.normal(0, 1e-3, img.shape)
    path = write_image(tmp_path / "rot.fits", img, w, beam)
    ra, dec = w.pixel_to_world_values(px, py)
    near = stack_images(path, np.c_[ra, dec], stamp_size=32, weighting="none")
    fx, fy = near.cube.frac_x.values, near.cube.frac_y.values
    exact = np.mean(gauss_beam(-(m[0, 0] * fx + m[0, 1] * fy), -(m[1, 0] * fx + m[1, 1] * fy), *beam))
    assert near.flux_jy == pytest.approx(exact, abs=5e-4)
    assert near.pixelisation_factor == pytest.approx(exact, abs=3e-3)
    assert near.pixel_arcsec == pytest.approx((0.5, 0.5))
    sub = stack_images(path, np.c_[ra, dec], stamp_size=32, weighting="none", subpixel="fourier")
    assert sub.flux_jy == pytest.approx(1.0, abs=3e-3)


@pytest.mark.parametrize("size", [31, 33, 48])
def test_odd_and_even_stamp_sizes_center_the_source(fields, size):
    path, ra, dec, _, _ = fields[0.5]
    c = size // 2
    for sub in (False, "fourier", "spline"):
        res = stack_images(path, np.c_[ra[:100], dec[:100]], stamp_size=size, weighting="none", subpixel=sub)
        assert res.stacked.shape == (size, size)
        assert np.unravel_index(np.nanargmax(res.stacked.values), res.stacked.shape) == (c, c)
        assert float(res.stacked.x[c]) == 0.0 and float(res.stacked.y[c]) == 0.0
        assert res.flux_jy == pytest.approx(float(res.psf_stamp.values[c, c]), abs=4e-3)
