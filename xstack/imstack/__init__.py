"""Image-stacking (Lindroos et al. 2015, §3.2): stamps around known positions, stacked per pixel.

:func:`xstack.imstack.stack.stack_images` (also ``xstack.stack_images``) is the entry point;
the kernels are plain numpy in :mod:`xstack.imstack.kernels`. See ``docs/imstack.md``.
"""

from __future__ import annotations

from typing import Any

__all__ = ["ImstackOptions", "ImstackResult", "stack_images"]
_LINE = ["ImLineStackResult", "stack_line_cube"]


def __getattr__(name: str) -> Any:
    # lazy: importing the sub-package does not import astropy and the kernels
    if name in __all__:
        from xstack.imstack import stack

        return getattr(stack, name)
    if name in _LINE:
        from xstack.imstack import line

        return getattr(line, name)
    raise AttributeError(f"module 'xstack.imstack' has no attribute {name!r}")
