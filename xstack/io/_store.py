"""Writing an xstack store region by region, with the atomic protocol of ``write_store``.

:func:`xstack.schema.write_store` computes dask-backed partitions itself. ``convert`` fills
its arrays from casacore sequentially instead (one reader, reused buffers), so it needs the
store created first and filled afterwards; :func:`region_store` does exactly what
``write_store`` does around that: same root attributes, temporary name via
:func:`xstack._atomic.atomic_output`, ``xstack_complete`` set last, rename at the end.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import xarray as xr

from xstack._atomic import atomic_output
from xstack.errors import XstackError
from xstack.schema import KINDS, SCHEMA_NAME, SCHEMA_VERSION, validate_partition


@contextlib.contextmanager
def region_store(
    partitions: Mapping[str, xr.Dataset],
    path: str | os.PathLike,
    *,
    kind: str = "processing_set",
    overwrite: bool = False,
    attrs: Mapping[str, Any] | None = None,
    encoding: Mapping[str, Mapping[str, Any]] | None = None,
) -> Iterator[Any]:
    """Create a store whose dask-backed variables are left for the caller to fill.

    Coordinates and numpy-backed variables are written at once; dask-backed variables
    (placeholders, never computed) only get their zarr arrays, chunked like the dask arrays.
    Inside the ``with`` block the caller writes them, chunk-aligned, through the yielded
    root :class:`zarr.Group` (``root[partition][variable][region] = values``). On a clean exit
    the completion flag is set and the store renamed into place; on an error or interruption
    nothing valid is left behind. ``encoding`` (variable -> zarr encoding, e.g.
    ``{"VISIBILITY": {"compressors": None}}``) applies to every partition.
    """
    import zarr

    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}")
    if not partitions:
        raise XstackError("nothing to write: no partitions")
    for name, ds in partitions.items():
        validate_partition(ds, name)
    with atomic_output(path, overwrite=overwrite) as tmp:
        root = zarr.open_group(str(tmp), mode="w", zarr_format=3)
        root.attrs.update({
            "xstack_schema": SCHEMA_NAME,
            "xstack_schema_version": SCHEMA_VERSION,
            "xstack_kind": kind,
            "xstack_complete": False,
            "partitions": sorted(partitions),
            **(dict(attrs) if attrs else {}),
        })
        for name, ds in partitions.items():
            enc = {k: dict(v) for k, v in (encoding or {}).items() if k in ds.variables}
            ds.drop_encoding().to_zarr(str(tmp), group=name, mode="w", zarr_format=3,
                                       consolidated=False, compute=False, encoding=enc)
        yield zarr.open_group(str(tmp), mode="r+", zarr_format=3)
        root = zarr.open_group(str(tmp), mode="r+", zarr_format=3)
        root.attrs["xstack_complete"] = True
    return Path(path)
