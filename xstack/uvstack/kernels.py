"""Numerical kernels of uv-stacking (paper eq. 4): numpy and numba only, no dask, no xarray.

The stacking phasor of one visibility row (baseline coordinates u, v, w in metres, as stored
in the MS) at frequency nu is::

    P(row, nu) = sum_k W_k A_k(nu)^-1 exp(-2 pi i (u l_k + v m_k + w (n_k - 1)) nu / c) / sum_k W_k

and the stacked visibility is ``V * P`` (the sign that undoes eq. 1, ``docs/conventions.md``).
Callers pass the already normalised coefficients ``coef[k, c] = W_k A_k(nu_c)^-1 / sum W``.

Engines
-------
``numba``
    Direct evaluation, parallel over rows. The phase of every (row, position) pair is computed
    in float64 *turns* ``t = d nu / c`` (``d = u l + v m + w (n - 1)``, metres); ``t - round(t)``
    is exact in floating point, so the range reduction adds no error, and (cos, sin)(2 pi t) is
    evaluated with a branch-free polynomial that the compiler vectorises (SIMD over positions).
    Across evenly spaced channels the phasor advances by the recurrence
    ``z(c+1) = z(c) * exp(-2 pi i d dnu / c)``; it is re-seeded exactly every ``reseed``
    channels, which bounds the recurrence error by ``reseed`` times a few 1e-16
    (measured in ``tests/test_uvstack_kernels.py``). Unevenly spaced channels are seeded exactly
    in every channel.
``antenna``
    :func:`phasor_antenna`: the same phasor through per-antenna factors for rows ordered
    (time, baseline) with known antenna ids. The baseline phasor factorises,
    ``exp(-2 pi i nu/c b.s) = E_a1 conj(E_a2)`` with ``E_a = exp(-2 pi i nu/c uvw_a.s)``, so
    the sine/cosine and the channel recurrence run per (time, antenna, position) instead of
    per (time, baseline, position); each (row, channel, position) costs four multiply-adds.
    The antenna UVW are solved by least squares (:mod:`xstack._antenna`) and used only when
    the bound of the phase error this can cause is below a tolerance (default 1e-9 rad).
``numpy``
    :func:`stack_phasor_numpy`: plain vectorised numpy (``np.exp`` of the full phase per
    channel), in blocks of rows. The slow but obviously-correct path.
``nufft``
    :func:`stack_phasor_nufft`: a type-3 non-uniform FFT (``ducc0.nufft.experimental.nu2nu``),
    one transform per channel, accuracy ``epsilon`` (>= 2e-13 in double precision). It wins for
    very many positions in a compact field.

Passing float32 ``uvw``/``l``/``m``/``n_minus_1``/``frequency`` arrays to the numba kernel
computes the phase in float32: kept only to *measure* what single precision costs (the
public pipeline always uses float64 phases).
"""

from __future__ import annotations

import math
import os
import threading

import numba
import numpy as np

from xstack._antenna import ANTENNA_TOL_RAD, FactorisationError, antenna_layout
from xstack._cluster import cap_numba_threads
from xstack._phase import antenna_channel, antenna_phases
from xstack._phase import cis_minus_turns as _cis_minus_turns
from xstack.coords import SPEED_OF_LIGHT

# The kernel already uses every core (numba prange); calls from several dask threads are
# serialised, which also keeps numba's default 'workqueue' threading layer (not thread-safe
# for concurrent launches) safe.
_KERNEL_LOCK = threading.Lock()

#: Re-seed the channel recurrence exactly every this many channels.
DEFAULT_RESEED = 16


