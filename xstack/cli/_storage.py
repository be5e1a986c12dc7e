"""``--storage-options JSON``: options of the filesystems of store URLs (``s3://``...).

:func:`add_storage_options` adds the option to a sub-command's parser (one call per command
that reads or writes stores); :func:`xstack.cli.main` runs the command inside
:func:`storage_of`, so every store URL the command opens or writes without options of its
own gets these (:func:`xstack._fs.use_storage_options`). Without the option a protocol is
configured its own way (``AWS_ENDPOINT_URL``, ``FSSPEC_S3_ENDPOINT_URL``, profiles...).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any


def _json_object(text: str) -> dict[str, Any]:
    try:
        value = json.loads(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"not JSON ({exc.args[0]})") from None
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError('expected a JSON object, e.g. \'{"anon": true}\'')
    return value


def add_storage_options(parser: argparse.ArgumentParser) -> None:
    """Add ``--storage-options JSON`` to one sub-command's parser."""
    parser.add_argument("--storage-options", type=_json_object, default=None, metavar="JSON",
                        help="options of the filesystem of store URLs (s3://, gs://, ...), a "
                             'JSON object, e.g. \'{"endpoint_url": "http://localhost:9000"}\'; '
                             "default: the protocol's own configuration (AWS_ENDPOINT_URL, "
                             "FSSPEC_S3_ENDPOINT_URL, profiles)")


@contextlib.contextmanager
def storage_of(args: argparse.Namespace) -> Iterator[None]:
    """The storage options a parsed command line gives, in force for the command's run."""
    from xstack._fs import use_storage_options

    with use_storage_options(getattr(args, "storage_options", None)):
        yield


def cli_path(text: str | os.PathLike) -> Path | str:
    """A path argument as the command works with it: a :class:`~pathlib.Path`, or a store URL
    kept as it is (``Path`` would fold the ``//`` of ``s3://``)."""
    from xstack._fs import is_url

    return text if is_url(text) else Path(text)


def path_exists(text: str | os.PathLike) -> bool:
    """True if a path, or a store URL (with the command's storage options), exists."""
    from xstack._fs import locate

    return locate(text).exists()
