"""uv-domain spectral-line stacking: every visibility phase-rotated to each target (paper eq. 4)
and assigned, by overlap, to the velocity bins about the target's own line centre.

``stack_lines(data, positions, line_frequency=..., ...)`` plans like the continuum stack
(:func:`xstack.uvstack.stack.stack_uv`: the catalog, which positions enter which partition,
position weights W_k, primary beams per channel, uv range, polarizations, flags, weights: the
same functions) and runs one lazy pass over the data's time x baseline chunks with the kernel
of :mod:`xstack.uvstack.line_kernels`. Per bin j::

    S_j = sum_k W_k sum w o_kij Re(V e^{-i phi_k}) / A_k(nu_i) / sum_k W_k sum w o_kij

with o_kij the length (km/s) of channel i's velocity interval about target k's observed line
centre inside bin j; neighbouring bins share channels, so the result carries the full
covariance of the S_j. Data in TOPO are converted per integration to the frame asked for
(:func:`xstack.frames.frame_ratio` at the pointing centre); data already in that frame are
used as they are.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from typing import Any

import dask
import dask.array as da
import numpy as np
import xarray as xr
from astropy.table import Table

from xstack._lazy import LazyResult
from xstack._result import Result, json_ready
from xstack._select import uv_range_mask
from xstack.beams import DEFAULT_PB_CUTOFF
from xstack.errors import NoDataError, OptionError, XstackWarning
from xstack.spectral import (
    SPEED_OF_LIGHT_KMS,
    line_centres_hz,
    rest_frequency,
    velocity_edges,
)
from xstack.uvstack import line_kernels
from xstack.uvstack.stack import UvstackOptions, _as_dask, _load, _optimised_now, _plan

#: Frames a line stack can be made in (xstack._vocabulary.LINE_FRAMES).
try:
    from xstack._vocabulary import LINE_FRAMES
except ImportError:  # pragma: no cover - before the vocabulary has them
    LINE_FRAMES = ("lsrk", "bary")

# columns of a target's row in the per-partition parameter array (then W_k / A_k per channel)
_L, _M, _N1, _CENTRE, _WK, _NPAR = 0, 1, 2, 3, 4, 5


@dataclass(kw_only=True)
class LineStackResult(Result):
    """The result of :func:`stack_lines`.

    Attributes
    ----------
    velocity_edges_kms, velocity_kms
        The bins' edges (nbin + 1) and centres (nbin), km/s, v = c (nu_c - nu) / nu_c about
        each target's observed line centre.
    flux_jy, flux_err_jy
        Per bin the stacked point-source flux density (Jy) and its 1-sigma error from the
        weights; NaN in bins no target covers.
    flux_cov_jy2
        (nbin, nbin) covariance of ``flux_jy`` (Jy^2): neighbouring bins share channels.
    n_targets_per_bin
        Targets with at least one usable visibility in the bin.
    n_positions
        Targets that entered some pointing with weight > 0 and cover some bin.
    n_visibilities
        Visibilities (unflagged, selected correlations, uv range, weight > 0) that entered
        some bin.
    positions
        The catalog with ``used``, ``weight_used``, ``attenuation`` (per partition, as
        :class:`~xstack.uvstack.stack.StackResult`), ``n_pointings``, ``line_centre_hz`` and
        ``n_bins`` (bins the target covers).
    rest_frequency_hz, frame
        The line's rest frequency; the frame of the velocities (``lsrk`` or ``bary``).
    options
        The options used (JSON-ready).
    out
        The stacked store written, or None.
    """

    velocity_edges_kms: np.ndarray
    velocity_kms: np.ndarray
    flux_jy: np.ndarray
    flux_err_jy: np.ndarray
    flux_cov_jy2: np.ndarray
    n_targets_per_bin: np.ndarray
    n_positions: int
    n_visibilities: int
    positions: Table
    rest_frequency_hz: float
    frame: str
    options: dict[str, Any] = field(default_factory=dict)
    out: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: the spectrum (bin centres, edges, flux, error, targets per
        bin), n_positions, n_visibilities, rest frequency, frame, options (NaN as None)."""
        return json_ready({
            "velocity_kms": self.velocity_kms, "velocity_edges_kms": self.velocity_edges_kms,
            "flux_jy": self.flux_jy, "flux_err_jy": self.flux_err_jy,
            "n_targets_per_bin": self.n_targets_per_bin, "n_positions": self.n_positions,
            "n_visibilities": self.n_visibilities, "rest_frequency_hz": self.rest_frequency_hz,
            "frame": self.frame, "options": self.options, "out": self.out})

    def table(self) -> Table:
        """One row per catalog position (see ``positions``)."""
        return Table(self.positions, copy=True)


