"""Model fitting of stacked data: uv-domain (:func:`fit_uv`) and image-domain PSF fitting
(:func:`fit_image`), paper section 3.4. See ``docs/fit.md``."""

from __future__ import annotations

from typing import Any

__all__ = ["FitResult", "fit_image", "fit_uv"]


def __getattr__(name: str) -> Any:
    if name == "fit_uv":
        from xstack.fit.uvfit import fit_uv
        return fit_uv
    if name == "fit_image":
        from xstack.fit.imfit import fit_image
        return fit_image
    if name == "FitResult":
        from xstack.fit.result import FitResult
        return FitResult
    raise AttributeError(name)
