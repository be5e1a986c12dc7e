"""``xstack simulate`` on the command line."""

from __future__ import annotations

import json

import numpy as np
from _sim_helpers import TINY_SCENE
from astropy.table import Table

from xstack.cli import main
from xstack.schema import open_store

SCENE = TINY_SCENE



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


def test_print_scene_round_trips_every_preset(tmp_path, capsys):
    import tomllib

    from xstack.sim.presets import PRESETS, preset_scene
    from xstack.sim.scene import load_scene

    for name in PRESETS:
        assert main(["simulate", "--preset", name, "--print-scene"]) == 0
        text = capsys.readouterr().out
        assert load_scene(tomllib.loads(text)) == preset_scene(name)
    # a scaled preset written out and simulated from the file
    assert main(["simulate", "--preset", "paper-1", "--print-scene", "--scale", "0.01"]) == 0
    path = tmp_path / "p1.toml"
    path.write_text(capsys.readouterr().out)
    assert load_scene(path) == preset_scene("paper-1").scaled(0.01)
    assert main(["simulate", str(path)]) == 1
    assert "missing the output store" in capsys.readouterr().err
