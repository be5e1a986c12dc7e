"""MS -> zarr -> MS -> zarr round trips, compared with a direct python-casacore read."""

from __future__ import annotations

import json
from pathlib import Path

import casacore.tables as pt
import numpy as np
import pytest
from _io_helpers import assert_cells_equal, assert_stores_identical, ms_cells, store_cells

import xstack
from xstack.io.convert import convert_ms
from xstack.io.export import export_ms
from xstack.schema import iter_partitions, open_store, validate_store
from xstack.testing import make_test_ms, require_real_ms

VARIANTS = {
    "basic": {},
    "mosaic_spws_scans": dict(n_fields=2, n_spws=2, n_channels=[3, 5], scans=4, n_antennas=7,
                              missing_baselines=3, missing_rows=0.15, flag_row_fraction=0.1),
    "weight_row_only": dict(weight_spectrum=False, pols=("RR", "RL", "LR", "LL"), telescope="VLA"),
    "sigma_only": dict(weight_spectrum=False, write_weight=False, missing_rows=0.3),
    "complex128": dict(complex128=True, autocorrelations=True),
}


def _round_trip(ms, tmp_path, **convert_kw):
    z1, ms2, z2 = tmp_path / "a.zarr", tmp_path / "b.ms", tmp_path / "b.zarr"
    convert_ms(ms, z1, **convert_kw)
    export_ms(z1, ms2)
    convert_ms(ms2, z2, **{k: v for k, v in convert_kw.items() if k != "datacolumn"})
    return z1, ms2, z2


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_round_trip_generated(tmp_path, variant):
    ms = make_test_ms(tmp_path / "in.ms", seed=7, **VARIANTS[variant])
    z1, ms2, z2 = _round_trip(ms, tmp_path, chunks={"time": 4, "baseline_id": 6})
    expected = ms_cells(ms)
    cells1, n_pad = store_cells(z1)
    assert_cells_equal(expected, cells1)
    if VARIANTS[variant].get("missing_rows"):
        assert n_pad > 0  # the irregular grid really was padded
    # the exported MS has exactly the original rows (padding dropped) ...
    assert_cells_equal(expected, ms_cells(ms2))
    # ... and converts to an identical store
    assert_stores_identical(z1, z2)
    want = np.complex128 if VARIANTS[variant].get("complex128") else np.complex64
    assert all(ds["VISIBILITY"].dtype == want for _, ds in iter_partitions(open_store(z1)))


def test_store_contents_and_provenance(tmp_path):
    ms = make_test_ms(tmp_path / "in.ms", n_fields=2, n_spws=2, n_channels=[4, 6], scans=3, seed=2)
    out = convert_ms(ms, tmp_path / "s.zarr")
    attrs = validate_store(out)
    assert attrs["source_ms"] == str(ms.resolve())
    assert attrs["data_column"] == "DATA"
    assert attrs["xstack_version"] == xstack.__version__
    parts = dict(iter_partitions(open_store(out)))
    assert sorted(parts) == ["spw0_field0", "spw0_field1", "spw1_field0", "spw1_field1"]
    spw_tab = pt.table(f"{ms}/SPECTRAL_WINDOW", ack=False)
    field_tab = pt.table(f"{ms}/FIELD", ack=False)
    ant_tab = pt.table(f"{ms}/ANTENNA", ack=False)
    for ds in parts.values():
        spw, fid = ds.attrs["spectral_window_id"], ds.attrs["field_id"]
        np.testing.assert_array_equal(ds["frequency"].values, spw_tab.getcell("CHAN_FREQ", spw))
        np.testing.assert_array_equal(ds["channel_width"].values, spw_tab.getcell("CHAN_WIDTH", spw))
        np.testing.assert_array_equal(ds.attrs["phase_center"], field_tab.getcell("PHASE_DIR", fid)[0])
        np.testing.assert_array_equal(ds["ANTENNA_POSITION"].values, ant_tab.getcol("POSITION"))
        np.testing.assert_array_equal(ds["DISH_DIAMETER"].values, ant_tab.getcol("DISH_DIAMETER"))
        assert list(ds["antenna_name"].values) == list(ant_tab.getcol("NAME"))
        assert list(ds["polarization"].values) == ["XX", "YY"]
        assert ds.attrs["telescope_name"] == "ALMA"
        assert ds.attrs["weight_source"] == "WEIGHT_SPECTRUM"
        assert ds["time"].attrs["integration_time"] == 6.0
        assert ds["VISIBILITY"].dtype == np.complex64
    # field 0 is observed in scans 1 and 3 with one integration time: one time grid, no split
    assert set(parts["spw0_field0"]["scan_number"].values.tolist()) == {1, 3}


