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


def test_nearest_bright_distance_is_the_brute_force_one(bench):
    from astropy.table import Table

    rng = np.random.default_rng(5)
    # across the RA wrap and near the pole, where a flat-sky distance would be wrong
    targets = Table({"ra": rng.uniform(-0.05, 0.05, 40) % 360, "dec": rng.uniform(-89.99, -89.9, 40)})
    sources = Table({"ra": rng.uniform(-0.05, 0.05, 7) % 360, "dec": rng.uniform(-89.99, -89.9, 7)})
    got = bench.nearest_arcsec(targets, sources)
    r1, d1 = np.radians(targets["ra"])[:, None], np.radians(targets["dec"])[:, None]
    r2, d2 = np.radians(sources["ra"])[None], np.radians(sources["dec"])[None]
    hav = np.sin((d2 - d1) / 2) ** 2 + np.cos(d1) * np.cos(d2) * np.sin((r2 - r1) / 2) ** 2
    want = np.degrees(2 * np.arcsin(np.sqrt(hav))).min(axis=1) * 3600
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-6)


def test_no_bright_sources_put_every_target_in_the_farthest_bin(bench):
    from astropy.table import Table

    targets = Table({"ra": [10.0, 10.1], "dec": [-30.0, -30.1]})
    empty = Table({"ra": np.zeros(0), "dec": np.zeros(0)})
    assert np.all(np.isinf(bench.nearest_arcsec(targets, empty)))


def test_distance_bins_count_every_finite_value_once(bench):
    rng = np.random.default_rng(9)
    sep = np.r_[rng.uniform(0, 300, 200), 10.0, 30.0, np.inf, np.inf]
    values = rng.normal(size=sep.size)
    values[[3, 50]] = np.nan  # a target off the map
    bins = bench.distance_bins(values, sep)
    assert sum(b["n"] for b in bins) == np.isfinite(values).sum()
    # an edge belongs to the bin it opens; infinity (no bright source) to the last one
    for b in bins:
        hi = b["to_arcsec"]
        m = np.isfinite(values) & (sep >= b["from_arcsec"]) & ((sep < hi) | np.isinf(hi))
        assert b["n"] == m.sum()
        assert b["mean_jy"] == pytest.approx(values[m].mean())
        assert b["median_jy"] == pytest.approx(np.median(values[m]))
    assert bench.distance_bins(np.array([np.nan]), np.array([5.0]))[0]["mean_jy"] is None
