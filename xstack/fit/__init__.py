"""Model fitting of stacked data: uv-domain (:func:`fit_uv`) and image-domain PSF fitting
(:func:`fit_image`), paper section 3.4, and pictures of the fits (:func:`plot_uv_fit`,
:func:`plot_image_fit`). See ``docs/fit.md``. Stacked line spectra: :func:`fit_line` (a
Gaussian with the bins' covariance) and :func:`integrate_line` (``docs/linestack.md``)."""

from __future__ import annotations

from typing import Any

__all__ = ["FitResult", "ImageFitOptions", "LineFit", "UvFitOptions", "fit_image", "fit_line",
           "fit_uv", "integrate_line", "plot_image_fit", "plot_uv_fit"]


def __getattr__(name: str) -> Any:
    if name == "fit_uv":
        from xstack.fit.uvfit import fit_uv
        return fit_uv
    if name == "fit_image":
        from xstack.fit.imfit import fit_image
        return fit_image
    if name == "UvFitOptions":
        from xstack.fit.uvfit import UvFitOptions
        return UvFitOptions
    if name == "ImageFitOptions":
        from xstack.fit.imfit import ImageFitOptions
        return ImageFitOptions
    if name == "FitResult":
        from xstack.fit.result import FitResult
        return FitResult
    if name in ("fit_line", "integrate_line", "LineFit"):
        from xstack.fit import line
        return getattr(line, name)
    if name in ("plot_uv_fit", "plot_image_fit"):
        from xstack.fit import plot
        return getattr(plot, name)
    raise AttributeError(name)
