"""Exceptions and warnings raised by xstack for problems a user can fix.

Every exception is an :class:`XstackError`; the specific kinds are also the matching Python
builtins, so code that does not know xstack still catches them naturally:

==========================  =====================================================
:class:`OptionError`        a bad option or argument value (a :class:`ValueError`)
:class:`OutputExistsError`  an output exists and ``overwrite`` is not set
                            (a :class:`FileExistsError`)
:class:`NoDataError`        nothing usable to work on: every visibility flagged, no
                            position inside a pointing, an empty catalog
:class:`SchemaError`        a store or Dataset that does not follow the xstack schema
==========================  =====================================================

Library messages name API parameters (``skip_outside``, ``min_separation_arcsec``), never
command-line flags. :class:`XstackWarning` and :class:`XstackError` carry the parameter they
concern in their ``option`` attribute; the command line prints them as one ``warning: ...``
or ``error: ...`` line that names the flag instead (``--min-separation``).
:class:`WeightsWarning` is the :class:`XstackWarning` of weights that disagree with the data.
"""

from __future__ import annotations


class XstackError(Exception):
    """A user-facing error: bad input, a missing file, an existing output.

    The command line prints ``error: <message>`` on one line and exits with status 1,
    without a traceback, for every exception of this type.

    Parameters
    ----------
    *args
        The message (one line; it names API parameters, never command-line flags).
    option
        The API parameter(s) the error concerns (e.g. ``"overwrite"``), or None; the command
        line names their flags instead (:func:`xstack.cli.name_flags`).
    """

    def __init__(self, *args: object, option: str | tuple[str, ...] | None = None) -> None:
        super().__init__(*args)
        self.option = option


class SchemaError(XstackError):
    """A zarr store or xarray Dataset that does not follow the xstack schema."""


class OptionError(XstackError, ValueError):
    """A bad option or argument value (unknown name, out of range, inconsistent)."""


class OutputExistsError(XstackError, FileExistsError):
    """An output path exists and overwriting was not asked for."""


class NoDataError(XstackError):
    """No usable data: everything flagged, no position inside a pointing, nothing to stack."""


class XstackWarning(UserWarning):
    """A warning about a result the user may want to act on.

    Parameters
    ----------
    message
        One sentence; it names API parameters, never command-line flags.
    option
        The API parameter(s) the warning concerns (e.g. ``"errors"``,
        ``"min_separation_arcsec"``), or None. The command line translates it to the
        option string of its flag and names that.
    """

    def __init__(self, message: str, option: str | tuple[str, ...] | None = None) -> None:
        super().__init__(message)
        self.option = option

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class WeightsWarning(XstackWarning):
    """The visibility weights and the data's own scatter disagree (the uv stack's check).

    Its own kind so that code stacking the same data again (subsets of a catalog) can
    silence the repeat by category, not by the message's text.
    """
