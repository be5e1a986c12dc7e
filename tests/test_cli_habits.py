"""CLI habits, the same in every command (issue 11 item 4): results on stdout, messages on
stderr, ``--json`` alone on stdout, progress bars only on a terminal, ``-q``, ``-v``,
``--log FILE``, and one way of printing figures."""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys

import numpy as np
import pytest
from _imstack_helpers import make_field
from _sim_helpers import TINY_SCENE
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.table import Table

from xstack.cli import build_parser, main
from xstack.cli._output import count, figure
from xstack.coords import lm_to_radec
from xstack.schema import write_store
from xstack.testing import make_test_ms

SCENE = TINY_SCENE


FLUX = 0.05  # Jy, the point source at the catalog position


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("habits")
    ra, dec = lm_to_radec(2e-3, -1e-3, *VLA_CENTER)
    ds = make_stack_partition(n_time=10, n_ant=7, n_chan=3, sigma=0.01, seed=21,
                              sources=[(ra, dec, FLUX)], dtype=np.complex64)
    data = write_store({"spw0_field0": ds}, d / "data.zarr")
    cat = d / "cat.csv"
    cat.write_text(f"ra,dec,flux\n{float(np.degrees(ra))!r},{float(np.degrees(dec))!r},"
                   f"{FLUX}\n")
    ms = make_test_ms(d / "in.ms", n_times=4, seed=3)
    scene = d / "scene.toml"
    scene.write_text(SCENE)
    image, ira, idec, _, _ = make_field(d, np.random.default_rng(21), 0.5, beam=(3.2, 1.6, 0.0),
                                       n_side=4, noise=0.01, psf=True)
    icat = d / "icat.ecsv"
    Table({"ra": ira, "dec": idec}).write(icat)
    return {"data": data, "cat": cat, "ms": ms, "scene": scene, "image": image, "icat": icat}


def _argv(command, inputs, tmp):
    """A small successful run of ``command``; outputs under ``tmp``."""
    i = inputs
    return {
        "convert": ["convert", str(i["ms"]), str(tmp / "c.zarr")],
        "export": ["export", str(i["data"]), str(tmp / "e.ms")],
        "simulate": ["simulate", str(i["scene"]), str(tmp / "s.zarr")],
        "image": ["image", str(i["data"]), str(tmp / "i.fits"), "--size", "64", "--cell", "2"],
        "subtract": ["subtract", str(i["data"]), str(i["cat"]), str(tmp / "r.zarr"),
                     "--primary-beam", "none"],
        "uvstack": ["uvstack", str(i["data"]), str(i["cat"]), str(tmp / "u.zarr"),
                    "--primary-beam", "none"],
        "imstack": ["imstack", str(i["image"]), str(i["icat"]), str(tmp / "m.fits"),
                    "--stamp-size", "16", "--no-png"],
        "noise": ["noise", str(i["data"]), str(i["cat"]), "--method", "analytic"],
    }[command]


RESULT = {  # what the result on stdout starts with
    "convert": "wrote ", "export": "wrote ", "simulate": "wrote ", "image": "wrote ",
    "subtract": "wrote ", "uvstack": "stacked flux ", "imstack": "stacked flux ",
    "noise": "noise estimate ",
}


def test_every_command_has_the_common_options():
    top = build_parser()
    (sub,) = [a for a in top._actions if isinstance(a, argparse._SubParsersAction)]
    for name, parser in sub.choices.items():
        flags = set(parser._option_string_actions)
        assert {"-q", "--quiet", "-v", "--verbose", "--log", "--no-progress"} <= flags, name
        with pytest.raises(SystemExit):  # -q and -v exclude each other
            parser.parse_args(["-q", "-v"])


@pytest.mark.parametrize("command", list(RESULT))
def test_result_on_stdout_json_alone(command, inputs, tmp_path, capsys):
    """Each command prints its result on stdout (and nothing but warnings on stderr); -v
    adds detail on stderr, not on stdout; with --json stdout is exactly one JSON object."""
    argv = _argv(command, inputs, tmp_path / "h")
    (tmp_path / "h").mkdir()
    assert main(argv) == 0
    out, err = capsys.readouterr()
    assert out.startswith(RESULT[command]), out
    assert all(x.startswith("warning: ") for x in err.splitlines()), err
    (tmp_path / "v").mkdir()
    assert main([*_argv(command, inputs, tmp_path / "v"), "-v"]) == 0
    out_v, err_v = capsys.readouterr()
    assert out_v.startswith(RESULT[command]) and out_v.count("\n") == out.count("\n")
    assert err_v.splitlines()[-1].startswith(f"xstack {command}: done in ")
    (tmp_path / "j").mkdir()
    assert main([*_argv(command, inputs, tmp_path / "j"), "--json"]) == 0
    out, err = capsys.readouterr()
    assert isinstance(json.loads(out), dict)  # one object, nothing else on stdout
    assert all(x.startswith("warning: ") for x in err.splitlines()), err


