"""Expected smearing loss of stacking positions, and which data carry smearing (plan time).

A source at (l, m) off the phase center loses flux to bandwidth and time-average smearing
(:mod:`xstack.smearing`). uv-stacking corrects for it as for the primary beam: the loss
``L_k(nu)`` of position k is the weighted mean smearing factor over the visibilities of its
pointing, per channel, and the coefficient of k becomes ``W_k / (A_k L_k) / sum W``, so the
stacked flux is unbiased (``docs/uvstack.md``).

``L_k`` needs only UVW, WEIGHT and FLAG (never VISIBILITY), from a deterministic subsample of
at most :data:`MAX_ROWS` (time, baseline) rows: times evenly spread over the whole track and
baselines drawn by a golden-ratio (Weyl) sequence, so every part of the track and every
baseline length is represented. Accuracy against all rows: ``benchmarks/bench_smearing.py``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import dask
import dask.array as da
import numpy as np
import xarray as xr

from xstack import _vocabulary
from xstack.errors import OptionError
from xstack.smearing import mean_factors

#: ``smearing=`` choices of :func:`xstack.uvstack.uvstack`.
MODES = _vocabulary.SMEARING_MODES
#: Rows (time x baseline) sampled per partition for the loss; all rows when fewer.
MAX_ROWS = 10_000
#: A used position losing more than this fraction of its flux to smearing gets a warning.
WARN_LOSS = 0.10

_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def check_mode(mode: Any) -> str:
    """Validate a ``smearing=`` value; raise :class:`XstackError` otherwise."""
    if mode not in MODES:
        raise OptionError(f"unknown smearing {mode!r} (use {', '.join(MODES)})")
    return str(mode)


def data_effects(ds: xr.Dataset, mode: str) -> tuple[bool, bool]:
    """(bandwidth, time): the smearing effects to correct in partition ``ds``.

    ``none``: neither; ``correct``: both; ``auto``: those the data carry. A simulated
    partition records them in its ``smearing`` attribute ({"bandwidth": bool, "time":
    bool}); a partition without the attribute is real data (both), except one written by
    ``xstack simulate`` before the attribute existed (``source = "xstack simulate"``:
    simulated without smearing).
    """
    if mode == "none":
        return False, False
    if mode == "correct":
        return True, True
    attr = ds.attrs.get("smearing")
    if isinstance(attr, Mapping):
        return bool(attr.get("bandwidth", False)), bool(attr.get("time", False))
    if str(ds.attrs.get("source", "")) == "xstack simulate":
        return False, False
    return True, True


def sample_rows(nt: int, nb: int, max_rows: int = MAX_ROWS) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic (time, baseline) indices of at most ``max_rows`` rows (all if fewer).

    Times evenly spaced over the track (integration j of n at (j + 1/2) nt / n), baselines
    by the golden-ratio sequence frac(j phi) nb: spread over the track and the baselines.
    """
    total = nt * nb
    if total <= max_rows:
        t, b = np.divmod(np.arange(total), nb)
        return t.astype(np.int64), b.astype(np.int64)
    j = np.arange(int(max_rows))
    t = np.minimum(((j + 0.5) * nt / max_rows).astype(np.int64), nt - 1)
    b = np.minimum((np.mod(j * _GOLDEN, 1.0) * nb).astype(np.int64), nb - 1)
    return t, b


def _take(arr: Any, t: np.ndarray, b: np.ndarray) -> Any:
    if isinstance(arr, da.Array):
        return arr.vindex[t, b]
    return np.asarray(arr)[t, b]


def loss_factors(ds: xr.Dataset, l: np.ndarray, m: np.ndarray, n_minus_1: np.ndarray, *,
                 bandwidth: bool, time: bool, pol_mask: np.ndarray,
                 uv_select: Callable[[np.ndarray, np.ndarray], np.ndarray | None] | None = None,
                 max_rows: int = MAX_ROWS) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean smearing factors ``L`` of positions in one partition.

    Parameters
    ----------
    ds
        The partition (UVW, WEIGHT, FLAG, ``frequency``, ``channel_width``, ``time`` with its
        ``integration_time`` attribute, ``phase_center``).
    l, m, n_minus_1
        (npos,) direction cosines of the positions relative to the phase center.
    bandwidth, time
        Which effects to include (without ``integration_time`` the time effect is 0).
    pol_mask
        (npol,) bool: the polarizations of the flux.
    uv_select
        ``f(uvw (nrow, 3), frequency) -> (nrow, nchan) bool or None``: the uv range of the
        flux.
    max_rows
        Row budget of the subsample (:func:`sample_rows`).

    Returns
    -------
    per_channel, mean
        (npos, nchan) factors per channel and (npos,) at the partition's mean frequency and
        channel width (dimensionless, 1 = no loss).
    """
    freq = np.asarray(ds["frequency"].values, dtype=np.float64)
    npos = np.asarray(l).size
    ones = np.ones((npos, freq.size)), np.ones(npos)
    it = ds["time"].attrs.get("integration_time") if time else None
    dt = float(it) if it is not None and np.isfinite(float(it)) else 0.0
    if npos == 0 or not (bandwidth or dt > 0):
        return ones
    width = np.abs(np.asarray(ds["channel_width"].values, dtype=np.float64)) \
        if "channel_width" in ds.coords or "channel_width" in ds else np.zeros(freq.size)
    nt, nb = ds.sizes["time"], ds.sizes["baseline_id"]
    t, b = sample_rows(nt, nb, max_rows)
    pm = np.asarray(pol_mask, dtype=bool)
    uvw, wt, fl = dask.compute(_take(ds["UVW"].data, t, b), _take(ds["WEIGHT"].data, t, b),
                               _take(ds["FLAG"].data, t, b))
    uvw = np.asarray(uvw, dtype=np.float64)
    wt = np.asarray(wt, dtype=np.float64)[:, :, pm]
    ok = ~np.asarray(fl, dtype=bool)[:, :, pm] & (wt > 0) & np.isfinite(wt)
    w = np.where(ok, wt, 0.0).sum(axis=2)  # (nrow, nchan)
    w[~np.all(np.isfinite(uvw), axis=1)] = 0.0
    uvw = np.nan_to_num(uvw)
    if uv_select is not None:
        mask = uv_select(uvw, freq)
        if mask is not None:
            w = np.where(mask, w, 0.0)
    dec0 = float(ds.attrs["phase_center"][1])
    kw = dict(bandwidth=bandwidth, time=dt > 0)
    per_chan = mean_factors(uvw, w, freq, width, dt, l, m, n_minus_1, dec0, **kw)
    wsum = w.sum(axis=1)
    mean_width = float(np.sum(width * w.sum(axis=0)) / w.sum()) if w.sum() > 0 \
        else float(np.mean(width))
    mean = mean_factors(uvw, wsum[:, None], np.array([freq.mean()]), np.array([mean_width]),
                        dt, l, m, n_minus_1, dec0, **kw)[:, 0]
    return per_chan, mean
