"""Image-stacking (Lindroos et al. 2015, §3.2): stamps around known positions, stacked per pixel.

``xstack.imstack.stack.imstack`` is the entry point; the kernels are plain numpy in
:mod:`xstack.imstack.kernels`. See ``docs/imstack.md``.

``xstack.imstack`` is both this package and, in the lazy top-level API, the function. Once the
package is imported it shadows the lazy name on ``xstack``, so the package itself is made
callable: ``xstack.imstack(images, positions, ...)`` works either way.
"""

from __future__ import annotations

import sys
import types
from typing import Any

__all__ = ["imstack", "ImstackResult"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from xstack.imstack import stack

        return getattr(stack, name)
    raise AttributeError(name)


class _CallablePackage(types.ModuleType):
    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        from xstack.imstack.stack import imstack

        return imstack(*args, **kwargs)


sys.modules[__name__].__class__ = _CallablePackage
