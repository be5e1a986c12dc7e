"""Shared builders for the imaging tests: simulated point-source partitions and stores."""

from __future__ import annotations

import numpy as np

from xstack.coords import radec_to_lmn
from xstack.imaging.kernels import point_source_visibilities
from xstack.schema import baseline_pairs, new_partition

PHASE_CENTER = (np.radians(57.29579), np.radians(-30.0))  # near the paper's field center


def synthetic_uvw(n_ant: int = 12, n_time: int = 24, dec0: float = PHASE_CENTER[1],
                  max_baseline: float = 3000.0, hour_span: float = 3.0, seed: int = 0):
    """Earth-rotation uvw (time, baseline, 3) in metres for random antennas, plus pairs."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-max_baseline / 2, max_baseline / 2, size=(n_ant, 3))
    xyz[:, 2] *= 0.2
    a1, a2 = baseline_pairs(n_ant)
    b = xyz[a2] - xyz[a1]
    h = np.radians(15.0 * np.linspace(-hour_span / 2, hour_span / 2, n_time))[:, None]
    sd, cd = np.sin(dec0), np.cos(dec0)
    sh, ch = np.sin(h), np.cos(h)
    x, y, z = b[None, :, 0], b[None, :, 1], b[None, :, 2]
    u = sh * x + ch * y
    v = -sd * ch * x + sd * sh * y + cd * z
    w = cd * ch * x - cd * sh * y + sd * z
    return np.stack([u, v, w], axis=-1), a1, a2, xyz


def make_sky_partition(sources=(), *, n_ant: int = 12, n_time: int = 24, n_chan: int = 4,
                       freq0: float = 1.4e9, chan_width: float = 50e6, pols=("XX", "YY"),
                       noise: float = 0.0, seed: int = 0, phase_center=PHASE_CENTER,
                       max_baseline: float = 3000.0, telescope: str = "VLA", dish: float = 25.0,
                       field_id: int = 0, flag_fraction: float = 0.0, hour_span: float = 3.0,
                       fwhm_arcsec=None, attenuation=None):
    """A partition whose visibilities follow paper eq. 1 for ``sources`` [(ra, dec, flux) rad/Jy].

    Gaussian noise of ``noise`` Jy per real/imaginary part per visibility (weights 1/noise^2).
    """
    rng = np.random.default_rng(seed + 1000)
    uvw, a1, a2, xyz = synthetic_uvw(n_ant, n_time, phase_center[1], max_baseline, hour_span, seed)
    freq = freq0 + chan_width * np.arange(n_chan)
    shape = (n_time, a1.size, n_chan, len(pols))
    vis = np.zeros(shape, dtype=np.complex128)
    if len(sources):
        src = np.asarray(sources, dtype=np.float64)
        l, m, _, n1 = radec_to_lmn(src[:, 0], src[:, 1], *phase_center)
        fw = None if fwhm_arcsec is None else np.radians(np.asarray(fwhm_arcsec) / 3600.0)
        model = point_source_visibilities(uvw.reshape(-1, 3), freq, l, m, n1, src[:, 2],
                                          attenuation=attenuation, fwhm=fw)
        model = model.reshape(n_time, a1.size, n_chan)
        for p, name in enumerate(pols):
            if name.upper() in ("XX", "YY", "RR", "LL", "I"):
                vis[..., p] = model
    if noise > 0:
        vis += noise * (rng.normal(size=shape) + 1j * rng.normal(size=shape))
        weight = np.full(shape, 1.0 / noise**2, dtype=np.float32)
    else:
        weight = np.ones(shape, dtype=np.float32)
    flag = rng.uniform(size=shape) < flag_fraction
    return new_partition(
        visibility=vis.astype(np.complex64), weight=weight, flag=flag, uvw=uvw,
        time=5e9 + 10.0 * np.arange(n_time), antenna1=a1, antenna2=a2,
        antenna_names=[f"A{i:02d}" for i in range(n_ant)],
        antenna_positions=xyz + np.array([-1601185.4, -5041977.5, 3554875.9]),
        dish_diameters=np.full(n_ant, dish), frequency=freq,
        channel_width=np.full(n_chan, chan_width), polarization=list(pols),
        phase_center=phase_center, telescope_name=telescope, integration_time=10.0,
        field_id=field_id,
        # visibilities at channel centers and integration mid-points: not smeared
        attrs={"smearing": {"bandwidth": False, "time": False}})


def offset_position(dra_arcsec: float, ddec_arcsec: float, center=PHASE_CENTER):
    """(ra, dec) radians offset by (east, north) arcsec on the sky from ``center`` (exact)."""
    from astropy import units as u
    from astropy.coordinates import SkyCoord

    c = SkyCoord(center[0] * u.rad, center[1] * u.rad)
    sep = np.hypot(dra_arcsec, ddec_arcsec) * u.arcsec
    pa = np.arctan2(dra_arcsec, ddec_arcsec) * u.rad
    d = c.directional_offset_by(pa, sep)
    return float(d.ra.rad), float(d.dec.rad)
