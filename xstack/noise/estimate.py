"""Noise and bias of a stack (paper section 3.5): analytic, Monte Carlo, random, bootstrap.

The uv-stacking flux estimator used throughout is the paper's equation 4 followed by the
weighted mean of Re V over all Stokes-I visibilities: in one partition (pointing)

    F = sum_vis W Re(V P) / sum_vis W,   P = sum_k w_k A_k(nu)^-1 exp(-i phi_k) / sum_k w_k,

over the positions k inside that pointing's primary beam (A >= cutoff); with several
pointings the numerators and the weight sums of the pointings that hold a position add.
Every method evaluates this estimator for many position sets in ONE pass over the data
(:mod:`xstack.noise.kernels`); the Monte Carlo injection is added analytically (stacking is
linear: stack(data + model, pos) = stack(data, pos) + stack(model, pos)).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from xstack import _options as _opt
from xstack import _vocabulary
from xstack._antenna import MIN_ROWS_PER_ANTENNA
from xstack._cluster import active_client
from xstack._inputs import Positions
from xstack._json import finite_or_none
from xstack._lazy import LazyResult
from xstack._result import Result, json_ready
from xstack._scatter import EMPIRICAL_TOLERANCE
from xstack._select import uv_limits
from xstack.beams import (
    DEFAULT_PB_CUTOFF,
    PrimaryBeam,
    dish_diameter,
    inside_field,
    standard_beam,
)
from xstack.coords import SPEED_OF_LIGHT, angular_separation, radec_to_lmn
from xstack.errors import NoDataError, OptionError, XstackError
from xstack.fit._data import (
    as_partitions,
    parallel_hand_index,
    parse_uv_limit,
    stokes_i_blocks,
    time_blocks,
    uv_range_mask,
)
from xstack.noise import kernels
from xstack.noise.positions import ARCSEC, Region, make_region, random_positions

METHODS = _vocabulary.NOISE_METHODS
ENGINES = _vocabulary.NOISE_ENGINES
WEIGHTINGS = _vocabulary.NOISE_WEIGHTINGS


@dataclass(kw_only=True)
class NoiseResult(Result):
    """Noise (1-sigma scatter) and bias of a stacked flux density.

    Attributes
    ----------
    method : analytic | mc | random | bootstrap
    noise_jy : the noise estimate, Jy (std of ``values`` with ddof=1; for analytic the
        thermal noise of the estimator actually used, from the visibility weights)
    bias_jy : mc: mean(values - injected); random: mean(values); bootstrap:
        mean(values) - target_flux_jy; analytic: None
    realizations : number of realisations (0 for analytic)
    values : stacked flux of each realisation, Jy
    injected : flux each realisation would give without noise (mc), Jy
    target_flux_jy : the stacked flux at the real target positions (same estimator)
    n_positions : positions per realisation
    profile : uv-profiles of the realisations (``q_klambda``, ``values`` (R, nbins),
        ``weight`` per bin) when requested
    options : the options used (:meth:`NoiseOptions.to_dict`), with what the run decided
        (``min_separation_arcsec`` when defaulted, the ``engine`` that ran)
    """

    method: str
    noise_jy: float
    bias_jy: float | None
    realizations: int
    values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    injected: np.ndarray | None = None
    target_flux_jy: float | None = None
    n_positions: int = 0
    domain: str = "uv"
    profile: dict[str, Any] | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)
    #: (R, n, 2) ra, dec (deg) of the random positions (mc, random), not written to JSON
    positions_deg: np.ndarray | None = None
    #: (R, n) fluxes injected at those positions (mc), Jy
    injected_flux_jy: np.ndarray | None = None

    def to_dict(self, include_values: bool = True) -> dict[str, Any]:
        """JSON-ready dictionary."""
        out = {"method": self.method, "domain": self.domain, "noise_jy": finite_or_none(self.noise_jy),
               "bias_jy": finite_or_none(self.bias_jy), "realizations": int(self.realizations),
               "n_positions": int(self.n_positions),
               "target_flux_jy": finite_or_none(self.target_flux_jy)}
        if include_values:
            out["values_jy"] = [finite_or_none(v) for v in self.values]
            if self.injected is not None:
                out["injected_jy"] = [finite_or_none(v) for v in self.injected]
        for k, v in self.extra.items():
            out[k] = finite_or_none(v) if isinstance(v, (float, np.floating)) else v
        if self.options:
            out["options"] = json_ready(self.options)
        return out

    def table(self):
        """Per-realisation values as an astropy Table (realization, flux_jy, injected_jy)."""
        from astropy.table import Table

        t = Table()
        t["realization"] = np.arange(self.values.size)
        t["flux_jy"] = self.values
        if self.injected is not None:
            t["injected_jy"] = self.injected
            t["offset_jy"] = self.values - self.injected
        for name in t.colnames[1:]:
            t[name].unit = "Jy"
        return t



# ----------------------------------------------------------------------------- options

def _describe(value: Any) -> Any:
    """A JSON-ready account of an option value given as an object (path, table, beam, array)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, PrimaryBeam):
        return value.model
    if isinstance(value, Region):
        return value.kind
    if hasattr(value, "colnames"):  # an astropy Table of positions
        return f"table of {len(value)} rows"
    return json_ready(np.asarray(value, dtype=np.float64))


def _number(name: str, value: Any, kind: type = float) -> Any:
    """``value`` as ``kind`` (int or float), or an OptionError naming ``name``."""
    try:
        out = kind(value)
    except (TypeError, ValueError):
        raise OptionError(f"{name} must be a number, got {value!r}", option=name) from None
    if kind is int and out != value and not isinstance(value, str):
        raise OptionError(f"{name} must be a whole number, got {value!r}", option=name)
    return out


