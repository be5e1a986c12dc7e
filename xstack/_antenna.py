"""Per-antenna UVW of (time, baseline)-ordered visibility rows (shared by uvstack and noise).

The baseline phasor factorises, exp(-2 pi i nu/c b.s) = E_a1 conj(E_a2) with
E_a = exp(-2 pi i nu/c uvw_a.s), when the baseline UVW are differences of per-antenna UVW.
:func:`antenna_layout` solves those per integration (least squares over the rows that
matter) and :meth:`AntennaLayout.phase_error` bounds the phase error the factorisation can
make, to be checked against a tolerance (:data:`ANTENNA_TOL_RAD`) before it is used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from xstack.coords import SPEED_OF_LIGHT


class FactorisationError(ValueError):
    """The baseline UVW of a block are not differences of per-antenna UVW (to tolerance)."""


@dataclass(frozen=True)
class AntennaLayout:
    """Per-antenna UVW of a block of rows ordered (time, baseline).

    Attributes
    ----------
    uvw : (ntime, nant, 3) float64, metres; a solution of
        ``uvw_row = uvw[t, antenna1[b]] - uvw[t, antenna2[b]]`` for row ``t * nbl + b``
    antenna1, antenna2 : (nbl,) int64, compact antenna indices (0 .. nant - 1)
    used : (ntime, nant) bool, antenna takes part in a used row at that time
    rows : (nrow,) bool, rows the solution was fitted to and checked on
    residual : (nrow, 3) float64, ``|uvw_row - (U_a1 - U_a2)|`` in metres (0 for unused rows)
    """

    uvw: np.ndarray
    antenna1: np.ndarray
    antenna2: np.ndarray
    used: np.ndarray
    rows: np.ndarray
    residual: np.ndarray

    @property
    def rows_per_antenna(self) -> float:
        """Used rows per used (time, antenna): the factor fewer sine/cosine evaluations."""
        return float(self.rows.sum()) / max(int(self.used.sum()), 1)

    def phase_error(self, l: np.ndarray, m: np.ndarray, n_minus_1: np.ndarray,
                    frequency: np.ndarray) -> float:
        """Upper bound (radians) of the phase error the factorisation makes at any position.

        ``2 pi nu_max / c * max_rows(|du| max|l| + |dv| max|m| + |dw| max|n - 1|)`` with
        (du, dv, dw) the reconstruction residual of the row.
        """
        if not self.rows.any() or np.size(l) == 0:
            return 0.0
        lim = np.array([np.max(np.abs(l)), np.max(np.abs(m)), np.max(np.abs(n_minus_1))])
        worst = float(np.max(self.residual[self.rows] @ lim))
        return 2.0 * math.pi * float(np.max(np.abs(frequency))) / SPEED_OF_LIGHT * worst


def antenna_layout(uvw: np.ndarray, antenna1: np.ndarray, antenna2: np.ndarray,
                   row_ok: np.ndarray | None = None) -> AntennaLayout:
    """Solve per-antenna UVW from the baseline UVW of a (time, baseline)-ordered block.

    Per time, least squares over the used rows (``row_ok`` and finite UVW); the minimum-norm
    solution is taken, since a constant offset per connected set of antennas cancels in every
    baseline difference. Times with the same set of used rows share one pseudo-inverse.

    Parameters
    ----------
    uvw : (ntime * nbl, 3) float64, metres, rows ordered time-major
    antenna1, antenna2 : (nbl,) antenna ids of the baselines (any integers)
    row_ok : (ntime * nbl,) bool, rows that matter (default: all)

    Raises
    ------
    FactorisationError
        The rows are not a whole number of times of ``nbl`` baselines.
    """
    uvw = np.asarray(uvw, dtype=np.float64)
    a1 = np.asarray(antenna1).ravel()
    a2 = np.asarray(antenna2).ravel()
    nbl, nrow = a1.size, uvw.shape[0]
    if nbl == 0 or a2.size != nbl or nrow % nbl:
        raise FactorisationError(f"{nrow} rows are not whole times of {nbl} baselines")
    ntime = nrow // nbl
    ids, inv = np.unique(np.concatenate([a1, a2]), return_inverse=True)
    c1, c2 = inv[:nbl].astype(np.int64), inv[nbl:].astype(np.int64)
    nant = ids.size
    X = uvw.reshape(ntime, nbl, 3)
    ok = np.all(np.isfinite(X), axis=-1)
    if row_ok is not None:
        ok &= np.asarray(row_ok, dtype=bool).reshape(ntime, nbl)
    inc = np.zeros((nbl, nant))
    inc[np.arange(nbl), c1] += 1.0
    inc[np.arange(nbl), c2] -= 1.0  # an autocorrelation row is all zero: its uvw must be 0
    U = np.zeros((ntime, nant, 3))
    patterns, which = np.unique(ok, axis=0, return_inverse=True)
    which = np.asarray(which).ravel()
    for ip, pat in enumerate(patterns):
        if not pat.any():
            continue
        ts = np.flatnonzero(which == ip)
        pinv = np.linalg.pinv(inc[pat])
        Xp = X[ts][:, pat]
        Ut = np.einsum("ab,tbx->tax", pinv, Xp)
        # one step of iterative refinement: the SVD pseudo-inverse leaves ~10 ulp
        Ut += np.einsum("ab,tbx->tax", pinv, Xp - (Ut[:, c1[pat]] - Ut[:, c2[pat]]))
        U[ts] = Ut
    resid = np.where(ok[..., None], np.abs(np.where(ok[..., None], X, 0.0)
                                           - (U[:, c1] - U[:, c2])), 0.0)
    used = np.zeros((ntime, nant), dtype=bool)
    for c in (c1, c2):
        np.logical_or.at(used, (np.repeat(np.arange(ntime), nbl), np.tile(c, ntime)), ok.ravel())
    return AntennaLayout(U, c1, c2, used, ok.ravel(), resid.reshape(nrow, 3))


#: Default tolerance (radians) of the antenna factorisation's phase error, see
#: :meth:`AntennaLayout.phase_error`. Simulated and correlator UVW reach ~1e-12.
ANTENNA_TOL_RAD = 1e-9


#: Automatic engine choices take the antenna path only with at least this many fitted rows
#: per used antenna and time: the antenna phasors cost about what the sine/cosine of a row
#: saves.
MIN_ROWS_PER_ANTENNA = 2.0
