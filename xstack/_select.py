"""Which visibilities measure the sky: the selection every measuring stage shares.

Stokes I is formed from the *parallel hands* (XX and YY, RR and LL, or a correlation already
labelled ``I``), each visibility with its own weight. Autocorrelations (antenna1 == antenna2)
measure the system power of one antenna, not the sky's brightness distribution: imaging,
subtraction, uv-stacking, fitting and noise estimation leave them out unless asked, as CASA
and WSClean do. Defined once here so that no stage can disagree with another.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import xarray as xr

#: Correlations that form Stokes I: the parallel hands of linear and circular feeds, or I.
PARALLEL_HANDS = ("XX", "YY", "RR", "LL", "I")


def parallel_hand_mask(polarizations: Iterable[Any]) -> np.ndarray:
    """Boolean mask of the correlations in ``polarizations`` that are parallel hands (or I)."""
    return np.array([str(p).upper() in PARALLEL_HANDS for p in polarizations], dtype=bool)


def autocorrelation_mask(ds: xr.Dataset) -> np.ndarray:
    """Boolean (baseline_id,) mask, True where a baseline correlates an antenna with itself.

    Uses the antenna ids of the baselines, or their names when the ids are absent; a dataset
    with neither (a bare stacked dataset) is taken to hold cross-correlations only.
    """
    for a, b in (("baseline_antenna1_id", "baseline_antenna2_id"),
                 ("baseline_antenna1_name", "baseline_antenna2_name")):
        if a in ds.variables and b in ds.variables:
            return np.asarray(ds[a].values) == np.asarray(ds[b].values)
    return np.zeros(ds.sizes.get("baseline_id", 0), dtype=bool)


def without_autocorrelations(ds: xr.Dataset) -> xr.Dataset:
    """``ds`` with the autocorrelation baselines flagged (lazily for dask-backed data).

    The input is not modified; a dataset without autocorrelations is returned as it is.
    """
    auto = autocorrelation_mask(ds)
    if not auto.any():
        return ds
    flag = ds["FLAG"]
    mask = xr.DataArray(auto, dims=("baseline_id",))
    new = (flag | mask).transpose(*flag.dims).astype(bool)
    new.attrs = dict(flag.attrs)
    return ds.assign(FLAG=new)


def sky_correlations(ds: xr.Dataset, autocorrelations: bool = False) -> xr.Dataset:
    """The partition as a sky-measuring stage should read it: autocorrelations flagged unless
    ``autocorrelations`` is True."""
    return ds if autocorrelations else without_autocorrelations(ds)
