"""Model-visibility kernels: the paper's equation 1, in plain numpy + numba (no dask, no xarray).

For rows (u, v, w) in metres, as stored in a MeasurementSet, and channels of frequency nu::

    V(row, chan) = sum_k A_k(chan) S_k G_k(q, nu) exp(+2 pi i (u l_k + v m_k + w (n_k - 1)) nu / c)

    G_k = exp(-pi^2 theta_k^2 q^2 nu^2 / (4 ln 2 c^2)),   q^2 = u^2 + v^2

``theta_k`` is the full width at half maximum of a circular Gaussian source (radians); the
paper's r_k is ``theta_k / (2 sqrt(ln 2))``. The paper divides by n_k; we do not: catalog
fluxes are integrated flux densities, and the 1/n factor belongs to the image-plane brightness
(it differs from 1 by < 1e-5 within a VLA L-band primary beam). See ``docs/sim.md``.

Work that a call does not need is not done: no w-term arithmetic when ``n_minus_1`` is
``None``; no Gaussian factor for point sources (``fwhm`` ``None`` or 0); no phasors at all for
point sources at the phase center (their visibilities are the constant sum of their fluxes).
Which of these steps ran is counted in :data:`STEP_COUNTS` (see :func:`record_steps`) so the
tests can prove it without timing.

Speed: phases are float64. For uniformly spaced channels the phasor of channel k+1 is that of
channel k times a per-row step phasor (one ``sincos`` pair per row and source instead of one
per channel), re-synchronised exactly every :data:`RESYNC` channels; the error is a few ulp
per channel (measured in the tests and ``docs/bench/simulate.md``). Gaussian factors use the
matching second-order recurrence. Non-uniform channel layouts fall back to direct evaluation.
"""

from __future__ import annotations

import contextlib
import math
import threading
from collections import Counter
from collections.abc import Iterator
from typing import Any

import numba
import numpy as np

from xstack._cluster import cap_numba_threads
from xstack.coords import SPEED_OF_LIGHT
from xstack.smearing import delay_rate_scalar, factor_scalar

#: Exact re-evaluation interval of the channel recurrence (bounds the accumulated error).
RESYNC = 32
#: Gaussian factors exp(-x) with x above this are dropped (exp(-69) < 1e-30 of the flux).
GAUSS_CUTOFF = 69.0

#: Counts of the computational steps run by the kernels (process-wide, thread-safe).
STEP_COUNTS: Counter[str] = Counter()
_LOCK = threading.Lock()


def _count(*steps: str) -> None:
    with _LOCK:
        for s in steps:
            STEP_COUNTS[s] += 1


@contextlib.contextmanager
def record_steps() -> Iterator[Counter[str]]:
    """Context manager yielding a Counter of the kernel steps run inside the block.

    Works across dask threads (the counts are process-wide; do not nest concurrent blocks).
    Keys: ``"constant"`` (center point sources), ``"phase"`` (off-center phasors),
    ``"w_term"``, ``"gaussian"``, ``"attenuation"``, ``"smear_bandwidth"``, ``"smear_time"``.
    """
    with _LOCK:
        before = Counter(STEP_COUNTS)
    result: Counter[str] = Counter()
    try:
        yield result
    finally:
        with _LOCK:
            after = Counter(STEP_COUNTS)
        after.subtract(before)
        result.update({k: v for k, v in after.items() if v > 0})


