"""Low-level MeasurementSet writing with python-casacore, shared by export and the test MSs.

Builds a main table whose big columns (DATA, FLAG, WEIGHT_SPECTRUM...) use tiled storage
managers, whose UVW column is labelled J2000 (``default_ms`` alone labels it ITRF, leaves
DATA out and FLAG/WEIGHT/SIGMA variable-shaped), and fills the subtables CASA needs
(ANTENNA, FEED, FIELD, OBSERVATION, POLARIZATION, SPECTRAL_WINDOW, DATA_DESCRIPTION,
PROCESSOR, STATE, SOURCE, HISTORY, POINTING). Nothing here knows about zarr or xarray.

What CASA needs beyond the MS definition was found by comparing with MSs that CASA 6.7 writes
itself (``simulator``) and running ``listobs``/``tclean`` on the results
(``tests/test_export_casa.py``, ``docs/io.md``):

* every STATE_ID of the main table is a row of STATE, or all are -1 and STATE is empty.
  CASA's ``MSMetaData`` (listobs, tclean's intent maps) indexes its state -> intent table
  with STATE_ID without a bounds check as soon as STATE has a row, so STATE_ID = -1 beside a
  STATE row reads past a vector: listobs then segfaults or aborts (``std::bad_alloc``) in
  some runs and not others.
* SOURCE has the optional columns REST_FREQUENCY, SYSVEL and TRANSITION that CASA writes,
  each cell defined with NUM_LINES elements (no line known: NUM_LINES = 0, empty cells).
* no array cell a CASA reader visits is left undefined (OBSERVATION LOG and SCHEDULE hold
  empty arrays).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np

#: Stokes enumeration of casacore (``Stokes::StokesTypes``): code -> correlation name.
STOKES_NAMES = {
    1: "I", 2: "Q", 3: "U", 4: "V",
    5: "RR", 6: "RL", 7: "LR", 8: "LL",
    9: "XX", 10: "XY", 11: "YX", 12: "YY",
    13: "RX", 14: "RY", 15: "LX", 16: "LY",
    17: "XR", 18: "XL", 19: "YR", 20: "YL",
    21: "PP", 22: "PQ", 23: "QP", 24: "QQ",
    25: "RCircular", 26: "LCircular", 27: "Linear", 28: "Ptotal",
    29: "Plinear", 30: "PFtotal", 31: "PFlinear", 32: "Pangle",
}
STOKES_CODES = {name: code for code, name in STOKES_NAMES.items()}

#: Target bytes of one tile of the big columns (casacore's usual choice is ~1 MB).
TILE_BYTES = 1024 * 1024

#: SOURCE columns that CASA writes although the MS definition makes them optional.
SOURCE_LINE_COLUMNS = ("REST_FREQUENCY", "SYSVEL", "TRANSITION")

#: OBS_MODE of the STATE rows written for the STATE_IDs of the main table.
DEFAULT_OBS_MODE = "OBSERVE_TARGET#ON_SOURCE"

#: Rows of STATE_ID read per call when :func:`write_subtables` looks for the ids in use.
_ID_SCAN_ROWS = 4 * 1024**2


def corr_products(pols: Sequence[str]) -> np.ndarray:
    """CORR_PRODUCT (ncorr, 2) receptor indices for correlation names like ``XX``, ``RL``."""
    out = np.zeros((len(pols), 2), dtype=np.int32)
    for k, p in enumerate(pols):
        if len(p) == 2 and p[0] in "RLXYPQ" and p[1] in "RLXYPQ":
            out[k] = [0 if p[0] in "RXP" else 1, 0 if p[1] in "RXP" else 1]
    return out


def feed_types(pols: Sequence[str]) -> list[str]:
    """The two receptor types (``["X", "Y"]`` or ``["R", "L"]``) of a correlation set."""
    letters = "".join(p for p in pols if len(p) == 2)
    if any(c in letters for c in "RL"):
        return ["R", "L"]
    if any(c in letters for c in "PQ"):
        return ["P", "Q"]
    return ["X", "Y"]


def _tile_rows(cell_bytes: int) -> int:
    return int(max(16, min(65536, TILE_BYTES // max(1, cell_bytes))))


def main_table_desc(cell_shapes: Sequence[tuple[int, int]], *, data_columns: Sequence[str] = ("DATA",),
                    complex128: bool = False, weight_spectrum: bool = True,
                    fixed_weight: bool = True) -> tuple[dict, dict]:
    """Table description and data-manager info of an MS main table.

    Parameters
    ----------
    cell_shapes
        (n_channels, n_correlations) of every data description. If they are all equal the
        big columns get a fixed cell shape and a ``TiledColumnStMan``; otherwise they are
        variable-shaped with a ``TiledShapeStMan`` (as CASA writes them).
    data_columns
        Visibility columns to create, e.g. ``("DATA", "CORRECTED_DATA")``.
    complex128
        Store visibilities as double-precision complex.
    weight_spectrum
        Add a WEIGHT_SPECTRUM column.
    fixed_weight
        Give WEIGHT and SIGMA a fixed shape (only possible if all correlation counts agree).
    """
    import casacore.tables as pt

    shapes = {tuple(int(x) for x in s) for s in cell_shapes}
    fixed = len(shapes) == 1
    nchan, ncorr = next(iter(shapes)) if fixed else (max(s[0] for s in shapes), max(s[1] for s in shapes))
    ncorrs = {s[1] for s in shapes}
    fixed_corr = fixed_weight and len(ncorrs) == 1

    desc = pt.required_ms_desc("MAIN")
    desc.pop("_define_hypercolumn_", None)
    desc["UVW"]["keywords"] = {"QuantumUnits": ["m", "m", "m"],
                               "MEASINFO": {"type": "uvw", "Ref": "J2000"}}
    dminfo: dict[str, Any] = {}
    seq = [0]

    def add_tiled(name: str, coldesc: dict, cell_bytes: int, nrowtile: int | None = None) -> None:
        seq[0] += 1
        rows = nrowtile or _tile_rows(cell_bytes)
        cell = [ncorr, nchan] if coldesc.get("ndim") == 2 else [ncorr]
        if (fixed if coldesc.get("ndim") == 2 else fixed_corr):
            # column shapes are C-ordered in python-casacore, tile shapes Fortran-ordered
            coldesc["shape"] = np.asarray([nchan, ncorr] if coldesc.get("ndim") == 2
                                          else [next(iter(ncorrs))], dtype=np.int32)
            coldesc["option"] = 5  # Direct | FixedShape
            dm = "TiledColumnStMan"
        else:
            coldesc.pop("shape", None)
            coldesc["option"] = 0
            dm = "TiledShapeStMan"
        coldesc["dataManagerType"] = dm
        coldesc["dataManagerGroup"] = f"Tiled{name}"
        tile = [*cell, rows] if coldesc.get("ndim") == 2 else [cell[0], rows]
        dminfo[f"*{seq[0]}"] = {"TYPE": dm, "NAME": f"Tiled{name}",
                                "SPEC": {"DEFAULTTILESHAPE": np.asarray(tile, dtype=np.int32)},
                                "COLUMNS": [name]}
        desc[name] = coldesc

    vis_type = "dcomplex" if complex128 else "complex"
    vis_bytes = ncorr * nchan * (16 if complex128 else 8)
    for col in data_columns:
        cd = pt.makearrcoldesc(col, 0j, ndim=2, valuetype=vis_type,
                               keywords={"UNIT": "Jy"})["desc"]
        add_tiled(col, cd, vis_bytes)
    add_tiled("FLAG", dict(desc["FLAG"], ndim=2), ncorr * nchan)
    if weight_spectrum:
        cd = pt.makearrcoldesc("WEIGHT_SPECTRUM", 0.0, ndim=2, valuetype="float")["desc"]
        add_tiled("WEIGHT_SPECTRUM", cd, ncorr * nchan * 4)
    add_tiled("WEIGHT", dict(desc["WEIGHT"], ndim=1), ncorr * 4, 4096)
    add_tiled("SIGMA", dict(desc["SIGMA"], ndim=1), ncorr * 4, 4096)
    # UVW: fixed [3] doubles, tiled like CASA does
    seq[0] += 1
    desc["UVW"]["dataManagerType"] = "TiledColumnStMan"
    desc["UVW"]["dataManagerGroup"] = "TiledUVW"
    dminfo[f"*{seq[0]}"] = {"TYPE": "TiledColumnStMan", "NAME": "TiledUVW",
                            "SPEC": {"DEFAULTTILESHAPE": np.asarray([3, 4096], dtype=np.int32)},
                            "COLUMNS": ["UVW"]}
    # FLAG_CATEGORY stays variable-shaped and is never written (cells undefined)
    return desc, dminfo


def create_ms(path: str | os.PathLike, cell_shapes: Sequence[tuple[int, int]], **kwargs: Any) -> Any:
    """Create an empty MS (main table + all required subtables); return the open main table.

    ``kwargs`` are passed to :func:`main_table_desc`.
    """
    import casacore.tables as pt

    desc, dminfo = main_table_desc(cell_shapes, **kwargs)
    tab = pt.default_ms(str(path), desc, dminfo)
    return tab


def _subtable(ms_path: str, name: str, extra_desc: dict | None = None) -> Any:
    """Open (creating it if the MS lacks it) a subtable for writing."""
    import casacore.tables as pt

    path = os.path.join(ms_path, name)
    if not os.path.exists(path):
        desc = pt.required_ms_desc(name)
        if extra_desc:
            desc.update(extra_desc)
        sub = pt.default_ms_subtable(name, path, desc, {})
        sub.close()
        with pt.table(ms_path, readonly=False, ack=False) as main:
            main.putkeyword(name, f"Table: {os.path.abspath(path)}")
    return pt.table(path, readonly=False, ack=False)


def used_state_ids(ms_path: str | os.PathLike) -> int:
    """Number of STATE rows the main table refers to: max(STATE_ID) + 1, 0 if all are -1.

    Read in slices of :data:`_ID_SCAN_ROWS` rows, so memory stays small for any MS.
    """
    import casacore.tables as pt

    top = -1
    with pt.table(str(ms_path), ack=False) as tab:
        n = tab.nrows()
        for r0 in range(0, n, _ID_SCAN_ROWS):
            ids = tab.getcol("STATE_ID", startrow=r0, nrow=min(_ID_SCAN_ROWS, n - r0))
            if ids.size:
                top = max(top, int(ids.max()))
    return top + 1


def _ensure_columns(tab: Any, table_type: str, names: Sequence[str]) -> None:
    """Add the optional MS columns ``names`` (casacore's standard descriptions) if missing."""
    import casacore.tables as pt

    full = pt.complete_ms_desc(table_type)
    for name in names:
        if name not in tab.colnames():
            tab.addcols(pt.maketabdesc([{"name": name, "desc": full[name]}]))


def _put(tab: Any, values: dict[str, Any]) -> None:
    for col, val in values.items():
        if col not in tab.colnames():
            continue
        if isinstance(val, (list, tuple)) or (isinstance(val, np.ndarray) and val.dtype.kind in "OUT"):
            val = [str(v) for v in val]
            tab.putcol(col, val)
        else:
            arr = np.asarray(val)
            tab.putcol(col, arr)


def write_subtables(
    ms_path: str | os.PathLike,
    *,
    antenna_names: Sequence[str],
    antenna_positions: np.ndarray,
    dish_diameters: np.ndarray,
    telescope_name: str,
    fields: Sequence[dict],
    spws: Sequence[dict],
    pol_setups: Sequence[Sequence[str]],
    data_descriptions: Sequence[tuple[int, int]],
    time_range: tuple[float, float],
    observer: str = "xstack",
    project: str = "xstack",
    stations: Sequence[str] | None = None,
    mounts: Sequence[str] | None = None,
    history: str | None = None,
    n_states: int | None = None,
    obs_mode: str = DEFAULT_OBS_MODE,
) -> None:
    """Fill the subtables of a freshly created MS.

    Call it after the main table's rows are written (unless ``n_states`` is given, the
    STATE rows are derived from the main table's STATE_IDs).

    Parameters
    ----------
    fields
        One dict per field: ``name`` and ``phase_center`` (ra, dec) radians J2000/ICRS, and
        optionally ``code``.
    spws
        One dict per spectral window: ``chan_freq`` and ``chan_width`` (Hz), optionally
        ``name``, ``ref_frequency``, ``meas_freq_ref`` (default 5 = TOPO... see casacore).
    pol_setups
        Correlation names of every POLARIZATION row.
    data_descriptions
        (spectral window id, polarization id) of every DATA_DESCRIPTION row.
    time_range
        (start, end) of the observation, MJD seconds.
    history
        Message of the one HISTORY row (none if ``None``).
    n_states
        Number of STATE rows; ``None``: max(STATE_ID) + 1 of the main table, i.e. none when
        every STATE_ID is -1. CASA crashes on a STATE_ID that is not a STATE row while
        STATE has rows, so the two must agree.
    obs_mode
        OBS_MODE (scan intent) of the STATE rows.
    """
    import casacore.tables as pt

    ms_path = str(ms_path)
    nant = len(antenna_names)
    t0, t1 = float(time_range[0]), float(time_range[1])
    tmid = 0.5 * (t0 + t1)

    with pt.table(os.path.join(ms_path, "ANTENNA"), readonly=False, ack=False) as tab:
        tab.addrows(nant)
        _put(tab, {
            "NAME": list(antenna_names),
            "STATION": list(stations) if stations is not None else list(antenna_names),
            "TYPE": ["GROUND-BASED"] * nant,
            "MOUNT": list(mounts) if mounts is not None else ["ALT-AZ"] * nant,
            "POSITION": np.asarray(antenna_positions, dtype=np.float64).reshape(nant, 3),
            "OFFSET": np.zeros((nant, 3)),
            "DISH_DIAMETER": np.asarray(dish_diameters, dtype=np.float64),
            "FLAG_ROW": np.zeros(nant, dtype=bool),
        })

    receptors = feed_types(pol_setups[0]) if pol_setups else ["X", "Y"]
    with pt.table(os.path.join(ms_path, "FEED"), readonly=False, ack=False) as tab:
        tab.addrows(nant)
        _put(tab, {
            "ANTENNA_ID": np.arange(nant, dtype=np.int32),
            "FEED_ID": np.zeros(nant, dtype=np.int32),
            "SPECTRAL_WINDOW_ID": np.full(nant, -1, dtype=np.int32),
            "TIME": np.full(nant, tmid),
            "INTERVAL": np.full(nant, t1 - t0 if t1 > t0 else 0.0),
            "NUM_RECEPTORS": np.full(nant, 2, dtype=np.int32),
            "BEAM_ID": np.full(nant, -1, dtype=np.int32),
            "BEAM_OFFSET": np.zeros((nant, 2, 2)),
            "POL_RESPONSE": np.tile(np.eye(2, dtype=np.complex64), (nant, 1, 1)),
            "POSITION": np.zeros((nant, 3)),
            "RECEPTOR_ANGLE": np.tile(np.array([0.0, np.pi / 2]), (nant, 1)),
        })
        for k in range(nant):
            tab.putcell("POLARIZATION_TYPE", k, list(receptors))

    nf = len(fields)
    with pt.table(os.path.join(ms_path, "FIELD"), readonly=False, ack=False) as tab:
        tab.addrows(nf)
        dirs = np.array([[list(map(float, f["phase_center"]))] for f in fields], dtype=np.float64)
        _put(tab, {
            "NAME": [str(f["name"]) for f in fields],
            "CODE": [str(f.get("code", "")) for f in fields],
            "TIME": np.full(nf, tmid),
            "NUM_POLY": np.zeros(nf, dtype=np.int32),
            "DELAY_DIR": dirs, "PHASE_DIR": dirs, "REFERENCE_DIR": dirs,
            "SOURCE_ID": np.arange(nf, dtype=np.int32),
            "FLAG_ROW": np.zeros(nf, dtype=bool),
        })

    with pt.table(os.path.join(ms_path, "SPECTRAL_WINDOW"), readonly=False, ack=False) as tab:
        tab.addrows(len(spws))
        for k, spw in enumerate(spws):
            freq = np.asarray(spw["chan_freq"], dtype=np.float64)
            width = np.asarray(spw["chan_width"], dtype=np.float64)
            total = float(np.sum(np.abs(width)))
            tab.putcell("CHAN_FREQ", k, freq)
            tab.putcell("CHAN_WIDTH", k, width)
            tab.putcell("EFFECTIVE_BW", k, np.abs(width))
            tab.putcell("RESOLUTION", k, np.abs(width))
            tab.putcell("NUM_CHAN", k, int(freq.size))
            tab.putcell("REF_FREQUENCY", k, float(spw.get("ref_frequency", freq[0])))
            tab.putcell("TOTAL_BANDWIDTH", k, total)
            tab.putcell("MEAS_FREQ_REF", k, int(spw.get("meas_freq_ref", 5)))
            tab.putcell("NAME", k, str(spw.get("name", f"SPW{k}")))
            tab.putcell("NET_SIDEBAND", k, 1)
            tab.putcell("FREQ_GROUP", k, 0)
            tab.putcell("FREQ_GROUP_NAME", k, "")
            tab.putcell("IF_CONV_CHAIN", k, 0)
            tab.putcell("FLAG_ROW", k, False)

    with pt.table(os.path.join(ms_path, "POLARIZATION"), readonly=False, ack=False) as tab:
        tab.addrows(len(pol_setups))
        for k, pols in enumerate(pol_setups):
            codes = np.array([STOKES_CODES[str(p)] for p in pols], dtype=np.int32)
            tab.putcell("CORR_TYPE", k, codes)
            tab.putcell("CORR_PRODUCT", k, corr_products(pols))
            tab.putcell("NUM_CORR", k, len(pols))
            tab.putcell("FLAG_ROW", k, False)

    with pt.table(os.path.join(ms_path, "DATA_DESCRIPTION"), readonly=False, ack=False) as tab:
        tab.addrows(len(data_descriptions))
        _put(tab, {
            "SPECTRAL_WINDOW_ID": np.array([d[0] for d in data_descriptions], dtype=np.int32),
            "POLARIZATION_ID": np.array([d[1] for d in data_descriptions], dtype=np.int32),
            "FLAG_ROW": np.zeros(len(data_descriptions), dtype=bool),
        })

    with pt.table(os.path.join(ms_path, "OBSERVATION"), readonly=False, ack=False) as tab:
        tab.addrows(1)
        tab.putcell("TELESCOPE_NAME", 0, str(telescope_name))
        tab.putcell("TIME_RANGE", 0, np.array([t0, t1]))
        tab.putcell("OBSERVER", 0, observer)
        tab.putcell("PROJECT", 0, project)
        tab.putcell("SCHEDULE_TYPE", 0, "")
        # defined (empty) rather than undefined cells: nothing to trip over for a reader
        tab.putcell("LOG", 0, np.array([], dtype=str))
        tab.putcell("SCHEDULE", 0, np.array([], dtype=str))
        tab.putcell("RELEASE_DATE", 0, t0)
        tab.putcell("FLAG_ROW", 0, False)

    with pt.table(os.path.join(ms_path, "PROCESSOR"), readonly=False, ack=False) as tab:
        tab.addrows(1)
        tab.putcell("TYPE", 0, "CORRELATOR")
        tab.putcell("SUB_TYPE", 0, "")
        tab.putcell("TYPE_ID", 0, -1)
        tab.putcell("MODE_ID", 0, -1)
        tab.putcell("FLAG_ROW", 0, False)

    nstate = used_state_ids(ms_path) if n_states is None else int(n_states)
    with pt.table(os.path.join(ms_path, "STATE"), readonly=False, ack=False) as tab:
        if nstate > 0:
            tab.addrows(nstate)
            _put(tab, {
                "SIG": np.ones(nstate, dtype=bool),
                "REF": np.zeros(nstate, dtype=bool),
                "CAL": np.zeros(nstate),
                "LOAD": np.zeros(nstate),
                "SUB_SCAN": np.zeros(nstate, dtype=np.int32),
                "OBS_MODE": [str(obs_mode)] * nstate,
                "FLAG_ROW": np.zeros(nstate, dtype=bool),
            })

    # SOURCE is optional in the MS definition but CASA tasks (listobs, tclean) look for it
    with _subtable(ms_path, "SOURCE") as tab:
        _ensure_columns(tab, "SOURCE", SOURCE_LINE_COLUMNS)
        nspw = len(spws)
        tab.addrows(nf * nspw)
        row = 0
        for fid, f in enumerate(fields):
            for sid in range(nspw):
                tab.putcell("SOURCE_ID", row, fid)
                tab.putcell("TIME", row, tmid)
                tab.putcell("INTERVAL", row, t1 - t0 if t1 > t0 else 0.0)
                tab.putcell("SPECTRAL_WINDOW_ID", row, sid)
                tab.putcell("NUM_LINES", row, 0)
                tab.putcell("NAME", row, str(f["name"]))
                tab.putcell("CALIBRATION_GROUP", row, -1)
                tab.putcell("CODE", row, str(f.get("code", "")))
                tab.putcell("DIRECTION", row, np.asarray(f["phase_center"], dtype=np.float64))
                tab.putcell("PROPER_MOTION", row, np.zeros(2))
                # no spectral line known: NUM_LINES = 0 and defined, empty line cells
                tab.putcell("REST_FREQUENCY", row, np.zeros(0))
                tab.putcell("SYSVEL", row, np.zeros(0))
                tab.putcell("TRANSITION", row, np.array([], dtype=str))
                row += 1

    if history:
        with pt.table(os.path.join(ms_path, "HISTORY"), readonly=False, ack=False) as tab:
            tab.addrows(1)
            tab.putcell("TIME", 0, t0)
            tab.putcell("OBSERVATION_ID", 0, 0)
            tab.putcell("MESSAGE", 0, history)
            tab.putcell("PRIORITY", 0, "NORMAL")
            tab.putcell("ORIGIN", 0, "xstack")
            tab.putcell("OBJECT_ID", 0, 0)
            tab.putcell("APPLICATION", 0, "xstack")
            tab.putcell("CLI_COMMAND", 0, [history])
            tab.putcell("APP_PARAMS", 0, [""])
