"""Empirical visibility noise: the scatter of neighbouring channels (or integrations).

The WEIGHT column is often not 1/sigma^2 of the data (uncalibrated weights, missing
``statwt``, a correlator that writes a constant): the error bars computed from it are then
wrong by the same factor, silently. This module measures the noise from the visibilities
themselves, for any stage that needs it (uv-stacking error bars, analytic noise estimates).

Estimator
---------
For every baseline and correlation of a block of data (``ntime, nbl, nchan, npol``) the
differences ``d = V[t, c+1] - V[t, c]`` of neighbouring channels are formed over all times,
using only pairs where *both* cells are data (unflagged, finite, weight > 0). The pairs are
disjoint (channels 0-1, 2-3, ... of each run of data cells), so the differences are
independent and the small-sample correction below holds exactly (overlapping differences
share a cell, are correlated by -1/2, and bias the MAD differently for every run length). Continuum sky
signal nearly cancels in a channel difference (it changes by the fringe phase across one
channel width only), while independent noise of sigma per real/imaginary part gives
``Var(Re d) = Var(Im d) = 2 sigma^2``. The scatter is the median absolute deviation of the
real and imaginary parts (each about its own median, pooled),
``sigma^2 = (1.4826 MAD)^2 / 2`` times the small-sample correction ``m / (m - 2.6)``
(``m`` = 2 x pairs; measured by simulation of independent differences, unbiased to < 1 %
from 16 pairs on). The MAD
ignores a minority of outliers (RFI spikes, a few bad channels).

With a single channel the differences are taken between neighbouring integrations
(``V[t+1, c] - V[t, c]``) instead. They cancel the sky only where the fringe phase of the
source changes little between integrations: a bright source far from the phase center on
long baselines rotates through many radians per integration and its flux then counts as
noise (the estimate is too high, never too low). Channel differences are always preferred.

What the estimate assumes: noise independent between neighbouring channels (Hanning
smoothing or other correlated channels make the differences too small: Hanning correlates
neighbours by 2/3, and sigma is then low by sqrt(3) = 1.7), and a noise level constant
over the block's times and channels per baseline and correlation.

No dask or xarray here; numba kernels with plain numpy wrappers.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from xstack._cluster import cap_numba_threads
from xstack._vocabulary import MAD_TO_SIGMA

#: Fewest difference pairs for an estimate of one (baseline, correlation); below it the
#: estimate is NaN (relative error of sigma^2 from 16 pairs ~ 40 %, from 100 pairs ~ 16 %).
MIN_PAIRS = 16
#: Relative difference between an error from the weights and one from the measured noise
#: above which a stage warns that the weights are not 1/sigma^2 of the data
EMPIRICAL_TOLERANCE = 0.2
#: The MAD of a (baseline, correlation) uses at most about this many pairs, evenly spread
#: over the block (sigma^2 then to ~2.5 %; the medians are most of the cost)
MAX_PAIRS = 4096
#: Small-sample bias of the pooled MAD^2 (measured): E[est] = sigma^2 (1 - BIAS / m)
_MAD_BIAS = 2.6
#: Codes of the source of a (baseline, correlation)'s variance in :func:`noise_model`.
OWN, POOLED, WEIGHTS = 0, 1, 2


@numba.njit(cache=True)
def _good(v, w, f):
    return (not f) and w > 0 and np.isfinite(v.real) and np.isfinite(v.imag)


@numba.njit(parallel=True, cache=True)
def _pair_scatter_numba(vis, weight, flag, pol_mask, along_time, min_pairs, max_pairs, out_var,
                        out_n, out_invw):
    """Per (baseline, correlation): sigma^2 from pair differences, pair count, mean 1/w.

    One task per baseline reads its cells in memory order (time, channel, correlation).
    """
    nt, nb, nc, npol = vis.shape
    maxn = max(1, nt * (nc // 2) if not along_time else (nt // 2) * nc)
    nstate = nc * npol if along_time else npol
    for b in numba.prange(nb):
        dr = np.empty((npol, maxn))
        di = np.empty((npol, maxn))
        n = np.zeros(npol, dtype=np.int64)
        sinv = np.zeros(npol)
        ngood = np.zeros(npol, dtype=np.int64)
        prev = np.zeros(nstate, dtype=np.bool_)
        pr = np.zeros(nstate)
        pim = np.zeros(nstate)
        for t in range(nt):
            if not along_time:
                prev[:] = False  # channel pairs stay inside one integration
            for c in range(nc):
                for p in range(npol):
                    if not pol_mask[p]:
                        continue
                    k = c * npol + p if along_time else p
                    v = vis[t, b, c, p]
                    w = np.float64(weight[t, b, c, p])
                    ok = _good(v, w, flag[t, b, c, p])
                    if ok:
                        vr = np.float64(v.real)
                        vi = np.float64(v.imag)
                        sinv[p] += 1.0 / w
                        ngood[p] += 1
                        if prev[k]:
                            dr[p, n[p]] = vr - pr[k]
                            di[p, n[p]] = vi - pim[k]
                            n[p] += 1
                            # disjoint pairs: each cell in one difference only
                            ok = False
                        pr[k] = vr
                        pim[k] = vi
                    prev[k] = ok
        for p in range(npol):
            out_var[b, p] = np.nan
            out_n[b, p] = n[p]
            out_invw[b, p] = sinv[p] / ngood[p] if ngood[p] > 0 else np.nan
            if not pol_mask[p] or n[p] < min_pairs or n[p] == 0:
                continue
            # the medians dominate the cost: at most ~max_pairs pairs, spread evenly
            step = (n[p] + max_pairs - 1) // max_pairs
            xr = dr[p, :n[p]:step].copy()
            xi = di[p, :n[p]:step].copy()
            m = xr.size
            mr = np.median(xr)
            mi = np.median(xi)
            dev = np.empty(2 * m)
            for i in range(m):
                dev[i] = abs(xr[i] - mr)
                dev[m + i] = abs(xi[i] - mi)
            s = MAD_TO_SIGMA * np.median(dev)
            out_var[b, p] = 0.5 * s * s * (2.0 * m) / (2.0 * m - _MAD_BIAS)


@numba.njit(cache=True)
def _pooled_pairs(vis, weight, flag, pol_mask, along_time, step, zr, zi):
    """Walk the block's disjoint neighbour pairs (the order of :func:`_pooled_scale_numba`);
    store the normalised difference of every ``step``-th pair in ``zr``/``zi`` (when they
    have room). Returns the number of pairs."""
    nt, nb, nc, npol = vis.shape
    n = 0
    for b in range(nb):
        for p in range(npol):
            if not pol_mask[p]:
                continue
            outer = nc if along_time else nt
            inner = nt if along_time else nc
            for o in range(outer):
                prev = False
                pr = 0.0
                pim = 0.0
                pinv = 0.0
                for i in range(inner):
                    t = i if along_time else o
                    c = o if along_time else i
                    v = vis[t, b, c, p]
                    w = np.float64(weight[t, b, c, p])
                    ok = _good(v, w, flag[t, b, c, p])
                    if ok:
                        vr = np.float64(v.real)
                        vi = np.float64(v.imag)
                        if prev:
                            if n % step == 0 and n // step < zr.size:
                                norm = 1.0 / math.sqrt(pinv + 1.0 / w)
                                zr[n // step] = (vr - pr) * norm
                                zi[n // step] = (vi - pim) * norm
                            n += 1
                            ok = False
                        pr = vr
                        pim = vi
                        pinv = 1.0 / w
                    prev = ok
    return n


@numba.njit(cache=True)
def _pooled_scale_numba(vis, weight, flag, pol_mask, along_time, min_pairs, max_pairs):
    """(measured / claimed) variance of all disjoint pairs of the block, and the pair count.

    Each difference is normalised by the variance the weights claim for it,
    ``z = d / sqrt(1/w1 + 1/w2)``, so ``Var(Re z) = scale`` when the weights are right up to
    one factor; ``scale`` from the MAD of every k-th normalised difference, k = ceil(pairs /
    max_pairs) (as in the kernel above). Two walks over the block -- one counts the pairs,
    one keeps every k-th -- so memory is O(max_pairs), not O(block).
    """
    empty = np.empty(0)
    n = _pooled_pairs(vis, weight, flag, pol_mask, along_time, 1, empty, empty)
    if n < min_pairs or n == 0:
        return np.nan, n
    step = (n + max_pairs - 1) // max_pairs
    k = (n + step - 1) // step
    xr = np.empty(k)
    xi = np.empty(k)
    _pooled_pairs(vis, weight, flag, pol_mask, along_time, step, xr, xi)
    mr = np.median(xr)
    mi = np.median(xi)
    dev = np.empty(2 * k)
    for i in range(k):
        dev[i] = abs(xr[i] - mr)
        dev[k + i] = abs(xi[i] - mi)
    s = MAD_TO_SIGMA * np.median(dev)
    m = 2.0 * k
    return s * s * m / (m - _MAD_BIAS), n


def _prepare(vis, weight, flag, pol_mask):
    vis = np.asarray(vis)
    if vis.ndim != 4:
        raise ValueError(f"vis must have shape (ntime, nbl, nchan, npol), got {vis.shape}")
    if vis.dtype.kind != "c":
        vis = vis.astype(np.complex128)
    weight = np.broadcast_to(np.asarray(weight), vis.shape)
    flag = np.broadcast_to(np.asarray(flag, dtype=bool), vis.shape)
    npol = vis.shape[3]
    pm = (np.ones(npol, dtype=bool) if pol_mask is None
          else np.ascontiguousarray(pol_mask, dtype=bool))
    return vis, weight, flag, pm


def pair_variance(vis, weight, flag, *, pol_mask=None, along: str = "auto",
                  min_pairs: int = MIN_PAIRS, max_pairs: int = MAX_PAIRS
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise variance per (baseline, correlation) from differences of neighbouring cells.

    Parameters
    ----------
    vis : (ntime, nbl, nchan, npol) complex array
        Visibilities, Jy.
    weight : (ntime, nbl, nchan, npol) array
        Visibility weights (only their sign is used for the estimate: weight > 0 is data).
    flag : (ntime, nbl, nchan, npol) bool array
        Flags.
    pol_mask : (npol,) bool, optional
        Correlations to estimate (the others are NaN); default all.
    along
        ``"channel"``, ``"time"`` or ``"auto"`` (channels when nchan > 1, else time).
    min_pairs
        Fewest difference pairs for an estimate.
    max_pairs
        With more pairs than this, every k-th pair is used (k = ceil(pairs / max_pairs)).

    Returns
    -------
    variance : (nbl, npol) float64
        sigma^2 per real (and imaginary) part, Jy^2; NaN with fewer than ``min_pairs`` pairs.
    n_pairs : (nbl, npol) int64
        Number of difference pairs found (before thinning to ``max_pairs``).
    mean_inverse_weight : (nbl, npol) float64
        Mean of 1/weight over the data cells (the variance the weights claim), 1/Jy^-2 = Jy^2;
        NaN without data.
    """
    vis, weight, flag, pm = _prepare(vis, weight, flag, pol_mask)
    nt, nb, nc, npol = vis.shape
    if along == "auto":
        along = "channel" if nc > 1 else "time"
    if along not in ("channel", "time"):
        raise ValueError(f"along must be 'channel', 'time' or 'auto', got {along!r}")
    var = np.empty((nb, npol))
    n = np.empty((nb, npol), dtype=np.int64)
    invw = np.empty((nb, npol))
    if vis.size:
        cap_numba_threads()
        _pair_scatter_numba(vis, weight, flag, pm, along == "time", int(min_pairs),
                            max(1, int(max_pairs)), var, n, invw)
    else:
        var[:] = np.nan
        n[:] = 0
        invw[:] = np.nan
    return var, n, invw


