"""argparse types of the command-line options that are physical quantities.

Every option that takes a quantity uses one of these as its ``type=``; the parsing itself is
that of :mod:`xstack.coords` (``parse_angle``, ``parse_flux``, ``parse_distance``,
``parse_frequency``, ``parse_velocity``), built on :mod:`astropy.units`.

Units on the command line:

* astropy's spelling is taken as written: ``5mJy`` is milli-, ``5MJy`` mega-jansky;
* any other case is accepted where it has one meaning (``0.4ARCSEC``, ``20UJY``,
  ``23.8KLAMBDA``) and refused where it has several, with an error naming them (``5MJY``: mJy
  or MJy; ``1420mhz``: mHz or MHz);
* a plain number keeps the option's default unit, named in its ``--help`` (arcsec for angles,
  Jy for flux densities, metres for uv distances).

A bad value is an argparse error: ``argument --cell: '0.4Jy' is not an angle (...)``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from xstack.errors import XstackError

#: Help text fragments naming the accepted forms and the default unit of a plain number.
ANGLE_HELP = "an angle: 0.4arcsec, 2arcmin, 1e-4deg; a plain number is arcsec"
FLUX_HELP = "a flux density: 20uJy, 2mJy; a plain number is Jy"
DIST_HELP = "a uv distance: 5000m, 5km, 23.8klambda, 1e5lambda; a plain number is metres"


def _argparse_type(name: str, parse: Callable[[str], Any],
                   check: Callable[[Any], str | None] | None = None) -> Callable[[str], Any]:
    """An argparse ``type=``: ``parse`` the text, then ``check`` the value (a message or None)."""

    def convert(text: str) -> Any:
        try:
            value = parse(text)
        except XstackError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        problem = check(value) if check is not None else None
        if problem:
            raise argparse.ArgumentTypeError(f"{text!r}: {problem}")
        return value

    convert.__name__ = name
    convert.__qualname__ = name
    return convert


def _angle_arcsec(text: str) -> float:
    from xstack.coords import parse_angle

    return parse_angle(text, "arcsec")


def _flux(text: str) -> float:
    from xstack.coords import parse_flux

    return parse_flux(text)


def _flux_per_beam(text: str) -> float:
    from xstack.coords import parse_flux

    return parse_flux(text, per_beam=True)


def _uv_distance(text: str) -> str:
    from xstack.coords import parse_distance

    parse_distance(text)  # checked here; the library reads the same text the same way
    return text.strip()


def _uv_distance_value(text: str) -> float:
    from xstack.coords import parse_distance

    return parse_distance(text)[0]


def _frequency(text: str) -> float:
    from xstack.coords import parse_frequency

    return parse_frequency(text, "Hz")


def _velocity(text: str) -> float:
    from xstack.coords import parse_velocity

    return parse_velocity(text, "km/s")


def _line_flux(text: str) -> float:
    """An integrated line flux in Jy km/s: 0.2, 0.2Jy km/s, 200mJy km/s, 2e-22W/m2 ... (any
    unit astropy converts to Jy km/s)."""
    import astropy.units as u

    t = str(text).strip()
    try:
        return float(t)
    except ValueError:
        pass
    try:
        return float(u.Quantity(t).to_value(u.Jy * u.km / u.s))
    except (TypeError, ValueError, u.UnitsError):
        raise XstackError(f"{text!r} is not an integrated line flux (0.2Jy km/s, 200mJy km/s; "
                          "a plain number is Jy km/s)") from None


def _positive(value: float) -> str | None:
    return None if value > 0 else "must be > 0"


def _not_negative(value: float) -> str | None:
    return None if value >= 0 else "must be >= 0"


#: An angle > 0 in arcsec (``--cell``, ``--fit-radius``, ``--field-radius``, ``--mask-radius``).
angle_arcsec = _argparse_type("angle", _angle_arcsec, _positive)
#: An angle >= 0 in arcsec (``--min-separation``).
separation_arcsec = _argparse_type("angle", _angle_arcsec, _not_negative)
#: A flux density in Jy (``--flux``).
flux_jy = _argparse_type("flux density", _flux)
#: A CLEAN threshold >= 0 in Jy (or Jy/beam: ``50uJy/beam``) (``--threshold``).
threshold_jy = _argparse_type("flux density", _flux_per_beam, _not_negative)
#: A uv distance >= 0, returned as the (checked) text (``--uvmin``, ``--uvmax``).
uv_distance = _argparse_type("uv distance", _uv_distance,
                             lambda text: _not_negative(_uv_distance_value(text)))
#: A frequency > 0 in Hz (``--line-frequency``).
frequency_hz = _argparse_type("frequency", _frequency, _positive)
#: An integrated line flux >= 0 in Jy km/s (``--line-flux``).
line_flux_jy_kms = _argparse_type("line flux", _line_flux, _not_negative)
#: A velocity in km/s (``--velocity-resolution``).
velocity_kms = _argparse_type("velocity", _velocity)


def filter_cells_or_distance(text: str) -> int | str:
    """``--filter``: ``3`` -> central 3 x 3 Fourier cells; ``4500m`` / ``20klambda`` -> a uv
    distance (returned as the checked text)."""
    try:
        return int(text)
    except ValueError:
        return uv_distance(text)
