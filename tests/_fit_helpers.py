"""Test data for the fit and noise stages, built independently of xstack.sim/uvstack.

Visibilities are written with plain numpy from the paper's equation 1 (sign convention of
docs/conventions.md), so the tests do not depend on the code under test.
"""

from __future__ import annotations

import numpy as np

from xstack.schema import baseline_pairs, new_partition

C = 299_792_458.0
ARCSEC = np.pi / 180 / 3600
GK = np.pi**2 / (4 * np.log(2))


def uv_coverage(n_ant: int = 12, n_time: int = 20, extent_m: float = 20e3, seed: int = 0,
                hours: float = 8.0, dec: float = -0.5236) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Earth-rotation uv tracks of a random array; returns (uvw (t, bl, 3), a1, a2)."""
    rng = np.random.default_rng(seed)
    # a Y-shaped array with logarithmic arm spacing, like the VLA
    arms = np.repeat(np.radians([0.0, 120.0, 240.0]), int(np.ceil(n_ant / 3)))[:n_ant]
    r = extent_m * np.geomspace(0.02, 1.0, n_ant) * rng.uniform(0.8, 1.0, n_ant)
    xyz = np.stack([r * np.cos(arms), r * np.sin(arms), rng.normal(0, 5.0, n_ant)], axis=1)
    a1, a2 = baseline_pairs(n_ant)
    b = xyz[a2] - xyz[a1]
    h = np.linspace(-hours / 2, hours / 2, n_time) * np.pi / 12
    sd, cd = np.sin(dec), np.cos(dec)
    uvw = np.empty((n_time, a1.size, 3))
    for i, hh in enumerate(h):
        sh, ch = np.sin(hh), np.cos(hh)
        uvw[i, :, 0] = sh * b[:, 0] + ch * b[:, 1]
        uvw[i, :, 1] = -sd * ch * b[:, 0] + sd * sh * b[:, 1] + cd * b[:, 2]
        uvw[i, :, 2] = cd * ch * b[:, 0] - cd * sh * b[:, 1] + sd * b[:, 2]
    return uvw, a1, a2


def partition_from(vis: np.ndarray, weight: np.ndarray, uvw: np.ndarray, a1, a2, freq,
                   phase_center=(1.0, -0.5236), flag=None, pols=("RR", "LL"),
                   telescope="VLA", dish=25.0, attrs=None):
    """Wrap numpy arrays into an xstack partition."""
    n_time = vis.shape[0]
    n_ant = int(max(a1.max(), a2.max()) + 1)
    return new_partition(
        visibility=vis, weight=weight.astype(np.float32),
        flag=np.zeros(vis.shape, bool) if flag is None else flag, uvw=uvw,
        time=5e9 + 10.0 * np.arange(n_time), antenna1=a1, antenna2=a2,
        antenna_names=[f"A{i:02d}" for i in range(n_ant)],
        antenna_positions=np.zeros((n_ant, 3)) + np.array([-1601185.0, -5041977.0, 3554875.0]),
        dish_diameters=np.full(n_ant, dish), frequency=np.asarray(freq, float),
        channel_width=np.full(len(freq), 1e6), polarization=list(pols),
        phase_center=phase_center, telescope_name=telescope, integration_time=10.0,
        attrs=attrs)


def gaussian_stack(flux: float, fwhm_arcsec: float, sigma: float, seed: int, *,
                   n_ant: int = 12, n_time: int = 20, freq=(1.3e9, 1.4e9, 1.5e9, 1.6e9),
                   extent_m: float = 20e3, coverage_seed: int = 0):
    """A 'stacked' partition: a circular Gaussian at the phase center plus Gaussian noise of
    rms ``sigma`` per real/imaginary part (weights 1/sigma^2)."""
    uvw, a1, a2 = uv_coverage(n_ant, n_time, extent_m, seed=coverage_seed)
    freq = np.asarray(freq, float)
    q2 = (uvw[..., 0] ** 2 + uvw[..., 1] ** 2)[..., None] * (freq / C) ** 2
    model = flux * np.exp(-GK * (fwhm_arcsec * ARCSEC) ** 2 * q2)
    rng = np.random.default_rng(seed)
    shape = q2.shape + (2,)
    vis = model[..., None] + sigma * (rng.normal(size=shape) + 1j * rng.normal(size=shape))
    weight = np.full(shape, 1.0 / sigma**2)
    return partition_from(vis.astype(np.complex128), weight, uvw, a1, a2, freq)


def lmn(ra, dec, ra0, dec0):
    """Direction cosines, written out independently of xstack.coords."""
    l = np.cos(dec) * np.sin(ra - ra0)
    m = np.sin(dec) * np.cos(dec0) - np.cos(dec) * np.sin(dec0) * np.cos(ra - ra0)
    n = np.sqrt(1 - l * l - m * m)
    return l, m, n - 1


def point_sources_vis(uvw, freq, ra, dec, flux, center, atten=None, fwhm_arcsec=None):
    """Equation 1 summed over sources: (t, bl, chan) complex, plain numpy."""
    l, m, n1 = lmn(np.asarray(ra), np.asarray(dec), *center)
    out = np.zeros(uvw.shape[:2] + (len(freq),), complex)
    flux = np.broadcast_to(flux, l.shape)
    for k in range(l.size):
        d = uvw[..., 0] * l[k] + uvw[..., 1] * m[k] + uvw[..., 2] * n1[k]
        ph = np.exp(2j * np.pi * d[..., None] * np.asarray(freq) / C)
        amp = flux[k] * (1.0 if atten is None else atten[k])
        if fwhm_arcsec is not None:
            q2 = (uvw[..., 0] ** 2 + uvw[..., 1] ** 2)[..., None] * (np.asarray(freq) / C) ** 2
            ph = ph * np.exp(-GK * (fwhm_arcsec * ARCSEC) ** 2 * q2)
        out += amp * ph
    return out


def stack_flux(vis, weight, uvw, freq, ra, dec, center, inv_att=None):
    """Reference uv-stack (eq. 4 + weighted mean of Re V over both hands), plain numpy.

    vis, weight: (t, bl, chan, pol); inv_att: (K, chan) or None."""
    l, m, n1 = lmn(np.asarray(ra), np.asarray(dec), *center)
    P = np.zeros(uvw.shape[:2] + (len(freq),), complex)
    for k in range(l.size):
        d = uvw[..., 0] * l[k] + uvw[..., 1] * m[k] + uvw[..., 2] * n1[k]
        ph = np.exp(-2j * np.pi * d[..., None] * np.asarray(freq) / C)
        P += ph * (1.0 if inv_att is None else inv_att[k])
    P /= l.size
    return float(np.sum(weight * (vis * P[..., None]).real) / np.sum(weight))


def noise_field(seed, *, n_ant=10, n_time=12, freq=(1.35e9, 1.4e9, 1.45e9), sigma=1.0,
                extent_m=3e3, extra_vis=None):
    """Pure-noise VLA-like partition (1.4 GHz, 25 m dishes), optional extra model vis."""
    uvw, a1, a2 = uv_coverage(n_ant, n_time, extent_m, seed=0)
    freq = np.asarray(freq, float)
    rng = np.random.default_rng(seed)
    shape = uvw.shape[:2] + (freq.size, 2)
    vis = sigma * (rng.normal(size=shape) + 1j * rng.normal(size=shape))
    if extra_vis is not None:
        vis = vis + extra_vis[..., None]
    return partition_from(vis, np.full(shape, 1 / sigma**2), uvw, a1, a2, freq), uvw, freq


class StampSimulator:
    """Dirty-image stamps by direct Fourier sums (natural weighting), independent of xstack.

    ``stamp(flux, fwhm, seed)`` = dirty image of a circular Gaussian at the center plus the
    dirty image of white visibility noise; ``psf`` = the dirty beam on a grid twice as big.
    """

    def __init__(self, n_ant=12, n_time=10, freq=(1.4e9, 1.5e9), extent_m=20e3, size=33,
                 pixel_arcsec=0.5, sigma=1.0):
        uvw, _, _ = uv_coverage(n_ant, n_time, extent_m, seed=0)
        f = np.asarray(freq, float)
        u = (uvw[..., 0][..., None] * f / C).ravel()
        v = (uvw[..., 1][..., None] * f / C).ravel()
        self.u, self.v, self.sigma, self.size, self.pix = u, v, sigma, size, pixel_arcsec
        self.q2 = u * u + v * v
        off = (np.arange(size) - size // 2) * pixel_arcsec * ARCSEC
        ph = 2 * np.pi * (off[:, None, None] * v[None, None, :] + off[None, :, None] * u[None, None, :])
        self.cos = np.cos(ph).reshape(size * size, -1)
        self.sin = np.sin(ph).reshape(size * size, -1)
        big = 2 * size + 1
        off2 = (np.arange(big) - big // 2) * pixel_arcsec * ARCSEC
        ph2 = 2 * np.pi * (off2[:, None, None] * v[None, None, :] + off2[None, :, None] * u[None, None, :])
        self.psf = np.cos(ph2).mean(axis=-1)

    def stamp(self, flux, fwhm_arcsec, seed):
        rng = np.random.default_rng(seed)
        vis = flux * np.exp(-GK * (fwhm_arcsec * ARCSEC) ** 2 * self.q2) + 0j
        vis = vis + self.sigma * (rng.normal(size=vis.size) + 1j * rng.normal(size=vis.size))
        # I(x) = mean Re(V exp(+2 pi i (u l + v m)))
        img = (self.cos @ vis.real - self.sin @ vis.imag) / vis.size
        return img.reshape(self.size, self.size)


def write_stamp_fits(sim: StampSimulator, img: np.ndarray, path) -> None:
    """Write a stacked stamp of ``sim`` (0.5" pixels, SIN, centered) with its PSF as an HDU."""
    from astropy.io import fits

    hdr = fits.Header({"CTYPE1": "RA---SIN", "CTYPE2": "DEC--SIN", "CDELT1": -0.5 / 3600,
                       "CDELT2": 0.5 / 3600, "CRPIX1": sim.size // 2 + 1,
                       "CRPIX2": sim.size // 2 + 1, "CRVAL1": 57.0, "CRVAL2": -30.0,
                       "CUNIT1": "deg", "CUNIT2": "deg"})
    fits.HDUList([fits.PrimaryHDU(img, header=hdr), fits.ImageHDU(sim.psf, name="PSF")]).writeto(path)


def assert_fits_recover(f, fe, t, te, flux: float, fwhm: float) -> None:
    """Over realisations: flux and FWHM within 2 reported sigma in >= 90 %, reported errors
    matching the scatter within 15 %, flux unbiased within the scatter of the mean."""
    assert np.mean(np.abs(f - flux) < 2 * fe) >= 0.9
    assert np.mean(np.abs(t - fwhm) < 2 * te) >= 0.9
    assert abs(np.mean(fe) / np.std(f) - 1.0) <= 0.15
    assert abs(np.mean(te) / np.std(t) - 1.0) <= 0.15
    assert abs(np.mean(f) - flux) <= 3 * np.std(f) / np.sqrt(f.size)
