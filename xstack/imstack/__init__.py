"""Image-stacking (Lindroos et al. 2015, §3.2): stamps around known positions, stacked per pixel.

``xstack.imstack.stack.imstack`` is the entry point (also ``xstack.imstack``); the kernels
are plain numpy in :mod:`xstack.imstack.kernels`. See ``docs/imstack.md``.
"""

from __future__ import annotations

__all__ = ["imstack", "ImstackResult"]


def __getattr__(name: str):
    if name in __all__:
        from xstack.imstack import stack

        return getattr(stack, name)
    raise AttributeError(name)
