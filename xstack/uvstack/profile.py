"""uv-profile of a stacked dataset: Re V and Im V in bins of uv distance (paper Figs 5-7).

Bins are in uv distance measured in wavelengths (per channel: sqrt(u^2 + v^2) nu / c), since
a source's visibility is a function of (u, v)/lambda. Every bin holds the weighted mean of Re V
and Im V over the unflagged selected polarizations, and its standard error estimated from the
weighted scatter inside the bin: ``sqrt(sum w^2 (x - mean)^2) / sum w`` (honest whatever the
normalisation of the stored weights, as long as there are several visibilities per bin).
"""

from __future__ import annotations

from typing import Any

import dask
import dask.array as da
import numpy as np
import xarray as xr
from astropy import units as u
from astropy.table import Table

from xstack._select import parallel_hand_mask
from xstack.coords import SPEED_OF_LIGHT, parse_distance
from xstack.errors import XstackError
from xstack.uvstack import kernels


def _partitions(stacked: Any) -> list[xr.Dataset]:
    from xstack._inputs import partitions

    return [ds for _, ds in partitions(stacked)]


def _block_range(uvw, frequency):
    q = np.hypot(uvw[..., 0], uvw[..., 1]).ravel()
    fmax = float(np.max(frequency)) / SPEED_OF_LIGHT
    fmin = float(np.min(frequency)) / SPEED_OF_LIGHT
    good = q > 0
    if not good.any():
        return np.array([[[np.inf, -np.inf]]])
    return np.array([[[q[good].min() * fmin, q.max() * fmax]]])


def _block_hist(vis, weight, flag, uvw, frequency, edges, pol_mask):
    return kernels.profile_sums(vis, weight, flag, uvw, frequency, edges, pol_mask)[None, None]


def uv_profile(stacked: Any, bins: int | Any = 20, uvmin: Any = None, uvmax: Any = None,
               polarizations: Any = "parallel") -> Table:
    """Re V and Im V of a stacked dataset in bins of uv distance.

    Parameters
    ----------
    stacked
        A :class:`~xstack.uvstack.stack.StackResult`, a dict of stacked partitions, a
        DataTree or a stacked store path.
    bins
        Number of equal-width bins between the smallest and largest uv distance (or
        ``uvmin``/``uvmax``), or an array of bin edges in kilo-wavelengths.
    uvmin, uvmax
        Range (``"20klambda"``, ``"5000m"``); metres are converted with the mean frequency.
    polarizations
        ``parallel`` (default), ``all`` or a list of correlation names.

    Returns
    -------
    astropy.table.Table
        Columns ``uvdist_klambda`` (bin center), ``uvdist_m`` (center at the mean
        wavelength), ``bin_lo_klambda``, ``bin_hi_klambda``, ``re_jy``, ``re_err_jy``,
        ``im_jy``, ``im_err_jy``, ``sum_weight``, ``count``. Empty bins hold NaN.
    """
    parts = _partitions(stacked)
    edges, fmean = profile_edges(parts, bins, uvmin, uvmax)
    graphs = [profile_graph(ds, edges, polarizations) for ds in parts]
    return profile_table(np.sum(dask.compute(*graphs), axis=0), edges, fmean)


def profile_edges(parts: list[xr.Dataset], bins: int | Any = 20, uvmin: Any = None,
                  uvmax: Any = None) -> tuple[np.ndarray, float]:
    """Bin edges (wavelengths) of a uv-profile of ``parts`` and their mean frequency (Hz).

    Parameters as :func:`uv_profile`. With a number of bins and no ``uvmin``/``uvmax`` the
    uv range is measured from the partitions' UVW (a pass over UVW only).
    """
    if not parts:
        raise XstackError("no stacked partitions")
    fmean = float(np.mean(np.concatenate([np.asarray(ds["frequency"].values) for ds in parts])))
    lam = SPEED_OF_LIGHT / fmean

    def to_lambda(lim):
        if lim is None:
            return None
        value, unit = parse_distance(lim)
        return value if unit == "lambda" else value / lam

    lo, hi = to_lambda(uvmin), to_lambda(uvmax)
    if np.ndim(bins) == 0:
        nbin = int(bins)
        if nbin < 1:
            raise XstackError("bins must be >= 1")
        if lo is None or hi is None:
            ranges = []
            for ds in parts:
                uvw = ds["UVW"].data
                if not isinstance(uvw, da.Array):
                    uvw = da.from_array(np.asarray(uvw))
                ranges.append(da.map_blocks(_block_range, uvw, np.asarray(ds["frequency"].values),
                                            dtype=float, chunks=((1,) * uvw.numblocks[0],
                                                                 (1,) * uvw.numblocks[1], (2,))))
            rs = dask.compute(*ranges)
            qmin = min(float(np.min(r[..., 0])) for r in rs)
            qmax = max(float(np.max(r[..., 1])) for r in rs)
            lo = qmin if lo is None else lo
            hi = qmax if hi is None else hi
        if not hi > lo:
            raise XstackError("empty uv range for the profile")
        return np.linspace(lo, hi, nbin + 1), fmean
    edges = np.asarray(bins, dtype=np.float64) * 1e3
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise XstackError("bin edges must be increasing")
    return edges, fmean