@dataclass(frozen=True, kw_only=True)
class NoiseOptions:
    """Every option of :func:`estimate_noise`, checked before any data are read.

    The fields are the keyword arguments of :func:`estimate_noise` (same names, defaults and
    units; see there). A bad value raises :class:`~xstack.errors.OptionError` naming the
    parameter. ``realizations``, ``profile_bins``, ``seed``, ``pb_cutoff`` and the radii are
    stored normalized (int / float); a string ``flux`` is stored in Jy.

    Attributes
    ----------
    uv_range : (uvmin, uvmax) parsed as ``(value, "m" | "lambda")`` pairs (or None each).
    """

    method: str = "mc"
    realizations: int = 100
    flux: Any = None
    min_separation_arcsec: float | None = None
    avoid: Any = None
    seed: int = 0
    domain: str = "uv"
    weighting: str = "pb"
    primary_beam: str | PrimaryBeam | None = None
    pb_cutoff: float = DEFAULT_PB_CUTOFF
    uvmin: Any = None
    uvmax: Any = None
    field_radius_arcsec: float | None = None
    profile_bins: int = 0
    psf: Any = None
    progress: bool = False
    engine: str = "auto"
    antenna_tol_rad: float = kernels.ANTENNA_TOL_RAD
    region: Any = "hull"
    image_corrected: bool | None = None
    autocorrelations: bool = False
    compute: bool = True
    uv_range: tuple[Any, Any] = field(init=False, repr=False, compare=False, default=(None, None))

    def __post_init__(self) -> None:
        self._check_names()
        set_ = object.__setattr__  # frozen: normalized values are set once, here
        set_(self, "realizations", _number("realizations", self.realizations, int))
        if self.method != "analytic" and self.realizations < 2:
            raise OptionError("need at least 2 realisations to estimate a scatter, got "
                              f"{self.realizations}", option="realizations")
        set_(self, "seed", _number("seed", self.seed, int))
        set_(self, "profile_bins", _number("profile_bins", self.profile_bins, int))
        set_(self, "pb_cutoff", _number("pb_cutoff", self.pb_cutoff))
        set_(self, "antenna_tol_rad", _number("antenna_tol_rad", self.antenna_tol_rad))
        checks = (("profile_bins", self.profile_bins >= 0, "must be >= 0"),
                  ("pb_cutoff", 0 <= self.pb_cutoff < 1, "must be in [0, 1)"),
                  ("antenna_tol_rad", self.antenna_tol_rad > 0, "must be > 0"))
        for name, ok, rule in checks:
            if not ok:
                raise OptionError(f"{name} {rule}, got {getattr(self, name)}", option=name)
        for name, lowest in (("min_separation_arcsec", 0.0), ("field_radius_arcsec", None)):
            value = getattr(self, name)
            if value is not None:
                value = _number(name, value)
                if not (value >= 0 if lowest == 0.0 else value > 0):
                    raise OptionError(f"{name} must be {'>= 0' if lowest == 0.0 else '> 0'}, "
                                      f"got {value}", option=name)
                set_(self, name, value)
        if isinstance(self.flux, str):
            from xstack.coords import parse_flux

            try:
                set_(self, "flux", parse_flux(self.flux))
            except XstackError as exc:
                raise OptionError(f"flux: {exc}", option="flux") from None
        for name in ("uvmin", "uvmax"):
            try:
                parse_uv_limit(getattr(self, name))
            except (XstackError, ValueError, TypeError) as exc:
                raise OptionError(f"{name}: {exc}", option=name) from None
        set_(self, "uv_range", uv_limits(self.uvmin, self.uvmax))

    def _check_names(self) -> None:
        """The options that take one of a few names."""
        for name, value, allowed in (("method", self.method, METHODS),
                                     ("domain", self.domain, ("uv", "image")),
                                     ("weighting", self.weighting, WEIGHTINGS),
                                     ("engine", self.engine, ENGINES)):
            _opt.choice(name, value, allowed, what="noise method" if name == "method" else None)
        if self.domain == "image" and not (
                self.region is None or (isinstance(self.region, str) and self.region.lower() == "hull")):
            raise OptionError("region: only the default (hull) is available for images so far; "
                              "leave out region=", option="region")
        if (self.domain == "uv" and not isinstance(self.primary_beam, PrimaryBeam)
                and self.primary_beam not in (None, "auto", "airy", "gaussian", "none")):
            raise OptionError(f"unknown primary beam {self.primary_beam!r} for the noise "
                              "estimate (use airy, gaussian or none)", option="primary_beam")
        if self.domain == "image" and not self.compute:
            raise OptionError("compute=False is for the uv domain (an image is read at once)",
                              option="compute")
        if self.image_corrected not in (None, True, False):
            raise OptionError(f"image_corrected must be True, False or None, got "
                              f"{self.image_corrected!r}", option="image_corrected")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready options (what the result's ``options`` starts from; ``progress`` and
        ``compute``, which change no number, are left out; objects such as tables or beams
        are described)."""
        out: dict[str, Any] = {}
        for f in fields(self):
            if f.name in ("progress", "compute", "uv_range"):
                continue
            value = getattr(self, f.name)
            out[f.name] = str(value) if f.name in ("uvmin", "uvmax") and value is not None \
                else _describe(value)
        return out


# ----------------------------------------------------------------------------- inputs

def _positions_from(positions: Any) -> tuple[np.ndarray, np.ndarray, Any]:
    """(ra, dec) in radians and the catalog table (or None): :class:`xstack._inputs.Positions`."""
    pos = Positions.from_any(positions)
    return pos.ra, pos.dec, pos.table


class _Pointing:
    """One partition: its beam, frequencies and blocks."""

    def __init__(self, name: str, ds: Any, primary_beam: str | None, cutoff: float):
        self.name = name
        self.ds = ds
        self.center = tuple(float(x) for x in ds.attrs["phase_center"])
        self.freq = np.asarray(ds["frequency"].values, dtype=np.float64)
        dish = dish_diameter(ds)
        if isinstance(primary_beam, PrimaryBeam):
            self.beam = primary_beam
        else:  # a model name, checked by NoiseOptions
            self.beam = standard_beam(str(ds.attrs["telescope_name"]), dish, model=primary_beam,
                                      cutoff=cutoff)
        self.fmid = float(np.mean(self.freq))
        # rows of a block are (time, baseline): the antenna ids allow the per-antenna kernel
        self.antennas = None
        if "baseline_antenna1_id" in ds and "baseline_antenna2_id" in ds:
            self.antennas = (np.asarray(ds["baseline_antenna1_id"].values),
                             np.asarray(ds["baseline_antenna2_id"].values))

    def attenuation(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        """(nchan, K) power attenuation of positions in this pointing."""
        theta = angular_separation(ra, dec, self.center[0], self.center[1])
        return self.beam.main_lobe(theta[None, :], self.freq[:, None])

    def inside(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        """In this pointing: the one rule of every stage (:func:`xstack.beams.inside_field`)."""
        theta = angular_separation(ra, dec, self.center[0], self.center[1])
        return inside_field(self.beam, theta, self.freq)

    def radius(self, field_radius: float | None) -> float:
        if field_radius is not None:
            return field_radius
        if self.beam.model == "none":
            raise XstackError("primary_beam='none' has no edge: give field_radius_arcsec to say "
                              "where random positions may be placed")
        # the highest channel has the smallest beam: a position must be inside in every
        # channel (``inside``), so the field for random positions ends where that one does
        return float(self.beam.radius_at(max(self.beam.cutoff, 1e-3), float(self.freq.max())))


def _blocks(pt: _Pointing, bp: _BlockPlan):
    """(uvw, vis_w, wsum, wvar) per block of ``pt`` read in this process (the local pass):
    :func:`xstack.fit._data.stokes_i_blocks` then :func:`_prepare_block`."""
    for uvw, vis, wt in stokes_i_blocks(pt.ds, pt.name):
        yield _prepare_block(uvw, vis, wt, bp)


def _max_q_lambda(pointings: list[_Pointing]) -> float:
    """Longest baseline in wavelengths (at each pointing's highest frequency).

    A dask reduction over the UVW chunks: on a cluster it runs on the workers and only the
    maxima come back (max is exact, so the value is the same on any scheduler)."""
    import dask
    import dask.array as da

    maxima = []
    for pt in pointings:
        uvw = pt.ds["UVW"].data
        uvw = uvw.astype(np.float64) if isinstance(uvw, da.Array) else np.asarray(uvw, np.float64)
        xp = da if isinstance(uvw, da.Array) else np
        maxima.append(xp.nanmax(xp.hypot(uvw[..., 0], uvw[..., 1])))
    q = 0.0
    for pt, value in zip(pointings, dask.compute(*maxima)):
        q = max(q, float(value) * pt.freq.max() / SPEED_OF_LIGHT)
    return q


# ----------------------------------------------------------------------------- one block
# numpy and the kernels only, no scheduling: the local loop (:func:`_compute`) and the dask
# tasks (:func:`_pass_graph`) call the same functions, in the same order of additions.

@dataclass(frozen=True, eq=False)
class _BlockPlan:
    """What the sums of one block of a pointing need: positions, coefficients, options.

    In the dask pass this is one key per pointing that every block task depends on, so the
    (nchan, K) arrays travel once to each worker, not once per task."""

    name: str
    method: str
    freq: np.ndarray          # (nchan,) Hz
    n_baselines: int
    uv_range: tuple[Any, Any]
    l: np.ndarray             # (K,) direction cosines of every position (groups concatenated)
    m: np.ndarray
    n1: np.ndarray
    coef: np.ndarray          # (nchan, K) stacking coefficients w_k / A_k(nu) / sum w
    b: np.ndarray | None      # (nchan, K) injected apparent fluxes (mc), Jy
    starts: np.ndarray        # (G + 1,) group boundaries
    targets: slice            # the targets' positions (the last group)
    inv_a_t: np.ndarray       # (nchan, n_targets) 1/A of the targets (analytic, bootstrap)
    nbins: int
    edges: np.ndarray | None  # uv-profile bin edges, wavelengths
    engine: str
    tol_rad: float
    antennas: tuple[np.ndarray, np.ndarray] | None
    pidx: np.ndarray          # parallel-hand correlations (Stokes I) of a raw chunk


@dataclass
class _Partial:
    """Sums of the blocks of one pointing seen so far (folded in the data's order).

    Units: ``wchan`` sum of W per channel (Jy^-2), ``wvchan`` sum of W^2 sigma^2 (Jy^-2),
    ``num``/``prof`` data terms and ``num_m``/``prof_m`` injected-model terms (Jy^-1),
    ``X_t`` per-target data terms (Jy^-1), ``wbin`` sum of W per uv bin."""

    wchan: np.ndarray
    wvchan: np.ndarray
    wbin: np.ndarray
    X_t: np.ndarray
    num: np.ndarray
    num_m: np.ndarray
    prof: np.ndarray
    prof_m: np.ndarray
    any_data: bool = False
    engine_blocks: dict[str, int] = field(default_factory=lambda: {"antenna": 0, "numba": 0})
    engine_info: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def zeros(cls, bp: _BlockPlan) -> _Partial:
        """No block yet."""
        nchan, G, nbins = bp.freq.size, bp.starts.size - 1, max(bp.nbins, 0)
        return cls(wchan=np.zeros(nchan), wvchan=np.zeros(nchan), wbin=np.zeros(nbins),
                   X_t=np.zeros(bp.inv_a_t.shape[1]), num=np.zeros(G), num_m=np.zeros(G),
                   prof=np.zeros((G, nbins)), prof_m=np.zeros((G, nbins)))


def _fold(acc: _Partial, part: _Partial | None) -> _Partial:
    """``acc`` then ``part`` added, as a new object (a task's input is never changed: a
    rerun task on a cluster must find it as it was).

    Blocks are folded in the data's order, one at a time, on every scheduler: each sum is
    the same sequence of float additions as the local loop's, so results are bitwise equal.
    """
    if part is None:
        return acc
    info = dict(acc.engine_info)
    _merge_engine_info(info, part.engine_info)
    return _Partial(
        wchan=acc.wchan + part.wchan, wvchan=acc.wvchan + part.wvchan, wbin=acc.wbin + part.wbin,
        X_t=acc.X_t + part.X_t, num=acc.num + part.num, num_m=acc.num_m + part.num_m,
        prof=acc.prof + part.prof, prof_m=acc.prof_m + part.prof_m,
        any_data=acc.any_data or part.any_data,
        engine_blocks={k: v + part.engine_blocks[k] for k, v in acc.engine_blocks.items()},
        engine_info=info)


def _merge_engine_info(into: dict[str, Any], new: dict[str, Any]) -> None:
    """What later blocks add to the engine report: the first fallback's reason is kept, the
    antenna path's phase error is the largest seen."""
    if "engine_fallback" in new:
        into.setdefault("engine_fallback", new["engine_fallback"])
    if "antenna_phase_error_rad" in new:
        into["antenna_phase_error_rad"] = max(into.get("antenna_phase_error_rad", 0.0),
                                              new["antenna_phase_error_rad"])


def _stokes_i_chunk(vis: np.ndarray, weight: np.ndarray, flag: np.ndarray, uvw: np.ndarray,
                    pidx: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One raw chunk (time, baseline, channel, correlation) as (uvw, vis, weight) rows.

    The same arithmetic as one block of :func:`xstack.fit._data.stokes_i_blocks` (parallel
    hands; weight 0 where flagged, non-finite or not positive); the tests check the two
    passes bitwise equal on flagged data with NaNs."""
    nchan = vis.shape[2]
    vis = np.asarray(vis[..., pidx], dtype=np.complex128)
    wt = np.asarray(weight[..., pidx], dtype=np.float64)
    flag = np.asarray(flag[..., pidx], dtype=bool)
    uvw = np.asarray(uvw, dtype=np.float64).reshape(-1, 3)
    bad = flag | ~np.isfinite(vis) | ~(wt > 0) | ~np.isfinite(wt)
    bad |= ~np.all(np.isfinite(uvw), axis=-1).reshape(vis.shape[:2])[..., None, None]
    wt = np.where(bad, 0.0, wt)
    vis = np.where(bad, 0.0, vis)
    return uvw, vis.reshape(-1, nchan, pidx.size), wt.reshape(-1, nchan, pidx.size)


def _prepare_block(uvw: np.ndarray, vis: np.ndarray, wt: np.ndarray, bp: _BlockPlan):
    """(uvw, vis_w, wsum, wvar) of one block with the uv cut applied.

    ``wvar`` (analytic; else None): sum over the parallel hands of W^2 sigma^2 per
    (row, channel), sigma^2 the noise measured from the block's own visibilities
    (:func:`xstack._scatter.noise_model`: scatter of neighbouring channels or integrations
    per baseline and correlation) -- Var(sum W Re V) whatever the weights' scale.
    """
    wvar = None
    if bp.method == "analytic":
        from xstack._scatter import noise_model

        shape = (-1, bp.n_baselines) + vis.shape[1:]
        v4, w4 = vis.reshape(shape), wt.reshape(shape)
        model = noise_model(v4, w4, ~(w4 > 0))                 # (nbl, npol, 3)
        a, b = model[None, :, None, :, 0], model[None, :, None, :, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            cell = np.where(w4 > 0, w4**2 * a + w4 * b, 0.0)  # W^2 (a + b / W)
        wvar = cell.sum(axis=-1).reshape(vis.shape[:2])
    mask = uv_range_mask(uvw, bp.freq, *bp.uv_range)
    if mask is not None:
        wt = wt * mask[..., None]
        if wvar is not None:
            wvar = wvar * mask
    return uvw, np.sum(wt * vis, axis=-1), np.sum(wt, axis=-1), wvar


def _block_partial(uvw: np.ndarray, vis_w: np.ndarray, wsum: np.ndarray,
                   wvar: np.ndarray | None, bp: _BlockPlan) -> _Partial | None:
    """The sums of one prepared block (:func:`_prepare_block`); None if it carries no weight."""
    if not np.any(wsum > 0):
        return None
    part = _Partial.zeros(bp)
    part.any_data = True
    part.wchan = wsum.sum(axis=0)
    if wvar is not None:
        part.wvchan = wvar.sum(axis=0)
    tsl = bp.targets
    if bp.method in ("analytic", "bootstrap"):
        part.X_t = kernels.position_sums(uvw, bp.freq, vis_w, wsum, bp.l[tsl], bp.m[tsl],
                                         bp.n1[tsl], bp.inv_a_t)
        return part
    bins = None
    if bp.nbins:
        q = (np.hypot(uvw[:, 0], uvw[:, 1])[:, None] * bp.freq[None, :] / SPEED_OF_LIGHT)
        bins = np.clip(np.searchsorted(bp.edges, q, side="right") - 1, 0, bp.nbins - 1)
        bins = np.where(wsum > 0, bins, -1)
        part.wbin = np.bincount(bins[bins >= 0], wsum[bins >= 0], bp.nbins)
    part.num, part.num_m, part.prof, part.prof_m = _group_sums(
        bp, uvw, vis_w, wsum, bins, part.engine_blocks, part.engine_info)
    return part


def _chunk_partial(vis: np.ndarray, weight: np.ndarray, flag: np.ndarray, uvw: np.ndarray,
                   bp: _BlockPlan) -> _Partial | None:
    """One dask task: the sums of one raw chunk of a pointing."""
    return _block_partial(*_prepare_block(*_stokes_i_chunk(vis, weight, flag, uvw, bp.pidx),
                                          bp), bp)


# ----------------------------------------------------------------------------- API

def estimate_noise(data: Any, positions: Any, *, method: str = "mc", realizations: int = 100,
                   flux: Any = None, min_separation_arcsec: float | None = None,
                   avoid: Any = None, seed: int = 0, domain: str = "uv",
                   weighting: str = "pb", primary_beam: str | PrimaryBeam | None = None,
                   pb_cutoff: float = DEFAULT_PB_CUTOFF, uvmin: Any = None, uvmax: Any = None,
                   field_radius_arcsec: float | None = None, profile_bins: int = 0,
                   psf: Any = None, progress: bool = False, engine: str = "auto",
                   antenna_tol_rad: float = kernels.ANTENNA_TOL_RAD,
                   region: Any = "hull", image_corrected: bool | None = None,
                   autocorrelations: bool = False, compute: bool = True) -> NoiseResult | LazyResult:
    """Estimate the noise and bias of the uv-stacked flux at ``positions``.

    Parameters
    ----------
    data
        The (residual) visibilities: store path, DataTree, Dataset or dict of Datasets; for
        ``domain="image"`` a (residual, not primary-beam corrected) FITS image.
    positions
        The targets: catalog path / astropy Table (``ra``, ``dec`` deg, optional ``flux`` Jy,
        ``weight``) or ``(ra_deg, dec_deg)`` arrays.
    method
        ``analytic`` (the thermal noise of the estimator used, from the visibility weights;
        the optimal-weights value of eq. 6 in ``extra["optimal_noise_jy"]``), ``mc``
        (inject fake sources of the targets' flux and number at random positions, stack,
        repeat), ``random`` (stack random empty positions) or ``bootstrap`` (resample the
        targets with replacement).
    realizations
        Number of realisations R (>= 2) for mc/random/bootstrap; all are computed in one
        pass over the data.
    flux
        Injected flux for ``mc``: a number (Jy or a string such as ``"2uJy"``) or an array of
        one flux per target; default: the catalog's ``flux`` column, else the stacked flux
        measured at the targets (if positive).
    min_separation_arcsec
        Minimum distance of random positions from targets, avoided sources and each other.
        Default: 3 synthesized-beam widths (lambda_min / q_max).
    avoid
        Further positions to keep away from (bright sources): catalog or (ra_deg, dec_deg).
    seed
        Seed of the random generator (positions, bootstrap resampling).
    domain
        ``"uv"`` (uv-stacking, eq. 4) or ``"image"`` (mean of the nearest pixels, divided by
        the primary beam; mc injects S A PSF, the PSF from ``psf`` or ``X.psf.fits``).
    weighting
        Position weights w_k, as in :func:`xstack.stack_uv`: ``pb`` (default; A_k^2 at the
        mean frequency, inverse variance for primary-beam corrected fluxes), ``none`` (1) or
        ``column`` (catalog ``weight``;
        random/mc positions reuse the targets' weights).
    primary_beam, pb_cutoff
        Beam model (``airy``, ``gaussian``, ``none``; default the telescope's standard) and the
        attenuation below which a position is outside a pointing.
    uvmin, uvmax
        uv range (``5000m``, ``23.8klambda``).
    field_radius_arcsec
        Radius around each pointing inside which random positions may be placed (further
        limited by ``region``). Default: the radius of the beam cutoff (highest frequency).
    psf
        Image domain: the dirty beam (FITS) for ``mc``.
    profile_bins
        If > 0, also return the uv-profiles of the realisations (paper Fig. 9) in this many
        bins of uv distance.
    progress
        Progress bar on stderr.
    engine
        Kernel of ``mc``/``random`` (the results agree to float64 rounding): ``auto``
        (default) uses per-antenna phasors for every block whose baseline UVW are differences
        of per-antenna UVW to ``antenna_tol_rad`` and the per-row kernel for the others;
        ``antenna`` requires the antenna path everywhere (error otherwise); ``numba`` forces
        the per-row kernel. ``analytic`` and ``bootstrap`` always use the per-row kernel.
        The engine used is reported in ``extra["engine"]`` (``antenna``, ``numba`` or
        ``mixed``), with the block counts and the reason of the first fallback.
    region
        Where random / injected positions are drawn (``mc``, ``random``), always intersected
        with the pointings' discs: ``"hull"`` (default: the targets' footprint, convex hulls
        of their friends-of-friends groups grown by half their median nearest-neighbour
        spacing, :func:`xstack.noise.positions.hull_region`), ``"beam"`` (the whole beam
        inside the cutoff / field radius), a polygon file (ECSV/CSV of vertex ``ra``, ``dec``
        in degrees) or a FITS mask (finite nonzero pixels inside). Reported in
        ``extra["region"]`` with its area. Stacked noise grows as 1/A towards the beam edge,
        so positions must sample the same beam response as the targets.
    antenna_tol_rad
        Largest accepted phase error (radians, at the highest frequency and the farthest
        position) of the per-antenna factorisation; see
        :meth:`xstack.noise.kernels.AntennaLayout.phase_error`.
    image_corrected
        Image domain: whether the image is primary-beam corrected (default: its header's
        ``XSPBCOR``; see :func:`xstack.imstack.io.image_beam`). Corrected and uncorrected
        images give the same answer.
    autocorrelations
        uv domain: include autocorrelation baselines (off: they do not measure the sky).
    compute
        False (uv domain): plan only and return a :class:`~xstack._lazy.LazyResult`, computed
        later in one pass with other lazy results (``xstack.compute(stack, noise)``).

    Returns
    -------
    NoiseResult
        Or a LazyResult computing to it. With a ``distributed.Client`` active the pass runs
        on its workers (one task per chunk; the same numbers, bitwise).

    Raises
    ------
    XstackError
        Unknown method, fewer than 2 realisations, no data in the uv range, a catalog too
        dense to place random positions; ``compute=False`` in the image domain.
    """
    # every keyword is the NoiseOptions field of the same name (the tests check it)
    options = NoiseOptions(**{k: v for k, v in locals().items() if k not in ("data", "positions")})
    if options.domain == "image":
        from xstack.noise.image import estimate_noise_image

        return estimate_noise_image(data, positions, options)
    inputs = _load(data, positions, options)       # targets, weights, pointings (no data)
    plan = _plan(inputs, options)                  # every realisation's positions (no data)
    if not options.compute:
        return _lazy(inputs, plan, options)        # the pass as a dask collection
    # the one pass over the visibilities: tasks on a cluster, else this process's loop
    run = _compute_dask if active_client() is not None else _compute
    return _assemble(inputs, plan, run(inputs, plan, options), options)


# ----------------------------------------------------------------------------- phases

@dataclass(frozen=True)
class _Inputs:
    """The normalized inputs: targets (radians), their weights, the pointings (no data read)."""

    ra: np.ndarray
    dec: np.ndarray
    cat: Any
    w: np.ndarray
    pointings: list[_Pointing]
    inside_any: np.ndarray  # target inside some pointing (the one rule of every stage)


@dataclass
class _Plan:
    """The position groups evaluated in the one pass: R random ones (mc, random), then the
    targets; and what the random draws decided (separation, region, bootstrap resamples)."""

    groups_ra: list[np.ndarray]
    groups_dec: list[np.ndarray]
    groups_w: list[np.ndarray]
    groups_s: list[np.ndarray]
    n_real: int
    min_sep: float | None
    region: Any
    need_flux_for_mc: bool
    nbins: int
    edges: np.ndarray | None
    counts: np.ndarray | None  # (R, n_targets) bootstrap multiplicities

    def __post_init__(self) -> None:
        self.sizes = np.array([g.size for g in self.groups_ra])
        self.starts = np.concatenate([[0], np.cumsum(self.sizes)]).astype(np.int64)
        self.all_ra, self.all_dec = np.concatenate(self.groups_ra), np.concatenate(self.groups_dec)
        self.all_w, self.all_s = np.concatenate(self.groups_w), np.concatenate(self.groups_s)


@dataclass
class _Measured:
    """Sums of the one pass over the data, per group (G) and per target and pointing (P, n)."""

    num: np.ndarray           # sum of data terms, per group
    num_m: np.ndarray         # sum of injected-model terms, per group
    den: np.ndarray           # sum of weights of the pointings a group is inside
    expect: np.ndarray        # injected flux seen by a noiseless stack
    prof: np.ndarray
    prof_m: np.ndarray
    prof_w: np.ndarray
    X_t: np.ndarray           # per-target data term (1/A coefficients)
    inside_t: np.ndarray
    var_t: np.ndarray         # sum_c W_c / A_kc^2 per pointing
    var_emp_t: np.ndarray     # the same with measured noise
    wk_t: np.ndarray          # w_k of the targets per pointing
    wtot_p: np.ndarray
    any_data: bool = False
    engine_blocks: dict[str, int] = field(default_factory=lambda: {"antenna": 0, "numba": 0})
    engine_info: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def zeros(cls, n_groups: int, nbins: int, n_pointings: int, n_targets: int) -> _Measured:
        """All sums zero."""
        g, p = np.zeros(n_groups), np.zeros((n_groups, max(nbins, 0)))
        t = np.zeros((n_pointings, n_targets))
        return cls(num=g.copy(), num_m=g.copy(), den=g.copy(), expect=g.copy(), prof=p.copy(),
                   prof_m=p.copy(), prof_w=p.copy(), X_t=t.copy(),
                   inside_t=np.zeros((n_pointings, n_targets), bool), var_t=t.copy(),
                   var_emp_t=t.copy(), wk_t=t.copy(), wtot_p=np.zeros(n_pointings))


def _load(data: Any, positions: Any, options: NoiseOptions) -> _Inputs:
    """Targets, their weights and the pointings (beams, frequencies; no visibility read)."""
    ra_t, dec_t, cat = _positions_from(positions)
    w_t = np.ones(ra_t.size)
    if options.weighting == "column":
        if cat is None or "weight" not in cat.colnames:
            raise XstackError("weighting='column' needs a catalog with a weight column")
        w_t = np.asarray(cat["weight"], dtype=np.float64)
    beam = None if options.primary_beam == "auto" else options.primary_beam
    pointings = [_Pointing(n, ds, beam, options.pb_cutoff)
                 for n, ds in as_partitions(data, options.autocorrelations)]
    inside_any = np.zeros(ra_t.size, dtype=bool)
    for pt in pointings:
        inside_any |= pt.inside(ra_t, dec_t)
    if not inside_any.any():
        raise NoDataError("no target position lies inside a primary beam (above the cutoff)")
    return _Inputs(ra=ra_t, dec=dec_t, cat=cat, w=w_t, pointings=pointings,
                   inside_any=inside_any)


def _plan(inputs: _Inputs, options: NoiseOptions) -> _Plan:
    """The position groups of every realisation (random draws, no visibility read; only the
    UVW when the default separation or the profile bins need the longest baseline)."""
    rng = np.random.default_rng(options.seed)
    groups: tuple[list, list, list, list] = ([], [], [], [])
    min_sep = region = None
    n_real = 0
    if options.method in ("mc", "random"):
        min_sep, region = _random_groups(inputs, options, rng, groups)
        n_real = options.realizations
    # the real targets form the last group (measured flux; no injection)
    for g, v in zip(groups, (inputs.ra, inputs.dec, inputs.w, np.zeros(inputs.ra.size))):
        g.append(v)
    cat = inputs.cat
    need_flux = (options.method == "mc" and options.flux is None
                 and (cat is None or "flux" not in cat.colnames))
    nbins = options.profile_bins if options.method in ("mc", "random") else 0
    edges = None
    if nbins > 0:
        edges = np.linspace(0.0, _max_q_lambda(inputs.pointings) * (1 + 1e-9), nbins + 1)
    counts = None
    if options.method == "bootstrap":
        # resample the targets that enter the stack (inside some pointing), as many as there
        # are: the same positions, and the same count, as every other method and uvstack use
        idx_in = np.flatnonzero(inputs.inside_any)
        n_in, n_t = idx_in.size, inputs.ra.size
        counts = np.stack([np.bincount(idx_in[rng.integers(0, n_in, n_in)], minlength=n_t)
                           for _ in range(options.realizations)])
    return _Plan(groups_ra=groups[0], groups_dec=groups[1], groups_w=groups[2],
                 groups_s=groups[3], n_real=n_real, min_sep=min_sep, region=region,
                 need_flux_for_mc=need_flux, nbins=nbins, edges=edges, counts=counts)


def _random_groups(inputs: _Inputs, options: NoiseOptions, rng: np.random.Generator,
                   groups: tuple[list, list, list, list]) -> tuple[float, Any]:
    """Append the R random position groups (mc, random) to ``groups``; return the minimum
    separation (radians) and the region's description."""
    pointings, ra_t, dec_t, inside_any = inputs.pointings, inputs.ra, inputs.dec, inputs.inside_any
    if options.min_separation_arcsec is None:
        qmax = _max_q_lambda(pointings)
        min_sep = 3.0 / qmax if qmax > 0 else 0.0
    else:
        min_sep = float(options.min_separation_arcsec) * ARCSEC
    av_ra, av_dec = [ra_t], [dec_t]
    if options.avoid is not None:
        a_ra, a_dec, _ = _positions_from(options.avoid)
        av_ra.append(a_ra)
        av_dec.append(a_dec)
    # where random positions go: the targets' footprint (default), the whole beam, a
    # polygon or a mask; always inside some pointing's disc (beam cutoff / field radius)
    reg = make_region(options.region, ra_t[inside_any], dec_t[inside_any], min_margin=min_sep)
    field_radius = options.field_radius_arcsec
    centers = np.array([pt.center for pt in pointings])
    radii = np.array([
        np.pi if (field_radius is None and pt.beam.model == "none"
                  and reg.proposal is not None)  # no beam edge: the region alone
        else pt.radius(None if field_radius is None else field_radius * ARCSEC)
        for pt in pointings])
    uniq, idx = np.unique(np.round(centers, 12), axis=0, return_index=True)
    region = reg.describe(centers[idx], radii[idx])
    n_fake = int(inside_any.sum())
    r_ra, r_dec = random_positions(n_fake, options.realizations, centers[idx], radii[idx],
                                   avoid_ra=np.concatenate(av_ra),
                                   avoid_dec=np.concatenate(av_dec), min_separation=min_sep,
                                   rng=rng, region=reg)
    s_fake = np.zeros(n_fake)
    if options.method == "mc":
        s_fake = _injected_fluxes(options.flux, inputs.cat, inside_any, n_fake)
        if s_fake is None:  # unit flux now, scaled by the measured target flux later
            s_fake = np.ones(n_fake)
    w_fake = inputs.w[inside_any]
    for r in range(options.realizations):
        perm = rng.permutation(n_fake)
        for g, v in zip(groups, (r_ra[r], r_dec[r], w_fake[perm], s_fake[perm])):
            g.append(v)
    return min_sep, region


def _compute(inputs: _Inputs, plan: _Plan, options: NoiseOptions) -> _Measured:
    """The one pass over the data of every pointing in this process: the sums of every
    group at once (block by block, each block's sums folded in the data's order)."""
    from xstack._progress import progress_iter

    setups = [_setup(pt, plan, options) for pt in inputs.pointings]
    parts = []
    for pt, st in zip(inputs.pointings, setups):
        acc = _Partial.zeros(st.block)
        for block in progress_iter(_blocks(pt, st.block), f"noise {pt.name}",
                                   enabled=options.progress):
            acc = _fold(acc, _block_partial(*block, st.block))
        parts.append(acc)
    return _measured(inputs, plan, options, setups, parts)


def _compute_dask(inputs: _Inputs, plan: _Plan, options: NoiseOptions) -> _Measured:
    """The same pass as dask tasks on the active scheduler (a distributed Client)."""
    import dask

    from xstack._progress import dask_progress

    setups, graph = _pass_graph(inputs, plan, options)
    with dask_progress("noise", enabled=options.progress):
        parts = dask.compute(*graph)
    return _measured(inputs, plan, options, setups, list(parts))


def _lazy(inputs: _Inputs, plan: _Plan, options: NoiseOptions) -> LazyResult:
    """The pass as a dask collection that finishes (in the caller) into a NoiseResult."""
    setups, graph = _pass_graph(inputs, plan, options)

    def finish(parts: list[Any]) -> NoiseResult:
        return _assemble(inputs, plan, _measured(inputs, plan, options, setups, parts), options)

    return LazyResult(graph, finish, "estimate_noise")


def _pass_graph(inputs: _Inputs, plan: _Plan, options: NoiseOptions
                ) -> tuple[list[_Setup], list[Any]]:
    """The pass as dask tasks; returns the setups and one Delayed per pointing (its
    :class:`_Partial`, :func:`_pointing_graph`)."""
    setups = [_setup(pt, plan, options) for pt in inputs.pointings]
    return setups, [_pointing_graph(_block_arrays(pt.ds), st.block)
                    for pt, st in zip(inputs.pointings, setups)]


def _pointing_graph(arrays: list[Any], block: _BlockPlan) -> Any:
    """One pointing's pass: one task per chunk (its sums) and a chain of folds in the chunks'
    order (bitwise the local loop's sums), as one graph layer.

    The chunk tasks take the store's own chunk keys, so another lazy result over the same
    store (``stack_uv(..., compute=False)``) computed together reads each chunk once. The
    block plan is one key that every chunk task depends on: shipped once to each worker.
    The layer is written out (not built from ``dask.delayed`` calls, each of which merges the
    graph so far: quadratic in the chunks, 3.6 s for 2000 chunks).
    """
    from dask.base import tokenize
    from dask.core import flatten
    from dask.delayed import Delayed
    from dask.highlevelgraph import HighLevelGraph

    token = tokenize(block, [a.name for a in arrays])
    name = f"noise-pass-{token}"
    plan_key, sums, folds = f"noise-block-plan-{token}", f"noise-chunk-sums-{token}", name
    layer: dict[Any, Any] = {plan_key: block, (folds, 0): (_Partial.zeros, plan_key)}
    keys = [list(flatten(a.__dask_keys__())) for a in arrays] or [[]]
    for i, chunk in enumerate(zip(*keys, strict=True)):
        layer[(sums, i)] = (_chunk_partial, *chunk, plan_key)
        layer[(folds, i + 1)] = (_fold, (folds, i), (sums, i))
    graph = HighLevelGraph.from_collections(name, layer, dependencies=arrays)
    return Delayed((folds, len(keys[0])), graph, layer=name)


def _block_arrays(ds: Any) -> list[Any]:
    """VISIBILITY, WEIGHT, FLAG, UVW as dask arrays chunked like the local loop's blocks
    (:func:`xstack.fit._data.time_blocks` along time, whole along the other axes). A store
    chunked that way (the usual case) keeps its own chunk keys."""
    import dask.array as da

    tchunks = (tuple(s.stop - s.start for s in time_blocks(ds)),)
    if not tchunks[0]:
        return []  # no time: no chunk, no sums
    out = []
    for var in ("VISIBILITY", "WEIGHT", "FLAG", "UVW"):
        arr = ds[var].data
        want = tchunks + tuple((n,) for n in arr.shape[1:])
        if not isinstance(arr, da.Array):
            arr = da.from_array(arr, chunks=want)
        elif arr.chunks != want:
            arr = arr.rechunk(want)
        out.append(arr)
    return out


@dataclass
class _Setup:
    """One pointing's plan in the caller: the block plan and what finishes its sums."""

    block: _BlockPlan
    inside: np.ndarray   # (K,) positions inside the pointing
    wk: np.ndarray       # (K,) position weights (0 outside)
    gsum: np.ndarray     # (G,) sum of w_k per group
    inv_a: np.ndarray    # (nchan, K) 1/A (0 outside)


def _setup(pt: _Pointing, plan: _Plan, options: NoiseOptions) -> _Setup:
    """Positions of every group in pointing ``pt``: weights, coefficients (no data read)."""
    method, starts, sizes = options.method, plan.starts, plan.sizes
    A = pt.attenuation(plan.all_ra, plan.all_dec)                     # (nchan, K)
    inside = pt.inside(plan.all_ra, plan.all_dec)
    l, m, _, n1 = radec_to_lmn(plan.all_ra, plan.all_dec, *pt.center)
    wk = plan.all_w.copy()
    if options.weighting == "pb":
        wk = np.asarray(pt.beam(angular_separation(plan.all_ra, plan.all_dec, *pt.center),
                                pt.fmid)) ** 2
    wk = np.where(inside, wk, 0.0)
    gsum = np.add.reduceat(wk, starts[:-1]) if sizes.size else np.zeros(0)
    gsum = np.where(sizes > 0, gsum, 0.0)
    norm = np.repeat(np.where(gsum > 0, gsum, 1.0), sizes)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_a = np.where(inside[None, :] & (A > 0), 1.0 / A, 0.0)
    coef = inv_a * (wk / norm)[None, :]                  # (nchan, K)
    b = plan.all_s[None, :] * A if method == "mc" else None
    tsl = slice(int(starts[-2]), int(starts[-1]))
    pidx = parallel_hand_index(pt.ds, pt.name)
    block = _BlockPlan(
        name=pt.name, method=method, freq=pt.freq, n_baselines=int(pt.ds.sizes["baseline_id"]),
        uv_range=options.uv_range, l=l, m=m, n1=n1, coef=coef, b=b, starts=starts,
        targets=tsl, inv_a_t=np.ascontiguousarray(inv_a[:, tsl]), nbins=plan.nbins,
        edges=plan.edges, engine=options.engine, tol_rad=options.antenna_tol_rad,
        antennas=pt.antennas, pidx=pidx)
    return _Setup(block=block, inside=inside, wk=wk, gsum=gsum, inv_a=inv_a)


def _measured(inputs: _Inputs, plan: _Plan, options: NoiseOptions, setups: list[_Setup],
              parts: list[_Partial]) -> _Measured:
    """The pass's sums combined over the pointings (in their order), as in xstack.uvstack:
    each pointing weighted by its sum of w_k. NoDataError if no block carried weight."""
    acc = _Measured.zeros(plan.sizes.size, plan.nbins, len(inputs.pointings), inputs.ra.size)
    for ip, (st, part) in enumerate(zip(setups, parts, strict=True)):
        _finish_pointing(ip, st, part, plan, acc)
    if not acc.any_data:
        raise NoDataError(f"no visibilities left after the uv cuts (uvmin={options.uvmin}, "
                          f"uvmax={options.uvmax}) or all data flagged")
    return acc


def _finish_pointing(ip: int, st: _Setup, part: _Partial, plan: _Plan, acc: _Measured) -> None:
    """Add pointing ``ip``'s sums (``part``, every block of its data) to ``acc``."""
    bp, gsum, inv_a, tsl = st.block, st.gsum, st.inv_a, st.block.targets
    acc.any_data = acc.any_data or part.any_data
    for k, v in part.engine_blocks.items():
        acc.engine_blocks[k] += v
    _merge_engine_info(acc.engine_info, part.engine_info)
    acc.inside_t[ip] = st.inside[tsl]
    acc.wk_t[ip] = st.wk[tsl]
    acc.X_t[ip] += part.X_t
    wchan = part.wchan
    wtot = float(wchan.sum())
    acc.wtot_p[ip] = wtot
    acc.num += gsum * part.num
    acc.num_m += gsum * part.num_m
    acc.den += gsum * wtot
    acc.var_t[ip] = (wchan[:, None] * inv_a[:, tsl] ** 2).sum(axis=0)
    acc.var_emp_t[ip] = (part.wvchan[:, None] * inv_a[:, tsl] ** 2).sum(axis=0)
    if bp.b is not None:
        acc.expect += gsum * np.add.reduceat((wchan[:, None] * bp.coef * bp.b).sum(axis=0),
                                             plan.starts[:-1]) * (plan.sizes > 0)
    if plan.nbins:
        acc.prof += gsum[:, None] * part.prof
        acc.prof_m += gsum[:, None] * part.prof_m
        acc.prof_w += gsum[:, None] * part.wbin[None, :]


def _assemble(inputs: _Inputs, plan: _Plan, measured: _Measured,
              options: NoiseOptions) -> NoiseResult:
    """The result: noise, bias, values and the JSON extras from the pass's sums."""
    extra: dict[str, Any] = {"weighting": options.weighting,
                             "uvmin": None if options.uvmin is None else str(options.uvmin),
                             "uvmax": None if options.uvmax is None else str(options.uvmax),
                             "n_pointings": len(inputs.pointings), "seed": options.seed}
    used = options.to_dict()  # the options, completed with what the run decided
    if plan.min_sep is not None:
        extra["min_separation_arcsec"] = used["min_separation_arcsec"] = float(plan.min_sep / ARCSEC)
        extra["region"] = plan.region
    if options.method in ("mc", "random"):
        blocks = measured.engine_blocks
        extra["engine"] = used["engine"] = ("mixed" if all(blocks.values()) else
                                            "antenna" if blocks["antenna"] else "numba")
        extra["engine_blocks"] = dict(blocks)
        extra.update(measured.engine_info)
    if options.method in ("analytic", "bootstrap"):
        return _assemble_targets(inputs, plan, measured, options, extra, used)
    return _assemble_realizations(plan, measured, options, extra, used)


def _assemble_targets(inputs: _Inputs, plan: _Plan, acc: _Measured, options: NoiseOptions,
                      extra: dict[str, Any], used: dict[str, Any]) -> NoiseResult:
    """analytic and bootstrap: from the per-target sums."""
    args = (acc.X_t, acc.inside_t, acc.wtot_p, acc.wk_t)
    target_flux = _combine_targets(*args, np.ones(inputs.ra.size))
    if options.method == "bootstrap":
        vals = np.array([_combine_targets(*args, c) for c in plan.counts])
        return NoiseResult(method="bootstrap", noise_jy=float(np.std(vals, ddof=1)),
                           bias_jy=float(np.mean(vals) - target_flux),
                           realizations=options.realizations, values=vals,
                           target_flux_jy=target_flux, n_positions=int(inputs.inside_any.sum()),
                           extra=extra, options=used)
    noise, extra_a, n_used = _analytic_noise(acc.var_t, acc.inside_t, acc.wtot_p, acc.wk_t)
    extra.update(extra_a)
    # the same estimator's noise with the variance measured from the visibilities
    # (not trusting WEIGHT as 1/sigma^2), as xstack.uvstack's flux_err_empirical_jy
    emp, _, _ = _analytic_noise(acc.var_emp_t, acc.inside_t, acc.wtot_p, acc.wk_t)
    extra["noise_empirical_jy"] = emp
    if np.isfinite(emp) and noise > 0 and abs(emp / noise - 1.0) > EMPIRICAL_TOLERANCE:
        warnings.warn(
            f"analytic noise from WEIGHT ({noise:.3g} Jy) and from the visibilities' "
            f"own scatter ({emp:.3g} Jy) differ by a factor {emp / noise:.3g}: the "
            "weights are not 1/sigma^2 of the data; trust noise_empirical_jy (or a "
            "random/mc estimate)", stacklevel=4)  # the caller of estimate_noise
    return NoiseResult(method="analytic", noise_jy=noise, bias_jy=None, realizations=0,
                       target_flux_jy=target_flux, n_positions=n_used, extra=extra,
                       options=used)


def _assemble_realizations(plan: _Plan, acc: _Measured, options: NoiseOptions,
                           extra: dict[str, Any], used: dict[str, Any]) -> NoiseResult:
    """mc and random: from the per-group sums (the targets are the last group)."""
    n_real, num, den = plan.n_real, acc.num, acc.den
    dens = np.where(den > 0, den, np.nan)
    target_flux = float(num[-1] / dens[-1])
    scale = 1.0
    if plan.need_flux_for_mc:
        # fluxes were injected at 1 Jy; everything injected is linear in the flux
        scale = max(target_flux, 0.0)
        extra["injected_flux_jy"] = scale
    flux_vals = (num + scale * acc.num_m) / dens
    expect = acc.expect * scale
    prof = acc.prof + scale * acc.prof_m
    vals = flux_vals[:n_real]
    profile = None
    if plan.nbins:
        edges = plan.edges
        with np.errstate(invalid="ignore", divide="ignore"):
            pv = prof / acc.prof_w
        profile = {"q_klambda": (0.5 * (edges[1:] + edges[:-1]) / 1e3).tolist(),
                   "edges_klambda": (edges / 1e3).tolist(),
                   "values": pv[:n_real], "target": pv[-1], "weight": acc.prof_w[0]}
    pos = np.degrees(np.stack([np.stack(plan.groups_ra[:n_real]),
                               np.stack(plan.groups_dec[:n_real])], -1))
    common = dict(realizations=n_real, values=vals, target_flux_jy=target_flux,
                  n_positions=int(plan.sizes[0]), profile=profile, extra=extra,
                  positions_deg=pos, options=used)
    if options.method == "random":
        return NoiseResult(method="random", noise_jy=float(np.std(vals, ddof=1)),
                           bias_jy=float(np.mean(vals)), **common)
    injected = expect[:n_real] / np.where(den[:n_real] > 0, den[:n_real], np.nan)
    if plan.need_flux_for_mc:
        extra["injected_flux_from"] = "stacked target flux"
    if profile is not None:
        profile["injected"] = injected
    return NoiseResult(method="mc", noise_jy=float(np.std(vals, ddof=1)),
                       bias_jy=float(np.mean(vals - injected)), injected=injected,
                       injected_flux_jy=scale * np.stack(plan.groups_s[:n_real]), **common)


def _analytic_noise(var: np.ndarray, inside: np.ndarray, wtot: np.ndarray, w: np.ndarray
                    ) -> tuple[float, dict[str, Any], int]:
    """Noise of the estimator actually used, the extras (that of optimal weights, eq. 6),
    and the number of positions used.

    ``var[p, k]`` = Var(X_pk) = sum_vis W / A_pk^2 (W = 1 / sigma^2 of a real part),
    ``w[p, k]`` the position weights, ``wtot[p]`` = sum_vis W of pointing p. The stacked flux
    is F = sum_p sum_k w_pk X_pk / D with D = sum_p s_p W_p, s_p = sum_k w_pk (inside); for
    independent thermal noise and positions far apart compared with the synthesized beam

        Var F = sum_p sum_k w_pk^2 Var(X_pk) / D^2.

    The optimal (inverse-variance) weights give (sum_k sigma_k^-2)^-1/2 with sigma_k the noise
    of position k stacked alone (its pointings combined as for F).
    """
    wi = w * inside
    D = float(np.sum(wi.sum(axis=1) * wtot))
    noise = float(np.sqrt(np.sum(wi**2 * var)) / D) if D > 0 else float("nan")
    wsum_in = (wi * wtot[:, None]).sum(axis=0)
    ok = wsum_in > 0
    sig2 = np.full(w.shape[1], np.inf)
    sig2[ok] = (wi**2 * var).sum(axis=0)[ok] / wsum_in[ok] ** 2
    extra = {"optimal_noise_jy": float(1.0 / np.sqrt(np.sum(1.0 / sig2[ok]))),
             "sigma_k_median_jy": float(np.median(np.sqrt(sig2[ok])))}
    return noise, extra, int(ok.sum())


def _group_sums(bp: _BlockPlan, uvw, vis_w, wsum, bins, blocks: dict[str, int],
                info: dict[str, Any]):
    """Group sums of one block by the antenna path when valid (or forced), else per row."""
    l, m, n1, coef, b, starts, nbins = bp.l, bp.m, bp.n1, bp.coef, bp.b, bp.starts, bp.nbins
    if bp.engine != "numba":
        try:
            if bp.antennas is None:
                raise kernels.FactorisationError("no baseline antenna ids in the data")
            layout = kernels.antenna_layout(uvw, *bp.antennas, row_ok=np.any(wsum > 0, axis=1))
            if bp.engine == "auto" and layout.rows_per_antenna < MIN_ROWS_PER_ANTENNA:
                raise kernels.FactorisationError(
                    f"{layout.rows_per_antenna:.2f} baselines per antenna: no gain")
            err = layout.phase_error(l, m, n1, bp.freq)
            out = kernels.group_sums_antenna(layout, bp.freq, vis_w, wsum, l, m, n1, coef, b,
                                             starts, bins=bins, nbins=nbins, tol_rad=bp.tol_rad)
        except kernels.FactorisationError as exc:
            if bp.engine == "antenna":
                raise XstackError(f"engine='antenna' is not valid for {bp.name}: {exc}") from exc
            info.setdefault("engine_fallback", f"{bp.name}: {exc}")
        else:
            blocks["antenna"] += 1
            info["antenna_phase_error_rad"] = max(info.get("antenna_phase_error_rad", 0.0), err)
            return out
    blocks["numba"] += 1
    return kernels.group_sums(uvw, bp.freq, vis_w, wsum, l, m, n1, coef, b, starts, bins=bins,
                              nbins=nbins)


def _combine_targets(X: np.ndarray, inside: np.ndarray, wtot: np.ndarray, w: np.ndarray,
                     counts: np.ndarray) -> float:
    """Stacked flux of a multiset of targets (``counts`` per target) from per-target sums.

    ``X[p, k]`` = sum_vis Re(VW p_k) / A_pk, ``w[p, k]`` the position weights per pointing:
    F = sum_p sum_k c_k w_pk X_pk / sum_p s_p W_p with s_p = sum_k c_k w_pk (inside).
    """
    num = 0.0
    den = 0.0
    for ip in range(X.shape[0]):
        cw = counts * w[ip] * inside[ip]
        s = float(np.sum(cw))
        if s > 0:
            num += float(np.sum(cw * X[ip]))
            den += s * wtot[ip]
    return num / den if den > 0 else float("nan")


def _injected_fluxes(flux: Any, cat: Any, inside: np.ndarray, n_fake: int) -> np.ndarray | None:
    """Flux of each fake source (Jy): explicit, catalog column, or None (decide later)."""
    from xstack.coords import parse_flux

    if flux is None:
        if cat is not None and "flux" in cat.colnames:
            return np.asarray(cat["flux"], dtype=np.float64)[inside]
        return None
    if isinstance(flux, str):
        return np.full(n_fake, parse_flux(flux))
    arr = np.atleast_1d(np.asarray(flux, dtype=np.float64))
    if arr.size == 1:
        return np.full(n_fake, float(arr[0]))
    if arr.size == inside.size:
        return arr[inside]
    if arr.size == n_fake:
        return arr
    raise XstackError(f"flux: give one value or one per target ({inside.size}), got {arr.size}")
