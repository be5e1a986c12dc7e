"""What is in a MeasurementSet, an xstack store or a FITS image: ``xstack info``.

The facts CASA's ``listobs`` and ``imhead`` report, as one dictionary (``--json`` prints it):

* MeasurementSet or store: telescope, fields and their phase centers, spectral windows,
  correlations, the time range and integration time, antennas and baselines (their longest
  and shortest length from the antenna positions), whether autocorrelations are present,
  the flagged fraction of the *real* cells, and the weights against the data's own scatter.
* FITS image: size, cell, beam, units, frequency, phase and pointing center, primary-beam
  state (``XSPBCOR``, ``XSPBFILE``, ``XSPBCUT``), whether it is a mosaic.

Real cells. A store holds a regular (time, baseline) grid; cells without an MS row are
*padding* (NaN visibility with zero or NaN weight, ``docs/io.md``), not data. A cell is
*data* when it is unflagged, finite and of positive weight (``xstack._select``,
``xstack._scatter.data_cells``); the flagged fraction is 1 - data / real cells, where the
real cells are all cells but the padding. An MS is read through the same (time, baseline)
grid as ``xstack convert`` builds, so the MS and its store report the same numbers.

Weights. :func:`xstack._scatter.pooled_weight_scale` on a sample of each partition (the
first :data:`SAMPLE_CELLS` cells, parallel hands, cross-correlations) gives the ratio of the
variance measured from neighbouring-channel differences to the variance the weights claim
(1/w). Its median over the samples is reported; when its square root (the factor by which
error bars from WEIGHT are off) differs from 1 by more than
:data:`xstack._scatter.EMPIRICAL_TOLERANCE`, the weights are not 1/sigma^2 of the data and a
warning says so.
"""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from xstack.errors import XstackError

#: Cells (time x baseline x channel x correlation) per partition used to compare the weights
#: with the data's scatter (the first blocks of the partition).
SAMPLE_CELLS = 4_000_000
#: MJD seconds -> days
_DAY = 86400.0


# --------------------------------------------------------------------------- formatting
def sexagesimal(ra_deg: float, dec_deg: float) -> tuple[str, str]:
    """(``"hh:mm:ss.ssss"``, ``"+dd:mm:ss.sss"``) of a direction in degrees."""
    from astropy import units as u
    from astropy.coordinates import Angle

    ra = Angle(ra_deg % 360.0, u.deg).to_string(unit=u.hour, sep=":", precision=4, pad=True)
    dec = Angle(dec_deg, u.deg).to_string(unit=u.deg, sep=":", precision=3, pad=True,
                                          alwayssign=True)
    return ra, dec


def _direction(ra_rad: float, dec_rad: float) -> dict[str, Any]:
    ra, dec = math.degrees(ra_rad) % 360.0, math.degrees(dec_rad)
    hms, dms = sexagesimal(ra, dec)
    return {"ra_deg": ra, "dec_deg": dec, "ra_hms": hms, "dec_dms": dms}


def _utc(mjd_seconds: float) -> str:
    from astropy.time import Time

    return Time(mjd_seconds / _DAY, format="mjd", scale="utc").isot


# --------------------------------------------------------------------------- cell statistics
class _Tally:
    """Real, padding and data cells, and the weight-scale samples, over many blocks."""

    def __init__(self) -> None:
        self.cells = 0
        self.padding = 0
        self.data = 0
        self.scales: list[float] = []
        self.pairs = 0

    def add(self, vis: np.ndarray, weight: np.ndarray, flag: np.ndarray, pol_mask: np.ndarray,
            auto: np.ndarray, sample: bool) -> None:
        """Count a (time, baseline, channel, correlation) block; sample its weights if asked."""
        from xstack._scatter import data_cells, pooled_weight_scale

        finite = np.isfinite(vis.real) & np.isfinite(vis.imag)
        positive = weight > 0
        self.cells += vis.size
        self.padding += int(np.count_nonzero(~finite & ~positive))
        good = data_cells(vis, weight, flag)
        self.data += int(np.count_nonzero(good))
        if sample and pol_mask.any():
            cross_flag = flag | auto[None, :, None, None] if auto.any() else flag
            scale, n = pooled_weight_scale(vis, weight, cross_flag, pol_mask=pol_mask)
            if math.isfinite(scale) and n > 0:
                self.scales.append(scale)
                self.pairs += n

    def summary(self) -> dict[str, Any]:
        real = self.cells - self.padding
        return {"real_cells": real, "padding_cells": self.padding, "data_cells": self.data,
                "flagged_fraction": (real - self.data) / real if real else None}

    def weights(self) -> dict[str, Any]:
        from xstack._scatter import EMPIRICAL_TOLERANCE

        if not self.scales:
            return {"variance_ratio": None, "sigma_ratio": None, "n_pairs": self.pairs,
                    "n_samples": 0, "consistent": None}
        ratio = float(np.median(self.scales))
        sigma = math.sqrt(ratio) if ratio > 0 else float("nan")
        return {"variance_ratio": ratio, "sigma_ratio": sigma, "n_pairs": self.pairs,
                "n_samples": len(self.scales),
                "consistent": bool(abs(sigma - 1.0) <= EMPIRICAL_TOLERANCE)}