@numba.njit(parallel=True, fastmath={"reassoc", "contract"}, cache=True)
def _phasor_numba(uvw, fc, l, m, n1, coef_t, step, even, reseed, out_re, out_im):
    """Fill out_re/out_im (nrow, nchan) with the normalised phasor sum.

    fc: frequency / c (nchan,), 1/m. coef_t: (nchan, nsrc). step: (fc[1]-fc[0]) when the
    channels are evenly spaced. 'reassoc' only lets the compiler vectorise the sums over
    positions (a different summation order); phases are reduced exactly in turns.
    """
    nrow = uvw.shape[0]
    nchan = fc.shape[0]
    nsrc = l.shape[0]
    block = 64
    nblock = (nrow + block - 1) // block
    for b in numba.prange(nblock):
        d = np.empty(nsrc, dtype=l.dtype)
        zr = np.empty(nsrc)
        zi = np.empty(nsrc)
        rr = np.empty(nsrc)
        ri = np.empty(nsrc)
        for row in range(b * block, min(nrow, (b + 1) * block)):
            u = uvw[row, 0]
            v = uvw[row, 1]
            w = uvw[row, 2]
            for k in range(nsrc):
                d[k] = u * l[k] + v * m[k] + w * n1[k]
            if even and nchan > 1:
                for k in range(nsrc):
                    a, s = _cis_minus_turns(d[k] * step)
                    rr[k] = a
                    ri[k] = s
            for c in range(nchan):
                f = fc[c]
                if (not even) or c % reseed == 0:
                    for k in range(nsrc):
                        a, s = _cis_minus_turns(d[k] * f)
                        zr[k] = a
                        zi[k] = s
                else:
                    for k in range(nsrc):
                        a = zr[k] * rr[k] - zi[k] * ri[k]
                        zi[k] = zr[k] * ri[k] + zi[k] * rr[k]
                        zr[k] = a
                acc_r = 0.0
                acc_i = 0.0
                for k in range(nsrc):
                    acc_r += coef_t[c, k] * zr[k]
                    acc_i += coef_t[c, k] * zi[k]
                out_re[row, c] = acc_r
                out_im[row, c] = acc_i


