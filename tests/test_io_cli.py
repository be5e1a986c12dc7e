"""``xstack convert`` and ``xstack export`` on the command line."""

from __future__ import annotations

import json

import casacore.tables as pt
from _io_helpers import assert_cells_equal, ms_cells, store_cells

from xstack.cli import main
from xstack.testing import make_test_ms


def test_cli_convert_export_json(tmp_path, capsys):
    ms = make_test_ms(tmp_path / "in.ms", n_fields=2, n_times=6, missing_rows=0.2, seed=4)
    store, ms2 = tmp_path / "s.zarr", tmp_path / "out.ms"
    assert main(["convert", str(ms), str(store), "--chunks", "time=4,baseline_id=7", "--json"]) == 0
    out, err = capsys.readouterr()
    summary = json.loads(out)  # stdout holds exactly one JSON object
    assert sorted(summary["partitions"]) == ["spw0_field0", "spw0_field1"]
    part = summary["partitions"]["spw0_field0"]
    assert part["chunks"] == {"time": 4, "baseline_id": 7}
    assert part["polarization"] == ["XX", "YY"]
    assert summary["data_column"] == "DATA"
    assert summary["n_visibilities"] == sum(
        p["time"] * p["baseline_id"] * p["frequency"] * p["polarization"].__len__()
        for p in summary["partitions"].values())
    assert "convert in.ms" not in err  # progress bars only on a terminal
    assert main(["export", str(store), str(ms2), "--json"]) == 0
    out, err = capsys.readouterr()
    result = json.loads(out)
    with pt.table(str(ms), ack=False) as t:
        assert result["n_rows"] == t.nrows()
    assert "export out.ms" not in err
    assert_cells_equal(ms_cells(ms), ms_cells(ms2))
    assert_cells_equal(ms_cells(ms), store_cells(store)[0])


def test_cli_quiet_without_json(tmp_path, capsys):
    ms = make_test_ms(tmp_path / "in.ms", n_times=3)
    assert main(["convert", str(ms), str(tmp_path / "s.zarr"), "--no-progress"]) == 0
    assert main(["export", str(tmp_path / "s.zarr"), str(tmp_path / "o.ms"), "--no-progress"]) == 0
    out, err = capsys.readouterr()
    # one result line per command on stdout, nothing on stderr
    lines = out.splitlines()
    assert len(lines) == 2 and lines[0].startswith(f"wrote {tmp_path / 's.zarr'}: 1 partition, ")
    assert lines[1].startswith(f"wrote {tmp_path / 'o.ms'}: ") and err == ""
    assert main(["convert", str(ms), str(tmp_path / "s.zarr"), "--overwrite", "--no-progress",
                 "--datacolumn", "data"]) == 0
