"""Random stacking positions inside the primary beam(s), away from targets and bright sources.

Positions are drawn from a *region* (:class:`Region`, :func:`make_region`) intersected with
the pointings' discs: by default the footprint of the targets (convex hulls of their
friends-of-friends groups, grown by half their typical spacing, :func:`hull_region`), or the
whole beam, a polygon or a FITS mask.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from xstack.coords import angular_separation, lm_to_radec, mean_direction, radec_to_lmn
from xstack.errors import OptionError, XstackError, XstackWarning

ARCSEC = np.pi / 180.0 / 3600.0


def _xyz(ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
    cd = np.cos(dec)
    return np.stack([cd * np.cos(ra), cd * np.sin(ra), np.sin(dec)], axis=-1)


def _chord(angle: float) -> float:
    return 2.0 * np.sin(min(angle, np.pi) / 2.0)


def _uniform_in_union(n: int, centers: np.ndarray, radii: np.ndarray,
                      rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform on the sphere inside the union of discs (centers (P, 2) rad)."""
    out_ra, out_dec = [], []
    got = 0
    while got < n:
        m = int(1.5 * (n - got)) + 16
        ra, dec, cover = _mixture_draw(m, centers, radii, rng)
        # accept with probability 1 / (number of discs covering the point): uniform on the union
        keep = rng.uniform(size=m) * np.maximum(cover, 1) < 1.0
        out_ra.append(ra[keep])
        out_dec.append(dec[keep])
        got += int(keep.sum())
    return np.concatenate(out_ra)[:n], np.concatenate(out_dec)[:n]