@numba.njit(parallel=True, fastmath={"reassoc", "contract"}, cache=True)
def _phasor_antenna_numba(ant_uvw, ant_used, a1, a2, rows, fc, l, m, n1, coef_t, step, even,
                          reseed, out_re, out_im):
    """Fill out_re/out_im (ntime * nbl, nchan) at ``rows`` from per-antenna phasors.

    ant_uvw: (ntime, nant, 3) metres; rows are time-major, row = t * nbl + baseline, with
    baseline UVW = ant_uvw[t, a1] - ant_uvw[t, a2]. Per time the sine/cosine are evaluated
    per (antenna, position); each (row, channel, position) then costs four multiply-adds.
    """
    ntime = ant_uvw.shape[0]
    nant = ant_uvw.shape[1]
    nbl = a1.shape[0]
    nchan = fc.shape[0]
    nsrc = l.shape[0]
    tblock = 8
    for b in numba.prange((ntime + tblock - 1) // tblock):
        # per block of integrations: fresh large temporaries per integration cost page faults
        d = np.empty((nant, nsrc))
        er = np.empty((nant, nsrc))
        ei = np.empty((nant, nsrc))
        sr = np.empty((nant, nsrc))
        si = np.empty((nant, nsrc))
        fr = np.empty((nant, nsrc))
        fi = np.empty((nant, nsrc))
        for t in range(b * tblock, min(ntime, (b + 1) * tblock)):
            antenna_phases(ant_uvw[t], ant_used[t], l, m, n1, even and nchan > 1, step, d, sr, si)
            for c in range(nchan):
                cr = coef_t[c]
                antenna_channel(ant_used[t], (not even) or c % reseed == 0, fc[c], d, er, ei, sr, si)
                for ant in range(nant):
                    if not ant_used[t, ant]:
                        continue
                    era = er[ant]
                    eia = ei[ant]
                    # F = coef E once per antenna: a baseline then needs no coefficient load
                    fra = fr[ant]
                    fia = fi[ant]
                    for k in range(nsrc):
                        fra[k] = cr[k] * era[k]
                        fia[k] = cr[k] * eia[k]
                for bl in range(nbl):
                    row = t * nbl + bl
                    if not rows[row]:
                        continue
                    f1r = fr[a1[bl]]
                    f1i = fi[a1[bl]]
                    e2r = er[a2[bl]]
                    e2i = ei[a2[bl]]
                    acc_r = 0.0
                    acc_i = 0.0
                    for k in range(nsrc):
                        # coef E_a1 conj(E_a2): the baseline phasor of position k
                        acc_r += f1r[k] * e2r[k] + f1i[k] * e2i[k]
                        acc_i += f1i[k] * e2r[k] - f1r[k] * e2i[k]
                    out_re[row, c] = acc_r
                    out_im[row, c] = acc_i


def _check_inputs(uvw, frequency, l, m, n_minus_1, weight, inv_attenuation):
    uvw = np.asarray(uvw)
    frequency = np.asarray(frequency)
    if uvw.ndim != 2 or uvw.shape[1] != 3:
        raise ValueError(f"uvw must have shape (nrow, 3), got {uvw.shape}")
    nsrc = np.size(l)
    nchan = frequency.size
    weight = np.broadcast_to(np.asarray(weight, dtype=np.float64), (nsrc,))
    inv_att = np.broadcast_to(np.asarray(inv_attenuation, dtype=np.float64), (nsrc, nchan))
    return uvw, frequency, weight, inv_att


def normalised_coefficients(weight, inv_attenuation, nchan: int) -> np.ndarray:
    """``coef[k, c] = W_k A_k(nu_c)^-1 / sum_k W_k`` as float64 (nsrc, nchan).

    Raises ``ValueError`` when ``sum W`` is not positive (the wrappers turn that into a
    user-facing error before any kernel runs).
    """
    weight = np.asarray(weight, dtype=np.float64).ravel()
    total = weight.sum()
    if not total > 0:
        raise ValueError("sum of position weights is not positive")
    inv = np.broadcast_to(np.asarray(inv_attenuation, dtype=np.float64), (weight.size, nchan))
    return weight[:, None] * inv / total


def channels_evenly_spaced(frequency, uvw_max: float, l_max: float, tol_rad: float = 1e-10) -> bool:
    """Whether the channel recurrence is exact enough: the deviation of each channel from an
    evenly spaced grid, times the largest path difference, must stay below ``tol_rad``."""
    f = np.asarray(frequency, dtype=np.float64)
    if f.size < 2:
        return False
    grid = f[0] + (f[1] - f[0]) * np.arange(f.size)
    dev = np.max(np.abs(f - grid))
    return bool(2 * np.pi * dev * uvw_max * max(l_max, 1e-300) * 3 / SPEED_OF_LIGHT < tol_rad)


def stack_phasor(uvw, frequency, l, m, n_minus_1, weight, inv_attenuation, *,
                 reseed: int = DEFAULT_RESEED, engine: str = "numba",
                 epsilon: float = 1e-12, nthreads: int = 0) -> np.ndarray:
    """The normalised stacking phasor of paper eq. 4 for every (row, channel).

    Parameters
    ----------
    uvw : (nrow, 3) array
        Baseline coordinates in metres, as stored in the MS.
    frequency : (nchan,) array
        Channel frequencies, Hz.
    l, m, n_minus_1 : (nsrc,) arrays
        Direction cosines of the stacking positions relative to the phase center
        (:func:`xstack.coords.radec_to_lmn`).
    weight : (nsrc,) array
        Position weights W_k (>= 0, positive sum).
    inv_attenuation : (nsrc, nchan) array
        1 / A_k(nu_c), primary-beam correction per position and channel (1 for none).
    reseed
        Exact re-seeding interval of the channel recurrence (numba engine).
    engine
        ``"numba"`` (default), ``"numpy"`` or ``"nufft"``.
    epsilon
        Requested accuracy of the ``nufft`` engine.

    Returns
    -------
    numpy.ndarray, complex128, shape (nrow, nchan)
        ``sum_k W_k A_k^-1 exp(-2 pi i (u l_k + v m_k + w (n_k - 1)) nu_c / c) / sum_k W_k``.
        float32 inputs to the numba engine give a float32-phase result (for benchmarks).
    """
    uvw, frequency, weight, inv_att = _check_inputs(uvw, frequency, l, m, n_minus_1, weight,
                                                    inv_attenuation)
    coef = normalised_coefficients(weight, inv_att, frequency.size)
    return phasor_from_coefficients(uvw, frequency, l, m, n_minus_1, coef, reseed=reseed,
                                    engine=engine, epsilon=epsilon, nthreads=nthreads)


def phasor_from_coefficients(uvw, frequency, l, m, n_minus_1, coef, *,
                             reseed: int = DEFAULT_RESEED, engine: str = "numba",
                             epsilon: float = 1e-12, nthreads: int = 0) -> np.ndarray:
    """:func:`stack_phasor` with already normalised ``coef[k, c] = W_k A_kc^-1 / sum W``."""
    uvw = np.asarray(uvw)
    frequency = np.asarray(frequency)
    nchan = frequency.size
    coef = np.asarray(coef, dtype=np.float64)
    if engine == "numpy":
        return stack_phasor_numpy(uvw, frequency, l, m, n_minus_1, coef)
    if engine == "nufft":
        return stack_phasor_nufft(uvw, frequency, l, m, n_minus_1, coef, epsilon=epsilon,
                                  nthreads=nthreads)
    if engine != "numba":
        raise ValueError(f"unknown engine {engine!r}")
    single = uvw.dtype == np.float32
    dt = np.float32 if single else np.float64
    uvw_c = np.ascontiguousarray(uvw, dtype=dt)
    l_c = np.ascontiguousarray(l, dtype=dt)
    m_c = np.ascontiguousarray(m, dtype=dt)
    n_c = np.ascontiguousarray(n_minus_1, dtype=dt)
    fc = (np.asarray(frequency, dtype=np.float64) / SPEED_OF_LIGHT).astype(dt)
    nrow = uvw_c.shape[0]
    if nrow == 0 or l_c.size == 0:
        return np.zeros((nrow, nchan), dtype=np.complex128)
    out_re = np.empty((nrow, nchan))
    out_im = np.empty((nrow, nchan))
    umax = float(np.max(np.abs(uvw_c)))
    lmax = float(max(np.max(np.abs(l_c)), np.max(np.abs(m_c)), np.max(np.abs(n_c))))
    even = channels_evenly_spaced(frequency, umax, lmax)
    # the recurrence step must be the exact spacing of the frequency grid
    step = dt((frequency[1] - frequency[0]) / SPEED_OF_LIGHT) if nchan > 1 else dt(0.0)
    coef_t = np.ascontiguousarray(coef.T)
    cap_numba_threads()
    with _KERNEL_LOCK:
        _phasor_numba(uvw_c, fc, l_c, m_c, n_c, coef_t, step, even, max(1, int(reseed)),
                      out_re, out_im)
    out = np.empty((nrow, nchan), dtype=np.complex128)
    out.real = out_re
    out.imag = out_im
    return out


def phasor_antenna(uvw, frequency, l, m, n_minus_1, coef, antenna1, antenna2, *,
                   rows: np.ndarray | None = None, reseed: int = DEFAULT_RESEED,
                   tol_rad: float = ANTENNA_TOL_RAD, min_rows_per_antenna: float = 0.0
                   ) -> tuple[np.ndarray, float]:
    """:func:`phasor_from_coefficients` through per-antenna phasors (same values to ~1e-15).

    The phasor of baseline (a1, a2) factorises,
    ``exp(-2 pi i nu/c (u l + v m + w (n-1))) = E_a1 conj(E_a2)`` with
    ``E_a = exp(-2 pi i nu/c (u_a l + v_a m + w_a (n-1)))``, so per integration the
    sine/cosine (and the channel recurrence) are evaluated per antenna instead of per
    baseline. The antenna UVW are solved per integration by least squares
    (:func:`xstack._antenna.antenna_layout`) over the wanted rows with finite UVW, leaving
    out cross-baseline rows of UVW exactly zero (missing cells of an irregular grid); rows
    left out get the per-row (numba) kernel, so every wanted row is exact.

    Parameters
    ----------
    uvw : (ntime * nbl, 3) float64
        Baseline coordinates in metres, rows ordered time-major (time, baseline).
    frequency : (nchan,) array
        Channel frequencies, Hz.
    l, m, n_minus_1 : (nsrc,) arrays
        Direction cosines of the positions.
    coef : (nsrc, nchan) array
        Normalised coefficients ``W_k A_kc^-1 / sum W``.
    antenna1, antenna2 : (nbl,) int arrays
        Antenna ids of the baselines.
    rows : (ntime * nbl,) bool, optional
        Rows whose phasor is wanted (default all); the others are returned as 0.
    reseed
        Exact re-seeding interval of the channel recurrence.
    tol_rad
        Largest accepted bound of the factorisation's phase error
        (:meth:`xstack._antenna.AntennaLayout.phase_error`), radians.
    min_rows_per_antenna
        Refuse layouts with fewer fitted rows per used (time, antenna): no speed gain.

    Returns
    -------
    phasor : (ntime * nbl, nchan) complex128
    phase_error : float
        The bound of the factorisation's phase error, radians.

    Raises
    ------
    FactorisationError
        The rows are not whole integrations of the baselines, the bound exceeds
        ``tol_rad``, or there are too few rows per antenna.
    """
    uvw = np.ascontiguousarray(uvw, dtype=np.float64)
    freq = np.asarray(frequency, dtype=np.float64)
    l_c, m_c, n_c = (np.ascontiguousarray(x, dtype=np.float64) for x in (l, m, n_minus_1))
    coef = np.asarray(coef, dtype=np.float64)
    a1 = np.asarray(antenna1).ravel()
    a2 = np.asarray(antenna2).ravel()
    nrow, nchan = uvw.shape[0], freq.size
    want = np.ones(nrow, dtype=bool) if rows is None else np.asarray(rows, dtype=bool).ravel()
    if a1.size == 0 or a1.size != a2.size or nrow % a1.size:
        raise FactorisationError(f"{nrow} rows are not whole times of {a1.size} baselines")
    cross = np.tile(a1 != a2, nrow // a1.size)
    fit = want & ~(cross & np.all(uvw == 0.0, axis=1))
    layout = antenna_layout(uvw, a1, a2, row_ok=fit)
    if layout.rows_per_antenna < min_rows_per_antenna:
        raise FactorisationError(f"{layout.rows_per_antenna:.2f} rows per antenna: no gain")
    err = layout.phase_error(l_c, m_c, n_c, freq)
    if not err <= tol_rad:
        raise FactorisationError(f"antenna UVW reproduce the baseline UVW only to a phase error "
                                 f"of {err:.3g} rad (tolerance {tol_rad:.3g} rad)")
    out = np.zeros((nrow, nchan), dtype=np.complex128)
    if nrow == 0 or l_c.size == 0:
        return out, err
    ant_uvw = np.ascontiguousarray(layout.uvw)
    umax = float(np.max(np.abs(ant_uvw))) if ant_uvw.size else 0.0
    lmax = float(max(np.max(np.abs(l_c)), np.max(np.abs(m_c)), np.max(np.abs(n_c))))
    even = channels_evenly_spaced(freq, umax, lmax)
    step = (freq[1] - freq[0]) / SPEED_OF_LIGHT if nchan > 1 else 0.0
    out_re = np.zeros((nrow, nchan))
    out_im = np.zeros((nrow, nchan))
    cap_numba_threads()
    with _KERNEL_LOCK:
        _phasor_antenna_numba(ant_uvw, layout.used, layout.antenna1, layout.antenna2,
                              layout.rows, freq / SPEED_OF_LIGHT, l_c, m_c, n_c,
                              np.ascontiguousarray(coef.T), step, even, max(1, int(reseed)),
                              out_re, out_im)
    out.real = out_re
    out.imag = out_im
    rest = np.flatnonzero(want & ~layout.rows)
    if rest.size:
        out[rest] = phasor_from_coefficients(uvw[rest], freq, l_c, m_c, n_c, coef,
                                             reseed=reseed, engine="numba")
    return out, err


def stack_phasor_numpy(uvw, frequency, l, m, n_minus_1, coef, block_bytes: int = 64 * 2**20):
    """Plain-numpy evaluation of the phasor from normalised coefficients ``coef`` (nsrc, nchan).

    Every phase is computed directly in float64 (no recurrence); memory is bounded by
    processing blocks of rows.
    """
    uvw = np.asarray(uvw, dtype=np.float64)
    frequency = np.asarray(frequency, dtype=np.float64)
    lmn = np.stack([np.asarray(l, np.float64), np.asarray(m, np.float64),
                    np.asarray(n_minus_1, np.float64)], axis=1)  # (nsrc, 3)
    nrow, nsrc = uvw.shape[0], lmn.shape[0]
    out = np.empty((nrow, frequency.size), dtype=np.complex128)
    step = max(1, block_bytes // max(1, 16 * nsrc))
    for start in range(0, nrow, step):
        d = uvw[start:start + step] @ lmn.T  # (rows, nsrc) metres
        for c, nu in enumerate(frequency):
            out[start:start + step, c] = np.exp(-2j * np.pi * d * (nu / SPEED_OF_LIGHT)) @ coef[:, c]
    return out


def nufft_grid_cells(uvw, frequency, lmn) -> float:
    """Rough number of oversampled grid cells a type-3 NUFFT needs (space-bandwidth product)."""
    fmax = float(np.max(frequency)) / SPEED_OF_LIGHT
    cells = 1.0
    for d in range(3):
        xh = 0.5 * float(np.ptp(lmn[:, d])) if lmn.shape[0] else 0.0
        sh = 0.5 * float(np.ptp(uvw[:, d])) * 2 * np.pi * fmax if uvw.shape[0] else 0.0
        cells *= 2.0 * (16 + 4 * xh * sh / np.pi)
    return cells


def stack_phasor_nufft(uvw, frequency, l, m, n_minus_1, coef, *, epsilon: float = 1e-12,
                       nthreads: int = 0, max_grid_bytes: float = 2 * 2**30) -> np.ndarray:
    """Type-3 NUFFT evaluation (``ducc0.nufft.experimental.nu2nu``), one transform per channel.

    ``nu2nu(forward=True)`` computes ``sum_k a_k exp(-i x_k . s_j)``; we pass x = (l, m, n-1)
    and s = 2 pi (u, v, w) nu / c.
    """
    from ducc0.nufft.experimental import nu2nu

    uvw = np.asarray(uvw, dtype=np.float64)
    lmn = np.ascontiguousarray(np.stack([np.asarray(l, np.float64), np.asarray(m, np.float64),
                                         np.asarray(n_minus_1, np.float64)], axis=1))
    nthreads = nthreads or (os.cpu_count() or 1)
    cells = nufft_grid_cells(uvw, frequency, lmn)
    if cells * 16 > max_grid_bytes:
        raise MemoryError(f"nufft engine would need a ~{cells * 16 / 2**30:.1f} GiB grid for this "
                          "field and baseline range; use the numba engine")
    out = np.empty((uvw.shape[0], len(frequency)), dtype=np.complex128)
    eps = max(float(epsilon), 2.1e-13)
    for c, nu in enumerate(np.asarray(frequency, dtype=np.float64)):
        s = np.ascontiguousarray(uvw * (2 * np.pi * nu / SPEED_OF_LIGHT))
        out[:, c] = nu2nu(points_in=np.ascontiguousarray(coef[:, c].astype(np.complex128)),
                          coord_in=lmn, coord_out=s, forward=True, epsilon=eps,
                          nthreads=nthreads)
    return out


# --- reductions --------------------------------------------------------------------------

def _use_mask(vis, weight, flag, pol_mask, uv_mask):
    use = ~np.asarray(flag, dtype=bool)
    if pol_mask is not None:
        use = use & np.asarray(pol_mask, dtype=bool)[None, None, :]
    if uv_mask is not None:
        use = use & np.asarray(uv_mask, dtype=bool)[:, :, None]
    w = np.where(use, np.asarray(weight, dtype=np.float64), 0.0)
    # NaN/inf data under flags (or with zero weight) must not poison the sums
    good = use & (w > 0) & np.isfinite(vis)
    return good, np.where(good, w, 0.0)


def weighted_sums(vis, weight, flag, phasor, pol_mask=None, uv_mask=None) -> tuple[float, float]:
    """``(sum w Re(V P), sum w)`` over unflagged, selected visibilities of one chunk.

    Parameters
    ----------
    vis, weight, flag : (nrow, nchan, npol)
        Visibilities (Jy), weights (1/Jy^2), flags.
    phasor : (nrow, nchan) complex
        The stacking phasor (:func:`stack_phasor`); pass ``None`` for already stacked data.
    pol_mask : (npol,) bool, optional
        Correlations to use (the parallel hands for Stokes I).
    uv_mask : (nrow, nchan) bool, optional
        Visibilities inside the uv range.

    The weighted mean flux of the chunk is the ratio; sums of several chunks add.
    """
    s = stack_sums(vis, weight, flag, phasor, pol_mask, uv_mask)
    return float(s[0]), float(s[1])


#: Rows per partial sum of :func:`stack_sums`. The rows are cut into blocks of this fixed
#: size, the blocks summed in parallel and their sums added in order, so the result is the
#: same to the last bit whatever the number of threads (a prange reduction splits the rows
#: by thread count: ~1e-16 relative differences between a laptop and a cluster's workers).
SUM_BLOCK_ROWS = 512


@numba.njit(parallel=True, cache=True)
def _sums_numba(vis, weight, flag, phasor, has_phasor, pol_mask, uv_mask, has_uv, noise,
                has_noise):
    """One pass, no temporaries beyond the block sums: the NSUMS sums of :func:`stack_sums`."""
    nrow, nchan, npol = vis.shape
    nbl = noise.shape[0]
    nblock = (nrow + SUM_BLOCK_ROWS - 1) // SUM_BLOCK_ROWS
    part = np.zeros((nblock, 8))
    for blk in numba.prange(nblock):
        s0 = 0.0
        s1 = 0.0
        s2 = 0.0
        s3 = 0.0
        s4 = 0.0
        s5 = 0.0
        s6 = 0.0
        s7 = 0.0
        for r in range(blk * SUM_BLOCK_ROWS, min(nrow, (blk + 1) * SUM_BLOCK_ROWS)):
            b = r % nbl
            for c in range(nchan):
                if has_uv and not uv_mask[r, c]:
                    continue
                pr = 1.0
                pi = 0.0
                if has_phasor:
                    pr = phasor[r, c].real
                    pi = phasor[r, c].imag
                p2 = pr * pr + pi * pi
                for p in range(npol):
                    if not pol_mask[p] or flag[r, c, p]:
                        continue
                    w = np.float64(weight[r, c, p])
                    if not w > 0:
                        continue
                    vr = np.float64(vis[r, c, p].real)
                    vi = np.float64(vis[r, c, p].imag)
                    # NaN/inf data under flags (or with zero weight) never reach the sums
                    if not (math.isfinite(vr) and math.isfinite(vi)):
                        continue
                    s0 += w * (vr * pr - vi * pi)
                    s1 += w
                    s2 += w * p2
                    s3 += w * (vr * pi + vi * pr)
                    s4 += 1.0
                    if has_noise:
                        # measured sigma^2 = a + b / w (xstack._scatter.noise_model)
                        s5 += w * (w * noise[b, p, 0] + noise[b, p, 1]) * p2
                        kind = noise[b, p, 2]
                        if kind == 1.0:
                            s6 += 1.0
                        elif kind == 2.0:
                            s7 += 1.0
                    else:
                        s5 += w * p2
                        s7 += 1.0
        part[blk, 0] = s0
        part[blk, 1] = s1
        part[blk, 2] = s2
        part[blk, 3] = s3
        part[blk, 4] = s4
        part[blk, 5] = s5
        part[blk, 6] = s6
        part[blk, 7] = s7
    total = np.zeros(8)
    for blk in range(nblock):  # in order, however prange shared the blocks out
        for j in range(8):
            total[j] += part[blk, j]
    return total


#: Number of sums returned by :func:`stack_sums`.
NSUMS = 8


def stack_sums(vis, weight, flag, phasor, pol_mask=None, uv_mask=None, noise=None) -> np.ndarray:
    """The flux sums of one chunk (float64, length :data:`NSUMS`).

    ``[sum w Re(VP), sum w, sum w |P|^2, sum w Im(VP), count,
    sum w^2 sigma_e^2 |P|^2, count pooled, count weights]``.

    Parameters as in :func:`weighted_sums`, plus

    noise : (nbl, npol, 3) float64, optional
        The measured variance model of :func:`xstack._scatter.noise_model`,
        ``sigma_e^2 = a + b / w`` per (baseline, correlation) with its source code; rows are
        time-major, row ``r`` belongs to baseline ``r % nbl``. Without it ``sigma_e^2 = 1/w``
        (every visibility counts as "weights").

    ``sum w |P|^2`` gives the honest variance of the weighted mean when ``w = 1/sigma^2`` of
    the input visibility (per real component): ``Var(Re(VP)) = |P|^2 / w``, hence
    ``Var(mean) = sum_i s_i^2 w_i |P_i|^2 / (sum_i s_i w_i)^2`` with per-partition weight
    factors ``s_i`` (applied by the caller). ``sum w^2 sigma_e^2 |P|^2`` is the same variance
    with the measured sigma_e^2 in place of 1/w (right whatever the weights' scale). The two
    counts are the visibilities whose sigma_e^2 came from the block's pooled weight scale or
    from the weights as they are (:mod:`xstack._scatter`). Compiled (numba), one pass, no
    temporaries.
    """
    vis = np.asarray(vis)
    if vis.dtype.kind != "c":
        vis = vis.astype(np.complex128)
    nrow, nchan, npol = vis.shape
    weight = np.asarray(weight)
    flag = np.asarray(flag, dtype=bool)
    pm = (np.ones(npol, dtype=bool) if pol_mask is None
          else np.ascontiguousarray(pol_mask, dtype=bool))
    has_phasor = phasor is not None
    ph = (np.asarray(phasor, dtype=np.complex128) if has_phasor
          else np.ones((1, 1), dtype=np.complex128))
    has_uv = uv_mask is not None
    um = np.asarray(uv_mask, dtype=bool) if has_uv else np.ones((1, 1), dtype=bool)
    has_noise = noise is not None
    nz = (np.ascontiguousarray(noise, dtype=np.float64) if has_noise
          else np.zeros((1, npol, 3)))
    if has_noise and (nz.ndim != 3 or nz.shape[1:] != (npol, 3) or nz.shape[0] == 0
                      or nrow % nz.shape[0]):
        raise ValueError(f"noise must have shape (nbl, {npol}, 3) with nbl dividing {nrow} "
                         f"rows, got {nz.shape}")
    cap_numba_threads()
    with _KERNEL_LOCK:
        return _sums_numba(vis, weight, flag, ph, has_phasor, pm, um, has_uv, nz, has_noise)


def stack_sums_numpy(vis, weight, flag, phasor, pol_mask=None, uv_mask=None,
                     noise=None) -> np.ndarray:
    """Plain-numpy twin of :func:`stack_sums` (tests compare the two)."""
    vis = np.asarray(vis)
    good, w = _use_mask(vis, weight, flag, pol_mask, uv_mask)
    v = np.where(good, vis, 0).astype(np.complex128)
    if phasor is not None:
        p = np.asarray(phasor, dtype=np.complex128)[:, :, None]
        v = v * p
        p2 = (p.real**2 + p.imag**2) * np.ones((1, 1, vis.shape[2]))
    else:
        p2 = np.ones(vis.shape)
    if noise is None:
        var_w = w  # w^2 * (1/w)
        kind = np.full(vis.shape, 2.0)
    else:
        nz = np.asarray(noise, dtype=np.float64)
        per_row = np.tile(nz, (vis.shape[0] // nz.shape[0], 1, 1))[:, None, :, :]
        var_w = w * (w * per_row[..., 0] + per_row[..., 1])
        kind = np.broadcast_to(per_row[..., 2], vis.shape)
    return np.array([np.sum(w * v.real), np.sum(w), np.sum(w * p2), np.sum(w * v.imag),
                     float(np.count_nonzero(good)), np.sum(np.where(good, var_w, 0.0) * p2),
                     float(np.count_nonzero(good & (kind == 1))),
                     float(np.count_nonzero(good & (kind == 2)))])


#: Columns of :func:`profile_sums`: sum w, w Re, w Im, w^2, w^2 Re, w^2 Re^2, w^2 Im,
#: w^2 Im^2, count.
NPROFILE = 9


@numba.njit(cache=True)
def _profile_sums_numba(vis, weight, flag, uvw, fc, edges, pol_mask, out):
    nt, nb, nc, npol = vis.shape
    nbin = edges.size - 1
    lo = edges[0]
    hi = edges[-1]
    for t in range(nt):
        for b in range(nb):
            q0 = math.hypot(uvw[t, b, 0], uvw[t, b, 1])
            for c in range(nc):
                q = q0 * fc[c]
                if not (q >= lo and q <= hi):
                    continue
                k = np.searchsorted(edges, q, side="right") - 1
                k = min(max(k, 0), nbin - 1)
                for p in range(npol):
                    if flag[t, b, c, p] or not pol_mask[p]:
                        continue
                    w = np.float64(weight[t, b, c, p])
                    if not w > 0:
                        continue
                    re = np.float64(vis[t, b, c, p].real)
                    im = np.float64(vis[t, b, c, p].imag)
                    if not (math.isfinite(re) and math.isfinite(im)):
                        continue
                    w2 = w * w
                    out[k, 0] += w
                    out[k, 1] += w * re
                    out[k, 2] += w * im
                    out[k, 3] += w2
                    out[k, 4] += w2 * re
                    out[k, 5] += w2 * re * re
                    out[k, 6] += w2 * im
                    out[k, 7] += w2 * im * im
                    out[k, 8] += 1.0


def profile_sums(vis, weight, flag, uvw, frequency, edges, pol_mask) -> np.ndarray:
    """The uv-profile sums of one (time, baseline) block of stacked visibilities.

    Parameters
    ----------
    vis, weight, flag : (nt, nb, nchan, npol)
        Visibilities (Jy), weights, flags.
    uvw : (nt, nb, 3) float
        Baseline coordinates, metres.
    frequency : (nchan,) float
        Channel frequencies, Hz.
    edges : (nbin + 1,) float
        Increasing bin edges in wavelengths; a visibility at uv distance q (wavelengths)
        falls in bin k when ``edges[k] <= q < edges[k + 1]`` (the last bin includes its
        upper edge); outside ``[edges[0], edges[-1]]`` it is left out.
    pol_mask : (npol,) bool
        Polarizations that enter.

    Returns
    -------
    (nbin, NPROFILE) float64
        Per bin: sum w, w Re, w Im, w^2, w^2 Re, w^2 Re^2, w^2 Im, w^2 Im^2 and the count of
        unflagged, finite visibilities with positive weight. One pass, no chunk-sized
        temporaries (compiled).
    """
    edges = np.ascontiguousarray(edges, dtype=np.float64)
    out = np.zeros((edges.size - 1, NPROFILE))
    fc = np.asarray(frequency, dtype=np.float64) / SPEED_OF_LIGHT
    _profile_sums_numba(np.asarray(vis), np.asarray(weight), np.asarray(flag, dtype=bool),
                        np.asarray(uvw, dtype=np.float64), fc, edges,
                        np.ascontiguousarray(pol_mask, dtype=bool), out)
    return out
