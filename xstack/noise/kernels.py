"""One-pass Monte Carlo stacking sums (numpy/numba only; no dask, no xarray).

For one block of visibility rows the kernel evaluates, for every stacking position k (all
realisations at once), the stacking phasor p_kc = exp(-2 pi i (u l_k + v m_k + w (n_k - 1))
nu_c / c) (paper eq. 4) and accumulates

* ``X[k]  += sum_c a[c, k] Re(VW[row, c] p_kc)`` - the data term of position k, where
  ``VW = sum_pol W V`` over the parallel hands (Stokes I) and ``a`` is the stacking
  coefficient (w_k / A_k(nu) / sum w, or 1/A_k(nu) before normalisation);
* per group g (one Monte Carlo realisation), with P_gc = sum_{k in g} a[c, k] p_kc and the
  injected model M_gc = sum_{k in g} b[c, k] conj(p_kc) (b = S_k A_k(nu): equation 1),
  ``model[g] += sum_c WS[row, c] Re(M_gc P_gc)`` with ``WS = sum_pol W``. Because stacking is
  linear, stack(data + model_g, positions_g) = data term + this model term, exactly: the
  injected sources never have to be written into the visibilities;
* optionally the uv-profile of every group's stacked visibilities:
  ``prof[g, bin[row, c]] += Re(VW P_gc) + WS Re(M_gc P_gc)``.

Phases are computed in float64 *turns* with an exact range reduction and a branch-free
polynomial for exp(-2 pi i t) (vectorisable, error < 1e-15); along evenly spaced channels
the phasor advances by complex multiplication (recurrence), re-seeded exactly every
``reseed`` channels.

:func:`group_sums_antenna` computes the same sums for blocks of (time, baseline) rows whose
UVW are differences of per-antenna UVW (:func:`antenna_layout` solves and checks them): the
phasor factorises as p = E_a1 conj(E_a2), so the phases, sine/cosine and channel recurrence
are evaluated per antenna and time, and each (row, channel, position) costs one complex
product. :func:`group_sums` is the per-row kernel and the fallback.
"""

from __future__ import annotations

import numba
import numpy as np

from xstack._antenna import (  # noqa: F401  (re-exported: the noise API since its start)
    ANTENNA_TOL_RAD,
    AntennaLayout,
    FactorisationError,
    antenna_layout,
)
from xstack._cluster import cap_numba_threads
from xstack._phase import antenna_channel, antenna_phases
from xstack._phase import cis_minus_turns as _cis_minus
from xstack.coords import SPEED_OF_LIGHT

DEFAULT_RESEED = 16

_FM = {"reassoc", "contract", "nsz", "arcp"}


@numba.njit(inline="always")
def _row_terms(g, row, c, sPr, sPi, sMr, sMi, vw_re, vw_im, ws, bins, nbins, prof, profm):
    """Data term Re(VW P) and model term WS Re(M P) of one (row, channel) for group ``g``,
    added to the group's uv-profile bin when profiles are asked for."""
    dterm = vw_re[row, c] * sPr - vw_im[row, c] * sPi
    mterm = ws[row, c] * (sMr * sPr - sMi * sPi)
    if nbins > 0:
        bi = bins[row, c]
        if bi >= 0:
            prof[g, bi] += dterm
            profm[g, bi] += mterm
    return dterm, mterm


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def _group_numba(uvw, fc, step, even, reseed, vw_re, vw_im, ws, row_ok, l, m, n1, a, b,
                 starts, with_model, bins, nbins, data, model, prof, profm):
    nrow = uvw.shape[0]
    nchan = fc.shape[0]
    ngroup = starts.shape[0] - 1
    for g in numba.prange(ngroup):
        k0 = starts[g]
        nk = starts[g + 1] - k0
        pr = np.empty(nk)
        pi = np.empty(nk)
        dr = np.empty(nk)
        di = np.empty(nk)
        dd = np.empty(nk)
        dacc = 0.0
        macc = 0.0
        # 1-D views: indexing 2-D arrays inside the inner loops defeats vectorisation
        lg = l[k0:k0 + nk]
        mg = m[k0:k0 + nk]
        ng = n1[k0:k0 + nk]
        for row in range(nrow):
            if not row_ok[row]:
                continue
            u = uvw[row, 0]
            v = uvw[row, 1]
            w = uvw[row, 2]
            for j in range(nk):
                dd[j] = u * lg[j] + v * mg[j] + w * ng[j]
                dr[j], di[j] = _cis_minus(dd[j] * step)
            for c in range(nchan):
                if (not even) or c % reseed == 0:
                    for j in range(nk):
                        pr[j], pi[j] = _cis_minus(dd[j] * fc[c])
                sPr = 0.0
                sPi = 0.0
                sMr = 0.0
                sMi = 0.0
                arow = a[c, k0:k0 + nk]
                if with_model:
                    brow = b[c, k0:k0 + nk]
                    for j in range(nk):
                        ac = arow[j]
                        bc = brow[j]
                        re = pr[j]
                        im = pi[j]
                        sPr += ac * re
                        sPi += ac * im
                        sMr += bc * re
                        sMi -= bc * im
                        pr[j] = re * dr[j] - im * di[j]
                        pi[j] = re * di[j] + im * dr[j]
                else:
                    for j in range(nk):
                        ac = arow[j]
                        re = pr[j]
                        im = pi[j]
                        sPr += ac * re
                        sPi += ac * im
                        pr[j] = re * dr[j] - im * di[j]
                        pi[j] = re * di[j] + im * dr[j]
                dterm, mterm = _row_terms(g, row, c, sPr, sPi, sMr, sMi, vw_re, vw_im, ws,
                                          bins, nbins, prof, profm)
                dacc += dterm
                macc += mterm
        data[g] += dacc
        model[g] += macc


