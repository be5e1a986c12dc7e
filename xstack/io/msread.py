"""Reading MeasurementSets with python-casacore: metadata, the row index and row blocks.

casacore is not thread-safe, so every table access in this module happens under one
process-wide lock (:data:`CASACORE_LOCK`); dask tasks that read an MS call
:func:`read_block`, which holds the lock only while casacore copies rows out and scatters
them into the (time, baseline) grid outside it.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from xstack.errors import XstackError
from xstack.io._mswrite import STOKES_NAMES

#: One lock for every casacore call in this process (casacore is not thread-safe).
CASACORE_LOCK = threading.RLock()

_OPEN_TABLES: dict[str, Any] = {}

#: Bytes of row data copied out of casacore per call (bounds the temporary buffers).
READ_BATCH_BYTES = 8 * 1024**2

#: casacore direction frames that are taken as ICRS (the ~20 mas J2000 frame bias ignored).
ICRS_LIKE = ("J2000", "ICRS")
#: casacore direction frames converted to ICRS with astropy.
ASTROPY_FRAMES = {"B1950": "fk4", "B1950_VLA": "fk4", "GALACTIC": "galactic"}


def _table(path: str) -> Any:
    """A cached read-only table (call with :data:`CASACORE_LOCK` held)."""
    import casacore.tables as pt

    tab = _OPEN_TABLES.get(path)
    if tab is None:
        tab = pt.table(path, readonly=True, ack=False)
        _OPEN_TABLES[path] = tab
    return tab


def close_tables(prefix: str | None = None) -> None:
    """Close cached tables (all, or those whose path starts with ``prefix``)."""
    with CASACORE_LOCK:
        for key in list(_OPEN_TABLES):
            if prefix is None or key.startswith(prefix):
                _OPEN_TABLES.pop(key).close()


def check_ms(path: str | os.PathLike) -> Path:
    """Raise :class:`XstackError` unless ``path`` is a readable MeasurementSet."""
    import casacore.tables as pt

    path = Path(path)
    if not path.exists():
        raise XstackError(f"{path}: no such MeasurementSet")
    if not path.is_dir() or not (path / "table.dat").is_file() or not pt.tableexists(str(path)):
        raise XstackError(f"{path}: not a MeasurementSet (not a casacore table)")
    with CASACORE_LOCK:
        try:
            tab = _table(str(path.resolve()))
        except RuntimeError as exc:
            raise XstackError(f"{path}: cannot be opened as a MeasurementSet ({exc})") from None
        missing = [c for c in ("TIME", "ANTENNA1", "ANTENNA2", "DATA_DESC_ID", "FIELD_ID", "UVW")
                   if c not in tab.colnames()]
        keywords = tab.getkeywords()
    if missing:
        raise XstackError(f"{path}: not a MeasurementSet (no column {missing[0]})")
    for sub in ("ANTENNA", "SPECTRAL_WINDOW", "POLARIZATION", "DATA_DESCRIPTION", "FIELD"):
        if sub not in keywords or not (path / sub).is_dir():
            raise XstackError(f"{path}: not a MeasurementSet (no {sub} subtable)")
    return path


@dataclass
class MSMeta:
    """Everything convert needs from the subtables of one MS."""

    path: str
    antenna_names: list[str]
    antenna_positions: np.ndarray
    dish_diameters: np.ndarray
    telescope_name: str
    field_names: list[str]
    phase_centers: np.ndarray  # (nfield, 2) radians ICRS
    phase_center_frame: str
    spw_freqs: list[np.ndarray]
    spw_widths: list[np.ndarray]
    spw_names: list[str]
    pol_names: list[list[str]]
    ddid_spw: np.ndarray
    ddid_pol: np.ndarray
    extra: dict[str, Any] = field(default_factory=dict)


def _unique_names(names: list[str], fallback: str = "ANT") -> list[str]:
    """Antenna names usable as a coordinate: empty names and duplicates made unique."""
    out, seen = [], set()
    for k, name in enumerate(names):
        name = str(name).strip() or f"{fallback}{k}"
        if name in seen:
            name = f"{name}_{k}"
        seen.add(name)
        out.append(name)
    return out


def _direction_frame(tab: Any, col: str, row: int) -> str:
    """casacore reference frame name of a direction cell (fixed or variable reference)."""
    info = tab.getcolkeywords(col).get("MEASINFO", {})
    if "VarRefCol" in info and info["VarRefCol"] in tab.colnames():
        code = int(tab.getcell(info["VarRefCol"], row))
        types, codes = list(info.get("TabRefTypes", [])), list(info.get("TabRefCodes", []))
        if code in codes:
            return str(types[codes.index(code)])
        return "J2000"
    return str(info.get("Ref", "J2000"))


def to_icrs(ra: float, dec: float, frame: str, where: str) -> tuple[float, float]:
    """Convert a direction in a casacore frame to ICRS radians (J2000 taken as ICRS)."""
    frame = frame.upper()
    if frame in ICRS_LIKE:
        return float(ra), float(dec)
    if frame not in ASTROPY_FRAMES:
        raise XstackError(f"{where}: phase center frame {frame} is not supported "
                          f"(use one of {', '.join((*ICRS_LIKE, *ASTROPY_FRAMES))})")
    from astropy import units as u
    from astropy.coordinates import SkyCoord

    c = SkyCoord(ra * u.rad, dec * u.rad, frame=ASTROPY_FRAMES[frame]).icrs
    return float(c.ra.to_value(u.rad)), float(c.dec.to_value(u.rad))


def read_meta(path: str | os.PathLike) -> MSMeta:
    """Read the subtables of an MS (antennas, fields, windows, polarizations, telescope)."""
    import casacore.tables as pt

    path = str(Path(path).resolve())
    where = path
    with CASACORE_LOCK:
        with pt.table(f"{path}/ANTENNA", ack=False) as ant:
            n_ant = ant.nrows()
            names = _unique_names(list(ant.getcol("NAME")) if n_ant else [])
            positions = ant.getcol("POSITION").reshape(n_ant, 3) if n_ant else np.zeros((0, 3))
            dish = ant.getcol("DISH_DIAMETER") if n_ant else np.zeros(0)
        telescope = "unknown"
        if os.path.isdir(f"{path}/OBSERVATION"):
            with pt.table(f"{path}/OBSERVATION", ack=False) as obs:
                if obs.nrows():
                    telescope = str(obs.getcell("TELESCOPE_NAME", 0)) or "unknown"
        with pt.table(f"{path}/FIELD", ack=False) as fld:
            nf = fld.nrows()
            fnames = [str(n) for n in fld.getcol("NAME")] if nf else []
            centers = np.zeros((nf, 2))
            frames = []
            for k in range(nf):
                pd = np.asarray(fld.getcell("PHASE_DIR", k), dtype=np.float64).reshape(-1, 2)
                frame = _direction_frame(fld, "PHASE_DIR", k)
                frames.append(frame)
                ra, dec = to_icrs(pd[0, 0], pd[0, 1], frame, f"{where} FIELD {k}")
                centers[k] = (np.mod(ra, 2 * np.pi), dec)  # RA in [0, 2 pi)
        with pt.table(f"{path}/SPECTRAL_WINDOW", ack=False) as spw:
            freqs = [np.asarray(spw.getcell("CHAN_FREQ", k), dtype=np.float64) for k in range(spw.nrows())]
            widths = [np.asarray(spw.getcell("CHAN_WIDTH", k), dtype=np.float64)
                      for k in range(spw.nrows())]
            snames = [str(spw.getcell("NAME", k)) for k in range(spw.nrows())]
        with pt.table(f"{path}/POLARIZATION", ack=False) as pol:
            pols = []
            for k in range(pol.nrows()):
                codes = np.asarray(pol.getcell("CORR_TYPE", k)).ravel()
                try:
                    pols.append([STOKES_NAMES[int(c)] for c in codes])
                except KeyError as exc:
                    raise XstackError(f"{where}: unknown correlation type {exc} in POLARIZATION "
                                      f"row {k}") from None
        with pt.table(f"{path}/DATA_DESCRIPTION", ack=False) as dd:
            ddid_spw = dd.getcol("SPECTRAL_WINDOW_ID") if dd.nrows() else np.zeros(0, int)
            ddid_pol = dd.getcol("POLARIZATION_ID") if dd.nrows() else np.zeros(0, int)
    return MSMeta(path=path, antenna_names=names, antenna_positions=np.asarray(positions, np.float64),
                  dish_diameters=np.asarray(dish, np.float64), telescope_name=telescope,
                  field_names=fnames, phase_centers=centers,
                  phase_center_frame=",".join(sorted(set(frames))) or "J2000",
                  spw_freqs=freqs, spw_widths=widths, spw_names=snames, pol_names=pols,
                  ddid_spw=np.asarray(ddid_spw), ddid_pol=np.asarray(ddid_pol))


def read_index(path: str, columns: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Read small per-row columns of the whole main table (a few bytes per row)."""
    with CASACORE_LOCK:
        tab = _table(path)
        out = {}
        for col in columns:
            if col in tab.colnames():
                out[col] = tab.getcol(col)
        return out