def test_uvstack_result_survives_redirect(inputs, tmp_path):
    """`xstack uvstack ... > out.txt` keeps the result (it used to go to stderr)."""
    out_txt = tmp_path / "out.txt"
    with out_txt.open("w") as fh:
        proc = subprocess.run([sys.executable, "-m", "xstack",
                               *_argv("uvstack", inputs, tmp_path)],
                              stdout=fh, stderr=subprocess.PIPE, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    text = out_txt.read_text()
    assert "stacked flux" in text and "stacked flux" not in proc.stderr
    # the figure: "60.10 ± 1.25 mJy", the point source within 5 sigma
    m = re.search(r"stacked flux (-?[\d.]+) ± ([\d.]+) (mJy|µJy|Jy) ", text)
    assert m, text
    scale = {"Jy": 1.0, "mJy": 1e-3, "µJy": 1e-6}[m.group(3)]
    flux, err = float(m.group(1)) * scale, float(m.group(2)) * scale
    assert abs(flux - FLUX) < 5 * err
    assert len(m.group(1).split(".")[1]) == len(m.group(2).split(".")[1])  # matching decimals
    assert "from 1 position," in text  # singular


def test_progress_bars_only_on_a_terminal(inputs, tmp_path, capsys, monkeypatch):
    def convert(name, *extra):
        assert main(["convert", str(inputs["ms"]), str(tmp_path / name), *extra]) == 0
        return capsys.readouterr().err

    assert "convert in.ms" not in convert("a.zarr")  # not a terminal: no bar
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    assert "convert in.ms" in convert("b.zarr")  # a terminal: the bar
    assert convert("c.zarr", "-q") == ""  # -q: neither bar nor messages
    assert "convert in.ms" not in convert("d.zarr", "--no-progress")


def test_quiet_verbose_and_log(inputs, tmp_path, capsys):
    # verbose: detail on stderr (the partitions), the result unchanged on stdout
    assert main(["convert", str(inputs["ms"]), str(tmp_path / "v.zarr"), "-v"]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("wrote ") and "spw0_field0: field" in err
    assert main(["convert", str(inputs["ms"]), str(tmp_path / "n.zarr")]) == 0
    out2, err2 = capsys.readouterr()
    assert "spw0_field0: field" not in err2 and out2.startswith("wrote ")
    # quiet: only warnings on stderr (random noise: the weights warning), result on stdout
    log = tmp_path / "run.log"
    argv = _argv("uvstack", inputs, tmp_path)
    assert main([*argv, "-q", "--log", str(log)]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("stacked flux")
    assert err and all(x.startswith("warning: ") for x in err.splitlines())
    text = log.read_text()
    assert f"$ xstack {' '.join(argv)} -q --log {log}" in text
    assert "stacked flux" in text and "warning: " in text
    # errors go to the log as well, appended
    assert main([*argv, "--log", str(log)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1
    assert log.read_text().startswith(text) and "error: " in log.read_text()[len(text):]
    # a log that cannot be written: one error line
    assert main([*argv, "--log", str(tmp_path / "no" / "dir" / "x.log"), "--overwrite"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: --log") and err.count("\n") == 1


def test_figures():
    """One formatter: value and error to matching decimals, one SI prefix, plurals."""
    assert figure(16.49e-6, 3.18e-6) == "16.49 ± 3.18 µJy"
    assert figure(0.0601, 0.00125) == "60.10 ± 1.25 mJy"
    assert figure(2.5, 0.25) == "2.500 ± 0.250 Jy"  # three significant figures of the error
    assert figure(5.01e-3, unit="Jy/beam") == "5.01 mJy/beam"
    assert figure(3.0e-4, like=[0.06]) == "0.300 mJy"  # the line's prefix
    assert figure(1.52, 0.1, "arcsec") == "1.520 ± 0.100 arcsec"  # no prefix on arcsec
    assert figure(None) == "n/a"
    assert count(1, "position") == "1 position" and count(2, "position") == "2 positions"
    assert count(1260, "visibility") == "1,260 visibilities"


def test_imstack_result_per_beam(inputs, tmp_path, capsys):
    assert main(_argv("imstack", inputs, tmp_path)) == 0
    out = capsys.readouterr().out
    assert re.search(r"stacked flux -?[\d.]+ ± [\d.]+ [mµ]?Jy/beam at the stacking position "
                     r"from 16 positions", out), out


@pytest.mark.parametrize("command", ["convert", "export", "simulate", "image", "subtract",
                                     "uvstack", "imstack"])
def test_output_under_a_file_is_one_line_and_loses_nothing(command, inputs, tmp_path, capsys):
    """An output path whose parent is a regular file cannot be made: every command says so in
    one ``error:`` line (no traceback), exits 1, and leaves the file as it was."""
    blocker = tmp_path / "afile"
    blocker.write_text("keep me")
    assert main([*_argv(command, inputs, blocker), "-q"]) == 1
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(errors) == 1, err
    assert errors[0].startswith(f"error: {blocker} is a file, not a directory: "), errors
    assert ".partial-" not in errors[0], errors
    assert "Traceback" not in err
    assert blocker.read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_demo_outdir_under_a_file(tmp_path, capsys):
    blocker = tmp_path / "afile"
    blocker.write_text("keep me")
    assert main(["demo", "--outdir", str(blocker / "sub"), "-q"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {blocker / 'sub'}: Not a directory"], err
    assert blocker.read_text() == "keep me"
