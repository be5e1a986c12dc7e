"""Numerically hard cases of every stage but uv-stacking (that is tests/test_uvstack_hard.py).

Poles, RA wrap-around, fully flagged / zero-weight / NaN inputs and huge phase arguments,
each checked against an independent truth: astropy coordinates (SkyCoord offsets and
separations, the FITS WCS), explicit formulas and numpy long double.
"""

from __future__ import annotations

import math

import astropy.units as u
import numpy as np
import pytest
from astropy.coordinates import SkyCoord
from astropy.io import fits
from astropy.wcs import WCS
from scipy import stats

from xstack.errors import XstackError
from xstack.sim.arrays import enu_to_itrf, packaged_array
from xstack.sim.simulate import simulate_partitions

C = 299_792_458.0
ARCSEC = math.pi / 180.0 / 3600.0


# ----------------------------------------------------------------------------- helpers

def _scene(center_deg, populations, *, config="vla.d", antennas=range(6), freq=1.4e9,
           channels=3, bandwidth=None, w_term=True, n_int=3, hour_angle=(-1.0, 1.0), **kw):
    base = {
        "name": "hard",
        "array": {"config": config, "antennas": list(antennas)},
        "observation": {"hour_angle": list(hour_angle), "integration": 60.0,
                        "time_per_pointing": 60.0 * n_int},
        "spectral": {"center": freq, "bandwidth": bandwidth or freq * 0.02,
                     "channels": channels, "polarizations": ["RR", "LL"]},
        "pointings": {"mode": "single", "center": list(center_deg)},
        "effects": {"w_term": w_term},
        "visibility_dtype": "complex128",
        "populations": populations,
    }
    base.update(kw)
    return base


def _listed(name, ra, dec, flux):
    return {"name": name, "count": len(ra), "flux": {"kind": "fixed", "value": flux},
            "positions": {"kind": "list", "ra": list(ra), "dec": list(dec)}}


def _offsets(ra_deg, dec_deg, center_deg):
    """Direction cosines (l, m, n) of positions about a center, from astropy's offset frame.

    In SkyOffsetFrame the center is (lon, lat) = (0, 0), lon grows to the east and lat to
    the north, so the unit vector (cos lat cos lon, cos lat sin lon, sin lat) is (n, l, m).
    """
    center = SkyCoord(*center_deg, unit="deg", frame="icrs")
    off = SkyCoord(ra_deg, dec_deg, unit="deg", frame="icrs").transform_to(
        center.skyoffset_frame())
    lon, lat = off.lon.to_value(u.rad), off.lat.to_value(u.rad)
    return (np.cos(lat) * np.sin(lon), np.sin(lat), np.cos(lat) * np.cos(lon))


def _direct_eq1(uvw, freq, l, m, n, flux):
    """Equation 1 for one point source, straight from its definition (complex128)."""
    lam = C / np.asarray(freq, float)
    # n - 1 without cancellation: the w-term needs it to full precision
    nm1 = -(l * l + m * m) / (1.0 + n)
    phase = 2 * np.pi * (uvw[..., 0, None] * l + uvw[..., 1, None] * m
                         + uvw[..., 2, None] * nm1) / lam
    return flux * np.exp(1j * phase)


def _only(parts):
    (ds,) = parts.values()
    return ds.compute()


# ------------------------------------------------------------- 1. simulator: poles, RA wrap

