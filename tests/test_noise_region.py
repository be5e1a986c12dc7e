"""Where random / injection positions go: the targets' footprint, the beam, a polygon, a mask.

Every check of "inside" here is an independent plain-numpy (or astropy-coordinates)
computation: tangent-plane boxes at the region's own center, galactic latitudes, distances.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from _fit_helpers import noise_field
from test_noise_truth import _unproject  # the SIN inverse written out in plain numpy

from xstack.beams import standard_beam
from xstack.errors import XstackError
from xstack.noise.estimate import estimate_noise
from xstack.noise.positions import hull_region, make_region, random_positions

CENTER = (1.0, -0.5236)
ARCMIN = np.pi / 180 / 60
NO = np.zeros(0)


def _project(ra, dec, ra0, dec0):
    cd = np.cos(dec)
    l = cd * np.sin(ra - ra0)
    m = np.sin(dec) * np.cos(dec0) - cd * np.sin(dec0) * np.cos(ra - ra0)
    return l, m


def _box(center, half_arcmin, n, seed):
    rng = np.random.default_rng(seed)
    h = half_arcmin * ARCMIN
    return _unproject(rng.uniform(-h, h, n), rng.uniform(-h, h, n), *center)


def _draw(region, center, radius, n=3000, seed=1):
    ra, dec = random_positions(n, 1, np.array([center]), np.array([radius]), avoid_ra=NO,
                               avoid_dec=NO, min_separation=0.0,
                               rng=np.random.default_rng(seed), region=region)
    return ra[0], dec[0]


@pytest.mark.parametrize("center", [CENTER, (0.0002, 0.3), (2.0, np.radians(89.97)),
                                    (np.radians(359.99), np.radians(-89.99))])
def test_hull_of_a_box_is_the_box_also_at_the_poles_and_across_ra_zero(center):
    """300 targets in a 20'x20' box: random positions fill the box, and stay in it (up to the
    margin), wherever the box is: across RA = 0/360, and with a pole inside it."""
    ra, dec = _box(center, 10.0, 300, seed=2)
    if center[1] > 1.5:  # the pole is inside the box: RA covers all of 0..360
        assert np.ptp(np.degrees(ra)) > 300
    reg = hull_region(ra, dec)
    assert "1 group" in reg.description
    pr, pd = _draw(reg, center, 30 * ARCMIN)
    l, m = _project(pr, pd, *center)
    margin = float(reg.description.split("grown by ")[1].split(" arcsec")[0]) / 60 * ARCMIN
    assert np.abs(l).max() <= 10 * ARCMIN + margin * 1.01
    assert np.abs(m).max() <= 10 * ARCMIN + margin * 1.01
    # fills the box: each quadrant holds a quarter, the corners are reached
    for sl, sm in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        assert np.mean((np.sign(l) == sl) & (np.sign(m) == sm)) == pytest.approx(0.25, abs=0.04)
    assert np.mean((np.abs(l) > 8 * ARCMIN) & (np.abs(m) > 8 * ARCMIN)) > 0.02
    # its area is the box's (400 arcmin^2) within the hull's few-percent fuzz
    area = reg.area_sr(np.array([center]), np.array([30 * ARCMIN])) / ARCMIN**2
    assert area == pytest.approx(400.0, rel=0.06)


def test_separate_groups_get_separate_hulls():
    """Targets within 11.2" of pointings 1' apart (paper type 9): one small hull per
    pointing, nothing placed in the empty sky between them."""
    rng = np.random.default_rng(4)
    arcsec = ARCMIN / 60
    offsets = np.array([[0, 0], [70, 10], [-40, 80], [90, -90]]) * arcsec
    ra, dec, where = [], [], []
    for i, (ox, oy) in enumerate(offsets):
        r = 11.2 * arcsec * np.sqrt(rng.uniform(size=6))
        phi = rng.uniform(0, 2 * np.pi, 6)
        a, d = _unproject(ox + r * np.sin(phi), oy + r * np.cos(phi), *CENTER)
        ra.append(a)
        dec.append(d)
        where.append(np.full(6, i))
    ra, dec = np.concatenate(ra), np.concatenate(dec)
    reg = hull_region(ra, dec, min_margin=2 * arcsec)
    assert "4 groups" in reg.description
    pr, pd = _draw(reg, CENTER, 5 * ARCMIN, n=2000)
    l, m = _project(pr, pd, *CENTER)
    dist = np.hypot(l[:, None] - offsets[None, :, 0], m[:, None] - offsets[None, :, 1]).min(1)
    margin = float(reg.description.split("grown by ")[1].split(" arcsec")[0])
    assert dist.max() <= (11.2 + margin) * arcsec * 1.01


def test_polygon_file_and_beam(tmp_path):
    from astropy.table import Table

    ds, _, _ = noise_field(0, n_ant=6, n_time=4, extent_m=20e3)
    ra, dec = _box(CENTER, 12.0, 40, seed=5)
    pos = (np.degrees(ra), np.degrees(dec))
    # a polygon smaller than the catalog's box: an L-shaped survey area (non-convex)
    lv = np.array([-6, 6, 6, 0, 0, -6]) * ARCMIN
    mv = np.array([-6, -6, 0, 0, 6, 6]) * ARCMIN
    vra, vdec = _unproject(lv, mv, *CENTER)
    poly = tmp_path / "area.ecsv"
    Table({"ra": np.degrees(vra), "dec": np.degrees(vdec)}).write(poly)
    res = estimate_noise(ds, pos, method="random", realizations=20, region=str(poly),
                         min_separation_arcsec=5.0, weighting="none")
    assert "polygon area.ecsv" in res.extra["region"]
    area = float(res.extra["region"].split("; ")[-1].split(" arcmin")[0])
    assert area == pytest.approx(108.0, rel=0.03)
    l, m = _project(*np.radians(res.positions_deg.reshape(-1, 2)).T, *CENTER)
    tol = 1e-3 * ARCMIN
    assert np.all((np.abs(l) <= 6 * ARCMIN + tol) & (np.abs(m) <= 6 * ARCMIN + tol))
    assert not np.any((l > tol) & (m > tol))  # the cut-out quadrant stays empty
    # beam: the whole beam out to the cutoff radius (highest channel)
    res = estimate_noise(ds, pos, method="random", realizations=20, region="beam",
                         min_separation_arcsec=5.0, weighting="none")
    r_cut = float(standard_beam("VLA", 25.0).radius_at(0.1, 1.45e9))
    area = float(res.extra["region"].split("; ")[-1].split(" arcmin")[0])
    assert area == pytest.approx(2 * np.pi * (1 - np.cos(r_cut)) / ARCMIN**2, rel=0.03)
    # --field-radius still limits the disc of the pointing (with any region)
    for reg in ("beam", "hull"):
        res = estimate_noise(ds, pos, method="random", realizations=5, region=reg,
                             field_radius_arcsec=300.0, min_separation_arcsec=5.0)
        pr, pd = np.radians(res.positions_deg.reshape(-1, 2)).T
        sep = np.arccos(np.clip(np.sin(pd) * np.sin(CENTER[1]) + np.cos(pd) * np.cos(CENTER[1])
                                * np.cos(pr - CENTER[0]), -1, 1))
        assert sep.max() <= 300.0 / 3600 * np.pi / 180 * (1 + 1e-9)
    # a polygon nowhere near the pointing: a clear error naming the option
    far = tmp_path / "far.csv"
    Table({"ra": np.degrees(vra) + 20, "dec": np.degrees(vdec)}).write(far, format="ascii.csv")
    with pytest.raises(XstackError, match="change region="):
        estimate_noise(ds, pos, method="random", realizations=3, region=str(far))
    with pytest.raises(XstackError, match="not hull, beam"):
        estimate_noise(ds, pos, method="random", realizations=3, region="nowhere.csv")


def test_fits_mask_in_galactic_coordinates(tmp_path):
    """A mask with a galactic CAR WCS: inside = finite and nonzero; positions respect it."""
    from astropy import units as u
    from astropy.coordinates import SkyCoord
    from astropy.io import fits
    from astropy.wcs import WCS

    ds, _, _ = noise_field(0, n_ant=6, n_time=4, extent_m=20e3)
    c = SkyCoord(ra=CENTER[0] * u.rad, dec=CENTER[1] * u.rad).galactic
    w = WCS(naxis=2)
    w.wcs.ctype = ["GLON-CAR", "GLAT-CAR"]
    # reference latitude 0: pixel rows are exactly lines of constant galactic latitude
    w.wcs.crval = [c.l.deg, 0.0]
    w.wcs.crpix = [51, 51 - c.b.deg * 120]
    w.wcs.cdelt = [-0.5 / 60, 0.5 / 60]
    img = np.zeros((100, 100), np.float32)
    img[55:, :] = 1.0            # galactic latitude above b0 + ~2'
    img[80:, :] = np.nan          # NaN is outside
    hdr = w.to_header()
    mask = tmp_path / "mask.fits"
    fits.PrimaryHDU(img, header=hdr).writeto(mask)
    ra, dec = _box(CENTER, 12.0, 40, seed=5)
    res = estimate_noise(ds, (np.degrees(ra), np.degrees(dec)), method="random",
                         realizations=20, region=str(mask), min_separation_arcsec=5.0)
    assert "FITS mask mask.fits" in res.extra["region"]
    p = SkyCoord(ra=res.positions_deg[..., 0].ravel() * u.deg,
                 dec=res.positions_deg[..., 1].ravel() * u.deg).galactic
    db = (p.b.deg - c.b.deg) * 60  # arcmin; pixel rows 55..79 = (4.5 .. 29.5) * 0.5'
    assert db.min() >= 4.5 * 0.5 - 0.01 and db.max() <= 29.5 * 0.5 + 0.01


def test_warnings_for_an_ill_defined_footprint():
    ds, _, _ = noise_field(0, n_ant=6, n_time=4, extent_m=20e3)
    ra, dec = _box(CENTER, 8.0, 5, seed=1)
    with pytest.warns(UserWarning, match="only 5 targets.*region=.beam."):
        estimate_noise(ds, (np.degrees(ra), np.degrees(dec)), method="random", realizations=3)
    # collinear targets: a hull of no area
    t = np.linspace(-8, 8, 20) * ARCMIN
    ra, dec = _unproject(t, 0.3 * t, *CENTER)
    with pytest.warns(UserWarning, match="collinear.*region=.beam."):
        reg = hull_region(ra, dec)
    # the footprint is then the band of the margin around the line: positions stay on it
    pr, pd = _draw(reg, CENTER, 30 * ARCMIN, n=500)
    l, m = _project(pr, pd, *CENTER)
    margin = float(reg.description.split("grown by ")[1].split(" arcsec")[0]) / 60 * ARCMIN
    assert np.max(np.abs(m - 0.3 * l) / np.hypot(1, 0.3)) <= margin * 1.01
    # enough targets spread over an area: no warning; "beam" never warns
    ra, dec = _box(CENTER, 8.0, 50, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        hull_region(ra, dec)
        make_region("beam", ra[:2], dec[:2])


def test_image_domain_random_positions_stay_in_the_footprint(tmp_path):
    """The image-domain estimate draws from the same hull: targets in the left half of an
    image (no primary beam) get random positions in the left half only."""
    from astropy.io import fits
    from astropy.wcs import WCS

    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---SIN", "DEC--SIN"]
    w.wcs.cdelt = [-1 / 3600, 1 / 3600]
    w.wcs.crpix = [101, 101]
    w.wcs.crval = [57.3, -30.0]
    h = w.to_header()
    h["BMAJ"] = h["BMIN"] = 3 / 3600
    h["BPA"] = 0.0
    img = np.random.default_rng(0).normal(size=(200, 200))
    path = tmp_path / "img.fits"
    fits.PrimaryHDU(img, header=h).writeto(path)
    rng = np.random.default_rng(3)
    x, y = rng.uniform(10, 90, 60), rng.uniform(10, 190, 60)  # left half: x < 100
    ra, dec = w.pixel_to_world_values(x, y)
    res = estimate_noise(path, (ra, dec), method="random", realizations=10, domain="image",
                         primary_beam="none", field_radius_arcsec=200.0,
                         min_separation_arcsec=2.0)
    px, py = w.world_to_pixel_values(res.positions_deg[..., 0].ravel(),
                                     res.positions_deg[..., 1].ravel())
    # the hull is grown by half the spacing (~6 px here): nothing near the right edge
    assert px.max() < 100 and px.min() > 0
    assert py.min() < 40 and py.max() > 160  # and it is filled top to bottom


def test_no_primary_beam_needs_no_field_radius_with_a_region():
    """primary_beam='none' has no edge: the footprint alone bounds the random positions."""
    ds, _, _ = noise_field(0, n_ant=6, n_time=4, extent_m=20e3)
    ra, dec = _box(CENTER, 5.0, 30, seed=2)
    res = estimate_noise(ds, (np.degrees(ra), np.degrees(dec)), method="random",
                         realizations=5, primary_beam="none", min_separation_arcsec=5.0)
    l, m = _project(*np.radians(res.positions_deg.reshape(-1, 2)).T, *CENTER)
    assert np.abs(l).max() < 6 * ARCMIN and np.abs(m).max() < 6 * ARCMIN
    with pytest.raises(XstackError, match="field_radius"):
        estimate_noise(ds, (np.degrees(ra), np.degrees(dec)), method="random",
                       realizations=5, primary_beam="none", region="beam")
