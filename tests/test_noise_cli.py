"""``xstack noise`` command line."""

from __future__ import annotations

import json

import numpy as np
from _fit_helpers import noise_field

from xstack.cli import main
from xstack.noise.positions import random_positions
from xstack.schema import write_store


def _setup(tmp_path):
    from astropy.table import Table

    ds, _, _ = noise_field(0, n_ant=8, n_time=6, extent_m=20e3)
    store = write_store({"spw0_field0": ds}, tmp_path / "d.zarr")
    ra, dec = random_positions(10, 1, np.array([[1.0, -0.5236]]), np.array([np.radians(0.15)]),
                               avoid_ra=np.zeros(0), avoid_dec=np.zeros(0),
                               min_separation=np.radians(30 / 3600), rng=np.random.default_rng(0))
    cat = tmp_path / "cat.csv"
    Table({"ra": np.degrees(ra[0]), "dec": np.degrees(dec[0]),
           "flux": np.full(10, 0.05)}).write(cat, format="ascii.csv")
    return store, cat


def test_noise_cli(tmp_path, capsys):
    store, cat = _setup(tmp_path)
    png, prof, table = tmp_path / "h.png", tmp_path / "p.png", tmp_path / "t.ecsv"
    status = main(["noise", str(store), str(cat), "--method", "mc", "--realizations", "20",
                   "--png", str(png), "--profile-png", str(prof), "--table", str(table),
                   "--json"])
    out, _ = capsys.readouterr()
    assert status == 0
    d = json.loads(out)
    assert d["realizations"] == 20 and d["noise_jy"] > 0 and d["bias_jy"] is not None
    assert np.mean(d["injected_jy"]) > 0.04  # the catalog flux was injected
    for p in (png, prof, table):
        assert p.exists() and p.stat().st_size > 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    # existing outputs are not overwritten
    status = main(["noise", str(store), str(cat), "--png", str(png)])
    assert status == 1 and "exists" in capsys.readouterr().err
    for method in ("analytic", "random", "bootstrap"):
        assert main(["noise", str(store), str(cat), "--method", method, "--realizations", "5",
                     "--json"]) == 0
        d = json.loads(capsys.readouterr().out)
        assert d["method"] == method and d["noise_jy"] > 0


def test_noise_cli_bad_input(tmp_path, capsys):
    store, cat = _setup(tmp_path)
    assert main(["noise", str(store), str(cat), "--realizations", "1"]) == 1
    assert "at least 2 realisations" in capsys.readouterr().err
    assert main(["noise", str(store), str(cat), "--method", "random", "--realizations", "3",
                 "--min-separation", "900"]) == 1
    assert "too dense" in capsys.readouterr().err
    assert main(["noise", str(store), str(cat), "--uvmax", "1lambda", "--realizations", "3"]) == 1
    assert "no visibilities left" in capsys.readouterr().err


def test_noise_cli_engines_agree(tmp_path, capsys):
    store, cat = _setup(tmp_path)
    out = {}
    for engine in ("antenna", "numba"):
        assert main(["noise", str(store), str(cat), "--method", "random", "--realizations", "6",
                     "--engine", engine, "--json"]) == 0
        out[engine] = json.loads(capsys.readouterr().out)
    assert out["antenna"]["engine"] == "antenna" and out["numba"]["engine"] == "numba"
    assert abs(out["antenna"]["noise_jy"] / out["numba"]["noise_jy"] - 1) < 1e-9


def test_noise_cli_region_and_warnings(tmp_path, capsys):
    """The region used is printed (text and JSON); a poorly defined footprint warns,
    naming --region; analytic prints the optimal-weights noise beside its own."""
    from astropy.table import Table

    store, cat = _setup(tmp_path)
    assert main(["noise", str(store), str(cat), "--method", "random", "--realizations", "4"]) == 0
    out = capsys.readouterr().out
    assert "region: hull: convex hull of 10 targets" in out and "arcmin^2" in out
    assert main(["noise", str(store), str(cat), "--method", "mc", "--realizations", "4",
                 "--region", "beam", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["region"].startswith("beam:")
    few = tmp_path / "few.csv"
    Table.read(cat, format="ascii.csv")[:5].write(few, format="ascii.csv")
    assert main(["noise", str(store), str(few), "--method", "random", "--realizations",
                 "4"]) == 0
    err = capsys.readouterr().err
    assert "warning: only 5 targets" in err and "--region" in err
    assert main(["noise", str(store), str(cat), "--method", "analytic"]) == 0
    assert "optimal inverse-variance weights" in capsys.readouterr().out
    assert main(["noise", str(store), str(cat), "--method", "random", "--realizations", "3",
                 "--region", "nowhere.ecsv"]) == 1
    assert "not hull, beam" in capsys.readouterr().err
