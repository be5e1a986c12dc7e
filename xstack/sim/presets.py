"""The paper's eleven simulated data-set types (Lindroos et al. 2015, §2 and Table 1).

``preset_scene("paper-6")`` returns the :class:`~xstack.sim.scene.Scene` of type 6, and
``preset_scene("paper-6", scale=0.05)`` a quick version (observing time x 0.05, large
populations thinned, see :meth:`Scene.scaled`). Populations are named ``bright`` and
``targets``. Every choice the paper leaves open, and every deviation, is listed in
``docs/sim.md``; the main ones:

* Types 1–4: the bright sources are 10 mJy as in the text (Table 1 says 5 mJy).
* Type 5, 6, 7, 11: the Bondi et al. (2008) counts between S_min and 1 Jy, S_min chosen so
  that the counts predict 417 sources in the 30'x30' field (S_min ≈ 71 µJy).
* Type 7 is "based on type 6" (text): extended bright sources as in type 6.
* Type 10: an approximate tabulation of the Béthermin et al. (2012) 1.1 mm counts, limits
  chosen so they predict 282 sources in 100"x100" below 10 mJy.
* Types 8–10 noise: the paper used CASA's ALMA atmosphere model (PWV 2 mm); we add Gaussian
  noise of sigma = 1.2 Jy per real/imaginary part, calibrated so that one pointing reaches
  the paper's 0.5 mJy/beam (type 9) with natural weighting.
* Type 11: 8 antennas of VLA A (W16, W48, W72, E16, E48, E72, N32, N64); 600 000 s as
  repeated 9.4 h tracks on consecutive days; targets as type 5 (Table 1's S* = 0.5 mJy is a
  typo: the text says as type 5).

Two spectral-line presets (:data:`LINE_PRESETS`, not the paper's): ``hi-stack`` (HI with the
VLA) and ``co-stack`` (CO(1-0) with ALMA); their population is ``galaxies`` (see
:func:`_hi_stack`, :func:`_co_stack` and ``docs/sim.md``).
"""

from __future__ import annotations

import copy
import math
from typing import Any

from xstack.errors import XstackError
from xstack.sim.counts import FluxDistribution, s_min_for_count
from xstack.sim.scene import PAPER_FIELD_CENTER, Scene, load_scene

PRESETS = tuple(f"paper-{i}" for i in range(1, 12))
#: Spectral-line presets (issue 15): galaxies with lines at known redshifts, for line stacking.
LINE_PRESETS = ("hi-stack", "co-stack")

ARCSEC_SR = (math.pi / 180 / 3600) ** 2

#: Per-visibility noise of the ALMA types (Jy, real and imaginary part each): one pointing of
#: 32 antennas x 60 integrations x 100 channels x 2 polarizations -> 0.5 mJy/beam.
ALMA_SIGMA = 0.5e-3 * math.sqrt(496 * 60 * 100 * 2)

#: What CASA's simulator (``sm``, behind ``simobserve``, with which the paper made its data
#: sets) flags by default: every baseline of an antenna that is shadowed or sees the field
#: below 10 deg elevation. The VLA tracks of HA -4.8..4.8 h at dec -30 go below the horizon
#: at both ends (28 % of the integrations are below 10 deg); unflagged, those baselines
#: foreshorten to a few metres, see the whole field's flux, and bias a stack at any position
#: (docs/reproduction.md, type 6).
SIMULATOR_FLAGGING = {"shadowing": True, "elevation_limit_deg": 10.0}

SPARSE_ANTENNAS = ["W16", "W48", "W72", "E16", "E48", "E72", "N32", "N64"]


def _vla_base() -> dict[str, Any]:
    return {
        "array": {"config": "vla.a"},
        "observation": {"date": "2014-01-01", "hour_angle": [-4.8, 4.8], "integration": 10.0,
                        "time_per_pointing": 33840.0},
        "spectral": {"center": 1.4e9, "bandwidth": 250e6, "channels": 10,
                     "polarizations": ["RR", "LL"]},
        "pointings": {"mode": "single", "center": list(PAPER_FIELD_CENTER)},
        "effects": {"primary_beam": "auto", "w_term": True, "noise": {"sigma": 0.01},
                    "flagging": dict(SIMULATOR_FLAGGING)},
    }