def _uniform_in_region(n: int, centers: np.ndarray, radii: np.ndarray, region: Region | None,
                       rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points uniform on the sphere inside ``region`` and the union of the discs."""
    if region is None or region._contains is None:
        return _uniform_in_union(n, centers, radii, rng)
    pc, pr = region._proposal_for(centers, radii)
    out_ra, out_dec = [], []
    got, tried, rate = 0, 0, 0.5
    while got < n:
        m = int(min(2e6, 1.3 * (n - got) / max(rate, 1e-3))) + 16
        ra, dec = _uniform_in_union(m, pc, pr, rng)
        ok = region.contains(ra, dec) & _in_discs(ra, dec, centers, radii)
        tried += m
        got += int(ok.sum())
        out_ra.append(ra[ok])
        out_dec.append(dec[ok])
        rate = max(got / tried, 1e-3)
        if got == 0 and tried > 500000:
            raise OptionError(f"the region ({region.description}) does not overlap the primary "
                              "beams of the pointings: change region=", option="region")
    return np.concatenate(out_ra)[:n], np.concatenate(out_dec)[:n]


def random_positions(n: int, realizations: int, centers: np.ndarray, radii: np.ndarray, *,
                     avoid_ra: np.ndarray, avoid_dec: np.ndarray, min_separation: float,
                     rng: np.random.Generator, max_rounds: int = 30,
                     region: Any = None, region_targets: tuple[np.ndarray, np.ndarray] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """``realizations`` sets of ``n`` random positions (radians, arrays (R, n)).

    Positions are uniform on the sphere inside the union of the discs (``centers`` (P, 2),
    ``radii`` (P,) rad: primary beam above its cutoff) and inside ``region`` (if given: a
    :class:`Region`, or a :func:`make_region` spec such as ``"hull"`` built from
    ``region_targets`` = (ra, dec) rad with margin floor ``min_separation``; built once and
    cached for repeated calls), at least ``min_separation`` (rad) from every ``avoid``
    position (targets, bright sources) and from each other within a set.

    Raises
    ------
    XstackError
        If a set cannot be completed: the field is too crowded for this separation.
    """
    from scipy.spatial import cKDTree

    if region is not None and not isinstance(region, Region):
        if region_targets is None:
            region_targets = (np.zeros(0), np.zeros(0))
        region = cached_region(region, *region_targets, min_margin=min_separation)
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
            ra, dec = _uniform_in_region(4 * need + 16, centers, radii, region, rng)
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
                f"each other inside the primary beam{'' if region is None else ' and the region'}"
                f" (placed {len(kept_ra)}); lower min_separation_arcsec, use fewer positions"
                f"{'' if region is None else ' or a larger region='}",
                option=("min_separation_arcsec", "region"))
        out_ra[r] = kept_ra[:n]
        out_dec[r] = kept_dec[:n]
    return out_ra, out_dec


# ----------------------------------------------------------------------------- regions

ARCMIN2_SR = (np.pi / 180.0 / 60.0) ** 2

#: friends-of-friends linking length of the default footprint: targets closer than
#: HULL_LINK x s x sqrt(ln(n) / ln 2) belong to one group (one hull), s the median
#: nearest-neighbour spacing of the n targets (sqrt(ln n / ln 2) s is the largest
#: nearest-neighbour distance expected of n uniform points: with 3 of those, uniform
#: catalogs of >= 30 targets are one group in > 99.5 % of draws)
HULL_LINK = 3.0
#: the hull of each group grows by this many median nearest-neighbour spacings
HULL_MARGIN = 0.5
#: fewer targets than this: the footprint is poorly defined (a warning says so)
HULL_MIN_TARGETS = 10


def _mean_direction(ra: np.ndarray, dec: np.ndarray) -> tuple[float, float]:
    c = mean_direction(ra, dec)
    if c is None:
        raise XstackError("the positions spread over the whole sky: no tangent plane holds them "
                          "(give region='beam' or a polygon / mask)", option="region")
    return c


def _gnomonic(ra: np.ndarray, dec: np.ndarray, ra0: float, dec0: float
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gnomonic (tangent-plane) coordinates x = l/n, y = m/n and a mask n > 0.

    Great circles are straight lines in this projection, so a convex polygon there is a
    spherical convex polygon; it is exact at the poles and across RA = 0/360.
    """
    l, m, n, _ = radec_to_lmn(ra, dec, ra0, dec0)
    ok = n > 1e-6
    nn = np.where(ok, n, 1.0)
    return l / nn, m / nn, ok


def _seg_dist2(px: np.ndarray, py: np.ndarray, vx: np.ndarray, vy: np.ndarray) -> np.ndarray:
    """Squared distance of points (M,) to the closed polyline through vertices (V,): (M,)."""
    ax, ay = vx, vy
    bx, by = np.roll(vx, -1), np.roll(vy, -1)
    if vx.size == 2:  # a segment, not a closed loop
        ax, ay, bx, by = vx[:1], vy[:1], vx[1:], vy[1:]
    dx, dy = bx - ax, by - ay
    len2 = dx * dx + dy * dy
    t = ((px[:, None] - ax) * dx + (py[:, None] - ay) * dy) / np.where(len2 > 0, len2, 1.0)
    t = np.clip(np.where(len2 > 0, t, 0.0), 0.0, 1.0)
    ex = px[:, None] - (ax + t * dx)
    ey = py[:, None] - (ay + t * dy)
    return np.min(ex * ex + ey * ey, axis=1)


def _in_polygon(px: np.ndarray, py: np.ndarray, vx: np.ndarray, vy: np.ndarray) -> np.ndarray:
    """Even-odd rule: points inside the simple polygon with vertices (V,) (any orientation)."""
    inside = np.zeros(px.shape, dtype=bool)
    if vx.size < 3:
        return inside
    x1, y1 = vx, vy
    x2, y2 = np.roll(vx, -1), np.roll(vy, -1)
    for a, b, c, d in zip(x1, y1, x2, y2):
        crosses = (b > py) != (d > py)
        with np.errstate(divide="ignore", invalid="ignore"):
            xint = a + (py - b) * (c - a) / (d - b)
        inside ^= crosses & (px < xint)
    return inside


def _polygon_area(vx: np.ndarray, vy: np.ndarray) -> float:
    if vx.size < 3:
        return 0.0
    return 0.5 * abs(float(np.dot(vx, np.roll(vy, -1)) - np.dot(vy, np.roll(vx, -1))))


class Region:
    """Where random (and Monte Carlo injection) positions may be placed.

    A region is intersected with the pointings (a position must also lie inside some
    pointing's disc, see :func:`random_positions`). Build one with :func:`make_region`.

    Attributes
    ----------
    kind : ``hull``, ``beam``, ``polygon`` or ``mask``
    description : one line for people, completed with the area by :meth:`describe`
    n_targets : number of targets the region was derived from (hull), else 0
    proposal : (centers (Q, 2) rad, radii (Q,) rad) discs that contain the region, or None
        (the region is the whole sky: the pointings' discs bound it)
    """

    def __init__(self, kind: str, description: str, contains: Any = None,
                 proposal: tuple[np.ndarray, np.ndarray] | None = None, n_targets: int = 0):
        self.kind = kind
        self.description = description
        self._contains = contains
        self.proposal = proposal
        self.n_targets = int(n_targets)

    def contains(self, ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        """Boolean mask of the positions (radians) inside the region."""
        ra = np.asarray(ra, dtype=np.float64)
        if self._contains is None:
            return np.ones(ra.shape, dtype=bool)
        return np.asarray(self._contains(ra, np.asarray(dec, dtype=np.float64)), dtype=bool)

    def area_sr(self, centers: np.ndarray, radii: np.ndarray, n: int = 40000) -> float:
        """Area (sr) of the region inside the union of the discs, by Monte Carlo (~1 %)."""
        centers, radii = np.atleast_2d(centers), np.atleast_1d(radii)
        pc, pr = self._proposal_for(centers, radii)
        rng = np.random.default_rng(20150101)
        area = 2 * np.pi * (1.0 - np.cos(pr))
        ra, dec, cover = _mixture_draw(n, pc, pr, rng)
        ok = self.contains(ra, dec) & _in_discs(ra, dec, centers, radii)
        return float(area.sum() * np.mean(ok / np.maximum(cover, 1)))

    def describe(self, centers: np.ndarray, radii: np.ndarray) -> str:
        """``description`` with the area (arcmin^2) inside the pointings' discs."""
        a = self.area_sr(centers, radii) / ARCMIN2_SR
        return f"{self.description}; {a:.4g} arcmin^2 inside the pointings"

    def _proposal_for(self, centers: np.ndarray, radii: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """The smaller (in summed area) of the region's discs and the pointings' discs."""
        if self.proposal is None:
            return centers, radii
        pc, pr = self.proposal
        if np.sum(1 - np.cos(pr)) < np.sum(1 - np.cos(radii)):
            return pc, pr
        return centers, radii


def _in_discs(ra: np.ndarray, dec: np.ndarray, centers: np.ndarray, radii: np.ndarray
              ) -> np.ndarray:
    cxyz = _xyz(centers[:, 0], centers[:, 1])
    return np.any(_xyz(ra, dec) @ cxyz.T >= np.cos(radii)[None, :] - 1e-15, axis=1)


def _mixture_draw(m: int, centers: np.ndarray, radii: np.ndarray, rng: np.random.Generator
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``m`` points from the area-weighted mixture of uniform discs, and their cover counts."""
    area = 1.0 - np.cos(radii)
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
                                        centers[q, 0], centers[q, 1])
    cxyz = _xyz(centers[:, 0], centers[:, 1])
    cover = (_xyz(ra, dec) @ cxyz.T >= np.cos(radii)[None, :] - 1e-15).sum(axis=1)
    return ra, dec, cover


def _bounding_disc(ra: np.ndarray, dec: np.ndarray, pad: float) -> tuple[float, float, float]:
    c = _mean_direction(ra, dec)
    return c[0], c[1], float(angular_separation(ra, dec, *c).max()) + pad


def hull_region(ra: np.ndarray, dec: np.ndarray, *, min_margin: float = 0.0,
                link: float = HULL_LINK, margin: float = HULL_MARGIN) -> Region:
    """The default footprint of a catalog: convex hulls of its groups of targets, grown a little.

    Targets (radians) are projected on the tangent plane (gnomonic) about their mean
    direction. With s the median nearest-neighbour spacing, targets closer than
    ``link`` x s x sqrt(ln n / ln 2) are friends (friends-of-friends groups: the factor is
    the largest nearest-neighbour distance expected of n uniform points in units of s), and
    each group's convex hull grows by
    d = max(``margin`` x s, ``min_margin``) (rad): so the hull of points drawn uniformly in a
    box reaches the box edge, and a mosaic whose targets sit around pointings far apart gets
    one small hull per pointing instead of one spanning empty sky. A group of one or two
    targets (or collinear targets) is the disc / band of width d around them.

    Warns (naming ``--region``) for fewer than ``HULL_MIN_TARGETS`` targets and for a hull of
    near-zero area (collinear targets).
    """
    import warnings

    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import ConvexHull, QhullError, cKDTree

    ra = np.atleast_1d(np.asarray(ra, dtype=np.float64))
    dec = np.atleast_1d(np.asarray(dec, dtype=np.float64))
    n = ra.size
    if n == 0:
        raise XstackError("no target to derive a region from (give region=)", option="region")
    ra0, dec0 = _mean_direction(ra, dec)
    if float(angular_separation(ra, dec, ra0, dec0).max()) > np.radians(60):
        raise XstackError("the targets spread over more than 60 deg: no tangent-plane hull "
                          "(give region='beam', a polygon file or a FITS mask)", option="region")
    x, y, _ = _gnomonic(ra, dec, ra0, dec0)
    pts = np.stack([x, y], axis=1)
    uniq = np.unique(np.round(pts, 15), axis=0)
    s = 0.0
    if uniq.shape[0] >= 2:
        d, _ = cKDTree(uniq).query(uniq, k=2)
        s = float(np.median(d[:, 1]))
    d_margin = max(margin * s, float(min_margin))
    if d_margin <= 0:
        d_margin = 1.0 * ARCSEC
    if n < HULL_MIN_TARGETS:
        warnings.warn(XstackWarning(f"only {n} targets: their footprint (hull) is poorly "
                                    "defined; give the survey area with region=POLYGON "
                                    "(polygon file or FITS mask) or region='beam'",
                                    option="region"),
                      stacklevel=3)
    if uniq.shape[0] >= 2:
        link_len = link * s * np.sqrt(max(np.log(n), 1.0) / np.log(2.0))
        pairs = cKDTree(pts).query_pairs(link_len, output_type="ndarray")
    else:
        pairs = np.zeros((0, 2), dtype=np.int64)
    from scipy.sparse import coo_matrix

    adj = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    n_groups, label = connected_components(adj, directed=False)
    polys = []
    poly_area = 0.0
    thin = False
    biggest = np.bincount(label).argmax()
    for g in range(n_groups):
        gp = np.unique(np.round(pts[label == g], 15), axis=0)
        verts = gp
        if gp.shape[0] >= 3:
            try:
                h = ConvexHull(gp)
                verts = gp[h.vertices]
            except QhullError:
                verts = None
            if verts is not None:
                ext = float(np.max(np.ptp(gp, axis=0)))
                if _polygon_area(verts[:, 0], verts[:, 1]) < 0.01 * ext * ext:
                    verts = None
            if verts is None:  # collinear: the segment between the extreme points
                c = gp - gp.mean(axis=0)
                u = np.linalg.svd(c, full_matrices=False)[2][0]
                t = c @ u
                verts = gp[[np.argmin(t), np.argmax(t)]]
                if g == biggest:
                    thin = True
        polys.append(verts)
        poly_area += _polygon_area(verts[:, 0], verts[:, 1])
    if thin:
        warnings.warn(XstackWarning(f"the {n} targets are (nearly) collinear: their hull has "
                                    "almost no area; give the survey area with region=POLYGON "
                                    "(polygon file or FITS mask) or region='beam'",
                                    option="region"),
                      stacklevel=3)
    d2 = d_margin * d_margin

    def contains(r: np.ndarray, dd: np.ndarray) -> np.ndarray:
        px, py, ok = _gnomonic(r, dd, ra0, dec0)
        out = np.zeros(px.shape, dtype=bool)
        for v in polys:
            rest = ok & ~out
            if not rest.any():
                break
            qx, qy = px[rest], py[rest]
            hit = _in_polygon(qx, qy, v[:, 0], v[:, 1])
            hit[~hit] = _seg_dist2(qx[~hit], qy[~hit], v[:, 0], v[:, 1]) <= d2
            out[rest] = hit
        return out

    # proposal: one disc per group around its vertices (grown by the margin)
    pc, pr = [], []
    for v in polys:
        vra, vdec = lm_to_radec(*_unproject(v[:, 0], v[:, 1]), ra0, dec0)
        cra, cdec, rad = _bounding_disc(vra, vdec, 1.05 * d_margin + 1e-9)
        pc.append((cra, cdec))
        pr.append(rad)
    groups = "1 group" if n_groups == 1 else f"{n_groups} groups"
    desc = (f"hull: convex hull of {n} targets ({groups}, grown by "
            f"{d_margin / ARCSEC:.3g} arcsec)")
    return Region("hull", desc, contains, (np.array(pc), np.array(pr)), n_targets=n)


def _unproject(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gnomonic (x, y) -> direction cosines (l, m) on the near hemisphere."""
    n = 1.0 / np.sqrt(1.0 + x * x + y * y)
    return x * n, y * n


def polygon_region(ra_deg: np.ndarray, dec_deg: np.ndarray, name: str = "polygon") -> Region:
    """A spherical polygon (vertices in degrees, in order; edges are great circles)."""
    ra = np.radians(np.asarray(ra_deg, dtype=np.float64))
    dec = np.radians(np.asarray(dec_deg, dtype=np.float64))
    if ra.size < 3:
        raise XstackError(f"{name}: a polygon needs at least 3 vertices, got {ra.size}")
    ra0, dec0 = _mean_direction(ra, dec)
    if float(angular_separation(ra, dec, ra0, dec0).max()) > np.radians(80):
        raise XstackError(f"{name}: polygon wider than 80 deg from its center")
    vx, vy, _ = _gnomonic(ra, dec, ra0, dec0)
    if _polygon_area(vx, vy) <= 0:
        raise XstackError(f"{name}: the polygon has zero area")

    def contains(r: np.ndarray, d: np.ndarray) -> np.ndarray:
        px, py, ok = _gnomonic(r, d, ra0, dec0)
        return ok & _in_polygon(px, py, vx, vy)

    c = _bounding_disc(ra, dec, 1e-9)
    return Region("polygon", f"polygon {name} ({ra.size} vertices)", contains,
                  (np.array([c[:2]]), np.array([c[2]])))


def mask_region(path: str | Any) -> Region:
    """A FITS mask image: pixels that are finite and nonzero are inside (any celestial WCS)."""
    from astropy.io import fits
    from astropy.wcs import WCS

    name = str(path)
    try:
        with fits.open(path) as hdul:
            hdu = next((h for h in hdul if h.data is not None and h.data.ndim >= 2), None)
            if hdu is None:
                raise XstackError(f"{name}: no image in the FITS file")
            data = np.asarray(hdu.data, dtype=np.float64)
            wcs = WCS(hdu.header).celestial
    except OSError as exc:
        raise XstackError(f"{name}: cannot read the FITS mask ({exc})") from exc
    if wcs.naxis != 2:
        raise XstackError(f"{name}: the mask has no celestial WCS")
    while data.ndim > 2:
        data = data[0]
    good = np.isfinite(data) & (data != 0)
    if not good.any():
        raise XstackError(f"{name}: the mask selects no pixel")
    ny, nx = good.shape

    from astropy import units as u
    from astropy.coordinates import SkyCoord

    def contains(r: np.ndarray, d: np.ndarray) -> np.ndarray:
        # the mask's own frame (equatorial, galactic, ...): astropy transforms ICRS to it
        sky = SkyCoord(ra=np.atleast_1d(r) * u.rad, dec=np.atleast_1d(d) * u.rad, frame="icrs")
        with np.errstate(invalid="ignore"):
            x, y = wcs.world_to_pixel(sky)
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        ok = np.isfinite(x) & np.isfinite(y)
        ix = np.rint(np.where(ok, x, -1)).astype(np.int64)
        iy = np.rint(np.where(ok, y, -1)).astype(np.int64)
        ok &= (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        out = np.zeros(ix.shape, dtype=bool)
        out[ok] = good[iy[ok], ix[ok]]
        return out.reshape(np.shape(r))

    iy, ix = np.nonzero(good)
    step = max(1, iy.size // 200000)
    # the corners of the pixels inside bound the region
    sx, sy = ix[::step], iy[::step]
    cx = np.concatenate([sx - 0.5, sx + 0.5, sx - 0.5, sx + 0.5])
    cy = np.concatenate([sy - 0.5, sy - 0.5, sy + 0.5, sy + 0.5])
    corners = wcs.pixel_to_world(cx, cy).icrs
    wra, wdec = corners.ra.rad, corners.dec.rad
    ok = np.isfinite(wra) & np.isfinite(wdec)
    wra, wdec = wra[ok], wdec[ok]
    pad = 1e-9
    c = _bounding_disc(wra, wdec, pad)
    return Region("mask", f"FITS mask {Path(name).name} ({int(good.sum())} pixels)", contains,
                  (np.array([c[:2]]), np.array([c[2]])))


_REGION_CACHE: dict[tuple, Region] = {}


def cached_region(spec: Any, target_ra: np.ndarray, target_dec: np.ndarray, *,
                  min_margin: float = 0.0) -> Region:
    """:func:`make_region`, remembered for the same inputs (warnings are given once)."""
    ra = np.ascontiguousarray(target_ra, dtype=np.float64)
    dec = np.ascontiguousarray(target_dec, dtype=np.float64)
    key = (str(spec), ra.tobytes(), dec.tobytes(), float(min_margin))
    if key not in _REGION_CACHE:
        if len(_REGION_CACHE) > 8:
            _REGION_CACHE.clear()
        _REGION_CACHE[key] = make_region(spec, ra, dec, min_margin=min_margin)
    return _REGION_CACHE[key]


def make_region(spec: Any, target_ra: np.ndarray, target_dec: np.ndarray, *,
                min_margin: float = 0.0) -> Region:
    """The region for random positions from a user's choice.

    Parameters
    ----------
    spec
        ``"hull"`` (default footprint of the targets, :func:`hull_region`), ``"beam"`` (the
        whole primary beam inside the cutoff or the field radius), a polygon file (ECSV/CSV
        table of vertex ``ra``, ``dec`` in degrees, in order), a FITS mask image
        (``.fits``; finite nonzero pixels are inside) or a :class:`Region`.
    target_ra, target_dec
        Target positions (radians): the hull's points.
    min_margin
        Smallest growth of the hull (radians), e.g. the minimum separation of positions.
    """
    if isinstance(spec, Region):
        return spec
    if spec is None or (isinstance(spec, str) and spec.lower() == "hull"):
        return hull_region(target_ra, target_dec, min_margin=min_margin)
    if isinstance(spec, str) and spec.lower() == "beam":
        return Region("beam", "beam: the whole primary beam of every pointing (inside the "
                              "cutoff / field radius)")
    path = Path(spec)
    if not path.exists():
        raise XstackError(f"region {spec!r}: not hull, beam or an existing polygon / FITS file")
    if path.suffix.lower() in (".fits", ".fit", ".fts") or path.name.lower().endswith(".fits.gz"):
        return mask_region(path)
    from xstack.coords import read_catalog

    t = read_catalog(path)
    return polygon_region(np.asarray(t["ra"]), np.asarray(t["dec"]), name=path.name)
