"""Primary-beam models: power attenuation A(theta, nu) of a single dish, per channel.

Models (``docs/conventions.md``):

``airy``
    Power pattern of a uniformly illuminated circular aperture of diameter D with a central
    blockage of diameter b (epsilon = b / D)::

        E(x) = [2 J1(x)/x - eps^2 2 J1(eps x)/(eps x)] / (1 - eps^2),  x = pi D sin(theta) / lambda
        A = E^2

    ALMA 12 m antennas use D = 10.7 m, b = 0.75 m (the convention of CASA's ALMA model);
    any other telescope uses its physical dish and no blockage unless told otherwise.
``gaussian``
    A = exp(-4 ln 2 theta^2 / FWHM^2) with FWHM = 1.13 lambda / D (the ALMA handbook value).
``vla``
    The polynomial models of EVLA Memo 195 (Perley 2016), as CASA applies them:
    A = 1 + a x^2 + b x^4 + c x^6 (+ d x^8), x = theta[arcmin] * nu[GHz]; coefficients of the
    tabulated frequency nearest to each channel. Beyond the first null A = 0.

``standard_beam(telescope, dish_diameter)`` picks the telescope's standard model;
``dish_diameter(ds)`` reads a partition's dish diameter from its data. This module is the one
home of that vocabulary: :data:`DEFAULT_PB_CUTOFF`, :data:`TELESCOPE_DISH_DIAMETERS`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import j1

from xstack import _vocabulary
from xstack.coords import SPEED_OF_LIGHT
from xstack.errors import OptionError, SchemaError

#: Default attenuation below which a position is taken to be outside a pointing (defined in
#: the import-free :mod:`xstack._vocabulary` so the command line can use it cheaply).
DEFAULT_PB_CUTOFF = _vocabulary.DEFAULT_PB_CUTOFF

#: Primary-beam models by name.
BEAM_MODELS = ("airy", "gaussian", "vla", "none")

#: Physical dish diameters (m) of telescopes by (upper-case) name, for data and images that
#: do not carry their own (a FITS image's TELESCOP; a partition without DISH_DIAMETER).
TELESCOPE_DISH_DIAMETERS = {"ALMA": 12.0, "VLA": 25.0, "EVLA": 25.0, "JVLA": 25.0,
                            "MEERKAT": 13.5, "ATCA": 22.0, "WSRT": 25.0, "GMRT": 45.0,
                            "SMA": 6.0, "NOEMA": 15.0}


def telescope_dish_diameter(telescope: str) -> float:
    """Physical dish diameter (m) of a telescope known by name.

    Raises
    ------
    SchemaError
        If the telescope is not in :data:`TELESCOPE_DISH_DIAMETERS`.
    """
    name = str(telescope).strip().upper()
    if name not in TELESCOPE_DISH_DIAMETERS:
        raise SchemaError(f"no dish diameter for telescope {telescope!r} (known: "
                          f"{', '.join(sorted(TELESCOPE_DISH_DIAMETERS))})")
    return TELESCOPE_DISH_DIAMETERS[name]


def dish_diameter(ds: Any) -> float:
    """The dish diameter (m) of one partition, from its data.

    The median of the positive values of ``DISH_DIAMETER`` (antennas of one array share a
    beam model); if the partition has none, the physical dish of its ``telescope_name``
    (:data:`TELESCOPE_DISH_DIAMETERS`). Never a silent guess.

    Parameters
    ----------
    ds
        A partition (:class:`xarray.Dataset`) of a processing set.

    Returns
    -------
    float
        Dish diameter, metres.

    Raises
    ------
    SchemaError
        If the partition has no positive ``DISH_DIAMETER`` and its telescope is unknown.
    """
    if "DISH_DIAMETER" in ds.variables:
        values = np.asarray(ds["DISH_DIAMETER"].values, dtype=np.float64).ravel()
        values = values[np.isfinite(values) & (values > 0)]
        if values.size:
            return float(np.median(values))
    telescope = str(ds.attrs.get("telescope_name", ""))
    try:
        return telescope_dish_diameter(telescope)
    except SchemaError:
        raise SchemaError(f"the data carry no DISH_DIAMETER and telescope {telescope!r} has "
                          "no known dish diameter; add DISH_DIAMETER to the store") from None

# EVLA Memo 195 (Perley 2016) coefficients (a, b, c[, d]) by frequency in MHz; the full
# L band (the paper's 1.4 GHz) and one representative set in each higher band.
_VLA_COEFFS_MHZ: dict[float, tuple[float, ...]] = {
    1040: (-1.529e-3, 8.69e-7, -1.88e-10),
    1104: (-1.486e-3, 8.15e-7, -1.68e-10),
    1168: (-1.439e-3, 7.53e-7, -1.45e-10),
    1232: (-1.450e-3, 7.87e-7, -1.63e-10),
    1296: (-1.428e-3, 7.62e-7, -1.54e-10),
    1360: (-1.449e-3, 8.02e-7, -1.74e-10),
    1424: (-1.462e-3, 8.23e-7, -1.83e-10),
    1488: (-1.455e-3, 7.92e-7, -1.63e-10),
    1552: (-1.435e-3, 7.54e-7, -1.49e-10),
    1680: (-1.443e-3, 7.74e-7, -1.57e-10),
    1744: (-1.462e-3, 8.02e-7, -1.69e-10),
    1808: (-1.488e-3, 8.38e-7, -1.83e-10),
    1872: (-1.486e-3, 8.26e-7, -1.75e-10),
    1936: (-1.459e-3, 7.93e-7, -1.62e-10),
    2000: (-1.508e-3, 8.31e-7, -1.68e-10),
    3052: (-1.467e-3, 8.05e-7, -1.70e-10),
    6052: (-1.445e-3, 7.68e-7, -1.50e-10),
    10052: (-1.421e-3, 7.46e-7, -1.45e-10),
    15052: (-1.402e-3, 7.38e-7, -1.48e-10),
    21948: (-1.439e-3, 7.82e-7, -1.61e-10),
    28564: (-1.455e-3, 7.87e-7, -1.59e-10),
}
_VLA_FREQS = np.array(sorted(_VLA_COEFFS_MHZ))


@dataclass(frozen=True)
class PrimaryBeam:
    """A circularly symmetric primary-beam model.

    Parameters
    ----------
    model
        ``"airy"``, ``"gaussian"``, ``"vla"`` or ``"none"`` (A = 1 everywhere).
    dish_diameter
        Effective aperture diameter D, metres; required by ``airy`` and ``gaussian`` (no
        default: take it from the data, :func:`dish_diameter`).
    blockage_diameter
        Central blockage diameter b, metres (``airy``).
    cutoff
        Attenuation below which a direction counts as outside the beam.
    """

    model: str = "airy"
    dish_diameter: float = 0.0
    blockage_diameter: float = 0.0
    cutoff: float = DEFAULT_PB_CUTOFF

    def __post_init__(self) -> None:
        if self.model not in BEAM_MODELS:
            raise OptionError(f"unknown primary-beam model {self.model!r} "
                              "(use airy, gaussian, vla or none)")
        if self.model in ("airy", "gaussian") and not self.dish_diameter > 0:
            raise OptionError(f"dish diameter must be positive, got {self.dish_diameter}")
        blockage_ok = self.blockage_diameter == 0 or 0 < self.blockage_diameter < self.dish_diameter
        if not blockage_ok or not 0 <= self.cutoff < 1:
            raise OptionError("primary beam: need 0 <= blockage < dish and 0 <= cutoff < 1")

    def __call__(self, theta: Any, frequency: Any) -> np.ndarray:
        """Power attenuation at angular distance ``theta`` (rad) and ``frequency`` (Hz).

        ``theta`` and ``frequency`` broadcast against each other.
        """
        theta = np.asarray(theta, dtype=np.float64)
        freq = np.asarray(frequency, dtype=np.float64)
        if self.model == "none":
            return np.ones(np.broadcast_shapes(theta.shape, freq.shape))
        if self.model == "gaussian":
            fwhm = 1.13 * SPEED_OF_LIGHT / (freq * self.dish_diameter)
            return np.exp(-4.0 * np.log(2.0) * (theta / fwhm) ** 2)
        if self.model == "airy":
            return _airy_power(theta, freq, self.dish_diameter, self.blockage_diameter)
        return _vla_power(theta, freq)

    def fwhm(self, frequency: float) -> float:
        """Full width at half maximum (rad) at ``frequency`` (Hz), found numerically."""
        from scipy.optimize import brentq

        if self.model == "none":
            return np.inf
        guess = 1.5 * SPEED_OF_LIGHT / (frequency * max(self.dish_diameter, 1.0))
        return 2.0 * brentq(lambda t: float(self(t, frequency)) - 0.5, 1e-9, 2 * guess)

    def first_null(self, frequency: Any) -> np.ndarray:
        """Angular radius (rad) of the first null, the edge of the main lobe, per frequency (Hz).

        Infinite for ``gaussian`` and ``none``. Primary-beam correction divides by A, which is
        meaningful only inside the main lobe: stacking never uses a direction beyond it, even
        where a sidelobe of the model rises above the cutoff.
        """
        freq = np.asarray(frequency, dtype=np.float64)
        if self.model in ("none", "gaussian"):
            return np.full(freq.shape, np.inf)
        if self.model == "vla":
            idx = np.abs(_VLA_FREQS[:, None] - np.ravel(freq * 1e-6)[None, :]).argmin(axis=0)
            x = np.sqrt(_VLA_NULLS[idx.reshape(freq.shape)])  # arcmin * GHz
            return np.radians(x / (freq * 1e-9) / 60.0)
        x0 = _airy_first_zero(self.blockage_diameter / self.dish_diameter)
        s = x0 * SPEED_OF_LIGHT / (np.pi * self.dish_diameter * freq)
        return np.where(s < 1.0, np.arcsin(np.minimum(s, 1.0)), np.pi / 2)

    def main_lobe(self, theta: Any, frequency: Any) -> np.ndarray:
        """Attenuation for primary-beam correction: A inside the main lobe, 0 beyond the
        first null (where a model sidelobe would otherwise be divided by). Broadcasts like
        :meth:`__call__`."""
        theta = np.asarray(theta, dtype=np.float64)
        return np.where(theta < self.first_null(frequency), self(theta, frequency), 0.0)

    def radius_at(self, level: float, frequency: float) -> float:
        """Angular radius (rad) where the attenuation first falls to ``level``."""
        from scipy.optimize import brentq

        if self.model == "none":
            return np.inf
        guess = 1.5 * SPEED_OF_LIGHT / (frequency * max(self.dish_diameter, 1.0))
        hi = guess
        while float(self(hi, frequency)) > level and hi < np.pi / 2:
            hi *= 1.5
        return brentq(lambda t: float(self(t, frequency)) - level, 0.0, hi)


def _airy_first_zero(eps: float) -> float:
    """First zero x0 of the blocked-aperture voltage pattern (3.8317 for eps = 0)."""
    from scipy.optimize import brentq

    def voltage(x: float) -> float:
        return 2.0 * j1(x) / x - eps**2 * 2.0 * j1(eps * x) / (eps * x) if eps > 0 else 2.0 * j1(x) / x

    return float(brentq(voltage, 1.0, 3.8318))  # blockage moves the null inwards


def _airy_power(theta: np.ndarray, freq: np.ndarray, diameter: float, blockage: float) -> np.ndarray:
    x = np.pi * diameter * np.sin(theta) * freq / SPEED_OF_LIGHT
    eps = blockage / diameter
    small = np.abs(x) < 1e-8
    xs = np.where(small, 1.0, x)
    jinc = np.where(small, 1.0, 2.0 * j1(xs) / xs)
    if eps > 0:
        ex = eps * xs
        jinc_b = np.where(small, 1.0, 2.0 * j1(ex) / ex)
        voltage = (jinc - eps**2 * jinc_b) / (1.0 - eps**2)
    else:
        voltage = jinc
    return voltage * voltage


def _pad4(c: tuple[float, ...]) -> tuple[float, float, float, float]:
    return tuple(c) + (0.0,) * (4 - len(c))  # type: ignore[return-value]


def _first_null_x2(coeffs: tuple[float, float, float, float]) -> float:
    """Smallest positive y = x^2 where 1 + a y + b y^2 + c y^3 + d y^4 = 0."""
    a, b, c, d = coeffs
    roots = np.roots([d, c, b, a, 1.0])
    real = roots[(np.abs(roots.imag) < 1e-9 * np.abs(roots)) & (roots.real > 0)].real
    return float(real.min()) if real.size else np.inf


_VLA_TABLE = np.array([_pad4(_VLA_COEFFS_MHZ[f]) for f in _VLA_FREQS])
_VLA_NULLS = np.array([_first_null_x2(tuple(row)) for row in _VLA_TABLE])


def _vla_power(theta: np.ndarray, freq: np.ndarray) -> np.ndarray:
    freq_mhz = freq * 1e-6
    idx = np.abs(_VLA_FREQS[:, None] - np.ravel(freq_mhz)[None, :]).argmin(axis=0)
    idx = idx.reshape(np.shape(freq_mhz))
    a, b, c, d = (_VLA_TABLE[idx, k] for k in range(4))
    x2 = (np.degrees(theta) * 60.0 * freq_mhz / 1e3) ** 2
    power = 1.0 + x2 * (a + x2 * (b + x2 * (c + x2 * d)))
    # the polynomial describes the main lobe only: zero from the first null outwards
    return np.where((x2 < _VLA_NULLS[idx]) & (power > 0), power, 0.0)


def standard_beam(telescope: str, dish_diameter: float | None = None, model: str | None = None,
                  cutoff: float = DEFAULT_PB_CUTOFF) -> PrimaryBeam:
    """The conventional primary beam of a telescope.

    Parameters
    ----------
    telescope
        Telescope name as in an MS (``ALMA``, ``VLA``, ``EVLA``, ...).
    dish_diameter
        Physical dish diameter, metres (from the data: :func:`dish_diameter`); None takes the
        telescope's from :data:`TELESCOPE_DISH_DIAMETERS` (an unknown telescope is an error).
    model
        Force ``airy``, ``gaussian`` or ``none``; ``None`` picks the telescope's standard.
    cutoff
        Attenuation below which a direction is outside the beam.
    """
    name = telescope.strip().upper()
    if model == "none":
        return PrimaryBeam("none", cutoff=cutoff)
    if dish_diameter is None:
        dish_diameter = telescope_dish_diameter(name)
    is_alma = name.startswith("ALMA") and abs(dish_diameter - 12.0) < 0.5
    if model in (None, "airy") and is_alma:
        return PrimaryBeam("airy", 10.7, 0.75, cutoff)
    if model is None and name in ("VLA", "EVLA", "JVLA"):
        return PrimaryBeam("vla", dish_diameter, 0.0, cutoff)
    if model == "gaussian":
        return PrimaryBeam("gaussian", dish_diameter, 0.0, cutoff)
    return PrimaryBeam("airy", dish_diameter, 0.0, cutoff)


# ---------------------------------------------------------------------------------------------
# the one rule for "inside the field" (docs/conventions.md, "Inside the field")
# ---------------------------------------------------------------------------------------------

#: FITS keyword in which an image records the highest channel frequency (Hz) of the data it
#: was made from: the band edge at which :func:`inside_field` decides.
BAND_TOP_KEY = "XSFRQHI"


def covered(attenuation: Any, cutoff: float) -> np.ndarray:
    """Attenuation at the band edge -> inside: ``A >= cutoff`` and ``A > 0``.

    ``A > 0`` keeps a zero attenuation (beyond the first null, off a beam image) outside
    even with ``cutoff = 0``.
    """
    a = np.nan_to_num(np.asarray(attenuation, dtype=np.float64), nan=0.0)
    return (a >= cutoff) & (a > 0)


def inside_field(beam: Any, theta: Any, frequencies: Any, cutoff: float | None = None) -> np.ndarray:
    """Whether directions lie inside a pointing: the one rule every stage uses.

    A direction at angular distance ``theta`` from the pointing center is inside when it lies
    inside the main lobe and the attenuation is ``A >= cutoff`` at the **highest frequency the
    data span** (the band edge, where the beam is narrowest). For a circular beam A falls
    with theta * nu inside the main lobe, so this is the same as "A >= cutoff in every
    channel" for any set of channels with that highest frequency: the channels of a
    partition (uvstack, uv-domain noise) and the band an image covers (imstack, image-domain
    noise) give the same answer. (For the ``vla`` model, whose coefficients change with
    frequency, the rule is by definition that of the highest frequency.)

    Parameters
    ----------
    beam
        A :class:`PrimaryBeam` (its main lobe is used), or a callable
        ``beam(theta, frequency) -> A`` (theta in rad, frequency in Hz) for a sampled beam
        (a beam image).
    theta
        Angular distances from the pointing center, rad.
    frequencies
        Channel frequencies of the data, or the band (low, high), Hz; only the highest is
        used.
    cutoff
        Attenuation below which a direction is outside (default: the beam's ``cutoff``,
        else :data:`DEFAULT_PB_CUTOFF`).

    Returns
    -------
    numpy.ndarray
        bool, shaped like ``theta``. All True for the ``none`` model.
    """
    theta = np.asarray(theta, dtype=np.float64)
    top = float(np.max(np.asarray(frequencies, dtype=np.float64)))
    if cutoff is None:
        cutoff = float(getattr(beam, "cutoff", DEFAULT_PB_CUTOFF))
    if isinstance(beam, PrimaryBeam):
        if beam.model == "none":
            return np.ones(theta.shape, dtype=bool)
        return covered(beam.main_lobe(theta, top), cutoff)
    return covered(np.reshape(beam(theta, top), theta.shape), cutoff)
