"""Validators shared by the stages' option dataclasses (``UvstackOptions``, ``NoiseOptions``,
``ImageFitOptions``, ``UvFitOptions``): each bad value is an :class:`OptionError` naming the
parameter, raised when the options are built, i.e. before any data is read."""

from __future__ import annotations

import math
from numbers import Integral, Real
from typing import Any

import numpy as np

from xstack.errors import OptionError


def choice(name: str, value: Any, allowed: tuple[str, ...], *, what: str | None = None) -> str:
    """``value`` if it is one of ``allowed``; else an :class:`OptionError` for parameter
    ``name`` that calls it ``what`` (default: ``name``)."""
    if not isinstance(value, str) or value not in allowed:
        raise OptionError(f"unknown {what or name} {value!r} (use {', '.join(allowed)})",
                          option=name)
    return value


def flag(name: str, value: Any, *, optional: bool = False) -> bool | None:
    """``value`` as a bool (True/False, numpy booleans; None too if ``optional``)."""
    if value is None and optional:
        return None
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise OptionError(f"{name} must be True or False, got {value!r}", option=name)


def positive(name: str, value: Any, *, optional: bool = True) -> float | None:
    """``value`` as a finite float > 0 (None passes if ``optional``)."""
    if value is None and optional:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Real) \
            or not math.isfinite(float(value)) or not float(value) > 0:
        raise OptionError(f"{name} must be a finite number > 0, got {value!r}", option=name)
    return float(value)


def integer(name: str, value: Any) -> int:
    """``value`` as an int (integers, or floats with an integral value)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Real) \
            or not math.isfinite(float(value)) or (not isinstance(value, Integral)
                                                   and not float(value).is_integer()):
        raise OptionError(f"{name} must be an integer, got {value!r}", option=name)
    return int(value)
