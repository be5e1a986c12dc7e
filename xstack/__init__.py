"""xstack: stacking of radio-interferometric data in the uv- and image-domain.

The public API mirrors the command line and is imported lazily, so ``import xstack`` stays
cheap. See ``docs/`` and Lindroos et al. (2015, MNRAS 446, 3502) for the method.
"""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path
from typing import Any

__version__ = "0.1.0"


def numba_cache_dir() -> Path:
    """Where xstack's compiled numba kernels are cached: never inside the installed package.

    ``NUMBA_CACHE_DIR`` if the user set it; else ``XSTACK_CACHE_DIR/numba``; else
    ``$XDG_CACHE_HOME/xstack/numba`` (``~/.cache/xstack/numba``). numba's own default writes
    ``__pycache__/*.nbi`` files beside the package's modules: those outlive ``pip uninstall``
    and turn the directory into a namespace package that shadows a later install.
    """
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"])
    if os.environ.get("XSTACK_CACHE_DIR"):
        return Path(os.environ["XSTACK_CACHE_DIR"]) / "numba"
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "xstack" / "numba"


def _configure_numba_cache() -> None:
    # Must run before any kernel module is imported (they are, lazily, below this package):
    # numba reads NUMBA_CACHE_DIR when it is first imported, and config.CACHE_DIR when a
    # cached function is first compiled.
    path = str(numba_cache_dir())
    os.environ.setdefault("NUMBA_CACHE_DIR", path)
    numba = sys.modules.get("numba")
    if numba is not None and not getattr(numba.config, "CACHE_DIR", ""):
        numba.config.CACHE_DIR = path


_configure_numba_cache()

#: public name -> "module:attribute"
_API = {
    # data model and I/O
    "open_store": "xstack.schema:open_store",
    "use_storage_options": "xstack._fs:use_storage_options",
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
    "OptionError": "xstack.errors:OptionError",
    "OutputExistsError": "xstack.errors:OutputExistsError",
    "NoDataError": "xstack.errors:NoDataError",
    "SchemaError": "xstack.errors:SchemaError",
    "XstackWarning": "xstack.errors:XstackWarning",
    "WeightsWarning": "xstack.errors:WeightsWarning",
    "dish_diameter": "xstack.beams:dish_diameter",
    # simulation
    "Scene": "xstack.sim.scene:Scene",
    "load_scene": "xstack.sim.scene:load_scene",
    "preset_scene": "xstack.sim.presets:preset_scene",
    "simulate": "xstack.sim.simulate:simulate",
    # uv-stacking
    "stack_uv": "xstack.uvstack.stack:stack_uv",
    "compute": "xstack._lazy:compute",
    "LazyResult": "xstack._lazy:LazyResult",
    "uv_profile": "xstack.uvstack.stack:uv_profile",
    # spectral-line stacking
    "stack_lines": "xstack.uvstack.line:stack_lines",
    "rest_frequency": "xstack.spectral:rest_frequency",
    # imaging and image-stacking
    "make_image": "xstack.imaging.image:make_image",
    "clean": "xstack.imaging.clean:clean",
    "subtract": "xstack.imaging.subtract:subtract",
    "stack_images": "xstack.imstack.stack:stack_images",
    "stack_line_cube": "xstack.imstack.line:stack_line_cube",
    # measuring
    "fit_uv": "xstack.fit.uvfit:fit_uv",
    "fit_image": "xstack.fit.imfit:fit_image",
    "fit_line": "xstack.fit.line:fit_line",
    "subtract_continuum": "xstack.fit.line:subtract_continuum",
    "estimate_noise": "xstack.noise.estimate:estimate_noise",
    "estimate_line_noise": "xstack.noise.line:estimate_line_noise",
    # inspecting
    "info": "xstack._info:info",
    # where the dask work runs
    "use_cluster": "xstack._cluster:use_cluster",
}

__all__ = ["__version__", "numba_cache_dir", *_API]


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