def test_default_and_user_chunks(tmp_path, monkeypatch):
    ms = make_test_ms(tmp_path / "in.ms", n_antennas=8, n_times=12, n_channels=16)
    # a small target chunk size exercises the default chooser without a big MS
    monkeypatch.setattr("xstack.io.convert.DEFAULT_CHUNK_BYTES", 28 * 16 * 2 * 8 * 5)
    out = convert_ms(ms, tmp_path / "d.zarr")
    ds = dict(iter_partitions(open_store(out)))["spw0_field0"]
    assert ds["VISIBILITY"].data.chunks[0][0] == 5  # 5 integrations of all 28 baselines
    assert ds["VISIBILITY"].data.chunks[1] == (28,)
    assert ds["VISIBILITY"].data.chunks[2:] == ((16,), (2,))
    out2 = convert_ms(ms, tmp_path / "u.zarr", chunks="time=3,baseline_id=10")
    ds2 = dict(iter_partitions(open_store(out2)))["spw0_field0"]
    assert ds2["VISIBILITY"].data.chunks[:2] == ((3, 3, 3, 3), (10, 10, 8))
    # on-disk chunks equal the requested ones
    meta = json.loads((out2 / "spw0_field0" / "VISIBILITY" / "zarr.json").read_text())
    assert meta["chunk_grid"]["configuration"]["chunk_shape"] == [3, 10, 16, 2]
    assert_cells_equal(store_cells(out)[0], store_cells(out2)[0])


def test_other_data_columns(tmp_path):
    ms = make_test_ms(tmp_path / "in.ms", datacolumns=("DATA", "CORRECTED_DATA", "MODEL_DATA"),
                      sources=[(57.2958, -30.0, 1.5)])
    for col in ("corrected_data", "MODEL_DATA"):
        out = convert_ms(ms, tmp_path / f"{col}.zarr", datacolumn=col)
        assert validate_store(out)["data_column"] == col.upper()
        assert_cells_equal(ms_cells(ms, col.upper()), store_cells(out)[0])
    a = store_cells(tmp_path / "MODEL_DATA.zarr")[0]
    b = store_cells(tmp_path / "corrected_data.zarr")[0]
    key = next(iter(a))
    assert not np.array_equal(a[key]["vis"], b[key]["vis"])


def test_scan_split_when_integration_times_differ(tmp_path):
    """One field, two scans with different INTERVAL: a partition per scan."""
    ms = make_test_ms(tmp_path / "in.ms", scans=2, n_times=4)
    with pt.table(str(ms), readonly=False, ack=False) as t:
        scan = t.getcol("SCAN_NUMBER")
        interval = np.where(scan == 2, 3.0, 6.0)
        t.putcol("INTERVAL", interval)
    out = convert_ms(ms, tmp_path / "s.zarr")
    parts = dict(iter_partitions(open_store(out)))
    assert sorted(parts) == ["spw0_field0_scan1", "spw0_field0_scan2"]
    assert parts["spw0_field0_scan2"]["time"].attrs["integration_time"] == 3.0
    assert_cells_equal(ms_cells(ms), store_cells(out)[0])
    ms2 = export_ms(out, tmp_path / "b.ms")
    with pt.table(str(ms2), ack=False) as t:
        got = dict(zip(t.getcol("SCAN_NUMBER").tolist(), t.getcol("INTERVAL").tolist()))
    assert got == {1: 6.0, 2: 3.0}


