"""sigma_k of a primary-beam corrected image, measured where its noise is flat.

A corrected ALMA pointing's noise grows as 1/A away from the center, so a sigma_k stamp of
~300 beams spans a factor of several in noise. The truth here is analytic: white noise of
sigma_u (uncorrected) divided by an Airy beam written out in this file (not xstack.beams),
so the noise of the corrected flux at target k is exactly sigma_u / A_k.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _imstack_helpers import DEC0, RA0, sin_wcs, write_image
from astropy.io import fits
from scipy.special import j1

from xstack.imstack import kernels, stack_images
from xstack.imstack.io import beam_on_grid, flat_noise_image, image_beam, noise_to_corrected, read_image
from xstack.uvstack.localnoise import measure_local_noise

FREQ_HZ = 230e9
CELL = 0.2                      # arcsec
N = 256                         # pixels: 51 arcsec, the beam's FWHM is ~25 arcsec
BEAM = (1.0, 0.8, 0.0)          # restoring beam, arcsec
SIGMA_U = 1e-4                  # Jy/beam, the noise of the uncorrected image
CUTOFF = 0.1                    # xstack's default primary-beam cutoff


def airy_alma(theta_rad: np.ndarray) -> np.ndarray:
    """CASA's ALMA 12 m beam: an Airy pattern of a 10.7 m dish with a 0.75 m blockage."""
    eps = 0.75 / 10.7
    x = np.pi * 10.7 * np.sin(theta_rad) * FREQ_HZ / 299792458.0
    x = np.where(x == 0, 1e-12, x)
    amp = (2 * j1(x) / x - eps**2 * 2 * j1(eps * x) / (eps * x)) / (1 - eps**2)
    return amp**2


def _offsets(w, ra, dec):
    """Exact angular distance (rad) from the pointing (the WCS reference) of (ra, dec) deg."""
    r0, d0 = np.radians(RA0), np.radians(DEC0)
    r, d = np.radians(ra), np.radians(dec)
    cos_t = np.sin(d0) * np.sin(d) + np.cos(d0) * np.cos(d) * np.cos(r - r0)
    return np.arccos(np.clip(cos_t, -1, 1))


@pytest.fixture(scope="module")
def pointing(tmp_path_factory):
    """A corrected ALMA pointing of white noise sigma_u / A, its beam file, and targets."""
    tmp = tmp_path_factory.mktemp("flatnoise")
    rng = np.random.default_rng(2015)
    w = sin_wcs(N, CELL)
    yy, xx = np.mgrid[0:N, 0:N].astype(np.float64)
    ra_pix, dec_pix = w.pixel_to_world_values(xx, yy)
    a_pix = airy_alma(_offsets(w, ra_pix, dec_pix))
    corrected = rng.normal(0.0, SIGMA_U, (N, N)) / a_pix
    corrected[a_pix < CUTOFF] = np.nan          # blanked below the cutoff, as xstack image does
    beam_img = np.where(a_pix < CUTOFF, np.nan, a_pix)
    extra = {"TELESCOP": "ALMA", "XSPBCOR": True}
    model = write_image(tmp / "model.fits", corrected, w, BEAM, extra=extra, four_d=True,
                        freq_hz=FREQ_HZ)
    fits.PrimaryHDU(beam_img.astype(np.float32), header=w.to_header()).writeto(tmp / "onfile.pb.fits")
    onfile = write_image(tmp / "onfile.fits", corrected, w, BEAM,
                         extra=dict(extra, XSPBFILE="onfile.pb.fits"), four_d=True, freq_hz=FREQ_HZ)
    # targets from the center out to 14 arcsec (A ~ 0.45), in every direction
    radii = np.repeat([0.0, 4.0, 8.0, 11.0, 14.0], 4) / 3600.0
    angle = np.radians(np.tile([20.0, 110.0, 200.0, 290.0], 5))
    dec = DEC0 + radii * np.cos(angle)
    ra = RA0 + radii * np.sin(angle) / np.cos(np.radians(DEC0))
    a_k = airy_alma(_offsets(w, ra, dec))
    return {"model": model, "onfile": onfile, "ra": ra, "dec": dec, "a_k": a_k,
            "truth": SIGMA_U / a_k}


def _sigma_of(result) -> np.ndarray:
    """sigma_k of each catalog row from an ImstackResult's cube."""
    order = np.argsort(result.cube["position"].values)
    return np.asarray(result.cube["sigma"].values)[order]


