"""The one input normaliser for visibilities and the one positions type of every stage.

Every stage that reads visibilities (uvstack, image, subtract, fit, noise, the uv profile)
accepts the same kinds of input through :func:`partitions` (one data set) or
:func:`grouped_partitions` (several data sets, each with a label):

* a store path (``.zarr`` written by ``xstack convert``, ``simulate``, ``uvstack``...), or a
  store URL (``file://``, ``memory://``, ``s3://``...; :mod:`xstack._fs`: storage options
  given here, or set around the call with :func:`xstack.use_storage_options`);
* a MeasurementSet path (unless ``allow_ms=False``): converted lazily to a temporary store
  that lives exactly as long as some lazy object can still read it
  (:func:`xstack._lifetime.tie_lifetime`);
* an :class:`xarray.DataTree` (e.g. from :func:`xstack.open_store`);
* one partition as an :class:`xarray.Dataset`;
* a mapping of partition name to Dataset, or a list of ``(name, Dataset)`` pairs;
* an object with a ``stacked`` attribute holding one of these (e.g. a ``StackResult``).

Every stage that takes stacking positions builds a :class:`Positions` with
:meth:`Positions.from_any`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from xstack.errors import XstackError

#: The one message for an input that is no visibility data.
_KINDS = ("give a store path, a MeasurementSet path, an xarray DataTree or Dataset, "
          "or a dict or list of (name, Dataset) partitions")


def is_ms(path: str | os.PathLike) -> bool:
    """True if ``path`` is a MeasurementSet (a casacore table directory)."""
    from xstack._fs import is_remote, locate

    if is_remote(path):  # casacore reads local tables only
        return False
    path = Path(locate(path).path)
    return path.is_dir() and (path / "table.dat").exists()


def open_input(path: str | os.PathLike, *, allow_ms: bool = True,
               prefix: str = "xstack-input-",
               storage_options: Mapping[str, Any] | None = None) -> xr.DataTree:
    """Open a store path, or convert a MeasurementSet path lazily, as a DataTree.

    A MeasurementSet is converted into a temporary directory named ``<prefix>*``, said on
    the ``xstack`` logger (INFO; the command line prints it).

    Raises
    ------
    XstackError
        The path does not exist, is a MeasurementSet and ``allow_ms`` is false, or is no
        complete xstack store.
    """
    from xstack._fs import is_remote, locate
    from xstack._lifetime import TemporaryStoreOwner, tie_lifetime
    from xstack.schema import open_store

    if is_remote(path):
        return open_store(path, storage_options=storage_options)
    path = Path(locate(path).path)  # a file:// URL is its path
    if not path.exists():
        raise XstackError(f"{path}: no such store or MeasurementSet")
    if is_ms(path):
        if not allow_ms:
            raise XstackError(f"{path}: a MeasurementSet; convert it first (xstack.io.convert_ms)")
        from xstack.io.convert import convert_ms

        owner = TemporaryStoreOwner(prefix=prefix)
        store = convert_ms(path, Path(owner.path) / "converted.zarr")
        # not hidden: the user learns where the data went and how to keep them
        logging.getLogger("xstack").info(
            "%s: a MeasurementSet, converted to the MSv4 store %s for this run (removed "
            "afterwards; convert it once with xstack convert to reuse it)", path, store)
        return tie_lifetime(open_store(store), owner)
    return open_store(path)


def _is_pairs(data: Any) -> bool:
    return (isinstance(data, (list, tuple)) and len(data) > 0
            and all(isinstance(p, tuple) and len(p) == 2 and isinstance(p[1], xr.Dataset)
                    for p in data))


def _one(data: Any, allow_ms: bool, prefix: str = "xstack-input-"
         ) -> tuple[str | None, list[tuple[str, xr.Dataset]]]:
    """(label or None, partitions) of one data set; partitions not yet validated."""
    from xstack.schema import iter_partitions

    if hasattr(data, "stacked") and not isinstance(data, (xr.Dataset, xr.DataTree, Mapping)):
        data = data.stacked
    from xstack._fs import is_url

    label = None
    if isinstance(data, (str, os.PathLike)):
        label = str(data) if is_url(data) else str(Path(data))
        data = open_input(data, allow_ms=allow_ms, prefix=prefix)
    if isinstance(data, xr.DataTree):
        parts = list(iter_partitions(data))
    elif isinstance(data, xr.Dataset):
        parts = [("partition", data)]
    elif isinstance(data, Mapping):
        parts = [(str(k), v) for k, v in data.items()]
    elif _is_pairs(data):
        parts = [(str(n), ds) for n, ds in data]
    else:
        raise XstackError(f"cannot read visibilities from a {type(data).__name__}: {_KINDS}")
    if not parts:
        raise XstackError(f"{label or 'input'}: no partitions with visibilities")
    return label, parts


def _finish(parts: list[tuple[str, xr.Dataset]], autocorrelations: bool, validate: bool = True
            ) -> list[tuple[str, xr.Dataset]]:
    from xstack._select import sky_correlations
    from xstack.schema import validate_partition

    for name, ds in parts:
        if validate:
            validate_partition(ds, name)
        elif not isinstance(ds, xr.Dataset):
            raise XstackError(f"{name}: expected an xarray.Dataset, got {type(ds).__name__}")
    if autocorrelations:
        return parts
    return [(name, sky_correlations(ds, False)) for name, ds in parts]


def partitions(data: Any, *, allow_ms: bool = True, autocorrelations: bool = True
               ) -> list[tuple[str, xr.Dataset]]:
    """Normalise one data set (any kind in the module docstring) to ``[(name, Dataset)]``.

    Parameters
    ----------
    data
        Store or MeasurementSet path, DataTree, Dataset, mapping or list of
        ``(name, Dataset)`` pairs, or an object with a ``stacked`` attribute.
    allow_ms
        Convert a MeasurementSet path lazily (else refuse it).
    autocorrelations
        If false, autocorrelation baselines come back flagged
        (:func:`xstack._select.sky_correlations`): they do not measure the sky.

    Returns
    -------
    list of (str, xarray.Dataset)
        Every partition, validated against the schema (metadata only, nothing is read).

    Raises
    ------
    XstackError
        One line naming what is wrong with the input.
    """
    return _finish(_one(data, allow_ms)[1], autocorrelations)


def grouped_partitions(data: Any, *, allow_ms: bool = True, autocorrelations: bool = True,
                       prefix: str = "xstack-input-", validate: bool = True
                       ) -> list[tuple[str, list[tuple[str, xr.Dataset]]]]:
    """Normalise one or several data sets to ``[(label, [(name, Dataset), ...]), ...]``.

    ``data`` is one data set (as for :func:`partitions`) or a list/tuple of them; the
    label is the path of a path input, else ``data<i>`` (``i`` the position in the list).
    ``prefix`` names the temporary directory of a converted MeasurementSet. With
    ``validate=False`` in-memory partitions are not checked against the schema (uvstack
    works on partitions without baseline antenna ids); stores are always checked.
    """
    if _is_pairs(data) or not isinstance(data, (list, tuple)):
        items = [data]
    else:
        items = list(data)
    if not items:
        raise XstackError("no input data given")
    out = []
    for i, item in enumerate(items):
        label, parts = _one(item, allow_ms, prefix)
        out.append((label or f"data{i}", _finish(parts, autocorrelations, validate)))
    return out


@dataclass(frozen=True)
class Positions:
    """Stacking positions: the one positions type of every stage.

    Attributes
    ----------
    ra, dec : numpy.ndarray
        float64, radians (ICRS), one per position.
    table : astropy.table.Table or None
        The catalog as :func:`xstack.coords.read_catalog` reads it (columns ``ra``, ``dec``
        in degrees, optional ``weight``, ``flux``...), or None for bare coordinates.
    """

    ra: np.ndarray
    dec: np.ndarray
    table: Any = None
    #: The same positions in degrees, exactly as given (no radian round trip).
    ra_deg: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]
    dec_deg: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.ra_deg is None:
            object.__setattr__(self, "ra_deg", np.mod(np.degrees(self.ra), 360.0))
        if self.dec_deg is None:
            object.__setattr__(self, "dec_deg", np.degrees(self.dec))

    def __len__(self) -> int:
        return int(self.ra.size)

    @property
    def weight(self) -> np.ndarray | None:
        """The catalog's ``weight`` column (float64), or None."""
        if self.table is None or "weight" not in self.table.colnames:
            return None
        return np.asarray(self.table["weight"], dtype=np.float64)

    def as_table(self) -> Any:
        """The catalog table; for bare coordinates a table of ``ra``, ``dec`` (degrees)."""
        if self.table is not None:
            return self.table
        from astropy.table import Table

        from xstack.coords import read_catalog

        return read_catalog(Table({"ra": self.ra_deg, "dec": self.dec_deg}))

    @classmethod
    def from_any(cls, obj: Any) -> Positions:
        """Positions from a catalog path or Table, ``(ra_deg, dec_deg)`` or an (N, 2) array.

        Parameters
        ----------
        obj
            A :class:`Positions`; a catalog path or :class:`astropy.table.Table` (read by
            :func:`xstack.coords.read_catalog`); a 2-tuple ``(ra, dec)`` of scalars or
            equal-length arrays in degrees; or an array of shape (N, 2) or (2,) of
            ``(ra, dec)`` rows in degrees.

        Raises
        ------
        XstackError
            Any other input, empty or unequal arrays, non-finite values or |dec| > 90 deg.
        """
        from astropy.table import Table

        from xstack.coords import read_catalog

        if isinstance(obj, Positions):
            return obj
        if isinstance(obj, (str, os.PathLike, Table)):
            cat = read_catalog(obj)
            ra_deg = np.asarray(cat["ra"], dtype=np.float64)
            dec_deg = np.asarray(cat["dec"], dtype=np.float64)
            return cls(np.radians(ra_deg), np.radians(dec_deg), cat, ra_deg, dec_deg)
        try:
            if isinstance(obj, tuple) and len(obj) == 2:
                ra, dec = (np.atleast_1d(np.asarray(x, dtype=np.float64)) for x in obj)
            else:
                arr = np.asarray(obj, dtype=np.float64)
                if arr.ndim == 1 and arr.size == 2:
                    arr = arr[None, :]
                if arr.ndim != 2 or arr.shape[1] != 2:
                    raise ValueError
                ra, dec = arr[:, 0], arr[:, 1]
        except (TypeError, ValueError):
            raise XstackError("positions: give a catalog path, an astropy Table, (ra_deg, dec_deg) "
                              "arrays or an (N, 2) array of (ra, dec) in degrees") from None
        if ra.ndim != 1 or ra.shape != dec.shape or ra.size == 0:
            raise XstackError("positions: ra and dec must be non-empty arrays of equal length")
        if not (np.isfinite(ra).all() and np.isfinite(dec).all()) or np.any(np.abs(dec) > 90):
            raise XstackError("positions: non-finite value or |dec| > 90 deg")
        ra = np.mod(ra, 360.0)
        return cls(np.radians(ra), np.radians(dec), None, ra, dec)