@pytest.mark.parametrize("dec0", [89.9, -89.9, 90.0])
def test_simulator_near_the_poles(dec0):
    """A disc that contains the pole, a box beside it, and a source across the pole."""
    # the pole must be above the horizon: the VLA for the north, ALMA for the south (at
    # 1.4 GHz too, so that its primary beam holds the same 0.1 deg offsets)
    config = "vla.d" if dec0 > 0 else "alma.cycle1.6"
    center = (123.0, dec0)
    radius, box = 500.0, [300.0, 300.0]  # arcsec; the disc contains the pole (360" away)
    # the source: 0.105 deg from the center, across the pole (RA + 180 deg); 0.1 deg from a
    # center on the pole
    src = (303.0, math.copysign(89.995, dec0) if abs(dec0) < 90 else 89.9)
    pops = [
        _listed("src", [src[0]], [src[1]], 2e-3),
        {"name": "disc", "count": 400, "flux": {"kind": "fixed", "value": 0.0},
         "positions": {"kind": "disc", "radius_arcsec": radius}},
        {"name": "box", "count": 400, "flux": {"kind": "fixed", "value": 0.0},
         "positions": {"kind": "box", "size_arcsec": box}},
    ]
    parts, cats = simulate_partitions(_scene(center, pops, config=config), seed=3)
    ds = _only(parts)

    l, m, _ = _offsets(cats["disc"]["ra"], cats["disc"]["dec"], center)
    assert np.all(np.hypot(l, m) <= radius * ARCSEC * (1 + 1e-9))
    sep = SkyCoord(*center, unit="deg").separation(
        SkyCoord(cats["disc"]["ra"], cats["disc"]["dec"], unit="deg")).arcsec
    assert np.all(sep <= radius * (1 + 1e-6))
    # the disc really straddles the pole: its positions span every RA
    assert np.ptp(np.asarray(cats["disc"]["ra"])) > 300
    l, m, _ = _offsets(cats["box"]["ra"], cats["box"]["dec"], center)
    assert np.all(np.abs(l) <= box[0] / 2 * ARCSEC * (1 + 1e-9))
    assert np.all(np.abs(m) <= box[1] / 2 * ARCSEC * (1 + 1e-9))
    # uniform in the box: both halves about equally full (not bunched by the RA/Dec grid)
    assert 150 < np.sum(l > 0) < 250 and 150 < np.sum(m > 0) < 250

    # the catalog keeps the source where it was asked for
    assert SkyCoord(*src, unit="deg").separation(SkyCoord(
        cats["src"]["ra"][0], cats["src"]["dec"][0], unit="deg")).arcsec < 1e-9
    l, m, n = _offsets(src[0], src[1], center)
    expect = _direct_eq1(ds.UVW.values, ds.frequency.values, l, m, n, 2e-3)
    vis = ds.VISIBILITY.values
    np.testing.assert_allclose(vis[..., 0], expect, rtol=0, atol=2e-3 * 1e-9)
    np.testing.assert_allclose(vis[..., 1], expect, rtol=0, atol=2e-3 * 1e-9)
    # not trivially constant: the source is far enough off center to wind the phase
    assert np.ptp(np.angle(expect)) > 1.0


@pytest.mark.parametrize("center_ra", [359.99, 0.01])
def test_simulator_across_ra_zero(center_ra):
    center = (center_ra, -30.0)
    pops = [
        _listed("src", [0.02 if center_ra > 180 else 359.98], [-30.01], 1e-3),
        {"name": "box", "count": 400, "flux": {"kind": "fixed", "value": 0.0},
         "positions": {"kind": "box", "size_arcsec": [300.0, 120.0]}},
        {"name": "disc", "count": 400, "flux": {"kind": "fixed", "value": 0.0},
         "positions": {"kind": "disc", "radius_arcsec": 200.0}},
    ]
    parts, cats = simulate_partitions(_scene(center, pops), seed=5)
    ds = _only(parts)
    for name, half in (("box", (150.0, 60.0)), ("disc", None)):
        ra = np.asarray(cats[name]["ra"])
        assert np.all((ra >= 0) & (ra < 360))
        # both sides of RA 0 are populated
        assert np.any(ra < 1) and np.any(ra > 359)
        l, m, _ = _offsets(ra, cats[name]["dec"], center)
        if half:
            assert np.all(np.abs(l) <= half[0] * ARCSEC * (1 + 1e-9))
            assert np.all(np.abs(m) <= half[1] * ARCSEC * (1 + 1e-9))
        else:
            assert np.all(np.hypot(l, m) <= 200 * ARCSEC * (1 + 1e-9))
    # the box is centered on the pointing, not shifted by 360 deg or mirrored
    l, m, _ = _offsets(cats["box"]["ra"], cats["box"]["dec"], center)
    assert abs(np.mean(l)) < 10 * ARCSEC and abs(np.mean(m)) < 5 * ARCSEC

    src = (float(cats["src"]["ra"][0]), float(cats["src"]["dec"][0]))
    l, m, n = _offsets(*src, center)
    expect = _direct_eq1(ds.UVW.values, ds.frequency.values, l, m, n, 1e-3)
    np.testing.assert_allclose(ds.VISIBILITY.values[..., 0], expect, rtol=0, atol=1e-12)
    assert np.ptp(np.angle(expect)) > 1.0


# ------------------------------------------------------- 6. simulator: huge phase arguments

