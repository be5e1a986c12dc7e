"""sigma_k of a primary-beam corrected image, measured where its noise is flat.

A corrected ALMA pointing's noise grows as 1/A away from the center, so a sigma_k stamp of
~300 beams spans a factor of several in noise. The truth here is analytic: white noise of
sigma_u (uncorrected) divided by an Airy beam written out in this file (not xstack.beams),
so the noise of the corrected flux at target k is exactly sigma_u / A_k.
"""

from __future__ import annotations

import numpy as np
import pytest
from _imstack_helpers import DEC0, RA0, sin_wcs, write_image
from astropy.io import fits
from scipy.special import j1

from xstack.imstack import stack_images
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
    TELESCOP (evaluated on every pixel) and on the beam file on the image's own grid."""
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
