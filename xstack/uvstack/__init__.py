"""uv-stacking (Lindroos et al. 2015, section 3.3): phase-rotate visibilities to many positions.

Public API: :func:`xstack.uvstack.stack.uvstack`, :class:`~xstack.uvstack.stack.StackResult`,
:func:`xstack.uvstack.stack.uv_profile`, :func:`xstack.uvstack.stack.plot_uv_profile`; the
numerical kernels (numpy/numba only) are in :mod:`xstack.uvstack.kernels`, the plain-numpy
reference of the whole stack in :mod:`xstack.uvstack.reference`.

``xstack.uvstack`` is both this sub-package and the top-level function of the lazy public
API; once the sub-package has been imported it shadows the function on the ``xstack``
package, so the module itself is made callable: ``xstack.uvstack(data, positions, ...)``
always runs :func:`xstack.uvstack.stack.uvstack`.
"""

from __future__ import annotations

import sys
import types
from typing import Any

__all__ = ["StackResult", "plot_uv_profile", "uv_profile", "uvstack"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from xstack.uvstack import stack

        return getattr(stack, name)
    raise AttributeError(name)


class _CallableModule(types.ModuleType):
    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        from xstack.uvstack.stack import uvstack

        return uvstack(*args, **kwargs)


sys.modules[__name__].__class__ = _CallableModule
