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


#: A uv-distance limit: (value, "m") or (value, "lambda"), as :func:`xstack.coords.parse_distance`
UVLimit = tuple[float, str]


def parse_uv_limit(value: Any) -> UVLimit | None:
    """``None``, a number (metres), a string with units (``5000m``, ``23.8klambda``) or a
    ``(value, unit)`` pair."""
    from xstack.coords import parse_distance

    if value is None:
        return None
    if isinstance(value, tuple) and len(value) == 2:
        return float(value[0]), str(value[1])
    return parse_distance(value)


def uv_limits(uvmin: Any, uvmax: Any) -> tuple[UVLimit | None, UVLimit | None]:
    """Both limits parsed; an error when uvmin >= uvmax in the same unit."""
    from xstack.errors import OptionError

    lo, hi = parse_uv_limit(uvmin), parse_uv_limit(uvmax)
    if lo is not None and hi is not None and lo[1] == hi[1] and lo[0] >= hi[0]:
        raise OptionError(f"uvmin ({uvmin}) must be smaller than uvmax ({uvmax})",
                          option=("uvmin", "uvmax"))
    return lo, hi


def uv_range_mask(uvw: np.ndarray, frequency: np.ndarray, uvmin: UVLimit | None,
                  uvmax: UVLimit | None) -> np.ndarray | None:
    """Boolean (nrow, nchan) mask of visibilities with uvmin <= sqrt(u^2 + v^2) <= uvmax.

    Limits in metres or wavelengths (:func:`parse_uv_limit`); None when there is no cut.
    """
    from xstack.coords import SPEED_OF_LIGHT

    if uvmin is None and uvmax is None:
        return None
    q_m = np.hypot(uvw[:, 0], uvw[:, 1])[:, None]
    q_lam = q_m * (np.asarray(frequency)[None, :] / SPEED_OF_LIGHT)
    mask = np.ones((uvw.shape[0], len(frequency)), dtype=bool)
    for limit, above in ((uvmin, True), (uvmax, False)):
        if limit is None:
            continue
        value, unit = limit
        q = q_m if unit == "m" else q_lam
        mask &= (q >= value) if above else (q <= value)
    return mask