@numba.njit(nogil=True, cache=True)
def _row_kernel(r: int, u: np.ndarray, v: np.ndarray, w: np.ndarray, has_w: bool,
                freq: np.ndarray, uniform: bool, l: np.ndarray, m: np.ndarray,
                nm1: np.ndarray, amp: np.ndarray, gcoef: np.ndarray, has_g: bool,
                out: np.ndarray) -> None:
    nchan = freq.size
    nsrc = l.size
    twopi_c = 2.0 * math.pi / SPEED_OF_LIGHT
    f0 = freq[0]
    df = freq[1] - freq[0] if nchan > 1 else 0.0
    ur = u[r]
    vr = v[r]
    wr = w[r] if has_w else 0.0
    q2 = ur * ur + vr * vr
    acc = np.zeros(nchan, dtype=np.complex128)
    for k in range(nsrc):
        # phase per Hz (float64 throughout)
        if has_w:
            dot = ur * l[k] + vr * m[k] + wr * nm1[k]
        else:
            dot = ur * l[k] + vr * m[k]
        phase_per_hz = twopi_c * dot
        gauss = has_g and gcoef[k] > 0.0
        a = gcoef[k] * q2 if gauss else 0.0
        if gauss and a * f0 * f0 > GAUSS_CUTOFF:
            continue  # below 1e-30 of the flux in every channel (ascending frequencies)
        if uniform:
            ph = phase_per_hz * f0
            p = complex(math.cos(ph), math.sin(ph))
            sph = phase_per_hz * df
            step = complex(math.cos(sph), math.sin(sph))
            if gauss:
                g = math.exp(-a * f0 * f0)
                gr = math.exp(-a * (2.0 * f0 * df + df * df))
                grr = math.exp(-2.0 * a * df * df)
            else:
                g = 1.0
                gr = 1.0
                grr = 1.0
            for c in range(nchan):
                if c > 0 and c % RESYNC == 0:
                    # exact re-synchronisation bounds the recurrence error
                    ph = phase_per_hz * freq[c]
                    p = complex(math.cos(ph), math.sin(ph))
                    if gauss:
                        fc = freq[c]
                        g = math.exp(-a * fc * fc)
                        gr = math.exp(-a * (2.0 * fc * df + df * df))
                acc[c] += (amp[k, c] * g) * p
                p = p * step
                if gauss:
                    g = g * gr
                    gr = gr * grr
        else:
            for c in range(nchan):
                fc = freq[c]
                ph = phase_per_hz * fc
                val = amp[k, c] * complex(math.cos(ph), math.sin(ph))
                if gauss:
                    val = val * math.exp(-a * fc * fc)
                acc[c] += val
    for c in range(nchan):
        out[r, c] += acc[c]


@numba.njit(nogil=True, cache=True)
def _kernel_serial(u, v, w, has_w, freq, uniform, l, m, nm1, amp, gcoef, has_g, out):
    for r in range(u.size):
        _row_kernel(r, u, v, w, has_w, freq, uniform, l, m, nm1, amp, gcoef, has_g, out)


@numba.njit(nogil=True, parallel=True, cache=True)
def _kernel_parallel(u, v, w, has_w, freq, uniform, l, m, nm1, amp, gcoef, has_g, out):
    for r in numba.prange(u.size):
        _row_kernel(r, u, v, w, has_w, freq, uniform, l, m, nm1, amp, gcoef, has_g, out)


@numba.njit(nogil=True, cache=True)
def _kernel_f32(u, v, freq, l, m, amp, out):
    """float32 phases, direct sincos per channel, no w-term / Gaussian (benchmark path)."""
    twopi_c = np.float32(2.0 * math.pi / SPEED_OF_LIGHT)
    for r in range(u.size):
        ur = np.float32(u[r])
        vr = np.float32(v[r])
        for k in range(l.size):
            pph = twopi_c * (ur * np.float32(l[k]) + vr * np.float32(m[k]))
            for c in range(freq.size):
                ph = pph * np.float32(freq[c])
                out[r, c] += amp[k, c] * complex(math.cos(ph), math.sin(ph))


@numba.njit(nogil=True, cache=True)
def _antenna_phasors(ut, vt, wt, has_w, freq, uniform, lk, mk, nk, E):
    """E[a, c] = exp(+2 pi i (u_a l + v_a m + w_a (n-1)) nu_c / c) for one source and time."""
    twopi_c = 2.0 * math.pi / SPEED_OF_LIGHT
    nchan = freq.size
    f0 = freq[0]
    df = freq[1] - freq[0] if nchan > 1 else 0.0
    for a in range(ut.size):
        dot = ut[a] * lk + vt[a] * mk
        if has_w:
            dot += wt[a] * nk
        pph = twopi_c * dot
        if uniform:
            ph = pph * f0
            p = complex(math.cos(ph), math.sin(ph))
            sph = pph * df
            step = complex(math.cos(sph), math.sin(sph))
            for c in range(nchan):
                if c > 0 and c % RESYNC == 0:
                    ph = pph * freq[c]
                    p = complex(math.cos(ph), math.sin(ph))
                E[a, c] = p
                p = p * step
        else:
            for c in range(nchan):
                ph = pph * freq[c]
                E[a, c] = complex(math.cos(ph), math.sin(ph))


