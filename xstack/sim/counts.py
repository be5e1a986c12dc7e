"""Flux-density distributions of simulated source populations.

Every distribution is a differential source count dN/dS (per Jy per steradian, up to a
normalisation) between limits ``s_min`` and ``s_max``; fluxes are drawn by inverting the
numerically integrated cumulative distribution on a fine logarithmic grid (4097 points;
the sampling error is far below any count's own uncertainty).

Models
------
``fixed``
    every source has flux ``value``.
``schechter``
    dN/dS ∝ (S/S*)^alpha exp(-S/S*) (Lindroos et al. 2015 eq. 2 with the usual sign of
    alpha: with alpha = -1.6, S* = 1.7 µJy and limits 0.25–10 S* the mean flux is 0.98 µJy,
    the paper's quoted 0.99 µJy; the paper's printed exponent ``-alpha`` would give 4.4 µJy).
``power_law``
    dN/dS ∝ S^index.
``bondi2008``
    the 1.4 GHz COSMOS counts of Bondi et al. (2008):
    log10[(dN/dS) S^2.5 / (Jy^1.5 sr^-1)] = sum_n a_n [log10(S/mJy)]^n.
``bethermin2012_1.1mm``
    an *approximate* tabulation of the Béthermin et al. (2012) model counts at 1.1 mm
    (cumulative N(>S) per deg² at a few fluxes, interpolated log-log; see ``docs/sim.md``):
    not the published model itself, which is not available offline.
``table``
    user-tabulated (flux, dN/dS) pairs, interpolated log-log.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from xstack.errors import XstackError

BONDI2008_COEFFS = (0.805, 0.493, 0.564, -0.129, -0.195, 0.110, -0.017)

#: Approximate cumulative counts N(>S) (deg^-2) at 1.1 mm after the Béthermin et al. (2012)
#: model, as (S in mJy, N(>S)). Smooth by construction; slopes match the model's shape (flat,
#: ~-0.7, at sub-mJy fluxes, steepening to ~-2.5 above ~5 mJy). Documented in docs/sim.md.
BETHERMIN2012_1P1MM_CUMULATIVE = (
    (0.003, 1.2e6), (0.01, 5.0e5), (0.03, 2.3e5), (0.1, 8.0e4), (0.3, 2.6e4),
    (1.0, 6.0e3), (2.0, 2.2e3), (3.0, 1.0e3), (5.0, 2.8e2), (10.0, 3.0e1), (20.0, 2.0),
    (50.0, 0.05),
)

KINDS = ("fixed", "schechter", "power_law", "bondi2008", "bethermin2012_1.1mm", "table")
DEG2_PER_SR = (180.0 / np.pi) ** 2


@dataclass
class FluxDistribution:
    """A flux-density distribution (all fluxes in Jy).

    Parameters
    ----------
    kind
        One of :data:`KINDS`.
    value
        Flux of ``fixed``.
    s_min, s_max
        Limits of every other kind.
    alpha, s_star
        ``schechter`` parameters.
    index
        ``power_law`` slope of dN/dS.
    flux, dnds
        ``table``: fluxes (Jy) and dN/dS (any normalisation).
    """

    kind: str = "fixed"
    value: float | None = None
    s_min: float | None = None
    s_max: float | None = None
    alpha: float | None = None
    s_star: float | None = None
    index: float | None = None
    flux: list[float] = field(default_factory=list)
    dnds: list[float] = field(default_factory=list)

    def validate(self, where: str) -> None:
        """Raise :class:`XstackError` naming ``where`` for bad parameters."""
        if self.kind not in KINDS:
            raise XstackError(f"{where}.kind: unknown flux distribution {self.kind!r} "
                              f"(use {', '.join(KINDS)})")
        if self.kind == "fixed":
            if self.value is None or not np.isfinite(self.value) or self.value < 0:
                raise XstackError(f"{where}.value: a fixed flux must be a number >= 0 "
                                  f"(got {self.value!r})")
            return
        if self.s_min is None or self.s_max is None:
            raise XstackError(f"{where}: {self.kind} needs s_min and s_max")
        if not (0 < self.s_min < self.s_max) or not np.isfinite(self.s_max):
            raise XstackError(f"{where}.s_min/s_max: need 0 < s_min < s_max "
                              f"(got {self.s_min}, {self.s_max})")
        if self.kind == "schechter" and (self.alpha is None or not self.s_star
                                         or self.s_star <= 0):
            raise XstackError(f"{where}: schechter needs alpha and s_star > 0")
        if self.kind == "power_law" and self.index is None:
            raise XstackError(f"{where}.index: power_law needs an index")
        if self.kind == "table":
            f, d = np.asarray(self.flux, float), np.asarray(self.dnds, float)
            if f.size < 2 or f.size != d.size or np.any(f <= 0) or np.any(d < 0) \
                    or np.any(np.diff(f) <= 0):
                raise XstackError(f"{where}.flux/dnds: need >= 2 increasing positive fluxes "
                                  "and as many dN/dS values >= 0")

    def dnds_function(self, s: np.ndarray) -> np.ndarray:
        """dN/dS at fluxes ``s`` (Jy); per Jy per sr for the astrophysical counts."""
        s = np.asarray(s, dtype=np.float64)
        if self.kind == "schechter":
            x = s / self.s_star
            return x ** self.alpha * np.exp(-x)
        if self.kind == "power_law":
            return s ** self.index
        if self.kind == "bondi2008":
            x = np.log10(s * 1e3)
            poly = sum(a * x**n for n, a in enumerate(BONDI2008_COEFFS))
            return s ** -2.5 * 10.0 ** poly
        if self.kind == "bethermin2012_1.1mm":
            return bethermin_dnds(s)
        if self.kind == "table":
            f, d = np.log(np.asarray(self.flux)), np.asarray(self.dnds, float)
            logd = np.log(np.maximum(d, 1e-300))
            return np.exp(np.interp(np.log(s), f, logd, left=-np.inf, right=-np.inf))
        raise XstackError(f"flux distribution {self.kind!r} has no dN/dS")

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Draw ``n`` fluxes (Jy)."""
        if self.kind == "fixed":
            return np.full(n, float(self.value))
        grid, cdf = self._cdf()
        return np.exp(np.interp(rng.uniform(size=n), cdf, np.log(grid)))

    def mean(self) -> float:
        """Mean flux of the distribution (Jy)."""
        if self.kind == "fixed":
            return float(self.value)
        s = np.geomspace(self.s_min, self.s_max, 4097)
        d = self.dnds_function(s)
        return float(np.trapezoid(s * d * s, np.log(s)) / np.trapezoid(d * s, np.log(s)))

    def _cdf(self) -> tuple[np.ndarray, np.ndarray]:
        s = np.geomspace(self.s_min, self.s_max, 4097)
        # integrate dN/dS dS = dN/dS S dlnS, trapezoid in ln S
        y = self.dnds_function(s) * s
        c = np.concatenate([[0.0], np.cumsum(0.5 * (y[1:] + y[:-1]) * np.diff(np.log(s)))])
        if not c[-1] > 0:
            raise XstackError(f"flux distribution {self.kind!r}: no sources between "
                              f"{self.s_min} and {self.s_max} Jy")
        return s, c / c[-1]

    def expected_number(self, area_sr: float) -> float:
        """Expected number of sources between the limits in ``area_sr`` (absolute counts)."""
        s = np.geomspace(self.s_min, self.s_max, 4097)
        y = self.dnds_function(s) * s
        return float(np.trapezoid(y, np.log(s)) * area_sr)


