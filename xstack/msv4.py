"""xstack partitions on disk as MSv4 processing sets (xradio's schema 4.0), and back.

xstack's stages work on one *internal view* of a partition (built by
:func:`xstack.schema.new_partition`, checked by :func:`xstack.schema.validate_partition`):
an :class:`xarray.Dataset` with the visibilities, the antenna table
(``ANTENNA_POSITION``, ``DISH_DIAMETER`` on ``antenna_name``), baseline antenna ids, per-channel
``channel_width``, times in MJD seconds, one field whose phase center is the ``phase_center``
attribute, and padding cells flagged with weight 0.

On disk a store is an MSv4 processing set that xradio's ``open_processing_set`` opens and its
``check_datatree`` accepts. This module is the one place that translates:

* :func:`encode_partition`: internal view -> the nodes of one MSv4 partition: the
  ``VisibilityXds`` (times in Unix seconds, the schema's attributes, ``field_name`` and
  ``scan_name`` over time, fixed-width strings), its ``antenna_xds`` and
  ``field_and_source_base_xds`` children and, for a stacked store, the ``stack_positions``
  extension node. xstack's own attributes travel in the partition's ``xstack`` attribute.
* :func:`decode_partition`: one MSv4 partition node, written by xstack or by anyone else
  (xradio's converter), -> internal view(s): a partition with several fields over time (a
  mosaic) becomes one internal partition per field; the data group is chosen by name;
  MSv4 padding (NaN weight, flag unset) becomes xstack's (weight 0, flagged).

``docs/schema.md`` describes what xstack reads and writes.
"""

from __future__ import annotations

import datetime
from collections.abc import Mapping
from typing import Any

import numpy as np
import xarray as xr

from xstack.errors import SchemaError
from xstack.frames import frequency_frame, msv4_observer
from xstack.schema import SCHEMA_VERSION

#: The MSv4 schema version xstack writes (xradio 1.3.0's ``VisibilityXds``).
MSV4_SCHEMA_VERSION = "4.0.1"

#: Unix time 0 (1970-01-01, MJD 40587) in MJD seconds: MSv4 times are Unix seconds, MS and
#: xstack's internal times MJD seconds. Subtracting it from an MJD time and adding it back is
#: exact in float64 (the difference has no bits below the MJD time's last one).
UNIX_EPOCH_MJD_S = 40587.0 * 86400.0

#: Name of the child node of a stacked partition holding the stacking positions (an MSv4
#: extension: ``type = "extension:stack_positions.xstack"``).
STACK_NODE = "stack_positions"
STACK_NODE_TYPE = "extension:stack_positions.xstack"

#: Data group of a partition xstack writes.
BASE_GROUP = "base"

#: Internal variables and coordinates that live in ``antenna_xds`` on disk.
_ANTENNA_VARS = ("ANTENNA_POSITION", "DISH_DIAMETER")
_ANTENNA_COORDS = ("antenna_name", "cartesian_pos_label")


def fixed_strings(values: Any) -> np.ndarray:
    """``values`` as a numpy fixed-width unicode (``<U``) array, as MSv4 stores strings."""
    arr = np.asarray(values, dtype=object)
    flat = [str(v) for v in arr.ravel()]
    width = max((len(s) for s in flat), default=1) or 1
    return np.asarray(flat, dtype=f"<U{width}").reshape(arr.shape)


def _quantity(value: float, units: str, kind: str = "quantity", **extra: Any) -> dict[str, Any]:
    """An MSv4 scalar quantity attribute (an xarray DataArray as a dict)."""
    return {"data": float(value), "dims": [], "attrs": {"units": units, "type": kind, **extra}}


def _now() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat()


def _receptors(polarization: np.ndarray) -> list[str]:
    """Feed receptor types from the correlation names (``XX`` -> X, Y; ``RR`` -> R, L)."""
    letters = sorted({c for p in polarization for c in str(p)})
    if set(letters) <= {"R", "L"}:
        return ["R", "L"]
    return ["X", "Y"]