@numba.njit(nogil=True, cache=True)
def _antenna_time(t, u, v, w, has_w, freq, uniform, l, m, nm1, amp, gcoef, has_g, a1, a2,
                  has_s, swidth, sdt, sin_d, cos_d, out):
    nant = u.shape[1]
    nchan = freq.size
    f0 = freq[0]
    df = freq[1] - freq[0] if nchan > 1 else 0.0
    E = np.empty((nant, nchan), dtype=np.complex128)
    G = np.empty((nant, nchan), dtype=np.complex128)
    S = np.ones(nchan)
    for k in range(l.size):
        nk = nm1[k] if has_w else 0.0
        _antenna_phasors(u[t], v[t], w[t], has_w, freq, uniform, l[k], m[k], nk, E)
        for a in range(nant):
            for c in range(nchan):
                G[a, c] = amp[k, c] * E[a, c]
        gk = gcoef[k] if has_g else 0.0
        if gk == 0.0 and not has_s:
            for b in range(a1.size):
                i = a1[b]
                j = a2[b]
                for c in range(nchan):
                    out[t, b, c] += G[i, c] * E[j, c].conjugate()
            continue
        # Gaussian source or smearing: factors of the baseline, not of the antennas
        for b in range(a1.size):
            i = a1[b]
            j = a2[b]
            du = u[t, i] - u[t, j]
            dv = v[t, i] - v[t, j]
            if has_s:
                dw = w[t, i] - w[t, j]
                delay = du * l[k] + dv * m[k] + dw * nk
                rate = 0.0
                if sdt != 0.0:
                    rate = delay_rate_scalar(du, dv, dw, l[k], m[k], nk, sin_d, cos_d)
                for c in range(nchan):
                    S[c] = factor_scalar(delay, rate, freq[c], swidth[c], sdt)
            if gk == 0.0:
                for c in range(nchan):
                    out[t, b, c] += (G[i, c] * E[j, c].conjugate()) * S[c]
                continue
            a = gk * (du * du + dv * dv)
            if a * f0 * f0 > GAUSS_CUTOFF:
                continue
            if uniform:
                g = math.exp(-a * f0 * f0)
                gr = math.exp(-a * (2.0 * f0 * df + df * df))
                grr = math.exp(-2.0 * a * df * df)
                for c in range(nchan):
                    if c > 0 and c % RESYNC == 0:
                        fc = freq[c]
                        g = math.exp(-a * fc * fc)
                        gr = math.exp(-a * (2.0 * fc * df + df * df))
                    out[t, b, c] += (G[i, c] * E[j, c].conjugate()) * (g * S[c])
                    g = g * gr
                    gr = gr * grr
            else:
                for c in range(nchan):
                    fc = freq[c]
                    out[t, b, c] += (G[i, c] * E[j, c].conjugate()) * (math.exp(-a * fc * fc)
                                                                        * S[c])


@numba.njit(nogil=True, cache=True)
def _antenna_serial(u, v, w, has_w, freq, uniform, l, m, nm1, amp, gcoef, has_g, a1, a2,
                    has_s, swidth, sdt, sin_d, cos_d, out):
    for t in range(u.shape[0]):
        _antenna_time(t, u, v, w, has_w, freq, uniform, l, m, nm1, amp, gcoef, has_g, a1, a2,
                      has_s, swidth, sdt, sin_d, cos_d, out)


@numba.njit(nogil=True, parallel=True, cache=True)
def _antenna_parallel(u, v, w, has_w, freq, uniform, l, m, nm1, amp, gcoef, has_g, a1, a2,
                      has_s, swidth, sdt, sin_d, cos_d, out):
    for t in numba.prange(u.shape[0]):
        _antenna_time(t, u, v, w, has_w, freq, uniform, l, m, nm1, amp, gcoef, has_g, a1, a2,
                      has_s, swidth, sdt, sin_d, cos_d, out)