def _weights_warning(name: str, w: dict[str, Any]) -> str | None:
    if w["consistent"] is not False:
        return None
    return (f"{name}: the weights are not 1/sigma^2 of the data: the scatter of neighbouring "
            f"channels (or integrations) is {w['sigma_ratio']:.3g} x the sigma that WEIGHT "
            f"claims (variance ratio {w['variance_ratio']:.3g}, median of {w['n_samples']} "
            "samples); error bars "
            "from WEIGHT are off by that factor - use the empirical errors of uv-stacking "
            "(xstack uvstack --errors empirical)")


def _baseline_lengths(positions: np.ndarray, a1: np.ndarray, a2: np.ndarray) -> dict[str, Any]:
    cross = a1 != a2
    pairs = np.unique(np.column_stack([np.minimum(a1, a2), np.maximum(a1, a2)])[cross], axis=0)
    out: dict[str, Any] = {"count": int(pairs.shape[0]), "longest_m": None, "shortest_m": None}
    if pairs.shape[0] and positions.size:
        length = np.linalg.norm(positions[pairs[:, 1]] - positions[pairs[:, 0]], axis=1)
        out["longest_m"], out["shortest_m"] = float(length.max()), float(length.min())
    return out


def _finish(out: dict[str, Any], tally: _Tally, name: str) -> dict[str, Any]:
    out.update(tally.summary())
    out["weights"] = tally.weights()
    msgs = []
    msg = _weights_warning(name, out["weights"])
    if msg:
        msgs.append(msg)
    if out["real_cells"] and out["data_cells"] == 0:
        msgs.append(f"{name}: every cell is flagged, non-finite or of zero weight: no data")
    out["warnings"] = msgs
    for m in msgs:
        warnings.warn(m, stacklevel=3)
    return out


# --------------------------------------------------------------------------- stores
def _msv4_info(path: Path) -> dict[str, Any]:
    """The MSv4 writer and data groups of a store (from its partitions' metadata)."""
    import json

    from xstack._fs import locate

    loc = locate(path)  # a local path or a store URL
    try:
        docs = loc.read_many([f"{name}/zarr.json" for name, is_dir in loc.listdir() if is_dir])
    except OSError:
        docs = {}
    writers, groups = set(), []
    for key in sorted(docs):
        try:
            attrs = json.loads(docs[key]).get("attributes", {}) or {}
        except (ValueError, AttributeError):
            continue
        if attrs.get("type") != "visibility":
            continue
        creator = attrs.get("creator") or {}
        if isinstance(creator, dict):
            writers.add(" ".join(str(creator.get(k, "")) for k in ("software_name", "version")
                                 ).strip())
        for g in attrs.get("data_groups") or {}:
            if g not in groups:
                groups.append(str(g))
    return {"format": "MSv4 processing set", "written_by": sorted(w for w in writers if w),
            "data_groups": groups}


