"""Bandwidth and time-average smearing factors: one definition for the simulator and stacking.

Plain numpy + numba (no dask, no xarray). Conventions of ``docs/conventions.md``: with
(u, v, w) as stored in an MS (metres) a point source at (l, m) has the visibility
``V = S exp(+2 pi i d nu / c)`` with the delay ``d = u l + v m + w (n - 1)`` in metres.

Bandwidth smearing
    Averaging V over a rectangular channel of width ``dnu`` (a flat bandpass) multiplies it
    by ``sinc(pi d dnu / c)``, ``sinc(x) = sin(x) / x``: exact, since d (metres) does not
    depend on frequency.

Time-average smearing
    Earth rotation changes (u, v, w) at (hour angle rate ``omega``, phase-center declination
    ``dec0``)::

        du/dt = omega (w cos dec0 - v sin dec0)
        dv/dt = omega u sin dec0
        dw/dt = -omega u cos dec0

    so the delay drifts at ``d' = du/dt l + dv/dt m + dw/dt (n - 1)`` (m/s) and, to first
    order in the integration ``dt``, averaging over the integration multiplies V by
    ``sinc(pi nu d' dt / c)`` (= sinc(dphi/dt dt / 2)).

The w-term is part of d and d' only when ``n_minus_1`` is given (``None``: left out, as the
simulator does without ``effects.w_term``). Gaussian sources get the same factors (their
Gaussian factor varies slowly over a channel or an integration compared with the phase).
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from xstack._cluster import cap_numba_threads
from xstack.coords import SPEED_OF_LIGHT

#: Earth's rotation rate (rad per SI second), the rate of change of the hour angle.
EARTH_ROTATION_RATE = 7.2921150e-5

#: Names of the two effects (scene flags ``effects.bandwidth_smearing``/``time_smearing``,
#: keys of the partition attribute ``smearing``).
EFFECTS = ("bandwidth", "time")


@numba.njit(nogil=True, cache=True)
def sinc(x: float) -> float:
    """sin(x) / x, 1 at x = 0 (series below |x| < 1e-4, relative error < 1e-17)."""
    if abs(x) < 1e-4:
        return 1.0 - x * x / 6.0
    return math.sin(x) / x


@numba.njit(nogil=True, cache=True)
def delay_rate_scalar(u: float, v: float, w: float, l: float, m: float, nm1: float,
                      sin_dec0: float, cos_dec0: float) -> float:
    """d(delay)/dt in m/s of one baseline (u, v, w) for one direction (l, m, n - 1)."""
    du = EARTH_ROTATION_RATE * (w * cos_dec0 - v * sin_dec0)
    dv = EARTH_ROTATION_RATE * u * sin_dec0
    dw = -EARTH_ROTATION_RATE * u * cos_dec0
    return du * l + dv * m + dw * nm1


@numba.njit(nogil=True, cache=True)
def factor_scalar(delay: float, rate: float, frequency: float, width: float,
                  integration: float) -> float:
    """Bandwidth times time smearing factor of one visibility.

    ``delay`` (m), ``rate`` (m/s), ``frequency`` and ``width`` (Hz), ``integration`` (s);
    a zero ``width`` or ``integration`` leaves that effect out.
    """
    f = 1.0
    if width != 0.0:
        f *= sinc(math.pi * delay * width / SPEED_OF_LIGHT)
    if integration != 0.0:
        f *= sinc(math.pi * frequency * rate * integration / SPEED_OF_LIGHT)
    return f


def _as_rows(uvw: Any) -> np.ndarray:
    uvw = np.asarray(uvw, dtype=np.float64)
    if uvw.ndim != 2 or uvw.shape[1] != 3:
        raise ValueError(f"uvw must have shape (nrow, 3), got {uvw.shape}")
    return uvw


def delays(uvw: Any, l: Any, m: Any, n_minus_1: Any = None) -> np.ndarray:
    """Delays ``d = u l + v m + w (n - 1)`` (nrow, npos), metres.

    Parameters
    ----------
    uvw
        (nrow, 3) baseline coordinates, metres, as in an MS.
    l, m
        (npos,) direction cosines.
    n_minus_1
        (npos,) ``n - 1`` or ``None`` (no w-term).
    """
    uvw = _as_rows(uvw)
    l, m = np.atleast_1d(np.asarray(l, np.float64)), np.atleast_1d(np.asarray(m, np.float64))
    d = uvw[:, :1] * l[None, :] + uvw[:, 1:2] * m[None, :]
    if n_minus_1 is not None:
        d = d + uvw[:, 2:3] * np.atleast_1d(np.asarray(n_minus_1, np.float64))[None, :]
    return d


def delay_rates(uvw: Any, l: Any, m: Any, n_minus_1: Any, dec0: float) -> np.ndarray:
    """Earth-rotation rate of the delays (nrow, npos), m/s (see the module docstring).

    Parameters
    ----------
    uvw
        (nrow, 3) baseline coordinates, metres.
    l, m, n_minus_1
        (npos,) direction cosines and ``n - 1`` (``None``: no w-term).
    dec0
        Declination of the phase center, radians.
    """
    uvw = _as_rows(uvw)
    u, v, w = uvw[:, 0:1], uvw[:, 1:2], uvw[:, 2:3]
    s, c = math.sin(dec0), math.cos(dec0)
    l, m = np.atleast_1d(np.asarray(l, np.float64)), np.atleast_1d(np.asarray(m, np.float64))
    rate = EARTH_ROTATION_RATE * ((w * c - v * s) * l[None, :] + u * s * m[None, :])
    if n_minus_1 is not None:
        nm1 = np.atleast_1d(np.asarray(n_minus_1, np.float64))
        rate = rate - EARTH_ROTATION_RATE * u * c * nm1[None, :]
    return rate


def smearing_factors(uvw: Any, frequency: Any, channel_width: Any, integration_time: float,
                     l: Any, m: Any, n_minus_1: Any, dec0: float, *, bandwidth: bool = True,
                     time: bool = True) -> np.ndarray:
    """Smearing factors (nrow, npos, nchan) of point sources (numpy reference).

    Parameters
    ----------
    uvw
        (nrow, 3) baseline coordinates, metres.
    frequency, channel_width
        (nchan,) channel centers and widths, Hz.
    integration_time
        Integration (averaging) time, s.
    l, m, n_minus_1
        (npos,) direction cosines and ``n - 1`` (``None``: no w-term).
    dec0
        Phase-center declination, radians.
    bandwidth, time
        Which effects to include.

    Returns
    -------
    numpy.ndarray
        The factor multiplying each visibility, dimensionless (1 = no loss).
    """
    freq = np.atleast_1d(np.asarray(frequency, np.float64))
    width = np.broadcast_to(np.asarray(channel_width, np.float64), freq.shape)
    d = delays(uvw, l, m, n_minus_1)
    out = np.ones(d.shape + (freq.size,))
    if bandwidth:
        out *= np.sinc(d[..., None] * width / SPEED_OF_LIGHT)  # numpy sinc(x) = sin(pi x)/(pi x)
    if time and integration_time:
        rate = delay_rates(uvw, l, m, n_minus_1, dec0)
        out *= np.sinc(rate[..., None] * freq * float(integration_time) / SPEED_OF_LIGHT)
    return out


@numba.njit(nogil=True, cache=True)
def _sinc_from_sin(s: float, x: float) -> float:
    if abs(x) < 1e-4:
        return 1.0 - x * x / 6.0
    return s / x


@numba.njit(nogil=True, parallel=True, cache=True)
def _mean_factors(u, v, w, wt, l, m, nm1, freq, width, dt, sin_d, cos_d, uniform, out):
    """out[k, c] = sum_r wt[r, c] f_k(r, c) (the caller divides by sum_r wt[r, c]).

    ``uniform``: equally spaced channels of one width; the bandwidth factor is then one sin
    per (row, position) and the time factor's sin(x0 + c dx) follows by complex rotation
    (re-synchronised every 32 channels), as the simulator's phasors do.
    """
    npos = l.size
    nchan = freq.size
    inv_c = math.pi / SPEED_OF_LIGHT
    df = freq[1] - freq[0] if nchan > 1 else 0.0
    for k in numba.prange(npos):
        acc = np.zeros(nchan)
        for r in range(u.size):
            d = u[r] * l[k] + v[r] * m[k] + w[r] * nm1[k]
            rate = 0.0
            if dt != 0.0:
                rate = delay_rate_scalar(u[r], v[r], w[r], l[k], m[k], nm1[k], sin_d, cos_d)
            if uniform:
                fb = 1.0
                if width[0] != 0.0:
                    fb = sinc(d * width[0] * inv_c)
                if dt == 0.0:
                    for c in range(nchan):
                        acc[c] += wt[r, c] * fb
                    continue
                kk = rate * dt * inv_c  # x_c = kk * freq[c]
                z = complex(math.cos(kk * freq[0]), math.sin(kk * freq[0]))
                step = complex(math.cos(kk * df), math.sin(kk * df))
                for c in range(nchan):
                    if c > 0 and c % 32 == 0:
                        z = complex(math.cos(kk * freq[c]), math.sin(kk * freq[c]))
                    acc[c] += wt[r, c] * fb * _sinc_from_sin(z.imag, kk * freq[c])
                    z = z * step
            else:
                for c in range(nchan):
                    acc[c] += wt[r, c] * factor_scalar(d, rate, freq[c], width[c], dt)
        for c in range(nchan):
            out[k, c] = acc[c]


def mean_factors(uvw: Any, weight: Any, frequency: Any, channel_width: Any,
                 integration_time: float, l: Any, m: Any, n_minus_1: Any, dec0: float, *,
                 bandwidth: bool = True, time: bool = True) -> np.ndarray:
    """Weighted mean smearing factor per position and channel (npos, nchan).

    ``L[k, c] = sum_r weight[r, c] f_k(r, c) / sum_r weight[r, c]``: the fraction of a point
    source's flux at position k that survives in channel c of a weighted mean of its
    visibilities (1 where the weights are all zero).

    Parameters
    ----------
    uvw
        (nrow, 3) baseline coordinates, metres.
    weight
        (nrow, nchan) non-negative weights (0 for flagged visibilities).
    frequency, channel_width
        (nchan,) Hz.
    integration_time
        s.
    l, m, n_minus_1
        (npos,) direction (``n_minus_1`` ``None``: no w-term).
    dec0
        Phase-center declination, radians.
    bandwidth, time
        Which effects to include (both ``False``: all ones).

    Returns
    -------
    numpy.ndarray
        (npos, nchan) float64, dimensionless.
    """
    uvw = _as_rows(uvw)
    freq = np.ascontiguousarray(np.atleast_1d(frequency), dtype=np.float64)
    width = np.ascontiguousarray(np.broadcast_to(np.asarray(channel_width, np.float64),
                                                 freq.shape)) if bandwidth \
        else np.zeros(freq.size)
    dt = float(integration_time) if time else 0.0
    l = np.ascontiguousarray(np.atleast_1d(l), dtype=np.float64)
    m = np.ascontiguousarray(np.atleast_1d(m), dtype=np.float64)
    nm1 = np.zeros(l.size) if n_minus_1 is None else \
        np.ascontiguousarray(np.atleast_1d(n_minus_1), dtype=np.float64)
    wt = np.broadcast_to(np.asarray(weight, np.float64), (uvw.shape[0], freq.size))
    keep = np.any(wt > 0, axis=1)  # rows without weight cost nothing
    wt = np.ascontiguousarray(np.where(wt[keep] > 0, wt[keep], 0.0))
    uvw = uvw[keep]
    out = np.ones((l.size, freq.size))
    den = wt.sum(axis=0)
    if l.size == 0 or uvw.shape[0] == 0 or (not np.any(width) and dt == 0.0):
        return out
    order = np.argsort(freq, kind="stable")
    fs, ws = np.ascontiguousarray(freq[order]), np.ascontiguousarray(width[order])
    uniform = bool(fs.size < 2 or (np.all(ws == ws[0]) and np.all(
        np.abs(np.diff(fs) - (fs[1] - fs[0])) <= 1e-9 * np.abs(fs[1:]))))
    acc = np.zeros((l.size, freq.size))
    cap_numba_threads()
    _mean_factors(np.ascontiguousarray(uvw[:, 0]), np.ascontiguousarray(uvw[:, 1]),
                  np.ascontiguousarray(uvw[:, 2]), np.ascontiguousarray(wt[:, order]), l, m,
                  nm1, fs, ws, dt, math.sin(dec0), math.cos(dec0), uniform, acc)
    acc[:, order] = acc.copy()
    good = den > 0
    out[:, good] = acc[:, good] / den[good]
    return out


def approximate_loss(baseline_m: float, offset_rad: float, frequency_hz: float,
                     channel_width_hz: float = 0.0, integration_s: float = 0.0) -> float:
    """Order-of-magnitude loss ``1 - factor`` of a baseline of length q for a source θ off axis.

    Bandwidth: 1 - sinc(π Δν θ q / c) ≈ (π Δν θ q / c)² / 6 (the delay at most θ q);
    time: 1 - sinc(π ν ω θ q Δt / c) (the delay rate at most ω θ q). Worst-case orientation,
    a guide for docs and warnings, not the correction.

    Parameters
    ----------
    baseline_m
        Baseline length q, metres.
    offset_rad
        Distance θ of the source from the phase center, radians.
    frequency_hz, channel_width_hz
        Hz.
    integration_s
        s.
    """
    xb = math.pi * channel_width_hz * offset_rad * baseline_m / SPEED_OF_LIGHT
    xt = math.pi * frequency_hz * EARTH_ROTATION_RATE * offset_rad * baseline_m \
        * integration_s / SPEED_OF_LIGHT
    return 1.0 - float(sinc(xb)) * float(sinc(xt))
