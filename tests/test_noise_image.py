"""Image-domain noise estimates on correlated-noise images with a known scatter."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits
from astropy.wcs import WCS

from xstack.errors import XstackError
from xstack.noise.estimate import estimate_noise

SIZE, PIX, S_KER = 300, 0.5, 1.5  # pixels, arcsec, kernel sigma (pixels)


def _header():
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---SIN", "DEC--SIN"]
    w.wcs.cdelt = [-PIX / 3600, PIX / 3600]
    w.wcs.crpix = [SIZE / 2 + 1, SIZE / 2 + 1]
    w.wcs.crval = [57.3, -30.0]
    h = w.to_header()
    h["BMAJ"] = h["BMIN"] = 2.355 * S_KER * np.sqrt(2) * PIX / 3600
    h["BPA"] = 0.0
    return h


def _noise_image(seed):
    """White noise convolved with a Gaussian: unit variance, correlation exp(-r^2/(4 s^2))."""
    rng = np.random.default_rng(seed)
    white = rng.normal(size=(SIZE, SIZE))
    f = np.fft.fftfreq(SIZE)
    ker_ft = np.exp(-2 * np.pi**2 * S_KER**2 * (f[:, None] ** 2 + f[None, :] ** 2))
    img = np.fft.ifft2(np.fft.fft2(white) * ker_ft).real
    return img / np.sqrt(1 / (4 * np.pi * S_KER**2))


def _psf():
    y, x = np.mgrid[-50:51, -50:51]
    return np.exp(-(x**2 + y**2) / (4 * S_KER**2))


def _targets(n, seed=0):
    rng = np.random.default_rng(seed)
    w = WCS(_header())
    pts = []
    while len(pts) < n:
        p = rng.uniform(30, SIZE - 30, 2)
        if all(np.hypot(*(p - q)) > 12 for q in pts):
            pts.append(p)
    pts = np.array(pts)
    ra, dec = w.pixel_to_world_values(pts[:, 0], pts[:, 1])
    return np.asarray(ra), np.asarray(dec), pts


def _write(tmp_path, img, name="img.fits"):
    path = tmp_path / name
    fits.PrimaryHDU(img, header=_header()).writeto(path)
    return path


def test_image_estimates_match_true_scatter(tmp_path):
    ra, dec, pts = _targets(60)
    iy, ix = np.rint(pts[:, 1]).astype(int), np.rint(pts[:, 0]).astype(int)
    d2 = (iy[:, None] - iy[None]) ** 2 + (ix[:, None] - ix[None]) ** 2
    truth = np.sqrt(np.exp(-d2 / (4 * S_KER**2)).sum()) / len(ra)
    sims = [np.mean(_noise_image(100 + s)[iy, ix]) for s in range(200)]
    assert np.std(sims) == pytest.approx(truth, rel=0.15)
    psf = tmp_path / "psf.fits"
    fits.PrimaryHDU(_psf()).writeto(psf)
    for seed in (1, 2):
        path = _write(tmp_path, _noise_image(seed), f"n{seed}.fits")
        for method in ("random", "mc", "bootstrap"):
            res = estimate_noise(path, (ra, dec), domain="image", method=method, realizations=300,
                                 primary_beam="none", weighting="none", psf=psf, flux=1.0,
                                 min_separation_arcsec=4.0,
                                 seed=seed)
            assert res.domain == "image"
            assert res.noise_jy == pytest.approx(truth, rel=0.15), (method, seed)
        ana = estimate_noise(path, (ra, dec), domain="image", method="analytic",
                             primary_beam="none", weighting="none")
        assert ana.noise_jy == pytest.approx(truth, rel=0.15)


def test_image_mc_injection_is_exact(tmp_path):
    ra, dec, _ = _targets(10)
    img = _noise_image(5)
    path = _write(tmp_path, img)
    psf = tmp_path / "psf.fits"
    P = _psf()
    fits.PrimaryHDU(P).writeto(psf)
    res = estimate_noise(path, (ra, dec), domain="image", method="mc", realizations=3,
                         primary_beam="none", weighting="none", psf=psf, flux=2.0, seed=3)
    w = WCS(_header())
    for r in range(3):
        x, y = w.world_to_pixel_values(res.positions_deg[r, :, 0], res.positions_deg[r, :, 1])
        iy, ix = np.rint(y).astype(int), np.rint(x).astype(int)
        model = np.zeros_like(img)
        for yy, xx in zip(iy, ix):
            sl_y = slice(max(yy - 50, 0), min(yy + 51, SIZE))
            sl_x = slice(max(xx - 50, 0), min(xx + 51, SIZE))
            model[sl_y, sl_x] += 2.0 * P[sl_y.start - yy + 50:sl_y.stop - yy + 50,
                                         sl_x.start - xx + 50:sl_x.stop - xx + 50]
        assert res.values[r] == pytest.approx(np.mean((img + model)[iy, ix]), rel=1e-10)
    assert np.allclose(res.injected, 2.0)
    with pytest.raises(XstackError, match="PSF"):
        estimate_noise(path, (ra, dec), domain="image", method="mc", realizations=3,
                       primary_beam="none", flux=2.0)