def pooled_weight_scale(vis, weight, flag, *, pol_mask=None, along: str = "auto",
                        min_pairs: int = MIN_PAIRS) -> tuple[float, int]:
    """One factor for the whole block: measured variance / the variance the weights claim.

    All disjoint neighbour pairs of the selected correlations of all baselines (as in
    :func:`pair_variance`), each difference divided by ``sqrt(1/w1 + 1/w2)``; the factor is
    the (1.4826 MAD)^2 of the normalised differences with the same small-sample correction.
    Right when the weights are right *relative to each other* (their scale may be anything).

    Returns
    -------
    scale : float
        NaN with fewer than ``min_pairs`` pairs in the block.
    n_pairs : int
    """
    vis, weight, flag, pm = _prepare(vis, weight, flag, pol_mask)
    if along == "auto":
        along = "channel" if vis.shape[2] > 1 else "time"
    if not vis.size:
        return float("nan"), 0
    scale, n = _pooled_scale_numba(vis, weight, flag, pm, along == "time", int(min_pairs),
                                   16 * MAX_PAIRS)
    return float(scale), int(n)


def data_cells(vis, weight, flag) -> np.ndarray:
    """Boolean mask of the cells that are data: unflagged, finite, weight > 0."""
    vis = np.asarray(vis)
    return (~np.asarray(flag, dtype=bool)) & (np.asarray(weight) > 0) & np.isfinite(vis.real) \
        & np.isfinite(vis.imag)


