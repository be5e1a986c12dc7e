"""Shared numba helpers for float64 phases in turns (used by the uvstack and noise kernels).

:func:`cis_minus_turns` evaluates exp(-2 pi i t) for a phase ``t`` in turns. It is
branch-free so that loops calling it vectorise (SIMD over positions), and it is declared
``inline="always"``: numba inlines it at the IR level, so it is compiled with the caller's
``fastmath`` flags, exactly as the private copies it replaces were.
"""

from __future__ import annotations

import math

import numba

# Taylor coefficients of sin(x) (odd, x..x^15) and cos(x) (even, 1..x^16) on |x| <= pi/4:
# the first omitted terms are < 5e-17 there.
_S3, _S5, _S7, _S9 = -1.0 / 6, 1.0 / 120, -1.0 / 5040, 1.0 / 362880
_S11, _S13, _S15 = -1.0 / 39916800, 1.0 / 6227020800, -1.0 / 1307674368000
_C2, _C4, _C6, _C8 = -0.5, 1.0 / 24, -1.0 / 720, 1.0 / 40320
_C10, _C12, _C14, _C16 = -1.0 / 3628800, 1.0 / 479001600, -1.0 / 87178291200, 1.0 / 20922789888000
_TWO_PI = 2.0 * math.pi


@numba.njit(inline="always", fastmath=False)
def cis_minus_turns(t):
    """(cos, -sin)(2 pi t) = exp(-2 pi i t) as a (re, im) pair, ``t`` in turns (|t| < 2^52).

    Exact reduction to s = t - round(t) in [-1/2, 1/2], to the octant x = 2 pi (s - q/4) in
    [-pi/4, pi/4] (exact by Sterbenz), Taylor series there (error < 1e-15), and the quadrant
    rotation by q with exact {-1, 0, 1} factors.
    """
    s = t - math.floor(t + 0.5)
    q = math.floor(4.0 * s + 0.5)  # -2 .. 2
    x = _TWO_PI * (s - 0.25 * q)
    x2 = x * x
    sn = x * (1.0 + x2 * (_S3 + x2 * (_S5 + x2 * (_S7 + x2 * (_S9 + x2 * (_S11 + x2 * (
        _S13 + x2 * _S15)))))))
    cs = 1.0 + x2 * (_C2 + x2 * (_C4 + x2 * (_C6 + x2 * (_C8 + x2 * (_C10 + x2 * (
        _C12 + x2 * (_C14 + x2 * _C16)))))))
    qq = q * q
    cq = 1.0 + qq * (qq - 7.0) / 6.0  # cos(q pi/2), exact for q in -2..2
    sq = q * (4.0 - qq) / 3.0  # sin(q pi/2)
    return cs * cq - sn * sq, -(sn * cq + cs * sq)


# --- per-antenna phasors (the antenna-factorised kernels of xstack.uvstack and xstack.noise) --
# Baseline phasors are E_a1 conj(E_a2) with E_a = exp(-2 pi i nu/c (u_a l + v_a m + w_a (n-1)));
# per integration the kernels keep, per antenna and position, the phase per unit nu/c
# (``turns``), the current channel's E and the channel-step phasor. The helpers work on 1-D
# views of those (nant, npos) arrays: indexing 2-D arrays in the inner loops defeats
# vectorisation.

@numba.njit(inline="always")
def antenna_phases(ant_uvw_t, ant_used_t, l, m, n1, even, step, turns, step_re, step_im):
    """Set up one integration: ``turns`` of every used antenna and, for evenly spaced
    channels, its channel-step phasor exp(-2 pi i turns * step)."""
    for ant in range(ant_uvw_t.shape[0]):
        if not ant_used_t[ant]:
            continue
        u = ant_uvw_t[ant, 0]
        v = ant_uvw_t[ant, 1]
        w = ant_uvw_t[ant, 2]
        ta = turns[ant]
        if even:
            sra = step_re[ant]
            sia = step_im[ant]
            for k in range(ta.shape[0]):
                ta[k] = u * l[k] + v * m[k] + w * n1[k]
                sra[k], sia[k] = cis_minus_turns(ta[k] * step)
        else:
            for k in range(ta.shape[0]):
                ta[k] = u * l[k] + v * m[k] + w * n1[k]


@numba.njit(inline="always")
def antenna_channel(ant_used_t, seed, f, turns, e_re, e_im, step_re, step_im):
    """E of every used antenna at the next channel: evaluated exactly at frequency ``f``
    (per unit c) when ``seed``, else advanced from the previous channel by the step phasor."""
    for ant in range(turns.shape[0]):
        if not ant_used_t[ant]:
            continue
        ta = turns[ant]
        era = e_re[ant]
        eia = e_im[ant]
        if seed:
            for k in range(ta.shape[0]):
                era[k], eia[k] = cis_minus_turns(ta[k] * f)
        else:
            sra = step_re[ant]
            sia = step_im[ant]
            for k in range(ta.shape[0]):
                a = era[k] * sra[k] - eia[k] * sia[k]
                eia[k] = era[k] * sia[k] + eia[k] * sra[k]
                era[k] = a