def cell_defined(path: str, column: str, row: int) -> bool:
    """Whether ``column`` exists and holds a value in ``row``."""
    with CASACORE_LOCK:
        tab = _table(path)
        if column not in tab.colnames():
            return False
        try:
            return bool(tab.iscelldefined(column, int(row)))
        except RuntimeError:
            return False


def column_info(path: str, column: str) -> dict[str, Any] | None:
    """Column description, or None if the main table lacks the column."""
    with CASACORE_LOCK:
        tab = _table(path)
        if column not in tab.colnames():
            return None
        return dict(tab.getcoldesc(column))


def _get_rows(tab: Any, rows: np.ndarray, columns: list[str]) -> dict[str, np.ndarray]:
    """Read ``columns`` for sorted row numbers ``rows`` (one call per column)."""
    r0, n = int(rows[0]), int(rows.size)
    if int(rows[-1]) - r0 + 1 == n:  # contiguous: plain range read, the fastest
        return {c: tab.getcol(c, startrow=r0, nrow=n) for c in columns}
    sel = tab.selectrows(rows.tolist())
    try:
        return {c: sel.getcol(c) for c in columns}
    finally:
        sel.close()


@dataclass(frozen=True)
class BlockSpec:
    """How to read one partition of an MS (shared by all its blocks)."""

    path: str
    data_column: str
    n_channels: int
    n_pols: int
    vis_dtype: str
    weight_source: str  # WEIGHT_SPECTRUM | WEIGHT | SIGMA | NONE
    flag_defined: bool
    has_flag_row: bool
    has_centroid: bool
    has_exposure: bool
    #: Subtracted from the MS's times (MJD seconds) in TIME_CENTROID: the store's time origin
    #: (:data:`xstack.msv4.UNIX_EPOCH_MJD_S` for MSv4's Unix seconds).
    time_origin: float = 0.0


