"""Dirty image cubes (``xstack image --cube``) and the cube -> line-stack chain (issue 15)."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from _imaging_helpers import PHASE_CENTER, make_sky_partition
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS
from scipy.special import erf

from xstack.cli import main
from xstack.imaging.cube import make_cube
from xstack.imaging.fitsio import celestial_wcs, make_header
from xstack.imaging.image import make_image
from xstack.schema import open_store, write_store
from xstack.spectral import SPEED_OF_LIGHT_KMS as C_KMS

REST = 1420.405751786e6
NCHAN, F0, DF = 48, 1.3195e9, 0.1e6  # ~22.7 km/s channels, 1090 km/s
SIZE, CELL = 64, 2.0
# (pixel x, pixel y, line centre Hz, integral Jy km/s, FWHM km/s): the lines ~540 km/s apart,
# so neither's dirty sidelobes reach the other's channels (dirty cubes: no CLEAN)
LINES = [(SIZE // 2 + 6, SIZE // 2 - 4, 1.32068e9, 40.0, 120.0),
         (SIZE // 2, SIZE // 2, 1.32311e9, 40.0, 120.0)]


def channel_flux(nu_c, fint, fwhm):
    """Channel-averaged flux density (Jy) of a Gaussian line centred on nu_c (plain numpy)."""
    nu = F0 + DF * np.arange(NCHAN)
    va = C_KMS * (nu_c - (nu + DF / 2)) / nu_c
    vb = C_KMS * (nu_c - (nu - DF / 2)) / nu_c
    s = fwhm / (2 * np.sqrt(2 * np.log(2)))
    cdf = lambda v: 0.5 * (1 + erf(v / (np.sqrt(2) * s)))  # noqa: E731
    return fint * (cdf(vb) - cdf(va)) / (vb - va)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    d = tmp_path_factory.mktemp("cube")
    ds = make_sky_partition([], n_chan=NCHAN, freq0=F0, chan_width=DF, n_ant=10, n_time=12,
                            noise=0.0)
    # the line sources, injected with plain numpy: V = sum f(nu) exp(2 pi i (ul + vm + w(n-1)) nu/c)
    wcs = celestial_wcs(make_header(SIZE, SIZE, CELL, PHASE_CENTER))
    uvw = np.asarray(ds["UVW"].values, dtype=np.float64)
    nu = np.asarray(ds["frequency"].values)
    vis = np.zeros(ds["VISIBILITY"].shape, dtype=np.complex128)
    rows = []
    for px, py, nu_c, fint, fwhm in LINES:
        ra, dec = np.radians(wcs.pixel_to_world_values(px, py))
        l = np.cos(dec) * np.sin(ra - PHASE_CENTER[0])
        m = np.sin(dec) * np.cos(PHASE_CENTER[1]) - np.cos(dec) * np.sin(PHASE_CENTER[1]) * \
            np.cos(ra - PHASE_CENTER[0])
        n1 = np.sqrt(1 - l * l - m * m) - 1
        phase = 2j * np.pi * (uvw[..., 0, None] * l + uvw[..., 1, None] * m
                              + uvw[..., 2, None] * n1) * nu / 299_792_458.0
        vis += (channel_flux(nu_c, fint, fwhm) * np.exp(phase))[..., None]
        rows.append((np.degrees(ra), np.degrees(dec), nu_c / 1e6))
    ds["VISIBILITY"] = (ds["VISIBILITY"].dims, vis.astype(np.complex64))
    write_store({"spw0_field0": ds}, d / "line.zarr")
    cat = Table(rows=rows, names=("ra", "dec", "freq"))
    cat["freq"].unit = "MHz"
    cat.write(d / "cat.ecsv")
    return d


def test_planes_are_the_continuum_image_of_their_channels(store):
    data = open_store(store / "line.zarr")
    cube = make_cube(data, size=SIZE, cell_arcsec=CELL)
    assert cube.image.shape == (NCHAN, SIZE, SIZE)
    ds = open_store(store / "line.zarr")["spw0_field0"].ds
    for i in (0, 9, 17):
        one = make_image(ds.isel(frequency=slice(i, i + 1)), size=SIZE, cell_arcsec=CELL)
        # 1e-12 of the peak, not bit for bit: ducc0's threads may sum in another order
        np.testing.assert_allclose(cube.image[i], one.image, rtol=0,
                                   atol=1e-12 * np.abs(one.image).max())
        # a least-squares fit: rounding of the image moves it by ~1e-10
        assert tuple(cube.beams[i]) == pytest.approx(one.beam, rel=1e-7)
    np.testing.assert_allclose(cube.frequency_hz, F0 + DF * np.arange(NCHAN), rtol=1e-15)
    two = make_image(data, size=SIZE, cell_arcsec=CELL, cube=True, channels=2,
                     weighting="uniform")
    one = make_image(ds.isel(frequency=slice(6, 8)), size=SIZE, cell_arcsec=CELL,
                     weighting="uniform")
    np.testing.assert_allclose(two.image[3], one.image, rtol=0,
                               atol=1e-12 * np.abs(one.image).max())
    assert two.frequency_hz[3] == pytest.approx(F0 + 6.5 * DF, rel=1e-15)


def test_fits_cube_spectral_axis_and_beams(store, tmp_path):
    out = tmp_path / "c.fits"
    cube = make_cube(str(store / "line.zarr"), size=SIZE, cell_arcsec=CELL, out=out,
                     keep=True)
    with fits.open(out) as hdul:
        h = hdul[0].header
        assert hdul[0].data.shape == (1, NCHAN, SIZE, SIZE)
        np.testing.assert_array_equal(hdul[0].data[0], cube.image.astype(np.float32))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            w = WCS(h)
        assert w.has_spectral and w.wcs.spec == 2
        freq = w.spectral.pixel_to_world_values(np.arange(NCHAN))
        np.testing.assert_allclose(freq, F0 + DF * np.arange(NCHAN), rtol=1e-12)
        assert h["SPECSYS"] == "TOPOCENT" and h["CUNIT3"] == "Hz"
        # when and where (FITS WCS paper III): what a reader needs to convert the frame
        ds = open_store(store / "line.zarr")[list(open_store(store / "line.zarr").children)[0]]
        t = np.asarray(ds["time"].values)
        from astropy.time import Time

        t_mjd = Time(t, format="datetime64").mjd if t.dtype.kind == "M" else t / 86400.0
        assert h["MJD-OBS"] == pytest.approx(np.min(t_mjd), abs=1e-9)
        assert h["MJD-AVG"] == pytest.approx(np.mean(t_mjd), abs=1e-9)
        assert Time(h["DATE-OBS"], scale="utc").mjd == pytest.approx(np.min(t_mjd), abs=1e-8)
        pos = np.asarray(ds["ANTENNA_POSITION"].values).mean(axis=0)
        assert [h[f"OBSGEO-{a}"] for a in "XYZ"] == pytest.approx(list(pos), abs=1e-6)
        beams = hdul["BEAMS"].data
        assert len(beams) == NCHAN and h["CASAMBM"]
        np.testing.assert_allclose(beams["BMAJ"], cube.beams[:, 0], rtol=1e-6)
        assert list(beams["CHAN"]) == list(range(NCHAN))


def test_cli_cube_then_line_imstack_recovers_the_line(store, tmp_path, capsys):
    cube = tmp_path / "cube.fits"
    assert main(["image", str(store / "line.zarr"), str(cube), "--size", str(SIZE),
                 "--cell", str(CELL), "--cube", "--no-progress", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["n_planes"] == NCHAN
    out = tmp_path / "stack.fits"
    assert main(["imstack", str(cube), str(store / "cat.ecsv"), str(out),
                 "--line-frequency", "HI", "--velocity-resolution", "30km/s",
                 "--velocity-range=-270,270km/s", "--weighting", "none",
                 "--stamp-size", "24", "--json", "--no-progress", "--frame", "cube"]) == 0
    res = json.loads(capsys.readouterr().out)
    for key in ("velocity_kms", "flux_jy", "flux_err_jy", "integrated_flux_jy_kms",
                "integrated_flux_err_jy_kms", "line_fwhm_kms", "line_centre_kms",
                "n_positions", "n_visibilities", "n_targets_per_bin"):
        assert key in res
    assert res["n_positions"] == 2
    # noiseless: the line, integral over the whole grid
    flux = np.asarray(res["flux_jy"], dtype=float)
    integral = np.nansum(flux) * 30.0
    assert integral == pytest.approx(40.0, rel=1e-3)
    assert abs(res["line_centre_kms"]) < 2.0
    assert res["line_fwhm_kms"] == pytest.approx(120.0, rel=0.05)
    for suffix in ("_spectrum.ecsv", "_spectrum.png", "_mom0.png"):
        assert (tmp_path / f"stack{suffix}").exists()
    with fits.open(out) as hdul:
        assert hdul[0].header["CTYPE3"] == "VRAD"
    assert res["frame"] == "topo"

    # the catalog read as LSRK (the default): the cube's TOPOCENT axis converted with its
    # MJD-AVG and OBSGEO keywords, so the topocentric line moves by -c (r - 1), r = nu_lsrk /
    # nu_topo from astropy's SpectralCoord (not xstack.frames)
    import astropy.units as u
    from astropy.coordinates import EarthLocation, SkyCoord, SpectralCoord
    from astropy.time import Time

    h = fits.getheader(cube)
    obs = EarthLocation.from_geocentric(*(h[f"OBSGEO-{a}"] for a in "XYZ"), unit=u.m)
    sc = SpectralCoord(1.0 * u.GHz, observer=obs.get_itrs(Time(h["MJD-AVG"], format="mjd")),
                       target=SkyCoord(h["CRVAL1"] * u.deg, h["CRVAL2"] * u.deg))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = float((sc.with_observer_stationary_relative_to("lsrk") / sc).to_value(u.one))
    assert main(["imstack", str(cube), str(store / "cat.ecsv"), str(tmp_path / "lsrk.fits"),
                 "--line-frequency", "HI", "--velocity-resolution", "30km/s",
                 "--velocity-range=-270,270km/s", "--weighting", "none",
                 "--stamp-size", "24", "--json", "--no-progress"]) == 0
    lsrk = json.loads(capsys.readouterr().out)
    assert lsrk["frame"] == "lsrk"
    assert abs(C_KMS * (r - 1)) > 10.0
    # the factor itself (xstack.frames against astropy: ~2e-9 apart), and the line's fitted
    # centre moved by it (to 1.5 km/s: the two fits see the channels in other phases of the
    # 30 km/s bins, and the channels box-smooth the line by 23 km/s)
    assert lsrk["options"]["frame_ratio"] == pytest.approx(r, rel=1e-8)
    assert lsrk["line_centre_kms"] - res["line_centre_kms"] == pytest.approx(
        -C_KMS * (r - 1), abs=1.5)


def test_cli_line_bad_inputs(store, tmp_path, capsys):
    im = tmp_path / "im.fits"
    assert main(["image", str(store / "line.zarr"), str(im), "--size", str(SIZE),
                 "--cell", str(CELL), "--no-progress"]) == 0
    capsys.readouterr()
    rc = main(["imstack", str(im), str(store / "cat.ecsv"), str(tmp_path / "s.fits"),
               "--line-frequency", "HI", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and "needs an image cube" in err and len(err.splitlines()) == 1
    cube = tmp_path / "c.fits"
    assert main(["image", str(store / "line.zarr"), str(cube), "--size", str(SIZE),
                 "--cell", str(CELL), "--cube", "--channels", "4", "--no-progress"]) == 0
    Table.read(store / "cat.ecsv")["ra", "dec"].write(tmp_path / "noz.ecsv")
    capsys.readouterr()
    rc = main(["imstack", str(cube), str(tmp_path / "noz.ecsv"), str(tmp_path / "s.fits"),
               "--line-frequency", "HI", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and "z (redshift) or freq" in err and len(err.splitlines()) == 1


def test_cli_cube_option_conflicts(store, tmp_path, capsys):
    base = ["image", str(store / "line.zarr"), str(tmp_path / "x.fits"), "--size", str(SIZE),
            "--cell", str(CELL), "--no-progress"]
    assert main(base + ["--channels", "2"]) != 0
    assert "--channels needs --cube" in capsys.readouterr().err
    assert main(base + ["--cube", "--niter", "10"]) != 0
    assert "does not go with --cube" in capsys.readouterr().err
    assert not (tmp_path / "x.fits").exists()


def _astropy_lsrk_per_topo(times_mjd_s, ra_deg, dec_deg, itrf_m):
    """nu_lsrk / nu_topo per time (astropy's SpectralCoord, not xstack.frames)."""
    import astropy.units as u
    from astropy.coordinates import EarthLocation, SkyCoord, SpectralCoord
    from astropy.time import Time

    loc = EarthLocation.from_geocentric(*itrf_m, unit=u.m)
    target = SkyCoord(ra_deg * u.deg, dec_deg * u.deg)
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for t in np.atleast_1d(times_mjd_s):
            obs = loc.get_itrs(Time(t / 86400.0, format="mjd", scale="utc"))
            sc = SpectralCoord(1.0 * u.GHz, observer=obs, target=target)
            out.append(float((sc.with_observer_stationary_relative_to("lsrk") / sc)
                             .to_value(u.one)))
    return np.array(out)


def test_velocity_grid_cube_planes_are_overlap_weighted_lsrk_channels(store, tmp_path):
    """``make_cube(velocity_resolution=30, line_frequency=HI, frame='lsrk')`` of TOPO data:
    each plane at a source's pixel is the overlap-weighted mean, over integrations and
    channels, of the channel fluxes, with the channels' LSRK edges from astropy per
    integration (plain numpy here); the FITS axis is the radio-velocity grid."""
    ds = open_store(store / "line.zarr")["spw0_field0"].ds
    dv = 30.0
    cube = make_cube(str(store / "line.zarr"), size=SIZE, cell_arcsec=CELL,
                     velocity_resolution=dv, line_frequency="HI", frame="lsrk",
                     out=tmp_path / "v.fits", keep=True)
    t = np.asarray(ds["time"].values, dtype=np.float64)
    pc = np.degrees(np.asarray(ds.attrs["phase_center"], dtype=np.float64))
    itrf = np.asarray(ds["ANTENNA_POSITION"].values).mean(axis=0)
    r = _astropy_lsrk_per_topo(t, pc[0], pc[1], itrf)
    assert np.ptp(r) > 0 and abs(C_KMS * (r.mean() - 1)) > 1.0  # a real, moving shift
    hi = 1_420_405_751.768
    dnu = hi * dv / C_KMS
    nu = F0 + DF * np.arange(NCHAN)
    lo_e, hi_e = nu - DF / 2, nu + DF / 2
    w = np.asarray(ds["WEIGHT"].values, dtype=np.float64)[..., 0]  # (time, baseline, chan)
    # the planes: edges at HI (1 - k dv / c), wholly inside the band at every integration
    k = (hi - cube.frequency_hz) / dnu - 0.5
    np.testing.assert_allclose(k, np.round(k), atol=1e-6)
    assert np.all(cube.frequency_hz - dnu / 2 >= r.max() * lo_e.min() - 1e-3)
    assert np.all(cube.frequency_hz + dnu / 2 <= r.min() * hi_e.max() + 1e-3)
    assert np.all(np.diff(cube.frequency_hz) > 0)
    px, py, nu_c, fint, fwhm = LINES[1]  # the source at the centre pixel: the phase centre
    flux = channel_flux(nu_c, fint, fwhm)
    # the dirty image at the phase centre by a direct sum: the weighted mean of Re V (the
    # other source's sidelobes included)
    vis_re = np.asarray(ds["VISIBILITY"].values)[..., 0].real.astype(np.float64)
    checked = 0
    for p, centre in enumerate(cube.frequency_hz):
        a, b = r[:, None] * lo_e, r[:, None] * hi_e  # (time, chan) LSRK edges
        frac = np.clip(np.minimum(b, centre + dnu / 2) - np.maximum(a, centre - dnu / 2), 0,
                       None) / (b - a)
        ww = w * frac[:, None, :]
        expect = np.sum(ww * vis_re) / np.sum(ww)
        got = cube.image[p, py, px]
        # (the gridder: epsilon 1e-6 of the summed |V|: ~1e-5 of the peak here)
        assert got == pytest.approx(expect, abs=3e-5 * flux.max()), (p, got, expect)
        # and where this line is, the plane is its overlap-weighted channel flux (the other
        # line, 550 km/s away, adds its dirty sidelobes only in its own planes)
        alone = np.sum(ww * flux) / np.sum(ww)
        if alone > 0.05 * flux.max():
            assert alone == pytest.approx(expect, abs=1e-3 * flux.max())
            checked += 1
    assert checked >= 4  # the line spans several planes
    with fits.open(tmp_path / "v.fits") as hdul:
        h = hdul[0].header
        assert h["SPECSYS"] == "LSRK" and h["CTYPE3"] == "FREQ"
        assert h["RESTFRQ"] == pytest.approx(hi) and h["XSVRES"] == dv
        assert h["CDELT3"] == pytest.approx(dnu, rel=1e-12)
        assert h["CRVAL3"] == pytest.approx(cube.frequency_hz[0], rel=1e-14)


def test_velocity_grid_cube_then_imstack_centres_the_line(store, tmp_path, capsys):
    """The CLI chain: an LSRK velocity-grid cube of the TOPO data, then imstack with the
    catalog's frequencies taken as LSRK lines at r times the TOPO ones (the stack has no
    conversion to make: the cube is LSRK): centred to 2 km/s, integral kept to 1 %."""
    from xstack.frames import frame_ratio

    cube = tmp_path / "v.fits"
    assert main(["image", str(store / "line.zarr"), str(cube), "--size", str(SIZE),
                 "--cell", str(CELL), "--cube", "--velocity-resolution", "20km/s",
                 "--line-frequency", "HI", "--no-progress", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frame"] == "LSRK"
    ds = open_store(store / "line.zarr")["spw0_field0"].ds
    pc = np.degrees(np.asarray(ds.attrs["phase_center"], dtype=np.float64))
    r = frame_ratio(np.asarray(ds["time"].values, dtype=np.float64), pc[0], pc[1],
                    np.asarray(ds["ANTENNA_POSITION"].values).mean(axis=0), to_frame="lsrk")
    cat = Table.read(store / "cat.ecsv")
    cat["freq"] = cat["freq"] * float(r.mean())  # the lines' LSRK centres
    cat.write(tmp_path / "lsrk.ecsv")
    assert main(["imstack", str(cube), str(tmp_path / "lsrk.ecsv"), str(tmp_path / "s.fits"),
                 "--line-frequency", "HI", "--velocity-resolution", "30km/s",
                 "--velocity-range=-270,270km/s", "--weighting", "none",
                 "--stamp-size", "24", "--json", "--no-progress"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["frame"] == "lsrk" and res["options"]["frame_ratio"] == 1.0
    assert abs(res["line_centre_kms"]) < 2.0
    assert np.nansum(np.asarray(res["flux_jy"], dtype=float)) * 30.0 == pytest.approx(40.0,
                                                                                    rel=0.01)


def test_velocity_grid_cube_options(store, tmp_path, capsys):
    base = ["image", str(store / "line.zarr"), str(tmp_path / "x.fits"), "--size", str(SIZE),
            "--cell", str(CELL), "--no-progress"]
    for extra, words in ((["--cube", "--velocity-resolution", "20"], "go together"),
                         (["--cube", "--line-frequency", "HI"], "go together"),
                         (["--cube", "--frame", "lsrk"], "--frame needs"),
                         (["--velocity-resolution", "20", "--line-frequency", "HI"],
                          "needs --cube"),
                         (["--cube", "--channels", "2", "--velocity-resolution", "20",
                           "--line-frequency", "HI"], "does not go with"),
                         (["--cube", "--velocity-resolution", "5000", "--line-frequency",
                           "HI"], "no plane")):
        assert main(base + extra) != 0
        err = capsys.readouterr().err.strip()
        assert words in err and len(err.splitlines()) == 1, (extra, err)
    assert not (tmp_path / "x.fits").exists()


def test_line_in_a_casacore_ms_recovered_by_image_domain_stacking(tmp_path):
    """The uv tests' MS (python-casacore, LSRK; Gaussian lines of 1 Jy km/s, sigma 40 km/s at
    three targets with their own redshifts, injected with numpy, no noise) imaged as a cube and
    image-stacked at pixel-centred targets: the integral, centre and width of the injected line
    come back (to 1e-3, 0.5 km/s and 1 %)."""
    from test_uvstack_line import HI as HI_HZ
    from test_uvstack_line import _ms_with_lines

    from xstack.fit.line import fit_line
    from xstack.imstack.line import stack_line_cube
    from xstack.testing._ms import DEFAULT_PHASE_CENTER

    flux, sig = 1.0, 40.0
    nus = 1.30e9 + 50e3 * np.array([40.3, 127.9, 216.1])
    ra0, dec0 = np.degrees(DEFAULT_PHASE_CENTER)
    cell = 1.0
    # targets on pixel centres of the cube (the image stack takes the nearest pixel)
    wcs = celestial_wcs(make_header(64, 64, cell, DEFAULT_PHASE_CENTER))
    pix = [(32, 32), (20, 41), (43, 25)]
    radec = [tuple(float(x) for x in wcs.pixel_to_world_values(px, py)) for px, py in pix]
    targets = [(ra, dec, nu) for (ra, dec), nu in zip(radec, nus)]
    store, _, _ = _ms_with_lines(tmp_path, targets, flux, sig, 0.0)
    make_cube(store, size=64, cell_arcsec=cell, out=tmp_path / "cube.fits", keep=False)
    cat = Table({"ra": [t[0] for t in targets], "dec": [t[1] for t in targets],
                 "z": HI_HZ / nus - 1})
    res = stack_line_cube(tmp_path / "cube.fits", cat, line_frequency="HI",
                          velocity_resolution=20.0, velocity_range=(-300, 300),
                          weighting="none", primary_beam="auto", stamp_size=16)
    assert res.frame == "lsrk" and res.n_positions == 3
    integral = np.nansum(res.flux_jy) * 20.0
    # (the standard VLA beam divided out: 1e-4 at these 20" offsets)
    assert integral == pytest.approx(flux, rel=1e-3)
    cov = res.flux_cov_jy2 if np.all(np.isfinite(res.flux_cov_jy2)) else np.eye(res.flux_jy.size)
    fit = fit_line(res.velocity_kms, res.flux_jy, cov + 1e-12 * np.eye(res.flux_jy.size),
                   velocity_edges_kms=res.velocity_edges_kms)
    assert fit.converged
    assert abs(fit.centre_kms) < 0.5
    # 10 km/s channels and 20 km/s bins widen the 94.2 km/s line by < 1 %
    assert fit.fwhm_kms == pytest.approx(2 * np.sqrt(2 * np.log(2)) * sig, rel=0.01)