def encode_partition(ds: xr.Dataset, *, creator_version: str) -> dict[str, xr.Dataset]:
    """The MSv4 nodes of one internal partition, by path relative to the partition.

    Returns ``{"": VisibilityXds, "antenna_xds": ..., "field_and_source_base_xds": ...}`` and
    ``"stack_positions"`` when ``ds`` holds stacking positions. Lazy variables stay lazy
    (TIME_CENTROID is shifted to Unix seconds by a dask operation).
    """
    attrs = dict(ds.attrs)
    stack_vars = [v for v in ds.data_vars if "stack_position" in ds[v].dims]
    stack_coords = [c for c in ds.coords if "stack_position" in ds[c].dims]
    main = ds.drop_vars([*_ANTENNA_VARS, *_ANTENNA_COORDS, *stack_vars, *stack_coords],
                        errors="ignore")
    nt = ds.sizes["time"]
    time_attrs = {"type": "time", "units": "s", "scale": "utc", "format": "unix"}
    integration = ds["time"].attrs.get("integration_time")
    if integration is not None:
        time_attrs["integration_time"] = _quantity(integration, "s")
    freq = np.asarray(ds["frequency"].values, dtype=np.float64)
    width = np.asarray(ds["channel_width"].values, dtype=np.float64)
    spw_name = str(attrs.get("spectral_window_name", f"spw{attrs['spectral_window_id']}"))
    # the frame the channel frequencies are in, in xradio's spelling (absent: TOPO)
    observer = msv4_observer(frequency_frame(ds))
    freq_attrs = {
        "type": "spectral_coord", "units": "Hz", "observer": observer,
        "spectral_window_name": spw_name, "spectral_window_intents": ["UNSPECIFIED"],
        "reference_frequency": _quantity(freq[0] if freq.size else 0.0, "Hz", "spectral_coord",
                                         observer=observer),
        "channel_width": _quantity(float(np.median(width)) if width.size else 0.0, "Hz"),
    }
    field = str(attrs["field_name"])
    scans = (ds["scan_number"].values if "scan_number" in ds.coords
             else np.full(nt, attrs.get("scan_number", 0)))
    main = main.assign_coords(
        time=("time", np.asarray(ds["time"].values, np.float64) - UNIX_EPOCH_MJD_S, time_attrs),
        frequency=("frequency", freq, freq_attrs),
        channel_width=("frequency", width, {"type": "quantity", "units": "Hz"}),
        polarization=("polarization", fixed_strings(ds["polarization"].values)),
        uvw_label=("uvw_label", fixed_strings(ds["uvw_label"].values)),
        baseline_antenna1_name=("baseline_id", fixed_strings(ds["baseline_antenna1_name"].values)),
        baseline_antenna2_name=("baseline_id", fixed_strings(ds["baseline_antenna2_name"].values)),
        field_name=("time", fixed_strings(np.full(nt, field, dtype=object))),
        scan_name=("time", fixed_strings(scans), {"scan_intents": ["UNSPECIFIED"]}),
    )
    main["UVW"].attrs = {"type": "uvw", "units": "m", "frame": "icrs",
                         "convention": "as stored in a MeasurementSet"}
    main["VISIBILITY"].attrs = {"type": "quantity", "units": "Jy"}
    main["WEIGHT"].attrs = {"type": "quantity", "units": "Jy-2"}
    if "TIME_CENTROID" in main:
        main["TIME_CENTROID"] = main["TIME_CENTROID"] - UNIX_EPOCH_MJD_S
        main["TIME_CENTROID"].attrs = {"type": "time", "units": "s", "scale": "utc",
                                       "format": "unix"}
    if "EFFECTIVE_INTEGRATION_TIME" in main:
        main["EFFECTIVE_INTEGRATION_TIME"].attrs = {"type": "quantity", "units": "s"}
    now = _now()
    main.attrs = {
        "type": "visibility", "schema_version": MSV4_SCHEMA_VERSION,
        "creator": {"software_name": "xstack", "version": creator_version},
        "creation_date": now,
        "data_groups": {BASE_GROUP: {
            "correlated_data": "VISIBILITY", "flag": "FLAG", "weight": "WEIGHT", "uvw": "UVW",
            "field_and_source": "field_and_source_base_xds",
            "description": "visibilities written by xstack", "date": now}},
        "observation_info": {"observer": ["unknown"], "project_UID": "unknown",
                             "release_date": now},
        "processor_info": {"type": "CORRELATOR", "sub_type": ""},
        "xstack": attrs,
    }
    names = fixed_strings(ds["antenna_name"].values)
    telescope = str(attrs.get("telescope_name", "unknown"))
    receptors = _receptors(np.asarray(ds["polarization"].values))
    n_ant = names.size
    antenna = xr.Dataset(
        {"ANTENNA_POSITION": (("antenna_name", "cartesian_pos_label"),
                              np.asarray(ds["ANTENNA_POSITION"].values, np.float64),
                              {"type": "location", "units": "m", "frame": "ITRS",
                               "coordinate_system": "geocentric", "origin_object_name": "earth"}),
         "ANTENNA_DISH_DIAMETER": ("antenna_name", np.asarray(ds["DISH_DIAMETER"].values, np.float64),
                                   {"type": "quantity", "units": "m"})},
        coords={"antenna_name": names, "station_name": ("antenna_name", names),
                "mount": ("antenna_name", fixed_strings(["ALT-AZ"] * n_ant)),
                "telescope_name": ("antenna_name", fixed_strings([telescope] * n_ant)),
                "receptor_label": fixed_strings(["pol_0", "pol_1"]),
                "polarization_type": (("antenna_name", "receptor_label"),
                                      fixed_strings([receptors] * n_ant).reshape(n_ant, 2)),
                "cartesian_pos_label": fixed_strings(["x", "y", "z"])},
        attrs={"type": "antenna", "overall_telescope_name": telescope,
               "relocatable_antennas": False})
    frame = str(attrs.get("phase_center_frame", "ICRS")).lower()
    fields = xr.Dataset(
        {"FIELD_PHASE_CENTER_DIRECTION": (("field_name", "sky_dir_label"),
                                          np.asarray([attrs["phase_center"]], np.float64),
                                          {"type": "sky_coord", "units": "rad",
                                           "frame": frame if frame in ("icrs", "fk5") else "icrs"})},
        coords={"field_name": fixed_strings([field]),
                "source_name": ("field_name", fixed_strings([field])),
                "sky_dir_label": fixed_strings(["ra", "dec"])},
        attrs={"type": "field_and_source"})
    nodes = {"": main, "antenna_xds": antenna, "field_and_source_base_xds": fields}
    if stack_vars:
        ext = ds[stack_vars].drop_vars([c for c in ds.coords if c not in stack_coords
                                        and "stack_position" not in ds[c].dims],
                                       errors="ignore")
        for c in ext.coords:
            if ext[c].dtype.kind in "TUO":
                ext = ext.assign_coords({c: (ext[c].dims, fixed_strings(ext[c].values),
                                             ext[c].attrs)})
        for v in ext.data_vars:
            if ext[v].dtype.kind in "TUO":
                ext[v] = (ext[v].dims, fixed_strings(ext[v].values), ext[v].attrs)
        ext.attrs = {"type": STACK_NODE_TYPE, "schema_version": "1.0"}
        nodes[STACK_NODE] = ext
    for path, node in nodes.items():
        nodes[path] = _fixed_string_coords(node)
    return nodes