def _long_baseline_scene(src, center, channels):
    site = packaged_array("alma.cycle1.6").site
    # a 16 km east-west baseline and a 12 km north-south one, ALMA-like (at its site)
    enu = np.array([[0.0, 0.0, 0.0], [16_000.0, 0.0, 3.0], [-700.0, 12_000.0, -5.0]])
    pos = enu_to_itrf(enu, site).tolist()
    scene = _scene(center, [_listed("src", [src[0]], [src[1]], 1.0)], channels=channels,
                   freq=900e9, bandwidth=7.5e9, n_int=4)
    scene["array"] = {"positions": pos, "diameters": [12.0] * 3, "telescope": "ALMA",
                      "names": ["A", "B", "C"]}
    # 1' is far outside a 900 GHz primary beam: simulate the source without one
    scene["effects"] = {"w_term": True, "primary_beam": "none", "pb_cutoff": 0.0}
    return scene


@pytest.mark.parametrize("channels", [3, 70])  # 70: past two resyncs of the channel recurrence
def test_simulator_huge_phases_match_long_double(channels):
    center = (201.0, -23.0)
    src = (201.0 + 1.0 / 60 / math.cos(math.radians(23.0)) * 0.6, -23.0 + 0.8 / 60)  # 1' off
    parts, cats = simulate_partitions(_long_baseline_scene(src, center, channels))
    ds = _only(parts)
    assert SkyCoord(*center, unit="deg").separation(
        SkyCoord(*src, unit="deg")).arcmin == pytest.approx(1.0, rel=1e-3)

    ld = np.longdouble
    if np.finfo(ld).eps >= np.finfo(np.float64).eps:
        pytest.skip("no extended-precision long double on this platform")
    pi = np.arccos(ld(-1))
    to_rad = pi / ld(180)
    ra, dec = ld(float(cats["src"]["ra"][0])) * to_rad, ld(float(cats["src"]["dec"][0])) * to_rad
    ra0, dec0 = ld(center[0]) * to_rad, ld(center[1]) * to_rad
    l = np.cos(dec) * np.sin(ra - ra0)
    m = np.sin(dec) * np.cos(dec0) - np.cos(dec) * np.sin(dec0) * np.cos(ra - ra0)
    n = np.sqrt(1 - l * l - m * m)
    uvw = ds.UVW.values.astype(ld)
    freq = ds.frequency.values.astype(ld)
    turns = (uvw[..., 0, None] * l + uvw[..., 1, None] * m + uvw[..., 2, None] * (n - 1)) \
        * freq / ld(C)
    assert np.abs(turns).max() > 5e3  # phases of more than 3e4 radians
    reduced = (2 * pi * (turns - np.round(turns))).astype(np.float64)  # exact in [-pi, pi]
    vis = ds.VISIBILITY.values[..., 0]
    err = np.angle(vis * np.exp(-1j * reduced))
    assert np.abs(err).max() < 1e-6
    np.testing.assert_allclose(np.abs(vis), 1.0, rtol=1e-12)


# ------------------------------------------------------- 2. imaging at the pole / across RA 0