def bethermin_dnds(s: np.ndarray) -> np.ndarray:
    """dN/dS (Jy^-1 sr^-1) of :data:`BETHERMIN2012_1P1MM_CUMULATIVE` (log-log interpolation)."""
    tab = np.array(BETHERMIN2012_1P1MM_CUMULATIVE)
    ls, ln = np.log(tab[:, 0] * 1e-3), np.log(tab[:, 1] * DEG2_PER_SR)
    x = np.log(np.asarray(s, dtype=np.float64))
    logn = np.interp(x, ls, ln)
    slope = np.interp(x, 0.5 * (ls[1:] + ls[:-1]), np.diff(ln) / np.diff(ls))
    # N(>S) = exp(logn); dN/dS = -dN/dS(cumulative) = -slope N / S
    return np.where((x >= ls[0]) & (x <= ls[-1]), -slope * np.exp(logn) / np.exp(x), 0.0)


def s_min_for_count(dist: FluxDistribution, count: float, area_sr: float) -> float:
    """Lower flux limit (Jy) at which ``dist`` (absolute counts) predicts ``count`` sources
    above it, below ``dist.s_max``, in ``area_sr`` steradians."""
    from scipy.optimize import brentq

    def excess(log_smin: float) -> float:
        trial = FluxDistribution(**{**dist.__dict__, "s_min": float(np.exp(log_smin))})
        return trial.expected_number(area_sr) - count

    lo, hi = np.log(dist.s_max) - 30.0, np.log(dist.s_max) - 1e-6
    if excess(lo) < 0:
        raise XstackError(f"{dist.kind}: fewer than {count} sources in the area at any flux")
    return float(np.exp(brentq(excess, lo, hi, xtol=1e-10)))


def flux_from_value(value: Any, where: str) -> float:
    """A flux given as a number (Jy) or a string with units (``"20uJy"``)."""
    from xstack.coords import parse_flux

    try:
        out = parse_flux(value)
    except XstackError as exc:
        raise XstackError(f"{where}: {exc}") from None
    if not np.isfinite(out):
        raise XstackError(f"{where}: flux must be finite")
    if out < 0:
        raise XstackError(f"{where}: flux must not be negative (got {value!r})")
    return out