def test_phase_center_frame_converted_to_icrs(tmp_path):
    """FIELD directions in GALACTIC or B1950 are converted to ICRS."""
    ref = make_test_ms(tmp_path / "j.ms", n_fields=2)

    def centers(store):
        parts = dict(iter_partitions(open_store(store)))
        return [parts[name].attrs["phase_center"] for name in sorted(parts)]

    pc_ref = centers(convert_ms(ref, tmp_path / "j.zarr"))
    for frame in ("GALACTIC", "B1950"):
        ms = make_test_ms(tmp_path / f"{frame}.ms", n_fields=2, field_frame=frame)
        raw = pt.table(f"{ms}/FIELD", ack=False).getcol("PHASE_DIR")[:, 0]
        assert np.abs(raw - pt.table(f"{ref}/FIELD", ack=False).getcol("PHASE_DIR")[:, 0]).max() > 1e-3
        pcs = centers(convert_ms(ms, tmp_path / f"{frame}.zarr"))
        # astropy's FK4 round trip is good to ~1e-9 rad here
        np.testing.assert_allclose(pcs, pc_ref, rtol=0, atol=1e-9)


def test_weight_preference(tmp_path):
    """WEIGHT_SPECTRUM over WEIGHT over SIGMA, shown with deliberately inconsistent columns
    (a SIGMA of 4 would give weights 1/16; WEIGHT is set to 3)."""
    def weights(store):
        ds = dict(iter_partitions(open_store(store)))["spw0_field0"]
        return ds["WEIGHT"].values, ds.attrs["weight_source"]

    def edit(ms, **cols):
        with pt.table(str(ms), readonly=False, ack=False) as t:
            for col, value in cols.items():
                t.putcol(col, np.full(t.getcol(col).shape, value, dtype=np.float32))

    with_ws = make_test_ms(tmp_path / "ws.ms", n_times=3, missing_rows=0.0, seed=1)
    edit(with_ws, WEIGHT=3.0, SIGMA=4.0)
    with pt.table(str(with_ws), ack=False) as t:
        ws = t.getcol("WEIGHT_SPECTRUM")
    w, src = weights(convert_ms(with_ws, tmp_path / "ws.zarr"))
    assert src == "WEIGHT_SPECTRUM"
    np.testing.assert_array_equal(np.sort(w.ravel()), np.sort(ws.ravel()))
    assert not np.any(w == 3.0)

    row_only = make_test_ms(tmp_path / "w.ms", n_times=3, weight_spectrum=False, seed=1)
    edit(row_only, WEIGHT=3.0, SIGMA=4.0)
    w, src = weights(convert_ms(row_only, tmp_path / "w.zarr"))
    assert src == "WEIGHT" and np.all(w == 3.0)

    sigma_only = make_test_ms(tmp_path / "s.ms", n_times=3, weight_spectrum=False, write_weight=False,
                              seed=1)
    edit(sigma_only, SIGMA=4.0)
    w, src = weights(convert_ms(sigma_only, tmp_path / "s.zarr"))
    assert src == "SIGMA" and np.all(w == np.float32(1 / 16))


def test_flag_row_honoured(tmp_path):
    ms = make_test_ms(tmp_path / "in.ms", flag_fraction=0.0, flag_row_fraction=0.3)
    with pt.table(str(ms), ack=False) as t:
        flag_row = t.getcol("FLAG_ROW")
        assert not t.getcol("FLAG").any() and flag_row.any()
    cells, _ = store_cells(convert_ms(ms, tmp_path / "s.zarr"))
    n_flagged = sum(bool(c["flag"].all()) for c in cells.values())
    assert n_flagged == int(flag_row.sum())
    assert not any(c["flag"].any() and not c["flag"].all() for c in cells.values())


