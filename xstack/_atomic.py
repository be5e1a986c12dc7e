"""Atomic outputs: write under a temporary name beside the target, rename when done."""

from __future__ import annotations

import contextlib
import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path

from xstack.errors import OutputExistsError, XstackError


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        path.unlink(missing_ok=True)


def check_output(path: str | os.PathLike, overwrite: bool) -> Path:
    """Fail early, before any work, if ``path`` exists and ``overwrite`` is not set."""
    path = Path(path)
    if (path.exists() or path.is_symlink()) and not overwrite:
        raise OutputExistsError(f"{path} exists (pass overwrite=True to replace it)",
                                option="overwrite")
    if not path.parent.exists():
        raise XstackError(f"{path.parent}: output directory does not exist")
    return path


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Context manager yielding a temporary path to write ``path`` (file or directory) to.

    On success the temporary is renamed to ``path`` (an existing output is replaced only with
    ``overwrite``); on any error, or if the process is interrupted, the temporary is removed
    or, if the process was killed, left under a hidden ``.NAME.partial-*`` name that no
    xstack reader accepts.
    """
    path = check_output(path, overwrite)
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
        _remove(tmp)
        raise
