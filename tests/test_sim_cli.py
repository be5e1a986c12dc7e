"""``xstack simulate`` on the command line."""

from __future__ import annotations

import json

import numpy as np
from astropy.table import Table

from xstack.cli import main
from xstack.schema import open_store

SCENE = """
name = "cli"
[array]
config = "vla.d"
antennas = ["W08", "E08", "N08", "W02"]
[observation]
time_per_pointing = 30.0
[spectral]
channels = 3
[effects]
noise = { sigma = 0.01 }
[[populations]]
name = "targets"
count = 3
flux = { kind = "fixed", value = "2mJy" }
positions = { kind = "box", size_arcsec = [60, 60] }
"""


def test_cli_scene_file_json(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE)
    out = tmp_path / "o.zarr"
    assert main(["simulate", str(scene), str(out), "--seed", "4", "--json", "--no-progress"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["n_sources"] == {"targets": 3} and info["n_pointings"] == 1
    assert info["n_visibilities"] == 3 * 6 * 3 * 2 and info["seed"] == 4
    assert set(info["steps"]) == {"model", "phase", "noise"}
    ds = open_store(out)["spw0_field0"].to_dataset()
    assert ds.sizes["baseline_id"] == 6 and ds.sizes["time"] == 3
    t = Table.read(info["catalogs"]["targets"])
    assert np.all(t["flux"] == 2e-3)


def test_cli_preset_and_errors(tmp_path, capsys):
    out = tmp_path / "p.zarr"
    assert main(["simulate", "--preset", "paper-9", str(out), "--scale", "0.05",
                 "--no-progress"]) == 0
    assert len(list(open_store(out).children)) == 10
    capsys.readouterr()
    # existing output, bad preset, both scene and preset, bad scale, TOML typo
    assert main(["simulate", "--preset", "paper-9", str(out), "--scale", "0.05"]) == 1
    assert "exists" in capsys.readouterr().err
    assert main(["simulate", "--preset", "paper-99", str(tmp_path / "x.zarr")]) == 1
    assert "unknown preset" in capsys.readouterr().err
    scene = tmp_path / "s.toml"
    scene.write_text(SCENE.replace("channels = 3", "chanels = 3"))
    assert main(["simulate", str(scene), str(tmp_path / "y.zarr")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "spectral.chanels" in err and err.count("\n") == 1
    assert main(["simulate", str(scene), str(tmp_path / "y.zarr"), "--preset", "paper-1"]) == 1
    assert main(["simulate", "--preset", "paper-1", str(tmp_path / "z.zarr"), "--scale", "2"]) == 1
    capsys.readouterr()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.bright.ecsv", "p.targets.ecsv",
                                                          "p.zarr", "s.toml"]
