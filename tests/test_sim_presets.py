"""Presets paper-1 ... paper-11 at --scale 0.05 reproduce the layout of the paper's Table 1."""

from __future__ import annotations

import math

import numpy as np
import pytest

from xstack.coords import angular_separation
from xstack.sim.presets import PRESETS, preset_scene
from xstack.sim.simulate import simulate, simulate_partitions

SCALE = 0.05
VLA = {"antennas": 27, "channels": 10, "center": 1.4e9, "bandwidth": 250e6, "pols": ["RR", "LL"],
       "integration": 10.0, "time": 33840.0}
ALMA = {"antennas": 32, "channels": 100, "center": 230e9, "bandwidth": 4e9,
        "pols": ["XX", "YY"], "integration": 6.0, "time": 360.0}

#: (setup, fields, bright count, bright kind, bright extended, target count, target kind,
#:  target extended, field size in arcsec) from Table 1 / section 2 of the paper
TABLE1 = {
    1: (VLA, 1, 1, "fixed", False, 25, "fixed", False, 300),
    2: (VLA, 1, 1, "fixed", False, 25, "fixed", False, 300),
    3: (VLA, 1, 10, "fixed", False, 900, "fixed", False, 1800),
    4: (VLA, 1, 10, "fixed", False, 900, "schechter", False, 1800),
    5: (VLA, 1, 417, "bondi2008", False, 900, "schechter", False, 1800),
    6: (VLA, 1, 417, "bondi2008", True, 900, "schechter", False, 1800),
    7: (VLA, 1, 417, "bondi2008", True, 900, "fixed", True, 1800),
    8: (ALMA, 22, 10, "fixed", False, 50, "fixed", False, 100),
    9: (ALMA, 10, 10, "fixed", False, 50, "fixed", False, 300),
    10: (ALMA, 22, 282, "bethermin2012_1.1mm", False, 50, "fixed", False, 100),
    11: (dict(VLA, antennas=8, time=600000.0), 1, 417, "bondi2008", False, 900, "schechter",
         False, 1800),
}


#: Flux densities (Jy) and sizes of each type from Table 1 and section 2 of the paper:
#: ``("fixed", S)``; ``("schechter",)`` = alpha -1.6, S* 1.7 uJy, zero outside 0.25-10 S*;
#: ``("bondi2008",)`` / ``("bethermin",)`` = counts with at most 1 Jy / ~10 mJy; and the
#: Gaussian FWHM range in arcsec (None = point). Types 1-4 bright: the text's 10 mJy (Table 1
#: says 5 mJy; a deviation documented in docs/sim.md).
SCHECHTER = ("schechter",)
PAPER_FLUX = {
    1: (("fixed", 10e-3), None, ("fixed", 6e-6), None),
    2: (("fixed", 10e-3), None, ("fixed", 6e-6), None),
    3: (("fixed", 10e-3), None, ("fixed", 1e-6), None),
    4: (("fixed", 10e-3), None, SCHECHTER, None),
    5: (("bondi2008",), None, SCHECHTER, None),
    6: (("bondi2008",), (0.5, 5.0), SCHECHTER, None),
    7: (("bondi2008",), (0.5, 5.0), ("fixed", 2.96e-6), (1.5, 1.5)),
    8: (("fixed", 30e-3), None, ("fixed", 1e-3), None),
    9: (("fixed", 30e-3), None, ("fixed", 1e-3), None),
    10: (("bethermin",), None, ("fixed", 0.2e-3), None),
    11: (("bondi2008",), None, SCHECHTER, None),
}


@pytest.mark.parametrize("name", PRESETS)
def test_preset_fluxes_and_sizes_match_the_paper(name):
    n = int(name.split("-")[1])
    scene = preset_scene(name)
    _, cats = simulate_partitions(scene, seed=3, scale=SCALE)
    pops = {p.name: p for p in scene.populations}
    for key, spec, fwhm in (("bright", *PAPER_FLUX[n][:2]), ("targets", *PAPER_FLUX[n][2:])):
        flux = np.asarray(cats[key]["flux"])
        dist = pops[key].flux
        if spec[0] == "fixed":
            assert np.all(flux == spec[1]), (key, flux[:3])
        elif spec[0] == "schechter":
            assert (dist.kind, dist.alpha, dist.s_star) == ("schechter", -1.6, 1.7e-6)
            assert dist.s_min == pytest.approx(0.25 * 1.7e-6) and dist.s_max == pytest.approx(17e-6)
            assert np.all((flux >= 0.25 * 1.7e-6) & (flux <= 17e-6))
            assert np.ptp(flux) > 0
        elif spec[0] == "bondi2008":
            assert dist.kind == "bondi2008" and dist.s_max <= 1.0
            assert np.all(flux >= dist.s_min) and np.all(flux <= 1.0) and np.ptp(flux) > 0
        else:
            assert dist.kind == "bethermin2012_1.1mm"
            assert dist.s_max == pytest.approx(10e-3) and np.all(flux <= 10e-3)
        if fwhm is None:
            assert "fwhm_arcsec" not in cats[key].colnames
        else:
            size = np.asarray(cats[key]["fwhm_arcsec"])
            assert np.all((size >= fwhm[0]) & (size <= fwhm[1])), key
            if fwhm[0] < fwhm[1] and len(size) > 5:
                assert np.ptp(size) > 0.3 * (fwhm[1] - fwhm[0])  # really a distribution