def _fixed_string_coords(ds: xr.Dataset) -> xr.Dataset:
    """Every string coordinate of ``ds`` as ``<U`` (variable-length strings are not MSv4's)."""
    out = {c: (ds[c].dims, fixed_strings(ds[c].values), ds[c].attrs)
           for c in ds.coords if ds[c].dtype.kind in "TO"}
    return ds.assign_coords(out) if out else ds


# ------------------------------------------------------------------------------ reading

def _child(node: xr.DataTree, name: str | None, kind: str) -> xr.Dataset | None:
    """The child dataset named ``name``, else the first child whose ``type`` is ``kind``."""
    # inherit=False: a child node sees its parent's coordinates (time, frequency...) too
    if name and name in node.children:
        return node.children[name].to_dataset(inherit=False)
    for child in node.children.values():
        if child.attrs.get("type") == kind:
            return child.to_dataset(inherit=False)
    return None


def _data_group(attrs: Mapping[str, Any], data_group: str | None, where: str) -> dict[str, Any]:
    groups = attrs.get("data_groups") or {}
    if not isinstance(groups, Mapping) or not groups:
        return {"correlated_data": "VISIBILITY", "flag": "FLAG", "weight": "WEIGHT", "uvw": "UVW"}
    if data_group is None:
        data_group = BASE_GROUP if BASE_GROUP in groups else next(iter(groups))
    if data_group not in groups:
        raise SchemaError(f"{where}: no data group {data_group!r} (has {', '.join(groups)})")
    return dict(groups[data_group])


