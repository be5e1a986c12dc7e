"""Spectral-line vocabulary shared by the stages: rest frequencies, redshifts, velocities.

One place for what every line-stacking stage (simulator, uv- and image-domain line stacks,
noise) agrees on:

* the rest frequencies of the lines users stack, by name (:data:`LINES`, :func:`rest_frequency`);
* a target's observed line centre, nu_c = nu_rest / (1 + z) (:func:`observed_line_centre`);
* the velocity of a frequency about that centre, v = c (nu_c - nu) / nu_c (:func:`velocity_kms`)
  and its inverse (:func:`frequency_hz`) — the convention of DESIGN.md section 2: the rest-frame
  velocity offset of the emission from the target's own systemic velocity, positive for lower
  frequencies (receding gas).

Frequencies are in Hz, velocities in km/s, as at every xstack interface.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from xstack.errors import OptionError

#: The speed of light in km/s (exact, SI).
SPEED_OF_LIGHT_KMS = 299_792.458

#: Rest frequencies in Hz of the lines that are stacked most (CDMS / JPL line catalogues via
#: Splatalogue; HI: the hyperfine transition). Names are matched case-insensitively and
#: without spaces, brackets kept: ``HI``, ``CO(1-0)``, ``[CII]``.
LINES: dict[str, float] = {
    "HI": 1_420_405_751.768,
    "OH(1667)": 1_667_358_996.0,
    "CO(1-0)": 115.2712018e9,
    "CO(2-1)": 230.5380000e9,
    "CO(3-2)": 345.7959899e9,
    "CO(4-3)": 461.0407682e9,
    "CO(5-4)": 576.2679305e9,
    "CO(6-5)": 691.4730763e9,
    "CO(7-6)": 806.6518060e9,
    "[CI](1-0)": 492.1606510e9,
    "[CI](2-1)": 809.3419700e9,
    "[CII]": 1900.5369e9,
    "[NII]205": 1461.1314e9,
    "[OIII]88": 3393.006244e9,
    "HCN(1-0)": 88.6318473e9,
    "HCO+(1-0)": 89.1885247e9,
}


def _key(name: str) -> str:
    return "".join(name.split()).upper()


_BY_KEY = {_key(name): name for name in LINES}


def rest_frequency(line: Any) -> float:
    """The rest frequency of a line in Hz.

    Parameters
    ----------
    line
        A line name of :data:`LINES` (``"HI"``, ``"co(2-1)"``, ``"[CII]"``), a frequency with
        units (``"1420.405751786MHz"``, an astropy Quantity) or a number in Hz.

    Returns
    -------
    float
        Hz, > 0.

    Raises
    ------
    OptionError
        An unknown name (the message lists the known ones) or a frequency <= 0.
    """
    if isinstance(line, str):
        name = _BY_KEY.get(_key(line))
        if name is not None:
            return LINES[name]
        from xstack.coords import parse_frequency

        try:
            value = parse_frequency(line, "Hz")
        except Exception:
            raise OptionError(f"{line!r} is neither a known line ({', '.join(LINES)}) nor a "
                              "frequency such as 1420.405751786MHz",
                              option="line_frequency") from None
    else:
        try:
            import astropy.units as u

            value = (u.Quantity(line).to_value(u.Hz, equivalencies=u.spectral())
                     if hasattr(line, "unit") else float(line))
        except (TypeError, ValueError, u.UnitsError):
            raise OptionError(f"line frequency {line!r} is not a frequency",
                              option="line_frequency") from None
    if not (np.isfinite(value) and value > 0):
        raise OptionError(f"line frequency must be > 0 Hz, got {value!r}", option="line_frequency")
    return float(value)


def observed_line_centre(rest_hz: float, z: Any) -> np.ndarray:
    """Observed line centres nu_c = nu_rest / (1 + z) in Hz (z > -1, elementwise)."""
    z = np.asarray(z, dtype=np.float64)
    return np.float64(rest_hz) / (1.0 + z)


def velocity_kms(freq_hz: Any, centre_hz: Any) -> np.ndarray:
    """v = c (nu_c - nu) / nu_c in km/s of frequencies ``freq_hz`` about centres ``centre_hz``.

    At the target's rest frame this is the velocity offset from the systemic one to first order
    in v/c and exact for the observed-frequency scale: a channel of width d(nu) spans
    c d(nu) / nu_c in velocity, the same for every channel of one target.
    """
    centre = np.asarray(centre_hz, dtype=np.float64)
    return SPEED_OF_LIGHT_KMS * (centre - np.asarray(freq_hz, dtype=np.float64)) / centre


def frequency_hz(velocity: Any, centre_hz: Any) -> np.ndarray:
    """The inverse of :func:`velocity_kms`: nu = nu_c (1 - v / c) in Hz."""
    return np.asarray(centre_hz, dtype=np.float64) * (
        1.0 - np.asarray(velocity, dtype=np.float64) / SPEED_OF_LIGHT_KMS)


# --- velocity grids and regridding (the line stacks) ----------------------------------------

def velocity_edges(resolution_kms: Any, range_kms: Any) -> np.ndarray:
    """Edges (km/s, increasing) of the common velocity grid of a line stack.

    Bins of width ``resolution_kms`` from ``range_kms[0]``; when the range is not a whole
    number of bins the last bin ends beyond ``range_kms[1]`` (the range is covered, never cut).

    Raises
    ------
    OptionError
        A resolution <= 0 (``velocity_resolution``) or a range that is not two finite
        increasing velocities (``velocity_range``).
    """
    try:
        res = float(resolution_kms)
    except (TypeError, ValueError):
        res = float("nan")
    if not (np.isfinite(res) and res > 0):
        raise OptionError(f"velocity resolution must be > 0 km/s, got {resolution_kms!r}",
                          option="velocity_resolution")
    try:
        lo, hi = (float(x) for x in range_kms)
    except (TypeError, ValueError):
        lo = hi = float("nan")
    if not (np.isfinite(lo) and np.isfinite(hi) and hi > lo):
        raise OptionError(f"velocity range must be two increasing velocities in km/s, got "
                          f"{range_kms!r}", option="velocity_range")
    # a tolerance so that e.g. (-600, 600) at 20 km/s is exactly 60 bins
    nbin = max(1, int(np.ceil((hi - lo) / res - 1e-9)))
    return lo + res * np.arange(nbin + 1, dtype=np.float64)


def overlap_lengths(src_edges: Any, dst_edges: Any) -> np.ndarray:
    """Length of each source interval inside each destination bin, (nsrc, ndst).

    Parameters
    ----------
    src_edges
        (nsrc + 1,) edges of contiguous source intervals (increasing or decreasing), or
        (nsrc, 2) intervals (either order within a pair; gaps and overlaps allowed).
    dst_edges
        (ndst + 1,) increasing edges of the destination bins.

    Flux-conserving regridding: a source density f_i spread uniformly over its interval puts
    ``f_i * o[i, j]`` into bin j; sum_j o[i, j] is the part of interval i inside the grid, so
    the integral over the grid is conserved exactly. Units are those of the edges.
    """
    src = np.asarray(src_edges, dtype=np.float64)
    if src.ndim == 1:
        src = np.column_stack([src[:-1], src[1:]])
    if src.ndim != 2 or src.shape[1] != 2:
        raise ValueError("src_edges must be (n + 1,) edges or (n, 2) intervals")
    dst = np.asarray(dst_edges, dtype=np.float64)
    if dst.ndim != 1 or dst.size < 2 or np.any(np.diff(dst) <= 0):
        raise ValueError("dst_edges must be increasing (n + 1,) edges")
    lo = np.minimum(src[:, 0], src[:, 1])[:, None]
    hi = np.maximum(src[:, 0], src[:, 1])[:, None]
    return np.clip(np.minimum(hi, dst[None, 1:]) - np.maximum(lo, dst[None, :-1]), 0.0, None)


def line_centres_hz(table: Any, rest_hz: float) -> np.ndarray:
    """Observed line centres (Hz) of a catalog's targets: from ``z`` or ``freq``.

    ``z``: nu_c = rest_hz / (1 + z). ``freq``: the observed line centre itself, converted
    from the column's unit (astropy: Hz, MHz, GHz, or a wavelength/energy through the
    spectral equivalency), in Hz when the column has none. With both, ``freq`` is used.

    Raises
    ------
    XstackError
        No ``z`` or ``freq`` column, or rows whose centre is not finite and positive
        (z <= -1, missing values): the first few are named (1-based).
    """
    from xstack.errors import XstackError

    names = list(getattr(table, "colnames", []))
    if "freq" in names:
        col = table["freq"]
        unit = getattr(col, "unit", None)
        values = np.ma.filled(np.ma.asarray(col, dtype=np.float64), np.nan)
        if unit is not None:
            import astropy.units as u

            try:
                values = (values * u.Unit(unit)).to_value(u.Hz, equivalencies=u.spectral())
            except u.UnitsError:
                raise XstackError(f"catalog column freq has unit {unit}, not a frequency") \
                    from None
        what = "freq"
    elif "z" in names:
        z = np.ma.filled(np.ma.asarray(table["z"], dtype=np.float64), np.nan)
        with np.errstate(divide="ignore", invalid="ignore"):
            values = np.where(z > -1, observed_line_centre(rest_hz, z), np.nan)
        what = "z"
    else:
        raise XstackError("a line stack needs a catalog column z (redshift) or freq (observed "
                          f"line centre); the catalog has {', '.join(names) or 'no columns'}")
    values = np.asarray(values, dtype=np.float64)
    bad = np.flatnonzero(~(np.isfinite(values) & (values > 0)))
    if bad.size:
        rows = ", ".join(str(i + 1) for i in bad[:10]) + (" ..." if bad.size > 10 else "")
        raise XstackError(f"catalog rows {rows}: no valid line centre from column {what} "
                          f"({bad.size} of {len(values)} rows)")
    return values