def _source_terms(flux: np.ndarray, attenuation: Any, fwhm: Any, nchan: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Per-source amplitudes (nsrc, nchan) = flux x attenuation (Jy) and the Gaussian
    coefficients (0 for point sources) shared by both model kernels' wrappers."""
    nsrc = flux.size
    amp = np.broadcast_to(flux[:, None], (nsrc, nchan))
    if attenuation is not None:
        att = np.asarray(attenuation, dtype=np.float64)
        if att.shape != (nsrc, nchan):
            raise ValueError(f"attenuation must have shape (nsrc, nchan) = {(nsrc, nchan)}")
        amp = amp * att
        _count("attenuation")
    gcoef = np.zeros(nsrc)
    if fwhm is not None:
        th = np.broadcast_to(np.asarray(fwhm, dtype=np.float64), (nsrc,))
        if np.any(th < 0) or not np.all(np.isfinite(th)):
            raise ValueError("fwhm must be finite and >= 0")
        gcoef = gaussian_coefficient(th)
    return np.ascontiguousarray(amp, dtype=np.float64), gcoef


def _constant_sources(l: np.ndarray, m: np.ndarray, nm1: np.ndarray | None, gcoef: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, bool, bool]:
    """Split the sources: point sources exactly at the phase center have constant
    visibilities (no phasors). Returns (constant mask, the rest, whether the rest need the
    w-term, whether any of the rest is Gaussian)."""
    at_center = (l == 0.0) & (m == 0.0)
    if nm1 is not None:
        at_center &= nm1 == 0.0
    const = at_center & (gcoef == 0.0)
    if const.any():
        _count("constant")
    rest = ~const
    has_w = nm1 is not None and bool(np.any(nm1[rest] != 0.0))
    has_g = bool(np.any(gcoef[rest] > 0.0))
    return const, rest, has_w, has_g


def model_visibilities_antenna(antenna_uvw: Any, antenna1: Any, antenna2: Any, frequency: Any,
                               l: Any, m: Any, n_minus_1: Any, flux: Any,
                               attenuation: Any = None, fwhm: Any = None,
                               out_dtype: Any = np.complex128, *,
                               parallel: bool = True, channel_width: Any = None,
                               integration_time: float | None = None,
                               dec0: float = 0.0) -> np.ndarray:
    """Model visibilities from per-antenna phasors (same result as
    :func:`model_visibilities`, several times faster for many baselines).

    A baseline's phase is the difference of its antennas' phases, so with per-antenna
    coordinates ``antenna_uvw`` (ntime, nant, 3) such that the MS UVW of baseline b is
    ``antenna_uvw[:, antenna1[b]] - antenna_uvw[:, antenna2[b]]``,
    ``V_b = sum_k A_k S_k E_{a1,k} conj(E_{a2,k})`` with
    ``E_{a,k} = exp(+2 pi i (u_a l_k + v_a m_k + w_a (n_k - 1)) / lambda)``: one phasor per
    antenna instead of one per baseline. The Gaussian factor of extended sources (``fwhm``,
    radians) depends on the baseline length and is evaluated per baseline.

    Smearing (:mod:`xstack.smearing`), per baseline too: ``channel_width`` ((nchan,) Hz)
    multiplies each source's visibility by the bandwidth factor sinc(pi d dnu / c),
    ``integration_time`` (s) by the time-average factor sinc(pi nu d' dt / c), with the
    delay rate d' from Earth rotation about a phase center at declination ``dec0``
    (radians). ``None`` (default): not simulated, no extra work.

    Returns
    -------
    numpy.ndarray
        (ntime, nbaseline, nchan) complex visibilities, Jy.
    """
    ant = np.asarray(antenna_uvw, dtype=np.float64)
    if ant.ndim != 3 or ant.shape[2] != 3:
        raise ValueError(f"antenna_uvw must have shape (ntime, nant, 3), got {ant.shape}")
    a1 = np.ascontiguousarray(antenna1, dtype=np.int64)
    a2 = np.ascontiguousarray(antenna2, dtype=np.int64)
    freq = np.atleast_1d(np.asarray(frequency, dtype=np.float64))
    l = np.atleast_1d(np.asarray(l, dtype=np.float64))
    m = np.atleast_1d(np.asarray(m, dtype=np.float64))
    flux = np.atleast_1d(np.asarray(flux, dtype=np.float64))
    nsrc, nchan, nt = l.size, freq.size, ant.shape[0]
    nm1 = None if n_minus_1 is None else np.atleast_1d(np.asarray(n_minus_1, np.float64))
    amp, gcoef = _source_terms(flux, attenuation, fwhm, nchan)
    out = np.zeros((nt, a1.size, nchan), dtype=np.complex128)
    if nsrc == 0 or nt == 0 or a1.size == 0:
        return out.astype(out_dtype, copy=False)
    const, rest, has_w, has_g = _constant_sources(l, m, nm1, gcoef)
    if const.any():
        out += amp[const].sum(axis=0)[None, None, :]
    if rest.any():
        order = np.argsort(freq, kind="stable")
        fs = np.ascontiguousarray(freq[order])
        tmp = np.zeros((nt, a1.size, nchan), dtype=np.complex128)
        kern = _antenna_parallel if parallel else _antenna_serial
        cap_numba_threads()  # on a dask worker: its threads, not every core
        swidth = np.zeros(nchan)
        if channel_width is not None:
            swidth = np.ascontiguousarray(np.broadcast_to(
                np.asarray(channel_width, np.float64), (nchan,))[order])
        sdt = 0.0 if integration_time is None else float(integration_time)
        has_s = bool(np.any(swidth != 0.0)) or sdt != 0.0
        kern(np.ascontiguousarray(ant[..., 0]), np.ascontiguousarray(ant[..., 1]),
             np.ascontiguousarray(ant[..., 2]), has_w, fs, is_uniform(fs),
             np.ascontiguousarray(l[rest]), np.ascontiguousarray(m[rest]),
             np.ascontiguousarray(nm1[rest]) if has_w else np.zeros(int(rest.sum())),
             np.ascontiguousarray(amp[rest][:, order]), np.ascontiguousarray(gcoef[rest]),
             has_g, a1, a2, has_s, swidth, sdt, math.sin(dec0), math.cos(dec0), tmp)
        inv = np.empty_like(order)
        inv[order] = np.arange(nchan)
        out += tmp[:, :, inv]
        _count("phase", *(("w_term",) if has_w else ()), *(("gaussian",) if has_g else ()),
               *(("smear_bandwidth",) if np.any(swidth != 0.0) else ()),
               *(("smear_time",) if sdt != 0.0 else ()))
    return out.astype(out_dtype, copy=False)


def is_uniform(frequency: np.ndarray) -> bool:
    """True if channels are equally spaced and ascending to rounding (a few ulp)."""
    f = np.asarray(frequency, dtype=np.float64)
    if f.size < 2:
        return True
    df = f[1] - f[0]
    if df <= 0:
        return False
    k = np.arange(f.size)
    return bool(np.all(np.abs(f - (f[0] + k * df)) <= 8 * np.finfo(float).eps * np.abs(f)))


def gaussian_coefficient(fwhm: Any) -> np.ndarray:
    """Per-source ``pi^2 theta^2 / (4 ln 2 c^2)`` (s^2/m^2) for FWHM ``theta`` in radians."""
    th = np.asarray(fwhm, dtype=np.float64)
    return (math.pi**2 / (4.0 * math.log(2.0) * SPEED_OF_LIGHT**2)) * th * th


def model_visibilities(uvw: Any, frequency: Any, l: Any, m: Any, n_minus_1: Any, flux: Any,
                       attenuation: Any = None, fwhm: Any = None,
                       out_dtype: Any = np.complex128, *, parallel: bool = True) -> np.ndarray:
    """Model visibilities of point and circular-Gaussian sources (the paper's equation 1).

    Parameters
    ----------
    uvw
        (nrow, 3) baseline coordinates in metres, as stored in an MS (u east, v north,
        w towards the phase center; baseline = antenna2 - antenna1).
    frequency
        (nchan,) channel frequencies, Hz.
    l, m
        (nsrc,) direction cosines relative to the phase center
        (:func:`xstack.coords.radec_to_lmn`).
    n_minus_1
        (nsrc,) ``n - 1`` (computed without cancellation), or ``None`` to leave out the
        w-term entirely (no w arithmetic is done).
    flux
        (nsrc,) integrated flux densities, Jy (not divided by n; see the module docstring).
    attenuation
        (nsrc, nchan) primary-beam power attenuation per source and channel, or ``None`` (1).
    fwhm
        (nsrc,) Gaussian full width at half maximum, radians (0 = point source), or ``None``
        for all point sources (no Gaussian factor is evaluated).
    out_dtype
        Output dtype (complex128 or complex64); the sum is always accumulated in complex128.
    parallel
        Use numba's threads over rows (set ``False`` inside dask tasks, which are already
        parallel over chunks).

    Returns
    -------
    numpy.ndarray
        (nrow, nchan) complex visibilities, Jy.
    """
    uvw = np.asarray(uvw, dtype=np.float64)
    if uvw.ndim != 2 or uvw.shape[1] != 3:
        raise ValueError(f"uvw must have shape (nrow, 3), got {uvw.shape}")
    freq = np.atleast_1d(np.asarray(frequency, dtype=np.float64))
    l = np.atleast_1d(np.asarray(l, dtype=np.float64))
    m = np.atleast_1d(np.asarray(m, dtype=np.float64))
    flux = np.atleast_1d(np.asarray(flux, dtype=np.float64))
    nsrc, nchan, nrow = l.size, freq.size, uvw.shape[0]
    if m.size != nsrc or flux.size != nsrc:
        raise ValueError("l, m and flux must have the same length")
    nm1 = None if n_minus_1 is None else np.atleast_1d(np.asarray(n_minus_1, np.float64))
    if nm1 is not None and nm1.size != nsrc:
        raise ValueError("n_minus_1 must have the same length as l")

    amp, gcoef = _source_terms(flux, attenuation, fwhm, nchan)

    out = np.zeros((nrow, nchan), dtype=np.complex128)
    if nsrc == 0 or nrow == 0 or nchan == 0:
        return out.astype(out_dtype, copy=False)

    const, rest, has_w, has_g = _constant_sources(l, m, nm1, gcoef)
    if const.any():
        out += amp[const].sum(axis=0)[None, :]
    if rest.any():
        # ascending channel order for the recurrences; undone on output
        order = np.argsort(freq, kind="stable")
        fs = np.ascontiguousarray(freq[order])
        uniform = is_uniform(fs)
        u = np.ascontiguousarray(uvw[:, 0])
        v = np.ascontiguousarray(uvw[:, 1])
        w = np.ascontiguousarray(uvw[:, 2])
        nm1_r = np.ascontiguousarray(nm1[rest]) if has_w else np.zeros(int(rest.sum()))
        tmp = np.zeros((nrow, nchan), dtype=np.complex128)
        kern = _kernel_parallel if parallel else _kernel_serial
        cap_numba_threads()  # on a dask worker: its threads, not every core
        kern(u, v, w, has_w, fs, uniform, np.ascontiguousarray(l[rest]),
             np.ascontiguousarray(m[rest]), nm1_r, np.ascontiguousarray(amp[rest][:, order]),
             np.ascontiguousarray(gcoef[rest]), has_g, tmp)
        inv = np.empty_like(order)
        inv[order] = np.arange(nchan)
        out += tmp[:, inv]
        _count("phase", *(("w_term",) if has_w else ()), *(("gaussian",) if has_g else ()))
    return out.astype(out_dtype, copy=False)


def model_visibilities_float32(uvw: Any, frequency: Any, l: Any, m: Any, flux: Any,
                               attenuation: Any = None) -> np.ndarray:
    """Faster, less accurate point-source path: float32 phases, no w-term (benchmarks only).

    Returns (nrow, nchan) complex64. Its error against :func:`model_visibilities` is
    measured in ``benchmarks/bench_simulate.py``; it is never used by the simulator.
    """
    uvw = np.asarray(uvw, dtype=np.float64)
    freq = np.asarray(frequency, dtype=np.float64)
    flux = np.asarray(flux, dtype=np.float64)
    amp = np.broadcast_to(flux[:, None], (flux.size, freq.size))
    if attenuation is not None:
        amp = amp * np.asarray(attenuation)
    out = np.zeros((uvw.shape[0], freq.size), dtype=np.complex64)
    _kernel_f32(np.ascontiguousarray(uvw[:, 0]), np.ascontiguousarray(uvw[:, 1]), freq,
                np.asarray(l, np.float64), np.asarray(m, np.float64),
                np.ascontiguousarray(amp, dtype=np.float32), out)
    return out


def _gaussian_band(v_a: np.ndarray, v_b: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Fraction of a unit Gaussian of width ``sigma`` (km/s) between velocities v_a < v_b.

    The tails are taken from erfc, so a channel far from the line keeps its small value to
    full relative precision instead of the rounding of 1 - 1.
    """
    from scipy.special import erfc

    k = 1.0 / (math.sqrt(2.0) * sigma)
    xa, xb = v_a * k, v_b * k
    upper = 0.5 * (erfc(xa) - erfc(xb))  # right for xa >= 0
    lower = 0.5 * (erfc(-xb) - erfc(-xa))  # right for xb <= 0
    middle = 1.0 - 0.5 * (erfc(-xa) + erfc(xb))  # straddles 0
    return np.where(xa >= 0, upper, np.where(xb <= 0, lower, middle))


#: FWHM -> sigma of a Gaussian.
FWHM_TO_SIGMA = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))


def line_channel_flux(freq_lo: Any, freq_hi: Any, centre_hz: Any, flux_jy_kms: Any,
                      fwhm_kms: Any, profile: str = "gaussian") -> np.ndarray:
    """Channel-averaged flux density (Jy) of lines in channels [freq_lo, freq_hi] (Hz).

    Each source's line is a profile in v = c (nu_c - nu) / nu_c (km/s) about its centre
    ``centre_hz`` with integrated flux ``flux_jy_kms`` = integral of S dv and full width at
    half maximum ``fwhm_kms``; ``profile``: ``gaussian``, or ``double`` (two Gaussians of
    half the flux each, FWHM fwhm/3, at +-fwhm/3). The channel's value is the profile's
    integral over the channel's velocity interval divided by its width (erf of the edges),
    so the channels' flux density times their velocity widths sums to the line's flux.

    Parameters
    ----------
    freq_lo, freq_hi
        Channel edges (Hz) in the frame of the line centres, broadcasting against
        ``centre_hz[:, None]`` (e.g. (nchan,) or (nsrc, nchan)).
    centre_hz, flux_jy_kms, fwhm_kms
        One per source (nsrc,).

    Returns
    -------
    numpy.ndarray
        (nsrc, nchan) float64, Jy.
    """
    from xstack.spectral import SPEED_OF_LIGHT_KMS

    centre = np.atleast_1d(np.asarray(centre_hz, np.float64))[:, None]
    flux = np.atleast_1d(np.asarray(flux_jy_kms, np.float64))[:, None]
    fwhm = np.atleast_1d(np.asarray(fwhm_kms, np.float64))[:, None]
    # the low-frequency edge is the high-velocity one
    v_a = SPEED_OF_LIGHT_KMS * (centre - np.asarray(freq_hi, np.float64)) / centre
    v_b = SPEED_OF_LIGHT_KMS * (centre - np.asarray(freq_lo, np.float64)) / centre
    if profile == "gaussian":
        frac = _gaussian_band(v_a, v_b, fwhm * FWHM_TO_SIGMA)
    elif profile == "double":
        sig, off = fwhm / 3.0 * FWHM_TO_SIGMA, fwhm / 3.0
        frac = 0.5 * (_gaussian_band(v_a - off, v_b - off, sig)
                      + _gaussian_band(v_a + off, v_b + off, sig))
    else:
        raise ValueError(f"unknown line profile {profile!r}")
    return flux * frac / (v_b - v_a)


def line_half_width_kms(fwhm_kms: Any, profile: str = "gaussian", n_sigma: float = 9.0
                        ) -> np.ndarray:
    """Half the velocity range outside which a line's channels are < 1e-17 of its flux
    (``n_sigma`` Gaussian widths beyond the outermost component)."""
    fwhm = np.asarray(fwhm_kms, np.float64)
    if profile == "double":
        return fwhm / 3.0 + n_sigma * fwhm / 3.0 * FWHM_TO_SIGMA
    return n_sigma * fwhm * FWHM_TO_SIGMA