def _to_mjd(var: xr.DataArray) -> xr.DataArray:
    """A time variable in MJD seconds, from the formats MSv4 allows that xstack reads."""
    fmt = str(var.attrs.get("format", "unix")).lower()
    if fmt == "unix":
        return var + UNIX_EPOCH_MJD_S
    if fmt == "mjd":
        return var * 86400.0
    if fmt == "mjd_seconds":
        return var
    raise SchemaError(f"time format {fmt!r} is not read by xstack (unix or mjd)")


def _scalar(value: Any) -> float | None:
    """A scalar from an MSv4 quantity attribute (dict with ``data``) or a plain number."""
    if isinstance(value, Mapping):
        value = value.get("data")
    if value is None:
        return None
    arr = np.asarray(value, dtype=np.float64).ravel()
    return float(arr[0]) if arr.size else None


#: Attributes of the internal view's variables (:func:`xstack.schema.new_partition`).
_INTERNAL_ATTRS: dict[str, dict[str, str]] = {
    "VISIBILITY": {"units": "Jy"},
    "WEIGHT": {"units": "Jy-2"},
    "UVW": {"units": "m", "frame": "ICRS", "convention": "as stored in a MeasurementSet"},
    "channel_width": {"units": "Hz"},
    "EFFECTIVE_INTEGRATION_TIME": {"units": "s"},
}


def is_msv4_partition(node: xr.DataTree) -> bool:
    """Whether ``node`` is an MSv4 visibility partition (``type = "visibility"``)."""
    return node.attrs.get("type") == "visibility" and "schema_version" in node.attrs \
        and str(node.attrs["schema_version"]).startswith("4.")


