"""Simulated store -> exported MeasurementSet -> converted store: identical data."""

from __future__ import annotations

import numpy as np
import pytest

from xstack.schema import iter_partitions, open_store
from xstack.sim.scene import PAPER_FIELD_CENTER
from xstack.sim.simulate import simulate

export = pytest.importorskip("xstack.io.export")
convert = pytest.importorskip("xstack.io.convert")

RA0, DEC0 = PAPER_FIELD_CENTER


def test_simulate_export_convert_identical(tmp_path):
    scene = {
        "name": "roundtrip",
        "array": {"config": "alma.cycle1.2"},
        "observation": {"hour_angle": [-1.0, 1.0], "integration": 6.0, "time_per_pointing": 18.0},
        "spectral": {"center": 230e9, "bandwidth": 4e9, "channels": 5,
                     "polarizations": ["XX", "YY"]},
        "pointings": {"mode": "list", "positions": [[RA0, DEC0], [RA0, DEC0 + 20 / 3600]]},
        "effects": {"primary_beam": "auto", "w_term": True, "noise": {"sigma": 0.2},
                    "flagging": {"random_fraction": 0.05}},
        "populations": [{"name": "targets", "count": 4, "flux": {"kind": "fixed", "value": 0.01},
                         "positions": {"kind": "disc", "radius_arcsec": 12.0}}],
    }
    res = simulate(scene, tmp_path / "sim.zarr", seed=9)
    ms = export.export_ms(res.store, tmp_path / "sim.ms")
    back = convert.convert_ms(ms, tmp_path / "back.zarr")
    a = dict(iter_partitions(open_store(res.store)))
    b = dict(iter_partitions(open_store(back)))
    assert len(a) == len(b) == 2
    # match partitions by phase center (names may differ)
    for da in a.values():
        (db,) = [d for d in b.values() if np.allclose(d.attrs["phase_center"],
                                                     da.attrs["phase_center"], atol=1e-12)]
        for var in ("VISIBILITY", "WEIGHT", "FLAG", "UVW"):
            x, y = da[var].values, db[var].values
            assert x.shape == y.shape, var
            assert np.array_equal(x, y), var
        assert np.array_equal(da.time.values, db.time.values)
        assert np.array_equal(da.frequency.values, db.frequency.values)
        assert list(da.polarization.values) == list(db.polarization.values)


def test_imaging_puts_simulated_source_at_its_catalog_position(tmp_path):
    """Cross-stage convention check: xstack's (ducc0) imager finds the simulated source at
    the catalog RA/Dec with its flux (w-term and primary beam off)."""
    import math

    image = pytest.importorskip("xstack.imaging.image")
    ra = RA0 + 6 / 3600 / math.cos(math.radians(DEC0))
    dec = DEC0 + 3 / 3600
    scene = {
        "name": "img", "array": {"config": "alma.cycle1.2"},
        "observation": {"hour_angle": [-1, 1], "integration": 6.0, "time_per_pointing": 60.0},
        "spectral": {"center": 230e9, "bandwidth": 4e9, "channels": 4, "polarizations": ["XX", "YY"]},
        "pointings": {"mode": "single", "center": [RA0, DEC0]},
        "populations": [{"name": "s", "count": 1, "flux": {"kind": "fixed", "value": 1.0},
                         "positions": {"kind": "list", "ra": [ra], "dec": [dec]}}],
    }
    res = simulate(scene, tmp_path / "img.zarr")
    img = image.make_image(res.store, size=128, cell_arcsec=0.2)
    data = np.squeeze(img.image)
    iy, ix = np.unravel_index(np.argmax(data), data.shape)
    wcs = img.wcs.celestial if hasattr(img.wcs, "celestial") else img.wcs
    sky = wcs.pixel_to_world(ix, iy)
    assert abs(sky.ra.deg - ra) * 3600 * math.cos(math.radians(DEC0)) < 0.1
    assert abs(sky.dec.deg - dec) * 3600 < 0.1
    assert data.max() == pytest.approx(1.0, abs=0.01)
    # the mirrored position (wrong sign convention) would be empty
    assert data[data.shape[0] - iy, data.shape[1] - ix] < 0.5


def test_uvstack_recovers_the_injected_mosaic_flux(tmp_path):
    """Cross-stage: stacking a simulated noiseless ALMA mosaic (primary beam, w-term) at the
    true positions gives the injected flux (targets only, no bright sources)."""
    stack = pytest.importorskip("xstack.uvstack.stack")
    scene = {
        "name": "stack", "array": {"config": "alma.cycle1.2"},
        "observation": {"hour_angle": [-1, 1], "integration": 6.0, "time_per_pointing": 12.0},
        "spectral": {"center": 230e9, "bandwidth": 4e9, "channels": 4, "polarizations": ["XX", "YY"]},
        "pointings": {"mode": "hexagonal", "center": [RA0, DEC0], "size_arcsec": [40.0, 40.0],
                      "spacing_arcsec": 20.0},
        "effects": {"primary_beam": "auto", "w_term": True},
        "populations": [{"name": "targets", "count": 1, "flux": {"kind": "fixed", "value": 2e-3},
                         "positions": {"kind": "box", "size_arcsec": [20.0, 20.0]}}],
    }
    res = simulate(scene, tmp_path / "m.zarr", seed=2)
    out = stack.stack_uv(res.store, res.catalog_paths["targets"], weighting="pb")
    assert out.flux_jy == pytest.approx(2e-3, rel=1e-3)
