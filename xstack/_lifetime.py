"""Temporary stores that live exactly as long as the lazy objects reading them.

A lazy dask array reads its chunks when it is computed, which may be long after the function
that opened the store returned. A temporary store (e.g. the conversion of a MeasurementSet
that ``xstack.stack_uv`` reads) must therefore not be deleted while any lazy object built on it
exists. :func:`tie_lifetime` makes every dask-backed variable depend on an owner object that
holds the temporary directory: the directory is removed only when the last graph that could
read it is garbage-collected.
"""

from __future__ import annotations

import tempfile
from typing import Any

import dask.array as da
import xarray as xr


class TemporaryStoreOwner:
    """Owns a temporary directory; removed when the last reference to this object goes.

    Pickled copies (dask.distributed ships task arguments to workers) carry only the path and
    never delete anything: the directory belongs to the process that made it.
    """

    def __init__(self, prefix: str = "xstack-") -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix=prefix)
        self.path = self._tmp.name

    def __reduce__(self) -> tuple[Any, ...]:
        return (_PathOnly, (self.path,))

    def __dask_tokenize__(self) -> str:
        return f"xstack-temporary-store:{self.path}"


class _PathOnly:
    """What a :class:`TemporaryStoreOwner` becomes when pickled: the path, no ownership."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __dask_tokenize__(self) -> str:
        return f"xstack-temporary-store:{self.path}"


def _passthrough(block: Any, owner: Any = None) -> Any:
    # ``owner`` is never used: being an argument of every task keeps it (and so the
    # temporary directory) alive as long as the graph is
    return block


def _tie_dataset(ds: xr.Dataset, owner: Any) -> xr.Dataset:
    updates = {}
    for name, var in ds.variables.items():
        if isinstance(var.data, da.Array):
            arr = var.data
            updates[name] = var.copy(data=da.map_blocks(_passthrough, arr, owner=owner,
                                                        dtype=arr.dtype, meta=arr._meta))
    if not updates:
        return ds
    data_vars = {k: v for k, v in updates.items() if k in ds.data_vars}
    coords = {k: v for k, v in updates.items() if k not in ds.data_vars}
    out = ds.assign(data_vars)
    return out.assign_coords(coords) if coords else out


def tie_lifetime(obj: xr.Dataset | xr.DataTree, owner: Any) -> xr.Dataset | xr.DataTree:
    """``obj`` with every dask-backed variable depending on ``owner`` (kept alive by them)."""
    if isinstance(obj, xr.DataTree):
        return obj.map_over_datasets(lambda ds: _tie_dataset(ds, owner))
    return _tie_dataset(obj, owner)
