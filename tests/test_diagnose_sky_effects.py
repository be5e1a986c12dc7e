"""The scene variants of ``benchmarks/diagnose_sky_effects.py`` (nothing is simulated): what
each variant takes out of a paper preset, and the integration override of the CASA
comparison, against the preset itself."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from _bench_helpers import load_benchmark
from astropy.io import fits

import xstack


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("diagnose_sky_effects")


def _by_name(scene):
    return {p.name: p for p in scene.populations}


@pytest.mark.parametrize("variant, noise, bright", [
    ("targets", False, False), ("targets+noise", True, False),
    ("targets+bright", False, True), ("full", True, True)])
def test_variants_take_out_only_their_ingredients(bench, variant, noise, bright):
    preset = xstack.preset_scene("paper-6", scale=1.0)
    scene = bench.variant_scene(6, 1.0, variant)
    assert (scene.effects.noise is not None) is noise
    pops, ref = _by_name(scene), _by_name(preset)
    # emptied, not removed: population i keeps its random stream, so the targets are the
    # full scene's
    assert list(pops) == list(ref)
    assert pops["targets"] == ref["targets"]
    assert pops["bright"].count == (ref["bright"].count if bright else 0)
    assert scene.observation == preset.observation
    assert (scene.digest() == preset.digest()) is (variant == "full")


def test_integration_override_changes_the_integration_alone(bench):
    base = bench.variant_scene(6, 1.0, "targets+bright")
    longer = bench.variant_scene(6, 1.0, "targets+bright", integration=60.0)
    assert longer.observation.integration == 60.0 != base.observation.integration
    assert dataclasses.replace(longer, observation=base.observation) == base
    assert longer.digest() != base.digest()
    assert bench.variant_scene(6, 1.0, "targets+bright", integration=None) == base


def test_model_sums(bench, tmp_path):
    m = np.zeros((1, 1, 32, 32), np.float32)
    m[0, 0, 3, 4], m[0, 0, 10, 11] = 2e-3, -5e-4
    fits.writeto(tmp_path / "model.fits", m)
    got = bench._model_sums(tmp_path / "model.fits")
    assert got == {"model_total_jy": pytest.approx(1.5e-3, rel=1e-6), "model_components": 2}
    assert bench._model_sums(tmp_path / "absent.fits") == {}
