"""xstack: stacking of radio-interferometric data in the uv- and image-domain.

The public API mirrors the command line and is imported lazily, so ``import xstack`` stays
cheap. See ``docs/`` and Lindroos et al. (2015, MNRAS 446, 3502) for the method.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: public name -> "module:attribute"
_API = {
    # data model and I/O
    "open_store": "xstack.schema:open_store",
    "write_store": "xstack.schema:write_store",
    "validate_partition": "xstack.schema:validate_partition",
    "validate_store": "xstack.schema:validate_store",
    "iter_partitions": "xstack.schema:iter_partitions",
    "convert_ms": "xstack.io.convert:convert_ms",
    "export_ms": "xstack.io.export:export_ms",
    "read_catalog": "xstack.coords:read_catalog",
    "radec_to_lmn": "xstack.coords:radec_to_lmn",
    "PrimaryBeam": "xstack.beams:PrimaryBeam",
    "standard_beam": "xstack.beams:standard_beam",
    "XstackError": "xstack.errors:XstackError",
    # simulation
    "Scene": "xstack.sim.scene:Scene",
    "load_scene": "xstack.sim.scene:load_scene",
    "preset_scene": "xstack.sim.presets:preset_scene",
    "simulate": "xstack.sim.simulate:simulate",
    # uv-stacking
    "uvstack": "xstack.uvstack.stack:uvstack",
    "uv_profile": "xstack.uvstack.stack:uv_profile",
    # imaging and image-stacking
    "make_image": "xstack.imaging.image:make_image",
    "clean": "xstack.imaging.clean:clean",
    "subtract": "xstack.imaging.subtract:subtract",
    "imstack": "xstack.imstack.stack:imstack",
    # measuring
    "fit_uv": "xstack.fit.uvfit:fit_uv",
    "fit_image": "xstack.fit.imfit:fit_image",
    "estimate_noise": "xstack.noise.estimate:estimate_noise",
}

__all__ = ["__version__", *_API]


def __getattr__(name: str) -> Any:
    target = _API.get(name)
    if target is None:
        raise AttributeError(f"module 'xstack' has no attribute {name!r}")
    module, attr = target.split(":")
    try:
        value = getattr(importlib.import_module(module), attr)
    except (ModuleNotFoundError, AttributeError) as exc:
        raise AttributeError(f"xstack.{name} is not available ({exc})") from exc
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(__all__)
