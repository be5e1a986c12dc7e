"""Image-domain line stacking (issue 15): cubes made here with astropy.wcs and numpy."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS
from scipy.special import erf

from xstack.errors import OptionError, XstackError
from xstack.imstack.line import stack_line_cube
from xstack.spectral import SPEED_OF_LIGHT_KMS as C_KMS

REST = 1420.405751786e6
F0, DF = 1.290e9, 0.05e6  # first channel centre, channel width (Hz): ~11.6 km/s channels
CELL = 2.0 / 3600.0  # deg
BEAM_FWHM_PIX = 3.0


def profile(nu_lo, nu_hi, nu_c, flux_int, v0, fwhm):
    """Channel-averaged flux density (Jy) of a Gaussian line of integral ``flux_int``
    (Jy km/s), centre v0 and FWHM (km/s), for channels [nu_lo, nu_hi] (plain numpy/erf)."""
    va = C_KMS * (nu_c - nu_hi) / nu_c
    vb = C_KMS * (nu_c - nu_lo) / nu_c
    s = fwhm / (2 * np.sqrt(2 * np.log(2)))
    cdf = lambda v: 0.5 * (1 + erf((v - v0) / (np.sqrt(2) * s)))  # noqa: E731
    return flux_int * (cdf(vb) - cdf(va)) / (vb - va)


def make_cube(path, targets, *, n=40, nchan=60, noise=0.0, seed=0, ra0=150.0, dec0=2.0):
    """A FITS cube (1, nchan, n, n) with point sources at pixel centres: ``targets`` are
    (px, py, z, flux_int, v0, fwhm); returns the catalog (ra, dec, z)."""
    w = WCS(naxis=4)
    w.wcs.ctype = ["RA---SIN", "DEC--SIN", "FREQ", "STOKES"]
    w.wcs.cunit = ["deg", "deg", "Hz", ""]
    w.wcs.crval = [ra0, dec0, F0, 1.0]
    w.wcs.cdelt = [-CELL, CELL, DF, 1.0]
    w.wcs.crpix = [n // 2 + 1, n // 2 + 1, 1.0, 1.0]
    w.wcs.specsys = "LSRK"
    nu = F0 + DF * np.arange(nchan)
    yy, xx = np.mgrid[0:n, 0:n]
    s = BEAM_FWHM_PIX / (2 * np.sqrt(2 * np.log(2)))
    data = np.zeros((nchan, n, n))
    rows = []
    for px, py, z, fint, v0, fwhm in targets:
        nu_c = REST / (1 + z)
        f = profile(nu - DF / 2, nu + DF / 2, nu_c, fint, v0, fwhm)
        data += f[:, None, None] * np.exp(-((xx - px) ** 2 + (yy - py) ** 2) / (2 * s * s))
        ra, dec = w.celestial.pixel_to_world_values(px, py)
        rows.append((float(ra), float(dec), z))
    if noise:
        data += np.random.default_rng(seed).normal(scale=noise, size=data.shape)
    h = w.to_header()
    h["BMAJ"] = h["BMIN"] = BEAM_FWHM_PIX * CELL
    h["BPA"] = 0.0
    h["BUNIT"] = "Jy/beam"
    fits.PrimaryHDU(data[None].astype(np.float32), header=h).writeto(path, overwrite=True)
    return Table(rows=rows, names=("ra", "dec", "z"))


def z_at(nu_c):
    return REST / nu_c - 1


# four targets well inside the band (band 1.290..1.293 GHz, ~700 km/s)
NUC = [1.2915e9, 1.29151e9, 1.29147e9, 1.291523e9]
TARGETS = [(10, 10, z_at(NUC[0]), 2.0, 0.0, 100.0), (29, 11, z_at(NUC[1]), 2.0, 0.0, 100.0),
           (12, 28, z_at(NUC[2]), 2.0, 0.0, 100.0), (28, 29, z_at(NUC[3]), 2.0, 0.0, 100.0)]
GRID = dict(velocity_resolution=20.0, velocity_range=(-300.0, 300.0))


def test_noiseless_recovers_integral_centre_width(tmp_path):
    from xstack.fit.line import fit_line

    same = make_cube(tmp_path / "same.fits", [t[:2] + TARGETS[0][2:] for t in TARGETS])
    cat = make_cube(tmp_path / "c.fits", TARGETS)
    for method in ("mean", "median"):
        # the median is not linear: it conserves the integral exactly when the targets'
        # regridded spectra agree (the same line centre), the mean for any centres
        cube = tmp_path / ("c.fits" if method == "mean" else "same.fits")
        res = stack_line_cube(cube, cat if method == "mean" else same, line_frequency="HI",
                              method=method,
                              weighting="none", stamp_size=16, **GRID)
        assert np.all(res.n_targets_per_bin == 4)
        integral = np.sum(res.flux_jy * np.diff(res.velocity_edges_kms))
        assert integral == pytest.approx(2.0, rel=1e-6), method
        fit = fit_line(res.velocity_kms, res.flux_jy, np.diag(np.full(res.flux_jy.size, 1e-6)),
                       velocity_edges_kms=res.velocity_edges_kms)
        assert fit.converged
        assert abs(fit.centre_kms) < 0.5
        # the channels' boxcar (~11.6 km/s) broadens the line by ~1 %
        assert fit.fwhm_kms == pytest.approx(100.0, rel=0.02)


def test_with_noise_within_errors(tmp_path):
    from xstack.fit.line import fit_line

    cat = make_cube(tmp_path / "c.fits", TARGETS, noise=0.01, seed=3)
    res = stack_line_cube(tmp_path / "c.fits", cat, line_frequency="HI", stamp_size=24, **GRID)
    fit = fit_line(res.velocity_kms, res.flux_jy, res.flux_cov_jy2,
                   velocity_edges_kms=res.velocity_edges_kms, window_kms=(-300, 300))
    assert fit.converged
    assert abs(fit.integrated_flux_jy_kms - 2.0) < 3 * fit.integrated_flux_err_jy_kms
    assert abs(fit.centre_kms) < 3 * fit.centre_err_kms
    assert abs(fit.fwhm_kms - 100.0) < 3 * fit.fwhm_err_kms + 2.0


def test_partial_coverage_only_the_bins_covered(tmp_path):
    # target B's centre near the band's low-frequency edge: its high velocities are outside
    edge = F0 - DF / 2
    nu_b = edge / (1 - 150.0 / C_KMS)  # v = +150 km/s falls on the band edge
    targets = [TARGETS[0], (29, 29, z_at(nu_b), 2.0, 0.0, 100.0)]
    cat = make_cube(tmp_path / "c.fits", targets)
    res = stack_line_cube(tmp_path / "c.fits", cat, line_frequency="HI", weighting="none",
                          stamp_size=16, **GRID)
    v = res.velocity_kms
    assert np.all(res.n_targets_per_bin[v < 140] == 2)
    assert np.all(res.n_targets_per_bin[v > 160] == 1)
    alone = stack_line_cube(tmp_path / "c.fits", cat[:1], line_frequency="HI",
                            weighting="none", stamp_size=16, **GRID)
    # B adds nothing where it has no channels: there the stack is A's alone
    np.testing.assert_allclose(res.flux_jy[v > 160], alone.flux_jy[v > 160], rtol=1e-9,
                               atol=1e-15)
    # elsewhere the same line (different channel phases: a percent of the peak)
    np.testing.assert_allclose(res.flux_jy, alone.flux_jy, atol=2e-2 * alone.flux_jy.max())
    assert res.positions["n_bins"][1] < res.positions["n_bins"][0]


def test_errors_against_brute_force(tmp_path):
    n_real = 200
    cube = tmp_path / "n.fits"
    fluxes, errs = [], []
    for r in range(n_real):
        cat = make_cube(cube, TARGETS, n=32, nchan=60, noise=0.01, seed=100 + r)
        res = stack_line_cube(cube, cat, line_frequency="HI", stamp_size=20, **GRID)
        fluxes.append(res.flux_jy)
        errs.append(res.flux_err_jy)
        if r == 0:
            cov = res.flux_cov_jy2
    fluxes = np.asarray(fluxes)
    scatter = fluxes.std(axis=0, ddof=1)
    ratio = scatter / np.mean(errs, axis=0)
    assert np.all(np.abs(ratio - 1) < 0.15), ratio
    # neighbouring bins share channels: their correlation as predicted
    emp = np.corrcoef(fluxes.T)
    pred = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    j = np.arange(len(scatter) - 1)
    assert np.mean(pred[j, j + 1]) > 0.1
    assert abs(np.mean(emp[j, j + 1]) - np.mean(pred[j, j + 1])) < 0.05


def test_bad_inputs(tmp_path):
    cat = make_cube(tmp_path / "c.fits", TARGETS[:1])
    two_d = tmp_path / "im.fits"
    with fits.open(tmp_path / "c.fits") as h:
        w = WCS(h[0].header).celestial
        fits.PrimaryHDU(np.asarray(h[0].data[0, 0]), header=w.to_header()).writeto(two_d)
    with pytest.raises(XstackError, match="needs an image cube"):
        stack_line_cube(two_d, cat, line_frequency="HI")
    with pytest.raises(XstackError, match="column z .* or freq"):
        stack_line_cube(tmp_path / "c.fits", Table({"ra": cat["ra"], "dec": cat["dec"]}),
                        line_frequency="HI")


# --- frames: a topocentric cube and a catalog of LSRK redshifts ----------------------------

VLA_ITRF = (-1601185.4, -5041977.5, 3554875.9)  # m
MJD_AVG = 60100.3


def _astropy_topo_per_lsrk(ra, dec):
    """nu_topo / nu_lsrk towards (ra, dec) at MJD_AVG seen from the VLA: astropy's
    SpectralCoord (not xstack.frames)."""
    import warnings

    import astropy.units as u
    from astropy.coordinates import EarthLocation, SkyCoord, SpectralCoord
    from astropy.time import Time

    t = Time(MJD_AVG, format="mjd", scale="utc")
    obs = EarthLocation.from_geocentric(*VLA_ITRF, unit=u.m).get_itrs(obstime=t)
    target = SkyCoord(ra * u.deg, dec * u.deg, frame="icrs")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        topo = SpectralCoord(1.0 * u.GHz, observer=obs, target=target)
        lsrk = topo.with_observer_stationary_relative_to("lsrk")
    return float((topo / lsrk).to_value(u.one))


def _topo_cube(path, *, keywords=True):
    """The four targets' lines at their catalog (LSRK) centres, written at the topocentric
    frequencies astropy gives; the header says TOPOCENT (and when and where, if asked)."""
    q = _astropy_topo_per_lsrk(150.0, 2.0)
    # the lines at nu_topo = q nu_lsrk: the same cube as make_cube with z_topo
    targets = [(px, py, z_at(REST / (1 + z) * q), f, v0, fw)
               for px, py, z, f, v0, fw in TARGETS]
    make_cube(path, targets)
    with fits.open(path, mode="update") as hdul:
        h = hdul[0].header
        h["SPECSYS"] = "TOPOCENT"
        if keywords:
            h["MJD-AVG"] = MJD_AVG
            h["DATE-OBS"] = "2023-06-20T00:00:00"  # another time: MJD-AVG must win
            for axis, value in zip("XYZ", VLA_ITRF):
                h[f"OBSGEO-{axis}"] = value
    return Table(rows=[(ra, dec, z) for ra, dec, z in
                       zip(*(make_cube(path.with_suffix(".lsrk.fits"), TARGETS)[c]
                             for c in ("ra", "dec", "z")))], names=("ra", "dec", "z")), q


def test_topocentric_cube_is_converted_to_the_catalog_frame(tmp_path):
    """LSRK redshifts stacked on a TOPOCENT cube: converted with the header's MJD-AVG and
    OBSGEO (the line centred to 0.5 km/s); as the cube's own frame (frame='cube') the line
    sits at c (1 - q), q = nu_topo / nu_lsrk from astropy, within 0.5 km/s."""
    from xstack.fit.line import fit_line

    cat, q = _topo_cube(tmp_path / "topo.fits")
    shift = C_KMS * (1 - q)
    assert abs(shift) > 5.0  # the test means something: the Doppler shift is many km/s
    grid = dict(velocity_resolution=10.0, velocity_range=(-300.0, 300.0))
    fits_ = {}
    for frame in ("lsrk", "cube"):
        res = stack_line_cube(tmp_path / "topo.fits", cat, line_frequency=REST, frame=frame,
                              primary_beam="none", weighting="none", **grid)
        fit = fit_line(res.velocity_kms, res.flux_jy, res.flux_cov_jy2 + 1e-12 * np.eye(60),
                       velocity_edges_kms=res.velocity_edges_kms)
        fits_[frame] = (res, fit)
    res, fit = fits_["lsrk"]
    assert res.frame == "lsrk" and res.options["cube_frame"] == "topo"
    # xstack.frames against astropy: 2e-9 apart (0.7 m/s)
    assert res.options["frame_ratio"] == pytest.approx(1 / q, rel=1e-8)
    assert abs(fit.centre_kms) < 0.5, fit.centre_kms
    res, fit = fits_["cube"]
    assert res.frame == "topo"
    assert fit.centre_kms == pytest.approx(shift, abs=0.5)


def test_topocentric_cube_without_time_or_place_is_a_clear_error(tmp_path):
    cat, _ = _topo_cube(tmp_path / "bare.fits", keywords=False)
    with pytest.raises(OptionError, match=r"MJD-AVG/MJD-OBS/DATE-OBS, OBSGEO-X/Y/Z.*frame 'cube'"):
        stack_line_cube(tmp_path / "bare.fits", cat, line_frequency=REST, primary_beam="none")
    with pytest.raises(OptionError, match="unknown frame"):
        stack_line_cube(tmp_path / "bare.fits", cat, line_frequency=REST, frame="topo")
    res = stack_line_cube(tmp_path / "bare.fits", cat, line_frequency=REST, frame="cube",
                          primary_beam="none")
    assert res.frame == "topo"


def test_channel_noise_sees_through_a_bright_neighbour(tmp_path):
    """A 20-sigma continuum point (what CLEAN leaves of a bright source) 6 pixels from two
    of the four targets: the plain std of their stamp planes counts it as noise, the default
    clipped std does not. Truth: the same noise without the neighbour, whose errors
    test_errors_against_brute_force checks against the scatter of 200 realisations."""
    noise = 0.01
    clean = tmp_path / "clean.fits"
    cat = make_cube(clean, TARGETS, n=40, nchan=60, noise=noise, seed=7)
    with fits.open(clean) as hdul:
        data, header = hdul[0].data.astype(np.float64), hdul[0].header
    yy, xx = np.mgrid[0:40, 0:40]
    s = BEAM_FWHM_PIX / (2 * np.sqrt(2 * np.log(2)))
    for px, py in ((16, 10), (29, 17)):   # 6 px east of target 0, 6 px north of target 1
        data += 20 * noise * np.exp(-((xx - px) ** 2 + (yy - py) ** 2) / (2 * s * s))
    bright = tmp_path / "bright.fits"
    fits.PrimaryHDU(data.astype(np.float32), header=header).writeto(bright)

    kw = dict(line_frequency="HI", stamp_size=20, **GRID)
    ref = stack_line_cube(clean, cat, **kw)
    clipped = stack_line_cube(bright, cat, **kw)
    plain = stack_line_cube(bright, cat, noise_estimator="std", **kw)
    assert clipped.options["noise_estimator"] == "clipped"
    assert plain.options["noise_estimator"] == "std"
    inside = ref.n_targets_per_bin == 4
    r_clip = np.median(clipped.flux_err_jy[inside] / ref.flux_err_jy[inside])
    r_plain = np.median(plain.flux_err_jy[inside] / ref.flux_err_jy[inside])
    assert abs(r_clip - 1) < 0.05, r_clip     # 1.026: the neighbour's 1-3 sigma wings stay
    assert r_plain > 1.25, r_plain            # 1.36
    # the neighbour adds nothing at the targets: the clipped stack is the clean one's
    np.testing.assert_allclose(clipped.flux_jy[inside], ref.flux_jy[inside],
                               atol=0.5 * np.median(ref.flux_err_jy[inside]))
    with pytest.raises(OptionError, match="noise estimator"):
        stack_line_cube(clean, cat, noise_estimator="rms", **kw)