def _alma_base() -> dict[str, Any]:
    return {
        "array": {"config": "alma.cycle1.2"},
        "observation": {"date": "2014-01-01", "hour_angle": [-1.5, 1.5], "integration": 6.0,
                        "time_per_pointing": 360.0},
        "spectral": {"center": 230e9, "bandwidth": 4e9, "channels": 100,
                     "polarizations": ["XX", "YY"]},
        "pointings": {"mode": "hexagonal", "center": list(PAPER_FIELD_CENTER),
                      "size_arcsec": [100.0, 100.0], "spacing_arcsec": 20.0},
        "effects": {"primary_beam": "auto", "w_term": True,
                    "noise": {"sigma": ALMA_SIGMA}, "flagging": dict(SIMULATOR_FLAGGING)},
    }


def _pop(name: str, count: int, flux: dict[str, Any], size: float | None = None,
         shape: dict[str, Any] | None = None, positions: dict[str, Any] | None = None
         ) -> dict[str, Any]:
    return {"name": name, "count": count, "flux": flux,
            "positions": positions or {"kind": "box", "size_arcsec": [size, size]},
            "shape": shape or {"kind": "point"}}


def _schechter() -> dict[str, Any]:
    s_star = 1.7e-6
    return {"kind": "schechter", "alpha": -1.6, "s_star": s_star, "s_min": 0.25 * s_star,
            "s_max": 10 * s_star}


def _bondi(count: int, size_arcsec: float) -> dict[str, Any]:
    d = FluxDistribution("bondi2008", s_min=1e-7, s_max=1.0)
    s_min = s_min_for_count(d, count, size_arcsec**2 * ARCSEC_SR)
    return {"kind": "bondi2008", "s_min": s_min, "s_max": 1.0}


def _bethermin(count: int, size_arcsec: float) -> dict[str, Any]:
    d = FluxDistribution("bethermin2012_1.1mm", s_min=1e-7, s_max=10e-3)
    s_min = s_min_for_count(d, count, size_arcsec**2 * ARCSEC_SR)
    return {"kind": "bethermin2012_1.1mm", "s_min": s_min, "s_max": 10e-3}


def _definition(n: int) -> dict[str, Any]:
    fixed = lambda v: {"kind": "fixed", "value": v}  # noqa: E731
    gauss = lambda f: {"kind": "gaussian", "fwhm_arcsec": f}  # noqa: E731
    if 1 <= n <= 7 or n == 11:
        d = _vla_base()
        if n in (1, 2):
            pops = [_pop("bright", 1, fixed(10e-3), 300.0), _pop("targets", 25, fixed(6e-6), 300.0)]
        elif n == 3:
            pops = [_pop("bright", 10, fixed(10e-3), 1800.0),
                    _pop("targets", 900, fixed(1e-6), 1800.0)]
        elif n == 4:
            pops = [_pop("bright", 10, fixed(10e-3), 1800.0),
                    _pop("targets", 900, _schechter(), 1800.0)]
        else:
            bright_shape = gauss([0.5, 5.0]) if n in (6, 7) else None
            pops = [_pop("bright", 417, _bondi(417, 1800.0), 1800.0, bright_shape)]
            if n == 7:
                pops.append(_pop("targets", 900, fixed(2.96e-6), 1800.0, gauss([1.5])))
            else:
                pops.append(_pop("targets", 900, _schechter(), 1800.0))
        if n == 11:
            d["array"]["antennas"] = list(SPARSE_ANTENNAS)
            d["observation"]["time_per_pointing"] = 600000.0
        descr = {1: "basic VLA case", 2: "as 1 (0.5 arcsec pixels in imaging)",
                 3: "wide field", 4: "Schechter target fluxes",
                 5: "Bondi et al. 2008 bright-source counts", 6: "extended bright sources",
                 7: "extended targets", 11: "sparse array (8 VLA A antennas, 600 000 s)"}[n]
    else:
        d = _alma_base()
        if n == 8:
            pops = [_pop("bright", 10, fixed(30e-3), 100.0), _pop("targets", 50, fixed(1e-3), 100.0)]
            descr = "contiguous ALMA mosaic"
        elif n == 9:
            d["pointings"] = {"mode": "on_population", "population": "bright",
                              "center": list(PAPER_FIELD_CENTER)}
            pops = [_pop("bright", 10, fixed(30e-3), 300.0),
                    _pop("targets", 50, fixed(1e-3),
                         positions={"kind": "around_pointings", "radius_arcsec": 11.2})]
            descr = "non-contiguous ALMA mosaic on the bright sources"
        else:
            pops = [_pop("bright", 282, _bethermin(282, 100.0), 100.0),
                    _pop("targets", 50, fixed(0.2e-3), 100.0)]
            descr = "Béthermin et al. 2012 bright-source counts"
    d["populations"] = pops
    d["name"] = f"paper-{n}"
    d["description"] = f"Lindroos et al. 2015 data-set type {n}: {descr}"
    return d


