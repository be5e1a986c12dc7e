"""Shared helpers for the uv-stacking tests: small partitions with known content."""

from __future__ import annotations

import numpy as np
from dask.callbacks import Callback

from xstack.coords import SPEED_OF_LIGHT, radec_to_lmn
from xstack.schema import baseline_pairs, new_partition

VLA_CENTER = (np.radians(57.29579), np.radians(-30.0))


def antenna_layout(n_ant: int, extent_m: float, rng: np.random.Generator) -> np.ndarray:
    """Random local ENU antenna positions (n_ant, 3) within ``extent_m``."""
    enu = rng.uniform(-extent_m, extent_m, size=(n_ant, 3))
    enu[:, 2] *= 0.01
    return enu


def earth_rotation_uvw(enu: np.ndarray, n_time: int, dec0: float, hours: float = 4.0,
                       lat: float = np.radians(34.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """UVW (n_time, nbl, 3) metres from an ENU layout by the standard hour-angle rotation."""
    a1, a2 = baseline_pairs(len(enu))
    b_enu = enu[a2] - enu[a1]
    # ENU -> equatorial XYZ (local), then rotate by hour angle
    e, n, u = b_enu.T
    x = -np.sin(lat) * n + np.cos(lat) * u
    y = e
    z = np.cos(lat) * n + np.sin(lat) * u
    ha = np.linspace(-hours / 2, hours / 2, n_time) * np.pi / 12
    sh, ch = np.sin(ha)[:, None], np.cos(ha)[:, None]
    sd, cd = np.sin(dec0), np.cos(dec0)
    uu = sh * x + ch * y
    vv = -sd * ch * x + sd * sh * y + cd * z
    ww = cd * ch * x - cd * sh * y + sd * z
    return np.stack([uu, vv, ww], axis=-1), a1, a2


def point_source_vis(uvw: np.ndarray, freq: np.ndarray, ra, dec, flux, phase_center,
                     npol: int = 2) -> np.ndarray:
    """Noiseless eq.-1 visibilities of point sources (integrated flux, no 1/n), complex128."""
    l, m, n, n1 = radec_to_lmn(np.atleast_1d(ra), np.atleast_1d(dec), *phase_center)
    d = uvw @ np.stack([l, m, n1])  # (t, b, nsrc)
    vis = np.zeros(uvw.shape[:2] + (freq.size,), dtype=np.complex128)
    for c, nu in enumerate(freq):
        vis[..., c] = (np.exp(2j * np.pi * d * nu / SPEED_OF_LIGHT) * np.atleast_1d(flux)).sum(-1)
    return np.repeat(vis[..., None], npol, axis=-1)


def make_stack_partition(*, n_ant=8, n_time=20, n_chan=4, freq0=1.4e9, dfreq=25e6,
                         extent_m=2000.0, phase_center=VLA_CENTER, pols=("RR", "LL"),
                         sources=None, sigma=0.0, seed=0, telescope="VLA", dish=25.0,
                         dtype=np.complex128, field_id=0, flag_frac=0.0, weight_scale=None):
    """A partition with point ``sources`` [(ra, dec, flux) radians/Jy] plus Gaussian noise.

    Noise: Re and Im each N(0, sigma^2); WEIGHT = 1/sigma^2 (or ``weight_scale`` when
    noiseless).
    """
    rng = np.random.default_rng(seed)
    enu = antenna_layout(n_ant, extent_m, rng)
    uvw, a1, a2 = earth_rotation_uvw(enu, n_time, phase_center[1])
    freq = freq0 + dfreq * np.arange(n_chan)
    shape = uvw.shape[:2] + (n_chan, len(pols))
    vis = np.zeros(shape, dtype=np.complex128)
    if sources:
        ra, dec, flux = (np.array(x, dtype=float) for x in zip(*sources))
        vis += point_source_vis(uvw, freq, ra, dec, flux, phase_center, len(pols))
    if sigma > 0:
        vis += sigma * (rng.normal(size=shape) + 1j * rng.normal(size=shape))
        weight = np.full(shape, 1.0 / sigma**2)
    else:
        weight = (rng.uniform(0.5, 2.0, size=shape) if weight_scale is None
                  else np.full(shape, weight_scale))
    flag = rng.uniform(size=shape) < flag_frac
    return new_partition(
        visibility=vis.astype(dtype), weight=weight.astype(np.float32), flag=flag, uvw=uvw,
        time=5e9 + 10.0 * np.arange(n_time), antenna1=a1, antenna2=a2,
        antenna_names=[f"ea{i:02d}" for i in range(n_ant)],
        antenna_positions=enu + np.array([-1601185.4, -5041977.5, 3554875.9]),
        dish_diameters=np.full(n_ant, dish), frequency=freq,
        channel_width=np.full(n_chan, dfreq), polarization=list(pols),
        phase_center=phase_center, telescope_name=telescope, integration_time=10.0,
        field_id=field_id, field_name=f"field{field_id}",
        # visibilities at channel centers and integration mid-points: not smeared
        attrs={"smearing": {"bandwidth": False, "time": False}})


def direct_eq4(uvw_rows, freq, l, m, n, weight, inv_att):
    """Independent eq. 4: unit vectors, B.(S0 - Sk), literal sum over k (slow, exact)."""
    s0 = np.array([0.0, 0.0, 1.0])
    out = np.zeros((uvw_rows.shape[0], freq.size), dtype=np.complex128)
    for k in range(len(l)):
        sk = np.array([l[k], m[k], n[k]])
        proj = uvw_rows @ (s0 - sk)  # = -(u l + v m + w (n - 1))
        for c, nu in enumerate(freq):
            out[:, c] += weight[k] * inv_att[k, c] * np.exp(2j * np.pi * proj * nu / SPEED_OF_LIGHT)
    return out / np.sum(weight)


class CountVisibilityReads(Callback):
    """Counts the executed tasks that produce VISIBILITY chunks (dask's local schedulers)."""

    def __init__(self) -> None:
        super().__init__()
        self.reads = 0

    def _posttask(self, key, result, dsk, state, id):
        if "VISIBILITY" in str(key[0] if isinstance(key, tuple) else key):
            self.reads += 1
