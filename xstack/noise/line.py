"""Noise and bias of a uv line stack, per velocity bin: :func:`estimate_line_noise`.

Three empirical methods, each a set of R line stacks (:func:`xstack.uvstack.line.stack_lines`,
its public signature only) whose scatter per velocity bin is the noise:

``random``
    the targets moved to random positions (drawn as the continuum ``random`` method draws
    them: :func:`xstack.noise.estimate._random_groups`, inside the pointings and the region,
    away from the targets, the avoided sources and each other), each keeping a redshift
    drawn from the targets' own (permuted, or resampled with replacement), with its weight
    columns;
``mc``
    the same random targets, with Gaussian lines (integrated flux, FWHM) added to the
    visibilities at those positions and redshifts (the simulator's channel-averaged
    profile :func:`xstack.sim.kernels.line_channel_flux` times the primary beam, through
    :func:`xstack.sim.kernels.model_visibilities`, lazily per chunk), then stacked;
    the injected spectrum is the stack of the lines alone (same positions, weights and
    flags: stacking is linear), so ``bias = mean(recovered - injected)`` measures what the
    data add at random positions;
``bootstrap``
    the targets resampled with replacement.

Each realisation is one pass over the data (one ``stack_lines`` call; mc two: data plus
lines, and lines alone) -- the continuum's one pass for all realisations needs a multi-group
line kernel that ``stack_lines`` does not expose yet (see ``docs/linestack.md``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from xstack import _vocabulary
from xstack._inputs import Positions
from xstack._json import finite_or_none
from xstack._result import Result, json_ready
from xstack.beams import DEFAULT_PB_CUTOFF
from xstack.errors import OptionError

__all__ = ["LineNoiseResult", "estimate_line_noise"]

#: the line-noise methods (the continuum's analytic noise is the stack's own flux_err_jy)
LINE_NOISE_METHODS = ("random", "mc", "bootstrap")
#: how random targets get their redshifts from the targets'
REDSHIFT_DRAWS = _vocabulary.REDSHIFT_DRAWS


@dataclass(kw_only=True)
class LineNoiseResult(Result):
    """Noise and bias of a line stack per velocity bin (:func:`estimate_line_noise`).

    Attributes
    ----------
    method : random | mc | bootstrap
    velocity_kms, velocity_edges_kms : bin centres (nbin) and edges (nbin + 1), km/s
    noise_jy : (nbin,) standard deviation over the realisations (ddof=1; NaN where fewer
        than 2 realisations cover the bin), Jy
    bias_jy : (nbin,) random: mean of the realisations; mc: mean(recovered - injected);
        bootstrap: mean(realisations) - target stack; Jy
    realizations : R
    values : (R, nbin) the realisations' stacked spectra, Jy (NaN: bin not covered)
    injected : (R, nbin) mc: the stack of the injected lines alone, Jy; else None
    covariance_jy2 : (nbin, nbin) empirical covariance of the bins over the realisations
        (pairwise over the realisations covering both bins), Jy^2
    target_flux_jy, target_flux_err_jy : (nbin,) the stack at the real targets and its
        error from the weights (``LineStackResult.flux_err_jy``), Jy
    n_positions : targets per realisation (those inside some pointing)
    positions_deg : (R, n, 2) ra, dec of the random targets (mc, random), degrees
    redshift_index : (R, n) catalog row whose redshift (and weight columns) each random
        target took (mc, random) or the resampled rows (bootstrap)
    extra : JSON-ready details (region, separation, injected line, passes)
    options : the options used
    """

    method: str
    velocity_kms: np.ndarray
    velocity_edges_kms: np.ndarray
    noise_jy: np.ndarray
    bias_jy: np.ndarray
    realizations: int
    values: np.ndarray
    injected: np.ndarray | None = None
    covariance_jy2: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    target_flux_jy: np.ndarray | None = None
    target_flux_err_jy: np.ndarray | None = None
    n_positions: int = 0
    positions_deg: np.ndarray | None = None
    redshift_index: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)

    def to_dict(self, include_values: bool = True) -> dict[str, Any]:
        """JSON-ready dictionary: per bin ``velocity_kms``, ``noise_jy``, ``bias_jy``;
        ``realizations``; with ``include_values`` the spectra and the covariance."""
        out: dict[str, Any] = {
            "method": self.method, "domain": "uv", "line": True,
            "velocity_kms": self.velocity_kms,
            "velocity_edges_kms": self.velocity_edges_kms,
            "noise_jy": self.noise_jy, "bias_jy": self.bias_jy,
            "realizations": int(self.realizations), "n_positions": int(self.n_positions),
            "target_flux_jy": self.target_flux_jy, "target_flux_err_jy": self.target_flux_err_jy}
        if include_values:
            out["values_jy"] = self.values
            if self.injected is not None:
                out["injected_jy"] = self.injected
            out["covariance_jy2"] = self.covariance_jy2
        for k, v in self.extra.items():
            out[k] = finite_or_none(v) if isinstance(v, (float, np.floating)) else v
        if self.options:
            out["options"] = self.options
        return json_ready(out)

    def table(self):
        """Per bin: velocity, noise, bias, target flux and its analytic error (astropy Table)."""
        from astropy.table import Table

        t = Table()
        t["velocity_kms"] = self.velocity_kms
        t["velocity_lo_kms"] = self.velocity_edges_kms[:-1]
        t["velocity_hi_kms"] = self.velocity_edges_kms[1:]
        t["noise_jy"] = self.noise_jy
        t["bias_jy"] = self.bias_jy
        t["n_realizations"] = np.sum(np.isfinite(self.values), axis=0)
        if self.target_flux_jy is not None:
            t["target_flux_jy"] = self.target_flux_jy
            t["target_flux_err_jy"] = self.target_flux_err_jy
        for name in t.colnames:
            t[name].unit = ("km / s" if name.startswith("velocity") else
                            None if name == "n_realizations" else "Jy")
        return t


# ----------------------------------------------------------------------------- helpers

def _nan_cov(values: np.ndarray) -> np.ndarray:
    """Covariance of the columns of ``values`` (R, nbin), pairwise over finite rows."""
    ok = np.isfinite(values)
    x = np.where(ok, values, 0.0)
    nb = values.shape[1]
    cov = np.full((nb, nb), np.nan)
    for i in range(nb):
        for j in range(i, nb):
            both = ok[:, i] & ok[:, j]
            n = int(both.sum())
            if n >= 2:
                a, b = x[both, i], x[both, j]
                cov[i, j] = cov[j, i] = float(np.sum((a - a.mean()) * (b - b.mean())) / (n - 1))
    return cov


def _nan_stats(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column: std (ddof=1) and mean over the finite rows (NaN with < 2 / 0 rows)."""
    ok = np.isfinite(values)
    n = ok.sum(axis=0)
    x = np.where(ok, values, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(n > 0, x.sum(axis=0) / n, np.nan)
        var = np.where(n >= 2, (np.where(ok, values - mean, 0.0) ** 2).sum(axis=0) / (n - 1),
                       np.nan)
    return np.sqrt(var), mean


def _line_params(table: Any, rows: np.ndarray, value: Any, column: str, name: str,
                 unit: str) -> np.ndarray:
    """Per injected line: ``value`` (number or one per target), else the catalog column."""
    n = rows.size
    if value is None:
        if table is None or column not in table.colnames:
            raise OptionError(f"method='mc' needs {name} (or a catalog column {column!r})",
                              option=name)
        col = table[column]
        arr = np.asarray(col.to_value(unit) if getattr(col, "unit", None) is not None else col,
                         dtype=np.float64)[rows]
    else:
        arr = np.atleast_1d(np.asarray(value, dtype=np.float64))
        if arr.size == 1:
            arr = np.full(n, float(arr[0]))
        elif table is not None and arr.size == len(table):
            arr = arr[rows]
        else:
            raise OptionError(f"{name}: give one value or one per target, got {arr.size}",
                              option=name)
    if not np.all(np.isfinite(arr)) or np.any(arr <= 0 if name == "line_fwhm_kms" else arr < 0):
        raise OptionError(f"{name} must be finite and {'> 0' if name == 'line_fwhm_kms' else '>= 0'}",
                          option=name)
    return arr


def _inject_block(vis, uvw, ratio, *, freq, width, l, m, nm1, centre, flux, fwhm, att, pidx,
                  only_model):
    """vis (+) the lines' visibilities in one chunk (time, baseline, channel, pol)."""
    from xstack.sim.kernels import line_channel_flux, line_half_width_kms, model_visibilities
    from xstack.spectral import SPEED_OF_LIGHT_KMS

    nt, nb, nc, _ = vis.shape
    out = np.zeros(vis.shape, dtype=vis.dtype) if only_model else np.array(vis, copy=True)
    if l.size == 0:
        return out
    lo, hi = freq - width / 2, freq + width / 2
    r = np.asarray(ratio, dtype=np.float64)
    # one model evaluation per distinct frame ratio (one for data already in the frame)
    for rv in np.unique(r):
        ts = np.flatnonzero(r == rv)
        amp = line_channel_flux(rv * lo, rv * hi, centre, flux, fwhm) * att  # (nsrc, nchan)
        # each line on the channels it reaches (beyond 9 sigma: < 1e-17 of its flux, as the
        # simulator): a line spans a fraction of the band, so this is most of the saving
        v = SPEED_OF_LIGHT_KMS * (1.0 - rv * freq[None, :] / centre[:, None])
        reach = (np.abs(v) <= line_half_width_kms(fwhm)[:, None]
                 + rv * np.abs(width)[None, :] * SPEED_OF_LIGHT_KMS / centre[:, None])
        rows = np.asarray(uvw[ts], dtype=np.float64).reshape(-1, 3)
        for k in np.flatnonzero(reach.any(axis=1) & np.any(amp != 0, axis=1)):
            c = np.flatnonzero(reach[k])
            c0, c1 = int(c[0]), int(c[-1]) + 1
            mv = model_visibilities(rows, freq[c0:c1], l[k:k + 1], m[k:k + 1], nm1[k:k + 1],
                                    np.ones(1), amp[k:k + 1, c0:c1], parallel=False)
            mv = mv.reshape(ts.size, nb, c1 - c0).astype(out.dtype)
            for p in pidx:
                out[ts, :, c0:c1, p] += mv
    return out


def _with_lines(pt: Any, ra: np.ndarray, dec: np.ndarray, centre: np.ndarray,
                flux: np.ndarray, fwhm: np.ndarray, frame: str, only_model: bool) -> Any:
    """Partition ``pt.ds`` with the lines' visibilities added (or alone), lazily per chunk."""
    import dask.array as da

    from xstack.coords import radec_to_lmn
    from xstack.fit._data import parallel_hand_index, time_blocks
    from xstack.frames import frame_ratio, frequency_frame

    ds = pt.ds
    inside = pt.inside(ra, dec)
    att = pt.attenuation(ra, dec).T[inside]                                # (nsrc, nchan)
    l, m, _n, nm1 = radec_to_lmn(ra[inside], dec[inside], *pt.center)
    times = np.asarray(ds["time"].values, dtype=np.float64)
    ratio = np.ones(times.size)
    if frequency_frame(ds) == "TOPO" and frame.upper() != "TOPO":
        location = np.asarray(ds["ANTENNA_POSITION"].values, dtype=np.float64).mean(axis=0)
        ratio = frame_ratio(times, np.degrees(pt.center[0]), np.degrees(pt.center[1]),
                            location, to_frame=frame.upper(), from_frame="TOPO")
    vis = ds["VISIBILITY"].data
    tchunks = vis.chunks[0] if isinstance(vis, da.Array) else tuple(
        s.stop - s.start for s in time_blocks(ds))
    want = (tchunks, (vis.shape[1],), (vis.shape[2],), (vis.shape[3],))
    vis = da.from_array(vis, chunks=want) if not isinstance(vis, da.Array) else vis.rechunk(want)
    uvw = ds["UVW"].data
    uvw = (da.from_array(uvw, chunks=want[:2] + ((3,),)) if not isinstance(uvw, da.Array)
           else uvw.rechunk(want[:2] + ((3,),)))
    ratio_d = da.from_array(ratio, chunks=(tchunks,))
    new = da.blockwise(
        _inject_block, "tbcp", vis, "tbcp", uvw, "tbx", ratio_d, "t", dtype=vis.dtype,
        concatenate=True, freq=pt.freq,
        width=np.abs(np.asarray(ds["channel_width"].values, dtype=np.float64)),
        l=l, m=m, nm1=nm1, centre=centre[inside], flux=flux[inside], fwhm=fwhm[inside],
        att=att, pidx=parallel_hand_index(ds, pt.name), only_model=only_model)
    return ds.assign(VISIBILITY=(ds["VISIBILITY"].dims, new, ds["VISIBILITY"].attrs))


# ----------------------------------------------------------------------------- API

def estimate_line_noise(data: Any, positions: Any, *, line_frequency: Any,
                        method: str = "random", realizations: int = 50, seed: int = 0,
                        redshifts: str = "permute", line_flux_jy_kms: Any = None,
                        line_fwhm_kms: Any = None, min_separation_arcsec: float | None = None,
                        avoid: Any = None, region: Any = "hull",
                        field_radius_arcsec: float | None = None,
                        velocity_resolution: float = 20.0, velocity_range: Any = (-600, 600),
                        frame: str = "lsrk", weighting: str = "pb", primary_beam: Any = "auto",
                        pb_cutoff: float = DEFAULT_PB_CUTOFF, uvmin: Any = None,
                        uvmax: Any = None, polarizations: Any = "parallel",
                        progress: bool = False) -> LineNoiseResult:
    """Noise and bias of the uv line stack of ``positions``, per velocity bin.

    Parameters
    ----------
    data
        The (residual) visibilities: any input of :func:`xstack.uvstack.line.stack_lines`.
    positions
        The targets: catalog with ``ra``, ``dec`` (deg) and ``z`` or ``freq`` (observed
        line centre), optional ``weight``/``sigma`` and, for ``mc``, ``line_flux_jy_kms``
        and ``line_fwhm_kms``.
    line_frequency
        The line's rest frequency (name, frequency with units, or Hz).
    method
        ``random`` (targets at random positions with redshifts drawn from theirs),
        ``mc`` (Gaussian lines injected into the visibilities at random positions and
        redshifts, then recovered) or ``bootstrap`` (targets resampled with replacement).
    realizations
        R >= 2 line stacks.
    seed
        Seed of the random generator (positions, redshifts, resampling).
    redshifts
        ``permute`` (default: each random target takes the redshift, and the weight columns,
        of a different target: the same redshift distribution exactly) or ``resample``
        (drawn with replacement from the targets').
    line_flux_jy_kms, line_fwhm_kms
        mc: integrated flux (Jy km/s) and FWHM (km/s) of the injected Gaussian lines, one
        value or one per catalog row; default the catalog's ``line_flux_jy_kms`` /
        ``line_fwhm_kms`` columns (the simulator's catalogs have them).
    min_separation_arcsec, avoid, region, field_radius_arcsec
        Where random targets go, as for :func:`xstack.estimate_noise` (default separation:
        3 synthesized beams; region: the targets' footprint).
    velocity_resolution, velocity_range, frame, weighting, primary_beam, pb_cutoff, uvmin, \
    uvmax, polarizations
        The line stack's options (:func:`xstack.uvstack.line.stack_lines`). The injected
        lines are attenuated by the telescope's standard beam (or the named ``airy`` /
        ``gaussian`` model), the one the stack divides by with ``primary_beam="auto"``.
    progress
        Progress bars on stderr.

    Returns
    -------
    LineNoiseResult

    Raises
    ------
    OptionError
        Unknown method or redshift draw, fewer than 2 realisations, mc without line
        parameters, or any bad option of the line stack (before the data are read).
    XstackError
        As :func:`xstack.uvstack.line.stack_lines` and :func:`xstack.estimate_noise`
        (no target in a pointing, a catalog too dense for random positions).
    """
    from xstack._options import choice
    from xstack.noise import estimate as est
    from xstack.spectral import line_centres_hz, rest_frequency, velocity_edges
    from xstack.uvstack.line import stack_lines

    choice("method", method, LINE_NOISE_METHODS, what="line noise method")
    choice("redshifts", redshifts, REDSHIFT_DRAWS)
    realizations = est._number("realizations", realizations, int)
    if realizations < 2:
        raise OptionError(f"need at least 2 realisations to estimate a scatter, got "
                          f"{realizations}", option="realizations")
    seed = est._number("seed", seed, int)
    rest_hz = rest_frequency(line_frequency)
    velocity_edges(velocity_resolution, velocity_range)  # checked before any data are read
    stack_kw = dict(line_frequency=rest_hz, velocity_resolution=velocity_resolution,
                    velocity_range=velocity_range, frame=frame, weighting=weighting,
                    primary_beam=primary_beam, pb_cutoff=pb_cutoff, uvmin=uvmin, uvmax=uvmax,
                    polarizations=polarizations, progress=progress)
    # the continuum noise stage's inputs and random draws: the same pointings, inside rule,
    # separation and region (its weighting is irrelevant here: the line stack weights)
    beam = primary_beam if isinstance(primary_beam, str) and primary_beam in (
        "auto", "airy", "gaussian", "none") else None
    nopt = est.NoiseOptions(method="random", realizations=realizations, seed=seed,
                            min_separation_arcsec=min_separation_arcsec, avoid=avoid,
                            weighting="none", primary_beam=beam, pb_cutoff=pb_cutoff,
                            uvmin=uvmin, uvmax=uvmax, field_radius_arcsec=field_radius_arcsec,
                            region=region)
    inputs = est._load(data, positions, nopt)
    table = Positions.from_any(positions).as_table()
    line_centres_hz(table, rest_hz)  # bad z / freq rows named before any pass
    rows_in = np.flatnonzero(inputs.inside_any)
    if method == "mc":  # checked before any pass over the data
        flux = _line_params(table, rows_in, line_flux_jy_kms, "line_flux_jy_kms",
                            "line_flux_jy_kms", "Jy km / s")
        fwhm = _line_params(table, rows_in, line_fwhm_kms, "line_fwhm_kms",
                            "line_fwhm_kms", "km / s")
    parts = {pt.name: pt.ds for pt in inputs.pointings}
    rng = np.random.default_rng(seed)

    target = stack_lines(parts, table, **stack_kw)
    nbin = target.velocity_kms.size
    values = np.full((realizations, nbin), np.nan)
    injected = None
    extra: dict[str, Any] = {"passes": 0}
    pos_deg = idx_all = None

    if method in ("random", "mc"):
        groups: tuple[list, list, list, list] = ([], [], [], [])
        min_sep, region_desc = est._random_groups(inputs, nopt, rng, groups)
        extra["min_separation_arcsec"] = float(min_sep / est.ARCSEC)
        extra["region"] = region_desc
        n = rows_in.size
        idx_all = np.stack([rows_in[rng.permutation(n)] if redshifts == "permute"
                            else rows_in[rng.integers(0, n, n)] for _ in range(realizations)])
        pos_deg = np.degrees(np.stack([np.stack(groups[0]), np.stack(groups[1])], -1))
        if method == "mc":
            # a line goes with its target's redshift (the permuted row), as in the catalog
            where = {int(r): i for i, r in enumerate(rows_in)}
            injected = np.full((realizations, nbin), np.nan)
            extra["injected_line"] = {"profile": "gaussian",
                                      "flux_jy_kms_median": float(np.median(flux)),
                                      "fwhm_kms_median": float(np.median(fwhm))}
        centres = line_centres_hz(table, rest_hz)
        for r in range(realizations):
            fake = table[idx_all[r]]
            fake["ra"] = pos_deg[r, :, 0]
            fake["dec"] = pos_deg[r, :, 1]
            if method == "random":
                values[r] = stack_lines(parts, fake, **stack_kw).flux_jy
                continue
            sel = np.array([where[int(i)] for i in idx_all[r]])
            ra, dec = np.radians(pos_deg[r, :, 0]), np.radians(pos_deg[r, :, 1])
            args = (ra, dec, centres[idx_all[r]], flux[sel], fwhm[sel], str(frame))
            with_lines = {pt.name: _with_lines(pt, *args, only_model=False)
                          for pt in inputs.pointings}
            lines_only = {pt.name: _with_lines(pt, *args, only_model=True)
                          for pt in inputs.pointings}
            values[r] = stack_lines(with_lines, fake, **stack_kw).flux_jy
            injected[r] = stack_lines(lines_only, fake, **stack_kw).flux_jy
        extra["passes"] = 1 + realizations * (2 if method == "mc" else 1)
    else:  # bootstrap
        n = rows_in.size
        idx_all = np.stack([rows_in[rng.integers(0, n, n)] for _ in range(realizations)])
        for r in range(realizations):
            values[r] = stack_lines(parts, table[idx_all[r]], **stack_kw).flux_jy
        extra["passes"] = 1 + realizations

    noise, mean = _nan_stats(values)
    if method == "mc":
        _, bias = _nan_stats(values - injected)
    elif method == "bootstrap":
        bias = mean - target.flux_jy
    else:
        bias = mean
    used = {"method": method, "realizations": realizations, "seed": seed,
            "redshifts": redshifts, "line_frequency_hz": float(rest_hz),
            "line_flux_jy_kms": _describe(line_flux_jy_kms),
            "line_fwhm_kms": _describe(line_fwhm_kms),
            "min_separation_arcsec": extra.get("min_separation_arcsec", min_separation_arcsec),
            "avoid": None if avoid is None else str(avoid) if isinstance(avoid, (str, os.PathLike))
            else "positions", "region": str(region) if region is not None else None,
            "field_radius_arcsec": field_radius_arcsec, "stack": target.options}
    return LineNoiseResult(
        method=method, velocity_kms=target.velocity_kms,
        velocity_edges_kms=target.velocity_edges_kms, noise_jy=noise, bias_jy=bias,
        realizations=realizations, values=values, injected=injected,
        covariance_jy2=_nan_cov(values), target_flux_jy=target.flux_jy,
        target_flux_err_jy=target.flux_err_jy, n_positions=int(rows_in.size),
        positions_deg=pos_deg, redshift_index=idx_all, extra=extra, options=json_ready(used))


def _describe(value: Any) -> Any:
    if value is None or isinstance(value, (int, float)):
        return value
    arr = np.asarray(value, dtype=np.float64)
    return float(arr) if arr.ndim == 0 else f"{arr.size} values"



def plot_line_noise(result: LineNoiseResult, path: str | os.PathLike, *,
                    overwrite: bool = False, unit: str = "mJy") -> Any:
    """PNG of the noise per velocity bin: the realisations' scatter (steps), the target
    stack's error from the weights (dashed) and the bias (dotted)."""
    from xstack._atomic import atomic_output
    from xstack.noise.plot import _figure

    scale = {"Jy": 1.0, "mJy": 1e3, "uJy": 1e6}[unit]
    label = unit.replace("uJy", "µJy")
    plt = _figure()
    fig, ax = plt.subplots(figsize=(6.0, 4.0))
    e = result.velocity_edges_kms
    step = dict(where="post")
    ax.step(e, np.append(result.noise_jy, result.noise_jy[-1:]) * scale, color="k",
            label=f"noise ({result.method}, {result.realizations} realisations)", **step)
    if result.target_flux_err_jy is not None:
        ax.step(e, np.append(result.target_flux_err_jy, result.target_flux_err_jy[-1:]) * scale,
                color="C0", ls="--", label="stack error from the weights", **step)
    ax.step(e, np.append(result.bias_jy, result.bias_jy[-1:]) * scale, color="C3", ls=":",
            label="bias", **step)
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.set_xlabel("velocity [km/s]")
    ax.set_ylabel(f"flux density [{label}]")
    ax.set_title("line stack noise per velocity bin")
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_output(path, overwrite=overwrite) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    from pathlib import Path

    return Path(path)