# --- per partition ---------------------------------------------------------------------------

def _frame_ratios(ds: xr.Dataset, frame: str) -> np.ndarray:
    """Per time of ``ds``, nu_frame / nu_data (1 when the data are in ``frame`` already;
    :func:`xstack.frames.partition_frame_ratios`: TOPO converted towards the pointing centre,
    whose correction serves every target of it to < 1e-6 of nu for a 0.5 degree field)."""
    from xstack.frames import partition_frame_ratios

    return partition_frame_ratios(ds, frame)


def _block_line(vis, weight, flag, uvw, ratio_t, params, *, layout, frequency, edges, pol_mask,
                lo, hi, write):
    """One chunk's sums (1, 1, nsum) and, with ``write``, its stacked visibilities.

    sums: [N (nbin), D (nbin), C (nbin^2), count, coverage (ntarget * nbin)].
    """
    nt, nb, nc, npol = vis.shape
    n = nt * nb
    v, w, f = vis.reshape(n, nc, npol), weight.reshape(n, nc, npol), flag.reshape(n, nc, npol)
    x = uvw.reshape(n, 3)
    ratio = np.repeat(np.asarray(ratio_t, dtype=np.float64), nb)
    uv_mask = uv_range_mask(x, frequency, lo, hi)
    tg = (params[:, _L], params[:, _M], params[:, _N1], params[:, _CENTRE])
    out = line_kernels.line_sums(v, w, f, x, ratio, layout, *tg, params[:, _NPAR:],
                                 params[:, _WK], edges, pol_mask, uv_mask, write=write)
    sums, stacked = out if write else (out, None)
    # which bins each target covers with some usable visibility (the flux's selection)
    pm = np.asarray(pol_mask, dtype=bool)
    good = ~f[:, :, pm] & (w[:, :, pm] > 0) & np.isfinite(v[:, :, pm])
    if uv_mask is not None:
        good &= uv_mask[:, :, None]
    usable = good.any(axis=2).reshape(nt, nb, nc).any(axis=1)
    cover = line_kernels.line_coverage(usable, ratio_t, layout, params[:, _CENTRE], edges)
    total = np.concatenate([sums, cover.ravel()])[None, None, :]
    if not write:
        return total
    num, den, var = stacked
    nbin = edges.size - 1
    with np.errstate(divide="ignore", invalid="ignore"):
        sv = np.where(den > 0, num / den, np.nan).astype(vis.dtype)
        sw = np.where(var > 0, den**2 / var, 0.0).astype(np.float32)
    shape = (nt, nb, nbin, npol)
    return sv.reshape(shape), sw.reshape(shape), ~(den > 0).reshape(shape), total


def _get(pair, i):
    return pair[i]


@dataclass
class _Partition:
    """One active partition of the line stack: its lazy sums and (with out) stacked data."""

    name: str
    index: np.ndarray  # catalog rows of its targets
    sums: Any
    stacked: xr.Dataset | None


