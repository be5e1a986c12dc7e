"""Reading xstack stores block by block for the measuring stages (fit, noise).

Only Stokes I is used: the parallel hands (XX, YY or RR, LL; or a single ``I``), each with
its own weight; flagged, non-finite or non-positive-weight visibilities get weight 0.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import xarray as xr

from xstack._inputs import partitions
from xstack._select import (  # noqa: F401  (parse_uv_limit, uv_range_mask: re-exported)
    PARALLEL_HANDS,
    parse_uv_limit,
    sky_correlations,
    uv_range_mask,
)
from xstack.errors import XstackError

#: Visibilities per block when a partition is not dask-backed.
_BLOCK_VIS = 4_000_000


def as_partitions(data: Any, autocorrelations: bool = False) -> list[tuple[str, xr.Dataset]]:
    """Normalise any visibility input to validated partitions (:func:`xstack._inputs.partitions`).

    Unless ``autocorrelations``, autocorrelation baselines come back flagged
    (:func:`xstack._select.sky_correlations`): they do not measure the sky.
    """
    return partitions(data, autocorrelations=autocorrelations)


def parallel_hand_index(ds: xr.Dataset, name: str = "partition") -> np.ndarray:
    """Indices of the parallel-hand correlations of a partition (Stokes I)."""
    pols = [str(p).upper() for p in np.asarray(ds["polarization"].values)]
    idx = np.array([i for i, p in enumerate(pols) if p in PARALLEL_HANDS], dtype=np.int64)
    if idx.size == 0:
        raise XstackError(f"{name}: no parallel-hand correlations for Stokes I "
                          f"(polarizations {pols})")
    return idx


def time_blocks(ds: xr.Dataset) -> list[slice]:
    """Slices along time matching the dask chunks (or ~4e6 visibilities per block)."""
    ntime = ds.sizes["time"]
    chunks = ds["VISIBILITY"].chunks
    if chunks is not None:
        bounds = np.concatenate([[0], np.cumsum(chunks[0])])
    else:
        per_time = max(1, ds.sizes["baseline_id"] * ds.sizes["frequency"] * ds.sizes["polarization"])
        step = max(1, _BLOCK_VIS // per_time)
        bounds = np.append(np.arange(0, ntime, step), ntime)
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def stokes_i_blocks(ds: xr.Dataset, name: str = "partition"
                    ) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Yield ``(uvw, vis, weight)`` per time block of one partition.

    Returns
    -------
    uvw : (nrow, 3) float64, metres
    vis : (nrow, nchan, npar) complex128, Jy (parallel hands only)
    weight : (nrow, nchan, npar) float64, 1/Jy^2; 0 where flagged or unusable
    """
    pidx = parallel_hand_index(ds, name)
    nchan = ds.sizes["frequency"]
    for sl in time_blocks(ds):
        block = ds[["VISIBILITY", "WEIGHT", "FLAG", "UVW"]].isel(time=sl, polarization=pidx)
        vis = np.asarray(block["VISIBILITY"].values, dtype=np.complex128)
        wt = np.asarray(block["WEIGHT"].values, dtype=np.float64)
        flag = np.asarray(block["FLAG"].values, dtype=bool)
        uvw = np.asarray(block["UVW"].values, dtype=np.float64).reshape(-1, 3)
        bad = flag | ~np.isfinite(vis) | ~(wt > 0) | ~np.isfinite(wt)
        bad |= ~np.all(np.isfinite(uvw), axis=-1).reshape(vis.shape[:2])[..., None, None]
        wt = np.where(bad, 0.0, wt)
        vis = np.where(bad, 0.0, vis)
        yield (uvw, vis.reshape(-1, nchan, pidx.size), wt.reshape(-1, nchan, pidx.size))