def test_store_has_no_object_or_pickle_codecs(tmp_path):
    ms = make_test_ms(tmp_path / "in.ms", n_fields=2)
    out = convert_ms(ms, tmp_path / "s.zarr")
    allowed = {"bytes", "zstd", "blosc", "gzip", "crc32c", "transpose", "vlen-utf8", "sharding_indexed"}
    n_arrays = 0
    for meta_file in Path(out).rglob("zarr.json"):
        meta = json.loads(meta_file.read_text())
        if meta.get("node_type") != "array":
            continue
        n_arrays += 1
        assert meta["data_type"] not in ("object", "|O"), meta_file
        names = {c["name"] for c in meta.get("codecs", [])}
        assert names <= allowed, (meta_file, names)
        assert "pickle" not in json.dumps(meta).lower()
    assert n_arrays > 20


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["evla", "alma"])
def test_round_trip_real(tmp_path, name):
    ms = require_real_ms(name, tmp_path / "src")
    z1, ms2, z2 = _round_trip(ms, tmp_path)
    expected = ms_cells(ms)
    cells1, n_pad = store_cells(z1)
    assert_cells_equal(expected, cells1)
    assert_cells_equal(expected, ms_cells(ms2))
    assert_stores_identical(z1, z2)
    parts = dict(iter_partitions(open_store(z1)))
    field = pt.table(f"{ms}/FIELD", ack=False)
    obs = pt.table(f"{ms}/OBSERVATION", ack=False)
    for ds in parts.values():
        pd = field.getcell("PHASE_DIR", ds.attrs["field_id"])[0]
        np.testing.assert_allclose(ds.attrs["phase_center"], [np.mod(pd[0], 2 * np.pi), pd[1]],
                                   rtol=0, atol=1e-15)
        assert ds.attrs["telescope_name"] == obs.getcell("TELESCOPE_NAME", 0)
    if name == "evla":
        # jittered time stamps and 18 of 28 antennas: an irregular, padded grid
        ds = parts["spw0_field0"]
        assert list(ds["polarization"].values) == ["RR", "RL", "LR", "LL"]
        assert ds.sizes["baseline_id"] == 153 and n_pad > 0
        assert ds.attrs["weight_source"] == "WEIGHT_SPECTRUM"
    else:
        assert sorted(parts) == ["spw0_field2"]
        assert parts["spw0_field2"].attrs["weight_source"] == "WEIGHT"


def test_exported_ms_structure(tmp_path):
    """The exported MS has every required column and subtable, tiled big columns, one FEED
    row per antenna, and selections work as CASA's listobs/tclean would do them."""
    ms = make_test_ms(tmp_path / "in.ms", n_fields=2, n_spws=2, scans=2, n_antennas=5,
                      complex128=True, missing_rows=0.2, seed=9)
    ms2 = export_ms(convert_ms(ms, tmp_path / "s.zarr"), tmp_path / "out.ms")
    with pt.table(str(ms2), ack=False) as t:
        required = set(pt.required_ms_desc("MAIN")) - {"_define_hypercolumn_", "_keywords_",
                                                       "_private_keywords_"}
        assert required <= set(t.colnames())
        assert {"DATA", "WEIGHT_SPECTRUM"} <= set(t.colnames())
        assert t.getcoldesc("DATA")["valueType"] == "dcomplex"  # complex128 kept
        managers = {c: info["TYPE"] for info in t.getdminfo().values() for c in info["COLUMNS"]}
        for col in ("DATA", "FLAG", "WEIGHT_SPECTRUM", "WEIGHT", "SIGMA", "UVW"):
            assert managers[col].startswith("Tiled"), (col, managers[col])
        assert t.getcolkeywords("UVW")["MEASINFO"]["Ref"] == "J2000"
        kw = t.getkeywords()
        for sub in ("ANTENNA", "FEED", "FIELD", "OBSERVATION", "POLARIZATION", "SPECTRAL_WINDOW",
                    "DATA_DESCRIPTION", "SOURCE", "PROCESSOR", "STATE", "HISTORY", "POINTING"):
            assert sub in kw, sub
            with pt.table(f"{ms2}/{sub}", ack=False) as s:
                req = set(pt.required_ms_desc(sub)) - {"_define_hypercolumn_", "_keywords_",
                                                        "_private_keywords_"}
                assert req <= set(s.colnames()), (sub, req - set(s.colnames()))
        sel = pt.taql(f"select from {ms2} where FIELD_ID==1 and DATA_DESC_ID==1")
        assert sel.nrows() > 0 and set(sel.getcol("SCAN_NUMBER").tolist()) == {2}
        sel.close()
        np.testing.assert_allclose(t.getcol("SIGMA"), 1 / np.sqrt(t.getcol("WEIGHT")), rtol=1e-6)
        assert np.all(t.getcol("FLAG_ROW") == t.getcol("FLAG").all(axis=(1, 2)))
    assert pt.table(f"{ms2}/FEED", ack=False).nrows() == 5
    assert pt.table(f"{ms2}/ANTENNA", ack=False).nrows() == 5
    assert pt.table(f"{ms2}/OBSERVATION", ack=False).getcell("TELESCOPE_NAME", 0) == "ALMA"
    for sub in ("FIELD", "SPECTRAL_WINDOW", "POLARIZATION"):
        a = pt.table(f"{ms}/{sub}", ack=False)
        b = pt.table(f"{ms2}/{sub}", ack=False)
        col = {"FIELD": "PHASE_DIR", "SPECTRAL_WINDOW": "CHAN_FREQ", "POLARIZATION": "CORR_TYPE"}[sub]
        for r in range(a.nrows()):
            np.testing.assert_array_equal(a.getcell(col, r), b.getcell(col, r))


