"""CLEAN on stores, model subtraction (catalog and CLEAN model image), bad models."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _imaging_helpers import PHASE_CENTER, make_sky_partition, offset_position
from astropy.table import Table
from scipy import stats

from xstack.beams import standard_beam
from xstack.coords import angular_separation
from xstack.errors import XstackError
from xstack.imaging.clean import clean_data
from xstack.imaging.image import make_image
from xstack.imaging.subtract import subtract
from xstack.schema import open_store, write_store

NOISE = 0.5  # Jy per real/imaginary part per visibility


def _catalog(sources, path, fwhm=None):
    t = Table({"ra": [math.degrees(s[0]) for s in sources],
               "dec": [math.degrees(s[1]) for s in sources],
               "flux": [s[2] for s in sources]})
    if fwhm is not None:
        t["fwhm_arcsec"] = fwhm
    t.write(path, format="ascii.ecsv")
    return path


def _residual_vis(path):
    return open_store(path)["spw0_field0"].to_dataset().VISIBILITY.values


@pytest.fixture(scope="module")
def bright_scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("scene")
    srcs = [(*offset_position(40, -30), 2.0), (*offset_position(-70, 50), 1.0),
            (*offset_position(15, 90), 0.6)]
    ds = make_sky_partition(srcs, n_time=30, n_ant=14, noise=NOISE, seed=7)
    noise_only = make_sky_partition([], n_time=30, n_ant=14, noise=NOISE, seed=7)
    write_store({"spw0_field0": ds.chunk({"time": 8})}, d / "data.zarr")
    return d, srcs, ds, noise_only


def test_clean_then_subtract_reaches_thermal_noise(bright_scene):
    d, srcs, ds, _ = bright_scene
    n_vis = int(np.count_nonzero(~ds.FLAG.values))
    thermal = NOISE / math.sqrt(n_vis)  # natural-weighted image noise, Jy/beam
    result, cres = clean_data(d / "data.zarr", size=256, cell_arcsec=2.0, niter=2000,
                              threshold=3 * thermal)
    assert cres.converged and cres.n_major >= 2
    dirty_rms = np.std(result.extra["dirty"])
    assert dirty_rms > 5 * thermal  # the bright sources dominate before CLEAN
    assert np.std(cres.residual) < 1.15 * thermal
    assert cres.model.sum() == pytest.approx(3.6, rel=0.02)
    # subtract the CLEAN model from the visibilities; image the residual store
    model_path = d / "m.model.fits"
    result.write(model_path, cres.model, kind="model", overwrite=True)
    subtract(d / "data.zarr", model_path, d / "res.zarr", overwrite=True)
    resid = make_image(d / "res.zarr", size=256, cell_arcsec=2.0)
    assert np.std(resid.image) < 1.15 * thermal
    # the residual image equals the major-cycle residual (both are dirty - image(P(model)))
    assert np.max(np.abs(resid.image - cres.residual)) < 1e-3 * thermal + 1e-6


def test_perfect_catalog_leaves_pure_noise(bright_scene, tmp_path):
    d, srcs, ds, noise_only = bright_scene
    subtract(d / "data.zarr", _catalog(srcs, tmp_path / "c.ecsv"), tmp_path / "r.zarr",
             primary_beam="none")
    res = _residual_vis(tmp_path / "r.zarr")
    # exactly the injected noise (float32 storage rounding aside) ...
    assert np.max(np.abs(res - noise_only.VISIBILITY.values)) < 1e-5 * 3.6
    # ... and statistically pure Gaussian noise of the stated sigma
    z = np.concatenate([res.real.ravel(), res.imag.ravel()]) / NOISE
    assert stats.kstest(z, "norm").pvalue > 1e-3
    assert abs(z.mean()) < 5 / math.sqrt(z.size)
    assert abs(np.mean(z * z) - 1) < 5 * math.sqrt(2 / z.size)
    # the bright sources are gone from the image too
    assert np.std(make_image(tmp_path / "r.zarr", size=128, cell_arcsec=2.0).image) < \
        1.15 * NOISE / math.sqrt(z.size / 2)


def test_catalog_primary_beam_and_gaussian(tmp_path):
    """Off-axis Gaussian source: subtraction needs the VLA beam and the Gaussian factor."""
    pos = offset_position(540.0, 120.0)
    freq = 1.4e9 + 50e6 * np.arange(4)
    att = standard_beam("VLA", 25.0)(angular_separation(*PHASE_CENTER, *pos), freq)[None, :]
    assert 0.4 < att.min() < 0.95
    ds = make_sky_partition([(pos[0], pos[1], 1.0)], n_time=6, n_ant=8, attenuation=att,
                            fwhm_arcsec=[4.0])
    write_store({"spw0_field0": ds}, tmp_path / "d.zarr")
    cat = _catalog([(pos[0], pos[1], 1.0)], tmp_path / "c.ecsv", fwhm=[4.0])
    subtract(tmp_path / "d.zarr", cat, tmp_path / "r.zarr")
    assert np.max(np.abs(_residual_vis(tmp_path / "r.zarr"))) < 1e-5
    subtract(tmp_path / "d.zarr", cat, tmp_path / "r2.zarr", primary_beam="none")
    assert np.max(np.abs(_residual_vis(tmp_path / "r2.zarr"))) > 0.05
    point = _catalog([(pos[0], pos[1], 1.0)], tmp_path / "p.ecsv")
    subtract(tmp_path / "d.zarr", point, tmp_path / "r3.zarr")
    assert np.max(np.abs(_residual_vis(tmp_path / "r3.zarr"))) > 0.05


def test_cross_hands_untouched(tmp_path):
    ds = make_sky_partition([(*PHASE_CENTER, 1.0)], n_time=3, n_ant=5, pols=("RR", "RL", "LR", "LL"))
    vis = ds.VISIBILITY.values.copy()
    vis[..., 1:3] = 0.25 + 0.1j
    ds = ds.assign(VISIBILITY=(ds.VISIBILITY.dims, vis))
    write_store({"spw0_field0": ds}, tmp_path / "d.zarr")
    subtract(tmp_path / "d.zarr", _catalog([(*PHASE_CENTER, 1.0)], tmp_path / "c.ecsv"),
             tmp_path / "r.zarr")
    res = _residual_vis(tmp_path / "r.zarr")
    assert np.allclose(res[..., [0, 3]], 0, atol=1e-6)
    assert np.allclose(res[..., 1:3], 0.25 + 0.1j)


def test_bad_models_write_nothing(bright_scene, tmp_path):
    d, srcs, ds, _ = bright_scene
    res = make_image(ds, size=64, cell_arcsec=2.0)
    model = np.zeros((64, 64))
    model[10, 10] = 1.0
    # a model whose grid center is not the data's phase center
    h = res.header_for("model")
    h["CRVAL1"] += 0.01
    from xstack.imaging.fitsio import write_image

    write_image(tmp_path / "shifted.fits", model, h)
    out = tmp_path / "out.zarr"
    with pytest.raises(XstackError, match="does not match"):
        subtract(d / "data.zarr", tmp_path / "shifted.fits", out)
    assert not out.exists()
    h = res.header_for("model")
    h["CRPIX1"] = 20.0
    write_image(tmp_path / "offcenter.fits", model, h)
    with pytest.raises(XstackError, match="reference pixel"):
        subtract(d / "data.zarr", tmp_path / "offcenter.fits", out)
    res.write(tmp_path / "image.fits", model)  # Jy/beam image, not a model
    with pytest.raises(XstackError, match="Jy/pixel"):
        subtract(d / "data.zarr", tmp_path / "image.fits", out)
    Table({"ra": [1.0], "dec": [2.0]}).write(tmp_path / "noflux.ecsv")
    with pytest.raises(XstackError, match="flux"):
        subtract(d / "data.zarr", tmp_path / "noflux.ecsv", out)
    with pytest.raises(XstackError, match="no such model"):
        subtract(d / "data.zarr", tmp_path / "missing.fits", out)
    assert not out.exists()
    assert not any(p.name.startswith(".out.zarr") for p in tmp_path.iterdir())


def test_catalog_subtraction_per_mosaic_pointing(tmp_path):
    """ALMA mosaic: each pointing sees the source with its own primary-beam attenuation."""
    src = offset_position(8.0, 4.0)
    parts = {}
    for field, (dx, dy) in enumerate([(0.0, 0.0), (20.0, 0.0)]):
        center = offset_position(dx, dy)
        freq = 230e9 + 50e6 * np.arange(3)
        beam = standard_beam("ALMA", 12.0)
        att = beam(angular_separation(*center, *src), freq)[None, :]
        ds = make_sky_partition([(src[0], src[1], 0.03)], n_time=4, n_ant=8, freq0=230e9,
                                chan_width=50e6, n_chan=3, telescope="ALMA", dish=12.0,
                                max_baseline=300.0, phase_center=center, field_id=field,
                                attenuation=att)
        parts[f"spw0_field{field}"] = ds
    assert parts["spw0_field0"].attrs["phase_center"] != parts["spw0_field1"].attrs["phase_center"]
    write_store(parts, tmp_path / "m.zarr")
    subtract(tmp_path / "m.zarr", _catalog([(src[0], src[1], 0.03)], tmp_path / "c.ecsv"),
             tmp_path / "r.zarr")
    tree = open_store(tmp_path / "r.zarr")
    for name in parts:
        res = tree[name].to_dataset().VISIBILITY.values
        assert np.max(np.abs(res)) < 1e-7, name
        assert np.max(np.abs(parts[name].VISIBILITY.values)) > 0.005
