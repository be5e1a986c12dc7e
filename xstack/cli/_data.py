"""The ``--data-group`` option of the commands that read visibilities from a store."""

from __future__ import annotations

import argparse
import os
from typing import Any

from xstack.errors import XstackError


def add_data_group(p: argparse.ArgumentParser) -> None:
    """Add ``--data-group NAME`` to a command that reads visibilities."""
    p.add_argument("--data-group", default=None, metavar="NAME",
                   help="MSv4 data group to read (e.g. corrected: VISIBILITY_CORRECTED of a "
                        "store converted by xradio); default: base, else each partition's first")


def with_data_group(path: str | os.PathLike, group: str | None) -> Any:
    """``path`` itself, or with ``group`` the store opened with that group's correlated data
    as its visibilities (a MeasurementSet has no data groups: one-line error)."""
    if group is None:
        return path
    from xstack._inputs import is_ms
    from xstack.schema import open_store

    if is_ms(path):
        raise XstackError(f"{path}: a MeasurementSet has no data groups; choose its column with "
                          "xstack convert --datacolumn")
    return open_store(path, data_group=group)
