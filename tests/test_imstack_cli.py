"""``xstack imstack`` on the command line: JSON output, errors, nothing written on failure."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _imstack_helpers import make_field
from astropy.table import Table

from xstack.cli import main

BEAM = (3.2, 1.6, 0.0)


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    rng = np.random.default_rng(21)
    path, ra, dec, _, _ = make_field(d, rng, 0.5, beam=BEAM, n_side=10, noise=0.01, psf=True)
    cat = d / "targets.ecsv"
    Table({"ra": ra, "dec": dec}).write(cat)
    return d, path, cat


def test_cli_json_and_outputs(field, tmp_path, capsys):
    _, image, cat = field
    out = tmp_path / "s.fits"
    status = main(["imstack", str(image), str(cat), str(out), "--subpixel", "fourier",
                   "--stamp-size", "32", "--weighting", "none", "--json"])
    captured = capsys.readouterr()
    assert status == 0
    payload = json.loads(captured.out)
    assert payload["n_positions"] == 100
    assert payload["method"] == "mean" and payload["weighting"] == "none"
    assert abs(payload["flux_jy"] - 1.0) < 0.01
    assert 0 < payload["flux_err_jy"] < 0.01
    assert out.exists() and (tmp_path / "s.cube.zarr").is_dir() and (tmp_path / "s.png").exists()
    # a second run refuses to overwrite, then replaces with --overwrite
    assert main(["imstack", str(image), str(cat), str(out), "--stamp-size", "32"]) == 1
    assert "exists" in capsys.readouterr().err
    assert main(["imstack", str(image), str(cat), str(out), "--stamp-size", "32", "--method",
                 "median", "--overwrite", "--json", "--no-png", "--filter", "3"]) == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["method"] == "median" and payload["filter_lowfreq"] == 3


def test_cli_noise_options_reach_the_weights_and_the_header(field, tmp_path, capsys):
    from astropy.io import fits

    from xstack.imstack.stack import stack_images

    _, image, cat = field
    out = tmp_path / "n.fits"
    assert main(["imstack", str(image), str(cat), str(out), "--stamp-size", "32", "--json",
                 "--noise-estimator", "std", "--noise-stamp-size", "41", "--no-png"]) == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["noise_estimator"] == "std" and payload["noise_stamp_size"] == 41
    with fits.open(out) as hdul:
        assert hdul[0].header["STNOISE"] == "std" and hdul[0].header["STNOISEN"] == 41
    same = stack_images(image, cat, stamp_size=32, noise_estimator="std", noise_stamp_size=41)
    assert payload["flux_err_jy"] == pytest.approx(same.flux_err_jy, rel=1e-12)
    default = stack_images(image, cat, stamp_size=32)
    assert default.noise_estimator == "clipped" and default.noise_stamp_size == 85
    assert payload["flux_err_jy"] != pytest.approx(default.flux_err_jy, rel=1e-9)
    with pytest.raises(SystemExit) as exc:
        main(["imstack", str(image), str(cat), str(tmp_path / "x.fits"), "--noise-estimator",
              "rms"])
    assert exc.value.code == 2 and "invalid choice" in capsys.readouterr().err
    assert not (tmp_path / "x.fits").exists()


def test_cli_errors_write_nothing(field, tmp_path, capsys):
    d, image, cat = field
    out = tmp_path / "bad.fits"
    assert main(["imstack", str(image), str(cat), str(out), "--stamp-size", "5000"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error:") and "larger than the image" in err and "Traceback" not in err
    far = tmp_path / "far.csv"
    far.write_text("ra,dec\n10.0,20.0\n")
    assert main(["imstack", str(image), str(far), str(out)]) == 1
    assert "outside every image" in capsys.readouterr().err
    assert main(["imstack", str(image), str(cat)]) == 1
    assert list(tmp_path.iterdir()) == [far]