def _partition_graph(p, centres, edges, frame, options, rest_hz, write) -> _Partition:
    ds = _as_dask(p.ds)
    freq = np.asarray(ds["frequency"].values, dtype=np.float64)
    width = np.asarray(ds["channel_width"].values, dtype=np.float64)
    layout = line_kernels.ChannelLayout(freq, width)
    sel = p.used & (p.weight > 0)
    idx = np.flatnonzero(sel)
    # the continuum plan's coefficients W_k / (A_k(nu) L_k(nu) sum W): times sum W
    coef = p.params[:, 3:] * p.sum_weight
    params = np.column_stack([p.params[:, 0], p.params[:, 1], p.params[:, 2], centres[idx],
                              p.weight[idx], coef])
    ratio = _frame_ratios(ds, frame)
    vis = ds["VISIBILITY"].data
    ratio_d = da.from_array(ratio, chunks=(vis.chunks[0],), name=False)
    params_d = da.from_array(params, chunks=params.shape, name=False)
    nbin = edges.size - 1
    nsum = 2 * nbin + nbin * nbin + 1 + idx.size * nbin
    args = (vis, "tbcp", ds["WEIGHT"].data, "tbcp", ds["FLAG"].data, "tbcp", ds["UVW"].data,
            "tbx", ratio_d, "t", params_d, "kz")
    kwargs = dict(layout=layout, frequency=freq, edges=edges, pol_mask=p.pol_mask,
                  lo=options.uv_lo, hi=options.uv_hi)
    if not write:
        sums = da.blockwise(_block_line, "tbs", *args, dtype=np.float64, concatenate=True,
                            new_axes={"s": nsum}, adjust_chunks={"t": 1, "b": 1}, write=False,
                            **kwargs).sum(axis=(0, 1))
        return _Partition(p.name, idx, sums, None)
    quad = da.blockwise(_block_line, "tb", *args, dtype=object, concatenate=True,
                        meta=np.empty((0, 0), dtype=object), write=True, **kwargs)
    npol = vis.shape[3]
    parts = []
    for i, dtype in enumerate((vis.dtype, np.float32, bool)):
        parts.append(da.blockwise(_get, "tbcp", quad, "tb", dtype=dtype, i=i,
                                  new_axes={"c": nbin, "p": npol},
                                  meta=np.empty((0, 0, 0, 0), dtype=dtype)))
    sums = da.blockwise(_get, "tbs", quad, "tb", dtype=np.float64, i=3, new_axes={"s": nsum},
                        adjust_chunks={"t": 1, "b": 1},
                        meta=np.empty((0, 0, 0), dtype=np.float64)).sum(axis=(0, 1))
    centres_v = 0.5 * (edges[:-1] + edges[1:])
    keep = [k for k, var in ds.variables.items() if "frequency" not in var.dims]
    out = ds[keep].drop_encoding().copy()
    dims = ds["VISIBILITY"].dims
    # the velocity axis on the schema's channel axis: each bin's rest-frame frequency
    out = out.assign_coords(
        frequency=("frequency", rest_hz * (1 - centres_v / SPEED_OF_LIGHT_KMS),
                   {"units": "Hz", "observer": "REST"}),
        channel_width=("frequency", np.full(nbin, rest_hz * (edges[1] - edges[0])
                                             / SPEED_OF_LIGHT_KMS), {"units": "Hz"}),
        velocity=("frequency", centres_v, {"units": "km/s", "frame": frame,
                                            "convention": "v = c (nu_c - nu) / nu_c"}))
    out["VISIBILITY"] = (dims, parts[0], ds["VISIBILITY"].attrs)
    out["WEIGHT"] = (dims, parts[1], ds["WEIGHT"].attrs)
    out["FLAG"] = (dims, parts[2], ds["FLAG"].attrs)
    out.attrs.update({"data_kind": "stacked", "spectral_axis": "velocity",
                      "line_rest_frequency_hz": float(rest_hz), "velocity_frame": frame,
                      "velocity_edges_kms": [float(e) for e in edges],
                      "original_phase_center": [float(x) for x in p.ds.attrs["phase_center"]],
                      "linestack_n_positions": int(idx.size)})
    return _Partition(p.name, idx, sums, out)


# --- public API ------------------------------------------------------------------------------

