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

import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from xstack import _vocabulary
from xstack._antenna import MIN_ROWS_PER_ANTENNA
from xstack._inputs import Positions
from xstack._json import finite_or_none
from xstack._result import Result
from xstack._scatter import EMPIRICAL_TOLERANCE
from xstack.beams import (
    DEFAULT_PB_CUTOFF,
    PrimaryBeam,
    dish_diameter,
    inside_field,
    standard_beam,
)
from xstack.coords import SPEED_OF_LIGHT, angular_separation, radec_to_lmn
from xstack.errors import NoDataError, OptionError, XstackError
from xstack.fit._data import as_partitions, parse_uv_limit, stokes_i_blocks, uv_range_mask
from xstack.noise import kernels
from xstack.noise.positions import ARCSEC, make_region, random_positions

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
        else:
            if primary_beam not in (None, "airy", "gaussian", "none"):
                raise XstackError(f"unknown primary beam {primary_beam!r} for the noise "
                                  "estimate (use airy, gaussian or none)")
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


def _blocks(pt: _Pointing, uvmin, uvmax, empirical: bool = False):
    """(uvw, vis_w, wsum, wvar) per block with the uv cut applied.

    ``wvar`` (with ``empirical``; else None): sum over the parallel hands of W^2 sigma^2 per
    (row, channel), sigma^2 the noise measured from the block's own visibilities
    (:func:`xstack._scatter.noise_model`: scatter of neighbouring channels or integrations
    per baseline and correlation) -- Var(sum W Re V) whatever the weights' scale.
    """
    nb = pt.ds.sizes["baseline_id"]
    for uvw, vis, wt in stokes_i_blocks(pt.ds, pt.name):
        wvar = None
        if empirical:
            from xstack._scatter import noise_model

            shape = (-1, nb) + vis.shape[1:]
            v4, w4 = vis.reshape(shape), wt.reshape(shape)
            model = noise_model(v4, w4, ~(w4 > 0))                 # (nbl, npol, 3)
            a, b = model[None, :, None, :, 0], model[None, :, None, :, 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                cell = np.where(w4 > 0, w4**2 * a + w4 * b, 0.0)  # W^2 (a + b / W)
            wvar = cell.sum(axis=-1).reshape(vis.shape[:2])
        mask = uv_range_mask(uvw, pt.freq, uvmin, uvmax)
        if mask is not None:
            wt = wt * mask[..., None]
            if wvar is not None:
                wvar = wvar * mask
        yield uvw, np.sum(wt * vis, axis=-1), np.sum(wt, axis=-1), wvar


def _max_q_lambda(pointings: list[_Pointing]) -> float:
    q = 0.0
    for pt in pointings:
        uvw = np.asarray(pt.ds["UVW"].values, dtype=np.float64)
        q = max(q, float(np.nanmax(np.hypot(uvw[..., 0], uvw[..., 1]))) * pt.freq.max() / SPEED_OF_LIGHT)
    return q


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
                   autocorrelations: bool = False) -> NoiseResult:
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

    Returns
    -------
    NoiseResult

    Raises
    ------
    XstackError
        Unknown method, fewer than 2 realisations, no data in the uv range, a catalog too
        dense to place random positions.
    """
    if method not in METHODS:
        raise OptionError(f"unknown noise method {method!r} (use {', '.join(METHODS)})")
    if domain not in ("uv", "image"):
        raise OptionError(f"unknown domain {domain!r} (use uv or image)")
    if weighting not in WEIGHTINGS:
        raise OptionError(f"unknown weighting {weighting!r} (use {', '.join(WEIGHTINGS)})")
    if engine not in ENGINES:
        raise OptionError(f"unknown engine {engine!r} (use {', '.join(ENGINES)})")
    realizations = int(realizations)
    if method != "analytic" and realizations < 2:
        raise OptionError(f"need at least 2 realisations to estimate a scatter, got {realizations}")
    if domain == "image":
        from xstack.noise.image import estimate_noise_image

        if not (region is None or (isinstance(region, str) and region.lower() == "hull")):
            raise OptionError("region: only the default (hull) is available for images so far; "
                              "leave out region=", option="region")

        return estimate_noise_image(data, positions, method=method, realizations=realizations,
                                    flux=flux, min_separation_arcsec=min_separation_arcsec,
                                    avoid=avoid, seed=seed, weighting=weighting,
                                    primary_beam=primary_beam, pb_cutoff=pb_cutoff,
                                    field_radius_arcsec=field_radius_arcsec, psf=psf,
                                    image_corrected=image_corrected)
    lo, hi = parse_uv_limit(uvmin), parse_uv_limit(uvmax)
    ra_t, dec_t, cat = _positions_from(positions)
    n_t = ra_t.size
    w_t = np.ones(n_t)
    if weighting == "column":
        if cat is None or "weight" not in cat.colnames:
            raise XstackError("weighting='column' needs a catalog with a weight column")
        w_t = np.asarray(cat["weight"], dtype=np.float64)
    pointings = [_Pointing(n, ds, primary_beam, pb_cutoff)
                 for n, ds in as_partitions(data, autocorrelations)]
    rng = np.random.default_rng(seed)

    inside_any = np.zeros(n_t, dtype=bool)
    for pt in pointings:
        inside_any |= pt.inside(ra_t, dec_t)
    if not inside_any.any():
        raise NoDataError("no target position lies inside a primary beam (above the cutoff)")

    # ---- position groups -------------------------------------------------------------
    groups_ra, groups_dec, groups_w, groups_s = [], [], [], []
    n_real = 0
    min_sep = None
    if method in ("mc", "random"):
        if min_separation_arcsec is None:
            qmax = _max_q_lambda(pointings)
            min_sep = 3.0 / qmax if qmax > 0 else 0.0
        else:
            min_sep = float(min_separation_arcsec) * ARCSEC
        av_ra, av_dec = [ra_t], [dec_t]
        if avoid is not None:
            a_ra, a_dec, _ = _positions_from(avoid)
            av_ra.append(a_ra)
            av_dec.append(a_dec)
        # where random positions go: the targets' footprint (default), the whole beam, a
        # polygon or a mask; always inside some pointing's disc (beam cutoff / field radius)
        reg = make_region(region, ra_t[inside_any], dec_t[inside_any], min_margin=min_sep)
        centers = np.array([pt.center for pt in pointings])
        radii = np.array([
            np.pi if (field_radius_arcsec is None and pt.beam.model == "none"
                      and reg.proposal is not None)  # no beam edge: the region alone
            else pt.radius(None if field_radius_arcsec is None else field_radius_arcsec * ARCSEC)
            for pt in pointings])
        uniq, idx = np.unique(np.round(centers, 12), axis=0, return_index=True)
        extra_region = reg.describe(centers[idx], radii[idx])
        n_fake = int(inside_any.sum())
        r_ra, r_dec = random_positions(n_fake, realizations, centers[idx], radii[idx],
                                       avoid_ra=np.concatenate(av_ra),
                                       avoid_dec=np.concatenate(av_dec), min_separation=min_sep,
                                       rng=rng, region=reg)
        s_fake = np.zeros(n_fake)
        if method == "mc":
            s_fake = _injected_fluxes(flux, cat, inside_any, n_fake)
            if s_fake is None:  # unit flux now, scaled by the measured target flux below
                s_fake = np.ones(n_fake)
        w_fake = w_t[inside_any]
        for r in range(realizations):
            perm = rng.permutation(n_fake)
            groups_ra.append(r_ra[r])
            groups_dec.append(r_dec[r])
            groups_w.append(w_fake[perm])
            groups_s.append(s_fake[perm])
        n_real = realizations
    # the real targets form the last group (measured flux; no injection)
    groups_ra.append(ra_t)
    groups_dec.append(dec_t)
    groups_w.append(w_t)
    groups_s.append(np.zeros(n_t))
    sizes = np.array([g.size for g in groups_ra])
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    all_ra, all_dec = np.concatenate(groups_ra), np.concatenate(groups_dec)
    all_w, all_s = np.concatenate(groups_w), np.concatenate(groups_s)
    G = sizes.size
    need_flux_for_mc = method == "mc" and flux is None and (cat is None or "flux" not in cat.colnames)

    # ---- uv-profile bins -------------------------------------------------------------
    nbins = int(profile_bins) if method in ("mc", "random") else 0
    edges = None
    if nbins > 0:
        edges = np.linspace(0.0, _max_q_lambda(pointings) * (1 + 1e-9), nbins + 1)

    # ---- one pass over every pointing ---------------------------------------------------
    num = np.zeros(G)            # sum of data terms, per group
    num_m = np.zeros(G)          # sum of injected-model terms, per group
    den = np.zeros(G)            # sum of weights of the pointings a group is inside
    expect = np.zeros(G)         # injected flux seen by a noiseless stack
    prof = np.zeros((G, max(nbins, 0)))
    prof_m = np.zeros((G, max(nbins, 0)))
    prof_w = np.zeros((G, max(nbins, 0)))
    X_t = np.zeros((len(pointings), n_t))          # per-target data term (1/A coefficients)
    inside_t = np.zeros((len(pointings), n_t), bool)
    var_t = np.zeros((len(pointings), n_t))       # sum_c W_c / A_kc^2 per pointing
    var_emp_t = np.zeros((len(pointings), n_t))   # the same with measured noise
    wk_t = np.zeros((len(pointings), n_t))        # w_k of the targets per pointing
    wtot_p = np.zeros(len(pointings))
    any_data = False
    engine_blocks = {"antenna": 0, "numba": 0}
    engine_info: dict[str, Any] = {}
    from xstack._progress import progress_iter

    for ip, pt in enumerate(pointings):
        A = pt.attenuation(all_ra, all_dec)                     # (nchan, K)
        inside = pt.inside(all_ra, all_dec)
        l, m, _, n1 = radec_to_lmn(all_ra, all_dec, *pt.center)
        wk = all_w.copy()
        if weighting == "pb":
            wk = np.asarray(pt.beam(angular_separation(all_ra, all_dec, *pt.center), pt.fmid)) ** 2
        wk = np.where(inside, wk, 0.0)
        gsum = np.add.reduceat(wk, starts[:-1]) if G else np.zeros(0)
        gsum = np.where(sizes > 0, gsum, 0.0)
        norm = np.repeat(np.where(gsum > 0, gsum, 1.0), sizes)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_a = np.where(inside[None, :] & (A > 0), 1.0 / A, 0.0)
        coef = inv_a * (wk / norm)[None, :]                  # (nchan, K)
        b = all_s[None, :] * A if method == "mc" else None
        tsl = slice(starts[-2], starts[-1])
        inside_t[ip] = inside[tsl]
        wchan = np.zeros(pt.freq.size)
        wvchan = np.zeros(pt.freq.size)
        wbin = np.zeros(max(nbins, 0))
        wk_t[ip] = wk[tsl]
        num_p, num_m_p = np.zeros(G), np.zeros(G)
        prof_p, prof_m_p = np.zeros_like(prof), np.zeros_like(prof)
        blocks = progress_iter(_blocks(pt, lo, hi, empirical=method == "analytic"),
                               f"noise {pt.name}", enabled=progress)
        for uvw, vis_w, wsum, wvar in blocks:
            if not np.any(wsum > 0):
                continue
            any_data = True
            wchan += wsum.sum(axis=0)
            if wvar is not None:
                wvchan += wvar.sum(axis=0)
            if method in ("analytic", "bootstrap"):
                X_t[ip] += kernels.position_sums(uvw, pt.freq, vis_w, wsum, l[tsl], m[tsl], n1[tsl],
                                                 inv_a[:, tsl])
                continue
            bins = None
            if nbins:
                q = (np.hypot(uvw[:, 0], uvw[:, 1])[:, None] * pt.freq[None, :] / SPEED_OF_LIGHT)
                bins = np.clip(np.searchsorted(edges, q, side="right") - 1, 0, nbins - 1)
                bins = np.where(wsum > 0, bins, -1)
                wbin += np.bincount(bins[bins >= 0], wsum[bins >= 0], nbins)
            d, mdl, pr, prm = _group_sums(pt, uvw, vis_w, wsum, l, m, n1, coef, b, starts,
                                          bins, nbins, engine, antenna_tol_rad, engine_blocks,
                                          engine_info)
            num_p += d
            num_m_p += mdl
            prof_p += pr
            prof_m_p += prm
        # pointings combine as in xstack.uvstack: each weighted by its sum of w_k
        wtot = float(wchan.sum())
        wtot_p[ip] = wtot
        num += gsum * num_p
        num_m += gsum * num_m_p
        den += gsum * wtot
        var_t[ip] = (wchan[:, None] * inv_a[:, tsl] ** 2).sum(axis=0)
        var_emp_t[ip] = (wvchan[:, None] * inv_a[:, tsl] ** 2).sum(axis=0)
        if b is not None:
            expect += gsum * np.add.reduceat((wchan[:, None] * coef * b).sum(axis=0),
                                             starts[:-1]) * (sizes > 0)
        if nbins:
            prof += gsum[:, None] * prof_p
            prof_m += gsum[:, None] * prof_m_p
            prof_w += gsum[:, None] * wbin[None, :]
    if not any_data:
        raise NoDataError(f"no visibilities left after the uv cuts (uvmin={uvmin}, uvmax={uvmax}) "
                          "or all data flagged")

    extra: dict[str, Any] = {"weighting": weighting, "uvmin": None if uvmin is None else str(uvmin),
                             "uvmax": None if uvmax is None else str(uvmax),
                             "n_pointings": len(pointings), "seed": int(seed)}
    if min_sep is not None:
        extra["min_separation_arcsec"] = float(min_sep / ARCSEC)
        extra["region"] = extra_region
    if method in ("mc", "random"):
        extra["engine"] = ("mixed" if all(engine_blocks.values()) else
                           "antenna" if engine_blocks["antenna"] else "numba")
        extra["engine_blocks"] = dict(engine_blocks)
        extra.update(engine_info)
    # ---- results -------------------------------------------------------------------------
    if method in ("analytic", "bootstrap"):
        target_flux = _combine_targets(X_t, inside_t, wtot_p, wk_t, np.ones(n_t))
        if method == "analytic":
            noise, extra_a = _analytic_noise(var_t, inside_t, wtot_p, wk_t)
            n_used = int(extra_a.pop("_n_used"))
            extra.update(extra_a)
            # the same estimator's noise with the variance measured from the visibilities
            # (not trusting WEIGHT as 1/sigma^2), as xstack.uvstack's flux_err_empirical_jy
            emp, _ = _analytic_noise(var_emp_t, inside_t, wtot_p, wk_t)
            extra["noise_empirical_jy"] = emp
            if np.isfinite(emp) and noise > 0 and abs(emp / noise - 1.0) > EMPIRICAL_TOLERANCE:
                warnings.warn(
                    f"analytic noise from WEIGHT ({noise:.3g} Jy) and from the visibilities' "
                    f"own scatter ({emp:.3g} Jy) differ by a factor {emp / noise:.3g}: the "
                    "weights are not 1/sigma^2 of the data; trust noise_empirical_jy (or a "
                    "random/mc estimate)", stacklevel=2)
            return NoiseResult(method="analytic", noise_jy=noise, bias_jy=None, realizations=0,
                               target_flux_jy=target_flux, n_positions=n_used, extra=extra)
        # resample the targets that enter the stack (inside some pointing), as many as there
        # are: the same positions, and the same count, as every other method and uvstack use
        idx_in = np.flatnonzero(inside_any)
        n_in = idx_in.size
        counts = np.stack([np.bincount(idx_in[rng.integers(0, n_in, n_in)], minlength=n_t)
                           for _ in range(realizations)])
        vals = np.array([_combine_targets(X_t, inside_t, wtot_p, wk_t, c) for c in counts])
        return NoiseResult(method="bootstrap", noise_jy=float(np.std(vals, ddof=1)),
                           bias_jy=float(np.mean(vals) - target_flux), realizations=realizations,
                           values=vals, target_flux_jy=target_flux, n_positions=n_in,
                           extra=extra)

    dens = np.where(den > 0, den, np.nan)
    target_flux = float(num[-1] / dens[-1])
    scale = 1.0
    if need_flux_for_mc:
        # fluxes were injected at 1 Jy; everything injected is linear in the flux
        scale = max(target_flux, 0.0)
        extra["injected_flux_jy"] = scale
    flux_vals = (num + scale * num_m) / dens
    expect = expect * scale
    prof = prof + scale * prof_m
    vals = flux_vals[:n_real]
    profile = None
    if nbins:
        with np.errstate(invalid="ignore", divide="ignore"):
            pv = prof / prof_w
        profile = {"q_klambda": (0.5 * (edges[1:] + edges[:-1]) / 1e3).tolist(),
                   "edges_klambda": (edges / 1e3).tolist(),
                   "values": pv[:n_real], "target": pv[-1], "weight": prof_w[0]}
    pos = np.degrees(np.stack([np.stack(groups_ra[:n_real]), np.stack(groups_dec[:n_real])], -1))
    if method == "random":
        return NoiseResult(method="random", noise_jy=float(np.std(vals, ddof=1)),
                           bias_jy=float(np.mean(vals)), realizations=n_real, values=vals,
                           target_flux_jy=target_flux, n_positions=int(sizes[0]),
                           profile=profile, extra=extra, positions_deg=pos)
    injected = expect[:n_real] / np.where(den[:n_real] > 0, den[:n_real], np.nan)
    if need_flux_for_mc:
        extra["injected_flux_from"] = "stacked target flux"
    if profile is not None:
        profile["injected"] = injected
    return NoiseResult(method="mc", noise_jy=float(np.std(vals, ddof=1)),
                       bias_jy=float(np.mean(vals - injected)), realizations=n_real,
                       values=vals, injected=injected, target_flux_jy=target_flux,
                       n_positions=int(sizes[0]), profile=profile, extra=extra, positions_deg=pos,
                       injected_flux_jy=scale * np.stack(groups_s[:n_real]))


def _analytic_noise(var: np.ndarray, inside: np.ndarray, wtot: np.ndarray, w: np.ndarray
                    ) -> tuple[float, dict[str, Any]]:
    """Noise of the estimator actually used, and that of optimal weights (eq. 6).

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
             "sigma_k_median_jy": float(np.median(np.sqrt(sig2[ok]))),
             "_n_used": int(ok.sum())}
    return noise, extra


