"""uv-stacking kernels: the phasor against independent evaluations, and its precision."""

from __future__ import annotations

import numpy as np
import pytest
from _uvstack_helpers import direct_eq4

from xstack.coords import SPEED_OF_LIGHT, radec_to_lmn
from xstack.uvstack import kernels as K


def _random_problem(rng, nrow=300, nsrc=37, nchan=7, scale=3000.0, field=0.01, freq0=1.4e9):
    uvw = rng.normal(scale=scale, size=(nrow, 3))
    ra = 1.0 + rng.uniform(-field, field, nsrc)
    dec = -0.5 + rng.uniform(-field, field, nsrc)
    l, m, n, n1 = radec_to_lmn(ra, dec, 1.0, -0.5)
    freq = freq0 + 7.3e6 * np.arange(nchan)
    w = rng.uniform(0.1, 2.0, nsrc)
    ia = rng.uniform(1.0, 3.0, (nsrc, nchan))
    return uvw, freq, l, m, n, n1, w, ia


@pytest.mark.parametrize("engine", ["numba", "numpy", "nufft"])
def test_phasor_equals_independent_eq4(rng, engine):
    # compact field and baselines keep the nufft grid small
    uvw, freq, l, m, n, n1, w, ia = _random_problem(rng, scale=300.0, field=0.003)
    want = direct_eq4(uvw, freq, l, m, n, w, ia)
    got = K.stack_phasor(uvw, freq, l, m, n1, w, ia, engine=engine)
    assert got.dtype == np.complex128 and got.shape == want.shape
    tol = 1e-9 if engine == "nufft" else 1e-10  # the reference carries ~1e-12 phase rounding
    assert np.max(np.abs(got - want)) < tol * np.max(np.abs(want))


def test_single_position_is_plain_phase_shift(rng):
    uvw, freq, l, m, n, n1, w, ia = _random_problem(rng, nsrc=1)
    got = K.stack_phasor(uvw, freq, l, m, n1, [3.7], np.ones((1, freq.size)))
    d = uvw[:, 0] * l[0] + uvw[:, 1] * m[0] + uvw[:, 2] * n1[0]
    want = np.exp(-2j * np.pi * d[:, None] * freq[None, :] / SPEED_OF_LIGHT)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("reseed", [1, 4, 64])
def test_recurrence_error_bounded(rng, reseed):
    """256 evenly spaced channels, huge phases: the recurrence error stays ~1e-13 at most."""
    uvw, freq, l, m, n, n1, w, ia = _random_problem(rng, nrow=50, nsrc=5, nchan=256,
                                                    scale=30000.0, field=0.05)
    ia = np.ones_like(ia)
    exact = K.stack_phasor(uvw, freq, l, m, n1, w, ia, reseed=1)
    got = K.stack_phasor(uvw, freq, l, m, n1, w, ia, reseed=reseed)
    want = direct_eq4(uvw, freq, l, m, n, w, ia)
    # the reference itself carries float64 phase rounding of ~|phase| * 1e-16
    max_phase = 2 * np.pi * np.max(np.abs(uvw)) * 3 * 0.05 * freq[-1] / SPEED_OF_LIGHT
    phase_floor = 4 * max_phase * 2.2e-16  # float64 rounding of a ~1e5 rad phase: ~1e-10
    assert np.max(np.abs(exact - want)) < phase_floor
    # the recurrence adds a few 1e-16 per step on top of the float64 phase rounding
    assert np.max(np.abs(got - want)) < phase_floor + reseed * 1e-15


def test_uneven_channels_use_exact_seeds(rng):
    uvw, freq, l, m, n, n1, w, ia = _random_problem(rng, nchan=6)
    freq = freq + np.array([0, 3e3, -2e4, 0, 5e5, 1.0])
    want = direct_eq4(uvw, freq, l, m, n, w, ia)
    got = K.stack_phasor(uvw, freq, l, m, n1, w, ia)
    assert np.max(np.abs(got - want)) < 1e-10 * np.max(np.abs(want))


