"""The xstack data model: zarr (v3) MSv4 processing sets opened as :class:`xarray.DataTree`.

One store holds one dataset. Its root group carries the schema attributes; each child group
is one *partition* (spectral window x field, and scan where needed). On disk a partition is
an MSv4 ``VisibilityXds`` with its ``antenna_xds`` and field-and-source children
(:mod:`xstack.msv4` translates); the stages see it as one :class:`xarray.Dataset`, the
*internal view*::

    VISIBILITY  (time, baseline_id, frequency, polarization)  complex64 | complex128, Jy
    WEIGHT      (time, baseline_id, frequency, polarization)  float32, 1/Jy^2
    FLAG        (time, baseline_id, frequency, polarization)  bool, True = do not use
    UVW         (time, baseline_id, uvw_label)                float64, metres
    ANTENNA_POSITION (antenna_name, cartesian_pos_label)      float64, ITRF metres
    DISH_DIAMETER    (antenna_name)                            float64, metres

The full description, with every attribute, is ``docs/schema.md``. This module is the single
place that builds (:func:`new_partition`), checks (:func:`validate_partition`,
:func:`validate_store`), writes (:func:`write_store`) and opens (:func:`open_store`) them.
Stores hold only numeric, boolean and UTF-8 string arrays and JSON attributes: nothing is
ever pickled, so opening a store from elsewhere runs no code.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from xstack._atomic import atomic_store
from xstack._fs import Location, locate, output_path
from xstack.errors import SchemaError, XstackError

SCHEMA_NAME = "xstack.processing_set"
#: Version of xstack's store layout. 2.x: MSv4 processing sets (:mod:`xstack.msv4`);
#: 1.x (xstack before 0.2): xstack's own layout, no longer read.
SCHEMA_VERSION = "2.0"
KINDS = ("processing_set", "stacked")

VIS_DIMS = ("time", "baseline_id", "frequency", "polarization")
UVW_DIMS = ("time", "baseline_id", "uvw_label")
ANTENNA_DIMS = ("antenna_name", "cartesian_pos_label")

#: Required attributes of every partition, with the JSON type each must have.
PARTITION_ATTRS: dict[str, type | tuple[type, ...]] = {
    "schema_version": str,
    "field_name": str,
    "field_id": int,
    "spectral_window_id": int,
    "phase_center": list,  # [ra, dec] in radians, ICRS
    "telescope_name": str,
}

STRING_DTYPE = np.dtypes.StringDType()

#: Target size of one (time x baseline_id) chunk of VISIBILITY, bytes.
DEFAULT_CHUNK_BYTES = 128 * 1024**2


def as_strings(values: Any) -> np.ndarray:
    """Return ``values`` as a numpy variable-length UTF-8 string array (never object)."""
    return np.asarray([str(v) for v in np.ravel(np.asarray(values, dtype=object))],
                      dtype=STRING_DTYPE).reshape(np.shape(values))


def partition_name(spectral_window_id: int, field_id: int, scan: int | None = None) -> str:
    """Name of the group that holds one partition, e.g. ``spw0_field2`` or ``spw0_field2_scan5``."""
    name = f"spw{int(spectral_window_id)}_field{int(field_id)}"
    return name if scan is None else f"{name}_scan{int(scan)}"


def baseline_pairs(n_antennas: int, autocorrelations: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Antenna index pairs (i < j, or i <= j with autocorrelations) in MS order."""
    i, j = np.triu_indices(n_antennas, k=0 if autocorrelations else 1)
    return i.astype(np.int32), j.astype(np.int32)


