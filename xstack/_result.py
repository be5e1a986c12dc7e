"""The one protocol of every stage's result: ``to_dict``, ``write_json``, ``table``.

Every public result (:class:`~xstack.uvstack.stack.StackResult`,
:class:`~xstack.imstack.stack.ImstackResult`, :class:`~xstack.noise.estimate.NoiseResult`,
:class:`~xstack.fit.result.FitResult`, :class:`~xstack.imaging.image.ImageResult`,
:class:`~xstack.imaging.clean.CleanResult`, :class:`~xstack.sim.simulate.SimulationResult`)
is a keyword-only dataclass deriving from :class:`Result`:

``to_dict()``
    A JSON-ready summary (numbers, strings, lists, dicts; NaN and inf as ``None``): what
    ``xstack <command> --json`` prints.
``write_json(path, overwrite=False)``
    That summary written atomically (never over an existing file without ``overwrite``).
``table()``
    The result's rows as an :class:`astropy.table.Table` with units: per position (stacks),
    per realisation (noise), per parameter (fits), else one row of the summary's numbers.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

#: column-name suffix -> astropy unit string, for :meth:`Result.table`
UNIT_SUFFIXES = {"_jy": "Jy", "_arcsec": "arcsec", "_deg": "deg", "_hz": "Hz", "_s": "s",
                 "_m": "m", "_klambda": "klambda", "_seconds": "s"}


def json_ready(value: Any) -> Any:
    """``value`` with numpy scalars and arrays, tuples, paths and non-finite floats made JSON
    values (NaN and inf become ``None``: JSON has neither)."""
    if isinstance(value, dict):
        return {str(k): json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    if isinstance(value, np.ndarray):
        return [json_ready(v) for v in value.tolist()]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return value


def unit_of(name: str) -> str | None:
    """The unit a column name states by its suffix (``flux_jy`` -> Jy), else None."""
    for suffix, unit in UNIT_SUFFIXES.items():
        if name.endswith(suffix):
            return unit
    return None


def summary_table(summary: dict[str, Any]) -> Any:
    """One-row :class:`astropy.table.Table` of the scalar entries of ``summary`` (nested
    dicts flattened as ``outer.inner``), with units from the names' suffixes."""
    from astropy.table import Table

    flat: dict[str, Any] = {}

    def walk(prefix: str, d: dict[str, Any]) -> None:
        for key, value in d.items():
            name = f"{prefix}{key}"
            if isinstance(value, dict):
                walk(f"{name}.", value)
            elif value is None or isinstance(value, (bool, int, float, str, np.generic)):
                flat[name] = np.nan if value is None else value

    walk("", summary)
    table = Table()
    for name, value in flat.items():
        table[name] = [value]
        unit = unit_of(name)
        if unit is not None and table[name].dtype.kind == "f":
            table[name].unit = unit
    return table


class Result:
    """Mixin of the result protocol (see the module docstring). Subclasses define
    :meth:`to_dict` and may override :meth:`table`."""

    def to_dict(self) -> dict[str, Any]:  # pragma: no cover - every subclass defines it
        raise NotImplementedError

    def write_json(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write :meth:`to_dict` as indented JSON to ``path``, atomically.

        Raises
        ------
        OutputExistsError
            ``path`` exists and ``overwrite`` is False.
        """
        from xstack._atomic import atomic_output

        text = json.dumps(json_ready(self.to_dict()), indent=2, allow_nan=False)
        with atomic_output(path, overwrite=overwrite) as tmp:
            Path(tmp).write_text(text + "\n", encoding="utf-8")
        return Path(path)

    def table(self) -> Any:
        """The result as an :class:`astropy.table.Table` (default: one row of the numbers and
        strings of :meth:`to_dict`, units from the names' suffixes)."""
        return summary_table(json_ready(self.to_dict()))
