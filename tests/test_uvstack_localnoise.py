"""uv-stacking ``weighting="sigma2"`` with sigma_k measured in a residual image (paper §3.2).

(a) known noise varying across an image is recovered; (b) a source at the stamp center does
not inflate sigma_k; (c) end to end: a primary-beam corrected residual image of simulated
data gives weights 1/sigma_k^2 and a flux error no worse than equal weights; (d) bad input
gets a clear error and nothing is written.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from _imaging_helpers import PHASE_CENTER, make_sky_partition
from astropy.io import fits
from astropy.table import Table
from astropy.wcs import WCS

from xstack.beams import standard_beam
from xstack.cli import main
from xstack.coords import angular_separation, lm_to_radec
from xstack.errors import XstackError
from xstack.imaging.image import make_image
from xstack.schema import open_store, write_store
from xstack.uvstack.localnoise import CLIP_CORRECTION, local_noise, measure_local_noise
from xstack.uvstack.stack import stack_uv

CELL = 2.0  # arcsec, synthetic images
BMAJ = 6.0  # arcsec = 3 pixels


def _header(ny: int, nx: int, beam: bool = True, bunit: str = "Jy/beam") -> fits.Header:
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---SIN", "DEC--SIN"]
    w.wcs.crval = [150.0, 2.0]
    w.wcs.crpix = [nx // 2 + 1, ny // 2 + 1]
    w.wcs.cdelt = [-CELL / 3600, CELL / 3600]
    h = w.to_header()
    if beam:
        h["BMAJ"], h["BMIN"], h["BPA"] = BMAJ / 3600, BMAJ / 3600, 0.0
    h["BUNIT"] = bunit
    return h


def _world(hdu: fits.PrimaryHDU, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    ra, dec = WCS(hdu.header).pixel_to_world_values(x, y)
    return np.c_[ra, dec]


@pytest.fixture(scope="module")
def split_image():
    """White noise of sigma 1 on the left half of a 600 x 600 image and 3 on the right."""
    rng = np.random.default_rng(11)
    ny = nx = 600
    sig = np.where(np.arange(nx)[None, :] < nx // 2, 1.0, 3.0) * np.ones((ny, 1))
    data = rng.normal(size=(ny, nx)) * sig
    hdu = fits.PrimaryHDU(data, header=_header(ny, nx))
    # positions at least a stamp half-width (29 px) from the boundary and the edges
    x = np.r_[rng.uniform(35, 265, 20), rng.uniform(335, 565, 20)]
    y = rng.uniform(35, 565, 40)
    return hdu, _world(hdu, x, y), np.r_[np.full(20, 1.0), np.full(20, 3.0)]


# --- (a) known noise ------------------------------------------------------------------------

@pytest.mark.parametrize("estimator", ["clipped", "mad", "std"])
def test_known_noise_varying_across_field(split_image, estimator):
    hdu, pos, truth = split_image
    res = measure_local_noise(hdu, pos, estimator=estimator)
    # default stamp: ~300 beam areas (beam area 10.2 px -> 56 px, odd), mask radius = BMAJ
    assert res.stamp_size == 57 and res.mask_radius_arcsec == pytest.approx(BMAJ)
    assert res.bad_rows.size == 0 and res.unit == "Jy/beam"
    ratio = res.sigma / truth
    # ~3200 independent pixels per stamp: 1.3 % (std), 2 % (MAD) scatter per position
    assert np.max(np.abs(ratio - 1)) < (0.08 if estimator == "mad" else 0.05), ratio
    assert abs(np.mean(ratio) - 1) < 0.015
    # the public function returns the same array
    np.testing.assert_array_equal(local_noise(hdu, pos, estimator=estimator), res.sigma)


def test_clipped_estimator_is_unbiased_and_resists_outliers():
    # the truncation correction: converged 3-sigma clipping keeps |x| < 2.95 sigma
    assert CLIP_CORRECTION == pytest.approx(0.98485, abs=1e-4)
    rng = np.random.default_rng(5)
    data = rng.normal(size=(400, 400)) * 2.0
    clean = measure_local_noise(fits.PrimaryHDU(data, header=_header(400, 400)),
                                np.array([[150.0, 2.0]]), stamp_size=301).sigma[0]
    assert clean == pytest.approx(2.0, rel=0.015)
    # 1 % of the pixels are 20-sigma spikes (faint sources, artefacts): clipped ignores them
    spiky = data.copy()
    spiky.flat[rng.choice(data.size, data.size // 100, replace=False)] = 40.0
    hdu = fits.PrimaryHDU(spiky, header=_header(400, 400))
    clipped = measure_local_noise(hdu, np.array([[150.0, 2.0]]), stamp_size=301).sigma[0]
    std = measure_local_noise(hdu, np.array([[150.0, 2.0]]), stamp_size=301,
                              estimator="std").sigma[0]
    assert clipped == pytest.approx(clean, rel=0.02)
    assert std > 1.5 * clean


# --- (b) the central mask -------------------------------------------------------------------

def test_source_at_stamp_center_does_not_inflate_sigma():
    rng = np.random.default_rng(2)
    n = 200
    noise = rng.normal(size=(n, n))
    yy, xx = np.mgrid[0:n, 0:n]
    # a source shaped like the restoring beam at the center pixel
    shape = np.exp(-4 * np.log(2) * ((xx - 100) ** 2 + (yy - 100) ** 2) / (BMAJ / CELL) ** 2)
    h = _header(n, n)
    pos = _world(fits.PrimaryHDU(noise, header=h), np.array([100.0]), np.array([100.0]))

    def sigma(peak, **kw):
        return measure_local_noise(fits.PrimaryHDU(noise + peak * shape, header=h), pos,
                                   **kw).sigma[0]

    clean = sigma(0.0)
    assert clean == pytest.approx(1.0, rel=0.05)
    # the mask (radius BMAJ) cuts the source at 1/16 of its peak; the default clipped
    # estimator also drops the ring just outside it, even for a 200-sigma source
    assert sigma(200.0) == pytest.approx(clean, rel=0.03)
    # the paper's plain std: unaffected by a 30-sigma source, the mask does the work ...
    clean_std = sigma(0.0, estimator="std")
    assert sigma(30.0, estimator="std") == pytest.approx(clean_std, rel=0.03)
    # ... which without the mask would count the source as noise
    assert sigma(30.0, estimator="std", mask_radius_arcsec=0.1 * CELL) > 1.3 * clean_std
    assert sigma(200.0, estimator="std", mask_radius_arcsec=0.1 * CELL) > 3.0 * clean_std


def test_no_beam_defaults_and_blanked_pixels():
    rng = np.random.default_rng(4)
    data = rng.normal(size=(200, 200))
    data[:, :120] = np.nan  # blanked (e.g. beyond the primary-beam cutoff)
    hdu = fits.PrimaryHDU(data, header=_header(200, 200, beam=False))
    pos = _world(hdu, np.array([160.0, 121.0, 100.0]), np.array([100.0, 190.0, 100.0]))
    res = measure_local_noise(hdu, pos)
    assert res.stamp_size == 65 and res.mask_radius_arcsec == pytest.approx(5 * CELL)
    assert res.sigma[0] == pytest.approx(1.0, rel=0.06)
    # row 2, by the blanking and the image's edge: a third of its stamp, kept (>= 1/4)
    assert np.isfinite(res.sigma[1]) and res.n_pixels[1] < 0.5 * 65**2
    # row 3 sits on a blanked pixel
    assert res.bad_rows.tolist() == [2] and "blanked" in res.reasons[0]
    # asking for half the stamp rejects row 2, naming it and the pixel count
    strict = measure_local_noise(hdu, pos, min_fraction=0.5)
    assert strict.bad_rows.tolist() == [1, 2]
    assert f"only {res.n_pixels[1]} finite pixels" in strict.reasons[0]
    with pytest.raises(XstackError, match=r"2 of 3 positions: row 2 has only \d+ finite pixels"):
        local_noise(hdu, pos, min_fraction=0.5)


# --- (c) end to end -------------------------------------------------------------------------

N_POS = 40
FLUX = 0.02  # Jy, each target


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """VLA L-band pointing with 40 faint targets out to A ~ 0.33, noise, and its residual image.

    The data hold only noise and the (undetected) targets, so they are their own residual;
    the image is primary-beam corrected, so its noise rises as 1/A towards the field edge.
    """
    rng = np.random.default_rng(3)
    r = np.sqrt(rng.uniform(0, 1, N_POS)) * np.radians(17 / 60)
    phi = rng.uniform(0, 2 * np.pi, N_POS)
    ra, dec = lm_to_radec(r * np.sin(phi), r * np.cos(phi), *PHASE_CENTER)
    freq = 1.4e9 + 50e6 * np.arange(4)
    theta = angular_separation(PHASE_CENTER[0], PHASE_CENTER[1], ra, dec)
    att = standard_beam("VLA", 25.0)(theta[:, None], freq[None, :])
    ds = make_sky_partition(np.c_[ra, dec, np.full(N_POS, FLUX)], n_time=24, n_ant=12,
                            noise=0.5, seed=4, attenuation=att)
    img = make_image(ds, size=640, cell_arcsec=4.0, pbcor=True)
    tmp = tmp_path_factory.mktemp("localnoise")
    # the corrected dirty image (kind "image": XSPBCOR = T); the data are their own residual
    resid = img.write(tmp / "residual.fits", img.image, kind="image")
    plain = make_image(ds, size=640, cell_arcsec=4.0, pbcor=False)
    plain_path = plain.write(tmp / "residual_nopb.fits", plain.image, kind="residual")
    store = tmp / "data.zarr"
    write_store({"spw0_field0": ds}, store)
    cat = Table({"ra": np.degrees(ra), "dec": np.degrees(dec)})
    cat_path = tmp / "targets.ecsv"
    cat.write(cat_path, format="ascii.ecsv")
    return {"ds": ds, "img": img, "resid": resid, "plain": plain_path, "store": store,
            "cat": cat, "cat_path": cat_path, "att": att.mean(axis=1), "tmp": tmp}


def test_end_to_end_weights_follow_local_noise(scene):
    out = scene["tmp"] / "sigma2.zarr"
    res = stack_uv(scene["ds"], scene["cat"], weighting="sigma2", noise_image=scene["resid"],
                  out=out)
    sigma = local_noise(scene["resid"], scene["cat"])
    # the weights used are exactly 1/sigma_k^2 of the estimates
    np.testing.assert_allclose(res.positions["weight_used"][:, 0], 1.0 / sigma**2, rtol=1e-12)
    np.testing.assert_allclose(res.positions["sigma_local"], sigma, rtol=1e-12)
    # the noise of the pb-corrected image rises as 1/A: sigma_k A_k is nearly constant
    sa = sigma * scene["att"]
    assert np.std(sa) / np.mean(sa) < 0.08, sa
    assert res.options["sigma"] == f"local-noise:{scene['resid']}"
    assert res.options["local_noise"]["estimator"] == "clipped"
    assert res.options["local_noise"]["mask_radius_arcsec"] == pytest.approx(
        scene["img"].beam[0])
    stored = open_store(out).attrs["uvstack"]["options"]
    assert stored["sigma"] == res.options["sigma"]
    # an in-memory image gives the same weights
    mem = stack_uv(scene["ds"], scene["cat"], weighting="sigma2", noise_image=scene["img"])
    np.testing.assert_allclose(mem.positions["weight_used"], res.positions["weight_used"],
                               rtol=1e-6)
    assert mem.options["sigma"] == "local-noise:<in-memory image>"

    none = stack_uv(scene["ds"], scene["cat"], weighting="none")
    pb = stack_uv(scene["ds"], scene["cat"], weighting="pb")
    # measured (seed 3/4): flux_err 1.055 mJy (sigma2), 1.052 (pb), 1.226 (none)
    assert res.flux_err_jy <= none.flux_err_jy
    assert res.flux_err_jy < 0.9 * none.flux_err_jy
    assert res.flux_err_jy == pytest.approx(pb.flux_err_jy, rel=0.03)
    for r in (res, none, pb):
        assert abs(r.flux_jy - FLUX) < 4 * r.flux_err_jy


def test_catalog_sigma_column_is_overridden_with_a_warning(scene):
    cat = Table(scene["cat"], copy=True)
    cat["sigma"] = 1.0
    with pytest.warns(UserWarning, match="sigma column is ignored"):
        res = stack_uv(scene["ds"], cat, weighting="sigma2", noise_image=scene["resid"])
    assert res.options["sigma"].startswith("local-noise:")
    # without a noise image the column is used as before
    given = stack_uv(scene["ds"], cat, weighting="sigma2")
    assert given.options["sigma"] == "given"
    assert np.ptp(given.positions["weight_used"][:, 0]) == 0


def test_uncorrected_residual_image_gives_the_corrected_noise(scene):
    """An uncorrected residual (XSPBCOR = F) is divided by its beam: the same sigma_k (issue 10,
    item 5: one primary-beam convention, read from the header)."""
    corr = local_noise(scene["resid"], scene["cat"])
    plain = measure_local_noise(scene["plain"], scene["cat"])
    assert plain.pbcor is False and plain.beam is not None
    # sigma/A at the position vs the rms of a corrected stamp, whose pixels each carry their
    # own 1/A (the stamp spans a range of A): equal to a few % (measured up to 6.5 % at A~0.4)
    np.testing.assert_allclose(plain.sigma, corr, rtol=0.08)
    a = stack_uv(scene["ds"], scene["cat"], weighting="sigma2", noise_image=scene["plain"])
    b = stack_uv(scene["ds"], scene["cat"], weighting="sigma2", noise_image=scene["resid"])
    assert a.flux_err_jy == pytest.approx(b.flux_err_jy, rel=0.01)


def test_uncorrected_image_without_a_beam_warns(scene, tmp_path):
    from astropy.io import fits

    with fits.open(scene["plain"]) as h:
        hdu = h[0].copy()
    hdu.header["TELESCOP"] = "NOBODY"
    path = tmp_path / "nobeam.fits"
    hdu.writeto(path)
    with pytest.warns(UserWarning, match="not primary-beam corrected"):
        stack_uv(scene["ds"], scene["cat"], weighting="sigma2", noise_image=path)


def test_positions_in_no_pointing_need_no_estimate(scene):
    cat = Table(scene["cat"], copy=True)
    cat.add_row({"ra": float(cat["ra"][0]), "dec": float(cat["dec"][0]) + 5.0})  # far away
    with pytest.warns(UserWarning, match="lie in no pointing"):
        res = stack_uv(scene["ds"], cat, weighting="sigma2", noise_image=scene["resid"])
    assert res.n_positions == N_POS and np.isnan(res.positions["sigma_local"][-1])


def test_cli_noise_image(scene, capsys):
    out = scene["tmp"] / "cli.zarr"
    rc = main(["uvstack", str(scene["store"]), str(scene["cat_path"]), str(out), "--weighting",
               "sigma2", "--noise-image", str(scene["resid"]), "--json", "--no-progress",
               "--profile-bins", "4"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["options"]["sigma"] == f"local-noise:{scene['resid']}"
    assert doc["n_positions"] == N_POS


# --- (d) bad input --------------------------------------------------------------------------

def _written(tmp, stem):
    return sorted(p.name for p in tmp.iterdir() if p.name.startswith(stem))


@pytest.fixture
def linear_fits(tmp_path):
    h = fits.Header()
    h["CTYPE1"], h["CTYPE2"] = "LINEAR", "LINEAR"
    h["BUNIT"] = "Jy/beam"
    path = tmp_path / "linear.fits"
    fits.PrimaryHDU(np.zeros((64, 64)), header=h).writeto(path)
    return path


def test_api_bad_noise_images(scene, tmp_path, linear_fits):
    out = tmp_path / "bad.zarr"
    with pytest.raises(XstackError, match="celestial WCS"):
        stack_uv(scene["ds"], scene["cat"], weighting="sigma2", noise_image=linear_fits, out=out)
    with pytest.raises(XstackError, match="no such image file"):
        stack_uv(scene["ds"], scene["cat"], weighting="sigma2", noise_image=tmp_path / "x.fits",
                out=out)
    text = tmp_path / "notfits.fits"
    text.write_text("not a FITS file\n")
    with pytest.raises(XstackError, match="cannot read as a FITS image"):
        stack_uv(scene["ds"], scene["cat"], weighting="sigma2", noise_image=text, out=out)
    model = fits.PrimaryHDU(np.zeros((64, 64)), header=_header(64, 64, bunit="Jy/pixel"))
    with pytest.raises(XstackError, match="BUNIT is 'Jy/pixel'"):
        stack_uv(scene["ds"], scene["cat"], weighting="sigma2", noise_image=model, out=out)
    with pytest.raises(XstackError, match="only with weighting='sigma2'"):
        stack_uv(scene["ds"], scene["cat"], weighting="pb", noise_image=scene["resid"], out=out)
    with pytest.raises(XstackError, match="not both"):
        stack_uv(scene["ds"], scene["cat"], weighting="sigma2", sigma=1.0,
                noise_image=scene["resid"], out=out)
    assert not out.exists() and _written(tmp_path, "bad") == []


def test_api_positions_outside_the_image(scene, tmp_path):
    # a residual image covering only the inner 5' of the pointing: outer targets have no sigma_k
    small = make_image(scene["ds"], size=64, cell_arcsec=4.0, pbcor=True)
    with pytest.warns(UserWarning, match="no local-noise estimate") as rec:
        sig = local_noise(small, scene["cat"], on_bad="nan")
    bad = np.flatnonzero(np.isnan(sig))
    assert 0 < bad.size < N_POS and f"row {bad[0] + 1} " in str(rec[0].message)
    with pytest.raises(XstackError, match=rf"row {bad[0] + 1} \(ra=.*outside the image"):
        local_noise(small, scene["cat"])
    out = tmp_path / "outside.zarr"
    with pytest.raises(XstackError, match=rf"{bad.size} of {N_POS} positions: row {bad[0] + 1} "):
        stack_uv(scene["ds"], scene["cat"], weighting="sigma2", noise_image=small, out=out)
    assert not out.exists()


def test_cli_bad_input_writes_nothing(scene, tmp_path, linear_fits, capsys):
    small = make_image(scene["ds"], size=64, cell_arcsec=4.0, pbcor=True)
    small_path = small.write(tmp_path / "small.fits", small.image, kind="residual")
    base = ["uvstack", str(scene["store"]), str(scene["cat_path"])]
    cases = [
        (["--weighting", "sigma2", "--noise-image", str(linear_fits)], "celestial WCS"),
        (["--weighting", "sigma2", "--noise-image", str(tmp_path / "nope.fits")], "no such"),
        (["--weighting", "sigma2", "--noise-image", str(small_path)], "outside the image"),
        (["--weighting", "pb", "--noise-image", str(scene["resid"])], "needs --weighting sigma2"),
    ]
    for i, (extra, msg) in enumerate(cases):
        out = tmp_path / f"o{i}.zarr"
        rc = main([*base, str(out), *extra, "--no-progress"])
        err = capsys.readouterr().err
        # (a warning about the input may come first; the error is the last line)
        assert rc == 1 and err.strip().splitlines()[-1].startswith("error:") and msg in err, \
            (extra, err)
        assert "Traceback" not in err
        assert _written(tmp_path, f"o{i}") == [], extra
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the good run below must not warn
        rc = main([*base, str(tmp_path / "ok.zarr"), "--weighting", "sigma2", "--noise-image",
                   str(scene["resid"]), "--no-progress"])
    assert rc == 0