def _store_info(path: Path) -> dict[str, Any]:
    from xstack._select import autocorrelation_mask, parallel_hand_mask
    from xstack.schema import iter_partitions, open_store

    tree = open_store(path)
    fields: dict[int, dict[str, Any]] = {}
    spws: dict[int, dict[str, Any]] = {}
    parts = []
    tally = _Tally()
    t_lo, t_hi, intervals, n_times, scans = math.inf, -math.inf, [], set(), set()
    ant_names: list[str] = []
    positions: dict[str, np.ndarray] = {}
    pairs_named: set[tuple[str, str]] = set()
    auto_any = False
    telescopes = set()
    for name, ds in iter_partitions(tree):
        attrs = ds.attrs
        telescopes.add(str(attrs.get("telescope_name", "unknown")))
        fid = int(attrs.get("field_id", len(fields)))
        if fid not in fields:
            ra, dec = (float(x) for x in attrs["phase_center"])
            fields[fid] = {"id": fid, "name": str(attrs.get("field_name", f"field{fid}")),
                           **_direction(ra, dec)}
        sid = int(attrs.get("spectral_window_id", len(spws)))
        freq = np.asarray(ds["frequency"].values, dtype=np.float64)
        width = np.asarray(ds["channel_width"].values, dtype=np.float64) \
            if "channel_width" in ds.coords or "channel_width" in ds else np.zeros_like(freq)
        pols = [str(p) for p in ds["polarization"].values]
        spws.setdefault(sid, _spw(sid, freq, width, pols))
        time = np.asarray(ds["time"].values, dtype=np.float64)
        it = float(ds["time"].attrs.get("integration_time", 0.0) or 0.0)
        if time.size:
            t_lo, t_hi = min(t_lo, time.min() - it / 2), max(t_hi, time.max() + it / 2)
            n_times.update(time.tolist())
            intervals.append(it)
        if "scan_number" in ds.coords:
            scans.update(int(s) for s in np.asarray(ds["scan_number"].values))
        names = [str(n) for n in ds["antenna_name"].values] if "antenna_name" in ds.coords else []
        if "ANTENNA_POSITION" in ds:
            pos = np.asarray(ds["ANTENNA_POSITION"].values, dtype=np.float64)
            for k, n in enumerate(names):
                positions.setdefault(n, pos[k])
        for n in names:
            if n not in ant_names:
                ant_names.append(n)
        a1 = np.asarray(ds["baseline_antenna1_id"].values)
        a2 = np.asarray(ds["baseline_antenna2_id"].values)
        if names:
            pairs_named.update((names[i], names[j]) for i, j in zip(a1, a2))
        auto = autocorrelation_mask(ds)
        auto_any |= bool(auto.any())
        pol_mask = parallel_hand_mask(pols)
        nt = ds.sizes["time"]
        ct = ds["VISIBILITY"].chunks[0][0] if ds["VISIBILITY"].chunks else nt
        sampled = 0
        for t0 in range(0, nt, max(1, ct)):
            sel = ds[["VISIBILITY", "WEIGHT", "FLAG"]].isel(time=slice(t0, t0 + ct))
            vis, weight, flag = (np.asarray(sel[v].values) for v in ("VISIBILITY", "WEIGHT", "FLAG"))
            tally.add(vis, weight, flag, pol_mask, auto, sample=sampled < SAMPLE_CELLS)
            sampled += vis.size
        parts.append({"name": name, "field_id": fid, "spectral_window_id": sid,
                      "sizes": {k: int(v) for k, v in ds.sizes.items()}})
    if not parts:
        raise XstackError(f"{path}: the store has no partitions")
    index = {n: k for k, n in enumerate(ant_names)}
    a1 = np.array([index[p[0]] for p in sorted(pairs_named)], dtype=np.int64)
    a2 = np.array([index[p[1]] for p in sorted(pairs_named)], dtype=np.int64)
    pos = np.array([positions.get(n, np.full(3, np.nan)) for n in ant_names]).reshape(-1, 3)
    out: dict[str, Any] = {
        "path": str(path), "kind": "store",
        "store_kind": str(tree.attrs.get("xstack_kind", "")),
        **_msv4_info(path),
        "telescope": ",".join(sorted(telescopes)),
        "fields": [fields[k] for k in sorted(fields)],
        "spectral_windows": [spws[k] for k in sorted(spws)],
        "correlations": _union(s["correlations"] for s in spws.values()),
        "time": _times(t_lo, t_hi, float(np.median(intervals)) if intervals else 0.0,
                       len(n_times), len(scans) or None),
        "antennas": {"count": len(ant_names), "names": ant_names},
        "baselines": _baseline_lengths(pos, a1, a2),
        "autocorrelations": auto_any,
        "partitions": parts,
    }
    return _finish(out, tally, str(path))


