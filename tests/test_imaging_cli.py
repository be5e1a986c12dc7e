"""``xstack image`` and ``xstack subtract`` from the command line."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from _imaging_helpers import make_sky_partition, offset_position
from astropy.io import fits
from astropy.table import Table

from xstack.cli import main
from xstack.imaging.fitsio import read_image
from xstack.schema import open_store, write_store


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    src = offset_position(-20.0, 16.0)  # west and north
    ds = make_sky_partition([(src[0], src[1], 0.8)], n_time=10, n_ant=10, noise=0.2, seed=3)
    write_store({"spw0_field0": ds}, d / "d.zarr")
    return d, src


def test_image_cli_outputs(store, capsys):
    d, src = store
    out = d / "img.fits"
    rc = main(["image", str(d / "d.zarr"), str(out), "--size", "64",
               "--cell", "2", "--niter", "200", "--threshold", "20mJy", "--json", "--png",
               "--no-progress"])
    assert rc == 0
    payload = json.loads(capsys.readouterr().out)
    files = payload["files"]
    assert set(files) == {"image", "psf", "residual", "model", "pb", "png"}  # + the beam
    for f in files.values():
        assert (d / f.split("/")[-1]).exists()
    assert files["psf"].endswith("img.psf.fits")
    data, wcs, header = read_image(out)
    y, x = np.unravel_index(np.nanargmax(data), data.shape)
    world = wcs.pixel_to_world(x, y)
    from astropy import units as u
    from astropy.coordinates import SkyCoord

    assert world.separation(SkyCoord(src[0] * u.rad, src[1] * u.rad)).arcsec < 1.5
    assert payload["peak_jy_per_beam"] == pytest.approx(0.8, rel=0.05)
    assert payload["n_components"] > 0
    assert len(payload["beam_arcsec"]) == 2
    assert fits.getheader(files["model"])["BUNIT"] == "Jy/pixel"
    assert fits.getheader(files["psf"])["BUNIT"] == ""
    psf = read_image(files["psf"])[0]
    assert psf[32, 32] == pytest.approx(1.0, abs=1e-5)
    # existing outputs are not overwritten without --overwrite
    rc = main(["image", str(d / "d.zarr"), str(out), "--size", "64", "--cell", "2", "--no-progress"])
    assert rc == 1
    assert "exists" in capsys.readouterr().err


def test_subtract_cli(store, capsys, tmp_path):
    d, src = store
    cat = tmp_path / "c.csv"
    Table({"ra": [math.degrees(src[0])], "dec": [math.degrees(src[1])], "flux": [0.8]}).write(cat)
    out = tmp_path / "r.zarr"
    rc = main(["subtract", str(d / "d.zarr"), str(cat), str(out), "--primary-beam", "none",
               "--no-progress"])
    assert rc == 0
    res = open_store(out)["spw0_field0"].to_dataset().VISIBILITY.values
    assert abs(res[..., 0].real.mean()) < 5 * 0.2 / math.sqrt(res[..., 0].size)
    rc = main(["subtract", str(d / "d.zarr"), str(cat), str(out), "--no-progress"])
    assert rc == 1 and "exists" in capsys.readouterr().err


def test_image_cli_errors(store, capsys, tmp_path):
    d, _ = store
    rc = main(["image", str(d / "d.zarr"), str(tmp_path / "x.fits"), "--size", "31", "--cell", "1",
               "--no-progress"])
    assert rc == 1 and "even" in capsys.readouterr().err
    rc = main(["image", str(tmp_path / "none.zarr"), str(tmp_path / "x.fits"), "--size", "32",
               "--cell", "1", "--no-progress"])
    assert rc == 1 and "none.zarr" in capsys.readouterr().err
    from xstack.imaging.fitsio import make_header, write_image

    write_image(tmp_path / "mask.fits", np.ones((40, 40)), make_header(40, 40, 2.0, (1.0, -0.5)))
    rc = main(["image", str(d / "d.zarr"), str(tmp_path / "x.fits"), "--size", "64", "--cell", "2",
               "--niter", "5", "--mask", str(tmp_path / "mask.fits"), "--no-progress"])
    assert rc == 1 and "mask shape" in capsys.readouterr().err
    assert not list(tmp_path.glob("x*"))


def test_image_cli_mask_limits_components(store, tmp_path):
    d, _ = store
    from xstack.imaging.fitsio import make_header, write_image

    mask = np.zeros((64, 64))
    mask[:8, :8] = 1.0  # a corner far from the source
    write_image(tmp_path / "mask.fits", mask, make_header(64, 64, 2.0, (1.0, -0.5)))
    rc = main(["image", str(d / "d.zarr"), str(tmp_path / "m.fits"), "--size", "64", "--cell", "2",
               "--niter", "50", "--mask", str(tmp_path / "mask.fits"), "--no-progress"])
    assert rc == 0
    model = read_image(tmp_path / "m.model.fits")[0]
    assert np.count_nonzero(model) > 0
    assert np.all(model[8:, :] == 0) and np.all(model[:, 8:] == 0)


def test_image_cli_mosaic(tmp_path, capsys):
    """Two spectral windows x two pointings: one linear mosaic; CLEAN refused, nothing written."""
    from xstack.imaging.image import group_pointings, make_image, select_partitions

    src = offset_position(3.0, 2.0)
    parts = {}
    for field, dx in enumerate((-8.0, 8.0)):
        center = offset_position(dx, 0.0)
        for spw, f0 in enumerate((1.3e9, 1.5e9)):
            parts[f"spw{spw}_field{field}"] = make_sky_partition(
                [(src[0], src[1], 0.5)], n_time=4, n_ant=8, freq0=f0, phase_center=center,
                field_id=field, seed=spw + 2 * field).assign_attrs(spectral_window_id=spw)
    write_store(parts, tmp_path / "m.zarr")
    groups = group_pointings(select_partitions(tmp_path / "m.zarr", allow_mosaic=True))
    assert sorted(sorted(n for n, _ in g) for _, g in groups) == [
        ["spw0_field0", "spw1_field0"], ["spw0_field1", "spw1_field1"]]
    out = tmp_path / "mos.fits"
    assert main(["image", str(tmp_path / "m.zarr"), str(out), "--size", "64", "--cell", "2",
                 "--json", "--no-progress"]) == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["n_pointings"] == 2
    data = read_image(out)[0]
    ref = make_image(tmp_path / "m.zarr", size=64, cell_arcsec=2.0)
    np.testing.assert_allclose(data, ref.image, rtol=1e-6, atol=1e-7)  # float32 FITS
    assert fits.getheader(out)["XSMOSAIC"] == 2
    bad = tmp_path / "clean.fits"
    assert main(["image", str(tmp_path / "m.zarr"), str(bad), "--size", "64", "--cell", "2",
                 "--niter", "10", "--no-progress"]) == 1
    assert "different phase centers" in capsys.readouterr().err
    assert not list(tmp_path.glob("clean*"))
