"""Noise and bias of stacked fluxes (paper section 3.5): :func:`estimate_noise`.

See ``docs/noise.md``.
"""

from __future__ import annotations

from typing import Any

__all__ = ["NoiseOptions", "NoiseResult", "estimate_noise"]


def __getattr__(name: str) -> Any:
    if name in ("estimate_noise", "NoiseResult", "NoiseOptions"):
        from xstack.noise import estimate
        return getattr(estimate, name)
    raise AttributeError(name)
