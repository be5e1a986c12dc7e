"""Every stage's result speaks one protocol: keyword-only dataclass, ``to_dict`` (JSON-ready),
``write_json`` (atomic, no silent overwrite), ``table`` (astropy Table with units).

The results come from one real chain on a tiny simulation (simulate -> image -> clean ->
stack_uv -> stack_images -> fit_uv -> estimate_noise), so the protocol is checked on what a
user actually gets back, and the numbers in the JSON are checked against the objects.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from _sim_helpers import TINY_SCENE
from astropy.table import Table

import xstack
from xstack._result import Result
from xstack.errors import OutputExistsError


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("protocol")
    scene = tmp / "tiny.toml"
    scene.write_text(TINY_SCENE)
    sim = xstack.simulate(scene, tmp / "sim.zarr", seed=4)
    targets = sim.catalogs["targets"]
    img = xstack.make_image(sim.store, size=64, cell_arcsec=16.0)
    cln = xstack.clean(img.image, img.psf, threshold=0.0, niter=20)
    img_path = tmp / "img.fits"
    img.write(img_path)
    uv = xstack.stack_uv(sim.store, targets, weighting="none", primary_beam="none")
    im = xstack.stack_images(img_path, targets, stamp_size=32, weighting="none",
                             primary_beam="none", plot=False)
    fit = xstack.fit_uv(uv, model="point")
    noise = xstack.estimate_noise(sim.store, targets, method="bootstrap", realizations=5,
                                  seed=1, primary_beam="none")
    return tmp, {"simulate": sim, "image": img, "clean": cln, "stack_uv": uv,
                 "stack_images": im, "fit_uv": fit, "noise": noise}


STAGES = ["simulate", "image", "clean", "stack_uv", "stack_images", "fit_uv", "noise"]


@pytest.mark.parametrize("stage", STAGES)
def test_result_is_a_keyword_only_dataclass_with_the_protocol(chain, stage):
    res = chain[1][stage]
    assert isinstance(res, Result) and dataclasses.is_dataclass(res)
    fields = [f for f in dataclasses.fields(res) if f.init]
    assert fields and all(f.kw_only for f in fields)
    with pytest.raises(TypeError):
        type(res)(*[getattr(res, f.name) for f in fields])  # positional construction refused


@pytest.mark.parametrize("stage", STAGES)
def test_to_dict_is_strict_json_and_write_json_is_atomic(chain, stage):
    tmp, results = chain
    res = results[stage]
    text = json.dumps(res.to_dict(), allow_nan=False)  # no NaN / inf / numpy types left
    path = tmp / f"{stage}.json"
    res.write_json(path)
    assert json.loads(path.read_text()) == json.loads(text)
    before = path.read_bytes()
    with pytest.raises(OutputExistsError):
        res.write_json(path)
    assert path.read_bytes() == before
    res.write_json(path, overwrite=True)
    assert not [p for p in tmp.iterdir() if p.name.startswith(f".{stage}.json.partial")]


@pytest.mark.parametrize("stage", STAGES)
def test_table_is_an_astropy_table_with_units(chain, stage):
    t = chain[1][stage].table()
    assert isinstance(t, Table) and len(t) >= 1
    for name in t.colnames:
        if name.endswith("_jy") and t[name].dtype.kind == "f" and stage not in ("stack_uv",):
            assert t[name].unit is not None and "Jy" in str(t[name].unit), name


def test_numbers_agree_across_the_protocol(chain):
    _, r = chain
    uv, im, fit, noise = r["stack_uv"], r["stack_images"], r["fit_uv"], r["noise"]
    assert uv.to_dict()["flux_jy"] == uv.flux_jy
    assert len(uv.table()) == len(r["simulate"].catalogs["targets"])
    assert int(np.sum(uv.table()["n_pointings"] > 0)) == uv.n_positions
    # one image-stack row per stamp, and the stack is their mean at the center (weighting none)
    t = im.table()
    assert len(t) == im.n_stamps
    assert np.nanmean(t["center_jy"]) == pytest.approx(im.flux_jy, rel=1e-9)
    from xstack.fit.uvfit import UvFitOptions

    assert fit.options == UvFitOptions(model="point").to_dict() == fit.to_dict()["options"]
    assert uv.options["weighting"] == "none" and noise.options["method"] == "bootstrap"
    ft = fit.table()
    assert list(ft["parameter"]) == list(fit.parameters)
    assert ft["error"][list(ft["parameter"]).index("flux_jy")] == pytest.approx(fit.flux_err_jy)
    nt = noise.table()
    assert np.std(nt["flux_jy"], ddof=1) == pytest.approx(noise.noise_jy)
    s = r["simulate"].to_dict()
    assert s["catalogs"]["targets"]["n_sources"] == 3 and s["seed"] == 4
    i = r["image"].to_dict()
    assert i["shape"] == [64, 64] and math.isclose(i["cell_arcsec"], 16.0)
    c = r["clean"].table()
    assert c["n_components"][0] == r["clean"].n_components
