"""Atomic outputs: write under a temporary name beside the target, rename when done.

Object stores (``s3://``...) have no rename: there a file output is written to a local
temporary and uploaded when complete (one object appears whole), and a store is written in
place under its final name by :func:`atomic_store`, its ``xstack_complete`` flag last.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from xstack._fs import Location, locate
from xstack.errors import OutputExistsError, XstackError


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink(missing_ok=True)


def discard(path: str | os.PathLike) -> None:
    """Remove the temporary ``path`` of a failed or interrupted write, now and once more at
    interpreter exit.

    After an interrupt (Ctrl-C, SIGTERM) the threads of the computation that was running
    finish the tasks they had begun, and those may still write into ``path`` after it was
    removed here. Python joins those threads (dask's thread pool) before it runs the
    :mod:`atexit` callbacks, so the second removal comes after the last write.
    """
    path = Path(path)
    _remove(path)
    atexit.register(_remove, path)


def _check(loc: Location, overwrite: bool) -> None:
    if loc.exists() and not overwrite:
        raise OutputExistsError(f"{loc.name} exists (pass overwrite=True to replace it)",
                                option="overwrite")
    if not loc.parent_exists():
        if loc.local:
            raise XstackError(f"{Path(loc.path).parent}: output directory does not exist")
        raise XstackError(f"{loc.url}: its bucket does not exist")
    if loc.local and not Path(loc.path).parent.is_dir():
        raise XstackError(f"{Path(loc.path).parent} is a file, not a directory: "
                          f"{Path(loc.path).name} cannot be written in it")


def check_output(path: str | os.PathLike, overwrite: bool,
                 storage_options: Mapping[str, Any] | None = None) -> Path | str:
    """Fail early, before any work, if ``path`` exists and ``overwrite`` is not set.

    ``path`` is a local path or a URL (:mod:`xstack._fs`); returns the path (a
    :class:`~pathlib.Path`) or, for a remote output, the URL.
    """
    loc = locate(path, storage_options)
    _check(loc, overwrite)
    return Path(loc.path) if loc.local else loc.url


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, overwrite: bool = False,
                  storage_options: Mapping[str, Any] | None = None) -> Iterator[Path]:
    """Context manager yielding a temporary path to write ``path`` (file or directory) to.

    On success the temporary is renamed to ``path`` (an existing output is replaced only with
    ``overwrite``); on any error, or if the process is interrupted (Ctrl-C; SIGTERM in the
    ``xstack`` program), the temporary is removed (:func:`discard`) or, if the process was
    killed (SIGKILL), left under a hidden ``.NAME.partial-*`` name that no xstack reader
    accepts. For a remote ``path`` (a URL) the temporary is local and uploaded
    on success.
    """
    loc = locate(path, storage_options)
    if not loc.local:
        with _uploaded(loc, overwrite) as tmp:
            yield tmp
        return
    path = check_output(loc.path, overwrite)
    tmp = path.parent / f".{path.name}.partial-{uuid.uuid4().hex[:8]}"
    try:
        yield tmp
        if not tmp.exists():
            raise XstackError(f"{path}: nothing was written")
        if path.exists() or path.is_symlink():
            if not overwrite:  # appeared while we worked
                raise OutputExistsError(f"{path} exists (pass overwrite=True to replace it)",
                                        option="overwrite")
            trash = path.parent / f".{path.name}.old-{uuid.uuid4().hex[:8]}"
            os.replace(path, trash)
            os.replace(tmp, path)
            _remove(trash)
        else:
            os.replace(tmp, path)
    except BaseException:
        discard(tmp)
        raise


@contextlib.contextmanager
def _uploaded(loc: Location, overwrite: bool) -> Iterator[Path]:
    """A local temporary for a remote output, uploaded (after the old output is deleted, with
    ``overwrite``) once written."""
    _check(loc, overwrite)
    with tempfile.TemporaryDirectory(prefix="xstack-upload-") as tmpdir:
        tmp = Path(tmpdir) / Path(loc.path).name
        yield tmp
        if not tmp.exists():
            raise XstackError(f"{loc.url}: nothing was written")
        _check(loc, overwrite)  # appeared while we worked
        loc.remove()
        loc.fs.put(str(tmp), loc.path, recursive=tmp.is_dir())
        loc.fs.invalidate_cache(loc.path)


@contextlib.contextmanager
def atomic_store(path: str | os.PathLike | Location, overwrite: bool = False,
                 storage_options: Mapping[str, Any] | None = None) -> Iterator[Location]:
    """Context manager yielding where to write the zarr store ``path``.

    Local: a temporary beside ``path``, renamed into place on success
    (:func:`atomic_output`). Remote (no rename on object stores): ``path`` itself, an
    existing store deleted first with ``overwrite``; the writer sets ``xstack_complete`` as
    its very last write (:func:`xstack.schema.finish_store`), so an interrupted write never
    opens as a store, and an error removes what was written.
    """
    loc = locate(path, storage_options)
    if loc.local:
        with atomic_output(loc.path, overwrite=overwrite) as tmp:
            yield locate(tmp)
        return
    _check(loc, overwrite)
    loc.remove()
    try:
        yield loc
    except BaseException:
        with contextlib.suppress(Exception):
            loc.remove()
        raise
