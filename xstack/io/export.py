"""xstack zarr store -> MeasurementSet (``xstack export``).

Every partition becomes the rows of one DATA_DESC_ID / FIELD_ID (and scan). The store is read
one chunk at a time and its rows appended to the main table, so memory stays bounded by a
chunk whatever the size of the store. Cells that only pad an irregular grid (NaN visibility,
zero weight and flagged in every channel and polarization) are dropped, so a converted MS
exports to the rows it came from and MS -> zarr -> MS -> zarr is exact. The MS is written
under a temporary name and renamed into place at the end.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from xstack._atomic import atomic_output, check_output
from xstack._fs import is_url
from xstack._progress import progress_iter
from xstack.errors import XstackError
from xstack.frames import frequency_frame, meas_freq_ref
from xstack.io._mswrite import create_ms, write_subtables
from xstack.schema import iter_partitions, open_store

#: Bytes of visibilities handed to casacore per ``putcol`` call.
WRITE_BATCH_BYTES = 32 * 1024**2

#: Upper limit of casacore's tile cache per column while writing.
TILE_CACHE_BYTES = 16 * 1024**2

_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _chunk_edges(arr: Any, axis: int) -> list[int]:
    chunks = getattr(arr, "chunks", None)
    n = arr.shape[axis]
    if not chunks:
        return [0, n]
    return [0, *np.cumsum(chunks[axis]).tolist()]


def padding_mask(vis: np.ndarray, weight: np.ndarray, flag: np.ndarray) -> np.ndarray:
    """True for (time, baseline) cells that only pad the grid (no MS row behind them)."""
    axes = (-2, -1)
    return np.all(flag, axis=axes) & np.all(weight == 0, axis=axes) & np.all(np.isnan(vis), axis=axes)


def _load(arr: Any, where: str = "") -> np.ndarray:
    """Compute one (dask) block in this thread (on the cluster when a client is active).

    A chunk that cannot be decoded (a damaged store) becomes an :class:`XstackError` naming
    it, instead of whichever exception the codec happens to raise.
    """
    try:
        if hasattr(arr, "compute"):
            from xstack._cluster import local_scheduler

            return np.asarray(arr.compute(scheduler=local_scheduler("synchronous")))
        return np.asarray(arr)
    except (MemoryError, XstackError):
        raise
    except Exception as exc:
        raise XstackError(f"{where}: cannot be read, the store is damaged ({type(exc).__name__}: "
                          f"{exc})".replace("\n", " ")) from None


def _integration_time(ds: Any) -> float:
    it = ds["time"].attrs.get("integration_time")
    if it is not None and float(it) > 0:
        return float(it)
    t = np.asarray(ds["time"].values)
    if t.size > 1:
        return float(np.median(np.diff(t)))
    return 1.0


def _metadata(parts: list[tuple[str, Any]], where: str) -> dict[str, Any]:
    """Subtable contents shared by all partitions, and each partition's ids."""
    first = parts[0][1]
    ant_names = [str(a) for a in first["antenna_name"].values]
    positions = np.asarray(first["ANTENNA_POSITION"].values, dtype=np.float64)
    dish = np.asarray(first["DISH_DIAMETER"].values, dtype=np.float64)
    spws: dict[int, tuple[np.ndarray, np.ndarray, str]] = {}
    spw_frames: dict[int, int] = {}  # MEAS_FREQ_REF of each window
    fields: dict[int, tuple[str, tuple[float, float]]] = {}
    pols: list[tuple[str, ...]] = []
    ids = []
    t_min, t_max = np.inf, -np.inf
    for name, ds in parts:
        if [str(a) for a in ds["antenna_name"].values] != ant_names or not np.array_equal(
                np.asarray(ds["ANTENNA_POSITION"].values, dtype=np.float64), positions):
            raise XstackError(f"{where}: partitions {parts[0][0]} and {name} have different antenna "
                              "tables; export them separately")
        freq = np.asarray(ds["frequency"].values, dtype=np.float64)
        width = np.asarray(ds["channel_width"].values, dtype=np.float64)
        sid = int(ds.attrs["spectral_window_id"])
        if sid in spws and not (spws[sid][0].shape == freq.shape and np.array_equal(spws[sid][0], freq)):
            sid = max(spws) + 1  # same id, other frequencies (e.g. merged stores): a new window
        spws.setdefault(sid, (freq, width, str(ds.attrs.get("spectral_window_name", f"SPW{sid}"))))
        spw_frames.setdefault(sid, meas_freq_ref(frequency_frame(ds)))
        fid = int(ds.attrs["field_id"])
        center = (float(ds.attrs["phase_center"][0]), float(ds.attrs["phase_center"][1]))
        if fid in fields and fields[fid][1] != center:
            fid = max(fields) + 1
        fields.setdefault(fid, (str(ds.attrs["field_name"]), center))
        pol = tuple(str(p) for p in ds["polarization"].values)
        if pol not in pols:
            pols.append(pol)
        ids.append((sid, fid, pols.index(pol)))
        t = np.asarray(ds["time"].values)
        if t.size:
            half = 0.5 * _integration_time(ds)
            t_min, t_max = min(t_min, t.min() - half), max(t_max, t.max() + half)
    ddids: list[tuple[int, int]] = sorted({(s, p) for s, _, p in ids})
    return {"antenna_names": ant_names, "positions": positions, "dish": dish, "spws": spws,
            "spw_frames": spw_frames,
            "fields": fields, "pols": pols, "ddids": ddids,
            "part_ids": [(ddids.index((s, p)), f) for s, f, p in ids],
            "time_range": (float(t_min), float(t_max)) if np.isfinite(t_min) else (0.0, 0.0)}


