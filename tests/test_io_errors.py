"""Bad input to convert/export: one-line error naming the problem, nothing written or modified."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

import casacore.tables as pt
import pytest
import zarr
from _io_helpers import tree_listing

from xstack.cli import main
from xstack.errors import XstackError
from xstack.io.convert import convert_ms, parse_chunks
from xstack.io.export import export_ms
from xstack.testing import make_test_ms


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    d = tmp_path_factory.mktemp("good")
    ms = make_test_ms(d / "good.ms", n_times=4)
    store = convert_ms(ms, d / "good.zarr")
    return ms, store


def _snapshot(path):
    """{file: (size, mtime, sha256)} of every file under ``path`` (or of the file itself)."""
    path = Path(path)
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    out = {}
    for f in files:
        st = f.stat()
        out[str(f)] = (st.st_size, st.st_mtime_ns, hashlib.sha256(f.read_bytes()).hexdigest())
    return out


def _fails(func, args, match, workdir):
    """``func(*args)`` raises a one-line XstackError; nothing under ``workdir`` and no input
    (any existing path among ``args``) is written, modified or even touched."""
    watched = [Path(workdir), *(Path(a) for a in args if isinstance(a, (str, os.PathLike))
                                and Path(a).exists())]
    before = [(tree_listing(w) if w.is_dir() else None, _snapshot(w)) for w in watched]
    with pytest.raises(XstackError, match=match) as info:
        func(*args)
    msg = str(info.value)
    assert "\n" not in msg and len(msg) < 300
    after = [(tree_listing(w) if w.is_dir() else None, _snapshot(w)) for w in watched]
    for w, b, a in zip(watched, before, after):
        assert a[0] == b[0], f"something was written under {w}"
        assert a[1] == b[1], f"something under {w} was modified"
    return msg


def _cli_fails(argv, match, capsys, workdir=None):
    """The command exits 1 with one ``error:`` line and no traceback; with ``workdir``, it
    also writes or modifies nothing there nor in its existing input paths."""
    watched = [Path(a) for a in ([workdir] if workdir else []) + [a for a in argv if os.sep in a]
               if Path(a).exists()]
    before = [_snapshot(w) for w in watched]
    listing = [tree_listing(w) if w.is_dir() else None for w in watched]
    status = main(argv)
    out, err = capsys.readouterr()
    assert status == 1
    assert out == ""
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    assert pytest.importorskip("re").search(match, lines[0]), lines[0]
    assert [tree_listing(w) if w.is_dir() else None for w in watched] == listing
    assert [_snapshot(w) for w in watched] == before


# -- convert -----------------------------------------------------------------------------------

def test_convert_not_an_ms(tmp_path, good, capsys):
    ms, store = good
    (tmp_path / "file.ms").write_text("not a table")
    (tmp_path / "dir.ms").mkdir()
    out = tmp_path / "o.zarr"
    _fails(convert_ms, (tmp_path / "nothing.ms", out), "no such MeasurementSet", tmp_path)
    _fails(convert_ms, (tmp_path / "file.ms", out), "not a MeasurementSet", tmp_path)
    _fails(convert_ms, (tmp_path / "dir.ms", out), "not a MeasurementSet", tmp_path)
    _fails(convert_ms, (store, out), "not a MeasurementSet", tmp_path)
    # a casacore table that is not an MS (a subtable)
    _fails(convert_ms, (ms / "ANTENNA", out), r"not a MeasurementSet \(no column TIME\)", tmp_path)
    _cli_fails(["convert", str(tmp_path / "dir.ms"), str(out)], "not a MeasurementSet", capsys, tmp_path)


def test_convert_missing_or_unknown_column(tmp_path, good, capsys):
    ms, _ = good
    out = tmp_path / "o.zarr"
    for col, match in (("CORRECTED_DATA", "has no CORRECTED_DATA column"),
                       ("FOO", "unknown data column 'FOO'"),
                       ("FLAG", "'FLAG' is not a visibility column")):
        _fails(lambda m, o, c=col: convert_ms(m, o, datacolumn=c), (ms, out), match, tmp_path)
    assert tree_listing(tmp_path) == []
    _cli_fails(["convert", str(ms), str(out), "--datacolumn", "MODEL_DATA"], "no MODEL_DATA column",
               capsys, tmp_path)


def test_convert_empty_ms(tmp_path, capsys):
    import numpy as np

    from xstack.io._mswrite import create_ms, write_subtables

    ms = tmp_path / "e.ms"
    create_ms(ms, [(4, 2)]).close()
    write_subtables(ms, antenna_names=["A", "B"], antenna_positions=np.zeros((2, 3)),
                    dish_diameters=np.full(2, 12.0), telescope_name="ALMA",
                    fields=[{"name": "f", "phase_center": (1.0, -0.5)}],
                    spws=[{"chan_freq": np.arange(4) * 1e6 + 1e9, "chan_width": np.full(4, 1e6)}],
                    pol_setups=[["XX", "YY"]], data_descriptions=[(0, 0)], time_range=(0.0, 1.0))
    _fails(convert_ms, (ms, tmp_path / "o.zarr"), "has no rows", tmp_path)
    _cli_fails(["convert", str(ms), str(tmp_path / "o.zarr")], "has no rows", capsys, tmp_path)


def test_convert_existing_output(tmp_path, good, capsys):
    ms, _ = good
    out = tmp_path / "o.zarr"
    out.mkdir()
    (out / "precious.txt").write_text("keep me")
    _fails(convert_ms, (ms, out), "exists .*overwrite=True", tmp_path)
    _cli_fails(["convert", str(ms), str(out)], "exists", capsys, tmp_path)
    assert (out / "precious.txt").read_text() == "keep me"
    convert_ms(ms, out, overwrite=True)
    assert not (out / "precious.txt").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["o.zarr"]  # no temporaries left behind


def test_convert_bad_chunks(tmp_path, good, capsys):
    ms, _ = good
    for spec, match in (("time=0", "positive integer"), ("time=abc", "positive integer"),
                        ("frequency=2", "cannot chunk dimension 'frequency'"),
                        ("time", "bad chunk specification")):
        with pytest.raises(XstackError, match=match):
            parse_chunks(spec)
        _cli_fails(["convert", str(ms), str(tmp_path / "o.zarr"), "--chunks", spec], match, capsys, tmp_path)
    with pytest.raises(XstackError, match="positive integer"):
        convert_ms(ms, tmp_path / "o.zarr", chunks={"time": -3})
    assert tree_listing(tmp_path) == []


def test_convert_missing_output_directory(tmp_path, good):
    ms, _ = good
    _fails(convert_ms, (ms, tmp_path / "no" / "such" / "o.zarr"), "does not exist", tmp_path)


# -- export ------------------------------------------------------------------------------------

def test_export_not_a_store(tmp_path, good, capsys):
    ms, _ = good
    out = tmp_path / "o.ms"
    _fails(export_ms, (tmp_path / "nothing.zarr", out), "no such store", tmp_path)
    _fails(export_ms, (ms, out), "not a zarr v3 store", tmp_path)
    plain = tmp_path / "plain.zarr"
    g = zarr.open_group(str(plain), mode="w", zarr_format=3)
    g.create_array("x", shape=(3,), dtype="f8")
    _fails(export_ms, (plain, out), "neither an xstack store nor an MSv4", tmp_path)
    _cli_fails(["export", str(plain), str(out)], "neither an xstack store nor an MSv4", capsys,
               tmp_path)


def test_export_corrupt_store(tmp_path, good, capsys):
    _, store = good
    out = tmp_path / "o.ms"
    bad = tmp_path / "bad.zarr"
    shutil.copytree(store, bad)
    (bad / "zarr.json").write_text("{ not json")
    _fails(export_ms, (bad, out), "corrupt zarr.json", tmp_path)
    _cli_fails(["export", str(bad), str(out)], "corrupt zarr.json", capsys, tmp_path)
    # an interrupted write: completion flag not set
    inc = tmp_path / "incomplete.zarr"
    shutil.copytree(store, inc)
    meta = json.loads((inc / "zarr.json").read_text())
    meta["attributes"]["xstack_complete"] = False
    (inc / "zarr.json").write_text(json.dumps(meta))
    _fails(export_ms, (inc, out), "incomplete store", tmp_path)
    # a partition that lost its visibilities
    lost = tmp_path / "lost.zarr"
    shutil.copytree(store, lost)
    shutil.rmtree(lost / "spw0_field0" / "VISIBILITY")
    _fails(export_ms, (lost, out), "no partitions|VISIBILITY|cannot be opened", tmp_path)


def test_export_damaged_chunk(tmp_path, good, capsys):
    """Valid metadata, but a chunk that does not decode: a one-line error naming the array
    and chunk, and no MS (not even a temporary) is left behind."""
    _, store = good
    bad = tmp_path / "bad.zarr"
    shutil.copytree(store, bad)
    (chunk,) = [f for f in (bad / "spw0_field0" / "WEIGHT" / "c").rglob("*") if f.is_file()]
    chunk.write_bytes(b"garbage" * 10)
    out = tmp_path / "o.ms"
    _fails(export_ms, (bad, out), r"spw0_field0/WEIGHT \(time 0:4, baseline_id 0:\d+\): cannot be "
           "read, the store is damaged", tmp_path)
    _cli_fails(["export", str(bad), str(out)], "WEIGHT .*the store is damaged", capsys, tmp_path)


def test_export_store_with_unsafe_codec(tmp_path, good, capsys):
    """A store from elsewhere asking for a pickle codec is refused before anything is read."""
    _, store = good
    bad = tmp_path / "pickled.zarr"
    shutil.copytree(store, bad)
    meta_file = bad / "spw0_field0" / "FLAG" / "zarr.json"
    meta = json.loads(meta_file.read_text())
    meta["codecs"] = [{"name": "numcodecs.pickle", "configuration": {"protocol": 5}}]
    meta_file.write_text(json.dumps(meta))
    out = tmp_path / "o.ms"
    _fails(export_ms, (bad, out), "FLAG: codec 'numcodecs.pickle' is not allowed", tmp_path)
    _cli_fails(["export", str(bad), str(out)], "codec 'numcodecs.pickle' is not allowed", capsys,
               tmp_path)


def test_export_existing_output(tmp_path, good, capsys):
    _, store = good
    out = tmp_path / "o.ms"
    out.mkdir()
    (out / "precious.txt").write_text("keep me")
    _fails(export_ms, (store, out), "exists .*overwrite=True", tmp_path)
    _cli_fails(["export", str(store), str(out)], "exists", capsys, tmp_path)
    assert (out / "precious.txt").read_text() == "keep me"
    export_ms(store, out, overwrite=True)
    with pt.table(str(out), ack=False) as t:
        assert t.nrows() > 0
    assert [p.name for p in tmp_path.iterdir()] == ["o.ms"]


def test_convert_unsupported_phase_center_frame(tmp_path):
    ms = make_test_ms(tmp_path / "f.ms", n_times=2)
    with pt.table(f"{ms}/FIELD", readonly=False, ack=False) as t:
        kw = t.getcolkeywords("PHASE_DIR")
        kw["MEASINFO"]["Ref"] = "AZEL"
        t.putcolkeywords("PHASE_DIR", kw)
    _fails(convert_ms, (ms, tmp_path / "o.zarr"), "phase center frame AZEL is not supported", tmp_path)
