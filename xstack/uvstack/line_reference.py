"""A plain-numpy uv-domain line stacker: the reference the tests hold the kernel to.

Written apart from :mod:`xstack.uvstack.line_kernels` (nothing shared beyond
:mod:`xstack.spectral`'s regridding): loops over partitions, targets and channels, the phases
with ``np.exp``, the overlap of each channel's velocity interval with the bins from
:func:`xstack.spectral.overlap_lengths`, the covariance from a dense per-visibility matrix.
Slow and memory-hungry: small data only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from xstack.spectral import SPEED_OF_LIGHT_KMS, overlap_lengths

_C_M_S = SPEED_OF_LIGHT_KMS * 1e3  # m/s


@dataclass
class ReferencePartition:
    """One partition's data and targets, everything as plain arrays.

    vis, weight, flag: (ntime, nbl, nchan, npol); uvw: (ntime, nbl, 3) metres; ratio: (ntime,)
    nu_frame / nu_data; frequency, width: (nchan,) Hz; l, m, n1, centre_hz, wk: (ntarget,);
    inv_att: (ntarget, nchan) 1 / A_k(nu_i); pol_mask: (npol,) bool; uv_mask: (ntime, nbl,
    nchan) bool or None.
    """

    vis: np.ndarray
    weight: np.ndarray
    flag: np.ndarray
    uvw: np.ndarray
    ratio: np.ndarray
    frequency: np.ndarray
    width: np.ndarray
    l: np.ndarray
    m: np.ndarray
    n1: np.ndarray
    centre_hz: np.ndarray
    wk: np.ndarray
    inv_att: np.ndarray
    pol_mask: np.ndarray
    uv_mask: np.ndarray | None = None
    index: np.ndarray | None = None  # (ntarget,) catalog rows of the targets


def reference_line_stack(parts: list[ReferencePartition], edges: np.ndarray):
    """(flux (nbin), error (nbin), covariance (nbin, nbin), n_targets_per_bin (nbin)).

    S_j = sum W_k w o_kij Re(V exp(-i phi_k)) / A_k / sum W_k w o_kij over every usable
    visibility of the selected correlations (unflagged, weight > 0, finite, in the uv range);
    Cov(S_j, S_j') = sum w Re(Q_j conj Q_j') / (D_j D_j') with Q_j the visibility's
    coefficient of bin j. NaN where no target covers a bin.
    """
    edges = np.asarray(edges, dtype=np.float64)
    nbin = edges.size - 1
    num = np.zeros(nbin)
    den = np.zeros(nbin)
    cov = np.zeros((nbin, nbin))
    covered: dict[int, np.ndarray] = {}
    for p in parts:
        nt, nb, nc, npol = p.vis.shape
        use = ~p.flag & (p.weight > 0) & np.isfinite(p.vis.real) & np.isfinite(p.vis.imag)
        use &= p.pol_mask[None, None, None, :]
        if p.uv_mask is not None:
            use &= p.uv_mask[..., None]
        w = np.where(use, p.weight.astype(np.float64), 0.0)
        vw = np.sum(w * np.where(use, p.vis, 0).astype(np.complex128), axis=3)  # (nt, nb, nc)
        wsum = w.sum(axis=3)
        usable_tc = (wsum > 0).any(axis=1)  # (nt, nc)
        q = np.zeros((nt, nb, nc, nbin), dtype=np.complex128)
        d = np.zeros((nt, nc, nbin))
        cover = np.zeros((len(p.centre_hz), nbin), dtype=bool)
        for k in range(len(p.centre_hz)):
            for i in range(nc):
                lo = p.frequency[i] - abs(p.width[i]) / 2
                hi = p.frequency[i] + abs(p.width[i]) / 2
                # the channel's velocity interval per time, in the frame asked for
                v = SPEED_OF_LIGHT_KMS * (1 - np.outer(p.ratio, [hi, lo]) / p.centre_hz[k])
                o = overlap_lengths(v, edges)  # (nt, nbin)
                if not o.any():
                    continue
                phase = (p.uvw[..., 0] * p.l[k] + p.uvw[..., 1] * p.m[k]
                         + p.uvw[..., 2] * p.n1[k]) * p.frequency[i] / _C_M_S
                ph = np.exp(-2j * np.pi * phase)  # (nt, nb)
                q[:, :, i, :] += (p.wk[k] * p.inv_att[k, i] * ph)[..., None] * o[:, None, :]
                d[:, i, :] += p.wk[k] * o
                cover[k] |= (usable_tc[:, i, None] & (o > 0)).any(axis=0)
        num += np.einsum("tbc,tbcj->j", vw, q).real
        den += np.einsum("tbc,tcj->j", wsum, d)
        cov += np.einsum("tbc,tbcj,tbck->jk", wsum, q, q.conj()).real
        index = np.arange(len(p.centre_hz)) if p.index is None else p.index
        for k, row in enumerate(index):
            covered[int(row)] = covered.get(int(row), np.zeros(nbin, dtype=bool)) | cover[k]
    with np.errstate(divide="ignore", invalid="ignore"):
        flux = np.where(den > 0, num / den, np.nan)
        c = np.where(np.outer(den, den) > 0, cov / np.outer(den, den), np.nan)
    n_targets = np.sum(list(covered.values()), axis=0) if covered else np.zeros(nbin)
    return flux, np.sqrt(np.diag(c)), c, np.asarray(n_targets, dtype=np.int64)
