"""Shared fixtures. Real-data fixtures (pyuvdata's shipped MSs) live in xstack.testing."""

from __future__ import annotations

import numpy as np
import pytest

from xstack.schema import baseline_pairs, new_partition


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def make_partition(n_time: int = 6, n_ant: int = 5, n_chan: int = 4, pols=("XX", "YY"),
                   seed: int = 0, phase_center=(0.9, -0.5), telescope: str = "ALMA",
                   dish: float = 12.0, freq0: float = 230e9, dtype=np.complex64):
    """A small random partition in the xstack schema (numpy-backed)."""
    rng = np.random.default_rng(seed)
    a1, a2 = baseline_pairs(n_ant)
    nbl = a1.size
    shape = (n_time, nbl, n_chan, len(pols))
    vis = (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(dtype)
    enu = rng.normal(scale=200.0, size=(n_ant, 3))
    uvw = np.repeat((enu[a2] - enu[a1])[None], n_time, axis=0)
    uvw += rng.normal(scale=5.0, size=uvw.shape)
    return new_partition(
        visibility=vis, weight=rng.uniform(0.5, 2.0, size=shape).astype(np.float32),
        flag=rng.uniform(size=shape) < 0.05, uvw=uvw,
        time=5e9 + 6.0 * np.arange(n_time), antenna1=a1, antenna2=a2,
        antenna_names=[f"A{i:02d}" for i in range(n_ant)],
        antenna_positions=enu + np.array([2225142.18, -5440307.37, -2481029.85]),
        dish_diameters=np.full(n_ant, dish),
        frequency=freq0 + 1e8 * np.arange(n_chan), channel_width=np.full(n_chan, 1e8),
        polarization=list(pols), phase_center=phase_center, telescope_name=telescope,
        integration_time=6.0,
        # random numbers, not channel averages of a sky: nothing for uvstack to un-smear
        attrs={"smearing": {"bandwidth": False, "time": False}})


@pytest.fixture
def small_partition():
    return make_partition()
