"""Scene loading, validation (errors naming the field), presets and flux distributions."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from xstack.errors import XstackError
from xstack.sim.counts import FluxDistribution, s_min_for_count
from xstack.sim.presets import PRESETS, preset_dict, preset_scene
from xstack.sim.scene import Scene, load_scene

GOOD = """
name = "toml-test"
[array]
config = "alma.cycle1.2"
[observation]
integration = 6.0
time_per_pointing = 12.0
hour_angle = [-1.0, 1.0]
[spectral]
center = 230e9
bandwidth = 2e9
channels = 4
polarizations = ["XX", "YY"]
[pointings]
mode = "single"
center = ["3h49m10.99s", "-30d00m00s"]
[effects]
primary_beam = "auto"
noise = { sigma = 0.5 }
[[populations]]
name = "targets"
count = 5
flux = { kind = "fixed", value = "1mJy" }
positions = { kind = "disc", radius_arcsec = 5.0 }
"""


def test_toml_scene_loads_and_round_trips(tmp_path):
    path = tmp_path / "s.toml"
    path.write_text(GOOD)
    scene = load_scene(path)
    assert scene.populations[0].flux.value == pytest.approx(1e-3)
    assert scene.effects.noise.sigma == 0.5 and scene.effects.w_term is False
    again = load_scene(scene.to_dict())
    assert again == scene


@pytest.mark.parametrize("edit, field", [
    (("mode = \"single\"", "mdoe = \"single\""), "pointings.mdoe"),
    (("config = \"alma.cycle1.2\"", "config = \"alma.cycle9\""), "array.config"),
    (("bandwidth = 2e9", "bandwidth = 0.0"), "spectral.bandwidth"),
    (("value = \"1mJy\"", "value = \"-1mJy\""), "populations[0].flux.value"),
    (("count = 5", "count = \"five\""), "populations[0].count"),
    (("radius_arcsec = 5.0", "radius_arcsec = 500.0"), "populations[0].positions"),
    (("channels = 4", "channels = 0"), "spectral.channels"),
    (("noise = { sigma = 0.5 }", "noise = { sigma = 0.5, sefd = 3 }"), "effects.noise"),
    (("[effects]", "[efects]"), "efects"),
    # wrong types: each names the field
    (("primary_beam = \"auto\"", "primary_beam = \"auto\"\nw_term = \"yes\""),
     "effects.w_term"),
    (("hour_angle = [-1.0, 1.0]", "hour_angle = 3"), "observation.hour_angle"),
    (("polarizations = [\"XX\", \"YY\"]", "polarizations = \"XX\""), "spectral.polarizations"),
    (("integration = 6.0", "integration = \"six\""), "observation.integration"),
    (("kind = \"fixed\"", "kind = \"fixd\""), "populations[0].flux.kind"),
    (("radius_arcsec = 5.0", "radius_arcsec = 5.0, radius = 3"), "populations[0].positions.radius"),
    (("config = \"alma.cycle1.2\"", "config = 12"), "array.config"),
])
def test_bad_scenes_name_the_field_and_write_nothing(tmp_path, edit, field):
    from xstack.sim.simulate import simulate

    path = tmp_path / "bad.toml"
    path.write_text(GOOD.replace(*edit))
    out = tmp_path / "out.zarr"
    with pytest.raises(XstackError) as err:
        simulate(path, out)
    assert field in str(err.value)
    assert list(tmp_path.iterdir()) == [path]  # nothing written


def test_scene_toml_round_trip_covers_every_setting(tmp_path):
    """A scene built as dataclasses, using every kind of setting, written as TOML by
    scene_to_toml and read back by load_scene, is equal to the original."""
    from xstack.sim.counts import FluxDistribution
    from xstack.sim.scene import (
        ArraySpec,
        Effects,
        FlaggingSpec,
        NoiseSpec,
        Observation,
        Pointings,
        Population,
        Positions,
        Shape,
        Spectral,
        scene_to_toml,
    )

    site = np.array([2225142.18, -5440307.37, -2481029.85])
    scenes = [Scene(
        name="every-setting", description='quotes " and \\ survive',
        array=ArraySpec(positions=(site + [[0, 0, 0], [40, 0, 0], [0, 55, 0]]).tolist(),
                        diameters=[12.0, 12.0, 7.0], names=["A", "B", "C"], telescope="ALMA",
                        antennas=["A", "C"]),
        observation=Observation(date="2015-03-02", hour_angle=[-2.5, 3.0], integration=2.0,
                                time_per_pointing=20.0),
        spectral=Spectral(center=345e9, bandwidth=1.875e9, channels=7,
                          polarizations=["XX", "XY", "YX", "YY"]),
        pointings=Pointings(mode="rectangular", center=["3h49m10.99s", "-30d00m00s"],
                            size_arcsec=[40.0, 20.0], spacing_arcsec=10.0),
        effects=Effects(primary_beam="gaussian", pb_cutoff=0.05, w_term=True,
                        noise=NoiseSpec(tsys=75.0, aperture_efficiency=0.7, efficiency=0.9),
                        flagging=FlaggingSpec(random_fraction=0.02, shadowing=True)),
        populations=[
            Population("tab", 30, FluxDistribution("table", s_min=1e-4, s_max=1e-2,
                                                   flux=[1e-4, 1e-3, 1e-2], dnds=[1e6, 1e3, 1.0]),
                       Positions("disc", radius_arcsec=8.0, center=[57.29, -30.001]),
                       Shape("gaussian", [0.2, 0.9]), keep_count_below=5),
            Population("sch", 12, FluxDistribution("schechter", alpha=-1.6, s_star=1.7e-6,
                                                   s_min=4e-7, s_max=1.7e-5),
                       Positions("around_pointings", radius_arcsec=3.0), Shape("gaussian", [1.5])),
            Population("pl", 2, FluxDistribution("power_law", index=-2.5, s_min=1e-3, s_max=1.0),
                       Positions("list", ra=[57.2958, 57.2960], dec=[-30.0, -30.0002])),
            Population("bo", 3, FluxDistribution("bondi2008", s_min=1e-4, s_max=1.0),
                       Positions("box", size_arcsec=[30.0, 10.0])),
        ],
        visibility_dtype="complex128", time_chunk=3, baseline_chunk=2),
        load_scene(preset_dict("paper-9")),
        Scene(effects=Effects(noise=NoiseSpec(sefd=420.0)),
              pointings=Pointings(mode="list", positions=[[57.3, -30.0], [57.31, -30.01]]),
              populations=[Population("one", 1, FluxDistribution("fixed", 2e-3))]),
    ]
    for k, scene in enumerate(scenes):
        scene.validate()
        path = tmp_path / f"s{k}.toml"
        path.write_text(scene_to_toml(scene))
        again = load_scene(path)
        assert again == scene, path.read_text()
        assert scene_to_toml(again) == path.read_text()


def test_invalid_toml_syntax(tmp_path):
    path = tmp_path / "x.toml"
    path.write_text("[array\nconfig = 1")
    with pytest.raises(XstackError, match="not valid TOML"):
        load_scene(path)


def test_scaling_rule():
    scene = preset_scene("paper-5")
    small = scene.scaled(0.05)
    assert small.observation.time_per_pointing == pytest.approx(33840 * 0.05)
    counts = {p.name: p.count for p in small.populations}
    assert counts == {"bright": round(417 * 0.05), "targets": round(900 * 0.05)}
    assert {p.name: p.count for p in preset_scene("paper-1").scaled(0.05).populations} == \
        {"bright": 1, "targets": 10}
    with pytest.raises(XstackError, match="scale"):
        scene.scaled(0.0)
    assert isinstance(scene, Scene) and scene.populations[0].count == 417  # not modified


def test_unknown_preset():
    with pytest.raises(XstackError, match="unknown preset"):
        preset_dict("paper-12")
    assert len(PRESETS) == 11


def test_schechter_mean_matches_paper():
    """Paper §2.2.4: the target fluxes average 0.99 uJy."""
    d = FluxDistribution("schechter", alpha=-1.6, s_star=1.7e-6, s_min=0.425e-6, s_max=17e-6)
    assert d.mean() == pytest.approx(0.99e-6, rel=0.02)
    x = d.sample(200000, np.random.default_rng(3))
    assert x.min() >= 0.425e-6 and x.max() <= 17e-6
    assert x.mean() == pytest.approx(d.mean(), rel=0.01)


def test_sampling_follows_the_counts():
    """KS test of drawn fluxes against the analytic CDF of a power law."""
    d = FluxDistribution("power_law", index=-2.5, s_min=1e-3, s_max=1.0)
    x = d.sample(20000, np.random.default_rng(5))
    a = -1.5

    def cdf(s):
        return (s**a - 1e-3**a) / (1.0**a - 1e-3**a)

    assert stats.kstest(x, cdf).pvalue > 1e-3


def test_tabulated_counts_sample_their_distribution():
    """kind = "table": a tabulated dN/dS (log-log interpolated) of S^-2 between 0.1 and 10 mJy
    is sampled with the analytic power-law CDF (KS test)."""
    s = np.geomspace(1e-4, 1e-2, 7)
    d = FluxDistribution("table", s_min=1e-4, s_max=1e-2, flux=list(s), dnds=list(3.0 * s**-2.0))
    d.validate("t")
    x = d.sample(20000, np.random.default_rng(8))
    assert x.min() >= 1e-4 and x.max() <= 1e-2

    def cdf(v):
        return (1e-4**-1 - v**-1) / (1e-4**-1 - 1e-2**-1)

    assert stats.kstest(x, cdf).pvalue > 1e-3
    with pytest.raises(XstackError, match="t.flux/dnds"):
        FluxDistribution("table", s_min=1e-4, s_max=1e-2, flux=[1e-3, 1e-4], dnds=[1, 1]).validate("t")


def test_rectangular_mosaic_layout():
    """A 40" x 20" rectangular grid at 10" spacing: 5 x 3 pointings, 10" apart, centered."""
    from xstack.coords import angular_separation, radec_to_lmn
    from xstack.sim.simulate import simulate_partitions

    scene = {"array": {"config": "alma.cycle1.2"},
             "observation": {"integration": 6.0, "time_per_pointing": 6.0, "hour_angle": [-1, 1]},
             "spectral": {"center": 230e9, "bandwidth": 1e9, "channels": 1, "polarizations": ["XX"]},
             "pointings": {"mode": "rectangular", "center": [57.3, -30.0], "size_arcsec": [40, 20],
                           "spacing_arcsec": 10.0}}
    parts, _ = simulate_partitions(scene)
    pc = np.array([ds.attrs["phase_center"] for ds in parts.values()])
    assert len(pc) == 15
    l, m, _, _ = radec_to_lmn(pc[:, 0], pc[:, 1], np.radians(57.3), np.radians(-30.0))
    x, y = np.degrees(l) * 3600, np.degrees(m) * 3600
    assert sorted(set(np.round(x, 6))) == [-20.0, -10.0, 0.0, 10.0, 20.0]
    assert sorted(set(np.round(y, 6))) == [-10.0, 0.0, 10.0]
    d = angular_separation(pc[:, None, 0], pc[:, None, 1], pc[None, :, 0], pc[None, :, 1])
    np.fill_diagonal(d, np.inf)
    assert np.allclose(np.degrees(d.min(axis=1)) * 3600, 10.0, rtol=1e-6)


def test_bondi_counts_and_limit():
    d = FluxDistribution("bondi2008", s_min=1e-7, s_max=1.0)
    area = (1800 / 206264.806) ** 2
    s_min = s_min_for_count(d, 417, area)
    d.s_min = s_min
    assert d.expected_number(area) == pytest.approx(417, rel=1e-6)
    # independent check: Euclidean-normalised counts at 1 mJy = 10^a0 Jy^1.5/sr
    assert d.dnds_function(np.array([1e-3]))[0] * (1e-3) ** 2.5 == pytest.approx(10**0.805)
    assert 3e-5 < s_min < 2e-4


def test_bethermin_tabulation_is_consistent():
    d = FluxDistribution("bethermin2012_1.1mm", s_min=1e-4, s_max=1e-2)
    # integrating the tabulated dN/dS reproduces the tabulated N(>S) differences
    n = d.expected_number(1.0 / (180 / np.pi) ** 2)  # per deg^2, 0.1 to 10 mJy
    assert n == pytest.approx(8.0e4 - 3.0e1, rel=0.02)
