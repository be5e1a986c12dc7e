"""Numerical kernels of the uv-domain line stack: numpy and numba only, no dask, no xarray.

For target k (direction cosines l_k, m_k, n_k - 1; observed line centre nu_c,k; position
weight W_k; primary beam A_k(nu)) a visibility V of row r, channel i, correlation p with
weight w enters velocity bin j with the overlap o_kij (km/s) of the channel's velocity
interval about nu_c,k with the bin. Per (row, channel) the kernel forms

    Q_j = sum_k W_k o_kij / A_k(nu_i) exp(-2 pi i (u l_k + v m_k + w (n_k - 1)) nu_i / c)
    d_j = sum_k W_k o_kij

and adds, over the usable correlations (unflagged, weight > 0, finite),

    N_j += Re(sum_p w_p V_p Q_j),  D_j += (sum_p w_p) d_j,
    C_jj' += (sum_p w_p) Re(Q_j conj(Q_j'))

so that the stacked flux density of bin j is S_j = N_j / D_j and its covariance
C_jj' / (D_j D_j') (each visibility's real part has variance 1/w, as in the continuum stack's
``flux_err_jy``). The channel's velocity interval uses the channel's frequency edges scaled
by the row's frame ratio r (nu_frame = r nu_data); the phase uses the data frequency nu_i.

How it is evaluated: the targets are sorted by line centre, so a channel reaches a
contiguous range of them and each bin a contiguous sub-range; the overlaps W_k o / A_k of
every (channel, bin) are tabulated once per frame ratio (:func:`_bin_tables`: per row only
the phasors change). Each target's phasor advances from channel to channel by a step phasor
and is evaluated exactly every ``reseed`` channels (the continuum kernel's recurrence). The
covariance terms of 256 (row, channel) visibilities are added at once as dot products of
contiguous rows (:func:`_syrk_upper`): C costs ~nbin^2 multiply-adds per (row, channel),
the rest ~2 per (target, channel) reached.

Rows of one frame ratio are walked in batches (up to :data:`_MAX_ROWS`), channel by channel:
the phasors of the batch's rows advance together and each overlap weight is read once per
batch for all its rows, so the weight tables (~1 MB for 1000 targets and 256 channels) are
streamed from cache once per batch, not once per row (1.8x faster at 32 rows than row by row).

The rows are cut into blocks of :data:`xstack.uvstack.kernels.SUM_BLOCK_ROWS`, each block
summed serially and the blocks' sums added in block order (the batch size depends on the
number of targets only), so the sums are the same to the last bit on any number of threads.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from xstack._cluster import cap_numba_threads
from xstack._phase import cis_minus_turns
from xstack.spectral import SPEED_OF_LIGHT_KMS
from xstack.uvstack.kernels import (
    _KERNEL_LOCK,
    DEFAULT_RESEED,
    SUM_BLOCK_ROWS,
    channels_evenly_spaced,
)

#: Bytes of per-block covariance partial sums held at once (the blocks of a group are summed
#: in parallel, the groups one after the other; the group size depends on the number of bins
#: only, never on the thread count, so the fold order is fixed).
_GROUP_BYTES = 64 * 2**20


@numba.njit(cache=True)
def _first_above(a, x):
    """First index i with a[i] > x (a increasing)."""
    lo = 0
    hi = a.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if a[mid] > x:
            hi = mid
        else:
            lo = mid + 1
    return lo


@numba.njit(cache=True)
def _first_at_or_above(a, x):
    """First index i with a[i] >= x (a increasing)."""
    lo = 0
    hi = a.shape[0]
    while lo < hi:
        mid = (lo + hi) // 2
        if a[mid] >= x:
            hi = mid
        else:
            lo = mid + 1
    return lo


@numba.njit(cache=True)
def _channel_ranges(r, lo_s, hi_s, centre, e0, e1, monotone, s0, s1):
    """Per target, the sorted channels [s0, s1) whose interval can reach the grid [e0, e1]."""
    c = SPEED_OF_LIGHT_KMS
    nchan = lo_s.shape[0]
    for k in range(centre.shape[0]):
        if monotone:
            fmin = centre[k] * (1.0 - e1 / c) / r
            fmax = centre[k] * (1.0 - e0 / c) / r
            s0[k] = _first_above(hi_s, fmin)
            s1[k] = _first_at_or_above(lo_s, fmax)
        else:
            s0[k] = 0
            s1[k] = nchan


@numba.njit(cache=True)
def _bin_tables(r, lo_s, hi_s, centre, coef_s, wk, e0, dv, nbin, s0, s1):
    """The row-independent part of one frame ratio ``r``, per sorted channel s.

    Targets are sorted by line centre, so the targets a channel reaches are a contiguous
    range [klo[s], khi[s]) and, for each bin j, those whose channel interval overlaps it
    too: [kb0[s, j], kb0[s, j] + kn[s, j]). ``ew[koff[s, j] + i]`` is W_k o / A_k(nu_s) of the
    i-th of them (o: the overlap length, km/s), ``dw[s, j]`` the sum of W_k o; the bins
    reached are [jlo[s], jhi[s]].
    """
    c = SPEED_OF_LIGHT_KMS
    nchan = lo_s.shape[0]
    ntgt = centre.shape[0]
    klo = np.zeros(nchan, dtype=np.int64)
    khi = np.zeros(nchan, dtype=np.int64)
    for s in range(nchan):
        a = 0
        while a < ntgt and s1[a] <= s:
            a += 1
        b = a
        while b < ntgt and s0[b] <= s:
            b += 1
        klo[s] = a
        khi[s] = max(a, b)
    kb0 = np.zeros((nchan, nbin), dtype=np.int64)
    kn = np.zeros((nchan, nbin), dtype=np.int64)
    koff = np.zeros((nchan, nbin), dtype=np.int64)
    dw = np.zeros((nchan, nbin))
    jlo = np.full(nchan, nbin, dtype=np.int64)
    jhi = np.full(nchan, -1, dtype=np.int64)
    kend = np.zeros(nbin, dtype=np.int64)
    total = 0
    for s in range(nchan):
        for j in range(nbin):
            kb0[s, j] = khi[s]
            kend[j] = klo[s]
        for k in range(klo[s], khi[s]):
            vlo = c * (1.0 - r * hi_s[s] / centre[k])
            vhi = c * (1.0 - r * lo_s[s] / centre[k])
            j0 = max(0, int(math.floor((vlo - e0) / dv)))
            j1 = min(nbin - 1, int(math.floor((vhi - e0) / dv)))
            for j in range(j0, j1 + 1):
                if min(vhi, e0 + (j + 1) * dv) - max(vlo, e0 + j * dv) > 0:
                    kb0[s, j] = min(kb0[s, j], k)
                    kend[j] = max(kend[j], k + 1)
        for j in range(nbin):
            if kend[j] > kb0[s, j]:
                kn[s, j] = kend[j] - kb0[s, j]
                koff[s, j] = total
                total += kn[s, j]
                jlo[s] = min(jlo[s], j)
                jhi[s] = max(jhi[s], j)
            else:
                kb0[s, j] = 0
    ew = np.zeros(total)
    for s in range(nchan):
        for j in range(jlo[s], jhi[s] + 1):
            for i in range(kn[s, j]):
                k = kb0[s, j] + i
                vlo = c * (1.0 - r * hi_s[s] / centre[k])
                vhi = c * (1.0 - r * lo_s[s] / centre[k])
                o = min(vhi, e0 + (j + 1) * dv) - max(vlo, e0 + j * dv)
                if o > 0:
                    ew[koff[s, j] + i] = coef_s[k, s] * o
                    dw[s, j] += wk[k] * o
    return klo, khi, kb0, kn, koff, ew, dw, jlo, jhi


@numba.njit(fastmath={"reassoc", "contract"}, cache=True)
def _syrk_upper(at, ncol, acc, base, nbin):
    """acc[base + ja * nbin + jb] += sum_i at[ja, i] at[jb, i] for jb >= ja, i < ncol.

    The covariance of a batch of (row, channel) visibilities at once: dot products of
    contiguous rows, four at a time (each element of row ja loaded once for four), which
    'reassoc' lets vectorise; the order is fixed by the code, never by the thread count.
    Rows of ``at`` that are all zero are skipped."""
    nz = np.zeros(nbin, dtype=np.bool_)
    for ja in range(nbin):
        for i in range(ncol):
            if at[ja, i] != 0.0:
                nz[ja] = True
                break
    for ja in range(nbin):
        if not nz[ja]:
            continue
        ra = at[ja, :ncol]
        jb = ja
        while jb + 4 <= nbin:
            r0 = at[jb, :ncol]
            r1 = at[jb + 1, :ncol]
            r2 = at[jb + 2, :ncol]
            r3 = at[jb + 3, :ncol]
            t0 = 0.0
            t1 = 0.0
            t2 = 0.0
            t3 = 0.0
            for i in range(ncol):
                x = ra[i]
                t0 += x * r0[i]
                t1 += x * r1[i]
                t2 += x * r2[i]
                t3 += x * r3[i]
            o = base + ja * nbin + jb
            acc[o] += t0
            acc[o + 1] += t1
            acc[o + 2] += t2
            acc[o + 3] += t3
            jb += 4
        while jb < nbin:
            rb = at[jb, :ncol]
            t = 0.0
            for i in range(ncol):
                t += ra[i] * rb[i]
            acc[base + ja * nbin + jb] += t
            jb += 1


#: (row, channel) visibilities whose covariance terms are added in one batch (x2: the real
#: and imaginary parts of Q are two columns each)
_BATCH = 256
#: Rows (of one frame ratio) walked together channel by channel: each channel's overlap
#: weights (~1 MB per frame ratio for 1000 targets and 256 channels) are then read from cache
#: once per batch instead of once per row: 32 rows made the kernel 1.8x faster than 1
#: (1000 targets, 256 channels; 8: 1.4x, 64: no further gain). Fewer when the per-target
#: arrays of a batch (5 x 8 bytes per target and row, per thread) would pass _ROWS_BYTES.
_MAX_ROWS = 32
_ROWS_BYTES = 8 * 2**20


@numba.njit(parallel=True, fastmath={"contract"}, cache=True)
def _line_sums_numba(vis, weight, flag, uvw, ratio, order, lo_s, hi_s, fc_s, step, even, reseed,
                     l, m, n1, centre, coef_s, wk, e0, dv, nbin, monotone, pol_mask, uv_mask,
                     has_uv, write, out_num, out_den, out_var, group, nrows):
    nrow, _nchan, npol = vis.shape
    nchan = order.shape[0]
    ntgt = centre.shape[0]
    e1 = e0 + nbin * dv
    nblock = (nrow + SUM_BLOCK_ROWS - 1) // SUM_BLOCK_ROWS
    nsum = 2 * nbin + nbin * nbin + 1
    cbase = 2 * nbin
    total = np.zeros(nsum)
    for g0 in range(0, nblock, group):
        g1 = min(nblock, g0 + group)
        part = np.zeros((g1 - g0, nsum))
        for blk in numba.prange(g0, g1):
            acc = part[blk - g0]
            # per batch of rows (up to nrows, one frame ratio): Q_j of each row of the batch
            qr = np.zeros((nbin, nrows))
            qi = np.zeros((nbin, nrows))
            # the batch of sqrt(w) Q columns whose outer products make the covariance
            at = np.zeros((nbin, 2 * _BATCH))
            col = 0
            s0 = np.empty(ntgt, dtype=np.int64)
            s1 = np.empty(ntgt, dtype=np.int64)
            klo = np.zeros(nchan, dtype=np.int64)
            khi = np.zeros(nchan, dtype=np.int64)
            kb0 = np.zeros((nchan, nbin), dtype=np.int64)
            kn = np.zeros((nchan, nbin), dtype=np.int64)
            koff = np.zeros((nchan, nbin), dtype=np.int64)
            ew = np.zeros(0)
            dw = np.zeros((nchan, nbin))
            jlo = np.zeros(nchan, dtype=np.int64)
            jhi = np.full(nchan, -1, dtype=np.int64)
            # per target and row of the batch: path difference, the phasor at the channel
            # last processed and the channel-step phasor (the continuum kernel's recurrence)
            dk = np.empty((ntgt, nrows))
            zr = np.zeros((ntgt, nrows))
            zi = np.zeros((ntgt, nrows))
            sr = np.empty((ntgt, nrows))
            si = np.empty((ntgt, nrows))
            # per row of the batch: the flux's weighted sums of the current channel
            wsum_b = np.zeros(nrows)
            vwr_b = np.zeros(nrows)
            vwi_b = np.zeros(nrows)
            nuse_b = np.zeros(nrows, dtype=np.int64)
            last_r = np.nan
            row_end = min(nrow, (blk + 1) * SUM_BLOCK_ROWS)
            row = blk * SUM_BLOCK_ROWS
            while row < row_end:
                r = ratio[row]
                nrb = 1
                while nrb < nrows and row + nrb < row_end and ratio[row + nrb] == r:
                    nrb += 1
                if r != last_r:
                    # which targets and bins each channel reaches, and the overlaps, change
                    # with the frame ratio only
                    _channel_ranges(r, lo_s, hi_s, centre, e0, e1, monotone, s0, s1)
                    klo, khi, kb0, kn, koff, ew, dw, jlo, jhi = _bin_tables(
                        r, lo_s, hi_s, centre, coef_s, wk, e0, dv, nbin, s0, s1)
                    last_r = r
                for b in range(nrb):
                    u = uvw[row + b, 0]
                    v = uvw[row + b, 1]
                    w = uvw[row + b, 2]
                    for k in range(ntgt):
                        dk[k, b] = u * l[k] + v * m[k] + w * n1[k]
                if even:
                    for k in range(ntgt):
                        for b in range(nrb):
                            sr[k, b], si[k, b] = cis_minus_turns(dk[k, b] * step)
                prev_s = -2
                prev_khi = 0
                for s in range(nchan):
                    if jhi[s] < 0:
                        continue
                    ch = order[s]
                    # each row's flux correlations of this channel, and whether the batch
                    # has any visibility to use here
                    needed = False
                    for b in range(nrb):
                        in_uv = (not has_uv) or uv_mask[row + b, ch]
                        wsum = 0.0
                        vwr = 0.0
                        vwi = 0.0
                        nuse = 0
                        for p in range(npol):
                            if flag[row + b, ch, p]:
                                continue
                            wp = np.float64(weight[row + b, ch, p])
                            if not wp > 0:
                                continue
                            vr = np.float64(vis[row + b, ch, p].real)
                            vi = np.float64(vis[row + b, ch, p].imag)
                            if not (math.isfinite(vr) and math.isfinite(vi)):
                                continue
                            needed = needed or write
                            if in_uv and pol_mask[p]:
                                wsum += wp
                                vwr += wp * vr
                                vwi += wp * vi
                                nuse += 1
                        wsum_b[b] = wsum
                        vwr_b[b] = vwr
                        vwi_b[b] = vwi
                        nuse_b[b] = nuse
                        needed = needed or nuse > 0
                    if not needed:
                        continue
                    # the phasors of the targets this channel reaches, for every row of the
                    # batch: advanced from the previous channel where it was processed,
                    # exactly every reseed channels and for targets entering the range
                    f = fc_s[s]
                    ka = klo[s]
                    kb = khi[s]
                    kseed = ka
                    if even and s % reseed != 0 and prev_s == s - 1:
                        kseed = max(ka, min(kb, prev_khi))
                        for k in range(ka, kseed):
                            for b in range(nrb):
                                a_r = zr[k, b] * sr[k, b] - zi[k, b] * si[k, b]
                                zi[k, b] = zr[k, b] * si[k, b] + zi[k, b] * sr[k, b]
                                zr[k, b] = a_r
                    for k in range(kseed, kb):
                        for b in range(nrb):
                            zr[k, b], zi[k, b] = cis_minus_turns(dk[k, b] * f)
                    prev_s = s
                    prev_khi = kb
                    j_lo = jlo[s]
                    j_hi = jhi[s]
                    # Q_j of every row of the batch: each weight W_k o / A_k read once for the
                    # batch (the tables are streamed from cache once per batch, not per row)
                    for j in range(j_lo, j_hi + 1):
                        off = koff[s, j]
                        k0 = kb0[s, j]
                        for b in range(nrb):
                            qr[j, b] = 0.0
                            qi[j, b] = 0.0
                        for i in range(kn[s, j]):
                            ee = ew[off + i]
                            for b in range(nrb):
                                qr[j, b] += ee * zr[k0 + i, b]
                                qi[j, b] += ee * zi[k0 + i, b]
                    for b in range(nrb):
                        if nuse_b[b] > 0:
                            wsum = wsum_b[b]
                            vwr = vwr_b[b]
                            vwi = vwi_b[b]
                            sw = math.sqrt(wsum)
                            for ja in range(j_lo, j_hi + 1):
                                acc[ja] += vwr * qr[ja, b] - vwi * qi[ja, b]
                                acc[nbin + ja] += wsum * dw[s, ja]
                                at[ja, col] = sw * qr[ja, b]
                                at[ja, col + 1] = sw * qi[ja, b]
                            col += 2
                            if col == 2 * _BATCH:
                                _syrk_upper(at, col, acc, cbase, nbin)
                                at[:, :] = 0.0
                                col = 0
                            acc[nsum - 1] += nuse_b[b]
                        if write:
                            rw = row + b
                            for p in range(npol):
                                if flag[rw, ch, p]:
                                    continue
                                wp = np.float64(weight[rw, ch, p])
                                if not wp > 0:
                                    continue
                                vr = np.float64(vis[rw, ch, p].real)
                                vi = np.float64(vis[rw, ch, p].imag)
                                if not (math.isfinite(vr) and math.isfinite(vi)):
                                    continue
                                for ja in range(j_lo, j_hi + 1):
                                    out_num[rw, ja, p] += wp * complex(
                                        vr * qr[ja, b] - vi * qi[ja, b],
                                        vr * qi[ja, b] + vi * qr[ja, b])
                                    out_den[rw, ja, p] += wp * dw[s, ja]
                                    out_var[rw, ja, p] += wp * (qr[ja, b] * qr[ja, b]
                                                                + qi[ja, b] * qi[ja, b])
                row += nrb
            if col > 0:
                _syrk_upper(at, col, acc, cbase, nbin)
        for b in range(g1 - g0):  # in block order, however prange shared the blocks out
            for x in range(nsum):
                total[x] += part[b, x]
    # the covariance was summed on its upper triangle
    for ja in range(nbin):
        for jb in range(ja + 1, nbin):
            total[cbase + jb * nbin + ja] = total[cbase + ja * nbin + jb]
    return total


@numba.njit(cache=True)
def _coverage_numba(usable, ratio_t, lo_s, hi_s, centre, e0, dv, nbin, monotone, out):
    """out[k, j] = 1 where target k has a usable channel overlapping bin j."""
    ntime, nchan = usable.shape
    ntgt = centre.shape[0]
    c = SPEED_OF_LIGHT_KMS
    s0 = np.empty(ntgt, dtype=np.int64)
    s1 = np.empty(ntgt, dtype=np.int64)
    for t in range(ntime):
        r = ratio_t[t]
        _channel_ranges(r, lo_s, hi_s, centre, e0, e0 + nbin * dv, monotone, s0, s1)
        for k in range(ntgt):
            for s in range(s0[k], s1[k]):
                if not usable[t, s]:
                    continue
                vlo = c * (1.0 - r * hi_s[s] / centre[k])
                vhi = c * (1.0 - r * lo_s[s] / centre[k])
                j0 = max(0, int(math.floor((vlo - e0) / dv)))
                j1 = min(nbin - 1, int(math.floor((vhi - e0) / dv)))
                for j in range(j0, j1 + 1):
                    if min(vhi, e0 + (j + 1) * dv) - max(vlo, e0 + j * dv) > 0:
                        out[k, j] = 1.0


class ChannelLayout:
    """A partition's channels in increasing frequency: the order, edges and nu/c the kernels
    use (the channel axis of the data is left as it is)."""

    def __init__(self, frequency, channel_width):
        from xstack.coords import SPEED_OF_LIGHT

        freq = np.asarray(frequency, dtype=np.float64)
        width = np.abs(np.broadcast_to(np.asarray(channel_width, dtype=np.float64), freq.shape))
        self.order = np.argsort(freq, kind="stable").astype(np.int64)
        f = freq[self.order]
        half = 0.5 * width[self.order]
        self.lo = f - half
        self.hi = f + half
        self.fc = f / SPEED_OF_LIGHT
        # binary search of the channels a target reaches needs both edges increasing
        self.monotone = bool(np.all(np.diff(self.lo) >= 0) and np.all(np.diff(self.hi) >= 0))
        self.freq = f
        self.step = float(self.fc[1] - self.fc[0]) if f.size > 1 else 0.0


def line_sums(vis, weight, flag, uvw, ratio, layout: ChannelLayout, l, m, n_minus_1, centre_hz,
              coef, position_weight, edges, pol_mask=None, uv_mask=None, write=False,
              reseed=DEFAULT_RESEED):
    """The line-stack sums of one block of rows (float64, 2 nbin + nbin^2 + 1).

    Parameters
    ----------
    vis, weight, flag : (nrow, nchan, npol)
        Visibilities (Jy), weights (1/Jy^2), flags.
    uvw : (nrow, 3)
        Metres.
    ratio : (nrow,)
        Frame ratio per row: nu_frame = ratio * nu_data (1 for data in the frame asked for).
    layout
        :class:`ChannelLayout` of the data's channels.
    l, m, n_minus_1, centre_hz, position_weight : (ntarget,)
        Targets' direction cosines, observed line centres (Hz, in the frame) and W_k.
    coef : (ntarget, nchan)
        W_k / A_k(nu_i) in the data's channel order.
    edges : (nbin + 1,)
        Equal velocity bins, km/s (:func:`xstack.spectral.velocity_edges`).
    pol_mask : (npol,) bool, optional
        Correlations of the flux (all when None).
    uv_mask : (nrow, nchan) bool, optional
        Visibilities inside the uv range (the flux only).
    write
        Also return the stacked visibilities per (row, bin, correlation): every usable
        correlation, no uv range.
    reseed
        On evenly spaced channels each target's phasor advances by a step phasor from
        channel to channel and is evaluated exactly every ``reseed`` channels (as the
        continuum kernel: error ``reseed`` times a few 1e-16).

    Returns
    -------
    sums : ndarray
        ``[N (nbin), D (nbin), C (nbin * nbin, row-major), count]``.
    (num, den, var) : with ``write``, (nrow, nbin, npol) arrays: sum w V Q_j, sum w d_j and
        sum w |Q_j|^2 per row and correlation.
    """
    vis = np.asarray(vis)
    if vis.dtype.kind != "c":
        vis = vis.astype(np.complex128)
    nrow, nchan, npol = vis.shape
    edges = np.asarray(edges, dtype=np.float64)
    nbin = edges.size - 1
    dv = float(edges[1] - edges[0])
    pm = (np.ones(npol, dtype=bool) if pol_mask is None
          else np.ascontiguousarray(pol_mask, dtype=bool))
    has_uv = uv_mask is not None
    um = np.asarray(uv_mask, dtype=bool) if has_uv else np.ones((1, 1), dtype=bool)
    # targets sorted by line centre: a channel reaches a contiguous range of them (the sums
    # are per bin, so the order of the targets is not seen outside)
    centre_hz = np.asarray(centre_hz, dtype=np.float64)
    by_centre = np.argsort(centre_hz, kind="stable")
    l, m, n_minus_1, centre_hz, position_weight = (
        np.asarray(a, dtype=np.float64)[by_centre]
        for a in (l, m, n_minus_1, centre_hz, position_weight))
    coef_s = np.ascontiguousarray(
        np.asarray(coef, dtype=np.float64)[by_centre][:, layout.order])
    shape = (nrow, nbin, npol) if write else (1, 1, 1)
    num = np.zeros(shape, dtype=np.complex128)
    den = np.zeros(shape)
    var = np.zeros(shape)
    uvw = np.ascontiguousarray(uvw, dtype=np.float64)
    # the recurrence where the channels are evenly spaced to 1e-10 rad of phase (as the
    # continuum kernel decides it)
    even = bool(np.size(l) and nrow) and channels_evenly_spaced(
        layout.freq, float(np.abs(uvw).max(initial=0.0)),
        float(max(np.abs(l).max(), np.abs(m).max(), np.abs(n_minus_1).max())))
    group = max(1, min(64, _GROUP_BYTES // (8 * (2 * nbin + nbin * nbin + 1))))
    # rows walked together: set by the number of targets only, never by the thread count
    nrows = max(1, min(_MAX_ROWS, _ROWS_BYTES // (40 * max(1, np.size(l)))))
    args = (vis, np.asarray(weight), np.asarray(flag, dtype=bool),
            np.ascontiguousarray(uvw, dtype=np.float64),
            np.ascontiguousarray(ratio, dtype=np.float64), layout.order, layout.lo, layout.hi,
            layout.fc, layout.step, even, int(reseed),
            *(np.ascontiguousarray(a, dtype=np.float64)
                         for a in (l, m, n_minus_1, centre_hz)),
            coef_s, np.ascontiguousarray(position_weight, dtype=np.float64), float(edges[0]),
            dv, nbin, layout.monotone, pm, um, has_uv, bool(write), num, den, var, group,
            int(nrows))
    cap_numba_threads()
    with _KERNEL_LOCK:
        sums = _line_sums_numba(*args)
    return (sums, (num, den, var)) if write else sums


def line_coverage(usable, ratio_t, layout: ChannelLayout, centre_hz, edges) -> np.ndarray:
    """(ntarget, nbin) 1.0 where a target has a usable channel overlapping a bin.

    ``usable`` (ntime, nchan) in the data's channel order: some visibility of that time and
    channel enters the flux; ``ratio_t`` (ntime,) the frame ratio per time.
    """
    edges = np.asarray(edges, dtype=np.float64)
    nbin = edges.size - 1
    centre = np.ascontiguousarray(centre_hz, dtype=np.float64)
    out = np.zeros((centre.size, nbin))
    _coverage_numba(np.ascontiguousarray(np.asarray(usable, dtype=bool)[:, layout.order]),
                    np.ascontiguousarray(ratio_t, dtype=np.float64), layout.lo, layout.hi,
                    centre, float(edges[0]), float(edges[1] - edges[0]), nbin, layout.monotone,
                    out)
    return out