def _sin_wcs(center_deg, n, cell_arcsec):
    """The FITS SIN grid xstack images on, built by astropy from its definition."""
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---SIN", "DEC--SIN"]
    w.wcs.crval = list(center_deg)
    w.wcs.crpix = [n // 2 + 1, n // 2 + 1]
    w.wcs.cdelt = [-cell_arcsec / 3600, cell_arcsec / 3600]
    # l, m of docs/conventions.md at any center, the pole included (FITS's default LONPOLE
    # would turn the grid by 180 deg at dec0 = +90 exactly)
    w.wcs.lonpole = 180.0
    return w


def _peak(image):
    """(x, y) of the maximum, refined by a parabola through its neighbours on each axis."""
    iy, ix = np.unravel_index(np.argmax(image), image.shape)

    def vertex(a, b, c):
        return 0.5 * (a - c) / (a - 2 * b + c)

    return (ix + vertex(*image[iy, ix - 1:ix + 2]), iy + vertex(*image[iy - 1:iy + 2, ix]),
            ix, iy)


@pytest.mark.parametrize("center, pixel, src", [
    # 0.1 deg from the pole; the source 450" north: across the pole, on a pixel center
    ((123.0, 89.9), (7, 45), None),
    # centered exactly on the pole
    ((45.0, 90.0), (-12, 30), None),
    # the image straddles RA 0; the source at RA 359.99, on no particular pixel
    ((0.001, 10.0), None, (359.99, 10.02)),
])
def test_imaging_peak_at_the_true_position(center, pixel, src):
    from xstack.imaging.image import make_image

    n, cell = 128, 10.0
    truth = _sin_wcs(center, n, cell)
    if pixel is not None:  # pixel offsets (x west, y north) from the center pixel
        ra, dec = truth.pixel_to_world_values(n // 2 - pixel[0], n // 2 + pixel[1])
        src = (float(ra), float(dec))
    scene = _scene(center, [_listed("src", [src[0]], [src[1]], 1e-3)], antennas=range(0, 27, 2),
                   observation={
                       "hour_angle": [-3.0, 3.0], "integration": 1200.0,
                       "time_per_pointing": 9600.0})
    parts, _ = simulate_partitions(scene)
    res = make_image(parts, size=n, cell_arcsec=cell)
    x, y, ix, iy = _peak(res.image)
    want_x, want_y = truth.world_to_pixel_values(*src)
    if pixel is not None:
        assert (ix, iy) == (n // 2 - pixel[0], n // 2 + pixel[1])
    assert abs(x - want_x) < 0.15 and abs(y - want_y) < 0.15
    ra, dec = res.wcs.pixel_to_world_values(x, y)
    sep = SkyCoord(*src, unit="deg").separation(SkyCoord(ra, dec, unit="deg")).arcsec
    assert sep < 0.15 * cell
    assert res.image.max() == pytest.approx(1e-3, rel=0.02)


# ------------------------------------------- 3. image-stacking across RA 0 and near the pole

IMSTACK_BEAM = (3.2, 1.6, 30.0)  # arcsec, arcsec, deg


@pytest.mark.parametrize("ra0, dec0", [(0.0, -30.0), (200.0, 89.9), (123.0, 89.995)])
def test_imstack_across_ra_zero_and_near_the_pole(tmp_path, ra0, dec0):
    from _imstack_helpers import make_field

    from xstack.imstack import stack_images

    rng = np.random.default_rng(21)
    path, ra, dec, px, py = make_field(tmp_path, rng, 0.5, beam=IMSTACK_BEAM, n_side=6,
                                       noise=0.0, ra0=ra0, dec0=dec0)
    if ra0 == 0.0:
        assert (ra > 359).any() and (ra < 1).any()  # positions on both sides of RA 0
        ra = np.where(ra > 180, ra - 360.0, ra)  # and given as negative RAs too
    if dec0 > 89.99:  # the image holds the pole: the positions surround it
        assert np.ptp(ra) > 300
    res = stack_images(path, np.c_[ra, dec], stamp_size=32, weighting="none", subpixel="fourier")
    assert res.n_positions == 36
    assert res.flux_jy == pytest.approx(1.0, rel=0.01)
    # every stamp sits on its own source (a wrong RA branch would land off the image or on
    # another source)
    c = 16
    np.testing.assert_allclose(res.cube.values[:, c, c], 1.0, rtol=0.01)
    # sub-pixel offsets are those of the injected sources (astropy's pixel positions)
    np.testing.assert_allclose(res.cube.frac_x.values, px - np.floor(px + 0.5), atol=1e-6)
    np.testing.assert_allclose(res.cube.frac_y.values, py - np.floor(py + 0.5), atol=1e-6)


def test_imstack_blanked_stamps(tmp_path):
    """An all-NaN stamp is left out; a stack whose center nothing covers is an error."""
    from _imstack_helpers import make_field

    from xstack.imstack import stack_images

    rng = np.random.default_rng(22)
    path, ra, dec, px, py = make_field(tmp_path, rng, 0.5, beam=IMSTACK_BEAM, n_side=4,
                                       noise=1e-3, ra0=0.0, dec0=-30.0)
    with fits.open(path) as h:
        data, hdr = h[0].data.astype(np.float64), h[0].header
    x0, y0 = int(round(px[0])), int(round(py[0]))
    data[max(y0 - 16, 0):y0 + 16, max(x0 - 16, 0):x0 + 16] = np.nan  # its whole stamp
    blank = tmp_path / "blank.fits"
    fits.PrimaryHDU(data, header=hdr).writeto(blank)
    pos = np.c_[ra, dec]
    with pytest.raises(XstackError, match="1 of 16 positions"):
        stack_images(blank, pos, stamp_size=32)
    for weighting in ("sigma2", "none"):
        res = stack_images(blank, pos, stamp_size=32, weighting=weighting, subpixel="fourier",
                      skip_outside=True)
        assert res.skipped_rows == [1] and res.n_positions == 15
        assert np.isfinite(res.flux_jy) and np.isfinite(res.flux_err_jy)
        assert res.flux_jy == pytest.approx(1.0, abs=0.01)
        assert np.isfinite(res.stacked.values).all()
    # every stamp blanked: a clear error, not a NaN stack
    allnan = tmp_path / "allnan.fits"
    fits.PrimaryHDU(np.full_like(data, np.nan), header=hdr).writeto(allnan)
    with pytest.raises(XstackError, match="no position"):
        stack_images(allnan, pos, stamp_size=32, skip_outside=True)
    with pytest.raises(XstackError, match="outside every image"):
        stack_images(allnan, pos, stamp_size=32)


@pytest.mark.parametrize("subpixel", ["fourier", "spline"])
def test_imstack_center_lost_to_blanking_is_an_error(tmp_path, subpixel):
    """The nearest pixel is finite but a blanked neighbour makes the shifted center NaN."""
    from _imstack_helpers import make_field

    from xstack.imstack import stack_images

    rng = np.random.default_rng(23)
    path, ra, dec, px, py = make_field(tmp_path, rng, 0.5, beam=IMSTACK_BEAM, n_side=2,
                                       noise=1e-3)
    with fits.open(path) as h:
        data, hdr = h[0].data.astype(np.float64), h[0].header
    for x, y in zip(px, py):  # one blanked pixel beside every source
        data[int(round(y)), int(round(x)) + 2] = np.nan
    holes = tmp_path / "holes.fits"
    fits.PrimaryHDU(data, header=hdr).writeto(holes)
    with pytest.raises(XstackError, match="stacking position"):
        stack_images(holes, np.c_[ra, dec], stamp_size=32, weighting="none", subpixel=subpixel)
    # nearest-pixel alignment keeps every center and stacks fine
    res = stack_images(holes, np.c_[ra, dec], stamp_size=32, weighting="none")
    assert np.isfinite(res.flux_jy)


# --------------------------------------------------- 4. noise: random positions on the sphere

def _sep_deg(ra1, dec1, ra2, dec2):
    return SkyCoord(ra1, dec1, unit="deg").separation(SkyCoord(ra2, dec2, unit="deg")).deg


@pytest.mark.parametrize("center", [(40.0, 89.9), (0.0, -89.9), (359.999, 5.0)])
def test_random_positions_uniform_in_solid_angle(center):
    """1e5 placements in a disc (containing the pole for |dec| = 89.9): the radial
    distribution follows sin r dr, the position angle is uniform, none is outside."""
    from xstack.noise.positions import random_positions

    radius = np.radians(0.3)
    c = np.radians([center])
    ra, dec = random_positions(1000, 100, c, np.array([radius]), avoid_ra=np.zeros(0),
                               avoid_dec=np.zeros(0), min_separation=0.0,
                               rng=np.random.default_rng(1))
    ra, dec = np.degrees(ra).ravel(), np.degrees(dec).ravel()
    assert ra.size == 100_000 and np.all((ra >= 0) & (ra < 360))
    sky = SkyCoord(ra, dec, unit="deg")
    cen = SkyCoord(*center, unit="deg")
    r = cen.separation(sky).rad
    assert r.max() <= radius * (1 + 1e-9)
    # P(< r) = (1 - cos r) / (1 - cos R): uniform per unit solid angle
    ks = stats.kstest(r, lambda x: (1 - np.cos(x)) / (1 - np.cos(radius)))
    assert ks.pvalue > 1e-3
    pa = cen.position_angle(sky).rad
    assert stats.kstest(pa / (2 * np.pi), "uniform").pvalue > 1e-3
    # the pole itself is inside the disc: the density there is not special
    if abs(center[1]) > 89:
        near = _sep_deg(ra, dec, 0.0, math.copysign(90.0, center[1])) < 0.05
        expect = 100_000 * (1 - np.cos(np.radians(0.05))) / (1 - np.cos(radius))
        assert abs(near.sum() - expect) < 5 * np.sqrt(expect)


def test_random_positions_uniform_on_a_union_across_ra_zero():
    """Two overlapping discs either side of RA 0: the lens they share is not counted twice."""
    from xstack.noise.positions import random_positions

    R, d = 0.1, 0.1  # deg: radius and center distance
    centers = np.radians([[360.0 - d / 2, 0.0], [d / 2, 0.0]])
    ra, dec = random_positions(2000, 50, centers, np.radians([R, R]), avoid_ra=np.zeros(0),
                               avoid_dec=np.zeros(0), min_separation=0.0,
                               rng=np.random.default_rng(2))
    ra, dec = np.degrees(ra).ravel(), np.degrees(dec).ravel()
    s1 = _sep_deg(ra, dec, 360.0 - d / 2, 0.0)
    s2 = _sep_deg(ra, dec, d / 2, 0.0)
    assert np.all(np.minimum(s1, s2) <= R * (1 + 1e-9))
    # areas of the lens and of the union (plane geometry; the discs are tiny)
    lens = 2 * R**2 * np.arccos(d / (2 * R)) - d / 2 * np.sqrt(4 * R**2 - d**2)
    frac = lens / (2 * np.pi * R**2 - lens)
    n = ra.size
    got = np.sum((s1 <= R) & (s2 <= R))
    assert abs(got - n * frac) < 5 * np.sqrt(n * frac * (1 - frac))


def _noise_data(center, targets, *, sigma=1e-3):
    scene = _scene(center, [_listed("t", *targets, 0.0)], antennas=range(0, 27, 3),
                   freq=1.4e9, bandwidth=0.5e9, effects={"noise": {"sigma": sigma}})
    return simulate_partitions(scene, seed=11)[0]


@pytest.mark.parametrize("center", [(10.0, 89.9), (0.001, -20.0)])
@pytest.mark.parametrize("method", ["random", "mc"])
def test_noise_random_positions_inside_the_field_and_apart(center, method):
    from xstack.beams import standard_beam
    from xstack.noise.estimate import estimate_noise

    rng = np.random.default_rng(4)
    # targets within 0.2 deg of the center: across the pole, and on both sides of RA 0
    ra_t, dec_t = [], []
    cen = SkyCoord(*center, unit="deg")
    for pa, sep in zip(rng.uniform(0, 360, 12), 0.2 * np.sqrt(rng.uniform(0.05, 1, 12))):
        p = cen.directional_offset_by(pa * u.deg, sep * u.deg)
        ra_t.append(p.ra.deg)
        dec_t.append(p.dec.deg)
    ra_t, dec_t = np.array(ra_t), np.array(dec_t)
    data = _noise_data(center, (ra_t, dec_t))
    min_sep = 60.0
    res = estimate_noise(data, (ra_t, dec_t), method=method, realizations=30, flux=1e-3,
                         min_separation_arcsec=min_sep, seed=3)
    assert np.isfinite(res.noise_jy) and res.noise_jy > 0
    pos = res.positions_deg  # (R, n, 2)
    assert pos.shape == (30, 12, 2)
    r = _sep_deg(pos[..., 0], pos[..., 1], *center)
    # default region: the targets' footprint (hull grown by its margin), inside the beam
    margin = float(res.extra["region"].split("grown by ")[1].split(" arcsec")[0]) / 3600
    assert r.max() <= _sep_deg(ra_t, dec_t, *center).max() + 1.01 * margin
    beam = standard_beam("VLA", 25.0)
    freq = next(iter(data.values())).frequency.values
    assert np.all(beam(np.radians(r)[..., None], freq) >= beam.cutoff)
    for k in range(pos.shape[0]):
        sky = SkyCoord(pos[k, :, 0], pos[k, :, 1], unit="deg")
        _, d2d, _ = sky.match_to_catalog_sky(sky, nthneighbor=2)
        assert d2d.arcsec.min() >= min_sep * (1 - 1e-9)
        _, d2d, _ = sky.match_to_catalog_sky(SkyCoord(ra_t, dec_t, unit="deg"))
        assert d2d.arcsec.min() >= min_sep * (1 - 1e-9)
    if abs(center[1]) < 80:  # random positions fall on both sides of RA 0
        assert np.any(pos[..., 0] < 1) and np.any(pos[..., 0] > 359)


def _edge_targets(center, beam, fmax):
    """Targets out to (just inside) the cutoff radius of the highest channel."""
    r_cut = np.degrees(beam.radius_at(beam.cutoff, fmax))
    cen = SkyCoord(*center, unit="deg")
    ts = [cen.directional_offset_by(pa * u.deg, r_cut * 0.999 * u.deg) for pa in (0, 120, 240)]
    ts += [cen.directional_offset_by(pa * u.deg, 0.5 * r_cut * u.deg) for pa in (60, 180)]
    return np.array([t.ra.deg for t in ts]), np.array([t.dec.deg for t in ts]), r_cut


@pytest.mark.parametrize("default_field", [False, True])
def test_noise_random_positions_stay_inside_the_cutoff_at_every_channel(default_field):
    """Targets out to the cutoff radius of the highest channel: every random position must be
    stacked (A >= cutoff in every channel), as the targets are."""
    from xstack.beams import standard_beam
    from xstack.noise.estimate import estimate_noise

    center = (10.0, 89.9)
    beam = standard_beam("VLA", 25.0)
    data = _noise_data(center, ([10.0], [89.9]))
    freq = next(iter(data.values())).frequency.values
    ra_t, dec_t, r_cut = _edge_targets(center, beam, freq.max())
    assert np.all(beam(np.radians(_sep_deg(ra_t, dec_t, *center))[:, None], freq) >= 0.1)
    res = estimate_noise(data, (ra_t, dec_t), method="random", realizations=200,
                         min_separation_arcsec=1.0, seed=5,
                         field_radius_arcsec=None if default_field else 3600 * r_cut)
    r = np.radians(_sep_deg(res.positions_deg[..., 0], res.positions_deg[..., 1], *center))
    assert np.all(beam(r[..., None], freq) >= beam.cutoff)


# ------------------------------------------ 5. fully flagged, zero-weight and NaN inputs

def _small_partition(center=(150.0, 30.0), offset_deg=0.01, spw=0):
    src = (center[0], center[1] + offset_deg)
    scene = _scene(center, [_listed("s", [src[0]], [src[1]], 1e-3)], antennas=range(0, 27, 3),
                   n_int=4, effects={"w_term": True, "noise": {"sigma": 1e-3}},
                   spectral={"center": 1.4e9 + 0.1e9 * spw, "bandwidth": 0.05e9,
                             "channels": 2, "polarizations": ["RR", "RL", "LR", "LL"]})
    return _only(simulate_partitions(scene, seed=7 + spw)[0])


def _spoil(ds, how, where=None):
    """A copy of ``ds`` with the Stokes-I samples selected by ``where`` (all if None) made
    unusable: flagged, zero weight, NaN weight, NaN visibility, or a NaN uvw row."""
    out = ds.copy(deep=True)
    sel = np.ones(ds.VISIBILITY.shape, bool) if where is None else where
    if how == "flag":
        out["FLAG"].values[sel] = True
    elif how == "zero_weight":
        out["WEIGHT"].values[sel] = 0.0
    elif how == "nan_weight":
        out["WEIGHT"].values[sel] = np.nan
    elif how == "nan_vis":
        out["VISIBILITY"].values[sel] = np.nan + 1j * np.nan
    elif how == "nan_uvw":
        out["UVW"].values[sel.any(axis=(2, 3))] = np.nan
    return out


SPOILS = ["flag", "zero_weight", "nan_weight", "nan_vis", "nan_uvw"]


@pytest.mark.parametrize("how", SPOILS)
def test_imaging_unusable_partition(how):
    from xstack.imaging.image import make_image

    ds = _small_partition()
    with pytest.raises(XstackError, match="no unflagged parallel-hand visibilities"):
        make_image({"p": _spoil(ds, how)}, size=64, cell_arcsec=5.0)
    # a second spectral window of the same pointing that is entirely unusable adds nothing
    good = make_image({"p": ds}, size=64, cell_arcsec=5.0)
    both = make_image({"a": ds, "b": _spoil(_small_partition(spw=1), how)}, size=64,
                      cell_arcsec=5.0)
    assert np.isfinite(both.image).all() and np.isfinite(both.psf).all()
    np.testing.assert_allclose(both.image, good.image, rtol=0, atol=1e-12)
    # and half of it unusable: the same image as with those samples flagged
    half = np.zeros(ds.VISIBILITY.shape, bool)
    half[::2] = True
    part = make_image({"p": _spoil(ds, how, half)}, size=64, cell_arcsec=5.0)
    flagged = make_image({"p": _spoil(ds, "flag", half if how != "nan_uvw" else
                                      np.broadcast_to(half.any(axis=(2, 3))[..., None, None],
                                                      half.shape))},
                         size=64, cell_arcsec=5.0)
    assert np.isfinite(part.image).all()
    np.testing.assert_allclose(part.image, flagged.image, rtol=0, atol=1e-12)


@pytest.mark.parametrize("how", SPOILS)
def test_fit_unusable_stacked_data(how):
    from xstack.fit import fit_uv

    ds = _small_partition(offset_deg=0.0)  # a stacked data set: the source at the center
    for model in ("point", "gaussian"):
        with pytest.raises(XstackError, match="no usable visibilities"):
            fit_uv(_spoil(ds, how), model=model)
    # everything inside the uv range unusable, the rest fine: no fit, a clear message
    q = np.hypot(ds.UVW.values[..., 0], ds.UVW.values[..., 1])
    lo, hi = np.percentile(q, [30, 70])
    inside = ((q >= lo) & (q <= hi))[..., None, None] & np.ones(ds.VISIBILITY.shape, bool)
    spoilt = _spoil(ds, how, inside)
    with pytest.raises(XstackError, match="no visibilities left in the uv range"):
        fit_uv(spoilt, model="point", uvmin=f"{lo}m", uvmax=f"{hi}m")
    # outside the range the unusable samples are simply not there
    res = fit_uv(spoilt, model="point")
    ref = fit_uv(_spoil(ds, "flag", inside), model="point")
    assert np.isfinite(res.flux_jy) and np.isfinite(res.flux_err_jy)
    assert res.flux_jy == pytest.approx(ref.flux_jy, rel=1e-12)


@pytest.mark.parametrize("method", ["analytic", "random", "mc", "bootstrap"])
@pytest.mark.parametrize("how", ["zero_weight", "flag", "nan_vis"])
def test_noise_all_weights_zero(method, how):
    from xstack.noise.estimate import estimate_noise

    ds = _small_partition()
    ra, dec = np.array([150.0, 150.01]), np.array([30.01, 29.995])
    with pytest.raises(XstackError, match="all data flagged"):
        estimate_noise({"p": _spoil(ds, how)}, (ra, dec), method=method, realizations=5,
                       flux=1e-3, min_separation_arcsec=5.0)
    # a fully unusable second pointing does not poison the first
    res = estimate_noise({"p": ds, "q": _spoil(ds, how)}, (ra, dec), method=method,
                         realizations=5, flux=1e-3, min_separation_arcsec=5.0)
    ref = estimate_noise({"p": ds}, (ra, dec), method=method, realizations=5, flux=1e-3,
                         min_separation_arcsec=5.0)
    assert np.isfinite(res.noise_jy) and np.isfinite(res.target_flux_jy)
    assert res.target_flux_jy == pytest.approx(ref.target_flux_jy, rel=1e-9)


@pytest.mark.parametrize("pointings, src", [
    ([[359.9, 10.0], [0.1, 10.0]], (359.99, 10.02)),      # a mosaic straddling RA 0
    ([[0.0, 89.8], [180.0, 89.8]], (90.0, 89.97)),         # two pointings either side of the pole
])
def test_imaging_mosaic_across_ra_zero_and_the_pole(pointings, src):
    from xstack.imaging.image import make_image, mean_direction

    scene = _scene(pointings[0], [_listed("src", [src[0]], [src[1]], 1e-3)],
                   antennas=range(0, 27, 2), pointings={"mode": "list", "positions": pointings},
                   effects={"w_term": True, "primary_beam": "auto"},
                   observation={"hour_angle": [-3.0, 3.0], "integration": 1200.0,
                                "time_per_pointing": 9600.0})
    parts, _ = simulate_partitions(scene)
    assert len(parts) == 2
    n, cell = 128, 10.0
    res = make_image(parts, size=n, cell_arcsec=cell)
    # the mosaic center is the mean direction, on the right side of RA 0 / of the pole
    center = np.degrees(mean_direction(np.radians(pointings)))
    cen = SkyCoord(*center, unit="deg")
    for p in pointings:
        assert cen.separation(SkyCoord(*p, unit="deg")).deg == pytest.approx(
            0.5 * SkyCoord(*pointings[0], unit="deg").separation(
                SkyCoord(*pointings[1], unit="deg")).deg, rel=1e-9)
    truth = _sin_wcs(center, n, cell)
    img = np.nan_to_num(res.image, nan=-np.inf)
    x, y, _, _ = _peak(img)
    want_x, want_y = truth.world_to_pixel_values(*src)
    assert abs(x - want_x) < 0.15 and abs(y - want_y) < 0.15
    ra, dec = res.wcs.pixel_to_world_values(x, y)
    assert SkyCoord(*src, unit="deg").separation(SkyCoord(ra, dec, unit="deg")).arcsec \
        < 0.15 * cell
    # primary-beam corrected: the true flux
    assert np.nanmax(res.image) == pytest.approx(1e-3, rel=0.03)


def test_image_header_at_the_north_pole_keeps_its_orientation():
    from xstack.imaging.fitsio import celestial_wcs, grid_of, make_header

    h = make_header(64, 64, 10.0, (0.3, math.pi / 2))
    w = celestial_wcs(h)
    # one pixel north (y + 1) is 10" from the pole towards RA = ra0 + 180 deg (m > 0)
    ra, dec = w.pixel_to_world_values(32, 33)
    assert SkyCoord(ra, dec, unit="deg").separation(
        SkyCoord(math.degrees(0.3) + 180.0, 90.0 - 10 / 3600, unit="deg")).arcsec < 1e-6
    assert grid_of(h)["cell_arcsec"] == pytest.approx(10.0)
    # a third-party header without LONPOLE at CRVAL2 = 90 is a grid turned by 180 deg
    del h["LONPOLE"]
    with pytest.raises(XstackError, match="LONPOLE"):
        grid_of(h)
