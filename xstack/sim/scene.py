"""Scene descriptions: what to simulate, as Python dataclasses or the same as a TOML file.

A scene has an ``array``, an ``observation`` (date, hour angles, integration, time per
pointing), a ``spectral`` set-up, ``pointings``, ``effects`` (each opt-in) and a list of
``populations``. TOML example (``docs/sim.md`` has the full reference)::

    [array]
    config = "vla.a"

    [observation]
    date = "2014-01-01"
    hour_angle = [-4.7, 4.7]        # hours
    integration = 10.0              # seconds
    time_per_pointing = 33840.0     # seconds

    [spectral]
    center = 1.4e9
    bandwidth = 250e6
    channels = 10
    polarizations = ["RR", "LL"]

    [pointings]
    mode = "single"                 # single | hexagonal | rectangular | on_population | list
    center = ["3h49m10.99s", "-30d00m00s"]

    [effects]
    primary_beam = "auto"       # none | auto (the telescope's standard beam) | airy | gaussian
    w_term = true
    noise = { sigma = 0.01 }        # or { sefd = 420.0 } or { tsys = 90.0 }
    flagging = { random_fraction = 0.0, shadowing = false }   # elevation_limit_deg = 10.0
    bandwidth_smearing = false      # channel average: sinc(pi d dnu / c)
    time_smearing = false           # integration average (Earth rotation)

    [[populations]]
    name = "targets"
    count = 25
    flux = { kind = "fixed", value = "6uJy" }
    positions = { kind = "box", size_arcsec = [300, 300] }
    shape = { kind = "point" }

Unknown keys, wrong types and impossible values raise :class:`~xstack.errors.XstackError`
naming the field (``populations[0].flux.value: ...``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tomllib
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from xstack import _vocabulary
from xstack._vocabulary import DEFAULT_PB_CUTOFF
from xstack.errors import XstackError
from xstack.sim.counts import FluxDistribution, flux_from_value

#: The paper's field center, 3h49m10.99s -30d00m00s (J2000), degrees.
PAPER_FIELD_CENTER = (57.2957916666667, -30.0)


@dataclass
class ArraySpec:
    """Antenna configuration.

    ``config`` is a packaged name (``vla.a`` … ``vla.d``, ``alma.cycle1.1`` … ``.6``) or a
    path to a CASA ``.cfg`` file; ``antennas`` keeps a subset (names or indices); or give
    ``positions`` (ITRF metres), ``diameters`` (m), ``names`` and ``telescope`` directly.
    """

    config: str = "vla.a"
    antennas: list[Any] = field(default_factory=list)
    positions: list[list[float]] = field(default_factory=list)
    diameters: list[float] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    telescope: str = ""


@dataclass
class NoiseSpec:
    """Thermal noise: ``sigma`` (Jy, per real and per imaginary part of each visibility),
    or ``sefd`` (Jy), or ``tsys`` (K) with ``aperture_efficiency``; ``efficiency`` is the
    correlator efficiency."""

    sigma: float | None = None
    sefd: float | None = None
    tsys: float | None = None
    aperture_efficiency: float = 0.71
    efficiency: float = 0.88


@dataclass
class FlaggingSpec:
    """Flagging: a random fraction of visibilities (per time, baseline, channel and
    polarization), antenna shadowing, and/or an elevation limit."""

    random_fraction: float = 0.0
    shadowing: bool = False
    #: flag every baseline of an antenna that sees the field center below this elevation
    #: (degrees; ``None``: none), as a telescope (and CASA's simulator, default 10 deg) would
    elevation_limit_deg: float | None = None


@dataclass
class Effects:
    """Opt-in effects. Each step runs only if asked for (``docs/sim.md``)."""

    primary_beam: str = "none"
    pb_cutoff: float = DEFAULT_PB_CUTOFF
    w_term: bool = False
    noise: NoiseSpec | None = None
    flagging: FlaggingSpec | None = None
    #: average each visibility over its rectangular channel (``xstack.smearing``)
    bandwidth_smearing: bool = False
    #: average each visibility over its integration (Earth rotation, first order)
    time_smearing: bool = False


@dataclass
class Observation:
    """Time sampling. Pointings are observed one after the other, ``time_per_pointing``
    seconds each, in integrations of ``integration`` s, within the ``hour_angle`` window
    (hours) of the field center on ``date``; the whole run is centered in the window when it
    fits and otherwise continues in the same window on the following days."""

    date: str = "2014-01-01"
    hour_angle: list[float] = field(default_factory=lambda: [-4.7, 4.7])
    integration: float = 10.0
    time_per_pointing: float = 33840.0


@dataclass
class Spectral:
    """Channels: ``channels`` equal channels over ``bandwidth`` (Hz) around ``center`` (Hz)."""

    center: float = 1.4e9
    bandwidth: float = 250e6
    channels: int = 10
    polarizations: list[str] = field(default_factory=lambda: ["RR", "LL"])
    #: frame of the channel frequencies, recorded in the store (:mod:`xstack.frames`):
    #: ``TOPO`` (not given: a store that does not say, read as TOPO), ``LSRK``, ``BARY``...
    frame: str | None = None
    #: rest frequency of the populations' lines: a name of :data:`xstack.spectral.LINES`
    #: (``HI``, ``CO(1-0)``...) or a frequency (Hz, or a string with units)
    line: Any = None
    #: frame the lines' centres are fixed in: ``lsrk`` (default) or ``bary``; with channels
    #: in another frame the lines move over the track (:func:`xstack.frames.frame_ratio`)
    line_frame: str | None = None

    def frequencies(self) -> tuple[np.ndarray, np.ndarray]:
        """Channel center frequencies and widths, Hz."""
        width = self.bandwidth / self.channels
        k = np.arange(self.channels) - (self.channels - 1) / 2.0
        return self.center + k * width, np.full(self.channels, width)


@dataclass
class Pointings:
    """Phase centers: ``single`` (``center``), a ``hexagonal`` or ``rectangular`` mosaic of
    ``size_arcsec`` with ``spacing_arcsec``, one pointing on each source of ``population``
    (``on_population``), or a ``list`` of ``positions`` [[ra_deg, dec_deg], ...]."""

    mode: str = "single"
    center: list[Any] = field(default_factory=lambda: list(PAPER_FIELD_CENTER))
    size_arcsec: list[float] = field(default_factory=lambda: [100.0, 100.0])
    spacing_arcsec: float = 20.0
    population: str = ""
    positions: list[list[float]] = field(default_factory=list)


@dataclass
class Positions:
    """Source positions: uniform in a ``box`` (``size_arcsec`` [width, height] in the tangent
    plane) or ``disc`` (``radius_arcsec``) around ``center`` (default: the pointings'
    center), uniform in a disc of ``radius_arcsec`` around a randomly chosen pointing
    (``around_pointings``), or a given ``list`` (``ra``, ``dec`` in degrees)."""

    kind: str = "box"
    size_arcsec: list[float] = field(default_factory=lambda: [300.0, 300.0])
    radius_arcsec: float = 0.0
    center: list[Any] = field(default_factory=list)
    ra: list[float] = field(default_factory=list)
    dec: list[float] = field(default_factory=list)


@dataclass
class Shape:
    """Source shape: ``point`` or ``gaussian`` with ``fwhm_arcsec`` fixed (one number) or
    uniform between two numbers [min, max]."""

    kind: str = "point"
    fwhm_arcsec: list[float] = field(default_factory=list)


@dataclass
class Line:
    """A spectral line on every source of a population (``docs/sim.md``).

    The line's rest frequency and frame are the scene's (``spectral.line``,
    ``spectral.line_frame``); each source has an observed centre nu_c = nu_rest / (1 + z) in
    that frame, from ``z`` ([z] fixed, [min, max] uniform), ``z_values`` (one per source) or
    ``centre_hz`` (observed centres, one per source). ``flux_jy_kms`` (integrated flux
    F = integral of S dv, v = c (nu_c - nu) / nu_c) and ``fwhm_kms`` are [value] or
    [min, max] (uniform). ``profile``: ``gaussian``, or ``double`` (a double horn: two
    Gaussians of F/2 each, of FWHM fwhm/3, centred at +-fwhm/3, so that the sum's full width
    at half maximum is close to ``fwhm_kms``). Each channel holds the profile averaged over
    the channel's width.
    """

    profile: str = "gaussian"
    flux_jy_kms: list[float] = field(default_factory=lambda: [1.0])
    fwhm_kms: list[float] = field(default_factory=lambda: [200.0])
    z: list[float] = field(default_factory=list)
    z_values: list[float] = field(default_factory=list)
    centre_hz: list[float] = field(default_factory=list)


@dataclass
class Population:
    """A sky population: ``count`` sources with a flux distribution, positions and shape,
    and optionally a spectral ``line`` (:class:`Line`; ``flux`` is then the continuum)."""

    name: str = "targets"
    count: int = 1
    flux: FluxDistribution = field(default_factory=lambda: FluxDistribution("fixed", 1e-3))
    positions: Positions = field(default_factory=Positions)
    shape: Shape = field(default_factory=Shape)
    #: scaling rule: populations of at most this many sources keep their count at any scale
    keep_count_below: int = 10
    line: Line | None = None


@dataclass
class Scene:
    """A complete simulated observation (see the module docstring for the TOML form)."""

    name: str = "scene"
    array: ArraySpec = field(default_factory=ArraySpec)
    observation: Observation = field(default_factory=Observation)
    spectral: Spectral = field(default_factory=Spectral)
    pointings: Pointings = field(default_factory=Pointings)
    effects: Effects = field(default_factory=Effects)
    populations: list[Population] = field(default_factory=list)
    description: str = ""
    visibility_dtype: str = "complex64"
    time_chunk: int = 0  # integrations per chunk; 0 = automatic
    baseline_chunk: int = 0  # baselines per chunk; 0 = all

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON/TOML-able dictionary (``load_scene(scene.to_dict())`` round-trips)."""
        return _strip_none(dataclasses.asdict(self))

    def digest(self) -> str:
        """SHA-256 (hex) of the scene's canonical JSON form: equal digests, equal scenes.

        Runs that reuse earlier results (``xstack reproduce``) compare it, so a result made
        from a scene that has since changed (e.g. a preset that gained flags) is not mixed in.
        """
        text = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()

    def validate(self) -> Scene:
        """Check values (not just types); raise :class:`XstackError` naming the field."""
        validate_scene(self)
        return self

    def scaled(self, scale: float) -> Scene:
        """A copy with observing time per pointing times ``scale`` (at least one integration)
        and population counts times ``scale`` (populations of at most ``keep_count_below``
        sources keep their count; larger ones never drop below that number)."""
        if not 0 < scale <= 1:
            raise XstackError(f"scale must be in (0, 1], got {scale}")
        new = dataclasses.replace(self, observation=dataclasses.replace(self.observation),
                                  populations=[dataclasses.replace(p) for p in self.populations])
        if scale == 1:
            return new
        obs = new.observation
        obs.time_per_pointing = max(obs.integration, obs.time_per_pointing * scale)
        for p in new.populations:
            if p.count > p.keep_count_below:
                p.count = max(p.keep_count_below, int(round(p.count * scale)))
        return new