# The row/channel phasor recurrence below repeats _group_numba's on purpose (the only copy
# the duplicates audit keeps, with the antenna loops of uvstack.kernels): numba vectorises each
# prange body as one unit over its 1-D scratch views; a shared callee would need its own.
@numba.njit(parallel=True, cache=True, fastmath=_FM)
def _position_numba(uvw, fc, step, even, reseed, vw_re, vw_im, row_ok, l, m, n1, a, X):
    nrow = uvw.shape[0]
    nchan = fc.shape[0]
    K = l.shape[0]
    nblock = (K + 255) // 256
    for g in numba.prange(nblock):
        k0 = g * 256
        nk = min(K, k0 + 256) - k0
        pr = np.empty(nk)
        pi = np.empty(nk)
        dr = np.empty(nk)
        di = np.empty(nk)
        dd = np.empty(nk)
        xl = np.zeros(nk)
        lg = l[k0:k0 + nk]
        mg = m[k0:k0 + nk]
        ng = n1[k0:k0 + nk]
        for row in range(nrow):
            if not row_ok[row]:
                continue
            u = uvw[row, 0]
            v = uvw[row, 1]
            w = uvw[row, 2]
            for j in range(nk):
                dd[j] = u * lg[j] + v * mg[j] + w * ng[j]
                dr[j], di[j] = _cis_minus(dd[j] * step)
            for c in range(nchan):
                if (not even) or c % reseed == 0:
                    for j in range(nk):
                        pr[j], pi[j] = _cis_minus(dd[j] * fc[c])
                vr = vw_re[row, c]
                vi = vw_im[row, c]
                arow = a[c, k0:k0 + nk]
                for j in range(nk):
                    re = pr[j]
                    im = pi[j]
                    xl[j] += arow[j] * (vr * re - vi * im)
                    pr[j] = re * dr[j] - im * di[j]
                    pi[j] = re * di[j] + im * dr[j]
        for j in range(nk):
            X[k0 + j] += xl[j]


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def _group_antenna_numba(ant_uvw, ant_used, a1, a2, fc, step, even, reseed, vw_re, vw_im, ws,
                         row_ok, l, m, n1, a, b, starts, with_model, bins, nbins, data, model,
                         prof, profm):
    ntime = ant_uvw.shape[0]
    nant = ant_uvw.shape[1]
    nbl = a1.shape[0]
    nchan = fc.shape[0]
    ngroup = starts.shape[0] - 1
    for g in numba.prange(ngroup):
        k0 = starts[g]
        nk = starts[g + 1] - k0
        # per antenna: phase in turns per (1/m), current phasor, channel-step phasor
        dd = np.empty((nant, nk))
        er = np.empty((nant, nk))
        ei = np.empty((nant, nk))
        sr = np.empty((nant, nk))
        si = np.empty((nant, nk))
        dacc = 0.0
        macc = 0.0
        lg = l[k0:k0 + nk]
        mg = m[k0:k0 + nk]
        ng = n1[k0:k0 + nk]
        for t in range(ntime):
            r0 = t * nbl
            any_ok = False
            for bl in range(nbl):
                if row_ok[r0 + bl]:
                    any_ok = True
                    break
            if not any_ok:
                continue
            antenna_phases(ant_uvw[t], ant_used[t], lg, mg, ng, even, step, dd, sr, si)
            for c in range(nchan):
                antenna_channel(ant_used[t], (not even) or c % reseed == 0, fc[c], dd, er, ei,
                                sr, si)
                arow = a[c, k0:k0 + nk]
                brow = b[c, k0:k0 + nk]
                for bl in range(nbl):
                    row = r0 + bl
                    if not row_ok[row]:
                        continue
                    e1r = er[a1[bl]]
                    e1i = ei[a1[bl]]
                    e2r = er[a2[bl]]
                    e2i = ei[a2[bl]]
                    sPr = 0.0
                    sPi = 0.0
                    sMr = 0.0
                    sMi = 0.0
                    if with_model:
                        for j in range(nk):
                            # p = E1 conj(E2): the baseline phasor of position j
                            re = e1r[j] * e2r[j] + e1i[j] * e2i[j]
                            im = e1i[j] * e2r[j] - e1r[j] * e2i[j]
                            ac = arow[j]
                            bc = brow[j]
                            sPr += ac * re
                            sPi += ac * im
                            sMr += bc * re
                            sMi -= bc * im
                    else:
                        for j in range(nk):
                            re = e1r[j] * e2r[j] + e1i[j] * e2i[j]
                            im = e1i[j] * e2r[j] - e1r[j] * e2i[j]
                            ac = arow[j]
                            sPr += ac * re
                            sPi += ac * im
                    dterm, mterm = _row_terms(g, row, c, sPr, sPi, sMr, sMi, vw_re, vw_im, ws,
                                              bins, nbins, prof, profm)
                    dacc += dterm
                    macc += mterm
        data[g] += dacc
        model[g] += macc