def stack_lines(data: Any, positions: Any, *, line_frequency: Any,
                velocity_resolution: float = 20.0, velocity_range: Any = (-600, 600),
                frame: str = "lsrk", weighting: str = "pb", primary_beam: Any = "auto",
                pb_cutoff: float = DEFAULT_PB_CUTOFF, uvmin: Any = None, uvmax: Any = None,
                polarizations: Any = "parallel", out: str | os.PathLike | None = None,
                overwrite: bool = False, progress: bool = False,
                compute: bool = True) -> LineStackResult | LazyResult:
    """Stack the spectra of catalog targets at their own redshifts, in the uv-domain.

    Parameters
    ----------
    data
        Any input of :func:`xstack.stack_uv` (store, MeasurementSet, DataTree, Dataset(s)).
    positions
        Catalog (:class:`astropy.table.Table` or path) with ``ra``, ``dec`` (degrees) and
        ``z`` (redshift) or ``freq`` (observed line centre, in the column's unit, else Hz, in
        the frame ``frame``); ``weight`` for ``weighting="column"``, ``sigma`` (Jy) for
        ``"sigma2"``.
    line_frequency
        The line's rest frequency: a name of :data:`xstack.spectral.LINES` (``"HI"``,
        ``"CO(2-1)"``), a frequency with units or a number in Hz.
    velocity_resolution
        Bin width, km/s.
    velocity_range
        (low, high) km/s about each target's line centre; v = c (nu_c - nu) / nu_c.
    frame
        ``lsrk`` or ``bary``: the frame of the catalog's redshifts. TOPO data are converted
        per integration (the correction at the pointing centre); data already in the frame
        are used as they are; data in another frame are an error.
    weighting, primary_beam, pb_cutoff, uvmin, uvmax, polarizations
        As :func:`xstack.stack_uv`: W_k, the beam A_k(nu) per channel, the uv range and the
        correlations of the flux. Smearing is not corrected (line channels are narrow).
    out
        Write the stacked store here (kind ``stacked``; the channel axis holds the velocity
        bins, see ``docs/schema.md``): per row, bin and correlation the W_k w o-weighted
        mean over targets and channels, WEIGHT its inverse variance, FLAG where nothing
        entered.
    overwrite
        Replace an existing ``out``.
    progress
        Progress bars on stderr.
    compute
        True: run the pass over the data now. False: return a
        :class:`xstack._lazy.LazyResult` whose pass runs later, together with other lazy
        results in one pass over shared data (``xstack.compute(continuum, line)`` reads each
        chunk once), as ``stack_uv(..., compute=False)``. With ``out`` the store is begun now
        and finished by the compute (removed if it fails or the result is dropped).

    Returns
    -------
    LineStackResult
        Or, with ``compute=False``, a lazy result that computes to it.

    Raises
    ------
    OptionError
        A bad option value, before the catalog or data are read; data in a frame other than
        TOPO and ``frame``.
    XstackError
        A catalog without ``z``/``freq`` or with bad rows (named), no position in a
        pointing, an existing ``out``; :class:`~xstack.errors.NoDataError` when no usable
        visibility falls in any bin.
    """
    rest_hz = rest_frequency(line_frequency)
    edges = velocity_edges(velocity_resolution, velocity_range)
    frame_l = str(frame).lower()
    if frame_l not in LINE_FRAMES:
        raise OptionError(f"frame must be one of {', '.join(LINE_FRAMES)}, got {frame!r}",
                          option="frame")
    options = UvstackOptions(weighting=weighting, primary_beam=primary_beam,
                             pb_cutoff=pb_cutoff, uvmin=uvmin, uvmax=uvmax,
                             polarizations=polarizations, out=out, overwrite=overwrite,
                             progress=progress, smearing="none")
    inputs = _load(data, positions, options)
    centres = line_centres_hz(inputs.table, rest_hz)
    plan = _plan(inputs, options)
    write = out is not None
    graphs = [_partition_graph(p, centres, edges, frame_l, options, rest_hz, write)
              for p in plan.active]
    if not compute:
        return _lazy(plan, graphs, centres, edges, rest_hz, frame_l, options)
    results = _run(graphs, options, edges, len(inputs.table))
    return _assemble(plan, graphs, results, centres, edges, rest_hz, frame_l, options)


def _run(graphs: list[_Partition], options: UvstackOptions, edges: np.ndarray,
         npos: int) -> tuple[Any, ...]:
    from xstack._progress import dask_progress

    sums = [g.sums for g in graphs]
    if options.out is None:
        with dask_progress("linestack", enabled=options.progress):
            return dask.compute(*sums)
    from xstack.schema import write_store

    done: list[tuple[Any, ...]] = []

    def keep(results: tuple[Any, ...]) -> dict[str, Any]:
        done.append(results)
        return _store_attrs(_combine(graphs, results, edges, npos), edges)

    # one task per chunk makes the stacked chunk and its sums (no fusion: computed once)
    with dask.config.set({"optimization.fuse.active": False}):
        write_store({g.name: g.stacked for g in graphs}, options.out, kind="stacked",
                    overwrite=options.overwrite, progress=options.progress,
                    description="linestack", compute_with=sums, final_attrs=keep)
    return done[-1]


def _lazy(plan, graphs: list[_Partition], centres, edges, rest_hz, frame,
          options: UvstackOptions) -> LazyResult:
    """The line stack's pass as a dask collection that finishes into a LineStackResult (the
    pattern of :func:`xstack.uvstack.stack._lazy`: with ``out`` the store is begun now, its
    chunk writes made by the same task per chunk as the sums, and finished in the caller)."""
    sums = [g.sums for g in graphs]
    write = None
    writes: list[Any] = []
    if options.out is not None:
        from xstack.schema import StoreWrite

        # as the eager write (_run): no low-level fusion, or the task making a stacked chunk
        # and its sums runs once for each; the sums are optimised now so that the caller's
        # configuration at compute time cannot fuse them
        with dask.config.set({"optimization.fuse.active": False}):
            write = StoreWrite({g.name: g.stacked for g in graphs}, options.out,
                               kind="stacked", overwrite=options.overwrite)
            sums = [_optimised_now(x) for x in sums]
        writes = write.graphs
    npos = len(plan.inputs.table)

    def finish(values: list[Any]) -> LineStackResult:
        results = tuple(values[len(writes):])
        try:
            spec = _combine(graphs, results, edges, npos)
            if write is not None:
                write.finish(_store_attrs(spec, edges))
        except BaseException:
            if write is not None:  # every task has run: nothing writes into it any more
                write.abort()
            raise
        return _assemble(plan, graphs, results, centres, edges, rest_hz, frame, options)

    return LazyResult([*writes, *sums], finish, "stack_lines", write=write)


