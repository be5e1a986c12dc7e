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
