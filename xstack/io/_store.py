"""Writing an xstack store region by region, with the atomic protocol of ``write_store``.

:func:`xstack.schema.write_store` computes dask-backed partitions itself. ``convert`` fills
its arrays from casacore sequentially instead (one reader, reused buffers), so it needs the
store created first and filled afterwards; :func:`region_store` does exactly what
``write_store`` does around that: same root attributes, temporary name via
:func:`xstack._atomic.atomic_store`, ``xstack_complete`` set last, rename at the end (on an
object store, no rename: the store is written in place, the completion flag last).
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr

from xstack._atomic import atomic_store
from xstack._fs import output_path
from xstack.schema import finish_store, new_store_attrs, partition_nodes, write_skeleton

_BLOSC_SHUFFLE = {"noshuffle": 0, "shuffle": 1, "bitshuffle": 2}


@contextlib.contextmanager
def region_store(
    partitions: Mapping[str, xr.Dataset],
    path: str | os.PathLike,
    *,
    kind: str = "processing_set",
    overwrite: bool = False,
    attrs: Mapping[str, Any] | None = None,
    encoding: Mapping[str, Mapping[str, Any]] | None = None,
    storage_options: Mapping[str, Any] | None = None,
    with_location: bool = False,
) -> Iterator[Any]:
    """Create a store whose dask-backed variables are left for the caller to fill.

    Coordinates and numpy-backed variables are written at once; dask-backed variables
    (placeholders, never computed) only get their zarr arrays, chunked like the dask arrays.
    Inside the ``with`` block the caller writes them, chunk-aligned, through the yielded
    root :class:`zarr.Group` (``root[partition][variable][region] = values``). On a clean exit
    the completion flag is set and the store renamed into place; on an error or interruption
    nothing valid is left behind. ``encoding`` (variable -> zarr encoding, e.g.
    ``{"VISIBILITY": {"compressors": None}}``) applies to every partition. ``path`` may be a
    URL (:mod:`xstack._fs`, options in ``storage_options``). With ``with_location`` the block
    gets ``(root, location)``: the :class:`xstack._fs.Location` being written (the temporary
    one for a local store), for writers in other processes to open it themselves.
    """
    import zarr

    root_attrs = new_store_attrs(partitions, kind, attrs)
    with atomic_store(path, overwrite=overwrite, storage_options=storage_options) as loc:
        write_skeleton(loc, partition_nodes(partitions), root_attrs, encoding)
        root = zarr.open_group(loc.zarr_store(), mode="r+", zarr_format=3)
        yield (root, loc) if with_location else root
        finish_store(loc, consolidated=True)
    return output_path(path)


class ChunkFiles:
    """Whole chunks of one zarr v3 array in a local store, written straight to their files.

    zarr's own write path costs a round of Python and asyncio per chunk and (for a chunk at
    the edge of the array) a full-size copy; worse, python-casacore holds the GIL while it
    reads, so those Python steps wait for the reader. For the plain codec chains ``convert``
    uses - ``bytes`` (little-endian) alone, or followed by ``blosc`` or ``zstd`` - the chunk
    file is simply the chunk's C-order bytes, or their compressed frame, so it is written here
    with a few
    GIL-free calls and exactly the bytes zarr would write. Build with :meth:`for_array`,
    which returns None for anything else (other stores, codecs, sharding), where the caller
    falls back to ``array[region] = values``.

    Files are written in place, not under a temporary name: the store as a whole is the
    atomic unit (:func:`region_store`).
    """

    def __init__(self, root: Path, dtype: np.dtype, chunk_shape: tuple[int, ...], fill_value: Any,
                 encode_key: Any, compressor: Any | None) -> None:
        self.root = root
        self.dtype = dtype
        self.chunk_shape = chunk_shape
        self.fill_value = fill_value
        self._encode_key = encode_key
        self._compressor = compressor
        #: Uncompressed: a chunk file is the chunk's bytes, so it can be written piece by piece.
        self.raw = compressor is None
        self.chunk_nbytes = int(np.prod(chunk_shape)) * dtype.itemsize

    @classmethod
    def for_array(cls, array: Any) -> ChunkFiles | None:
        """A writer for ``array`` (a :class:`zarr.Array`), or None if its layout is not plain."""
        from numcodecs import Blosc, Zstd
        from zarr.codecs import BloscCodec, BytesCodec, ZstdCodec
        from zarr.core.chunk_grids import RegularChunkGrid
        from zarr.storage import LocalStore

        meta = array.metadata
        store = array.store_path.store
        if getattr(meta, "zarr_format", None) != 3 or not isinstance(store, LocalStore):
            return None
        if meta.storage_transformers or not isinstance(meta.chunk_grid, RegularChunkGrid):
            return None
        dtype = np.dtype(array.dtype)
        codecs = tuple(meta.codecs)
        if sys.byteorder != "little" or dtype.hasobject or dtype.byteorder == ">":
            return None
        if not codecs or not isinstance(codecs[0], BytesCodec) or len(codecs) > 2:
            return None
        endian = codecs[0].endian
        if dtype.itemsize > 1 and (endian is None or endian.value != "little"):
            return None
        compressor = None
        if len(codecs) == 2:
            # the numcodecs codecs zarr's BloscCodec and ZstdCodec build: identical frames
            codec = codecs[1]
            if isinstance(codec, BloscCodec) and codec.typesize is not None:
                compressor = Blosc(cname=codec.cname.value, clevel=codec.clevel,
                                   shuffle=_BLOSC_SHUFFLE[codec.shuffle.value],
                                   blocksize=codec.blocksize, typesize=codec.typesize)
            elif isinstance(codec, ZstdCodec):
                compressor = Zstd(level=codec.level, checksum=codec.checksum)
            else:
                return None
        root = Path(store.root) / array.store_path.path
        return cls(root, dtype, tuple(meta.chunk_grid.chunk_shape), array.fill_value,
                   meta.encode_chunk_key, compressor)

    def path(self, coords: tuple[int, ...]) -> Path:
        """File of the chunk at chunk-grid position ``coords``."""
        return self.root / self._encode_key(tuple(int(c) for c in coords))

    def open(self, coords: tuple[int, ...]) -> int:
        """Create the chunk file (and its directories); return a descriptor for :meth:`write_at`."""
        path = self.path(coords)
        path.parent.mkdir(parents=True, exist_ok=True)
        return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_BINARY", 0), 0o666)

    @staticmethod
    def write_at(fd: int, data: np.ndarray, offset: int) -> None:
        """Write the bytes of C-contiguous ``data`` at byte ``offset`` of a raw chunk file."""
        view = memoryview(data.reshape(-1).view(np.uint8))
        while view.nbytes:
            done = os.pwrite(fd, view, offset)
            view, offset = view[done:], offset + done

    def read_into(self, coords: tuple[int, ...], out: np.ndarray) -> bool:
        """Read the chunk at ``coords`` into ``out`` (C-contiguous, the chunk's shape and dtype).

        Raw chunks are read straight into ``out``; compressed ones are decompressed into it,
        so memory holds ``out`` plus the compressed bytes (zarr's own read also holds the
        decoded chunk before copying it out). A chunk never written holds the fill value.
        Returns False if the file does not have the chunk's size (a damaged chunk: the
        caller lets zarr read it and report).
        """
        target = memoryview(out.reshape(-1).view(np.uint8))
        try:
            with open(self.path(coords), "rb", buffering=0) as fh:
                if self._compressor is None:
                    return fh.readinto(target) == self.chunk_nbytes
                data = fh.read()
        except FileNotFoundError:
            out.fill(self.fill_value)
            return True
        try:
            self._compressor.decode(data, out=target)
        except Exception:  # noqa: BLE001 - damaged: zarr's read reports it
            return False
        return True

    def write(self, coords: tuple[int, ...], chunk: np.ndarray) -> None:
        """Encode and write one whole chunk (``chunk`` has exactly the chunk shape and dtype)."""
        if chunk.shape != self.chunk_shape or chunk.dtype != self.dtype or not chunk.flags.c_contiguous:
            raise ValueError(f"chunk {chunk.shape} {chunk.dtype} does not match the array's "
                             f"{self.chunk_shape} {self.dtype} (C order)")
        data = chunk.reshape(-1).view(np.uint8)
        if self._compressor is not None:
            data = np.frombuffer(self._compressor.encode(data), dtype=np.uint8)
        fd = self.open(coords)
        try:
            self.write_at(fd, data, 0)
        finally:
            os.close(fd)
