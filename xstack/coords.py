"""Sky geometry, unit parsing and catalogs shared by every stage.

Conventions (``docs/conventions.md``): direction cosines relative to a phase center
(ra0, dec0) are, exactly,

    l = cos(dec) sin(ra - ra0)
    m = sin(dec) cos(dec0) - cos(dec) sin(dec0) cos(ra - ra0)
    n = sqrt(1 - l^2 - m^2)

and a point source of flux S at (l, m) appears in the visibilities as
``S exp(+2 pi i (u l + v m + w (n - 1)) / lambda)`` with (u, v, w) as stored in the MS.
"""

from __future__ import annotations

import functools
import itertools
import os
import re
from typing import Any

import numpy as np
from astropy import units as u
from astropy.table import Table

from xstack.errors import XstackError

SPEED_OF_LIGHT = 299_792_458.0  # m/s


def radec_to_lmn(ra: Any, dec: Any, ra0: float, dec0: float) -> tuple[np.ndarray, ...]:
    """Direction cosines (l, m, n) of (ra, dec) relative to the phase center (ra0, dec0).

    All angles in radians; arithmetic in float64. ``n - 1`` is returned as well, computed
    without cancellation (``-(l^2 + m^2) / (1 + n)``), since the w-term needs it to full
    precision even for positions close to the phase center.

    Returns
    -------
    l, m, n, n_minus_1 : numpy.ndarray
    """
    ra = np.asarray(ra, dtype=np.float64)
    dec = np.asarray(dec, dtype=np.float64)
    dra = ra - ra0
    cos_dec = np.cos(dec)
    l = cos_dec * np.sin(dra)
    m = np.sin(dec) * np.cos(dec0) - cos_dec * np.sin(dec0) * np.cos(dra)
    r2 = l * l + m * m
    # positions more than 90 deg away have no (l, m) in the visible hemisphere
    n = np.sqrt(np.clip(1.0 - r2, 0.0, None))
    # n for the far hemisphere is negative: cos(separation) < 0
    cos_sep = np.sin(dec) * np.sin(dec0) + cos_dec * np.cos(dec0) * np.cos(dra)
    n = np.where(cos_sep < 0, -n, n)
    n_minus_1 = np.where(cos_sep < 0, n - 1.0, -r2 / (1.0 + n))
    return l, m, n, n_minus_1


def mean_direction(ra: Any, dec: Any) -> tuple[float, float] | None:
    """Direction (ra, dec) of the mean unit vector of the given directions, radians.

    None when the unit vectors (nearly) cancel (directions spread over the whole sky): the
    caller decides what that means (an error, or a fallback).
    """
    ra = np.atleast_1d(np.asarray(ra, dtype=np.float64))
    dec = np.atleast_1d(np.asarray(dec, dtype=np.float64))
    cd = np.cos(dec)
    v = np.array([np.sum(cd * np.cos(ra)), np.sum(cd * np.sin(ra)), np.sum(np.sin(dec))])
    norm = float(np.linalg.norm(v))
    if not norm > 1e-9 * max(ra.size, 1):
        return None
    v /= norm
    return float(np.mod(np.arctan2(v[1], v[0]), 2 * np.pi)), float(np.arcsin(np.clip(v[2], -1, 1)))