def _fill_gaps(items: dict[int, Any], dummy: Any) -> list[Any]:
    """List indexed by id; ids without a partition get ``dummy`` (keeps ids stable)."""
    return [items.get(k, dummy) for k in range(max(items) + 1)]


def _write_partition(tab: Any, ds: Any, ddid: int, field_id: int, bar: Any, where: str = "") -> int:
    """Append the rows of one partition, chunk by chunk; return the number of rows written."""
    vis_da, w_da, f_da, uvw_da = ds["VISIBILITY"].data, ds["WEIGHT"].data, ds["FLAG"].data, ds["UVW"].data
    times = np.asarray(ds["time"].values, dtype=np.float64)
    interval = _integration_time(ds)
    if "scan_number" in ds.coords:
        scans = np.asarray(ds["scan_number"].values, dtype=np.int32)
    else:
        scans = np.full(times.size, int(ds.attrs.get("scan_number", 1)), dtype=np.int32)
    a1_all = np.asarray(ds["baseline_antenna1_id"].values, dtype=np.int32)
    a2_all = np.asarray(ds["baseline_antenna2_id"].values, dtype=np.int32)
    centroid_da = ds["TIME_CENTROID"].data if "TIME_CENTROID" in ds else None
    exposure_da = ds["EFFECTIVE_INTEGRATION_TIME"].data if "EFFECTIVE_INTEGRATION_TIME" in ds else None
    t_edges, b_edges = _chunk_edges(vis_da, 0), _chunk_edges(vis_da, 1)
    nchan, npol = vis_da.shape[2], vis_da.shape[3]
    written = 0
    for i in range(len(t_edges) - 1):
        ts = slice(t_edges[i], t_edges[i + 1])
        for j in range(len(b_edges) - 1):
            bs = slice(b_edges[j], b_edges[j + 1])
            # one array at a time, so only one chunk is being decoded at any moment
            at = f"time {ts.start}:{ts.stop}, baseline_id {bs.start}:{bs.stop}"
            vis = _load(vis_da[ts, bs], f"{where}/VISIBILITY ({at})")
            weight = _load(w_da[ts, bs], f"{where}/WEIGHT ({at})")
            flag = _load(f_da[ts, bs], f"{where}/FLAG ({at})")
            uvw = _load(uvw_da[ts, bs], f"{where}/UVW ({at})")
            centroid = _load(centroid_da[ts, bs], f"{where}/TIME_CENTROID ({at})") \
                if centroid_da is not None else None
            exposure = _load(exposure_da[ts, bs], f"{where}/EFFECTIVE_INTEGRATION_TIME ({at})") \
                if exposure_da is not None else None
            ti, bi = np.nonzero(~padding_mask(vis, weight, flag))
            n = ti.size
            if bar is not None:
                bar.update(1)
            if n == 0:
                del vis, weight, flag, uvw, centroid, exposure
                continue
            r0 = tab.nrows()
            tab.addrows(n)
            t_abs = times[ts][ti]
            tab.putcol("TIME", t_abs, startrow=r0, nrow=n)
            tab.putcol("TIME_CENTROID", centroid[ti, bi] if centroid is not None else t_abs,
                       startrow=r0, nrow=n)
            tab.putcol("INTERVAL", np.full(n, interval), startrow=r0, nrow=n)
            tab.putcol("EXPOSURE", exposure[ti, bi] if exposure is not None else np.full(n, interval),
                       startrow=r0, nrow=n)
            tab.putcol("ANTENNA1", a1_all[bs][bi], startrow=r0, nrow=n)
            tab.putcol("ANTENNA2", a2_all[bs][bi], startrow=r0, nrow=n)
            tab.putcol("SCAN_NUMBER", scans[ts][ti], startrow=r0, nrow=n)
            tab.putcol("FIELD_ID", np.full(n, field_id, dtype=np.int32), startrow=r0, nrow=n)
            tab.putcol("DATA_DESC_ID", np.full(n, ddid, dtype=np.int32), startrow=r0, nrow=n)
            zeros = np.zeros(n, dtype=np.int32)
            for col in ("FEED1", "FEED2", "ARRAY_ID", "OBSERVATION_ID", "PROCESSOR_ID"):
                tab.putcol(col, zeros, startrow=r0, nrow=n)
            # the one STATE row (an on-source target observation), as CASA's simulator writes
            # it: a STATE_ID of -1 beside a STATE row crashes CASA (see xstack.io._mswrite)
            tab.putcol("STATE_ID", np.zeros(n, dtype=np.int32), startrow=r0, nrow=n)
            tab.putcol("UVW", uvw[ti, bi], startrow=r0, nrow=n)
            # big columns in batches, so the gathered copies stay small
            batch = max(1, WRITE_BATCH_BYTES // max(1, nchan * npol * vis.itemsize))
            for k in range(0, n, batch):
                tk, bk = ti[k:k + batch], bi[k:k + batch]
                m, rk = tk.size, r0 + k
                tab.putcol("DATA", vis[tk, bk], startrow=rk, nrow=m)
                fl = flag[tk, bk]
                tab.putcol("FLAG", fl, startrow=rk, nrow=m)
                tab.putcol("FLAG_ROW", np.all(fl, axis=(1, 2)), startrow=rk, nrow=m)
                ws = weight[tk, bk]
                tab.putcol("WEIGHT_SPECTRUM", ws, startrow=rk, nrow=m)
                wrow = ws.mean(axis=1, dtype=np.float64).astype(np.float32)
                tab.putcol("WEIGHT", wrow, startrow=rk, nrow=m)
                with np.errstate(divide="ignore"):
                    sigma = np.where(wrow > 0, 1.0 / np.sqrt(np.maximum(wrow, 1e-30)), _FLOAT32_MAX)
                tab.putcol("SIGMA", sigma.astype(np.float32), startrow=rk, nrow=m)
            written += n
            # free this chunk before the next one is decoded (halves the peak memory)
            del vis, weight, flag, uvw, centroid, exposure, fl, ws, wrow, sigma
    return written


def export_ms(
    store: str | os.PathLike,
    out_ms: str | os.PathLike,
    *,
    overwrite: bool = False,
    progress: bool = False,
) -> Path:
    """Write an xstack store as a MeasurementSet that CASA reads (listobs, tclean).

    Parameters
    ----------
    store
        An xstack ``.zarr`` store (converted, simulated or stacked).
    out_ms
        Output MeasurementSet directory; written under a temporary name and renamed.
    overwrite
        Replace an existing ``out_ms``.
    progress
        Progress bar on stderr.

    Returns
    -------
    pathlib.Path
        ``out_ms``.

    Notes
    -----
    The main table gets DATA (VISIBILITY), FLAG, FLAG_ROW (all channels and polarizations
    flagged), WEIGHT_SPECTRUM (WEIGHT), WEIGHT (its mean over channels), SIGMA
    (1/sqrt(WEIGHT)), UVW, TIME, TIME_CENTROID, INTERVAL, EXPOSURE, ANTENNA1/2, FIELD_ID,
    DATA_DESC_ID, SCAN_NUMBER and STATE_ID (0: the one STATE row, intent
    ``OBSERVE_TARGET#ON_SOURCE``), with tiled storage managers for the array columns. The
    subtables ANTENNA, FEED (one row per antenna), FIELD, OBSERVATION, POLARIZATION,
    SPECTRAL_WINDOW, DATA_DESCRIPTION, SOURCE (with REST_FREQUENCY, SYSVEL and TRANSITION,
    NUM_LINES = 0), PROCESSOR, STATE and HISTORY are filled; POINTING and FLAG_CMD are empty
    (a store does not record where the antennas pointed). The structure is that of the MSs
    CASA 6.7 writes where CASA relies on it (``docs/io.md``). Phase centers are written as
    J2000 (= ICRS here). Padding cells of irregular grids are not written.

    Raises
    ------
    XstackError
        If ``store`` is not a complete xstack store, a chunk of it cannot be decoded, or
        ``out_ms`` exists without ``overwrite``; nothing is written then.
    """
    import casacore.tables as pt

    from xstack import __version__

    check_output(out_ms, overwrite)
    tree = open_store(store)
    parts = list(iter_partitions(tree))
    meta = _metadata(parts, str(store))
    complex128 = any(ds["VISIBILITY"].dtype == np.complex128 for _, ds in parts)
    shapes = []
    for sid, pid in meta["ddids"]:
        shapes.append((meta["spws"][sid][0].size, len(meta["pols"][pid])))
    first_spw = meta["spws"][min(meta["spws"])]
    spw_rows = [{"chan_freq": f, "chan_width": w, "name": n, "meas_freq_ref": ref}
                for (f, w, n), ref in zip(_fill_gaps(meta["spws"], (*first_spw[:2], "unused")),
                                          _fill_gaps(meta["spw_frames"], 5))]
    first_field = meta["fields"][min(meta["fields"])]
    field_rows = [{"name": n, "phase_center": c}
                  for n, c in _fill_gaps(meta["fields"], ("unused", first_field[1]))]
    telescope = str(parts[0][1].attrs.get("telescope_name", "unknown"))
    n_blocks = sum((len(_chunk_edges(ds["VISIBILITY"].data, 0)) - 1)
                   * (len(_chunk_edges(ds["VISIBILITY"].data, 1)) - 1) for _, ds in parts)

    with atomic_output(out_ms, overwrite=overwrite) as tmp:
        tab = create_ms(tmp, shapes, data_columns=("DATA",), complex128=complex128,
                        weight_spectrum=True)
        # casacore's tile caches otherwise grow with the number of rows written
        for col in ("DATA", "FLAG", "WEIGHT_SPECTRUM", "WEIGHT", "SIGMA", "UVW"):
            tab.setmaxcachesize(col, TILE_CACHE_BYTES)
        bar = progress_iter(range(n_blocks), f"export {Path(out_ms).name}", enabled=progress) \
            if progress else None
        try:
            for (name, ds), (ddid, fid) in zip(parts, meta["part_ids"]):
                _write_partition(tab, ds, ddid, fid, bar, f"{store}/{name}")
            tab.flush()
        finally:
            tab.close()
            if bar is not None:
                bar.close()
        write_subtables(
            tmp, antenna_names=meta["antenna_names"], antenna_positions=meta["positions"],
            dish_diameters=meta["dish"], telescope_name=telescope, fields=field_rows,
            spws=spw_rows, pol_setups=meta["pols"], data_descriptions=meta["ddids"],
            time_range=meta["time_range"], n_states=1,
            history=f"xstack {__version__} export_ms from "
                    f"{store if is_url(store) else Path(store).resolve()}")
        # a quick self-check: the MS reopens and has its rows (catches casacore surprises)
        with pt.table(str(tmp), ack=False) as check:
            check.nrows()
    return Path(out_ms)