def _store_attrs(spec: _Spectrum, edges: np.ndarray) -> dict[str, Any]:
    """The root attributes of the written stack: the spectrum (NaN as null)."""
    return {"linestack": json_ready({
        "velocity_kms": 0.5 * (edges[:-1] + edges[1:]), "flux_jy": spec.flux,
        "flux_err_jy": np.sqrt(np.diag(spec.cov)),
        "n_targets_per_bin": spec.covered.sum(axis=0), "n_visibilities": spec.nvis})}


@dataclass
class _Spectrum:
    flux: np.ndarray  # (nbin,) NaN where nothing entered
    cov: np.ndarray  # (nbin, nbin)
    nvis: int
    covered: np.ndarray  # (npos, nbin) bool


def _combine(graphs, results, edges, npos) -> _Spectrum:
    """Add the partitions' sums: S_j = N_j / D_j, Cov = C / (D D^T)."""
    nbin = edges.size - 1
    num = np.zeros(nbin)
    den = np.zeros(nbin)
    cov = np.zeros((nbin, nbin))
    nvis = 0
    covered = np.zeros((npos, nbin), dtype=bool)
    for g, s in zip(graphs, results):
        s = np.asarray(s, dtype=np.float64)
        num += s[:nbin]
        den += s[nbin:2 * nbin]
        cov += s[2 * nbin:2 * nbin + nbin * nbin].reshape(nbin, nbin)
        nvis += int(round(s[2 * nbin + nbin * nbin]))
        covered[g.index] |= s[2 * nbin + nbin * nbin + 1:].reshape(g.index.size, nbin) > 0
    if not (den > 0).any() or nvis == 0:
        raise NoDataError("no unflagged visibility with positive weight falls in a velocity "
                          "bin of any target (check velocity_range and line_frequency)")
    with np.errstate(divide="ignore", invalid="ignore"):
        flux = np.where(den > 0, num / den, np.nan)
        dd = np.outer(den, den)
        c = np.where(dd > 0, cov / dd, np.nan)
    return _Spectrum(flux, c, nvis, covered)


def _assemble(plan, graphs, results, centres, edges, rest_hz, frame, options) -> LineStackResult:
    npos = len(plan.inputs.table)
    spec = _combine(graphs, results, edges, npos)
    flux, c, nvis, covered = spec.flux, spec.cov, spec.nvis, spec.covered
    n_bins = covered.sum(axis=1)
    used_any = np.zeros(npos, dtype=bool)
    for p in plan.active:
        used_any |= p.used & (p.weight > 0)
    outside = int(np.count_nonzero(used_any & (n_bins == 0)))
    if outside:
        warnings.warn(XstackWarning(
            f"{outside} of {int(used_any.sum())} targets in a pointing have no usable channel "
            "in the velocity range about their line (outside the band or flagged): not "
            "stacked; check velocity_range and line_frequency", option="velocity_range"),
            stacklevel=3)
    pos = Table(plan.inputs.table, copy=True)
    parts = plan.partitions
    pos["used"] = np.stack([p.used & (p.weight > 0) for p in parts], axis=1)
    pos["weight_used"] = np.stack([p.weight for p in parts], axis=1)
    pos["attenuation"] = np.stack([p.attenuation for p in parts], axis=1)
    pos["n_pointings"] = pos["used"].sum(axis=1)
    pos["line_centre_hz"] = centres
    pos["n_bins"] = n_bins
    pos.meta["partitions"] = [p.name for p in parts]
    record = {k: v for k, v in plan.record.items()
              if k not in ("smearing", "smearing_corrected", "engine", "engine_rows")}
    record.update({"line_frequency_hz": float(rest_hz), "frame": frame,
                   "velocity_resolution_kms": float(edges[1] - edges[0]),
                   "velocity_range_kms": [float(edges[0]), float(edges[-1])]})
    return LineStackResult(
        velocity_edges_kms=edges, velocity_kms=0.5 * (edges[:-1] + edges[1:]), flux_jy=flux,
        flux_err_jy=np.sqrt(np.diag(c)), flux_cov_jy2=c,
        n_targets_per_bin=covered.sum(axis=0).astype(np.int64),
        n_positions=int(np.count_nonzero(n_bins > 0)), n_visibilities=nvis, positions=pos,
        rest_frequency_hz=float(rest_hz), frame=frame, options=json_ready(record),
        out=None if options.out is None else str(options.out))