def channels_evenly_spaced(frequency: np.ndarray, rtol: float = 1e-9) -> bool:
    """True if the channel frequencies are evenly spaced (the recurrence applies)."""
    f = np.asarray(frequency, dtype=np.float64)
    if f.size < 3:
        return True
    d = np.diff(f)
    return bool(np.all(np.abs(d - d[0]) <= rtol * np.abs(f).max()))


def _prepare(uvw, frequency, vis_w, wsum, l, m, n_minus_1, a):
    uvw = np.ascontiguousarray(uvw, dtype=np.float64)
    freq = np.asarray(frequency, dtype=np.float64)
    nrow, nchan = uvw.shape[0], freq.size
    vis_w = np.asarray(vis_w).reshape(nrow, nchan)
    wsum = np.ascontiguousarray(np.asarray(wsum, dtype=np.float64).reshape(nrow, nchan))
    l, m, n1 = (np.ascontiguousarray(x, dtype=np.float64) for x in (l, m, n_minus_1))
    a = np.ascontiguousarray(np.broadcast_to(a, (nchan, l.size)), dtype=np.float64)
    even = channels_evenly_spaced(freq)
    fc = freq / SPEED_OF_LIGHT
    step = float(fc[1] - fc[0]) if nchan > 1 else 0.0
    row_ok = np.any(wsum > 0, axis=1)
    vr = np.ascontiguousarray(vis_w.real, dtype=np.float64)
    vi = np.ascontiguousarray(vis_w.imag, dtype=np.float64)
    return uvw, fc, step, even, vr, vi, wsum, row_ok, l, m, n1, a


def _check_starts(starts, K):
    starts = np.ascontiguousarray(starts, dtype=np.int64)
    if starts[0] != 0 or starts[-1] != K or np.any(np.diff(starts) < 0):
        raise ValueError("starts must run from 0 to K, non-decreasing")
    return starts


def _bins(bins, nbins, nrow, nchan):
    if bins is None or nbins <= 0:
        return np.full((1, 1), -1, dtype=np.int64), 0
    return np.ascontiguousarray(bins, dtype=np.int64).reshape(nrow, nchan), int(nbins)