def profile_graph(ds: xr.Dataset, edges: np.ndarray, polarizations: Any = "parallel") -> da.Array:
    """The lazy uv-profile sums (nbin, :data:`~xstack.uvstack.kernels.NPROFILE`) of one
    stacked partition: one task per chunk (:func:`~xstack.uvstack.kernels.profile_sums`),
    summed. Computed together with the graph that makes ``ds``'s arrays, it adds no pass."""
    pols = [str(p).upper() for p in ds["polarization"].values]
    if polarizations == "parallel":
        pmask = parallel_hand_mask(pols)
    elif polarizations == "all":
        pmask = np.ones(len(pols), bool)
    else:
        pmask = np.array([p in {str(x).upper() for x in polarizations} for p in pols])
    arrs = []
    for var in ("VISIBILITY", "WEIGHT", "FLAG"):
        a = ds[var].data
        arrs.append(a if isinstance(a, da.Array) else da.from_array(np.asarray(a)))
    vis, wt, fl = arrs
    vis = vis.rechunk({2: -1, 3: -1})
    wt = wt.rechunk(vis.chunks)
    fl = fl.rechunk(vis.chunks)
    uvw = ds["UVW"].data
    uvw = (uvw if isinstance(uvw, da.Array) else da.from_array(np.asarray(uvw)))
    uvw = uvw.rechunk((vis.chunks[0], vis.chunks[1], -1))
    nbin = edges.size - 1
    h = da.blockwise(_block_hist, "tbsk", vis, "tbcp", wt, "tbcp", fl, "tbcp", uvw, "tbx",
                     dtype=np.float64, concatenate=True,
                     new_axes={"s": nbin, "k": kernels.NPROFILE},
                     adjust_chunks={"t": 1, "b": 1}, frequency=np.asarray(ds["frequency"].values),
                     edges=edges, pol_mask=pmask)
    return h.sum(axis=(0, 1))


def profile_table(total: np.ndarray, edges: np.ndarray, fmean: float) -> Table:
    """The :func:`uv_profile` table from the summed sums of :func:`profile_graph`."""
    lam = SPEED_OF_LIGHT / fmean
    sw, swr, swi, sw2, sw2r, sw2rr, sw2i, sw2ii, count = np.asarray(total).T
    with np.errstate(invalid="ignore", divide="ignore"):
        re = swr / sw
        im = swi / sw
        var_re = np.clip(sw2rr - 2 * re * sw2r + re * re * sw2, 0, None) / sw**2
        var_im = np.clip(sw2ii - 2 * im * sw2i + im * im * sw2, 0, None) / sw**2
        # scatter of a single visibility is unknown: no error from one sample
        var_re = np.where(count > 1, var_re * count / (count - 1), np.nan)
        var_im = np.where(count > 1, var_im * count / (count - 1), np.nan)
    centers = 0.5 * (edges[1:] + edges[:-1])
    t = Table()
    t["uvdist_klambda"] = centers / 1e3
    t["uvdist_m"] = centers * lam
    t["bin_lo_klambda"] = edges[:-1] / 1e3
    t["bin_hi_klambda"] = edges[1:] / 1e3
    t["re_jy"] = re
    t["re_err_jy"] = np.sqrt(var_re)
    t["im_jy"] = im
    t["im_err_jy"] = np.sqrt(var_im)
    t["sum_weight"] = sw
    t["count"] = count.astype(np.int64)
    t["uvdist_m"].unit = u.m
    for c in ("re_jy", "re_err_jy", "im_jy", "im_err_jy"):
        t[c].unit = u.Jy
    t.meta["mean_frequency_hz"] = fmean
    return t


# the drawing lives in a light module (no dask, xarray or numba), re-exported here
from xstack.uvstack.plot import (  # noqa: E402,F401
    draw_uv_profile,
    plot_uv_profile,
    profile_scale,
    save_png,
    uv_profile_figure,
)
