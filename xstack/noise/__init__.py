"""Noise and bias of stacked fluxes (paper section 3.5): :func:`estimate_noise`.

See ``docs/noise.md``.
"""

from __future__ import annotations

from typing import Any

__all__ = ["LineNoiseResult", "NoiseOptions", "NoiseResult", "estimate_line_noise",
           "estimate_noise"]


def __getattr__(name: str) -> Any:
    if name in ("estimate_noise", "NoiseResult", "NoiseOptions"):
        from xstack.noise import estimate
        return getattr(estimate, name)
    if name in ("estimate_line_noise", "LineNoiseResult"):
        from xstack.noise import line
        return getattr(line, name)
    raise AttributeError(name)