def default_time_chunk(n_baselines: int, n_channels: int, n_pols: int, itemsize: int = 8,
                       target_bytes: int = DEFAULT_CHUNK_BYTES) -> int:
    """Number of integrations per chunk so a VISIBILITY chunk holds ~``target_bytes``."""
    per_time = max(1, n_baselines * n_channels * n_pols * itemsize)
    return max(1, int(target_bytes // per_time))


def new_partition(
    *,
    visibility: Any,
    weight: Any,
    flag: Any,
    uvw: Any,
    time: Any,
    antenna1: Any,
    antenna2: Any,
    antenna_names: Any,
    antenna_positions: Any,
    dish_diameters: Any,
    frequency: Any,
    channel_width: Any,
    polarization: Any,
    phase_center: tuple[float, float],
    field_name: str = "field0",
    field_id: int = 0,
    spectral_window_id: int = 0,
    telescope_name: str = "unknown",
    integration_time: float | None = None,
    attrs: Mapping[str, Any] | None = None,
    frequency_frame: str | None = None,
) -> xr.Dataset:
    """Build one partition Dataset in the xstack schema from plain or dask arrays.

    Parameters
    ----------
    visibility, weight, flag
        Arrays of shape (time, baseline, channel, polarization): complex visibilities in Jy,
        weights in 1/Jy^2 (1/sigma^2), flags (True = bad).
    uvw
        Baseline coordinates, shape (time, baseline, 3), metres, as stored in an MS.
    time
        Integration mid-points, MJD seconds (UTC), as in an MS TIME column.
    antenna1, antenna2
        Antenna index (into ``antenna_names``) of each baseline.
    antenna_names, antenna_positions, dish_diameters
        Antenna table: names, ITRF positions (n, 3) in metres, dish diameters in metres.
    frequency, channel_width
        Channel center frequencies and widths, Hz.
    polarization
        Correlation names, e.g. ``["XX", "YY"]`` or ``["RR", "RL", "LR", "LL"]``.
    phase_center
        (ra, dec) of the phase center, radians, ICRS.
    attrs
        Extra JSON-serialisable attributes (provenance, stacking options...).
    frequency_frame
        The spectral frame of ``frequency`` (``"TOPO"``, ``"LSRK"``, ``"BARY"``...; see
        :mod:`xstack.frames`), kept as the coordinate's ``observer`` attribute; default: not
        said, which :func:`xstack.frames.frequency_frame` reads as TOPO.
    """
    antenna1 = np.asarray(antenna1, dtype=np.int32)
    antenna2 = np.asarray(antenna2, dtype=np.int32)
    names = as_strings(antenna_names)
    nbl = antenna1.size
    coords = {
        "time": ("time", np.asarray(time, dtype=np.float64),
                 {"units": "s", "scale": "utc", "format": "mjd_seconds",
                  **({"integration_time": float(integration_time)}
                     if integration_time is not None else {})}),
        "baseline_id": ("baseline_id", np.arange(nbl, dtype=np.int64)),
        "baseline_antenna1_id": ("baseline_id", antenna1),
        "baseline_antenna2_id": ("baseline_id", antenna2),
        "baseline_antenna1_name": ("baseline_id", names[antenna1] if nbl else as_strings([])),
        "baseline_antenna2_name": ("baseline_id", names[antenna2] if nbl else as_strings([])),
        "frequency": ("frequency", np.asarray(frequency, dtype=np.float64),
                      {"units": "Hz", **({} if frequency_frame is None
                                         else {"observer": _observer(frequency_frame)})}),
        "channel_width": ("frequency", np.asarray(channel_width, dtype=np.float64),
                          {"units": "Hz"}),
        "polarization": ("polarization", as_strings(polarization)),
        "uvw_label": ("uvw_label", as_strings(["u", "v", "w"])),
        "antenna_name": ("antenna_name", names),
        "cartesian_pos_label": ("cartesian_pos_label", as_strings(["x", "y", "z"])),
    }
    vis = visibility
    if np.dtype(getattr(vis, "dtype", np.complex64)) not in (np.complex64, np.complex128):
        vis = vis.astype(np.complex64)
    data_vars = {
        "VISIBILITY": (VIS_DIMS, vis, {"units": "Jy"}),
        "WEIGHT": (VIS_DIMS, weight.astype(np.float32) if weight.dtype != np.float32 else weight,
                   {"units": "Jy-2"}),
        "FLAG": (VIS_DIMS, flag.astype(bool) if flag.dtype != bool else flag),
        "UVW": (UVW_DIMS, uvw.astype(np.float64) if uvw.dtype != np.float64 else uvw,
                {"units": "m", "frame": "ICRS", "convention": "as stored in a MeasurementSet"}),
        "ANTENNA_POSITION": (ANTENNA_DIMS, np.asarray(antenna_positions, dtype=np.float64),
                             {"units": "m", "frame": "ITRF"}),
        "DISH_DIAMETER": ("antenna_name", np.asarray(dish_diameters, dtype=np.float64),
                          {"units": "m"}),
    }
    ds_attrs = {
        "schema_version": SCHEMA_VERSION,
        "field_name": str(field_name),
        "field_id": int(field_id),
        "spectral_window_id": int(spectral_window_id),
        "phase_center": [float(phase_center[0]), float(phase_center[1])],
        "phase_center_frame": "ICRS",
        "phase_center_units": "rad",
        "telescope_name": str(telescope_name),
    }
    if attrs:
        ds_attrs.update(attrs)
    ds = xr.Dataset(data_vars, coords=coords, attrs=ds_attrs)
    validate_partition(ds)
    return ds


def _observer(frame: str) -> str:
    """``frame`` as MSv4's ``observer`` attribute (xstack.frames imports nothing heavy)."""
    from xstack.frames import msv4_observer

    return msv4_observer(frame)


def _fail(where: str, what: str) -> None:
    raise SchemaError(f"{where}: {what}")


def validate_partition(ds: xr.Dataset, name: str = "partition") -> xr.Dataset:
    """Check that ``ds`` follows the xstack partition schema; return it unchanged.

    Only metadata (names, dims, dtypes, attributes, shapes) is checked: no data is read.

    Raises
    ------
    SchemaError
        Naming the first problem found.
    """
    if not isinstance(ds, xr.Dataset):
        _fail(name, f"expected an xarray.Dataset, got {type(ds).__name__}")
    for var, dims in (("VISIBILITY", VIS_DIMS), ("WEIGHT", VIS_DIMS), ("FLAG", VIS_DIMS),
                      ("UVW", UVW_DIMS)):
        if var not in ds.variables:
            _fail(name, f"missing variable {var}")
        if tuple(ds[var].dims) != dims:
            _fail(name, f"{var} has dims {tuple(ds[var].dims)}, expected {dims}")
    kinds = {"VISIBILITY": "c", "WEIGHT": "f", "FLAG": "b", "UVW": "f"}
    for var, kind in kinds.items():
        if ds[var].dtype.kind != kind:
            _fail(name, f"{var} has dtype {ds[var].dtype}, expected kind '{kind}'")
    if ds["UVW"].dtype != np.float64:
        _fail(name, f"UVW has dtype {ds['UVW'].dtype}, expected float64")
    if ds.sizes.get("uvw_label") != 3:
        _fail(name, "uvw_label must have length 3")
    for coord in ("time", "frequency", "polarization", "baseline_antenna1_id",
                  "baseline_antenna2_id", "channel_width"):
        if coord not in ds.coords:
            _fail(name, f"missing coordinate {coord}")
    for var in ds.variables.values():
        if var.dtype == object:
            _fail(name, "object arrays are not allowed in a store (use numeric or string dtypes)")
    for key, typ in PARTITION_ATTRS.items():
        if key not in ds.attrs:
            _fail(name, f"missing attribute {key!r}")
        if not isinstance(ds.attrs[key], typ):
            _fail(name, f"attribute {key!r} has type {type(ds.attrs[key]).__name__}")
    if len(ds.attrs["phase_center"]) != 2:
        _fail(name, "attribute 'phase_center' must be [ra, dec] in radians")
    major = str(ds.attrs["schema_version"]).split(".")[0]
    if major != SCHEMA_VERSION.split(".")[0]:
        _fail(name, f"schema version {ds.attrs['schema_version']} is not supported "
                    f"(this xstack reads {SCHEMA_VERSION})")
    return ds


def iter_partitions(tree: xr.DataTree, data_group: str | None = None
                    ) -> Iterator[tuple[str, xr.Dataset]]:
    """Yield ``(name, Dataset)`` for every partition of a store, as xstack's stages see it.

    MSv4 partitions (``type = "visibility"``: every store xstack writes, and those of other
    MSv4 writers such as xradio's converter) are translated to the internal view by
    :func:`xstack.msv4.decode_partition` (a partition with several fields over time becomes
    one per field); other groups holding ``VISIBILITY`` (trees built in memory from internal
    partitions) are yielded as they are. Partitions come in sorted name order, whatever
    order the store's directory listing gives, so that results (and anything seeded per
    partition) are reproducible.

    Parameters
    ----------
    tree
        The opened store.
    data_group
        MSv4 data group whose correlated data are ``VISIBILITY`` (``base``, ``corrected``...);
        default: ``base``, else each partition's first.
    """
    from xstack.msv4 import decode_partition, is_msv4_partition

    nodes = sorted((node for node in tree.subtree
                    if is_msv4_partition(node) or "VISIBILITY" in node.ds.variables),
                   key=lambda node: node.path)
    spw_names = sorted({str(node["frequency"].attrs.get("spectral_window_name", ""))
                        for node in nodes if is_msv4_partition(node)
                        and not isinstance(node.attrs.get("xstack"), Mapping)})
    spw_ids = {n: i for i, n in enumerate(spw_names)}
    for node in nodes:
        name = node.path.strip("/") or "/"
        if is_msv4_partition(node):
            yield from decode_partition(node, name, data_group=data_group,
                                        spectral_window_ids=spw_ids)
        else:
            yield name, node.to_dataset()


def _read_root_attrs(loc: Location) -> dict[str, Any]:
    """Read the root group's attributes as plain JSON (never through a codec)."""
    path = loc.name
    if loc.local and not (loc.local_path.is_dir() and (loc.local_path / "zarr.json").is_file()):
        raise SchemaError(f"{path}: not a zarr v3 store (no zarr.json)")
    try:
        doc = json.loads(loc.read_bytes("zarr.json"))
    except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
        raise SchemaError(f"{path}: not a zarr v3 store (no zarr.json)") from None
    except (OSError, ValueError) as exc:
        raise SchemaError(f"{path}: corrupt zarr.json ({exc})") from None
    if doc.get("node_type") != "group":
        raise SchemaError(f"{path}: zarr root is not a group")
    return doc.get("attributes", {}) or {}


#: Compress VISIBILITY? Visibilities are noise-like and shrink by only ~10 %, while compressing
#: 128 MB chunks costs more than reading them (benchmarks/bench_convert.py), so by default not.
COMPRESS_VISIBILITY = False


def store_encoding() -> dict[str, dict[str, Any]]:
    """zarr codecs of the big arrays of every store xstack writes (converted, simulated,
    stacked, subtracted): blosc-lz4 with byte shuffle (as small as zarr's default zstd at a
    fraction of its CPU time) for weights and UVW, bit shuffle for flags, and no compression
    for the visibilities unless :data:`COMPRESS_VISIBILITY` (zstd spent ~0.5 s of CPU per
    190 MB of a stacked type-6 store to save 10 %: benchmarks/bench_uvstack_cli.py)."""
    from zarr.codecs import BloscCodec

    fast = BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")
    return {"VISIBILITY": {"compressors": fast if COMPRESS_VISIBILITY else None},
            "WEIGHT": {"compressors": fast},
            "UVW": {"compressors": fast},
            "FLAG": {"compressors": BloscCodec(cname="lz4", clevel=5, shuffle="bitshuffle")}}


#: zarr codecs a store may use: plain byte layouts, checksums, compressors and UTF-8 strings.
#: None of them can run code on decoding; anything else (a pickle or other object codec, a
#: codec this xstack does not know) makes a store unsafe to open and is refused.
SAFE_CODECS = frozenset({"bytes", "transpose", "crc32c", "blosc", "zstd", "gzip", "vlen-utf8",
                         "sharding_indexed"})
#: zarr data types a store may use (numeric, boolean, strings, numpy times); never object.
SAFE_DATA_TYPES = frozenset({
    "bool", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64",
    "float16", "float32", "float64", "complex64", "complex128", "string",
    "fixed_length_utf32", "numpy.datetime64", "numpy.timedelta64"})


def _codec_names(codecs: Any, where: str) -> Iterator[str]:
    """Every codec name in a zarr v3 codec list, including those nested in sharding."""
    if not isinstance(codecs, list):
        raise SchemaError(f"{where}: malformed codec list")
    for codec in codecs:
        name = codec.get("name") if isinstance(codec, Mapping) else codec
        if not isinstance(name, str):
            raise SchemaError(f"{where}: malformed codec {codec!r}")
        yield name
        conf = codec.get("configuration", {}) if isinstance(codec, Mapping) else {}
        for key in ("codecs", "index_codecs"):
            if isinstance(conf, Mapping) and key in conf:
                yield from _codec_names(conf[key], where)


def check_array_metadata(path: str | os.PathLike | Location,
                         storage_options: Mapping[str, Any] | None = None) -> int:
    """Check every array of a store on disk uses only safe data types and codecs.

    Metadata are read as plain JSON before zarr or xarray see the store, so a store from
    elsewhere that asks for a pickle (or any unknown) codec, an object data type or zarr v2
    metadata is refused before anything could be decoded. Chunk directories are not listed.
    ``path`` may be a URL (:mod:`xstack._fs`): there the consolidated metadata of the root
    ``zarr.json`` are checked, which are what :func:`open_store` reads on a remote store (one
    request, not one per node); without them, one listing per group and the zarr.json files
    of its children fetched in one batch.

    Returns
    -------
    int
        The number of arrays checked.

    Raises
    ------
    SchemaError
        Naming the first offending array and what is wrong with it.
    """
    root = locate(path, storage_options)
    if not root.local:
        nodes = consolidated_nodes(root)
        if nodes is not None:
            base = root.name.rstrip("/")
            return sum(_check_node(f"{base}/{key}", meta) for key, meta in sorted(nodes.items()))
    n_arrays = 0
    todo = [""]  # groups to look into, relative to the root
    while todo:
        rel = todo.pop()
        group = root.join(rel) if rel else root
        entries = group.listdir()
        for v2 in (".zarray", ".zgroup", ".zattrs", ".zmetadata"):
            if any(name == v2 for name, _ in entries):
                raise SchemaError(f"{group.name}: zarr v2 metadata ({v2}) in a zarr v3 store")
        children = [name for name, is_dir in entries if is_dir]
        try:
            docs = group.read_many([f"{child}/zarr.json" for child in children])
        except OSError as exc:
            raise SchemaError(f"{group.name}: corrupt zarr.json ({exc})") from None
        for child in children:
            text = docs.get(f"{child}/zarr.json")
            if text is None:
                continue
            where = f"{root.name.rstrip('/')}/{rel + '/' if rel else ''}{child}"
            try:
                meta = json.loads(text)
            except ValueError as exc:
                raise SchemaError(f"{where}: corrupt zarr.json ({exc})") from None
            if _check_node(where, meta):
                n_arrays += 1
            else:
                todo.append(f"{rel}/{child}" if rel else child)
    return n_arrays


def _check_node(where: str, meta: Any) -> bool:
    """Check the metadata of one zarr node: True for a (safe) array, False for a group."""
    if not isinstance(meta, Mapping):
        raise SchemaError(f"{where}: corrupt zarr.json (not a JSON object)")
    if meta.get("node_type") == "group":
        return False
    if meta.get("node_type") != "array":
        raise SchemaError(f"{where}: unknown zarr node type {meta.get('node_type')!r}")
    dtype = meta.get("data_type")
    dname = dtype.get("name") if isinstance(dtype, Mapping) else dtype
    if dname not in SAFE_DATA_TYPES:
        raise SchemaError(f"{where}: data type {dname!r} is not allowed in an xstack "
                          "store (numeric, bool and string arrays only)")
    for name in _codec_names(meta.get("codecs", []), where):
        if name not in SAFE_CODECS:
            raise SchemaError(f"{where}: codec {name!r} is not allowed in an xstack "
                              f"store (only {', '.join(sorted(SAFE_CODECS))})")
    return True


def consolidated_nodes(loc: Location) -> dict[str, Any] | None:
    """The consolidated metadata (node path -> zarr.json document) in a store's root
    ``zarr.json``, or None if it has none."""
    try:
        doc = json.loads(loc.read_bytes("zarr.json"))
    except (OSError, ValueError):
        return None
    cm = doc.get("consolidated_metadata") if isinstance(doc, Mapping) else None
    nodes = cm.get("metadata") if isinstance(cm, Mapping) else None
    return dict(nodes) if isinstance(nodes, Mapping) and nodes else None


def validate_store(path: str | os.PathLike | Location,
                   storage_options: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Check the root attributes of an xstack store on disk; return them.

    A store left behind by an interrupted write never validates: the ``xstack_complete``
    flag is written last, and stores are renamed into place only after that. Every array's
    metadata is checked too (:func:`check_array_metadata`): only safe codecs and data types,
    so a store that passes can be opened and read without running any code. ``path`` may be
    a URL (:mod:`xstack._fs`); on object stores, which have no rename, the flag is the
    store's very last write.
    """
    loc = locate(path, storage_options)
    path = loc.name
    if not loc.exists():
        raise XstackError(f"{path}: no such store")
    attrs = _read_root_attrs(loc)
    if attrs.get("xstack_schema") != SCHEMA_NAME:
        if attrs.get("type") == "processing_set":
            # an MSv4 processing set of another writer (xradio's converter): its partitions
            # are checked as they are read (xstack.msv4.decode_partition)
            check_array_metadata(loc)
            return {**attrs, "xstack_kind": "processing_set", "xstack_foreign": True}
        raise SchemaError(f"{path}: neither an xstack store nor an MSv4 processing set (no "
                          "xstack_schema or type attribute)")
    if not attrs.get("xstack_complete", False):
        raise SchemaError(f"{path}: incomplete store (an interrupted write?)")
    version = str(attrs.get("xstack_schema_version", ""))
    if version.split(".")[0] != SCHEMA_VERSION.split(".")[0]:
        raise SchemaError(f"{path}: written in xstack's store layout {version!r}, which this "
                          f"xstack no longer reads (it reads {SCHEMA_VERSION}, MSv4 processing "
                          "sets): convert the MeasurementSet again (or simulate again)")
    if attrs.get("xstack_kind") not in KINDS:
        raise SchemaError(f"{path}: unknown store kind {attrs.get('xstack_kind')!r}")
    check_array_metadata(loc)
    return attrs


class DamagedChunkError(SchemaError):
    """A chunk of a store that cannot be read or decoded (a damaged store)."""


def _describe_chunk(array: Any, key: Any) -> tuple[str, str]:
    """Where a dask block of a store lies, as far as the (xarray-wrapped) zarr array behind it
    tells: ``("STORE/PARTITION/VAR (time 0:10, baseline_id 21:42)", "c/0/1/0/0")`` (the
    time and baseline_id ranges, other dimensions where the block does not span them whole;
    the chunk file, when the block is one chunk on disk)."""
    inner = array
    for _ in range(8):  # xarray's lazy-indexing wrappers around the backend array
        if not hasattr(inner, "array"):
            break
        inner = inner.array
    zarr_array = getattr(inner, "_array", None)
    where = str(getattr(zarr_array, "store_path", "") or "a store").removeprefix("file://")
    slices = key if isinstance(key, tuple) else (key,)
    if not all(isinstance(s, slice) for s in slices):
        return f"{where} {key!r}", ""
    dims = getattr(getattr(zarr_array, "metadata", None), "dimension_names", None) or ()
    disk = getattr(zarr_array, "chunks", None) or ()
    shape = getattr(zarr_array, "shape", None) or ()
    ranges, index = [], []
    for i, s in enumerate(slices):
        name = dims[i] if i < len(dims) and dims[i] else f"axis {i}"
        start = s.start or 0
        stop = s.stop if s.stop is not None else (shape[i] if i < len(shape) else start)
        whole = i < len(shape) and start == 0 and stop == shape[i]
        if name in ("time", "baseline_id") or not whole:
            ranges.append(f"{name} {start}:{stop}")
        if i < len(disk) and disk[i] and start % disk[i] == 0 and stop - start <= disk[i]:
            index.append(str(start // disk[i]))
    chunk = "c/" + "/".join(index) if slices and len(index) == len(slices) else ""
    return (f"{where} ({', '.join(ranges)})" if ranges else where), chunk


#: xarray's wrappers around a zarr array that leave its values as they are
_IDENTITY_WRAPPERS = ("ImplicitToExplicitIndexingAdapter", "CopyOnWriteArray")


def _read_raw_chunk(array: Any, key: Any) -> np.ndarray | None:
    """The block ``key`` read straight from its chunk file, or None to let zarr read it.

    For a chunk of a local zarr v3 array with a plain codec chain (``bytes``, optionally
    ``zstd`` or ``blosc``: what xstack writes; :class:`xstack.io._store.ChunkFiles`) the file
    is read (raw) or decompressed straight into the block's own array, so a read holds the
    block once, plus the compressed bytes. zarr's path holds it about three times (the file's
    bytes, the decoded chunk, the output it is copied into): most of a uv-stack's memory per
    chunk. Only when xarray leaves the values alone (no decoding wrapper, no pending index)
    and ``key`` lies in one chunk; anything else (other codecs, sharding, remote stores, a
    damaged file) goes to zarr.
    """
    inner = array
    for _ in range(8):
        kind = type(inner).__name__
        if kind in _IDENTITY_WRAPPERS:
            inner = inner.array
        elif kind == "LazilyIndexedArray":
            if any(k != slice(None) for k in inner.key.tuple):
                return None
            inner = inner.array
        else:
            break
    zarr_array = getattr(inner, "_array", None) if type(inner).__name__ == "ZarrArrayWrapper" \
        else None
    slices = key if isinstance(key, tuple) else (key,)
    if zarr_array is None or len(slices) != zarr_array.ndim or \
            not all(isinstance(k, slice) and k.step in (None, 1) for k in slices):
        return None
    from xstack.io._store import ChunkFiles

    files = ChunkFiles.for_array(zarr_array)
    if files is None:
        return None
    coords, region = [], []
    for k, size, chunk in zip(slices, zarr_array.shape, files.chunk_shape, strict=True):
        start, stop = k.start or 0, size if k.stop is None else k.stop
        if start % chunk or not 0 < stop - start <= chunk or stop > size:
            return None
        coords.append(start // chunk)
        region.append(slice(0, stop - start))
    block = np.empty(files.chunk_shape, dtype=files.dtype)
    if not files.read_into(tuple(coords), block):
        return None  # a damaged chunk file: zarr's read reports it
    region = tuple(region)
    if all(r.stop == c for r, c in zip(region, files.chunk_shape)):
        return block
    # an edge chunk: the array's part of it (a copy when the view would not be contiguous)
    return np.ascontiguousarray(block[region])


def read_chunk(array: Any, key: Any, asarray: bool = True, lock: Any = None) -> Any:
    """Read one block of a store-backed dask array (the ``getitem`` of :func:`open_store`).

    Raises
    ------
    DamagedChunkError
        If the chunk cannot be read or decoded (a damaged store): one line naming the store,
        the variable and the chunk, instead of whatever the codec raised.
    """
    from dask.array.core import getter

    try:
        direct = _read_raw_chunk(array, key)
        if direct is not None:
            return direct
        return getter(array, key, asarray=asarray, lock=lock)
    except (MemoryError, KeyboardInterrupt, XstackError):
        raise
    except Exception as exc:
        where, chunk = _describe_chunk(array, key)
        text = " ".join(f"{type(exc).__name__}: {exc}".split())
        raise DamagedChunkError(f"{where}: cannot be read, the store is damaged ("
                                + (f"chunk file {chunk}; " if chunk else "") + f"{text})") from None


def open_store(path: str | os.PathLike, chunks: Mapping[str, int] | None = None,
               data_group: str | None = None, *,
               storage_options: Mapping[str, Any] | None = None) -> xr.DataTree:
    """Open an xstack store or any MSv4 processing set lazily (dask-backed) as an
    :class:`xarray.DataTree`.

    Parameters
    ----------
    path
        The ``.zarr`` directory written by ``xstack convert``, ``simulate``, ``uvstack``...,
        or an MSv4 processing set written by another tool (xradio's converter): a local path
        or any fsspec URL (``file://``, ``memory://``, ``s3://``...).
    chunks
        Optional dask chunks per dimension; default: the chunks on disk.
    data_group
        MSv4 data group checked here (see :func:`iter_partitions`).
    storage_options
        Options of a URL's filesystem (:func:`xstack._fs.locate`), e.g.
        ``{"endpoint_url": ..., "anon": True}`` for ``s3://``.

    Returns
    -------
    xarray.DataTree
        One child per partition in xstack's internal view (:mod:`xstack.msv4`: the antenna
        table, phase center and times as the stages use them), root attributes as stored.

    Raises
    ------
    SchemaError
        If the path is not a complete xstack store of a supported schema version, or a
        partition does not follow the schema.
    """
    loc = locate(path, storage_options)
    path = loc.name
    validate_store(loc)
    try:
        # every chunk is read through read_chunk: a chunk that does not decode becomes one
        # XstackError naming the store, variable and chunk, wherever it is computed
        # the metadata of every node, not the consolidated copy at the root (written for
        # other readers, e.g. xradio): it is what check_array_metadata has just read, and a
        # store damaged since it was written shows here, not when a chunk is computed.
        # Remote stores excepted: there every node costs a request, and the consolidated
        # metadata are what check_array_metadata has just checked
        consolidated = not loc.local and consolidated_nodes(loc) is not None
        with quiet_zarr_warnings():
            tree = xr.open_datatree(loc.zarr_store(read_only=True), engine="zarr",
                                    chunks=dict(chunks or {}),
                                    consolidated=consolidated, zarr_format=3,
                                    from_array_kwargs={"getitem": read_chunk})
    except Exception as exc:  # zarr/xarray raise many types for damaged stores
        raise SchemaError(f"{path}: cannot be opened as a zarr store ({exc})") from None
    parts = {}
    for name, ds in iter_partitions(tree, data_group):
        parts[name] = validate_partition(ds, f"{path}/{name}")
    if not parts:
        raise SchemaError(f"{path}: store holds no partitions")
    # the stages' view: one node per partition as xstack.msv4 translates it (several per
    # MSv4 partition that holds several fields), the store's root attributes
    view = xr.DataTree.from_dict(parts)
    view.attrs = dict(tree.attrs)
    view.encoding = {"source": str(path)}
    return view


@contextlib.contextmanager
def quiet_zarr_warnings() -> Iterator[None]:
    """A context in which zarr's notes on what MSv4 stores use are silent: fixed-width
    unicode strings (``<U``, MSv4's strings) and consolidated metadata are "not in the zarr v3
    specification" yet; xradio writes and reads both, and so does xstack, on purpose."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"The data type \(FixedLengthUTF32")
        warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part")
        yield


def partition_nodes(partitions: Mapping[str, xr.Dataset]) -> dict[str, xr.Dataset]:
    """The zarr groups (path -> Dataset) of internal partitions written as MSv4: each
    partition's VisibilityXds first, then its child nodes (:func:`xstack.msv4.encode_partition`)."""
    from xstack import __version__
    from xstack.msv4 import encode_partition

    nodes: dict[str, xr.Dataset] = {}
    for name, ds in partitions.items():
        for sub, node in encode_partition(ds, creator_version=__version__).items():
            nodes[f"{name}/{sub}" if sub else name] = node
    return nodes


def finish_store(path: str | os.PathLike | Location,
                 storage_options: Mapping[str, Any] | None = None, *,
                 consolidated: bool = False) -> None:
    """Consolidate a store's metadata and mark it complete (the last step of every writer,
    before the rename into place of a local store).

    The completion flag is the very last write, after every chunk and the consolidated
    metadata: on an object store (no rename) the store is written under its final name, and
    a write interrupted before that one never opens (:func:`validate_store`). It rewrites the
    root ``zarr.json`` whole (one object), keeping the consolidated metadata in it. With
    ``consolidated`` the writer has consolidated them already (from metadata it built in
    memory: no walk over the store's nodes, one request per node on an object store).
    """
    import zarr

    store = locate(path, storage_options).zarr_store()
    with quiet_zarr_warnings():
        if not consolidated:
            zarr.consolidate_metadata(store, zarr_format=3)
        root = zarr.open_group(store, mode="r+", zarr_format=3, use_consolidated=True)
        root.attrs["xstack_complete"] = True


def write_skeleton(loc: Location, nodes: Mapping[str, xr.Dataset], root_attrs: Mapping[str, Any],
                   encoding: Mapping[str, Mapping[str, Any]] | None = None) -> None:
    """Create a store at ``loc`` (which must not exist) with every node's metadata, its
    numpy-backed variables written and its dask-backed ones (never computed) as empty zarr
    arrays chunked like the dask arrays, and the consolidated metadata.

    The skeleton (a few dozen small objects) is built in memory and then written out in one
    go: through a local store every object costs a round trip to zarr's I/O thread, on an
    object store several requests (xarray's ``mode="w"``), where one batch of puts does here.
    Writing chunks does not change the consolidated metadata, so they are final already.
    """
    import zarr

    skeleton: dict[str, Any] = {}
    memory = zarr.storage.MemoryStore(store_dict=skeleton)
    root = zarr.open_group(memory, mode="w", zarr_format=3)
    root.attrs.update(dict(root_attrs))
    with quiet_zarr_warnings():
        for name, ds in nodes.items():
            enc = {k: dict(v) for k, v in (encoding or {}).items() if k in ds.variables}
            ds.drop_encoding().to_zarr(memory, group=name, mode="w", zarr_format=3,
                                       consolidated=False, compute=False, encoding=enc)
        zarr.consolidate_metadata(memory, zarr_format=3)
    if loc.local:
        loc.local_path.mkdir()
    loc.write_many({key: value.to_bytes() for key, value in skeleton.items()})


def _store_lazy(root: Any, nodes: Mapping[str, xr.Dataset]) -> Any:
    """One delayed write of every dask-backed variable of ``nodes`` into the arrays that
    :func:`write_skeleton` created under ``root`` (opened from its consolidated metadata:
    no request per array, where xarray's ``to_zarr`` makes several on an object store).
    Each variable is encoded as xarray's ``to_zarr`` encodes it, so the chunks are the same."""
    import dask
    import dask.array as da
    from xarray.backends.zarr import encode_zarr_variable

    sources, targets = [], []
    for name, ds in nodes.items():
        for var, value in ds.drop_encoding().variables.items():
            if isinstance(value.data, da.Array):
                encoded = encode_zarr_variable(value, name=var, zarr_format=3)
                sources.append(encoded.data)
                targets.append(root[f"{name}/{var}"])
    # dask's store(compute=False) gives arrays, which a compute beside other arrays would
    # fuse with them: a task shared with another result (a stack's chunk and its flux sums)
    # then runs once for each. One Delayed of the store's chunks, its graph optimised now,
    # keeps it a task of its own, as xarray's to_zarr(compute=False) on a local disk.
    stored = da.store(sources, targets, lock=False, compute=False)
    stored = stored if isinstance(stored, (tuple, list)) else (stored,)
    parts = [d for a in stored for d in a.to_delayed(optimize_graph=True).ravel()]
    return dask.delayed(_all_stored, pure=True)(*parts)


def _all_stored(*_: Any) -> None:
    """The end of a store's chunk writes (:func:`_store_lazy`)."""
    return None


def new_store_attrs(partitions: Mapping[str, xr.Dataset], kind: str,
                    attrs: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Root attributes of a new, not yet complete store; validates what is to be written.

    Every writer of stores (:func:`write_store`, the converter) starts from these, and sets
    ``xstack_complete`` only once all data are in place.
    """
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}")
    if not partitions:
        raise XstackError("nothing to write: no partitions")
    for name, ds in partitions.items():
        validate_partition(ds, name)
    return {
        "type": "processing_set",
        "xstack_schema": SCHEMA_NAME,
        "xstack_schema_version": SCHEMA_VERSION,
        "xstack_kind": kind,
        "xstack_complete": False,
        "partitions": sorted(partitions),
        **(dict(attrs) if attrs else {}),
    }


def write_store(
    partitions: Mapping[str, xr.Dataset],
    path: str | os.PathLike,
    *,
    kind: str = "processing_set",
    overwrite: bool = False,
    attrs: Mapping[str, Any] | None = None,
    progress: bool = False,
    description: str = "writing",
    compute_with: Sequence[Any] = (),
    final_attrs: Callable[[tuple[Any, ...]], Mapping[str, Any]] | None = None,
    storage_options: Mapping[str, Any] | None = None,
) -> Path | str:
    """Write partitions to a new store, atomically.

    Data are written under a temporary name beside ``path``; the completion flag is set and
    the directory renamed into place only after everything has been written, so an
    interrupted run never leaves a store that opens as valid. Dask-backed partitions are
    computed chunk by chunk while writing (memory bounded by a few chunks).

    Parameters
    ----------
    partitions
        Mapping of group name (see :func:`partition_name`) to partition Dataset.
    path
        Output ``.zarr`` directory, or a URL (``s3://bucket/out.zarr``...): there, with no
        rename, the store is written in place and its completion flag last
        (:func:`finish_store`).
    kind
        ``"processing_set"`` or ``"stacked"``.
    overwrite
        Replace an existing output. Without it an existing ``path`` is an error.
    attrs
        Extra JSON-serialisable root attributes (provenance).
    progress
        Show a progress bar on stderr.
    compute_with
        Further dask collections computed in the same pass as the write, so that work they
        share with the written arrays (e.g. the phasors of a stack and its flux sums) is done
        once.
    final_attrs
        Called with the computed ``compute_with`` results; the root attributes it returns are
        stored before the store is marked complete.
    storage_options
        Options of a URL's filesystem (:func:`xstack._fs.locate`).

    Returns
    -------
    pathlib.Path or str
        ``path`` (the URL, for a remote store).
    """
    from concurrent.futures import ThreadPoolExecutor

    import dask

    from xstack._progress import dask_progress

    writer = StoreWrite(partitions, path, kind=kind, overwrite=overwrite, attrs=attrs,
                        storage_options=storage_options)
    try:
        # an own thread pool, shut down before a failure aborts the write: no task still
        # running may write into the temporary after it has been removed
        pool = ThreadPoolExecutor(dask.config.get("num_workers", None) or os.cpu_count() or 1)
        try:
            with dask_progress(description, enabled=progress), dask.config.set(pool=pool):
                results = dask.compute(*writer.graphs, *compute_with)
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
        extra = None if final_attrs is None else final_attrs(tuple(results[len(writer.graphs):]))
    except BaseException:
        writer.abort()
        raise
    return writer.finish(extra)


class StoreWrite:
    """A new store written in three steps: begin, the chunk writes, finish (or abort).

    :func:`write_store` is this class run at once; a lazy stage
    (``stack_uv(..., out=..., compute=False)``) keeps it open while its graph waits to be
    computed together with others. Creating it (*begin*) validates the partitions and makes
    the store's skeleton - every group, the root attributes with ``xstack_complete`` false
    and the numpy-backed variables - at a temporary name beside ``path`` (in place on an
    object store, :func:`xstack._atomic.atomic_store`); nothing of it opens as a store.

    Parameters
    ----------
    partitions, path, kind, overwrite, attrs, storage_options
        As :func:`write_store`. An existing ``path`` without ``overwrite`` is an
        :class:`~xstack.errors.OutputExistsError` here, before any work.

    Attributes
    ----------
    graphs : list
        Dask collections (one delayed per node on a local disk, one for all on an object
        store) that write every chunk of the dask-backed variables when computed; compute
        them once, then call :meth:`finish`.
    location : xstack._fs.Location
        Where the chunks go (the temporary of a local store).
    """

    def __init__(self, partitions: Mapping[str, xr.Dataset], path: str | os.PathLike, *,
                 kind: str = "processing_set", overwrite: bool = False,
                 attrs: Mapping[str, Any] | None = None,
                 storage_options: Mapping[str, Any] | None = None) -> None:
        import threading

        import zarr

        root_attrs = new_store_attrs(partitions, kind, attrs)
        self._path = path
        self._state = "open"
        self._lock = threading.Lock()
        # atomic_store's generator holds the protocol (temporary, rename, removal on error):
        # entered here, left by finish (normally) or abort (with an exception)
        self._atomic = atomic_store(path, overwrite=overwrite, storage_options=storage_options)
        self.location = loc = self._atomic.__enter__()
        try:
            tmp = loc.zarr_store()
            nodes = partition_nodes(partitions)
            encoding = store_encoding()
            if loc.local:
                root = zarr.open_group(tmp, mode="w", zarr_format=3)
                root.attrs.update(root_attrs)
            else:  # every array xarray creates costs several requests on an object store
                write_skeleton(loc, nodes, root_attrs, encoding)
            # stale encodings (chunks of a source store) must not override dask chunks; a
            # partition's own group is written before its children (mode "w" clears a group)
            with quiet_zarr_warnings():
                if loc.local:
                    self.graphs = [ds.drop_encoding().to_zarr(
                        tmp, group=name, mode="w", zarr_format=3, consolidated=False,
                        compute=False, encoding={k: dict(v) for k, v in encoding.items()
                                                 if k in ds.variables})
                        for name, ds in nodes.items()]
                else:
                    self.graphs = [_store_lazy(zarr.open_group(tmp, mode="r+", zarr_format=3,
                                                               use_consolidated=True), nodes)]
        except BaseException:
            self.abort()
            raise

    def __getstate__(self) -> dict[str, Any]:
        # a copy sent elsewhere (a distributed scheduler serialises the whole computation,
        # finishing function included) cannot finish or abort: only the process that began
        # the write holds its protocol
        return {**self.__dict__, "_lock": None, "_atomic": None}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)

    @property
    def name(self) -> str:
        """The output, for messages (its path or URL)."""
        return str(self._path)

    @property
    def state(self) -> str:
        """``"open"`` (chunks may be written), ``"finished"`` or ``"aborted"``."""
        return self._state

    def _close(self, state: str) -> bool:
        with self._lock:
            if self._state != "open":
                return False
            self._state = state
            return True

    def finish(self, attrs: Mapping[str, Any] | None = None) -> Path | str:
        """Once every chunk is written: store ``attrs`` (e.g. measured numbers) in the root,
        consolidate, set ``xstack_complete`` and rename into place. Returns the path (the
        URL of a remote store). Any failure aborts the write.

        Raises
        ------
        XstackError
            The write was finished or aborted already (a store is written once).
        """
        import zarr

        if self._atomic is None:  # a copy in another process (a cluster's worker)
            raise XstackError(f"{self._path}: a store is finished only in the process that "
                              "began writing it: compute a lazy result that writes a store "
                              "with xstack.compute() or its .compute() on a cluster, not "
                              "dask.compute()")
        if not self._close("finished"):
            raise XstackError(f"{self._path}: this store write is {self._state} already "
                              "(a store is written once)")
        loc = self.location
        try:
            # (quiet: a remote store's consolidated metadata are parsed and written again here)
            if attrs is not None:
                with quiet_zarr_warnings():
                    root = zarr.open_group(loc.zarr_store(), mode="r+", zarr_format=3)
                    root.attrs.update(dict(attrs))
            finish_store(loc, consolidated=not loc.local)
        except BaseException as exc:
            self._atomic.__exit__(type(exc), exc, exc.__traceback__)
            raise
        self._atomic.__exit__(None, None, None)
        return output_path(loc if not loc.local else self._path)

    def abort(self) -> None:
        """Remove what was written (the temporary; on an object store the store in place).
        Does nothing once finished or aborted, or in a copy in another process. Call it only
        when no chunk write still runs."""
        if self._atomic is None or not self._close("aborted"):
            return
        exc = XstackError(f"{self._path}: store write aborted")
        self._atomic.__exit__(XstackError, exc, None)

    def remove_leftovers(self) -> None:
        """After an abort: remove again what a chunk write still running then may have
        written since (a worker's task is not stopped by an error elsewhere)."""
        if self._atomic is not None and self._state == "aborted":
            with contextlib.suppress(Exception):
                self.location.remove()
