"""estimate_noise as validate -> plan -> compute -> assemble (issue 11 item 9).

Options are a frozen dataclass checked before any data are read, the result carries them
back, the plan reads no visibility, and the entry function stays a table of contents.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import json

import numpy as np
import pytest
from _fit_helpers import noise_field
from astropy.table import Table

from xstack.beams import PrimaryBeam
from xstack.errors import OptionError, XstackError
from xstack.noise import NoiseOptions, estimate_noise
from xstack.noise import estimate as estimate_module
from xstack.noise import image as image_module
from xstack.noise.positions import random_positions

CENTER = (1.0, -0.5236)
MISSING = "/nonexistent/xstack-noise-options/data.zarr"
# few targets on purpose (fast): the hull-region warning about it is expected
pytestmark = pytest.mark.filterwarnings("ignore:only .* targets:UserWarning")


def _targets(n=6, seed=0):
    ra, dec = random_positions(n, 1, np.array([CENTER]), np.array([np.radians(8 / 60)]),
                               avoid_ra=np.zeros(0), avoid_dec=np.zeros(0),
                               min_separation=np.radians(60 / 3600),
                               rng=np.random.default_rng(seed))
    return np.degrees(ra[0]), np.degrees(dec[0])


BAD = [
    ({"method": "jackknife"}, "method"),
    ({"domain": "radio"}, "domain"),
    ({"weighting": "loud"}, "weighting"),
    ({"engine": "gpu"}, "engine"),
    ({"realizations": 1}, "realizations"),
    ({"realizations": "many"}, "realizations"),
    ({"realizations": 2.5}, "realizations"),
    ({"seed": "abc"}, "seed"),
    ({"profile_bins": -1}, "profile_bins"),
    ({"pb_cutoff": 1.5}, "pb_cutoff"),
    ({"antenna_tol_rad": 0.0}, "antenna_tol_rad"),
    ({"min_separation_arcsec": -1.0}, "min_separation_arcsec"),
    ({"field_radius_arcsec": 0.0}, "field_radius_arcsec"),
    ({"flux": "5 parsec"}, "flux"),
    ({"uvmin": "ten metres"}, "uvmin"),
    ({"uvmax": "3 seconds"}, "uvmax"),
    ({"uvmin": "10klambda", "uvmax": "1klambda"}, ("uvmin", "uvmax")),
    ({"primary_beam": "bessel"}, "primary_beam"),
    ({"domain": "image", "region": "beam"}, "region"),
    ({"image_corrected": "yes"}, "image_corrected"),
]


@pytest.mark.parametrize(("bad", "name"), BAD, ids=[str(b) for b, _ in BAD])
def test_bad_option_is_refused_before_the_data_are_opened(bad, name):
    # the data path does not exist: an OptionError proves the check came first
    with pytest.raises(OptionError) as info:
        estimate_noise(MISSING, ([150.0], [2.0]), **bad)
    assert info.value.option == name
    assert "\n" not in str(info.value)
    with pytest.raises(OptionError):
        NoiseOptions(**bad)


def test_good_options_reach_the_missing_data():
    """Control of the test above: valid options get as far as opening the data."""
    with pytest.raises(XstackError, match="no such store") as info:
        estimate_noise(MISSING, ([150.0], [2.0]), method="analytic", uvmin="1klambda")
    assert not isinstance(info.value, OptionError)


def test_options_are_frozen_and_normalized():
    opts = NoiseOptions(realizations="7", flux="2mJy", seed=np.int64(3), pb_cutoff="0.2",
                        uvmin="500m", uvmax="20klambda", min_separation_arcsec=10)
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.method = "random"
    assert opts.realizations == 7 and type(opts.realizations) is int
    assert opts.flux == pytest.approx(2e-3) and opts.seed == 3 and opts.pb_cutoff == 0.2
    assert opts.uv_range == ((500.0, "m"), (20e3, "lambda"))
    assert opts.min_separation_arcsec == 10.0
    # every keyword of estimate_noise is a field, with the same default
    params = inspect.signature(estimate_noise).parameters
    init_fields = {f.name: f for f in dataclasses.fields(NoiseOptions) if f.init}
    kwargs = {k: p for k, p in params.items() if p.kind is p.KEYWORD_ONLY}
    assert set(kwargs) == set(init_fields)
    for k, p in kwargs.items():
        assert init_fields[k].default == p.default, k


def test_to_dict_is_json_ready():
    cat = Table({"ra": [150.0, 150.1], "dec": [2.0, 2.1]})
    opts = NoiseOptions(avoid=cat, primary_beam=PrimaryBeam("gaussian", 25.0),
                        flux=np.array([1e-3, 2e-3]), uvmin=5000)
    d = opts.to_dict()
    assert json.loads(json.dumps(d)) == d
    assert d["avoid"] == "table of 2 rows" and d["primary_beam"] == "gaussian"
    assert d["flux"] == [1e-3, 2e-3] and d["uvmin"] == "5000" and "progress" not in d


@pytest.fixture(scope="module")
def field():
    ds, _, _ = noise_field(1, n_ant=6, n_time=4, extent_m=20e3)
    return ds


@pytest.mark.parametrize("method", ["analytic", "bootstrap", "random", "mc"])
def test_result_options_round_trip(field, method, tmp_path):
    kw = dict(method=method, realizations=4, seed=2, uvmax="200klambda")
    if method == "mc":
        kw["flux"] = "1mJy"
    res = estimate_noise(field, _targets(), **kw)
    expected = NoiseOptions(**kw).to_dict()
    if method in ("mc", "random"):  # what the run decided: the default separation, the engine
        expected["min_separation_arcsec"] = res.extra["min_separation_arcsec"]
        expected["engine"] = res.extra["engine"]
        assert expected["engine"] in ("antenna", "numba", "mixed")
    assert res.options == expected
    assert json.loads(res.write_json(tmp_path / "n.json").read_text())["options"] == expected
    # no private keys travel in the result
    assert not [k for k in res.to_dict() if k.startswith("_")]
    assert not [k for k in res.extra if k.startswith("_")]


class _Unreadable(Exception):
    pass


def test_plan_reads_no_visibility(field):
    """load + plan run on data whose VISIBILITY cannot be computed; compute then reads it."""
    da = pytest.importorskip("dask.array")

    def refuse(block):
        raise _Unreadable("VISIBILITY was computed")

    vis = field["VISIBILITY"]
    lazy = da.from_array(vis.values, chunks=vis.shape).map_blocks(refuse, dtype=vis.dtype)
    ds = field.assign(VISIBILITY=(vis.dims, lazy, vis.attrs))
    for method in ("mc", "random", "bootstrap", "analytic"):
        opts = NoiseOptions(method=method, realizations=3, profile_bins=2)
        inputs = estimate_module._load(ds, _targets(), opts)
        plan = estimate_module._plan(inputs, opts)
        assert plan.sizes.size == (4 if method in ("mc", "random") else 1)
        with pytest.raises(_Unreadable):
            estimate_module._compute(inputs, plan, opts)


def _code_lines(func) -> int:
    """Lines of a function after its signature and docstring."""
    node = ast.parse(inspect.getsource(func).lstrip()).body[0]
    body = node.body[1:] if ast.get_docstring(node) else node.body
    return node.end_lineno - body[0].lineno + 1


def test_entry_point_reads_like_a_table_of_contents():
    assert _code_lines(estimate_noise) <= 30
    assert _code_lines(image_module.estimate_noise_image) <= 10
    for module in (estimate_module, image_module):
        for name, func in inspect.getmembers(module, inspect.isfunction):
            if func.__module__ == module.__name__:
                assert len(inspect.getsource(func).splitlines()) <= 120, name
