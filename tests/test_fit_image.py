"""Image-domain PSF fitting: errors honest for correlated (dirty-image) noise."""

from __future__ import annotations

import numpy as np
import pytest
from _fit_helpers import StampSimulator

from xstack.errors import XstackError
from xstack.fit.imfit import fit_image


@pytest.fixture(scope="module")
def sim():
    return StampSimulator()


def test_noiseless_recovery(sim):
    sim0 = StampSimulator(sigma=0.0)
    img = sim0.stamp(2.0, 1.8, 0) + 0.01
    r = fit_image(img, psf=sim0.psf, pixel_arcsec=0.5, sigma_jy=1e-3)
    assert r.flux_jy == pytest.approx(2.0, rel=2e-3)
    assert r.fwhm_arcsec == pytest.approx(1.8, rel=5e-3)
    assert r.extra["background_jy_per_beam"] == pytest.approx(0.01, abs=2e-3)
    p = fit_image(sim0.stamp(2.0, 0.0, 0), psf=sim0.psf, pixel_arcsec=0.5, model="point",
                  background=False, sigma_jy=1e-3)
    assert p.flux_jy == pytest.approx(2.0, rel=1e-6)


@pytest.mark.parametrize("fwhm", [0.0, 1.5, 3.0])
def test_noiseless_fit_exact_at_any_flux_scale(fwhm):
    """A noiseless dirty stamp (direct Fourier sum) is fitted exactly, in Jy and in nJy.

    The fit once stopped after two evaluations for a µJy stack (least_squares' absolute gtol
    on residuals in Jy/beam): a 3 µJy point source came out 0.41" wide and 1.6 % bright. A
    PSF no larger than the stamp (as xstack imstack writes it) must not bias it either."""
    sim0 = StampSimulator(sigma=0.0)
    unit = sim0.stamp(1.0, fwhm, 0)
    h, c = sim0.size // 2, sim0.psf.shape[0] // 2
    stamp_sized_psf = sim0.psf[c - h:c + h + 1, c - h:c + h + 1]
    for flux in (1.0, 3e-6, 1e-9):
        # the PSF twice the stamp holds the model wholly: exact; a stamp-sized one leaves
        # the Gaussian's tail beyond the 3-sigma border out of the fit (2e-4 of a 3" source)
        for psf, tol in ((sim0.psf, 1e-6), (stamp_sized_psf, 1e-3)):
            r = fit_image(flux * unit, psf=psf, pixel_arcsec=0.5)
            assert r.flux_jy == pytest.approx(flux, rel=tol)
            assert r.fwhm_arcsec == pytest.approx(fwhm, abs=2 * tol)
            assert abs(r.extra["background_jy_per_beam"]) < tol * flux


def test_errors_match_scatter(sim):
    """100 noise realisations: >= 90 % within 2 sigma, reported errors = scatter +- 15 %."""
    flux, fwhm = 1.0, 1.5
    out = []
    white = []
    for seed in range(100):
        img = sim.stamp(flux, fwhm, seed)
        r = fit_image(img, psf=sim.psf, pixel_arcsec=0.5)
        out.append((r.flux_jy, r.flux_err_jy, r.fwhm_arcsec, r.fwhm_err_arcsec))
        if seed < 3:
            white.append(fit_image(img, psf=sim.psf, pixel_arcsec=0.5,
                                   noise_correlation="none").flux_err_jy)
    f, fe, t, te = np.array(out).T
    assert np.mean(np.abs(f - flux) < 2 * fe) >= 0.9
    assert np.mean(np.abs(t - fwhm) < 2 * te) >= 0.9
    assert np.mean(fe) / np.std(f) == pytest.approx(1.0, abs=0.15)
    assert np.mean(te) / np.std(t) == pytest.approx(1.0, abs=0.15)
    # ignoring the pixel correlation would understate the error several times
    assert np.mean(white) < 0.5 * np.std(f)


def test_point_source_with_gaussian_model(sim):
    z = []
    for seed in range(20):
        r = fit_image(sim.stamp(1.0, 0.0, 1000 + seed), psf=sim.psf, pixel_arcsec=0.5)
        assert np.isfinite(r.fwhm_upper_limit_arcsec) and r.fwhm_upper_limit_arcsec >= r.fwhm_arcsec
        z.append(r.values[1] / np.sqrt(r.covariance[1, 1]))
    z = np.array(z)
    assert np.mean(np.abs(z) < 2) >= 0.8
    assert abs(np.mean(z)) < 1.0


def test_fits_input_and_bad_input(tmp_path, sim):
    from astropy.io import fits
    from astropy.wcs import WCS

    img = sim.stamp(1.0, 1.5, 7)
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---SIN", "DEC--SIN"]
    w.wcs.cdelt = [-0.5 / 3600, 0.5 / 3600]
    w.wcs.crpix = [sim.size // 2 + 1, sim.size // 2 + 1]
    w.wcs.crval = [57.3, -30.0]
    hdr = w.to_header()
    path = tmp_path / "stamp.fits"
    fits.HDUList([fits.PrimaryHDU(img, header=hdr),
                  fits.ImageHDU(sim.psf, name="PSF")]).writeto(path)
    a = fit_image(path)
    b = fit_image(img, psf=sim.psf, pixel_arcsec=0.5)
    assert a.flux_jy == pytest.approx(b.flux_jy, rel=1e-10)
    assert a.fwhm_arcsec == pytest.approx(b.fwhm_arcsec, rel=1e-8)
    # an imstack PSF with nearest-pixel smear (PSFSMEAR, peak < 1) is used as it is
    sim0 = StampSimulator(sigma=0.0)
    smear = 0.9 * sim0.psf
    ph = fits.Header({"PSFSMEAR": True, "PSFPEAK": 0.9})
    spath = tmp_path / "smeared.fits"
    fits.HDUList([fits.PrimaryHDU(0.9 * sim0.stamp(1.0, 0.0, 0), header=hdr),
                  fits.ImageHDU(smear, header=ph, name="PSF")]).writeto(spath)
    s = fit_image(spath, model="point", sigma_jy=1e-3)
    assert s.flux_jy == pytest.approx(1.0, rel=1e-6) and not s.extra["psf_normalized"]
    s2 = fit_image(spath, model="point", sigma_jy=1e-3, normalize_psf=True)
    assert s2.flux_jy == pytest.approx(0.9, rel=1e-6)
    nopsf = tmp_path / "nopsf.fits"
    fits.PrimaryHDU(img, header=hdr).writeto(nopsf)
    with pytest.raises(XstackError, match="no PSF"):
        fit_image(nopsf)
    with pytest.raises(XstackError, match="pixel_arcsec"):
        fit_image(img, psf=sim.psf)
    with pytest.raises(XstackError, match="not positive"):
        fit_image(-img, psf=sim.psf, pixel_arcsec=0.5)
    assert fit_image(-img, psf=sim.psf, pixel_arcsec=0.5, model="point").flux_jy < 0
    with pytest.raises(XstackError, match="usable pixels"):
        fit_image(img, psf=sim.psf, pixel_arcsec=0.5, fit_radius_arcsec=0.1)
