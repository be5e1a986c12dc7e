"""Plain-numpy reference implementation of the whole uv-stack (eq. 4, mosaics, flux).

Written to be *obviously* right rather than fast, and independent of the production path
(:mod:`xstack.uvstack.stack` with the numba kernel): the phase is the paper's literal
``B . (S_0 - S_k)`` with unit vectors built from RA/Dec, the sum over positions is an explicit
loop, everything is in memory. Tests and ``benchmarks/bench_uvstack.py`` compare against it.
Only in-memory-sized data, please.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import xarray as xr

from xstack._select import PARALLEL_HANDS
from xstack.beams import DEFAULT_PB_CUTOFF, dish_diameter, standard_beam
from xstack.coords import SPEED_OF_LIGHT, parse_distance


def unit_vectors(ra: np.ndarray, dec: np.ndarray, ra0: float, dec0: float) -> np.ndarray:
    """Unit vectors (npos, 3) of (ra, dec) in the (l, m, n) frame of phase center (ra0, dec0).

    Built by rotating equatorial Cartesian vectors: e_l = east, e_m = north, e_n = center.
    """
    ra = np.atleast_1d(np.asarray(ra, dtype=np.float64))
    dec = np.atleast_1d(np.asarray(dec, dtype=np.float64))
    xyz = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=1)
    e_n = np.array([np.cos(dec0) * np.cos(ra0), np.cos(dec0) * np.sin(ra0), np.sin(dec0)])
    e_l = np.array([-np.sin(ra0), np.cos(ra0), 0.0])
    e_m = np.cross(e_n, e_l)
    return xyz @ np.stack([e_l, e_m, e_n], axis=1)


def reference_uvstack(partitions: list[tuple[str, xr.Dataset]], ra_deg: Any, dec_deg: Any, *,
                      weighting: str = "none", primary_beam: str = "none",
                      pb_cutoff: float = DEFAULT_PB_CUTOFF, column_weight: Any = None, sigma: Any = None,
                      uvmin: Any = None, uvmax: Any = None) -> dict[str, Any]:
    """Stack in plain numpy; returns ``flux_jy``, ``flux_err_jy``, ``n_visibilities``,
    ``stacked`` (name -> complex128 VISIBILITY array) and ``sum_weight`` (name -> sum W_l).

    Same conventions as :func:`xstack.uvstack.stack.stack_uv` (``docs/uvstack.md``); the
    primary beam is ``none`` or a model name for :func:`xstack.beams.standard_beam`.
    Autocorrelations are left out. ``sigma2`` with ``sigma`` is implemented for one
    partition only (the per-pointing rule of several is checked analytically in the tests).
    """
    partitions = list(partitions)
    if weighting == "sigma2" and sigma is not None and len(partitions) > 1:
        raise NotImplementedError("reference sigma2 weights on several partitions")
    ra = np.radians(np.asarray(ra_deg, dtype=np.float64))
    dec = np.radians(np.asarray(dec_deg, dtype=np.float64))
    num = den = var = 0.0
    nvis = 0
    stacked: dict[str, np.ndarray] = {}
    sums: dict[str, float] = {}
    lims = [parse_distance(x) if x is not None else None for x in (uvmin, uvmax)]
    for name, ds in partitions:
        ra0, dec0 = (float(x) for x in ds.attrs["phase_center"])
        freq = np.asarray(ds["frequency"].values, dtype=np.float64)
        vis = np.asarray(ds["VISIBILITY"].values).astype(np.complex128)
        wt = np.asarray(ds["WEIGHT"].values, dtype=np.float64)
        flag = np.asarray(ds["FLAG"].values, dtype=bool)
        if "baseline_antenna1_id" in ds.variables:  # autocorrelations do not measure the sky
            auto = ds["baseline_antenna1_id"].values == ds["baseline_antenna2_id"].values
            flag = flag | auto[None, :, None, None]
        uvw = np.asarray(ds["UVW"].values, dtype=np.float64)
        s = unit_vectors(ra, dec, ra0, dec0)
        theta = np.arccos(np.clip(s[:, 2], -1, 1))
        if primary_beam == "none":
            att = np.ones((ra.size, freq.size))
            inside = s[:, 2] > 0
        else:
            dish = dish_diameter(ds)
            model = None if primary_beam == "auto" else primary_beam
            beam = standard_beam(str(ds.attrs["telescope_name"]), dish, model=model)
            att = np.array([[float(beam(t, f)) for f in freq] for t in theta])
            inside = (s[:, 2] > 0) & np.all(att >= pb_cutoff, axis=1)
        att_ref = (np.array([float(beam(t, freq.mean())) for t in theta])
                   if primary_beam != "none" else np.ones(ra.size))
        if weighting == "none":
            w = np.ones(ra.size)
        elif weighting == "pb" or (weighting == "sigma2" and sigma is None):
            w = att_ref**2
        elif weighting == "sigma2":
            w = 1.0 / np.asarray(sigma, dtype=np.float64) ** 2
        else:
            w = np.asarray(column_weight, dtype=np.float64)
        w = np.where(inside, w, 0.0)
        total = w.sum()
        if total <= 0:
            continue
        phasor = np.zeros(uvw.shape[:2] + (freq.size,), dtype=np.complex128)
        s0 = np.array([0.0, 0.0, 1.0])
        for k in range(ra.size):
            if w[k] == 0:
                continue
            proj = uvw @ (s0 - s[k])  # B . (S_0 - S_k), metres
            for c, nu in enumerate(freq):
                phasor[..., c] += w[k] / att[k, c] * np.exp(2j * np.pi * proj * nu / SPEED_OF_LIGHT)
        phasor /= total
        out = vis * phasor[..., None]
        stacked[name] = out
        sums[name] = total
        pols = [str(p).upper() for p in ds["polarization"].values]
        q = np.hypot(uvw[..., 0], uvw[..., 1])[..., None] * np.ones(freq.size)
        ql = q * freq / SPEED_OF_LIGHT
        inrange = np.ones(q.shape, dtype=bool)
        if lims[0] is not None:
            inrange &= (q if lims[0][1] == "m" else ql) >= lims[0][0]
        if lims[1] is not None:
            inrange &= (q if lims[1][1] == "m" else ql) <= lims[1][0]
        for p, pol in enumerate(pols):
            if pol not in PARALLEL_HANDS:
                continue
            good = (~flag[..., p]) & (wt[..., p] > 0) & inrange & np.isfinite(vis[..., p])
            ww = wt[..., p][good] * total
            num += np.sum(ww * out[..., p][good].real)
            den += np.sum(ww)
            # Var(Re(V P)) = |P|^2 / WEIGHT for circular Gaussian noise of 1/WEIGHT per part
            var += np.sum(ww**2 * np.abs(phasor[good]) ** 2 / wt[..., p][good])
            nvis += int(good.sum())
    return {"flux_jy": num / den if den > 0 else np.nan,
            "flux_err_jy": np.sqrt(var) / den if den > 0 else np.nan,
            "n_visibilities": nvis, "stacked": stacked, "sum_weight": sums}
