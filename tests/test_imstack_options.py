"""stack_images as validate -> plan -> compute -> assemble, its options an ImstackOptions.

Truth from outside the code under test: the keyword defaults of the public signature, the
parameters passed, a path that does not exist, and the numbers of the code before the split.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import json
import textwrap

import numpy as np
import pytest
from _imstack_helpers import make_field

from xstack.errors import OptionError, XstackError
from xstack.imstack.stack import stack_images

MISSING = "/nonexistent/dir/image.fits"
MISSING_CATALOG = "/nonexistent/dir/targets.ecsv"

#: (bad keyword options, the parameter the error must name)
BAD = [
    ({"method": "mode"}, "method"),
    ({"weighting": "optimal"}, "weighting"),
    ({"subpixel": "cubic"}, "subpixel"),
    ({"subpixel": True}, "subpixel"),
    ({"stamp_size": 4}, "stamp_size"),
    ({"stamp_size": 10.5}, "stamp_size"),
    ({"stamp_size": True}, "stamp_size"),
    ({"stamp_size": "big"}, "stamp_size"),
    ({"cube_format": "hdf5"}, "cube_format"),
    ({"pbcor": True, "image_corrected": True}, "pbcor"),
    ({"pbcor": True, "image_corrected": [False, True]}, "image_corrected"),
    ({"beam_mask_arcsec": 0.0}, "beam_mask_arcsec"),
    ({"beam_mask_arcsec": -2.0}, "beam_mask_arcsec"),
    ({"beam_mask_arcsec": float("nan")}, "beam_mask_arcsec"),
    ({"beam_mask_arcsec": "wide"}, "beam_mask_arcsec"),
    ({"filter_lowfreq": 2}, "filter_lowfreq"),
    ({"filter_lowfreq": 0}, "filter_lowfreq"),
    ({"filter_lowfreq": 65}, "filter_lowfreq"),          # not smaller than the 64-pixel stamp
    ({"filter_lowfreq": 9, "stamp_size": 9}, "filter_lowfreq"),
    ({"filter_lowfreq": "20 furlongs"}, "filter_lowfreq"),
]


def _options_class():
    # imported here so that, on code without the class, the stack_images tests still run
    from xstack.imstack import ImstackOptions

    return ImstackOptions


def _signature_defaults() -> dict:
    """The keyword options of the public entry point and their defaults."""
    params = inspect.signature(stack_images).parameters.values()
    return {p.name: p.default for p in params if p.kind is inspect.Parameter.KEYWORD_ONLY}


# ---- (a) frozen, validated, before any input is read ------------------------------------------

@pytest.mark.parametrize(("kwargs", "name"), BAD)
def test_bad_option_is_an_option_error_naming_the_parameter(kwargs, name):
    with pytest.raises(OptionError) as exc:
        _options_class()(**kwargs)
    assert name in str(exc.value)
    assert "\n" not in str(exc.value)
    option = exc.value.option
    assert name == option or name in option  # the CLI translates it into its flag


@pytest.mark.parametrize(("kwargs", "name"), BAD)
def test_bad_option_fails_before_the_inputs_are_opened(kwargs, name):
    with pytest.raises(OptionError) as exc:
        stack_images(MISSING, MISSING_CATALOG, **kwargs)
    assert name in str(exc.value)
    assert "nonexistent" not in str(exc.value)


def test_good_options_do_reach_the_inputs():
    # the control for the test above: the same call with good options fails on the paths
    with pytest.raises(XstackError) as exc:
        stack_images(MISSING, MISSING_CATALOG, stamp_size=16, filter_lowfreq=3)
    assert not isinstance(exc.value, OptionError)
    assert "nonexistent" in str(exc.value)


def test_options_are_frozen_and_hold_exactly_the_entry_points_keywords():
    cls = _options_class()
    opts = cls()
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.method = "median"  # type: ignore[misc]
    with pytest.raises(TypeError):
        cls(64)  # keyword-only, like stack_images
    init = {f.name: f.default for f in dataclasses.fields(cls) if f.init}
    assert init == _signature_defaults()


def test_derived_values_are_fields_not_private_keys():
    cls = _options_class()
    assert cls(subpixel="nearest").subpixel is False
    assert cls(subpixel=None).subpixel is False
    assert cls(stamp_size=np.int64(32)).stamp_size == 32
    assert type(cls(stamp_size=32.0).stamp_size) is int
    assert cls(filter_lowfreq=3).filter_cells == 3 and cls(filter_lowfreq=3).filter_uv is None
    # 20 klambda = 20000 wavelengths; 4.5 km = 4500 m
    assert cls(filter_lowfreq="20klambda").filter_uv == pytest.approx((20000.0, "lambda"))
    assert cls(filter_lowfreq="4.5km").filter_uv[0] == pytest.approx(4500.0)
    assert cls(filter_lowfreq="4.5km").filter_uv[1] == "m"
    assert cls().filter_cells is None and cls().filter_uv is None
    assert cls(pbcor=True).corrected is False
    assert cls(image_corrected=[True, None]).corrected == [True, None]
    assert cls().output_paths() is None
    paths = cls(out="/x/stack.fits", plot=False, cube_format="fits").output_paths()
    assert {k: str(v) for k, v in paths.items()} == {"fits": "/x/stack.fits",
                                                     "cube": "/x/stack.cube.fits"}
    assert not any(k.startswith("_") for k in cls().to_dict())


# ---- (b) the result's options: the dataclass's, plus what was measured ------------------------

@pytest.fixture(scope="module")
def field_path(tmp_path_factory):
    rng = np.random.default_rng(12)
    path, ra, dec, _, _ = make_field(tmp_path_factory.mktemp("opts"), rng, 0.5, beam=(3.2, 1.6, 0.0),
                                     name="f.fits", psf=True, n_side=8)
    return path, np.c_[ra, dec]


def test_result_options_round_trip(field_path):
    from xstack.beams import PrimaryBeam

    path, pos = field_path
    kwargs = {"stamp_size": 24, "method": "median", "weighting": "none", "subpixel": "nearest",
              "primary_beam": PrimaryBeam("airy", dish_diameter=25.0), "image_corrected": True,
              "beam_mask_arcsec": 2.5, "filter_lowfreq": 3, "progress": False}
    res = stack_images(path, pos, **kwargs)
    expected = dict(_signature_defaults(), **kwargs)
    expected["subpixel"] = False  # "nearest" is the default alignment, spelled False
    expected["primary_beam"] = {"type": "PrimaryBeam", "model": "airy", "dish_diameter": 25.0,
                                "blockage_diameter": 0.0, "cutoff": 0.1}
    opts = _options_class()(**kwargs).to_dict()
    assert opts == expected
    assert res.options == {**opts, "n_images": 1, "mask_radius_arcsec": 2.5}
    payload = json.loads(json.dumps(res.to_dict(), allow_nan=False))
    assert payload["options"] == res.options
    # what the options say is what ran
    assert res.method == "median" and res.mask_radius_arcsec == 2.5
    assert res.stacked.shape == (24, 24)


def test_options_describe_arrays_and_objects():
    cls = _options_class()
    d = cls(primary_beam=np.ones((10, 12)), psf=[None, "p.psf.fits"]).to_dict()
    assert d["primary_beam"] == "array 10x12"
    assert d["psf"] == [None, "p.psf.fits"]
    json.dumps(d, allow_nan=False)


@pytest.mark.filterwarnings("ignore::xstack.errors.XstackWarning")  # no XSPBCOR: as is
def test_numbers_are_those_of_the_code_before_the_split(field_path):
    # recorded with the code before the split (commit 8071987) on this field, whose sigma_k
    # was the plain std on the stamp itself: still there as noise_estimator="std" with
    # noise_stamp_size = stamp_size
    path, pos = field_path
    old = {"noise_estimator": "std", "noise_stamp_size": 32}
    res = stack_images(path, pos, stamp_size=32, **old)
    assert res.flux_jy == pytest.approx(0.966562194188727, rel=1e-12)
    assert res.flux_err_jy == pytest.approx(0.004534809533223295, rel=1e-12)
    res = stack_images(path, pos, stamp_size=32, subpixel="fourier", weighting="none", **old)
    assert res.flux_jy == pytest.approx(0.9983982569434138, rel=1e-12)
    assert res.flux_err_jy == pytest.approx(0.005240659509830136, rel=1e-12)
    res = stack_images(path, pos, stamp_size=32, filter_lowfreq=3, beam_mask_arcsec=4.0, **old)
    # the filtered peak and its error as recorded then; since the filter response (the stacked
    # PSF's filtered / unfiltered peak) divides both, flux_jy is a flux again (~1.0 here)
    assert res.flux_jy * res.filter_response == pytest.approx(0.7991689397730652, rel=1e-12)
    assert res.flux_err_jy * res.filter_response == pytest.approx(0.004668716521228087, rel=1e-12)
    assert res.flux_jy == pytest.approx(0.9829727652060197, rel=1e-12)


# ---- (c) imstack is eager numpy: no lazy plan phase to test -----------------------------------

# ---- (d) the entry point stays a table of contents --------------------------------------------

def _code_lines(func) -> int:
    """Lines of ``func``'s source without its docstring."""
    src = textwrap.dedent(inspect.getsource(func))
    node = ast.parse(src).body[0]
    doc = node.body[0]
    n_doc = doc.end_lineno - doc.lineno + 1 if isinstance(doc, ast.Expr) and isinstance(
        getattr(doc, "value", None), ast.Constant) else 0
    return len(src.splitlines()) - n_doc


def test_entry_point_is_short_and_phases_are_bounded():
    from xstack.imstack import stack

    # signature (7) + building the options (6) + the phases (7): the parameters are
    # documented in its docstring, which is not counted
    assert _code_lines(stack.stack_images) <= 30
    for name in ("_load", "_plan", "_coverage", "_cut_stamps", "_weights", "_compute",
                 "_assemble", "_save"):
        assert len(inspect.getsource(getattr(stack, name)).splitlines()) <= 120, name