def _scaled(n):
    return n if n <= 10 else max(10, round(n * SCALE))


@pytest.mark.parametrize("name", PRESETS)
def test_preset_matches_table1(name):
    n = int(name.split("-")[1])
    setup, fields, nb, kb, eb, nt, kt, et, size = TABLE1[n]
    full = preset_scene(name)
    assert full.spectral.channels == setup["channels"]
    assert full.spectral.center == setup["center"] and full.spectral.bandwidth == setup["bandwidth"]
    assert full.observation.integration == setup["integration"]
    assert full.observation.time_per_pointing == setup["time"]
    pops = {p.name: p for p in full.populations}
    assert set(pops) == {"bright", "targets"}
    assert (pops["bright"].count, pops["bright"].flux.kind) == (nb, kb)
    assert (pops["targets"].count, pops["targets"].flux.kind) == (nt, kt)
    assert (pops["bright"].shape.kind == "gaussian") == eb
    assert (pops["targets"].shape.kind == "gaussian") == et

    parts, cats = simulate_partitions(full, seed=2, scale=SCALE)
    assert len(parts) == fields
    assert {k: len(v) for k, v in cats.items()} == {"bright": _scaled(nb), "targets": _scaled(nt)}
    for ds in parts.values():
        assert ds.sizes["frequency"] == setup["channels"]
        assert list(ds.polarization.values) == setup["pols"]
        assert ds.sizes["antenna_name"] == setup["antennas"]
        assert ds.sizes["baseline_id"] == setup["antennas"] * (setup["antennas"] - 1) // 2
        assert ds.sizes["time"] == max(1, round(setup["time"] * SCALE / setup["integration"]))
        assert np.ptp(ds.frequency.values) == pytest.approx(
            setup["bandwidth"] * (1 - 1 / setup["channels"]))
    ra0, dec0 = math.radians(57.2957916666667), math.radians(-30.0)
    for key, table in cats.items():
        assert ("fwhm_arcsec" in table.colnames) == (eb if key == "bright" else et)
        if n != 9 or key == "bright":
            # uniform in the field box of Table 1
            dx = np.degrees(np.radians(table["ra"]) - ra0) * 3600 * math.cos(dec0)
            dy = (table["dec"] - (-30.0)) * 3600
            assert np.all(np.abs(dx) <= size / 2 + 1) and np.all(np.abs(dy) <= size / 2 + 1)
    if n == 9:
        # pointings on the bright sources; targets within 11.2" of a pointing
        pc = np.array([ds.attrs["phase_center"] for ds in parts.values()])
        b = cats["bright"]
        assert np.allclose(np.sort(pc[:, 1]), np.sort(np.radians(b["dec"])))
        t = cats["targets"]
        sep = angular_separation(np.radians(t["ra"])[:, None], np.radians(t["dec"])[:, None],
                                 pc[None, :, 0], pc[None, :, 1]).min(axis=1)
        assert np.all(np.degrees(sep) * 3600 <= 11.2 + 1e-6)
    if n in (8, 10):
        pc = np.array([ds.attrs["phase_center"] for ds in parts.values()])
        d = angular_separation(pc[:, None, 0], pc[:, None, 1], pc[None, :, 0], pc[None, :, 1])
        np.fill_diagonal(d, np.inf)
        assert np.allclose(np.degrees(d.min(axis=1)) * 3600, 20.0, rtol=1e-6)  # 20" apart


@pytest.mark.slow
@pytest.mark.parametrize("name", PRESETS)
def test_every_preset_simulates_and_writes(name, tmp_path):
    res = simulate(preset_scene(name), tmp_path / "p.zarr", seed=1, scale=SCALE)
    assert res.n_visibilities > 0 and set(res.catalogs) == {"bright", "targets"}
    assert all(p.exists() for p in res.catalog_paths.values())


@pytest.mark.parametrize("name, span_h", [("paper-1", 9.4), ("paper-8", 2.2)])
def test_observations_are_centered_on_transit(name, span_h):
    from xstack.sim import arrays

    parts, _ = simulate_partitions(preset_scene(name), scale=1.0)
    times = np.concatenate([ds.time.values for ds in parts.values()])
    first = next(iter(parts.values()))
    pos = first.ANTENNA_POSITION.values
    lon, _, _ = arrays.geodetic(pos.mean(axis=0))
    ra0 = math.radians(57.2957916666667)
    mid = 0.5 * (times.min() + times.max())
    ha = (arrays.greenwich_sidereal_angle(mid)[0] + lon - ra0 + math.pi) % (2 * math.pi) - math.pi
    assert abs(math.degrees(ha) / 15) < 0.01
    assert (times.max() - times.min()) / 3600 == pytest.approx(span_h, abs=0.01)