def _group_sums(pt: _Pointing, uvw, vis_w, wsum, l, m, n1, coef, b, starts, bins, nbins,
                engine: str, tol_rad: float, blocks: dict[str, int], info: dict[str, Any]):
    """Group sums of one block by the antenna path when valid (or forced), else per row."""
    if engine != "numba":
        try:
            if pt.antennas is None:
                raise kernels.FactorisationError("no baseline antenna ids in the data")
            layout = kernels.antenna_layout(uvw, *pt.antennas, row_ok=np.any(wsum > 0, axis=1))
            if engine == "auto" and layout.rows_per_antenna < MIN_ROWS_PER_ANTENNA:
                raise kernels.FactorisationError(
                    f"{layout.rows_per_antenna:.2f} baselines per antenna: no gain")
            err = layout.phase_error(l, m, n1, pt.freq)
            out = kernels.group_sums_antenna(layout, pt.freq, vis_w, wsum, l, m, n1, coef, b,
                                             starts, bins=bins, nbins=nbins, tol_rad=tol_rad)
        except kernels.FactorisationError as exc:
            if engine == "antenna":
                raise XstackError(f"engine='antenna' is not valid for {pt.name}: {exc}") from exc
            info.setdefault("engine_fallback", f"{pt.name}: {exc}")
        else:
            blocks["antenna"] += 1
            info["antenna_phase_error_rad"] = max(info.get("antenna_phase_error_rad", 0.0), err)
            return out
    blocks["numba"] += 1
    return kernels.group_sums(uvw, pt.freq, vis_w, wsum, l, m, n1, coef, b, starts, bins=bins,
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
