"""A damaged chunk (a chunk file that does not decode) in every stage that reads chunks: one
``error:`` line naming the store, the variable and the chunk, exit status 1, no traceback,
nothing written (issue 11 item 6)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, make_stack_partition

from xstack.cli import main
from xstack.coords import lm_to_radec
from xstack.errors import XstackError
from xstack.schema import open_store, write_store

GARBAGE = b"not a zstd frame" * 4


def _corrupt(store: Path, var: str = "VISIBILITY") -> Path:
    """Overwrite the first chunk file of ``var`` (in the only partition) with garbage."""
    files = sorted(f for f in (store / "spw0_field0" / var / "c").rglob("*") if f.is_file())
    files[0].write_bytes(GARBAGE)
    return files[0]


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """Good and damaged data and stacked stores, and a catalog with a flux column."""
    from xstack.uvstack.stack import stack_uv

    d = tmp_path_factory.mktemp("damaged")
    ra, dec = lm_to_radec(2e-3, -1e-3, *VLA_CENTER)
    ds = make_stack_partition(n_time=10, n_ant=7, n_chan=3, sigma=0.01, seed=21,
                              sources=[(ra, dec, 0.05)], dtype=np.complex64)
    data = write_store({"spw0_field0": ds}, d / "data.zarr")
    cat = d / "cat.csv"
    cat.write_text(f"ra,dec,flux\n{float(np.degrees(ra))!r},{float(np.degrees(dec))!r},0.05\n")
    stacked = d / "stacked.zarr"
    with pytest.warns(UserWarning):  # random visibilities: the weights are "mis-scaled"
        stack_uv(data, str(cat), primary_beam="none", out=stacked)
    bad = d / "bad.zarr"
    shutil.copytree(data, bad)
    _corrupt(bad)
    bad_stacked = d / "bad_stacked.zarr"
    shutil.copytree(stacked, bad_stacked)
    _corrupt(bad_stacked)
    return {"data": data, "bad": bad, "bad_stacked": bad_stacked, "cat": cat}


def _listing(path: Path) -> set[str]:
    return {str(p.relative_to(path)) for p in path.rglob("*")}


def _one_error_line(err: str, store: Path, var: str = "VISIBILITY") -> str:
    lines = [x for x in err.splitlines() if x.strip()]
    assert len(lines) == 1, err
    line = lines[0]
    assert line.startswith("error: "), line
    # the store, the variable and the chunk (its ranges and its file)
    assert f"{store}/spw0_field0/{var} (time 0:10, baseline_id 0:21)" in line, line
    assert "cannot be read, the store is damaged" in line and "chunk file c/0/0/0/0" in line
    assert "Traceback" not in err
    return line


@pytest.mark.parametrize("command", ["uvstack", "image", "subtract", "fit", "noise-analytic",
                                     "noise-bootstrap"])
def test_damaged_chunk_one_line_error(command, stores, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    bad, cat = stores["bad"], stores["cat"]
    argv = {
        "uvstack": ["uvstack", str(bad), str(cat), "out.zarr", "--primary-beam", "none"],
        "image": ["image", str(bad), "out.fits", "--size", "64", "--cell", "1"],
        "subtract": ["subtract", str(bad), str(cat), "out.zarr"],
        "fit": ["fit", str(stores["bad_stacked"]), "--png", "fit.png"],
        "noise-analytic": ["noise", str(bad), str(cat), "--method", "analytic", "--table",
                           "t.ecsv"],
        "noise-bootstrap": ["noise", str(bad), str(cat), "--method", "bootstrap",
                            "--realizations", "3", "--table", "t.ecsv"],
    }[command]
    before = _listing(stores["bad"].parent)
    capsys.readouterr()
    rc = main(argv)
    out, err = capsys.readouterr()
    assert rc == 1 and out == ""
    _one_error_line(err, stores["bad_stacked"] if command == "fit" else bad)
    assert list(tmp_path.iterdir()) == []  # nothing written, not even a temporary
    assert _listing(stores["bad"].parent) == before  # inputs untouched


def test_damaged_weight_chunk_names_weight(stores, tmp_path, capsys):
    bad = tmp_path / "badw.zarr"
    shutil.copytree(stores["data"], bad)
    _corrupt(bad, "WEIGHT")
    rc = main(["uvstack", str(bad), str(stores["cat"]), str(tmp_path / "o.zarr")])
    assert rc == 1
    _one_error_line(capsys.readouterr().err, bad, "WEIGHT")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["badw.zarr"]


def test_library_raises_xstack_error(stores):
    """The library raises one XstackError (not the codec's RuntimeError) wherever the chunk
    is computed."""
    tree = open_store(stores["bad"])
    with pytest.raises(XstackError, match=re.escape("spw0_field0/VISIBILITY (time 0:10")):
        tree["spw0_field0"]["VISIBILITY"].values  # noqa: B018
    with pytest.raises(XstackError, match="store is damaged"):
        tree["spw0_field0"]["VISIBILITY"].data.sum().compute()
    # the undamaged variables still read
    assert np.isfinite(tree["spw0_field0"]["UVW"].values).all()


def test_real_process_prints_no_traceback(stores, tmp_path):
    """The installed command, in its own process: one line, status 1."""
    proc = subprocess.run([sys.executable, "-m", "xstack", "image", str(stores["bad"]),
                           str(tmp_path / "o.fits"), "--size", "64", "--cell", "1"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1 and proc.stdout == ""
    _one_error_line(proc.stderr, stores["bad"])
    assert list(tmp_path.iterdir()) == []
