"""The result of a model fit, in either domain."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from xstack._json import finite_or_none
from xstack._result import Result, json_ready


@dataclass(kw_only=True)
class FitResult(Result):
    """Fitted flux density and size of a stacked source.

    Attributes
    ----------
    model : "point" or "gaussian"
    domain : "uv" or "image"
    flux_jy, flux_err_jy : integrated flux density and its 1-sigma error, Jy
    fwhm_arcsec, fwhm_err_arcsec : FWHM of the circular Gaussian and its 1-sigma error
        (None for the point model). The size is fitted as ``fwhm^2``; the error is half the
        width of the 1-sigma interval of ``fwhm^2`` mapped through the square root.
    fwhm_upper_limit_arcsec : 95 % upper limit on the FWHM (flat prior on fwhm^2 >= 0)
    resolved : True when the fitted fwhm^2 is more than 3 sigma above 0
    parameters : names of the fitted parameters, in the order of ``covariance``
    values : fitted parameter values, same order (fwhm2 in arcsec^2)
    covariance : parameter covariance (after ``error_scale`` is applied)
    chi2, dof, chi2_reduced : goodness of fit (real and imaginary parts for uv fits)
    error_scale : factor the errors were multiplied by (sqrt(chi2_reduced) or 1)
    n_data : number of visibilities (uv) or pixels (image) used
    extra : stage-specific details (constant term, correlation treatment, bins, ...)
    options : the fit's options as given (:class:`~xstack.fit.imfit.ImageFitOptions` or
        :class:`~xstack.fit.uvfit.UvFitOptions` ``.to_dict()``)
    """

    model: str
    domain: str
    flux_jy: float
    flux_err_jy: float
    fwhm_arcsec: float | None = None
    fwhm_err_arcsec: float | None = None
    fwhm_upper_limit_arcsec: float | None = None
    resolved: bool | None = None
    parameters: tuple[str, ...] = ()
    values: np.ndarray = field(default_factory=lambda: np.zeros(0))
    covariance: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    chi2: float = float("nan")
    dof: int = 0
    chi2_reduced: float = float("nan")
    error_scale: float = 1.0
    n_data: int = 0
    extra: dict[str, Any] = field(default_factory=dict)
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def n_vis(self) -> int:
        """Number of visibilities used (uv fits)."""
        return self.n_data

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (NaN/inf become None)."""
        out = {
            "model": self.model,
            "domain": self.domain,
            "flux_jy": finite_or_none(self.flux_jy),
            "flux_err_jy": finite_or_none(self.flux_err_jy),
            "fwhm_arcsec": finite_or_none(self.fwhm_arcsec),
            "fwhm_err_arcsec": finite_or_none(self.fwhm_err_arcsec),
            "fwhm_upper_limit_arcsec": finite_or_none(self.fwhm_upper_limit_arcsec),
            "resolved": self.resolved,
            "parameters": list(self.parameters),
            "values": [finite_or_none(v) for v in np.ravel(self.values)],
            "covariance": [[finite_or_none(v) for v in row] for row in np.atleast_2d(self.covariance)],
            "chi2": finite_or_none(self.chi2),
            "dof": int(self.dof),
            "chi2_reduced": finite_or_none(self.chi2_reduced),
            "error_scale": finite_or_none(self.error_scale),
            "n_data": int(self.n_data),
            "options": json_ready(self.options),
        }
        for key, value in self.extra.items():
            if isinstance(value, (np.generic,)):
                value = value.item()
            if isinstance(value, float):
                value = finite_or_none(value)
            out[key] = value
        return out

    def table(self) -> Any:
        """One row per fitted parameter: ``parameter``, ``value``, ``error`` (the square root of
        the covariance's diagonal; fwhm2 in arcsec^2)."""
        from astropy.table import Table

        values = np.ravel(self.values).astype(np.float64)
        cov = np.atleast_2d(self.covariance)
        err = np.sqrt(np.diag(cov)) if cov.size else np.full(values.size, np.nan)
        return Table({"parameter": list(self.parameters), "value": values, "error": err})