def test_export_of_a_store_not_from_an_ms(tmp_path):
    """A store built in memory (as simulate/uvstack write them: no TIME_CENTROID, no scan
    numbers) exports, and converts back to the same arrays."""
    from conftest import make_partition

    from xstack.schema import write_store

    p0 = make_partition(n_time=5, n_ant=4, n_chan=3, seed=1)
    p1 = make_partition(n_time=7, n_ant=4, n_chan=3, seed=2, phase_center=(0.91, -0.49))
    p1.attrs.update(field_id=1, field_name="field1")
    with pytest.raises(xstack.XstackError, match="different antenna tables"):
        export_ms(write_store({"spw0_field0": p0, "spw0_field1": p1}, tmp_path / "bad.zarr"),
                  tmp_path / "bad.ms")
    assert not (tmp_path / "bad.ms").exists()
    p1["ANTENNA_POSITION"] = p0["ANTENNA_POSITION"]  # one array observed both fields
    src = write_store({"spw0_field0": p0, "spw0_field1": p1}, tmp_path / "src.zarr", kind="stacked")
    ms = export_ms(src, tmp_path / "x.ms")
    with pt.table(str(ms), ack=False) as t:
        assert t.nrows() == (5 + 7) * 6
        assert set(t.getcol("SCAN_NUMBER").tolist()) == {1}
        np.testing.assert_array_equal(t.getcol("INTERVAL"), 6.0)
    back = convert_ms(ms, tmp_path / "back.zarr")
    assert_stores_identical(src, back)


def test_rows_in_any_order(tmp_path):
    """An MS whose rows are not time-ordered (baseline-major, reversed) converts to the
    same cells: the reader falls back from in-place range reads to row selections."""
    ms = make_test_ms(tmp_path / "in.ms", n_spws=2, n_times=6, missing_rows=0.1, seed=11)
    shuffled = tmp_path / "shuffled.ms"
    with pt.table(str(ms), ack=False) as t:
        pt.taql(f"select from $t orderby ANTENNA2 DESC, ANTENNA1, TIME DESC giving {shuffled} as plain")
    with pt.table(str(shuffled), ack=False) as t:
        time = t.getcol("TIME")
        assert np.any(np.diff(time) < 0)  # really out of order
    a = convert_ms(ms, tmp_path / "a.zarr")
    b = convert_ms(shuffled, tmp_path / "b.zarr", chunks={"time": 4})
    assert_cells_equal(ms_cells(shuffled), store_cells(b)[0])
    assert_stores_identical(a, b)