def group_sums(uvw: np.ndarray, frequency: np.ndarray, vis_w: np.ndarray, wsum: np.ndarray,
               l: np.ndarray, m: np.ndarray, n_minus_1: np.ndarray, a: np.ndarray,
               b: np.ndarray | None, starts: np.ndarray, *, bins: np.ndarray | None = None,
               nbins: int = 0, reseed: int = DEFAULT_RESEED
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Stacking sums of every group (Monte Carlo realisation) for one block of rows.

    Parameters
    ----------
    uvw : (nrow, 3) float64, metres
    frequency : (nchan,) Hz
    vis_w : (nrow, nchan) complex, sum over the parallel hands of W * V (Jy^-1)
    wsum : (nrow, nchan) float, sum over the parallel hands of W (Jy^-2)
    l, m, n_minus_1 : (K,) direction cosines of all positions (groups concatenated)
    a : (nchan, K) stacking coefficients (w_k / A_k(nu) / sum_{k in group} w_k)
    b : (nchan, K) injected apparent fluxes S_k A_k(nu) in Jy, or None (no injection)
    starts : (G + 1,) int, positions of group g are ``starts[g]:starts[g+1]``
    bins : (nrow, nchan) int, uv-bin of each visibility (-1: none), with ``nbins`` bins

    Returns
    -------
    data : (G,) sum over rows, channels of Re(VW P_g)
    model : (G,) sum of WS Re(M_g P_g) (the injected sources, stacked; zeros if b is None)
    prof, prof_model : (G, nbins) per-uv-bin sums of the data and the model terms
    """
    uvw, fc, step, even, vr, vi, wsum, row_ok, l, m, n1, a = _prepare(
        uvw, frequency, vis_w, wsum, l, m, n_minus_1, a)
    nrow, nchan, K = uvw.shape[0], fc.size, l.size
    with_model = b is not None
    b = (np.ascontiguousarray(np.broadcast_to(b, (nchan, K)), dtype=np.float64) if with_model
         else np.zeros((nchan, K)))
    starts = _check_starts(starts, K)
    G = starts.size - 1
    bins_arr, nbins = _bins(bins, nbins, nrow, nchan)
    data = np.zeros(G)
    model = np.zeros(G)
    prof = np.zeros((G, nbins))
    profm = np.zeros((G, nbins))
    if nrow and K:
        cap_numba_threads()
        _group_numba(uvw, fc, step, even, int(max(reseed, 1)), vr, vi, wsum, row_ok, l, m, n1,
                     a, b, starts, with_model, bins_arr, int(nbins), data, model, prof, profm)
    return data, model, prof, profm


def position_sums(uvw: np.ndarray, frequency: np.ndarray, vis_w: np.ndarray, wsum: np.ndarray,
                  l: np.ndarray, m: np.ndarray, n_minus_1: np.ndarray, a: np.ndarray, *,
                  reseed: int = DEFAULT_RESEED) -> np.ndarray:
    """Data term of every position separately: X[k] = sum a[c, k] Re(VW p_kc), (K,)."""
    uvw, fc, step, even, vr, vi, wsum, row_ok, l, m, n1, a = _prepare(
        uvw, frequency, vis_w, wsum, l, m, n_minus_1, a)
    X = np.zeros(l.size)
    if uvw.shape[0] and l.size:
        cap_numba_threads()
        _position_numba(uvw, fc, step, even, int(max(reseed, 1)), vr, vi, row_ok, l, m, n1, a, X)
    return X


def group_sums_antenna(layout: AntennaLayout, frequency: np.ndarray, vis_w: np.ndarray,
                       wsum: np.ndarray, l: np.ndarray, m: np.ndarray, n_minus_1: np.ndarray,
                       a: np.ndarray, b: np.ndarray | None, starts: np.ndarray, *,
                       bins: np.ndarray | None = None, nbins: int = 0,
                       reseed: int = DEFAULT_RESEED, tol_rad: float = ANTENNA_TOL_RAD
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`group_sums` through per-antenna phasors (same results to float64 rounding).

    The stacking phasor of baseline (a1, a2) factorises,
    ``exp(-2 pi i nu/c (u l + v m + w (n-1))) = E_a1 conj(E_a2)`` with
    ``E_a = exp(-2 pi i nu/c (u_a l + v_a m + w_a (n-1)))``: per time integration the
    sine/cosine evaluations are done for the antennas, not for every baseline, and each
    (baseline, channel, position) costs complex multiplications only.

    Parameters
    ----------
    layout : from :func:`antenna_layout` on this block's UVW (rows ordered time-major)
    tol_rad : largest accepted :meth:`AntennaLayout.phase_error`, radians
    (others as :func:`group_sums`)

    Raises
    ------
    FactorisationError
        The layout's phase error exceeds ``tol_rad``, or a row with weight was not part of
        the layout's fit.
    """
    freq = np.asarray(frequency, dtype=np.float64)
    nrow = layout.rows.size
    uvw_dummy = np.zeros((nrow, 3))
    _, fc, step, even, vr, vi, wsum, row_ok, l, m, n1, a = _prepare(
        uvw_dummy, freq, vis_w, wsum, l, m, n_minus_1, a)
    if np.any(row_ok & ~layout.rows):
        raise FactorisationError("rows with weight were not part of the antenna solution")
    err = layout.phase_error(l, m, n1, freq)
    if not err <= tol_rad:
        raise FactorisationError(f"antenna UVW reproduce the baseline UVW only to a phase error "
                                 f"of {err:.3g} rad (tolerance {tol_rad:.3g} rad)")
    nchan, K = fc.size, l.size
    with_model = b is not None
    b = (np.ascontiguousarray(np.broadcast_to(b, (nchan, K)), dtype=np.float64) if with_model
         else np.zeros((nchan, K)))
    starts = _check_starts(starts, K)
    G = starts.size - 1
    bins_arr, nbins = _bins(bins, nbins, nrow, nchan)
    data, model = np.zeros(G), np.zeros(G)
    prof, profm = np.zeros((G, nbins)), np.zeros((G, nbins))
    if nrow and K:
        cap_numba_threads()
        _group_antenna_numba(np.ascontiguousarray(layout.uvw), layout.used, layout.antenna1,
                             layout.antenna2, fc, step, even, int(max(reseed, 1)), vr, vi, wsum,
                             row_ok, l, m, n1, a, b, starts, with_model, bins_arr, int(nbins),
                             data, model, prof, profm)
    return data, model, prof, profm


def _phasors_numpy(uvw, frequency, l, m, n_minus_1):
    uvw = np.asarray(uvw, dtype=np.float64)
    fc = np.asarray(frequency, dtype=np.float64) / SPEED_OF_LIGHT
    d = uvw[:, 0:1] * l[None] + uvw[:, 1:2] * m[None] + uvw[:, 2:3] * n_minus_1[None]
    return np.exp(-2j * np.pi * d[:, None, :] * fc[None, :, None])  # (nrow, nchan, K)


def position_sums_numpy(uvw, frequency, vis_w, wsum, l, m, n_minus_1, a):
    """Plain-numpy reference of :func:`position_sums`."""
    p = _phasors_numpy(uvw, frequency, l, m, n_minus_1)
    a = np.broadcast_to(a, (p.shape[1], len(l)))
    return np.einsum("rc,ck,rck->k", vis_w, a, p).real


def group_sums_numpy(uvw, frequency, vis_w, wsum, l, m, n_minus_1, a, b, starts, *, bins=None,
                     nbins: int = 0):
    """Plain-numpy reference of :func:`group_sums` (np.exp of the full phase; slow)."""
    p = _phasors_numpy(uvw, frequency, l, m, n_minus_1)
    nchan, K = p.shape[1], len(l)
    a = np.broadcast_to(a, (nchan, K))
    G = len(starts) - 1
    data, model = np.zeros(G), np.zeros(G)
    prof, profm = np.zeros((G, nbins)), np.zeros((G, nbins))
    for g in range(G):
        sl = slice(starts[g], starts[g + 1])
        P = np.einsum("ck,rck->rc", a[:, sl], p[:, :, sl])
        stacked = (vis_w * P).real
        data[g] = stacked.sum()
        mt = np.zeros_like(stacked)
        if b is not None:
            bb = np.broadcast_to(b, (nchan, K))
            M = np.einsum("ck,rck->rc", bb[:, sl], np.conj(p[:, :, sl]))
            mt = (wsum * M * P).real
            model[g] = mt.sum()
        if nbins:
            ok = bins >= 0
            prof[g] = np.bincount(bins[ok], stacked[ok], nbins)
            profm[g] = np.bincount(bins[ok], mt[ok], nbins)
    return data, model, prof, profm