def decode_partition(node: xr.DataTree, name: str, *, data_group: str | None = None,
                     spectral_window_ids: Mapping[str, int] | None = None
                     ) -> list[tuple[str, xr.Dataset]]:
    """The internal view(s) of one MSv4 partition node.

    Parameters
    ----------
    node
        The partition's DataTree node (with its ``antenna_xds`` and field-and-source children).
    name
        The partition's name; a partition with several fields over time gives one internal
        partition per field, named ``{name}_{field}``.
    data_group
        The data group whose correlated data become ``VISIBILITY`` (e.g. ``"corrected"``);
        default ``base``, else the first the partition lists.
    spectral_window_ids
        Spectral window name -> id over the whole processing set (foreign stores carry names
        only).

    Raises
    ------
    SchemaError
        A required part is missing (no antenna table, no field table, an unknown time format).
    """
    ds = node.to_dataset()
    where = name
    own = isinstance(ds.attrs.get("xstack"), Mapping)
    group = _data_group(ds.attrs, data_group, where)
    renames = {}
    for role, internal in (("correlated_data", "VISIBILITY"), ("flag", "FLAG"),
                           ("weight", "WEIGHT"), ("uvw", "UVW")):
        actual = group.get(role, internal)
        if actual not in ds.variables:
            raise SchemaError(f"{where}: data group variable {actual!r} is missing")
        if actual != internal:
            renames[actual] = internal
    if renames:
        ds = ds.drop_vars([v for v in renames.values() if v in ds.variables])
        ds = ds.rename(renames)
    # antennas
    antenna = _child(node, "antenna_xds", "antenna")
    if antenna is None:
        raise SchemaError(f"{where}: no antenna_xds")
    names = np.asarray(antenna["antenna_name"].values).astype(str)
    dish_var = "ANTENNA_DISH_DIAMETER" if "ANTENNA_DISH_DIAMETER" in antenna else "DISH_DIAMETER"
    ds = ds.assign_coords(antenna_name=("antenna_name", names),
                          cartesian_pos_label=("cartesian_pos_label",
                                               np.asarray(["x", "y", "z"])))
    ds["ANTENNA_POSITION"] = (("antenna_name", "cartesian_pos_label"),
                              np.asarray(antenna["ANTENNA_POSITION"].values, np.float64),
                              {"units": "m", "frame": "ITRF"})
    dish = (np.asarray(antenna[dish_var].values, np.float64) if dish_var in antenna
            else np.full(names.size, np.nan))
    ds["DISH_DIAMETER"] = ("antenna_name", dish, {"units": "m"})
    if "baseline_antenna1_id" not in ds.coords:
        index = {n: i for i, n in enumerate(names)}
        ids = []
        for which in ("baseline_antenna1_name", "baseline_antenna2_name"):
            bl = np.asarray(ds[which].values).astype(str)
            missing = sorted(set(bl) - set(index))
            if missing:
                raise SchemaError(f"{where}: baseline antenna {missing[0]!r} is not in antenna_xds")
            ids.append(np.asarray([index[b] for b in bl], dtype=np.int32))
        ds = ds.assign_coords(baseline_antenna1_id=("baseline_id", ids[0]),
                              baseline_antenna2_id=("baseline_id", ids[1]))
    # times in MJD seconds
    time_attrs = dict(ds["time"].attrs)
    integration = _scalar(time_attrs.get("integration_time"))
    internal_time = {"units": "s", "scale": "utc", "format": "mjd_seconds"}
    if integration is not None:
        internal_time["integration_time"] = integration
    ds = ds.assign_coords(time=("time", np.asarray(_to_mjd(ds["time"]).values, np.float64),
                                internal_time))
    if "TIME_CENTROID" in ds:
        ds["TIME_CENTROID"] = _to_mjd(ds["TIME_CENTROID"]).assign_attrs(
            units="s", scale="utc", format="mjd_seconds")
    # channel widths
    freq_attrs = dict(ds["frequency"].attrs)
    if "channel_width" not in ds.coords:
        width = _scalar(freq_attrs.get("channel_width"))
        if "EFFECTIVE_CHANNEL_WIDTH" in ds.coords:
            widths = np.asarray(ds["EFFECTIVE_CHANNEL_WIDTH"].values, np.float64)
        else:
            widths = np.full(ds.sizes["frequency"], np.nan if width is None else width)
        ds = ds.assign_coords(channel_width=("frequency", widths, {"units": "Hz"}))
    # the internal view keeps the frame (xstack.frames.frequency_frame) in MSv4's spelling;
    # TOPO, the default, is left unsaid so that a partition written without a frame reads back
    # identical
    internal_freq = {"units": "Hz"}
    observer = str(freq_attrs.get("observer") or "").strip()
    if observer and observer.upper() != "TOPO":
        internal_freq["observer"] = observer
    ds = ds.assign_coords(frequency=("frequency", np.asarray(ds["frequency"].values, np.float64),
                                     internal_freq))
    # the internal attributes of the variables MSv4 describes in its own words
    for var, internal_attrs in _INTERNAL_ATTRS.items():
        if var in ds.variables:
            ds[var].attrs = dict(internal_attrs)
    scan_names = (np.asarray(ds["scan_name"].values).astype(str) if "scan_name" in ds.coords
                  else None)
    field_names = (np.asarray(ds["field_name"].values).astype(str)
                   if "field_name" in ds.coords and ds["field_name"].dims == ("time",) else None)
    ds = ds.drop_vars([c for c in ("scan_name", "field_name") if c in ds.coords])
    stack = _child(node, STACK_NODE, STACK_NODE_TYPE)
    if own:
        ds.attrs = dict(ds.attrs["xstack"])
        if stack is not None:
            # by variable, not by merge: the extension's coordinates are on its own
            # dimension, nothing to align
            ds = ds.assign_coords({c: stack[c].variable for c in stack.coords})
            ds = ds.assign({v: stack[v].variable for v in stack.data_vars})
        return [(name, ds)]
    # a store written by another MSv4 writer (xradio's converter)
    ds = _msv4_padding(ds)
    if scan_names is not None and "scan_number" not in ds.coords:
        ds = ds.assign_coords(scan_number=("time", _scan_numbers(scan_names)))
    fields_node = _child(node, group.get("field_and_source"), "field_and_source")
    if fields_node is None or "FIELD_PHASE_CENTER_DIRECTION" not in fields_node:
        raise SchemaError(f"{where}: no field_and_source_xds with FIELD_PHASE_CENTER_DIRECTION")
    table = [str(f) for f in np.asarray(fields_node["field_name"].values).ravel()]
    centers = np.asarray(fields_node["FIELD_PHASE_CENTER_DIRECTION"].values, np.float64)
    centers = centers.reshape(-1, centers.shape[-1])
    frame = str(fields_node["FIELD_PHASE_CENTER_DIRECTION"].attrs.get("frame", "icrs"))
    if field_names is None:
        field_names = np.full(ds.sizes["time"], table[0])
    telescope = str(antenna.attrs.get("overall_telescope_name", "unknown"))
    spw_name = str(freq_attrs.get("spectral_window_name", name))
    spw_id = int((spectral_window_ids or {}).get(spw_name, 0))
    base_attrs = {
        "spectral_window_id": spw_id, "spectral_window_name": spw_name,
        "telescope_name": telescope, "phase_center_frame": "ICRS",
        "phase_center_units": "rad", "source_phase_center_frame": frame.upper(),
        "msv4_partition": name, "msv4_creator": dict(ds.attrs.get("creator") or {}),
    }
    unique = list(dict.fromkeys(field_names.tolist()))
    out = []
    for field in unique:
        if field not in table:
            raise SchemaError(f"{where}: field {field!r} is not in the field_and_source table")
        fid = table.index(field)
        part = ds if len(unique) == 1 else ds.isel(time=np.flatnonzero(field_names == field))
        part = part.copy()
        part.attrs = {"schema_version": SCHEMA_VERSION, "field_name": field,
                      "field_id": fid, "phase_center": [float(centers[fid][0]),
                                                        float(centers[fid][1])],
                      **base_attrs}
        out.append((name if len(unique) == 1 else f"{name}_{field}", part))
    return out


def _scan_numbers(scan_names: np.ndarray) -> np.ndarray:
    """Integer scan numbers from MSv4 scan names (their numbers where numeric)."""
    try:
        return np.asarray([int(s) for s in scan_names], dtype=np.int32)
    except ValueError:
        _, inverse = np.unique(scan_names, return_inverse=True)
        return inverse.astype(np.int32)


def _msv4_padding(ds: xr.Dataset) -> xr.Dataset:
    """MSv4 padding (cells with no data: NaN weight, flag unset, NaN UVW) as xstack's
    (weight 0, flagged, UVW 0), lazily."""
    weight = ds["WEIGHT"]
    missing = weight.isnull()
    ds = ds.assign(WEIGHT=weight.where(~missing, 0.0).astype(weight.dtype).assign_attrs(weight.attrs),
                   FLAG=(ds["FLAG"] | missing).assign_attrs(ds["FLAG"].attrs))
    uvw = ds["UVW"]
    return ds.assign(UVW=uvw.where(uvw.notnull(), 0.0).assign_attrs(uvw.attrs))
