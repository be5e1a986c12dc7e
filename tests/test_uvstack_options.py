"""stack_uv split into validate -> plan -> compute -> assemble, options as a frozen dataclass
(issue 11 item 9).

Truth from outside the code under test: the option values the caller passed (the result
records them), the uv limits written out by hand, the old code's numbers for one stack
(recorded before the split, bit-for-bit on the machine that ran both), and a VISIBILITY
that raises when computed (the plan must not touch it).
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import json
import textwrap

import dask.array as da
import numpy as np
import pytest
import xarray as xr
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.table import Table
from dask.callbacks import Callback

from xstack.errors import OptionError
from xstack.uvstack import UvstackOptions
from xstack.uvstack import stack as st

RA0, DEC0 = VLA_CENTER
SOURCES = [(RA0 + 1e-4, DEC0 - 5e-5, 2.0), (RA0 - 3e-4, DEC0 + 2e-4, 1.0)]


@pytest.fixture(scope="module")
def tree():
    p1 = make_stack_partition(sources=SOURCES, sigma=0.5, seed=1, flag_frac=0.05)
    p2 = make_stack_partition(sources=SOURCES, sigma=0.7, seed=2, field_id=1,
                              phase_center=(RA0 + 2e-4, DEC0))
    return xr.DataTree.from_dict({"p1": p1, "p2": p2})


@pytest.fixture(scope="module")
def cat():
    # the third row lies 0.5 rad away: in no pointing
    return Table({"ra": np.degrees([s[0] for s in SOURCES] + [RA0 + 0.5]),
                  "dec": np.degrees([s[1] for s in SOURCES] + [DEC0]),
                  "sigma": [1.0, 2.0, 1.5], "weight": [1.0, 3.0, 2.0]})


# --- (a) validation before any input is opened ---------------------------------------------

BAD = [
    ("weighting", dict(weighting="bogus")),
    ("engine", dict(engine="fast")),
    ("smearing", dict(smearing="bogus")),
    ("pb_cutoff", dict(pb_cutoff=1.0)),
    ("pb_cutoff", dict(pb_cutoff=-0.1)),
    ("pb_cutoff", dict(pb_cutoff="high")),
    ("uvmin", dict(uvmin="abc")),
    ("uvmax", dict(uvmax="5 furlongs")),
    ("uvmin", dict(uvmin="5km", uvmax="100m")),
    ("primary_beam", dict(primary_beam="cosine")),
    ("noise_image", dict(noise_image="residual.fits")),
    ("sigma", dict(weighting="sigma2", sigma=1.0, noise_image="residual.fits")),
    ("sigma", dict(weighting="sigma2", sigma="abc")),
    ("antenna_tol_rad", dict(antenna_tol_rad=-1.0)),
    ("antenna_tol_rad", dict(antenna_tol_rad=float("nan"))),
    ("polarizations", dict(polarizations=[])),
]


@pytest.mark.parametrize(("name", "kwargs"), BAD, ids=[f"{n}-{i}" for i, (n, _) in enumerate(BAD)])
def test_bad_option_is_an_option_error_before_any_input_is_read(tmp_path, name, kwargs):
    missing = tmp_path / "no-such.zarr"
    with pytest.raises(OptionError) as info:
        UvstackOptions(**kwargs)
    options = info.value.option if isinstance(info.value.option, tuple) else (info.value.option,)
    assert name in options
    assert name in str(info.value) and "\n" not in str(info.value)
    # the entry point: the same error although neither the data nor the catalog exists
    with pytest.raises(OptionError) as info2:
        st.stack_uv(missing, tmp_path / "no-such.ecsv", **kwargs)
    assert str(info2.value) == str(info.value)
    assert isinstance(info2.value, ValueError)


def test_options_are_frozen_and_carry_derived_uv_limits():
    opts = UvstackOptions(uvmin="500m", uvmax="20klambda", polarizations="RR, LL")
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.weighting = "none"  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.uv_lo = None  # type: ignore[misc]
    # written out by hand: 500 metres, 20 000 wavelengths
    assert opts.uv_lo == (500.0, "m")
    assert opts.uv_hi == pytest.approx((20000.0, "lambda")) and opts.uv_hi[1] == "lambda"
    assert opts.polarizations == ("RR", "LL")
    # every keyword of stack_uv is a field with the same default (one list of options)
    params = inspect.signature(st.stack_uv).parameters
    fields = {f.name: f.default for f in dataclasses.fields(UvstackOptions) if f.init}
    keywords = {k: p.default for k, p in params.items() if p.kind is p.KEYWORD_ONLY}
    assert keywords.pop("compute") is True  # when the pass runs, not how: no stack option
    assert fields == keywords
    assert UvstackOptions() == UvstackOptions(weighting="pb")
    json.dumps(opts.to_dict())


def test_sigma_of_the_wrong_length_is_an_option_error(tree, cat):
    with pytest.raises(OptionError, match="sigma") as info:
        st.stack_uv(tree, cat, weighting="sigma2", sigma=[1.0, 2.0])
    assert info.value.option == "sigma"


# --- (b) options round trip ---------------------------------------------------------------

EXTRAS = {"smearing_corrected", "sigma", "stack_center_deg", "engine_rows"}


@pytest.mark.parametrize("kwargs", [
    dict(),
    dict(weighting="column", uvmin="500m", uvmax="20klambda", polarizations="all",
         engine="numba", pb_cutoff=0.2, primary_beam="gaussian"),
    dict(weighting="sigma2", sigma=[1.0, 2.0, 3.0], polarizations=["RR"]),
])
def test_result_options_are_the_options_plus_what_was_measured(tree, cat, tmp_path, kwargs):
    out = tmp_path / "s.zarr"
    with pytest.warns(UserWarning, match="in no pointing"):
        res = st.stack_uv(tree, cat, out=out, **kwargs)
    given = UvstackOptions(**kwargs).to_dict()
    assert set(res.options) == set(given) | EXTRAS
    assert {k: res.options[k] for k in given if k != "engine"} == \
        {k: v for k, v in given.items() if k != "engine"}
    # the requested engine, or the one that ran
    want_engine = "numba" if kwargs.get("engine") == "numba" else "antenna"
    assert res.options["engine"] == want_engine
    assert res.options["engine_rows"] == {want_engine: 2 * 20 * 28}  # 2 x time x baselines
    assert res.options["sigma"] == ("given" if "sigma" in kwargs else None)
    assert res.options["smearing_corrected"] == []
    # the documented order (the JSON written is the same as before the split)
    assert list(res.options) == ["weighting", "primary_beam", "pb_cutoff", "uvmin", "uvmax",
                                 "polarizations", "autocorrelations", "smearing",
                                 "smearing_corrected", "engine", "sigma", "stack_center_deg",
                                 "engine_rows"]
    assert json.loads(json.dumps(res.to_dict()))["options"] == res.options
    # each stacked partition records the options as planned (the requested engine)
    for ds in res.stacked.values():
        rec = ds.attrs["uvstack_options"]
        assert rec == {**{k: v for k, v in res.options.items() if k != "engine_rows"},
                       "engine": given["engine"]}


def test_numbers_are_those_of_the_code_before_the_split(tree, cat):
    """Recorded with the single-function stack_uv (HEAD 8071987) on the same inputs."""
    with pytest.warns(UserWarning, match="in no pointing") as rec:
        res = st.stack_uv(tree, cat)
    assert res.flux_jy == pytest.approx(1.679279430434432, rel=1e-12)
    assert res.flux_err_jy == pytest.approx(0.004638365603330544, rel=1e-12)
    assert res.n_visibilities > 0 and res.n_positions == 2 and len(res.uncovered) == 1
    # the warning points at the caller, through the phase functions
    assert rec[0].filename == __file__
    with pytest.warns(UserWarning, match="in no pointing"):
        col = st.stack_uv(tree, cat, weighting="column", uvmin="500m", uvmax="20klambda")
    assert col.flux_jy == pytest.approx(1.4714221642124807, rel=1e-12)
    assert col.flux_err_jy == pytest.approx(0.0052362091576423206, rel=1e-12)


def test_assemble_warning_points_at_the_caller(cat):
    ds = make_stack_partition(sources=SOURCES, sigma=0.5, seed=1)
    ds["WEIGHT"] = ds["WEIGHT"] * np.float32(4.0)  # claims half the true noise
    with pytest.warns(UserWarning, match="weights are mis-scaled") as rec:
        res = st.stack_uv({"p": ds}, cat[:2])
    assert res.weight_scale == pytest.approx(4.0, rel=0.1)
    assert [w.filename for w in rec] == [__file__]


@pytest.mark.filterwarnings("ignore:.*in no pointing")
def test_polarization_names_as_one_string(tree, cat):
    """``"RR,LL"`` is the list of names (it used to be read letter by letter: an error)."""
    both = st.stack_uv(tree, cat, polarizations="RR,LL")
    listed = st.stack_uv(tree, cat, polarizations=["RR", "LL"])
    assert both.flux_jy == listed.flux_jy
    assert both.options["polarizations"] == ["RR", "LL"]
    one = st.stack_uv(tree, cat, polarizations="RR")
    assert one.n_visibilities < both.n_visibilities


# --- (c) the plan reads no visibility ------------------------------------------------------

class _Computed(RuntimeError):
    pass


def _explode(block):
    raise _Computed("VISIBILITY was computed")


def test_plan_computes_no_data(cat):
    ds = make_stack_partition(sources=SOURCES, sigma=0.5, seed=1)
    vis = ds["VISIBILITY"]
    lazy = da.zeros(vis.shape, dtype=vis.dtype, chunks=(5, -1, -1, -1)).map_blocks(
        _explode, dtype=vis.dtype)
    ds = ds.assign(VISIBILITY=(vis.dims, lazy, vis.attrs))
    options = UvstackOptions(smearing="none")
    tasks: list = []
    with Callback(pretask=lambda key, dsk, state: tasks.append(key)):
        inputs = st._load({"p": ds}, cat[:2], options)
        plan = st._plan(inputs, options)
    assert tasks == []
    assert [p.name for p in plan.active] == ["p"]
    assert plan.used.tolist() == [True, True]
    with pytest.raises(_Computed):
        st._compute(plan, options)


# --- (d) the entry point stays a table of contents -----------------------------------------

def _code_lines(func) -> int:
    """Source lines of ``func`` without its docstring."""
    src = textwrap.dedent(inspect.getsource(func))
    node = ast.parse(src).body[0]
    doc = node.body[0]
    skip = doc.end_lineno - doc.lineno + 1 if isinstance(doc, ast.Expr) and \
        isinstance(doc.value, ast.Constant) and isinstance(doc.value.value, str) else 0
    return len(src.splitlines()) - skip


def test_entry_point_and_phases_stay_short():
    assert _code_lines(st.stack_uv) <= 25
    for phase in (st._load, st._position_sigma, st._plan, st._plan_partition, st._compute,
                  st._measure, st._stacked_dataset, st._assemble, UvstackOptions.__post_init__):
        assert len(inspect.getsource(phase).splitlines()) <= 120, phase.__name__
        assert phase.__doc__ or phase is UvstackOptions.__post_init__, phase.__name__