def _spw(sid: int, freq: np.ndarray, width: np.ndarray, pols: list[str]) -> dict[str, Any]:
    edges_lo = freq - np.abs(width) / 2
    edges_hi = freq + np.abs(width) / 2
    return {"id": sid, "n_channels": int(freq.size),
            "first_channel_hz": float(freq[0]) if freq.size else None,
            "last_channel_hz": float(freq[-1]) if freq.size else None,
            "channel_width_hz": float(np.median(width)) if width.size else None,
            "total_bandwidth_hz": float(edges_hi.max() - edges_lo.min()) if freq.size else 0.0,
            "center_hz": float((edges_hi.max() + edges_lo.min()) / 2) if freq.size else None,
            "correlations": pols}


def _union(lists: Any) -> list[str]:
    """The distinct items of several lists, in order of first appearance."""
    return list(dict.fromkeys(p for items in lists for p in items))


def _times(t_lo: float, t_hi: float, interval: float, n_times: int,
           n_scans: int | None) -> dict[str, Any]:
    if not math.isfinite(t_lo):
        return {"start_utc": None, "end_utc": None, "duration_s": 0.0, "integration_s": interval,
                "n_times": 0, "n_scans": n_scans}
    return {"start_utc": _utc(t_lo), "end_utc": _utc(t_hi), "start_mjd_s": t_lo,
            "end_mjd_s": t_hi, "duration_s": t_hi - t_lo, "integration_s": interval,
            "n_times": n_times, "n_scans": n_scans}


# --------------------------------------------------------------------------- MeasurementSets
def _ms_info(path: Path, datacolumn: str = "DATA") -> dict[str, Any]:
    from xstack._select import parallel_hand_mask
    from xstack.io import convert, msread

    msread.check_ms(path)
    full = str(path.resolve())
    try:
        column, vis_dtype = convert.check_datacolumn(full, datacolumn)
        meta = msread.read_meta(full)
        index = msread.read_index(full, (*convert.INDEX_COLUMNS, "EXPOSURE"))
        time = index["TIME"]
        if time.size == 0:
            raise XstackError(f"{path}: the MeasurementSet has no rows")
        plans = convert.plan_partitions(index, meta, str(path))
        tally = _Tally()
        itemsize = np.dtype(vis_dtype).itemsize
        for plan in plans:
            spec = convert.block_spec(full, plan, meta, column, vis_dtype)
            pols = meta.pol_names[int(meta.ddid_pol[plan.ddid])]
            pol_mask = parallel_hand_mask(pols)
            auto = plan.antenna1 == plan.antenna2
            ct, cb = convert.chunk_sizes(plan.times.size, plan.antenna1.size, spec.n_channels,
                                          spec.n_pols, itemsize, {})
            sampled = 0
            for t0, t1, b0, b1, rows, ti, bi in convert.chunk_blocks(plan, ct, cb):
                block = msread.read_block(spec, rows, ti, bi, t1 - t0, b1 - b0, plan.times[t0:t1])
                tally.add(block["VISIBILITY"], block["WEIGHT"], block["FLAG"], pol_mask,
                          auto[b0:b1], sample=sampled < SAMPLE_CELLS)
                sampled += block["VISIBILITY"].size
    finally:
        msread.close_tables(full)

    a1, a2 = index["ANTENNA1"], index["ANTENNA2"]
    fid, ddid = index["FIELD_ID"], index["DATA_DESC_ID"]
    interval = index.get("INTERVAL", np.zeros(time.size))
    rows_per_field = np.bincount(fid, minlength=len(meta.field_names))
    fields = [{"id": k, "name": meta.field_names[k], "n_rows": int(rows_per_field[k]),
               **_direction(*meta.phase_centers[k])} for k in range(len(meta.field_names))]
    spws = []
    for d in np.unique(ddid):
        sid = int(meta.ddid_spw[d])
        spws.append(_spw(sid, meta.spw_freqs[sid], meta.spw_widths[sid],
                         list(meta.pol_names[int(meta.ddid_pol[d])])))
    scans = index.get("SCAN_NUMBER")
    out: dict[str, Any] = {
        "path": str(path), "kind": "ms", "data_column": column,
        "telescope": meta.telescope_name,
        "fields": fields,
        "spectral_windows": spws,
        "correlations": _union(s["correlations"] for s in spws),
        "time": _times(float(np.min(time - interval / 2)), float(np.max(time + interval / 2)),
                       float(np.median(interval)), int(np.unique(time).size),
                       int(np.unique(scans).size) if scans is not None else None),
        "antennas": {"count": len(meta.antenna_names), "names": list(meta.antenna_names)},
        "baselines": _baseline_lengths(meta.antenna_positions, a1, a2),
        "autocorrelations": bool(np.any(a1 == a2)),
        "n_rows": int(time.size),
        "partitions": [{"name": p.name, "field_id": p.field_id,
                        "spectral_window_id": int(meta.ddid_spw[p.ddid]),
                        "sizes": {"time": int(p.times.size), "baseline_id": int(p.antenna1.size)}}
                       for p in plans],
    }
    return _finish(out, tally, str(path))