def empirical_variance(vis, weight, flag, *, pol_mask=None, along: str = "auto",
                       min_pairs: int = MIN_PAIRS) -> np.ndarray:
    """sigma^2 per real/imaginary part for every cell, measured from the data (Jy^2).

    The estimate of :func:`pair_variance` for the cell's (baseline, correlation), placed on
    every data cell of that baseline and correlation; NaN where the cell is not data
    (flagged, non-finite, weight <= 0) or its baseline and correlation has too few pairs.

    Parameters
    ----------
    vis, weight, flag : (ntime, nbl, nchan, npol) arrays
        Visibilities (Jy), weights, flags.
    pol_mask, along, min_pairs
        As in :func:`pair_variance`.

    Returns
    -------
    numpy.ndarray, float64, same shape as ``vis``
    """
    var, _, _ = pair_variance(vis, weight, flag, pol_mask=pol_mask, along=along,
                              min_pairs=min_pairs)
    good = data_cells(vis, weight, flag)
    return np.where(good, var[None, :, None, :], np.nan)


def noise_model(vis, weight, flag, *, pol_mask=None, along: str = "auto",
                min_pairs: int = MIN_PAIRS) -> np.ndarray:
    """Per (baseline, correlation) variance model ``sigma^2 = a + b / weight`` with its source.

    ``OWN``: the baseline/correlation's own estimate (a = sigma^2, b = 0). ``POOLED``: too few
    pairs of its own, so its weights are rescaled by the block's
    :func:`pooled_weight_scale` (a = 0, b = that scale). ``WEIGHTS``: fewer than
    ``min_pairs`` pairs in the whole block; the weights are taken as they are (a = 0, b = 1).

    Parameters
    ----------
    vis, weight, flag : (ntime, nbl, nchan, npol) arrays
        Visibilities (Jy), weights, flags.
    pol_mask, along, min_pairs
        As in :func:`pair_variance`.

    Returns
    -------
    numpy.ndarray, float64, (nbl, npol, 3)
        ``[..., 0]`` = a (Jy^2), ``[..., 1]`` = b, ``[..., 2]`` = the code (OWN, POOLED,
        WEIGHTS).
    """
    var, _, invw = pair_variance(vis, weight, flag, pol_mask=pol_mask, along=along,
                                 min_pairs=min_pairs)
    own = np.isfinite(var)
    model = np.zeros(var.shape + (3,))
    model[..., 1] = 1.0
    model[..., 2] = WEIGHTS
    # the pooled factor only where some baseline/correlation with data lacks its own
    if np.any(~own & np.isfinite(invw)):
        scale, _ = pooled_weight_scale(vis, weight, flag, pol_mask=pol_mask, along=along,
                                       min_pairs=min_pairs)
        if np.isfinite(scale) and scale > 0:
            model[..., 1] = scale
            model[..., 2] = POOLED
    model[own, 0] = var[own]
    model[own, 1] = 0.0
    model[own, 2] = OWN
    return model
