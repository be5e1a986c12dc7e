"""Independent reference implementations for the simulator tests (plain numpy, no numba)."""

from __future__ import annotations

import numpy as np

C = 299_792_458.0

#: A four-antenna VLA-D scene of three 2 mJy targets: seconds to simulate, for CLI tests.
TINY_SCENE = """
name = "tiny"
[array]
config = "vla.d"
antennas = ["W08", "E08", "N08", "W02"]
[observation]
time_per_pointing = 30.0
[spectral]
channels = 3
[effects]
noise = { sigma = 0.01 }
[[populations]]
name = "targets"
count = 3
flux = { kind = "fixed", value = "2mJy" }
positions = { kind = "box", size_arcsec = [60, 60] }
"""


def direct_eq1(uvw, freq, l, m, nm1, flux, attenuation=None, fwhm=None):
    """Equation 1 by brute force: one complex exponential per (row, channel, source)."""
    uvw = np.asarray(uvw, float)
    freq = np.asarray(freq, float)
    lam = C / freq  # (nchan,)
    u, v, w = (uvw[:, i][:, None, None] for i in range(3))
    lk = np.asarray(l, float)[None, None, :]
    mk = np.asarray(m, float)[None, None, :]
    nk = np.zeros_like(lk) if nm1 is None else np.asarray(nm1, float)[None, None, :]
    lamb = lam[None, :, None]
    phase = 2 * np.pi * (u * lk + v * mk + w * nk) / lamb
    amp = np.asarray(flux, float)[None, None, :] * np.ones((1, freq.size, 1))
    if attenuation is not None:
        amp = amp * np.asarray(attenuation, float).T[None, :, :]
    if fwhm is not None:
        r = np.asarray(fwhm, float) / (2 * np.sqrt(np.log(2)))  # the paper's r_k
        q = np.sqrt(u**2 + v**2)
        amp = amp * np.exp(-((np.pi * r[None, None, :] * q / lamb) ** 2))
    return (amp * np.exp(1j * phase)).sum(axis=2)
