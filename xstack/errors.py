"""Exceptions raised by xstack for problems a user can fix."""

from __future__ import annotations


class XstackError(Exception):
    """A user-facing error: bad input, a missing file, an existing output.

    The command line prints ``error: <message>`` on one line and exits with status 1,
    without a traceback, for every exception of this type.
    """


class SchemaError(XstackError):
    """A zarr store or xarray Dataset that does not follow the xstack schema."""