def lm_to_radec(l: Any, m: Any, ra0: float, dec0: float) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`radec_to_lmn` for the near hemisphere (n >= 0). Radians."""
    l = np.asarray(l, dtype=np.float64)
    m = np.asarray(m, dtype=np.float64)
    n = np.sqrt(np.clip(1.0 - l * l - m * m, 0.0, None))
    dec = np.arcsin(np.clip(m * np.cos(dec0) + n * np.sin(dec0), -1.0, 1.0))
    ra = ra0 + np.arctan2(l, n * np.cos(dec0) - m * np.sin(dec0))
    return np.mod(ra, 2 * np.pi), dec


def angular_separation(ra1: Any, dec1: Any, ra2: Any, dec2: Any) -> np.ndarray:
    """Great-circle distance in radians (Vincenty formula: stable at 0 and pi)."""
    ra1, dec1, ra2, dec2 = (np.asarray(x, dtype=np.float64) for x in (ra1, dec1, ra2, dec2))
    dra = ra2 - ra1
    s1, c1 = np.sin(dec1), np.cos(dec1)
    s2, c2 = np.sin(dec2), np.cos(dec2)
    num = np.hypot(c2 * np.sin(dra), c1 * s2 - s1 * c2 * np.cos(dra))
    den = s1 * s2 + c1 * c2 * np.cos(dra)
    return np.arctan2(num, den)


# ---------------------------------------------------------------------------------------------
# quantities with units (command-line options, API arguments)
# ---------------------------------------------------------------------------------------------
#
# One rule for every unit: the spelling astropy knows wins (``mJy`` is milli-, ``MJy`` mega-
# jansky); a spelling astropy does not know is matched ignoring case (``ARCSEC``, ``ujy``,
# ``23.8KLAMBDA``) when that gives one meaning for the quantity asked for, and refused with
# an error naming the meanings when it gives several (``5MJY``: mJy or MJy; ``1420mhz``: mHz or
# MHz). A plain number is in the quantity's default unit.

_QUANTITY_RE = re.compile(r"^([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(.*)$")

#: One wavelength: the unit of uv distances measured in wavelengths (astropy has none).
WAVELENGTH = u.def_unit("lambda", doc="one wavelength (uv distance)")
_WAVELENGTH_UNITS: dict[str, Any] = {
    name: (WAVELENGTH if factor == 1 else u.def_unit(name, factor * WAVELENGTH))
    for name, factor in (("lambda", 1.0), ("klambda", 1e3), ("Mlambda", 1e6),
                         ("Glambda", 1e9), ("kl", 1e3), ("Ml", 1e6))}
_WAVELENGTH_UNITS.update({"λ": _WAVELENGTH_UNITS["lambda"], "kλ": _WAVELENGTH_UNITS["klambda"],
                          "Mλ": _WAVELENGTH_UNITS["Mlambda"], "Gλ": _WAVELENGTH_UNITS["Glambda"]})
#: The units of a uv distance: wavelengths and the lengths of baselines (no parsecs).
_UV_DISTANCE_UNITS = {**_WAVELENGTH_UNITS, "m": u.m, "km": u.km, "cm": u.cm, "mm": u.mm}
#: Angle spellings astronomers write that astropy does not know.
_ANGLE_ALIASES: dict[str, Any] = {
    '"': u.arcsec, "''": u.arcsec, "″": u.arcsec, "'": u.arcmin, "′": u.arcmin, "°": u.deg,
    "asec": u.arcsec, "amin": u.arcmin, "arcsecs": u.arcsec, "arcmins": u.arcmin,
    "arcseconds": u.arcsec, "arcminutes": u.arcmin, "degrees": u.deg, "degs": u.deg}


@functools.lru_cache(maxsize=1)
def _units_by_lowercase() -> dict[str, list[tuple[str, Any]]]:
    out: dict[str, list[tuple[str, Any]]] = {}
    for name, unit in u.get_current_unit_registry().registry.items():
        out.setdefault(name.lower(), []).append((name, unit))
    return out


def _part_spellings(part: str, aliases: dict[str, Any], registry: bool) -> list[tuple[str, Any]]:
    """Every unit spelled ``part`` up to case (one part of a spelling astropy did not parse)."""
    key = part.lower()
    found = [(name, unit) for name, unit in aliases.items() if name.lower() == key]
    return found + (_units_by_lowercase().get(key, []) if registry else [])


def _unit_options(spelling: str, aliases: dict[str, Any],
                  registry: bool = True) -> list[tuple[str, Any]]:
    """Every (name, unit) the text ``spelling`` can mean (see the rule above).

    ``registry=False``: only the spellings in ``aliases`` are units.
    """
    if spelling in aliases:
        return [(spelling, aliases[spelling])]
    if registry:
        try:
            return [(spelling, u.Unit(spelling))]  # astropy's own spelling, compound ones too
        except (ValueError, TypeError):
            pass
    per_part = [_part_spellings(part.strip(), aliases, registry) for part in spelling.split("/")]
    if not all(per_part):
        return []
    options = []
    for combo in itertools.product(*per_part):
        unit = combo[0][1]
        for _, other in combo[1:]:
            unit = unit / other
        options.append(("/".join(name for name, _ in combo), unit))
    return options


def _parse_quantity(text: Any, default: Any, targets: tuple[Any, ...], what: str,
                    examples: str, aliases: dict[str, Any] | None = None,
                    registry: bool = True) -> tuple[float, Any]:
    """``(value, target unit)`` of a number with an optional unit; see the rule above.

    ``default`` is the unit of a plain number; ``targets`` the units the result may be
    expressed in (the first one equivalent to the unit given is used); ``registry=False``
    allows only the spellings in ``aliases``.
    """
    aliases = aliases or {}
    if isinstance(text, u.Quantity):
        value, spelling, label = float(text.value), str(text.unit), str(text)
        options = [(str(text.unit), text.unit)]
    elif isinstance(text, (int, float, np.integer, np.floating)) and not isinstance(text, bool):
        value, spelling, label, options = float(text), "", repr(text), []
    else:
        label = str(text)
        cleaned = label.strip().replace("µ", "u").replace("μ", "u")
        match = _QUANTITY_RE.match(cleaned)
        if not match:
            raise XstackError(f"cannot read {what} {label!r} (examples: {examples})")
        value, spelling = float(match.group(1)), match.group(2).strip()
        options = _unit_options(spelling, aliases, registry) if spelling else []
    if not np.isfinite(value):
        raise XstackError(f"{what} {label!r} is not finite")
    if spelling == "":
        target = next(t for t in targets if default.is_equivalent(t))
        return value * float(default.to(target)), target
    fitting: list[tuple[str, Any, float]] = []
    for name, unit in options:
        for target in targets:
            if unit.is_equivalent(target):
                fitting.append((name, target, float(unit.to(target))))
                break
    if not fitting:
        if options:
            kind = options[0][1].physical_type
            raise XstackError(f"{label!r} is not {what} ({options[0][0]} is "
                              f"{'a unit' if kind == 'unknown' else kind}; examples: {examples})")
        raise XstackError(f"{label!r}: unknown unit {spelling!r} (expected {what}, e.g. "
                          f"{examples})")
    distinct: list[tuple[str, Any, float]] = []
    for cand in fitting:
        if not any(t is cand[1] and np.isclose(f, cand[2], rtol=1e-12, atol=0)
                   for _, t, f in distinct):
            distinct.append(cand)
    if len(distinct) > 1:
        meanings = " or ".join(f"{name} (1 {name} = {factor:g} {target})"
                               for name, target, factor in distinct)
        raise XstackError(f"{label!r}: unit {spelling!r} is ambiguous when its case is ignored: "
                          f"{meanings}; write the unit with its case")
    _, target, factor = distinct[0]
    return value * factor, target


def parse_angle(text: str | float | u.Quantity, unit: str | Any = "arcsec") -> float:
    """Parse an angle such as ``0.4arcsec``, ``2arcmin``, ``1e-4deg``, ``3"``; return it in ``unit``.

    A plain number is taken to be in ``unit`` already. Units follow the rule of this module:
    astropy's spelling, else any case where that is unambiguous.

    Parameters
    ----------
    text : str, float or astropy.units.Quantity
        The angle.
    unit : str or astropy.units.Unit
        Unit of the result and of a plain number (default arcsec).

    Returns
    -------
    float
        The angle in ``unit``.

    Raises
    ------
    XstackError
        If the text is not a number with an angle unit, or the unit is ambiguous.
    """
    unit = u.Unit(unit)
    value, _ = _parse_quantity(text, unit, (unit,), "an angle", "0.4arcsec, 2arcmin, 1e-4deg",
                               _ANGLE_ALIASES)
    return value


def parse_distance(text: str | float | u.Quantity) -> tuple[float, str]:
    """Parse a uv distance such as ``5000m``, ``5km``, ``23.8klambda`` or ``1e5lambda``.

    Units: ``lambda``, ``klambda``, ``Mlambda``, ``Glambda`` (also ``kl``, ``Ml``, ``λ``) and
    ``m``, ``km``, ``cm``, ``mm``. Case is ignored: ``23.8KLAMBDA``, ``5KM``; ``1mlambda`` is
    1 Mλ (milli-wavelengths are no unit of a uv distance), ``5MM`` is 5 mm (megametres are
    not one either).

    Returns
    -------
    value, unit : float, str
        ``unit`` is ``"m"`` (value in metres) or ``"lambda"`` (value in wavelengths).
        A bare number is taken as metres.

    Raises
    ------
    XstackError
        If the text is not a distance or its unit is ambiguous.
    """
    value, target = _parse_quantity(text, u.m, (u.m, WAVELENGTH), "a uv distance",
                                    "5000m, 5km, 23.8klambda", _UV_DISTANCE_UNITS,
                                    registry=False)
    return value, ("m" if target is u.m else "lambda")


def parse_flux(text: str | float | u.Quantity, *, per_beam: bool = False) -> float:
    """Parse a flux density such as ``20uJy``, ``2mJy``, ``20µJy``, ``1.5e-3`` (Jy); return Jy.

    ``5mJy`` is milli-, ``5MJy`` mega-jansky (astropy's spelling); ``5mjy`` or ``5MJY`` are
    refused as ambiguous, ``20UJY`` is accepted. With ``per_beam=True`` a ``/beam`` suffix
    (``50uJy/beam``) is accepted as well (an image value in Jy/beam).

    Raises
    ------
    XstackError
        If the text is not a flux density or its unit is ambiguous.
    """
    if per_beam and isinstance(text, str):
        text = re.sub(r"\s*/\s*beam\s*$", "", text, flags=re.IGNORECASE)
    value, _ = _parse_quantity(text, u.Jy, (u.Jy,), "a flux density", "20uJy, 2mJy, 1.5e-3")
    return value


def parse_frequency(text: str | float | u.Quantity, unit: str | Any = "Hz") -> float:
    """Parse a frequency such as ``1420.405751786MHz`` or ``1.4GHz``; return it in ``unit``.

    A plain number is in ``unit`` (default Hz). ``1420mhz`` is refused (mHz or MHz).
    """
    unit = u.Unit(unit)
    value, _ = _parse_quantity(text, unit, (unit,), "a frequency", "1420.405751786MHz, 1.4GHz")
    return value


def parse_velocity(text: str | float | u.Quantity, unit: str | Any = "km/s") -> float:
    """Parse a velocity such as ``20km/s`` or ``2e4m/s``; return it in ``unit`` (default km/s).

    A plain number is in ``unit``.
    """
    unit = u.Unit(unit)
    value, _ = _parse_quantity(text, unit, (unit,), "a velocity", "20km/s, 2e4m/s")
    return value


# ---------------------------------------------------------------------------------------------
# catalogs
# ---------------------------------------------------------------------------------------------

#: Column names read as RA and Dec (case-insensitive, first match wins).
RA_NAMES = ("ra", "ra_deg", "radeg", "raj2000", "ra_j2000", "_raj2000", "ra_icrs", "_ra_icrs",
            "alpha_j2000", "alpha", "ra_hms", "ra_hours", "right_ascension", "rightascension")
DEC_NAMES = ("dec", "dec_deg", "decdeg", "de", "dej2000", "decj2000", "dec_j2000", "de_j2000",
             "_dej2000", "de_icrs", "dec_icrs", "_de_icrs", "delta_j2000", "delta", "dec_dms",
             "decl", "declination")
_FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz", ".fit.gz", ".fts.gz")
_VOTABLE_SUFFIXES = (".vot", ".votable", ".xml")
#: RA and Dec closer than this (deg) outside their range are rounding and wrapped / clipped.
_RANGE_TOLERANCE_DEG = 1e-9


def _read_table(label: str) -> Table:
    """Read a catalog file: the format from its content and name, ASCII formats guessed."""
    import warnings

    lower = label.lower()
    try:
        with open(label, "rb") as fh:
            head = fh.read(4096)
    except OSError as exc:
        raise XstackError(f"{label}: cannot read ({exc.strerror or exc})") from None
    if lower.endswith(_FITS_SUFFIXES) or head.startswith(b"SIMPLE"):
        fmt, kind = "fits", "a FITS"
    elif lower.endswith(_VOTABLE_SUFFIXES) or b"<VOTABLE" in head.upper():
        fmt, kind = "votable", "a VOTable"
    elif head.lstrip().startswith(b"# %ECSV") or lower.endswith(".ecsv"):
        fmt, kind = "ascii.ecsv", "an ECSV"
    elif lower.endswith(".csv"):
        fmt, kind = "ascii.csv", "a CSV"
    elif lower.endswith((".tsv", ".tab")):
        fmt, kind = "ascii.tab", "a tab-separated"
    else:
        fmt, kind = "ascii", "an ASCII (CSV, whitespace- or tab-separated)"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # unknown units etc. are judged below
            return Table.read(label, format=fmt)
    except Exception as exc:  # astropy raises many types for a malformed file
        reason = " ".join(str(exc).split())[:160] or type(exc).__name__
        if "Unable to guess table format" in reason:
            reason = "no format gives consistent columns"
        hint = ""
        if fmt.startswith("ascii") and fmt != "ascii.ecsv":
            hint = ("; a value with spaces, such as sexagesimal '10 08 00.016', must be quoted "
                    "or written with colons")
        raise XstackError(f"{label}: cannot read as {kind} table ({reason}){hint}") from None


def _name_unit(colname: str) -> Any | None:
    """The unit a column's name implies (``ra_deg``, ``ra_hours``, ``dec_rad``), or None."""
    low = colname.lower()
    if low.endswith(("_deg", "deg", "_dms")):
        return u.deg
    if low.endswith(("_hms", "_hours", "_hour", "_h")):
        return u.hourangle
    if low.endswith("_rad"):
        return u.rad
    return None


def _column_unit(column: Any, colname: str, is_ra: bool, label: str) -> Any | None:
    """The angle unit of a column's header (FITS TUNIT, ECSV/VOTable unit), or None."""
    unit = getattr(column, "unit", None)
    if unit is None or unit == u.dimensionless_unscaled:
        return None
    if isinstance(unit, u.UnrecognizedUnit):
        text = str(unit).strip("\"' ").lower().replace(" ", "")
        if text in ("h:m:s", "hms", "hh:mm:ss"):
            unit = u.hourangle
        elif text in ("d:m:s", "dms", "dd:mm:ss"):
            unit = u.deg
        else:
            raise XstackError(f"{label}: column {colname!r} has unit {str(unit)!r}, which is not "
                              "an angle unit astropy knows")
    elif unit == u.hour:
        unit = u.hourangle  # catalogs write hours of RA as 'h'
    if not unit.is_equivalent(u.deg):
        raise XstackError(f"{label}: column {colname!r} has unit {unit}, not an angle")
    if not is_ra and unit == u.hourangle:
        raise XstackError(f"{label}: column {colname!r} (dec) is in hours; a declination is in "
                          "degrees")
    return unit


def _text_form(text: str) -> str:
    """``number`` (152.0003), ``unit`` (152.0003deg, 10.13h) or ``sexagesimal``."""
    try:
        float(text)
        return "number"
    except ValueError:
        pass
    match = _QUANTITY_RE.match(text)
    if match and not re.search(r"\d", match.group(2)):
        return "unit"
    return "sexagesimal"


def _texts_to_degrees(texts: list[str], colname: str, name: str, is_ra: bool, unit: Any | None,
                      label: str) -> np.ndarray:
    """Angles written as text (numbers, numbers with units, sexagesimal) in degrees."""
    import warnings

    from astropy.coordinates import Angle

    forms = [_text_form(t) for t in texts]
    decimal = [f != "sexagesimal" for f in forms]
    for i, text in enumerate(texts):
        if text == "":
            raise XstackError(f"{label}: row {i + 1}: column {colname!r} is empty")
        if not re.search(r"\d", text):
            raise XstackError(f"{label}: row {i + 1}: cannot read {name}={text!r} as an angle "
                              "(degrees, or sexagesimal such as '10 08 00.016')")
    for i, text in enumerate(texts):
        if decimal[i] != decimal[0]:
            kinds = {True: "a decimal number", False: "sexagesimal"}
            raise XstackError(
                f"{label}: row {i + 1}: {name}={text!r} is {kinds[decimal[i]]} but row 1 "
                f"({texts[0]!r}) is {kinds[decimal[0]]}: mixed formats in one column are "
                f"ambiguous{' (a decimal RA is degrees, a sexagesimal RA hours)' if is_ra else ''}"
                "; write every row the same way")
        if not is_ra and re.search(r"[hHʰ]", text):
            raise XstackError(f"{label}: row {i + 1}: dec={text!r} is written in hours; a "
                              "declination is in degrees")
    implied = _name_unit(colname)
    if forms[0] == "sexagesimal":
        # the astronomers' convention: sexagesimal RA is hours, Dec degrees (h/d markers in
        # the text, a header unit or the column name say otherwise)
        default = unit or implied or (u.hourangle if is_ra else u.deg)
    else:
        default = unit or implied or u.deg
    out = np.empty(len(texts), dtype=np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # 60 seconds is read as the next minute
        try:
            out[:] = Angle(np.asarray(texts), unit=default).degree
            return out
        except Exception:  # find the row and say why
            pass
        for i, text in enumerate(texts):
            try:
                out[i] = Angle(text, unit=default).degree
            except Exception as exc:
                reason = " ".join(str(exc).split())[:120]
                what = {"hourangle": "hours", "deg": "degrees"}.get(str(default), str(default))
                raise XstackError(f"{label}: row {i + 1}: cannot read {name}={text!r} as an "
                                  f"angle in {what} ({reason})") from None
    return out


def _column_to_degrees(column: Any, colname: str, is_ra: bool, label: str,
                       wrap: bool = False) -> np.ndarray:
    """A catalog's RA or Dec column (numbers, Quantity, text) as float64 degrees, checked.

    ``wrap``: RA in (-360, 720) deg is wrapped into [0, 360) (tables computed in Python);
    else RA outside [0, 360) is refused (files).
    """
    name = "ra" if is_ra else "dec"
    unit = _column_unit(column, colname, is_ra, label)
    mask = np.ma.getmaskarray(np.ma.asanyarray(column))
    if mask.any():
        raise XstackError(f"{label}: row {int(np.argmax(mask)) + 1}: column {colname!r} is empty")
    data = np.asarray(column.value if isinstance(column, u.Quantity) else column)
    if data.ndim != 1:
        raise XstackError(f"{label}: column {colname!r} is not one value per row")
    shown: Any
    if data.dtype.kind in "fiu":
        factor = (unit or _name_unit(colname) or u.deg).to(u.deg)
        deg = data.astype(np.float64) * factor
        shown = [f"{float(v):.10g}" for v in data]
        in_hours = (unit or _name_unit(colname)) == u.hourangle
    elif data.dtype.kind in "USO":
        texts = [(v.decode() if isinstance(v, bytes) else str(v)).strip() for v in data]
        deg = _texts_to_degrees(texts, colname, name, is_ra, unit, label)
        shown = [repr(t) for t in texts]
        in_hours = False
    else:
        raise XstackError(f"{label}: column {colname!r} is neither numbers nor text")
    bad = np.flatnonzero(~np.isfinite(deg))
    if bad.size:
        raise XstackError(f"{label}: row {bad[0] + 1}: {name} is not finite")
    tol = _RANGE_TOLERANCE_DEG
    if is_ra:
        outside = ((deg <= -360.0) | (deg >= 720.0) if wrap
                   else (deg < -tol) | (deg >= 360.0 + tol))
        if outside.any():
            i = int(np.argmax(outside))
            rng = "[0h, 24h)" if in_hours else "[0, 360) deg"
            raise XstackError(f"{label}: row {i + 1}: ra={shown[i]} is outside {rng}; a right "
                              "ascension lies in [0, 360) deg (0h to 24h)")
        deg = np.mod(deg, 360.0)
        deg[deg >= 360.0] = 0.0
    else:
        outside = np.abs(deg) > 90.0 + tol
        if outside.any():
            i = int(np.argmax(outside))
            raise XstackError(f"{label}: row {i + 1}: dec={shown[i]} is outside [-90, 90] deg")
        deg = np.clip(deg, -90.0, 90.0)
    return deg


def _split_columns(table: Table, lower: dict[str, str]) -> tuple[tuple[np.ndarray, tuple], ...]:
    """CDS / VizieR split columns (RAh RAm RAs, DE- DEd DEm DEs) as sexagesimal text."""
    def text(value: Any) -> str:
        if np.ma.is_masked(value):
            return ""
        return value.decode() if isinstance(value, bytes) else str(value)

    ra_names = tuple(lower[n] for n in ("rah", "ram", "ras") if n in lower)
    dec_names = tuple(lower[n] for n in ("de-", "ded", "dem", "des") if n in lower)
    rows = range(len(table))
    ra = np.array([" ".join(text(table[n][i]) for n in ra_names) for i in rows], dtype=object)
    sign = lower.get("de-")
    dec = np.array([(text(table[sign][i]).strip() if sign else "")
                    + " ".join(text(table[n][i]) for n in dec_names if n != sign)
                    for i in rows], dtype=object)
    return (ra, ra_names), (dec, dec_names)


def read_catalog(path: str | os.PathLike | Table, required_flux: bool = False) -> Table:
    """Read a table of stacking positions as astronomers write them.

    Formats: FITS, VOTable, ECSV, CSV, tab- or whitespace-separated ASCII (anything astropy
    reads; the format from the content and the name). Positions: columns ``ra`` and ``dec``
    (any case; also ``RAJ2000``/``DEJ2000``, ``RA_ICRS``/``DE_ICRS``, ``ALPHA_J2000``/
    ``DELTA_J2000``, ``ra_deg``, ... :data:`RA_NAMES`, :data:`DEC_NAMES`), one SkyCoord
    column (ECSV), or CDS/VizieR split columns ``RAh RAm RAs DE- DEd DEm DEs``. Each column
    holds

    * numbers: degrees, or the unit of the column's header (``deg``, ``rad``, ``hourangle``;
      ``h`` for RA is hours) or name (``ra_hours``, ``dec_rad``);
    * text: decimal degrees (``"152.0003"``), numbers with units (``"10.1334h"``), or
      sexagesimal with spaces, colons or markers (``"10 08 00.016"``, ``"10:08:00.016"``,
      ``"10h08m00.016s"``; ``"+07 30 16.55"``, ``"+07d30m16.55s"``). Sexagesimal RA is hours
      unless the text (``d``, ``°``), the header unit or the name says degrees.

    Refused, with the row named: text that is no angle, decimal and sexagesimal rows mixed in
    one column, Dec in hours, RA outside [0, 360) deg (24h) in a file (an astropy Table made
    in Python may hold RA in (-360, 720) deg, e.g. offsets across RA 0: it is wrapped), Dec
    outside [-90, 90], empty or non-finite values. Optional ``weight`` and ``flux`` (Jy; a
    header unit such as mJy or mJy/beam is converted) columns; every other column is kept.

    Parameters
    ----------
    path : str, os.PathLike or astropy.table.Table
        Catalog file or table (Quantity and SkyCoord columns accepted).
    required_flux : bool
        Raise if there is no ``flux`` column.

    Returns
    -------
    astropy.table.Table
        A new table: float64 ``ra`` in [0, 360) and ``dec`` (degrees), then the other columns.

    Raises
    ------
    XstackError
        If the file cannot be read, a column is missing or a value is refused; the message
        names the row and why.
    """
    from astropy.coordinates import SkyCoord

    wrap = isinstance(path, Table)  # positions computed in Python may cross RA 0
    if isinstance(path, Table):
        table, label = Table(path, copy=True), "catalog"
    else:
        label = str(path)
        if not os.path.exists(label):
            raise XstackError(f"{label}: no such catalog file")
        table = _read_table(label)
    lower: dict[str, str] = {}
    for colname in table.colnames:
        lower.setdefault(colname.strip().lower(), colname)

    def find(candidates: tuple[str, ...]) -> str | None:
        return next((lower[c] for c in candidates if c in lower), None)

    ra_col, dec_col = find(RA_NAMES), find(DEC_NAMES)
    coord_col = None
    split = None
    if ra_col is None and dec_col is None:
        coords = [n for n in table.colnames if isinstance(table[n], SkyCoord)]
        if len(coords) == 1:
            coord_col = coords[0]
        elif "rah" in lower and "ded" in lower:
            split = _split_columns(table, lower)
    if coord_col is None and split is None:
        missing = [n for n, c in (("ra", ra_col), ("dec", dec_col)) if c is None]
        if missing:
            raise XstackError(f"{label}: missing column(s) {', '.join(missing)} "
                              f"(found: {', '.join(table.colnames) or 'none'})")
    if len(table) == 0:
        raise XstackError(f"{label}: catalog has no rows")
    if split is not None:
        (ra_text, ra_names), (dec_text, dec_names) = split
        ra = _column_to_degrees(ra_text, "/".join(ra_names), True, label)
        dec = _column_to_degrees(dec_text, "/".join(dec_names), False, label)
        ra_col, dec_col = ra_names, dec_names
    elif coord_col is not None:
        icrs = table[coord_col].icrs
        ra = _column_to_degrees(icrs.ra.to(u.deg), coord_col, True, label, wrap)
        dec = _column_to_degrees(icrs.dec.to(u.deg), coord_col, False, label)
    else:
        ra = _column_to_degrees(table[ra_col], ra_col, True, label, wrap)
        dec = _column_to_degrees(table[dec_col], dec_col, False, label)
    out = Table()
    out["ra"] = ra
    out["ra"].unit = u.deg
    out["dec"] = dec
    out["dec"].unit = u.deg
    units: dict[str, Any] = {}
    for name in table.colnames:
        if name in (ra_col, dec_col, coord_col) or (split and (name in ra_col or name in dec_col)):
            continue
        key = name.lower() if name.lower() in ("weight", "flux") else name
        units[key] = getattr(table[name], "unit", None)
        out[key] = table[name]
    for key in ("weight", "flux"):
        if key in out.colnames:
            try:
                values = np.asarray(out[key], dtype=np.float64)
            except (TypeError, ValueError):
                bad = next(i for i, v in enumerate(out[key]) if not _is_number(v))
                raise XstackError(f"{label}: row {bad + 1}: {key}={out[key][bad]!r} is not "
                                  "a number") from None
            bad_rows = np.flatnonzero(~np.isfinite(values))
            if bad_rows.size:
                raise XstackError(f"{label}: row {bad_rows[0] + 1}: {key} is not finite")
            unit = units.get(key)
            if key == "flux" and unit is not None and unit != u.dimensionless_unscaled:
                try:
                    unit = u.Unit(unit)
                    if unit.is_equivalent(u.Jy / u.beam):  # a peak: Jy/beam of a point source
                        unit = unit * u.beam
                    values = values * float(unit.to(u.Jy))
                except (ValueError, u.UnitsError):
                    raise XstackError(f"{label}: column flux has unit {unit}, not a flux "
                                      "density") from None
            out[key] = values
    if "weight" in out.colnames and np.any(out["weight"] < 0):
        bad = int(np.argmax(out["weight"] < 0))
        raise XstackError(f"{label}: row {bad + 1}: negative weight")
    if required_flux and "flux" not in out.colnames:
        raise XstackError(f"{label}: missing column flux (Jy)")
    return out


def _is_number(value: Any) -> bool:
    try:
        float(value)
        return True
    except (TypeError, ValueError):
        return False
