"""Random stacking positions inside the primary beam(s), away from targets and bright sources."""

from __future__ import annotations

import numpy as np

from xstack.coords import lm_to_radec
from xstack.errors import XstackError

ARCSEC = np.pi / 180.0 / 3600.0


def _xyz(ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
    cd = np.cos(dec)
    return np.stack([cd * np.cos(ra), cd * np.sin(ra), np.sin(dec)], axis=-1)


def _chord(angle: float) -> float:
    return 2.0 * np.sin(min(angle, np.pi) / 2.0)


def _uniform_in_union(n: int, centres: np.ndarray, radii: np.ndarray,
                      rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform on the sphere inside the union of discs (centres (P, 2) rad)."""
    area = 1.0 - np.cos(radii)
    cxyz = _xyz(centres[:, 0], centres[:, 1])
    out_ra, out_dec = [], []
    got = 0
    while got < n:
        m = int(1.5 * (n - got)) + 16
        p = rng.choice(len(radii), size=m, p=area / area.sum())
        cos_t = 1.0 - rng.uniform(size=m) * area[p]
        sin_t = np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None))
        phi = rng.uniform(0.0, 2 * np.pi, size=m)
        ra = np.empty(m)
        dec = np.empty(m)
        for q in np.unique(p):
            sel = p == q
            ra[sel], dec[sel] = lm_to_radec(sin_t[sel] * np.sin(phi[sel]),
                                            sin_t[sel] * np.cos(phi[sel]),
                                            centres[q, 0], centres[q, 1])
        xyz = _xyz(ra, dec)
        # accept with probability 1 / (number of discs covering the point): uniform on the union
        cover = (xyz @ cxyz.T >= np.cos(radii)[None, :] - 1e-15).sum(axis=1)
        keep = rng.uniform(size=m) * np.maximum(cover, 1) < 1.0
        out_ra.append(ra[keep])
        out_dec.append(dec[keep])
        got += int(keep.sum())
    return np.concatenate(out_ra)[:n], np.concatenate(out_dec)[:n]


def random_positions(n: int, realizations: int, centres: np.ndarray, radii: np.ndarray, *,
                     avoid_ra: np.ndarray, avoid_dec: np.ndarray, min_separation: float,
                     rng: np.random.Generator, max_rounds: int = 30
                     ) -> tuple[np.ndarray, np.ndarray]:
    """``realizations`` sets of ``n`` random positions (radians, arrays (R, n)).

    Positions are uniform inside the union of the discs (primary beam above its cutoff),
    at least ``min_separation`` (rad) from every ``avoid`` position (targets, bright sources)
    and from each other within a set.

    Raises
    ------
    XstackError
        If a set cannot be completed: the field is too crowded for this separation.
    """
    from scipy.spatial import cKDTree

    avoid_tree = cKDTree(_xyz(np.asarray(avoid_ra), np.asarray(avoid_dec))) if len(avoid_ra) else None
    chord = _chord(min_separation)
    out_ra = np.empty((realizations, n))
    out_dec = np.empty((realizations, n))
    for r in range(realizations):
        kept_xyz = np.zeros((0, 3))
        kept_ra, kept_dec = [], []
        for _ in range(max_rounds):
            need = n - len(kept_ra)
            if need <= 0:
                break
            ra, dec = _uniform_in_union(4 * need + 16, centres, radii, rng)
            xyz = _xyz(ra, dec)
            ok = np.ones(ra.size, dtype=bool)
            if avoid_tree is not None and min_separation > 0:
                d, _ = avoid_tree.query(xyz, k=1)
                ok &= d >= chord
            if kept_xyz.shape[0] and min_separation > 0:
                d, _ = cKDTree(kept_xyz).query(xyz, k=1)
                ok &= d >= chord
            idx = np.flatnonzero(ok)
            if min_separation > 0 and idx.size > 1:
                pairs = cKDTree(xyz[idx]).query_pairs(chord, output_type="ndarray")
                alive = np.ones(idx.size, dtype=bool)
                for i, j in pairs[np.argsort(pairs[:, 0], kind="stable")]:
                    if alive[i] and alive[j]:
                        alive[j] = False
                idx = idx[alive]
            idx = idx[:need]
            kept_ra.extend(ra[idx])
            kept_dec.extend(dec[idx])
            kept_xyz = np.vstack([kept_xyz, xyz[idx]])
        if len(kept_ra) < n:
            raise XstackError(
                f"catalog too dense: cannot place {n} random positions at least "
                f"{min_separation / ARCSEC:.3g} arcsec from the targets, the avoided sources and "
                f"each other inside the primary beam (placed {len(kept_ra)}); lower "
                "min_separation_arcsec or use fewer positions")
        out_ra[r] = kept_ra[:n]
        out_dec[r] = kept_dec[:n]
    return out_ra, out_dec