def _hi_stack() -> dict[str, Any]:
    """``hi-stack``: HI 21 cm in 1000 galaxies at 0.1 < z < 0.2 with the VLA in C
    configuration (no MeerKAT antenna file is packaged).

    L band 1.177-1.297 GHz in 1024 TOPO channels of 117 kHz (27-30 km/s; lines fixed in
    LSRK, so they drift over the track as real data do); a 4 h track of 60 s integrations
    around transit, both parallel hands, the VLA's standard primary beam, w-term, thermal
    noise from SEFD = 420 Jy (0.13 Jy per visibility, ~0.45 mJy per channel over the whole
    observation). Galaxies: uniform in a disc of 15' radius around the field centre, no
    continuum, Gaussian lines with integrated flux 0.05-0.3 Jy km/s and FWHM 150-400 km/s
    (uniform), z uniform in [0.1, 0.2]. Size at scale 1: 240 x 351 x 1024 x 2 = 1.7e8
    visibilities, a store of ~1.3 GB, ~1 min on 2 cores (measured with 2 cores shared with
    other work: scale 0.5, 120 integrations x 500 galaxies, 24 s and 0.64 GB; scale 0.2
    11 s; the cost is ~ integrations x (1 + galaxies / 800)). ``--scale 0.01``: 2
    integrations, 10 galaxies, under a second.
    """
    rest = 1_420_405_751.768
    f_lo, f_hi = 1.177e9, 1.297e9
    assert rest / 1.2 > f_lo + 4e6 and rest / 1.1 < f_hi - 4e6  # lines +-1000 km/s in band
    return {
        "name": "hi-stack",
        "description": "HI stacking: 1000 galaxies at 0.1 < z < 0.2, VLA C configuration, "
                       "L band, 1024 TOPO channels (27-30 km/s)",
        "array": {"config": "vla.c"},
        "observation": {"date": "2014-01-01", "hour_angle": [-2.0, 2.0], "integration": 60.0,
                        "time_per_pointing": 14400.0},
        "spectral": {"center": 0.5 * (f_lo + f_hi), "bandwidth": f_hi - f_lo, "channels": 1024,
                     "polarizations": ["RR", "LL"], "frame": "TOPO", "line": "HI",
                     "line_frame": "lsrk"},
        "pointings": {"mode": "single", "center": list(PAPER_FIELD_CENTER)},
        "effects": {"primary_beam": "auto", "w_term": True, "noise": {"sefd": 420.0}},
        "populations": [{
            "name": "galaxies", "count": 1000, "flux": {"kind": "fixed", "value": 0.0},
            "positions": {"kind": "disc", "radius_arcsec": 900.0},
            "shape": {"kind": "point"},
            "line": {"profile": "gaussian", "flux_jy_kms": [0.05, 0.3],
                     "fwhm_kms": [150.0, 400.0], "z": [0.1, 0.2]}}],
    }