def test_float64_phase_holds_where_float32_fails(rng):
    """ALMA-like 16 km baselines at 900 GHz, a position 2' off: ~1e5 rad phases."""
    nrow = 200
    uvw = rng.uniform(-16000, 16000, size=(nrow, 3))
    freq = np.array([900e9])
    l, m, n, n1 = radec_to_lmn(np.array([1.0 + 5.8e-4]), np.array([-0.5 + 2e-4]), 1.0, -0.5)
    w, ia = np.ones(1), np.ones((1, 1))
    # exact phase in extended precision (longdouble) as the truth
    d = (uvw.astype(np.longdouble) @ np.stack([l, m, n1]).astype(np.longdouble))[:, 0]
    turns = d * np.longdouble(freq[0]) / np.longdouble(SPEED_OF_LIGHT)
    frac = (turns - np.round(turns)).astype(np.float64)
    truth = np.exp(-2j * np.pi * frac)
    p64 = K.stack_phasor(uvw, freq, l, m, n1, w, ia)[:, 0]
    args32 = (x.astype(np.float32) for x in (uvw, freq, l, m, n1))
    p32 = K.stack_phasor(*args32, w, ia)[:, 0]
    err64 = np.max(np.abs(np.angle(p64 / truth)))
    err32 = np.max(np.abs(np.angle(p32 / truth)))
    assert np.max(np.abs(turns)) > 1e4  # the hard regime: > 6e4 rad
    assert err64 < 1e-6
    assert err32 > 1e-3


def test_cis_polynomial_accuracy():
    t = np.concatenate([np.linspace(-3, 3, 100001), np.array([1e6 + 0.123, -2.5e7 + 0.7])])
    re = np.empty_like(t)
    im = np.empty_like(t)
    for i, x in enumerate(t):
        re[i], im[i] = K._cis_minus_turns(x)
    frac = t - np.round(t)
    want = np.exp(-2j * np.pi * frac)
    assert np.max(np.abs(re + 1j * im - want)) < 5e-16


def test_weighted_sums_ignore_flagged_nan(rng):
    vis = rng.normal(size=(10, 3, 2)) + 1j * rng.normal(size=(10, 3, 2))
    wt = rng.uniform(0.5, 2, size=vis.shape)
    flag = rng.uniform(size=vis.shape) < 0.3
    vis[flag] = np.nan
    ph = np.exp(1j * rng.uniform(0, 6, size=(10, 3)))
    swv, sw = K.weighted_sums(vis, wt, flag, ph)
    good = ~flag
    vp = vis * ph[:, :, None]
    assert np.isfinite(swv)
    np.testing.assert_allclose(swv, np.sum(wt[good] * vp[good].real), rtol=1e-12)
    np.testing.assert_allclose(sw, np.sum(wt[good]), rtol=1e-12)


def test_zero_weight_sum_rejected():
    with pytest.raises(ValueError, match="not positive"):
        K.normalised_coefficients(np.zeros(3), np.ones((3, 2)), 2)


def test_nufft_refuses_huge_grid(rng):
    uvw, freq, l, m, n, n1, w, ia = _random_problem(rng, scale=30000.0, field=0.05)
    with pytest.raises(MemoryError, match="numba"):
        K.stack_phasor(uvw, freq, l, m, n1, w, ia, engine="nufft")


@pytest.mark.parametrize("dtype", [np.complex64, np.complex128])
@pytest.mark.parametrize("with_phasor", [True, False])
def test_compiled_sums_equal_numpy(rng, dtype, with_phasor):
    shape = (50, 4, 4)
    vis = (rng.normal(size=shape) + 1j * rng.normal(size=shape)).astype(dtype)
    wt = rng.uniform(0, 2, size=shape).astype(np.float32)
    wt[0] = 0.0
    flag = rng.uniform(size=shape) < 0.2
    vis[flag & (rng.uniform(size=shape) < 0.5)] = np.nan
    ph = np.exp(1j * rng.uniform(0, 6, size=shape[:2])) * rng.uniform(0.5, 1, size=shape[:2])
    ph = ph if with_phasor else None
    pol = np.array([True, False, False, True])
    uvm = rng.uniform(size=shape[:2]) < 0.7
    for kw in ({}, {"pol_mask": pol}, {"pol_mask": pol, "uv_mask": uvm}):
        got = K.stack_sums(vis, wt, flag, ph, **kw)
        want = K.stack_sums_numpy(vis, wt, flag, ph, **kw)
        np.testing.assert_allclose(got, want, rtol=1e-12)
        assert got[4] > 0
