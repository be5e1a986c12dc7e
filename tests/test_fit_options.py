"""The fit stage's options as frozen dataclasses and its entry points split into phases
(issue 11 item 9): options validated before any data is read, recorded in the result as
given, numbers unchanged by the split (the pre-split code's values), entry points short."""

from __future__ import annotations

import dataclasses
import inspect
import warnings

import numpy as np
import pytest
from _fit_helpers import StampSimulator, gaussian_stack, write_stamp_fits

from xstack.errors import OptionError
from xstack.fit import ImageFitOptions, UvFitOptions, fit_image, fit_uv, imfit, uvfit

MISSING = "/nonexistent/xstack-fit-options/stacked"


@pytest.fixture(scope="module")
def sim():
    return StampSimulator()


@pytest.fixture(scope="module")
def stamp(sim):
    return sim.stamp(1.0, 1.5, 7)


@pytest.fixture(scope="module")
def stacked():
    return gaussian_stack(1e-3, 1.5, 1e-3, seed=5, n_time=10)


# --- (a) frozen, validated, before the data path is opened -------------------------------

BAD_IMAGE = [("model", "disk"), ("model", None), ("noise_correlation", "white"),
             ("pixel_arcsec", -0.5), ("pixel_arcsec", (0.5, 0.0)), ("pixel_arcsec", (0.5,) * 3),
             ("pixel_arcsec", "0.5"), ("center", (16.5, 16)), ("center", (16,)),
             ("center", 16), ("fit_radius_arcsec", 0.0), ("fit_radius_arcsec", float("nan")),
             ("background", "no"), ("sigma_jy", -1e-3), ("sigma_jy", float("inf")),
             ("normalize_psf", "yes")]
BAD_UV = [("model", "disk"), ("binned", "yes"), ("rescale_errors", 0), ("nbins", 2.5),
          ("uvmin", "5 parsecs"), ("uvmax", float("nan"))]


@pytest.mark.parametrize(("name", "value"), BAD_IMAGE)
def test_fit_image_bad_option_before_reading(name, value):
    with pytest.raises(OptionError, match=name) as err:
        fit_image(MISSING + ".fits", **{name: value})
    assert err.value.option == name
    assert "\n" not in str(err.value)
    with pytest.raises(OptionError, match=name):
        ImageFitOptions(**{name: value})


@pytest.mark.parametrize(("name", "value"), BAD_UV + [("nbins", 2)])
def test_fit_uv_bad_option_before_reading(name, value):
    kwargs = {name: value} | ({"binned": True} if name == "nbins" else {})
    with pytest.raises(OptionError, match=name) as err:
        fit_uv(MISSING + ".zarr", **kwargs)
    assert err.value.option == name
    assert "\n" not in str(err.value)


def test_options_are_frozen_and_normalized():
    opts = ImageFitOptions(pixel_arcsec=0.5, center=(np.int64(16), 17.0))
    assert opts.pixel_arcsec == (0.5, 0.5) and opts.center == (16, 17)
    assert type(opts.center[1]) is int
    assert opts.n_parameters == 3
    assert ImageFitOptions(model="point", background=False).n_parameters == 1
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.model = "point"
    uv = UvFitOptions(uvmin="5km", uvmax=80e3)
    assert uv.uv_limits == ((5000.0, "m"), (80000.0, "m"))
    with pytest.raises(dataclasses.FrozenInstanceError):
        uv.nbins = 3
    with pytest.raises(TypeError):
        UvFitOptions("point")  # keyword-only, like the entry points
    # the defaults are those of the entry points
    for cls, fn in ((ImageFitOptions, fit_image), (UvFitOptions, fit_uv)):
        sig = inspect.signature(fn).parameters
        for f in dataclasses.fields(cls):
            if f.init:
                assert sig[f.name].default == f.default, (cls.__name__, f.name)


# --- (b) the options recorded in the result -----------------------------------------------

def test_image_result_records_options(sim, stamp):
    kwargs = dict(pixel_arcsec=0.5, noise_correlation="residual", fit_radius_arcsec=6.0,
                  sigma_jy=None)
    res = fit_image(stamp, psf=sim.psf, **kwargs).to_dict()
    opts = ImageFitOptions(**kwargs).to_dict()
    assert {k: res[k] for k in ("model", "noise_correlation", "pixel_arcsec")} == \
        {k: opts[k] for k in ("model", "noise_correlation", "pixel_arcsec")}
    # the measured extras: the center the fit used (the stamp's middle by default)
    assert opts["center"] is None and res["center_pixel"] == [16, 16]


def test_image_result_records_fits_geometry(tmp_path, sim, stamp):
    path = tmp_path / "stamp.fits"
    write_stamp_fits(sim, stamp, path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = fit_image(path, model="point", center=(15, 16))
    # the missing-STPBCOR warning still points at the caller, not into xstack
    assert [w.filename for w in caught] == [__file__]
    opts = ImageFitOptions(model="point", center=(15, 16)).to_dict()
    out = res.to_dict()
    assert out["model"] == opts["model"] and out["center_pixel"] == opts["center"]
    assert opts["pixel_arcsec"] is None and out["pixel_arcsec"] == pytest.approx([0.5, 0.5])


def test_uv_result_records_options(stacked):
    kwargs = dict(model="gaussian", uvmin="2000m", uvmax=60e3, binned=True, nbins=12)
    res = fit_uv(stacked, **kwargs).to_dict()
    opts = UvFitOptions(**kwargs).to_dict()
    for key in ("model", "uvmin", "uvmax", "binned"):
        assert res[key] == opts[key], key
    assert opts["uvmax"] == "60000.0" and opts["nbins"] == len(res["profile"]["re_jy"])


# --- the split changed no number: values of the code before it ---------------------------

def test_numbers_unchanged_by_the_split(sim, stamp, stacked):
    r = fit_image(stamp, psf=sim.psf, pixel_arcsec=0.5, noise_correlation="residual",
                  fit_radius_arcsec=6.0)
    assert r.values.tolist() == pytest.approx(
        [0.9268619921388163, 2.2437257447916674, -0.0009342028636407599], rel=1e-10)
    assert r.flux_err_jy == pytest.approx(0.04369040371674144, rel=1e-10)
    assert r.fwhm_err_arcsec == pytest.approx(0.13466331825652755, rel=1e-10)
    assert r.chi2 == pytest.approx(399.98398612978696, rel=1e-10)
    g = fit_uv(stacked, model="gaussian")
    assert g.values.tolist() == pytest.approx([0.0010159870781561327, 2.020930765521601],
                                              rel=1e-10)
    assert g.flux_err_jy == pytest.approx(1.924533742971155e-05, rel=1e-10)
    assert g.chi2 == pytest.approx(10700.823759023437, rel=1e-10)
    b = fit_uv(stacked, model="gaussian", binned=True, nbins=12)
    assert b.flux_jy == pytest.approx(0.0010168720035531255, rel=1e-10)
    assert b.fwhm_err_arcsec == pytest.approx(0.06083255394666031, rel=1e-10)


# --- (d) the entry points read like a table of contents ----------------------------------

def _lines(fn) -> int:
    return len(inspect.getsource(fn).splitlines())


@pytest.mark.parametrize("fn", [fit_image, fit_uv])
def test_entry_points_stay_short(fn):
    assert _lines(fn) <= 60


@pytest.mark.parametrize("fn", [imfit._load, imfit._plan, imfit._compute,
                                imfit._correlated_jacobian, imfit._assemble, uvfit._compute,
                                uvfit._assemble])
def test_phases_stay_short(fn):
    assert fn.__doc__ and _lines(fn) <= 120
