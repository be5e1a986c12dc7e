"""uv-stacking (Lindroos et al. 2015, section 3.3): phase-rotate visibilities to many positions.

Public API: :func:`xstack.uvstack.stack.stack_uv` (also ``xstack.stack_uv``),
:class:`~xstack.uvstack.stack.StackResult`, :class:`~xstack.uvstack.stack.UvstackOptions`
(every option, validated), :func:`xstack.uvstack.stack.uv_profile`,
:func:`xstack.uvstack.stack.plot_uv_profile`; the numerical kernels (numpy/numba only) are in
:mod:`xstack.uvstack.kernels`, the plain-numpy reference of the whole stack in
:mod:`xstack.uvstack.reference`.
"""

from __future__ import annotations

from typing import Any

__all__ = ["StackResult", "UvstackOptions", "plot_uv_profile", "stack_uv", "uv_profile"]


def __getattr__(name: str) -> Any:
    # lazy: importing the sub-package does not import dask and the kernels
    if name in __all__:
        from xstack.uvstack import stack

        return getattr(stack, name)
    raise AttributeError(f"module 'xstack.uvstack' has no attribute {name!r}")