BLOCK_VARS = ("VISIBILITY", "WEIGHT", "FLAG", "UVW", "TIME_CENTROID", "EFFECTIVE_INTEGRATION_TIME")


def block_buffers(spec: BlockSpec, n_time: int, n_baseline: int) -> dict[str, np.ndarray]:
    """Flat buffers big enough for one (n_time, n_baseline) block, reusable across blocks."""
    n = n_time * n_baseline
    m = n * spec.n_channels * spec.n_pols
    return {"VISIBILITY": np.empty(m, dtype=spec.vis_dtype), "WEIGHT": np.empty(m, dtype=np.float32),
            "FLAG": np.empty(m, dtype=bool), "UVW": np.empty(3 * n, dtype=np.float64),
            "TIME_CENTROID": np.empty(n, dtype=np.float64),
            "EFFECTIVE_INTEGRATION_TIME": np.empty(n, dtype=np.float64)}


def batch_rows(spec: BlockSpec) -> int:
    """Rows :func:`read_block` copies out of casacore per call (~:data:`READ_BATCH_BYTES`)."""
    cell_bytes = spec.n_channels * spec.n_pols * (np.dtype(spec.vis_dtype).itemsize + 5)
    return max(1, READ_BATCH_BYTES // cell_bytes)


def read_block(spec: BlockSpec, rows: np.ndarray, t_index: np.ndarray, b_index: np.ndarray,
               n_time: int, n_baseline: int, times: np.ndarray,
               buffers: dict[str, np.ndarray] | None = None,
               on_batch: Callable[[int, int], None] | None = None,
               vis_batch: Callable[[int, int], np.ndarray] | None = None,
               on_others: Callable[[], None] | None = None) -> dict[str, np.ndarray]:
    """Read MS rows into dense (time, baseline, ...) arrays of one block.

    Parameters
    ----------
    rows
        Sorted MS row numbers of the block.
    t_index, b_index
        Time and baseline position of every row inside the block.
    n_time, n_baseline
        Block shape; cells without a row stay padded (NaN visibility, zero weight, FLAG,
        zero UVW).
    times
        The block's time coordinate (TIME_CENTROID of padding cells).
    buffers
        Flat arrays from :func:`block_buffers` to fill (avoids allocating per block).
    on_batch
        Called as ``on_batch(start, stop)`` once cells ``start:stop`` (flat (time, baseline)
        cell numbers of the block) hold their final values in every returned array; cells
        are read in batches of ~:data:`READ_BATCH_BYTES`, so a caller can write them out
        while the next batch is read. Called only for batches whose rows land on
        consecutive cells (always the case when ``rows`` are consecutive and fill every cell
        in order); other cells are final only when the function returns.
    vis_batch
        With ``on_batch``: ``vis_batch(start, stop)`` returns the (stop - start, channel,
        polarization) array that the visibilities of such a batch are copied into instead of
        the block buffer (so a caller writing them out batch by batch needs no block-sized
        buffer for them); the returned VISIBILITY then lacks those cells.
    on_others
        With ``on_batch``, for a block whose consecutive rows fill every cell in order:
        every column but the visibilities is read first, then ``on_others()`` is called
        (every returned array but VISIBILITY is final), then the visibilities, batch by
        batch, each followed by ``on_batch`` - so a caller can compress the other arrays
        while the visibilities are still being read.

    Returns
    -------
    dict
        C-contiguous VISIBILITY, WEIGHT, FLAG (time, baseline, channel, polarization), UVW
        (time, baseline, 3), TIME_CENTROID and EFFECTIVE_INTEGRATION_TIME (time, baseline).
    """
    nc, npol = spec.n_channels, spec.n_pols
    buf = buffers if buffers is not None else block_buffers(spec, n_time, n_baseline)
    ncell = n_time * n_baseline
    shapes = {"VISIBILITY": (ncell, nc, npol), "WEIGHT": (ncell, nc, npol), "FLAG": (ncell, nc, npol),
              "UVW": (ncell, 3), "TIME_CENTROID": (ncell,), "EFFECTIVE_INTEGRATION_TIME": (ncell,)}
    # cell views: one row of the MS = one cell (time, baseline)
    cells = {k: buf[k][:int(np.prod(v))].reshape(v) for k, v in shapes.items()}
    vis, weight, flag, uvw = cells["VISIBILITY"], cells["WEIGHT"], cells["FLAG"], cells["UVW"]
    centroid, exposure = cells["TIME_CENTROID"], cells["EFFECTIVE_INTEGRATION_TIME"]
    cell_index = t_index.astype(np.int64) * n_baseline + b_index
    if rows.size < ncell:  # an irregular grid: pad the cells no row will fill
        vis[...] = complex(np.nan, np.nan)
        weight[...] = 0.0
        flag[...] = True
        uvw[...] = 0.0
        exposure[...] = 0.0
    centroid[...] = np.repeat(np.asarray(times, np.float64) - spec.time_origin, n_baseline)
    if not spec.has_exposure:
        exposure[...] = 0.0
    out = {"VISIBILITY": (n_time, n_baseline, nc, npol), "WEIGHT": (n_time, n_baseline, nc, npol),
           "FLAG": (n_time, n_baseline, nc, npol), "UVW": (n_time, n_baseline, 3),
           "TIME_CENTROID": (n_time, n_baseline), "EFFECTIVE_INTEGRATION_TIME": (n_time, n_baseline)}
    result = {k: cells[k].reshape(v) for k, v in out.items()}
    if rows.size == 0:
        return result

    small = ["FLAG_ROW"] if spec.has_flag_row else []
    if spec.weight_source in ("WEIGHT", "SIGMA"):
        small.append(spec.weight_source)
    if spec.has_centroid:
        small.append("TIME_CENTROID")
    if spec.has_exposure:
        small.append("EXPOSURE")
    big = [(spec.data_column, vis), ("UVW", uvw)]
    if spec.flag_defined:
        big.append(("FLAG", flag))
    if spec.weight_source == "WEIGHT_SPECTRUM":
        big.append(("WEIGHT_SPECTRUM", weight))
    batch = batch_rows(spec)
    # (columns, small columns, visibilities only?) of each pass over the rows
    passes: list[tuple[list[tuple[str, np.ndarray]], list[str], bool]] = [(big, small, False)]
    if on_others is not None and on_batch is not None and rows.size == ncell \
            and int(rows[-1]) - int(rows[0]) + 1 == ncell and bool(np.all(cell_index == np.arange(ncell))):
        passes = [(big[1:], small, False), (big[:1], [], True)]
    for cols, small_cols, vis_pass in passes:
        if vis_pass and on_others is not None:
            on_others()
        _read_pass(spec, rows, cell_index, batch, cols, small_cols, vis_pass, cells, on_batch, vis_batch)
    return result


def _read_pass(spec: BlockSpec, rows: np.ndarray, cell_index: np.ndarray, batch: int,
               big: list[tuple[str, np.ndarray]], small: list[str], vis_only: bool,
               cells: dict[str, np.ndarray], on_batch: Callable[[int, int], None] | None,
               vis_batch: Callable[[int, int], np.ndarray] | None) -> None:
    """One pass of :func:`read_block` over its rows, reading ``big`` and ``small`` columns."""
    nc, npol = spec.n_channels, spec.n_pols
    vis, weight, flag, uvw = cells["VISIBILITY"], cells["WEIGHT"], cells["FLAG"], cells["UVW"]
    centroid, exposure = cells["TIME_CENTROID"], cells["EFFECTIVE_INTEGRATION_TIME"]
    for k in range(0, rows.size, batch):
        r, c = rows[k:k + batch], cell_index[k:k + batch]
        n = r.size
        direct = (int(r[-1]) - int(r[0]) + 1 == n) and (int(c[-1]) - int(c[0]) + 1 == n) \
            and bool(np.all(np.diff(c) == 1))
        with CASACORE_LOCK:
            tab = _table(spec.path)
            try:
                if direct:
                    # rows map one-to-one onto consecutive cells: casacore writes in place
                    c0 = int(c[0])
                    for col, dest in big:
                        if dest is vis and vis_batch is not None and on_batch is not None:
                            out = vis_batch(c0, c0 + n)
                        else:
                            out = dest[c0:c0 + n]
                        tab.getcolnp(col, out, startrow=int(r[0]), nrow=n)
                    got = {col: tab.getcol(col, startrow=int(r[0]), nrow=n) for col in small}
                else:
                    got = _get_rows(tab, r, [col for col, _ in big] + small)
            except RuntimeError as exc:
                raise XstackError(f"{spec.path}: cannot read rows {int(r[0])}-{int(r[-1])} "
                                  f"({exc})") from None
        if vis_only:  # the second pass of a direct block (the other columns are done)
            if on_batch is not None:
                on_batch(int(c[0]), int(c[0]) + n)
            continue
        if direct:
            sl = slice(int(c[0]), int(c[0]) + n)
            if not spec.flag_defined:
                flag[sl] = False
            if spec.has_flag_row:
                fr = got["FLAG_ROW"].astype(bool)
                if fr.any():
                    flag[sl][fr] = True
        else:
            data = got[spec.data_column]
            if data.shape[1:] != (nc, npol):
                raise XstackError(f"{spec.path}: {spec.data_column} cells have shape {data.shape[1:]}, "
                                  f"expected ({nc}, {npol}) from the spectral window and polarization")
            vis[c] = data
            f = got["FLAG"].astype(bool, copy=False) if spec.flag_defined else np.zeros(data.shape, bool)
            if spec.has_flag_row:
                f = f | got["FLAG_ROW"].astype(bool)[:, None, None]
            flag[c] = f
            uvw[c] = got["UVW"]
            if spec.weight_source == "WEIGHT_SPECTRUM":
                weight[c] = got["WEIGHT_SPECTRUM"]
        if spec.weight_source == "WEIGHT":
            weight[c] = got["WEIGHT"][:, None, :]
        elif spec.weight_source == "SIGMA":
            sigma = got["SIGMA"].astype(np.float64)
            with np.errstate(divide="ignore", invalid="ignore"):
                w = np.where((sigma > 0) & np.isfinite(sigma), 1.0 / (sigma * sigma), 0.0)
            weight[c] = w[:, None, :].astype(np.float32)
        elif spec.weight_source == "NONE":
            weight[c] = 1.0
        if spec.has_centroid:
            centroid[c] = got["TIME_CENTROID"] - spec.time_origin
        if spec.has_exposure:
            exposure[c] = got["EXPOSURE"]
        if direct and on_batch is not None and any(dest is vis for _, dest in big):
            on_batch(int(c[0]), int(c[0]) + n)