@pytest.mark.parametrize("which", ["model", "onfile"])
def test_sigma_k_is_noise_over_attenuation(pointing, which):
    """Flattened: sigma_k within 4 % of sigma_u / A_k at every target, on the beam model of
    TELESCOP (evaluated on the noise stamps' pixels) and on the beam file on the image's own grid."""
    positions = np.column_stack([pointing["ra"], pointing["dec"]])
    res = stack_images(pointing[which], positions)
    assert res.noise_flattened
    sigma = _sigma_of(res)
    assert sigma.shape == pointing["truth"].shape
    np.testing.assert_allclose(sigma / pointing["truth"], 1.0, atol=0.04)

    # the uv stack's sigma_k (noise_image=) is the same measurement
    local = measure_local_noise(pointing[which], positions)
    assert local.beam is not None
    np.testing.assert_allclose(local.sigma, sigma, rtol=1e-9)


def test_unflattened_sigma_k_is_biased_high_off_center(pointing):
    """Without a beam (A = 1), sigma_k is the corrected map's own spread over a stamp of
    ~17 arcsec, across which A falls to ~0.5 even at the center: it is > 15 % high at every
    target -- the bias the flattening removes (the test above fails without it)."""
    positions = np.column_stack([pointing["ra"], pointing["dec"]])
    res = stack_images(pointing["model"], positions, primary_beam="none")
    assert not res.noise_flattened
    ratio = _sigma_of(res) / pointing["truth"]
    assert np.all(ratio > 1.15), ratio


def test_stamp_footprint_is_the_pixels_the_stamps_read():
    """The footprint is exactly the set of pixels extract_stamps reads, found by cutting the
    stamps out of an image of pixel indices: at the edges, off the image, overlapping, and
    for even and odd sizes."""

    ny, nx = 37, 53
    index = np.arange(ny * nx, dtype=np.float64).reshape(ny, nx)
    x = np.array([0.0, 52.4, 10.5, 11.2, -30.0, 26.0, np.nan, 60.0])
    y = np.array([0.0, 36.0, 18.49, 18.6, 5.0, -3.0, 4.0, 40.0])
    for size in (1, 4, 7, 20):
        stamps, _, _ = kernels.extract_stamps(index, x[np.isfinite(x)], y[np.isfinite(x)], size)
        read = np.zeros(ny * nx, dtype=bool)
        read[stamps[np.isfinite(stamps)].astype(np.int64)] = True
        foot = kernels.stamp_footprint((ny, nx), x, y, size)
        assert foot.shape == (ny, nx) and foot.dtype == bool
        np.testing.assert_array_equal(foot.ravel(), read)
    assert not kernels.stamp_footprint((ny, nx), [], [], 9).any()


def test_model_beam_is_evaluated_only_on_the_footprint(pointing):
    """A beam model is evaluated only on the noise stamps' pixels, gives the same A there as
    on every pixel, and sigma_k is unchanged: the same numbers as the whole-grid evaluation
    followed by the same clipped stamps (a second, direct path)."""

    info = read_image(pointing["model"])
    conv = image_beam(info, image_corrected=True)
    px, py = info.wcs.world_to_pixel_values(pointing["ra"], pointing["dec"])
    size = kernels.noise_stamp_size(BEAM[:2], CELL, CELL, BEAM[0], N)
    foot = kernels.stamp_footprint(info.shape, px[:4], py[:4], size)   # the central targets
    assert 0 < foot.sum() < 0.6 * foot.size

    evaluated = []

    def counting(ra, dec):
        evaluated.append(np.size(ra))
        return conv.values(ra, dec)

    counted = dataclasses.replace(conv, values=counting)
    part = beam_on_grid(counted, info, foot)
    assert sum(evaluated) == foot.sum()
    whole = beam_on_grid(conv, info)
    np.testing.assert_array_equal(part[foot], whole[foot])
    assert np.all(np.isnan(part[~foot]))
    with pytest.raises(ValueError, match="footprint has shape"):
        beam_on_grid(conv, info, foot[:-1])

    positions = np.column_stack([pointing["ra"], pointing["dec"]])
    res = stack_images(info, positions)
    local = measure_local_noise(info, positions)
    assert local.stamp_size == size
    flat, flattened = flat_noise_image(info, conv)          # every pixel
    assert flattened
    pix = np.hypot(info.pixel_matrix_deg[0], info.pixel_matrix_deg[1]) * 3600.0  # arcsec, x and y
    mask = kernels.central_mask(size, local.mask_radius_arcsec / pix[0],
                                local.mask_radius_arcsec / pix[1])
    sig, _ = kernels.stamp_noise(flat, px, py, size, mask, "clipped")
    a_k = np.asarray(conv.values(pointing["ra"], pointing["dec"]), np.float64)
    direct = noise_to_corrected(sig, conv, True, a_k)
    assert np.all(np.isfinite(direct))
    np.testing.assert_allclose(local.sigma, direct, rtol=1e-12)
    np.testing.assert_allclose(_sigma_of(res), direct, rtol=1e-12)