# --------------------------------------------------------------------------- FITS images
def _fits_info(path: Path) -> dict[str, Any]:
    from astropy.io import fits

    from xstack.imaging.fitsio import (
        PBCUT_KEY,
        PBFILE_KEY,
        beam_from_header,
        pb_corrected_from_header,
        pb_file_from_header,
        read_wcs,
    )
    from xstack.imaging.image import UVDIM_KEY

    try:
        with fits.open(path, memmap=True) as hdul:
            hdu = next((h for h in hdul if isinstance(h, (fits.PrimaryHDU, fits.ImageHDU))
                        and h.data is not None and h.data.ndim >= 2), None)
            if hdu is None:
                raise XstackError(f"{path}: no image data in the FITS file")
            header = hdu.header.copy()
            data = np.asarray(hdu.data, dtype=np.float64)
            extensions = [h.name for h in hdul]
    except OSError as exc:
        raise XstackError(f"{path}: not a FITS image, MeasurementSet or xstack store ({exc})") \
            from None
    wcs = read_wcs(header, str(path))
    out: dict[str, Any] = {"path": str(path), "kind": "fits", "hdus": extensions,
                           "shape": [int(n) for n in data.shape[::-1]],
                           "bunit": str(header.get("BUNIT", "")).strip(),
                           "telescope": str(header.get("TELESCOP", "")).strip() or None}
    axes = []
    for k in range(wcs.naxis):
        axes.append({"ctype": str(wcs.wcs.ctype[k]), "n": int(header.get(f"NAXIS{k + 1}", 1)),
                     "crval": float(wcs.wcs.crval[k]), "cdelt": float(wcs.wcs.cdelt[k]),
                     "crpix": float(wcs.wcs.crpix[k]), "cunit": str(wcs.wcs.cunit[k])})
    out["axes"] = axes
    msgs = []
    if wcs.has_celestial:
        cel = wcs.celestial
        scale = cel.proj_plane_pixel_scales()
        cell = [abs(float(s.to_value("arcsec"))) for s in scale]
        out["cell_arcsec"] = cell
        out["size"] = [int(header.get(f"NAXIS{wcs.wcs.lng + 1}")),
                       int(header.get(f"NAXIS{wcs.wcs.lat + 1}"))]
        out["field_of_view_arcsec"] = [cell[0] * out["size"][0], cell[1] * out["size"][1]]
        out["projection"] = str(cel.wcs.ctype[0])[-3:]
        out["frame"] = str(header.get("RADESYS", cel.wcs.radesys or "")).strip() or None
        out["reference"] = _direction(math.radians(cel.wcs.crval[0]),
                                      math.radians(cel.wcs.crval[1]))
        if "OBSRA" in header and "OBSDEC" in header:
            out["pointing"] = _direction(math.radians(float(header["OBSRA"])),
                                         math.radians(float(header["OBSDEC"])))
            out["pointing_from"] = "OBSRA/OBSDEC"
        else:
            out["pointing"] = out["reference"]
            out["pointing_from"] = "reference pixel"
    else:
        msgs.append(f"{path}: the image has no celestial WCS (RA/Dec axes)")
    freq = None
    if wcs.wcs.spec >= 0 and str(wcs.wcs.ctype[wcs.wcs.spec]).upper().startswith("FREQ"):
        freq = float(wcs.wcs.crval[wcs.wcs.spec])
        out["bandwidth_hz"] = abs(float(wcs.wcs.cdelt[wcs.wcs.spec])) \
            if int(header.get(f"NAXIS{wcs.wcs.spec + 1}", 1)) == 1 else None
    elif header.get("RESTFRQ") or header.get("RESTFREQ"):
        freq = float(header.get("RESTFRQ") or header.get("RESTFREQ"))
    out["frequency_hz"] = freq
    beam = beam_from_header(header)
    out["beam"] = None if beam is None else {"major_arcsec": beam[0], "minor_arcsec": beam[1],
                                             "pa_deg": beam[2]}
    uvdim = header.get(UVDIM_KEY)
    out["uv_dimensions"] = None if uvdim is None else int(uvdim)
    if uvdim is not None and int(uvdim) < 2:
        msgs.append(f"{path}: the uv coverage of this image is one-dimensional ({UVDIM_KEY} = "
                    f"{int(uvdim)}): its beam is not 2-D and its BMAJ/BMIN mean nothing")
    pbfile = pb_file_from_header(header, path)
    out["primary_beam"] = {
        "corrected": pb_corrected_from_header(header),
        "file": str(header.get(PBFILE_KEY)) if PBFILE_KEY in header else None,
        "file_exists": None if pbfile is None else pbfile.is_file(),
        "cutoff": float(header[PBCUT_KEY]) if PBCUT_KEY in header else None,
    }
    if pbfile is not None and not pbfile.is_file():
        msgs.append(f"{path}: its primary-beam file {pbfile.name} ({PBFILE_KEY}) is missing")
    n_pointings = int(header.get("XSMOSAIC", 1) or 1)
    out["mosaic"] = n_pointings > 1
    out["n_pointings"] = n_pointings
    finite = np.isfinite(data)
    out["blanked_fraction"] = float(1.0 - finite.mean()) if data.size else 0.0
    out["min"] = float(data[finite].min()) if finite.any() else None
    out["max"] = float(data[finite].max()) if finite.any() else None
    out["warnings"] = msgs
    for m in msgs:
        warnings.warn(m, stacklevel=3)
    return out


