"""Sky geometry, unit parsing and catalogs shared by every stage.

Conventions (``docs/conventions.md``): direction cosines relative to a phase centre
(ra0, dec0) are, exactly,

    l = cos(dec) sin(ra - ra0)
    m = sin(dec) cos(dec0) - cos(dec) sin(dec0) cos(ra - ra0)
    n = sqrt(1 - l^2 - m^2)

and a point source of flux S at (l, m) appears in the visibilities as
``S exp(+2 pi i (u l + v m + w (n - 1)) / lambda)`` with (u, v, w) as stored in the MS.
"""

from __future__ import annotations

import os
import re
from typing import Any

import numpy as np
from astropy import units as u
from astropy.table import Table

from xstack.errors import XstackError

SPEED_OF_LIGHT = 299_792_458.0  # m/s


def radec_to_lmn(ra: Any, dec: Any, ra0: float, dec0: float) -> tuple[np.ndarray, ...]:
    """Direction cosines (l, m, n) of (ra, dec) relative to the phase centre (ra0, dec0).

    All angles in radians; arithmetic in float64. ``n - 1`` is returned as well, computed
    without cancellation (``-(l^2 + m^2) / (1 + n)``), since the w-term needs it to full
    precision even for positions close to the phase centre.

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


_DIST_RE = re.compile(r"^\s*([-+]?[0-9.]+(?:[eE][-+]?[0-9]+)?)\s*([A-Za-z]*)\s*$")
_LAMBDA_UNITS = {"lambda": 1.0, "klambda": 1e3, "mlambda": 1e6, "kl": 1e3, "ml": 1e6}


def parse_distance(text: str | float) -> tuple[float, str]:
    """Parse a uv distance such as ``5000m``, ``5km``, ``23.8klambda`` or ``1e5lambda``.

    Returns
    -------
    value, unit : float, str
        ``unit`` is ``"m"`` (value in metres) or ``"lambda"`` (value in wavelengths).
        A bare number is taken as metres.
    """
    if isinstance(text, (int, float)):
        return float(text), "m"
    match = _DIST_RE.match(str(text))
    if not match:
        raise XstackError(f"cannot read uv distance {text!r} (examples: 5000m, 23.8klambda)")
    value, unit = float(match.group(1)), match.group(2).lower()
    if unit in ("", "m"):
        return value, "m"
    if unit == "km":
        return value * 1e3, "m"
    if unit in _LAMBDA_UNITS:
        return value * _LAMBDA_UNITS[unit], "lambda"
    raise XstackError(f"unknown unit {match.group(2)!r} in uv distance {text!r} "
                      "(use m, km, lambda, klambda or Mlambda)")


def parse_flux(text: str | float) -> float:
    """Parse a flux density such as ``20uJy``, ``2mJy``, ``1.5e-3`` (Jy); return Jy."""
    if isinstance(text, (int, float)):
        return float(text)
    try:
        q = u.Quantity(re.sub(r"([0-9.])\s*([a-zA-Zµ])", r"\1 \2", str(text).strip())
                       .replace("µJy", "uJy"))
    except (TypeError, ValueError):
        raise XstackError(f"cannot read flux {text!r} (examples: 20uJy, 2mJy)") from None
    if q.unit == u.dimensionless_unscaled:
        return float(q.value)
    try:
        return float(q.to_value(u.Jy))
    except u.UnitConversionError:
        raise XstackError(f"{text!r} is not a flux density (examples: 20uJy, 2mJy)") from None


def _column_to_degrees(column: Any, name: str, is_ra: bool, path: str) -> np.ndarray:
    """Convert a catalog column of degrees or sexagesimal strings to float64 degrees."""
    from astropy.coordinates import Angle

    unit = getattr(column, "unit", None)
    values = np.asarray(column)
    out = np.empty(len(values), dtype=np.float64)
    for i, value in enumerate(values):
        if np.ma.is_masked(value):
            raise XstackError(f"{path}: row {i + 1}: column {name!r} is empty")
        try:
            if isinstance(value, (str, bytes, np.str_)):
                text = value.decode() if isinstance(value, bytes) else str(value)
                try:
                    out[i] = float(text)
                except ValueError:
                    sexa_unit = (u.hourangle if is_ra and (":" in text or "h" in text)
                                 else u.deg)
                    out[i] = Angle(text, unit=sexa_unit).degree
            else:
                val = float(value)
                if unit is not None and unit != u.dimensionless_unscaled:
                    val = (val * unit).to_value(u.deg)
                out[i] = val
        except (ValueError, TypeError, u.UnitsError):
            raise XstackError(f"{path}: row {i + 1}: cannot read {name}={value!r} as an "
                              "angle (degrees or sexagesimal)") from None
        if not np.isfinite(out[i]):
            raise XstackError(f"{path}: row {i + 1}: {name} is not finite")
    if not is_ra and np.any(np.abs(out) > 90):
        bad = int(np.argmax(np.abs(out) > 90))
        raise XstackError(f"{path}: row {bad + 1}: dec={out[bad]} is outside [-90, 90] deg")
    return out


def read_catalog(path: str | os.PathLike | Table, required_flux: bool = False) -> Table:
    """Read a table of stacking positions (CSV, ECSV, FITS, VOTable: anything astropy reads).

    Columns: ``ra`` and ``dec`` (degrees or sexagesimal strings; case-insensitive, ``RA``,
    ``ra_deg`` ... accepted), optional ``weight`` and ``flux`` (Jy). Returns a new table with
    float64 ``ra`` and ``dec`` in degrees (RA wrapped to [0, 360)) and every other column kept.

    Raises
    ------
    XstackError
        If the file cannot be read, a column is missing, or a row is not numeric; the message
        names the row.
    """
    if isinstance(path, Table):
        table, label = Table(path, copy=True), "catalog"
    else:
        label = str(path)
        if not os.path.exists(label):
            raise XstackError(f"{label}: no such catalog file")
        table = None
        errors = []
        fmts = [None, "ascii.ecsv", "ascii.csv", "ascii.basic", "ascii"]
        for fmt in fmts:
            try:
                table = Table.read(label, format=fmt) if fmt else Table.read(label)
                break
            except Exception as exc:  # astropy raises many types while guessing a format
                errors.append(str(exc))
        if table is None:
            raise XstackError(f"{label}: cannot read as a table ({errors[-1][:200]})")
    lower = {name.lower(): name for name in table.colnames}

    def find(*candidates: str) -> str | None:
        for cand in candidates:
            if cand in lower:
                return lower[cand]
        return None

    ra_col = find("ra", "ra_deg", "raj2000", "ra_j2000", "alpha")
    dec_col = find("dec", "dec_deg", "dej2000", "decj2000", "dec_j2000", "delta")
    missing = [n for n, c in (("ra", ra_col), ("dec", dec_col)) if c is None]
    if missing:
        raise XstackError(f"{label}: missing column(s) {', '.join(missing)} "
                          f"(found: {', '.join(table.colnames) or 'none'})")
    if len(table) == 0:
        raise XstackError(f"{label}: catalog has no rows")
    ra = np.mod(_column_to_degrees(table[ra_col], "ra", True, label), 360.0)
    dec = _column_to_degrees(table[dec_col], "dec", False, label)
    out = Table()
    out["ra"] = ra
    out["ra"].unit = u.deg
    out["dec"] = dec
    out["dec"].unit = u.deg
    for name in table.colnames:
        if name in (ra_col, dec_col):
            continue
        key = name.lower() if name.lower() in ("weight", "flux") else name
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