def _co_stack() -> dict[str, Any]:
    """``co-stack``: CO(1-0) in 100 galaxies at 0.28 < z < 0.32 with ALMA in band 3.

    87.1-90.3 GHz in 512 TOPO channels of 6.25 MHz (21 km/s; lines fixed in LSRK), one
    pointing, 32 antennas (cycle 1 configuration 2), 1 h of 10 s integrations around transit,
    both parallel hands, ALMA's standard primary beam (FWHM ~ 65"), w-term, thermal noise from
    Tsys = 75 K (0.26 Jy per visibility, ~0.45 mJy per channel over the observation).
    Galaxies: uniform in a disc of 25" radius, no continuum, Gaussian lines with integrated
    flux 0.2-1 Jy km/s and FWHM 100-400 km/s, z uniform in [0.28, 0.32]. Size at scale 1:
    360 x 496 x 512 x 2 = 1.8e8 visibilities, a store of ~1.4 GB, ~40 s on 2 cores (measured
    with 2 cores shared: scale 0.5, 180 integrations x 50 galaxies, 18 s and 0.68 GB; scale
    0.25 12 s). ``--scale 0.01``: 4 integrations, 10 galaxies, about a second.
    """
    f_lo, f_hi = 87.1e9, 90.3e9
    rest = 115.2712018e9
    assert rest / 1.32 > f_lo + 0.2e9 and rest / 1.28 < f_hi - 0.2e9
    return {
        "name": "co-stack",
        "description": "CO(1-0) stacking: 100 galaxies at 0.28 < z < 0.32, ALMA band 3, "
                       "512 TOPO channels (21 km/s)",
        "array": {"config": "alma.cycle1.2"},
        "observation": {"date": "2014-01-01", "hour_angle": [-0.5, 0.5], "integration": 10.0,
                        "time_per_pointing": 3600.0},
        "spectral": {"center": 0.5 * (f_lo + f_hi), "bandwidth": f_hi - f_lo, "channels": 512,
                     "polarizations": ["XX", "YY"], "frame": "TOPO", "line": "CO(1-0)",
                     "line_frame": "lsrk"},
        "pointings": {"mode": "single", "center": list(PAPER_FIELD_CENTER)},
        "effects": {"primary_beam": "auto", "w_term": True, "noise": {"tsys": 75.0}},
        "populations": [{
            "name": "galaxies", "count": 100, "flux": {"kind": "fixed", "value": 0.0},
            "positions": {"kind": "disc", "radius_arcsec": 25.0},
            "shape": {"kind": "point"},
            "line": {"profile": "gaussian", "flux_jy_kms": [0.2, 1.0],
                     "fwhm_kms": [100.0, 400.0], "z": [0.28, 0.32]}}],
    }


_LINE_DEFINITIONS = {"hi-stack": _hi_stack, "co-stack": _co_stack}

_CACHE: dict[int, dict[str, Any]] = {}


def preset_dict(name: str) -> dict[str, Any]:
    """The TOML-equivalent dictionary of a preset (a fresh copy): ``paper-1`` ...
    ``paper-11`` (:data:`PRESETS`) or a line preset (:data:`LINE_PRESETS`)."""
    if str(name).lower() in _LINE_DEFINITIONS:
        return _LINE_DEFINITIONS[str(name).lower()]()
    try:
        n = int(str(name).lower().removeprefix("paper-"))
        if f"paper-{n}" not in PRESETS:
            raise ValueError
    except ValueError:
        raise XstackError(f"unknown preset {name!r} (known: "
                          f"{', '.join((*PRESETS, *LINE_PRESETS))})") from None
    if n not in _CACHE:
        _CACHE[n] = _definition(n)
    return copy.deepcopy(_CACHE[n])


def preset_scene(name: str, scale: float = 1.0) -> Scene:
    """The scene of a paper data-set type, ``"paper-1"`` … ``"paper-11"``, or of a line preset
    (``"hi-stack"``, ``"co-stack"``), optionally scaled.

    ``scale`` in (0, 1] multiplies the observing time per pointing and the size of
    populations larger than 10 sources (:meth:`Scene.scaled`); fields, channels and
    polarizations stay as in the paper.
    """
    scene = load_scene(preset_dict(name))
    return scene.scaled(scale) if scale != 1.0 else scene