def _is_fits(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            return fh.read(9) == b"SIMPLE  ="
    except OSError:
        return False


def info(path: str | os.PathLike, *, datacolumn: str = "DATA") -> dict[str, Any]:
    """Summary of a MeasurementSet, an xstack store or a FITS image (``xstack info``).

    Parameters
    ----------
    path
        A MeasurementSet directory, a zarr store written by xstack (or any store
        :func:`xstack.open_store` opens), or a FITS image.
    datacolumn
        MeasurementSet only: the visibility column whose cells are counted and compared
        with the weights (``DATA``, ``CORRECTED_DATA``, ``MODEL_DATA``).

    Returns
    -------
    dict
        ``kind`` (``"ms"``, ``"store"`` or ``"fits"``) and the facts of that kind (see
        ``docs/info.md``): for data, ``fields`` (phase centers in degrees and sexagesimal,
        ICRS), ``spectral_windows`` (Hz), ``time`` (UTC, seconds), ``antennas``,
        ``baselines`` (metres), ``correlations``, ``autocorrelations``,
        ``flagged_fraction`` (of the real cells), ``weights`` (``variance_ratio`` = measured
        variance / 1/WEIGHT, ``sigma_ratio`` its square root); for an image, ``size``,
        ``cell_arcsec``, ``beam``, ``bunit``, ``frequency_hz``, ``reference`` and
        ``pointing`` centers, ``primary_beam``, ``mosaic``. ``warnings`` lists what was
        warned about (each also issued as a :class:`UserWarning`).

    Raises
    ------
    XstackError
        If ``path`` does not exist or is none of the three kinds.
    """
    from xstack._fs import is_remote

    if is_remote(path):  # a store URL (s3://...): only stores live there
        return _store_info(path)
    path = Path(path)
    if not path.exists():
        raise XstackError(f"{path}: no such file, MeasurementSet or store")
    if path.is_dir():
        if (path / "table.dat").is_file():
            return _ms_info(path, datacolumn)
        if (path / "zarr.json").is_file() or (path / ".zgroup").is_file():
            return _store_info(path)
        raise XstackError(f"{path}: a directory that is neither a MeasurementSet (no table.dat) "
                          "nor a zarr store (no zarr.json)")
    if _is_fits(path):
        return _fits_info(path)
    raise XstackError(f"{path}: not a FITS image, MeasurementSet or xstack store")