def _strip_none(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _strip_none(v) for k, v in obj.items() if v is not None}
    if isinstance(obj, list):
        return [_strip_none(v) for v in obj]
    return obj


# ------------------------------------------------------------------ building from dicts

def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _convert(value: Any, tp: Any, where: str) -> Any:
    """Convert a TOML value to the annotated type ``tp``, naming ``where`` on failure."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        if value is None:
            return None
        inner = [a for a in args if a is not type(None)]
        return _convert(value, inner[0], where)
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise XstackError(f"{where}: expected a table of settings, got {value!r}")
        return _build(tp, value, where)
    if origin is list:
        if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple, np.ndarray)):
            raise XstackError(f"{where}: expected a list, got {value!r}")
        (item_tp,) = args or (Any,)
        return [_convert(v, item_tp, f"{where}[{i}]") for i, v in enumerate(value)]
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, (bool, np.bool_)):
            raise XstackError(f"{where}: expected true or false, got {value!r}")
        return bool(value)
    if tp is int:
        if isinstance(value, bool) or not float(value if isinstance(value, (int, float,
                                                                           np.number))
                                                  else np.nan).is_integer():
            raise XstackError(f"{where}: expected an integer, got {value!r}")
        return int(value)
    if tp is float:
        if isinstance(value, bool):
            raise XstackError(f"{where}: expected a number, got {value!r}")
        if isinstance(value, str):
            try:
                return float(value)
            except ValueError:
                raise XstackError(f"{where}: expected a number, got {value!r}") from None
        try:
            return float(value)
        except (TypeError, ValueError):
            raise XstackError(f"{where}: expected a number, got {value!r}") from None
    if tp is str:
        if not isinstance(value, str):
            raise XstackError(f"{where}: expected a string, got {value!r}")
        return value
    return value


_FLUX_FIELDS = {"value", "s_min", "s_max", "s_star"}


def _build(cls: type, data: Mapping[str, Any], where: str) -> Any:
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        here = f"{where}.{key}" if where else str(key)
        if key not in names:
            close = [n for n in names if _similar(n, str(key))]
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise XstackError(f"{here}: unknown key{hint}; known: {', '.join(sorted(names))}")
        if cls is FluxDistribution and key in _FLUX_FIELDS and value is not None:
            kwargs[key] = flux_from_value(value, here)
        elif cls is FluxDistribution and key == "flux":
            kwargs[key] = [flux_from_value(v, f"{here}[{i}]") for i, v in enumerate(value)]
        else:
            kwargs[key] = _convert(value, hints[key], here)
    return cls(**kwargs)


def _similar(a: str, b: str) -> bool:
    from difflib import SequenceMatcher

    return SequenceMatcher(None, a.lower(), b.lower()).ratio() > 0.75


def load_scene(source: str | os.PathLike | Mapping[str, Any] | Scene) -> Scene:
    """Build and validate a :class:`Scene` from a TOML file, a dictionary or a Scene.

    Raises
    ------
    XstackError
        Naming the offending field (unknown key, wrong type, impossible value).
    """
    if isinstance(source, Scene):
        return validate_scene(source)
    if isinstance(source, Mapping):
        data = dict(source)
        origin = "scene"
    else:
        path = Path(source)
        if not path.is_file():
            raise XstackError(f"{path}: no such scene file")
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise XstackError(f"{path}: not valid TOML ({exc})") from None
        origin = str(path)
    try:
        scene = _build(Scene, data, "")
    except XstackError as exc:
        raise XstackError(f"{origin}: {exc}") from None
    try:
        return validate_scene(scene)
    except XstackError as exc:
        raise XstackError(f"{origin}: {exc}") from None


POINTING_MODES = ("single", "hexagonal", "rectangular", "on_population", "list")
POSITION_KINDS = ("box", "disc", "around_pointings", "list")
SHAPE_KINDS = ("point", "gaussian")
PB_MODELS = _vocabulary.PRIMARY_BEAM_MODELS
KNOWN_POLS = {"RR", "RL", "LR", "LL", "XX", "XY", "YX", "YY"}


def validate_scene(scene: Scene) -> Scene:
    """Check the values of a scene; raise :class:`XstackError` naming the first bad field."""
    from xstack.sim.arrays import PACKAGED

    a = scene.array
    if a.positions:
        pos = np.asarray(a.positions, dtype=float)
        if pos.ndim != 2 or pos.shape[1] != 3 or len(pos) < 2:
            raise XstackError("array.positions: need a list of at least two [x, y, z] (ITRF m)")
        if len(a.diameters) != len(pos):
            raise XstackError("array.diameters: need one dish diameter per position")
        if a.names and len(a.names) != len(pos):
            raise XstackError("array.names: need one name per position")
        if not a.telescope:
            raise XstackError("array.telescope: name the telescope of user positions")
    elif a.config.lower().removesuffix(".cfg") not in PACKAGED and not Path(a.config).is_file():
        raise XstackError(f"array.config: unknown array {a.config!r} (known: "
                          f"{', '.join(PACKAGED)}, or a path to a .cfg file)")
    o = scene.observation
    if len(o.hour_angle) != 2 or not o.hour_angle[0] < o.hour_angle[1] \
            or o.hour_angle[1] - o.hour_angle[0] > 24:
        raise XstackError("observation.hour_angle: need [start, end] hours, start < end, "
                          "at most 24 h apart")
    if not o.integration > 0:
        raise XstackError(f"observation.integration: must be > 0 s (got {o.integration})")
    if not o.time_per_pointing >= o.integration:
        raise XstackError("observation.time_per_pointing: must be at least one integration")
    try:
        from astropy.time import Time

        Time(o.date, scale="utc")
    except ValueError:
        raise XstackError(f"observation.date: cannot read {o.date!r} (use 2014-01-01)") from None
    s = scene.spectral
    if s.channels < 1:
        raise XstackError(f"spectral.channels: need at least one channel (got {s.channels})")
    if not s.bandwidth > 0:
        raise XstackError(f"spectral.bandwidth: empty band (bandwidth {s.bandwidth} Hz)")
    if not s.center - s.bandwidth / 2 > 0:
        raise XstackError("spectral.center: the band must lie at positive frequencies")
    if not s.polarizations or any(p not in KNOWN_POLS for p in s.polarizations) \
            or len(set(s.polarizations)) != len(s.polarizations):
        raise XstackError(f"spectral.polarizations: need distinct names from "
                          f"{sorted(KNOWN_POLS)} (got {s.polarizations})")
    _validate_lines(scene)
    p = scene.pointings
    if p.mode not in POINTING_MODES:
        raise XstackError(f"pointings.mode: unknown mode {p.mode!r} ({', '.join(POINTING_MODES)})")
    if p.mode in ("hexagonal", "rectangular") and (len(p.size_arcsec) != 2
                                                   or min(p.size_arcsec) <= 0
                                                   or not p.spacing_arcsec > 0):
        raise XstackError("pointings.size_arcsec/spacing_arcsec: need [w, h] > 0 and spacing > 0")
    if p.mode == "on_population" and p.population not in [q.name for q in scene.populations]:
        raise XstackError(f"pointings.population: no population named {p.population!r}")
    if p.mode == "list" and (not p.positions or any(len(x) != 2 for x in p.positions)):
        raise XstackError("pointings.positions: need a list of [ra_deg, dec_deg]")
    _angle_pair(p.center, "pointings.center")
    e = scene.effects
    if e.primary_beam not in PB_MODELS:
        raise XstackError(f"effects.primary_beam: unknown model {e.primary_beam!r} "
                          f"({', '.join(PB_MODELS)})")
    if not 0 <= e.pb_cutoff < 1:
        raise XstackError("effects.pb_cutoff: must be in [0, 1)")
    if e.noise is not None:
        n = e.noise
        given = [x for x in (n.sigma, n.sefd, n.tsys) if x is not None]
        if len(given) != 1:
            raise XstackError("effects.noise: give exactly one of sigma, sefd or tsys")
        if not given[0] > 0:
            raise XstackError("effects.noise: sigma/sefd/tsys must be > 0")
        if not (0 < n.efficiency <= 1 and 0 < n.aperture_efficiency <= 1):
            raise XstackError("effects.noise: efficiencies must be in (0, 1]")
    if e.flagging is not None and not 0 <= e.flagging.random_fraction < 1:
        raise XstackError("effects.flagging.random_fraction: must be in [0, 1)")
    if (e.flagging is not None and e.flagging.elevation_limit_deg is not None
            and not -90 <= e.flagging.elevation_limit_deg < 90):
        raise XstackError("effects.flagging.elevation_limit_deg: must be in [-90, 90) degrees")
    if scene.visibility_dtype not in ("complex64", "complex128"):
        raise XstackError("visibility_dtype: complex64 or complex128")
    if scene.time_chunk < 0:
        raise XstackError("time_chunk: must be >= 0")
    if scene.baseline_chunk < 0:
        raise XstackError("baseline_chunk: must be >= 0")
    names = [q.name for q in scene.populations]
    if len(set(names)) != len(names):
        raise XstackError("populations: names must be unique")
    for i, q in enumerate(scene.populations):
        where = f"populations[{i}]"
        if not q.name or not q.name.replace("_", "").replace("-", "").isalnum():
            raise XstackError(f"{where}.name: use letters, digits, '-' and '_' (got {q.name!r})")
        if q.count < 0:
            raise XstackError(f"{where}.count: must be >= 0 (got {q.count})")
        q.flux.validate(f"{where}.flux")
        pos = q.positions
        if pos.kind not in POSITION_KINDS:
            raise XstackError(f"{where}.positions.kind: unknown {pos.kind!r} "
                              f"({', '.join(POSITION_KINDS)})")
        if pos.kind == "box" and (len(pos.size_arcsec) != 2 or min(pos.size_arcsec) <= 0):
            raise XstackError(f"{where}.positions.size_arcsec: need [width, height] > 0")
        if pos.kind in ("disc", "around_pointings") and not pos.radius_arcsec > 0:
            raise XstackError(f"{where}.positions.radius_arcsec: must be > 0")
        if pos.kind == "list" and (len(pos.ra) != q.count or len(pos.dec) != q.count):
            raise XstackError(f"{where}.positions.ra/dec: need {q.count} positions (count)")
        if pos.center:
            _angle_pair(pos.center, f"{where}.positions.center")
        sh = q.shape
        if sh.kind not in SHAPE_KINDS:
            raise XstackError(f"{where}.shape.kind: unknown {sh.kind!r} (point or gaussian)")
        if sh.kind == "gaussian" and (len(sh.fwhm_arcsec) not in (1, 2)
                                      or min(sh.fwhm_arcsec) <= 0
                                      or sh.fwhm_arcsec[0] > sh.fwhm_arcsec[-1]):
            raise XstackError(f"{where}.shape.fwhm_arcsec: need [fwhm] or [min, max] > 0")
        if p.mode == "on_population" and q.name == p.population \
                and pos.kind == "around_pointings":
            raise XstackError(f"{where}.positions.kind: the population that defines the "
                              "pointings cannot be placed around them")
    return scene


LINE_PROFILES = ("gaussian", "double")


def _validate_lines(scene: Scene) -> None:
    """The spectral-line settings (only looked at when given: continuum scenes skip this)."""
    from xstack.errors import OptionError
    from xstack.frames import DOPPLER_FRAMES, frame_name

    s = scene.spectral
    if s.frame is not None:
        try:
            name = frame_name(s.frame)
        except OptionError:
            name = ""
        if name not in DOPPLER_FRAMES:
            raise XstackError(f"spectral.frame: {s.frame!r} is not one of "
                              f"{', '.join(DOPPLER_FRAMES)}")
    if s.line_frame is not None and str(s.line_frame).lower() not in _vocabulary.LINE_FRAMES:
        raise XstackError(f"spectral.line_frame: {s.line_frame!r} is not one of "
                          f"{', '.join(_vocabulary.LINE_FRAMES)}")
    lines = [(i, q) for i, q in enumerate(scene.populations) if q.line is not None]
    if s.line is not None or lines:
        from xstack.spectral import rest_frequency

        if s.line is None:
            raise XstackError(f"spectral.line: populations[{lines[0][0]}] has a line: give "
                              "its rest frequency (a name such as HI or CO(1-0), or Hz)")
        try:
            rest_frequency(s.line)
        except OptionError as exc:
            raise XstackError(f"spectral.line: {exc}") from None
    for i, q in lines:
        where = f"populations[{i}].line"
        ln = q.line
        assert ln is not None
        if ln.profile not in LINE_PROFILES:
            raise XstackError(f"{where}.profile: unknown {ln.profile!r} "
                              f"({', '.join(LINE_PROFILES)})")
        for key, low in (("flux_jy_kms", 0.0), ("fwhm_kms", None)):
            v = getattr(ln, key)
            if len(v) not in (1, 2) or v[0] > v[-1] or not all(np.isfinite(v)) \
                    or (low is not None and min(v) < low) or (low is None and min(v) <= 0):
                raise XstackError(f"{where}.{key}: need [value] or [min, max], "
                                  f"{'>= 0' if low is not None else '> 0'}")
        given = [k for k in ("z", "z_values", "centre_hz") if getattr(ln, k)]
        if len(given) != 1:
            raise XstackError(f"{where}: give exactly one of z, z_values or centre_hz")
        if ln.z and (len(ln.z) not in (1, 2) or ln.z[0] > ln.z[-1] or min(ln.z) <= -1):
            raise XstackError(f"{where}.z: need [z] or [min, max] with z > -1")
        for key in ("z_values", "centre_hz"):
            v = getattr(ln, key)
            if v and len(v) < q.count:
                raise XstackError(f"{where}.{key}: need one value per source ({q.count})")
        if ln.z_values and min(ln.z_values) <= -1:
            raise XstackError(f"{where}.z_values: need z > -1")
        if ln.centre_hz and min(ln.centre_hz) <= 0:
            raise XstackError(f"{where}.centre_hz: need frequencies > 0 Hz")


def _angle_pair(pair: list[Any], where: str) -> tuple[float, float]:
    """(ra, dec) in degrees from numbers (deg) or sexagesimal strings."""
    from astropy import units as u
    from astropy.coordinates import Angle

    if len(pair) != 2:
        raise XstackError(f"{where}: need [ra, dec]")
    out = []
    for value, is_ra in zip(pair, (True, False), strict=True):
        try:
            if isinstance(value, str):
                unit = u.hourangle if is_ra and ("h" in value or ":" in value) else u.deg
                out.append(Angle(value, unit=unit).degree)
            else:
                out.append(float(value))
        except (ValueError, TypeError, u.UnitsError):
            raise XstackError(f"{where}: cannot read angle {value!r}") from None
    if not -90 <= out[1] <= 90:
        raise XstackError(f"{where}: declination out of range ({out[1]})")
    return out[0] % 360.0, out[1]


def angle_pair(pair: list[Any], where: str = "center") -> tuple[float, float]:
    """Public form of the (ra, dec) parser: degrees from numbers or sexagesimal strings."""
    return _angle_pair(pair, where)


# ------------------------------------------------------------------ writing TOML

def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, Mapping):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()
                                if not _empty(v)) + " }"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def _empty(value: Any) -> bool:
    return isinstance(value, (list, str)) and len(value) == 0


def scene_to_toml(scene: Scene) -> str:
    """The scene as a TOML document that :func:`load_scene` reads back to an equal scene."""
    data = scene.to_dict()
    lines: list[str] = []
    tables = {k: v for k, v in data.items() if isinstance(v, Mapping)}
    pops = data.pop("populations", [])
    for key, value in data.items():
        if key not in tables and not _empty(value):
            lines.append(f"{key} = {_toml_value(value)}")
    for key, table in tables.items():
        lines += ["", f"[{key}]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in table.items() if not _empty(v)]
    for pop in pops:
        lines += ["", "[[populations]]"]
        lines += [f"{k} = {_toml_value(v)}" for k, v in pop.items() if not _empty(v)]
    return "\n".join(lines) + "\n"
