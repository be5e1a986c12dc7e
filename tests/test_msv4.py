"""Stores are MSv4 processing sets (issue 13): xradio reads what xstack writes, xstack reads
what xradio writes.

The truth is xradio 1.3.0 (the test extra): its ``open_processing_set``, ``summary()`` and
``check_datatree`` judge every store that xstack's commands write, and its converter writes
the stores xstack must stack with the same flux as its own conversion of the same
MeasurementSet. The MSs are test MSs (single field, a mosaic with several fields and scans,
several spectral windows, an irregular time grid, two data columns) and the real MSs of the
pyuvdata wheel.

xradio ignores FLAG_ROW (it reads the FLAG column only; measured in
docs/audit/issue13-msv4.md), so the MSs compared with xradio's converter have no rows flagged
by FLAG_ROW alone (``flag_row_fraction=0``); the one test that has them shows the difference.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

import xstack
from xstack.errors import SchemaError
from xstack.msv4 import UNIX_EPOCH_MJD_S
from xstack.schema import iter_partitions, open_store
from xstack.testing import make_test_ms, require_real_ms

pytestmark = pytest.mark.filterwarnings("ignore::xstack.errors.XstackWarning")

xradio_ms = pytest.importorskip("xradio.measurement_set", reason="xradio (the test extra)")


def msv4_problems(store: Path) -> list[str]:
    """What xradio 1.3.0 objects to in ``store``: summary() failing, check_datatree issues."""
    from xradio.schema.check import check_datatree

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ps = xradio_ms.open_processing_set(str(store))
        problems = []
        try:
            summary = ps.xr_ps.summary()
            if len(summary) == 0:
                problems.append("summary(): no rows")
        except Exception as exc:  # noqa: BLE001 - any failure of xradio's own reader counts
            problems.append(f"summary(): {type(exc).__name__}: {exc}")
        problems += [str(issue) for issue in check_datatree(ps)]
    return problems


def xradio_convert(ms: Path, out: Path) -> Path:
    """xradio's converter (defaults: one partition per spectral window and observation)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        xradio_ms.convert_msv2_to_processing_set(str(ms), str(out), persistence_mode="w",
                                                 with_pointing=False)
    return out


#: test MSs: name -> make_test_ms keywords (no FLAG_ROW-only rows: see the module docstring)
TEST_MS = {
    "single": dict(seed=1, flag_row_fraction=0.0),
    "mosaic": dict(n_fields=4, scans=8, n_antennas=7, seed=2, missing_baselines=2,
                   missing_rows=0.1, flag_row_fraction=0.0),
    "spws": dict(n_spws=3, n_channels=[3, 4, 5], seed=3, flag_row_fraction=0.0),
    "irregular": dict(n_times=12, scans=3, missing_rows=0.3, seed=4, flag_row_fraction=0.0),
    "columns": dict(seed=5, datacolumns=("DATA", "CORRECTED_DATA"), flag_row_fraction=0.0),
}


@pytest.fixture(scope="module")
def mss(tmp_path_factory):
    d = tmp_path_factory.mktemp("ms")
    return {name: make_test_ms(d / f"{name}.ms", **kw) for name, kw in TEST_MS.items()}


@pytest.fixture(scope="module")
def converted(mss, tmp_path_factory):
    """name -> (xstack's store, xradio's store) of every test MS."""
    d = tmp_path_factory.mktemp("stores")
    return {name: (xstack.convert_ms(ms, d / f"xs_{name}.zarr"),
                   xradio_convert(ms, d / f"xr_{name}.ps.zarr"))
            for name, ms in mss.items()}


def _catalog(store: Path, n: int = 12, radius_arcsec: float = 15.0, seed: int = 0):
    """Positions around the pointings of ``store`` (inside their primary beams)."""
    from astropy.table import Table

    rng = np.random.default_rng(seed)
    centers = np.array([ds.attrs["phase_center"] for _, ds in iter_partitions(open_store(store))])
    pick = centers[rng.integers(0, len(centers), n)]
    off = rng.uniform(-radius_arcsec, radius_arcsec, (n, 2)) / 3600.0
    dec = np.degrees(pick[:, 1]) + off[:, 1]
    ra = np.degrees(pick[:, 0]) + off[:, 0] / np.cos(np.radians(dec))
    return Table({"ra": ra, "dec": dec})


@pytest.mark.parametrize("name", sorted(TEST_MS))
def test_converted_stores_are_valid_msv4(converted, name):
    store, _ = converted[name]
    assert msv4_problems(store) == []


def test_every_command_writes_valid_msv4(tmp_path):
    """simulate, subtract and uvstack (its stacked store with the positions extension)."""
    sim = xstack.simulate(xstack.preset_scene("paper-1", scale=0.005), tmp_path / "sim.zarr",
                          seed=3)
    sub = xstack.subtract(sim.store, sim.catalogs["bright"], tmp_path / "sub.zarr")
    xstack.stack_uv(sub, sim.catalogs["targets"], out=tmp_path / "stack.zarr")
    for store in (sim.store, tmp_path / "sub.zarr", tmp_path / "stack.zarr"):
        assert msv4_problems(store) == [], store


@pytest.mark.parametrize("name", ["mosaic", "spws", "irregular"])
def test_subtract_and_uvstack_of_converted_stores_are_valid_msv4(converted, name, tmp_path):
    """subtract and uvstack outputs of a mosaic (one stacked partition per field), of several
    spectral windows and of an irregular time grid."""
    store, _ = converted[name]
    cat = _catalog(store, n=4)
    bright = cat[:2].copy()
    bright["flux"] = [0.5, 0.2]
    sub = xstack.subtract(store, bright, tmp_path / "sub.zarr")
    xstack.stack_uv(sub, cat, out=tmp_path / "stack.zarr")
    for out in (tmp_path / "sub.zarr", tmp_path / "stack.zarr"):
        assert msv4_problems(out) == [], out


@pytest.mark.parametrize("name", sorted(TEST_MS))
def test_xradio_store_stacks_as_xstack_store(converted, name):
    """Same flux to 1e-9 from xradio's conversion and xstack's (the mosaic: all fields in
    one xradio partition, field_name over time, against xstack's one partition per field)."""
    ours, theirs = converted[name]
    cat = _catalog(ours)
    a = xstack.stack_uv(ours, cat)
    b = xstack.stack_uv(theirs, cat)
    assert b.flux_jy == pytest.approx(a.flux_jy, rel=1e-9, abs=0)
    assert b.flux_err_jy == pytest.approx(a.flux_err_jy, rel=1e-9, abs=0)
    assert b.n_visibilities == a.n_visibilities


def test_several_fields_per_partition_split_by_field(converted):
    """xradio keeps the mosaic's four fields in one partition; xstack reads it as one
    partition per field with that field's phase center, times and data."""
    ours, theirs = converted["mosaic"]
    mine = dict(iter_partitions(open_store(ours)))
    xr_parts = list(iter_partitions(open_store(theirs)))
    import xarray as xr

    assert len(xr.open_datatree(theirs, engine="zarr").children) == 1
    assert len(xr_parts) == 4 == len(mine)
    by_field = {ds.attrs["field_name"]: ds for _, ds in xr_parts}
    for ds in mine.values():
        # xradio names fields NAME_ID
        other = by_field[f"{ds.attrs['field_name']}_{ds.attrs['field_id']}"]
        assert other.attrs["phase_center"] == ds.attrs["phase_center"]
        np.testing.assert_array_equal(other["time"].values, ds["time"].values)
        keep = ~ds["FLAG"].values
        np.testing.assert_array_equal(other["FLAG"].values, ds["FLAG"].values)
        np.testing.assert_array_equal(other["VISIBILITY"].values[keep], ds["VISIBILITY"].values[keep])
        np.testing.assert_array_equal(other["WEIGHT"].values[keep], ds["WEIGHT"].values[keep])


def test_data_group_chooses_the_column(converted, mss, tmp_path):
    """xradio's 'corrected' data group stacks as xstack's conversion of CORRECTED_DATA."""
    _, theirs = converted["columns"]
    ours = xstack.convert_ms(mss["columns"], tmp_path / "corr.zarr", datacolumn="CORRECTED_DATA")
    cat = _catalog(ours)
    a = xstack.stack_uv(ours, cat)
    b = xstack.stack_uv(open_store(theirs, data_group="corrected"), cat)
    assert b.flux_jy == pytest.approx(a.flux_jy, rel=1e-9, abs=0)
    base = xstack.stack_uv(theirs, cat)
    assert base.flux_jy != pytest.approx(a.flux_jy, rel=1e-6)
    with pytest.raises(SchemaError, match="no data group 'model'"):
        open_store(theirs, data_group="model")


def test_times_round_trip_exactly(mss, converted):
    """Times are Unix seconds on disk (MSv4) and MJD seconds inside: the MS's TIME and
    TIME_CENTROID come back bit for bit; on disk they are the MS's minus 3506716800 s."""
    import casacore.tables as pt
    import zarr

    ms = str(mss["single"])
    with pt.table(ms, ack=False) as t:
        times = np.unique(t.getcol("TIME"))
        centroids = t.getcol("TIME_CENTROID")
    store, _ = converted["single"]
    (_, ds), = iter_partitions(open_store(store))
    np.testing.assert_array_equal(ds["time"].values, times)
    assert set(np.unique(ds["TIME_CENTROID"].values)) <= set(np.unique(centroids))
    group = zarr.open_group(str(store), mode="r")
    (name,) = [k for k in group.group_keys()]
    on_disk = group[name]["time"][:]
    np.testing.assert_array_equal(on_disk, times - UNIX_EPOCH_MJD_S)
    assert group[name]["time"].attrs["format"] == "unix"


def test_old_layout_refused_with_what_to_do(tmp_path):
    import zarr

    old = tmp_path / "old.zarr"
    root = zarr.open_group(str(old), mode="w", zarr_format=3)
    root.attrs.update({"xstack_schema": "xstack.processing_set", "xstack_schema_version": "1.0",
                       "xstack_kind": "processing_set", "xstack_complete": True})
    with pytest.raises(SchemaError, match="layout '1.0'.*convert the MeasurementSet again"):
        open_store(old)
    plain = tmp_path / "plain.zarr"
    zarr.open_group(str(plain), mode="w", zarr_format=3)
    with pytest.raises(SchemaError, match="neither an xstack store nor an MSv4 processing set"):
        open_store(plain)


def test_store_attributes_carry_xstack_and_msv4(converted):
    """Root: type processing_set and xstack's schema; partition: MSv4's required attributes,
    xstack's own under 'xstack'; consolidated metadata at the root."""
    store, _ = converted["spws"]
    doc = json.loads((store / "zarr.json").read_text())
    attrs = doc["attributes"]
    assert attrs["type"] == "processing_set" and attrs["xstack_schema_version"] == "2.0"
    assert doc.get("consolidated_metadata") is not None
    part = json.loads(next(p for p in sorted(store.glob("*/zarr.json"))).read_text())["attributes"]
    assert part["type"] == "visibility" and part["schema_version"].startswith("4.")
    assert part["xstack"]["spectral_window_id"] in (0, 1, 2)
    assert part["data_groups"]["base"]["correlated_data"] == "VISIBILITY"


def test_flag_row_is_kept_where_xradio_drops_it(tmp_path):
    """A row flagged by FLAG_ROW only: xstack's conversion flags it, xradio's does not, so
    the two stores differ exactly there (the one difference found in docs/audit)."""
    ms = make_test_ms(tmp_path / "fr.ms", seed=6, flag_row_fraction=0.2, flag_fraction=0.0)
    ours = xstack.convert_ms(ms, tmp_path / "xs.zarr")
    theirs = xradio_convert(ms, tmp_path / "xr.ps.zarr")
    (_, a), = iter_partitions(open_store(ours))
    (_, b), = iter_partitions(open_store(theirs))
    fa, fb = a["FLAG"].values, b["FLAG"].values
    assert fa.sum() > fb.sum() and not np.any(fb & ~fa)


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["evla", "alma", "ovro-lwa", "mwa", "mwa-small", "hera"])
def test_real_ms_both_ways(name, tmp_path):
    """The real MSs of the pyuvdata wheel: xstack's conversion is valid MSv4, and xradio's
    conversion stacks like it (the OVRO-LWA MS needs with_pointing=False in xradio)."""
    ms = require_real_ms(name, tmp_path)
    ours = xstack.convert_ms(ms, tmp_path / "xs.zarr")
    assert msv4_problems(ours) == []
    theirs = xradio_convert(ms, tmp_path / "xr.ps.zarr")
    (_, a), *rest_a = iter_partitions(open_store(ours))
    parts_b = dict(iter_partitions(open_store(theirs)))
    assert len(parts_b) == 1 + len(rest_a)
    cat = _catalog(ours, n=5, radius_arcsec=5.0)
    fa = ~a["FLAG"].values
    if not fa.any():
        pytest.skip(f"{name}: every visibility is flagged")
    # every correlation: the HERA MS holds XY only
    sa = xstack.stack_uv(ours, cat, polarizations="all")
    sb = xstack.stack_uv(theirs, cat, polarizations="all")
    assert sb.flux_jy == pytest.approx(sa.flux_jy, rel=1e-9, abs=1e-15)


def test_tree_opened_by_xradio_stacks_too(converted):
    """A DataTree from xradio's own reader, passed in instead of a path."""
    ours, theirs = converted["mosaic"]
    cat = _catalog(ours)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        tree = xradio_ms.open_processing_set(str(theirs))
    before = {node.path: {v: dict(node[v].attrs) for v in node.ds.variables}
              for node in tree.subtree}
    assert xstack.stack_uv(tree, cat).flux_jy == pytest.approx(
        xstack.stack_uv(ours, cat).flux_jy, rel=1e-9, abs=0)
    # reading it changed nothing in the user's tree
    assert before == {node.path: {v: dict(node[v].attrs) for v in node.ds.variables}
                      for node in tree.subtree}


def test_measurement_set_input_says_where_it_was_converted(mss, tmp_path, capsys):
    """No hidden conversion: given a MeasurementSet, the command says where its MSv4 store
    went (stderr, not with -q) and the result is that of the explicit conversion."""
    from xstack.cli import main

    ms = mss["single"]
    cat = _catalog(xstack.convert_ms(ms, tmp_path / "explicit.zarr"))
    cat.write(tmp_path / "cat.ecsv")
    assert main(["uvstack", str(ms), str(tmp_path / "cat.ecsv"), str(tmp_path / "a.zarr"),
                 "--json"]) == 0
    out, err = capsys.readouterr()
    line = next(x for x in err.splitlines() if "a MeasurementSet, converted to" in x)
    assert str(ms) in line and "converted.zarr" in line and "xstack convert" in line
    assert json.loads(out)["flux_jy"] == pytest.approx(
        xstack.stack_uv(tmp_path / "explicit.zarr", cat).flux_jy, rel=1e-12)
    assert main(["uvstack", str(ms), str(tmp_path / "cat.ecsv"), str(tmp_path / "b.zarr"),
                 "--json", "-q"]) == 0
    assert "converted to" not in capsys.readouterr().err


def test_cli_data_group(converted, mss, tmp_path, capsys):
    """`xstack uvstack --data-group corrected` stacks xradio's VISIBILITY_CORRECTED, as the
    API does; an unknown group and a MeasurementSet are one-line errors."""
    from xstack.cli import main

    _, theirs = converted["columns"]
    cat = _catalog(theirs)
    cat.write(tmp_path / "cat.ecsv")
    args = [str(theirs), str(tmp_path / "cat.ecsv")]
    assert main(["uvstack", *args, str(tmp_path / "a.zarr"), "--data-group", "corrected",
                 "--json"]) == 0
    flux = json.loads(capsys.readouterr().out)["flux_jy"]
    assert flux == pytest.approx(
        xstack.stack_uv(open_store(theirs, data_group="corrected"), cat).flux_jy, rel=1e-12)
    assert main(["uvstack", *args, str(tmp_path / "b.zarr"), "--data-group", "model"]) == 1
    assert "no data group 'model'" in capsys.readouterr().err
    assert main(["uvstack", str(mss["columns"]), str(tmp_path / "cat.ecsv"),
                 str(tmp_path / "c.zarr"), "--data-group", "corrected"]) == 1
    assert "has no data groups" in capsys.readouterr().err


def test_info_names_the_writer_and_data_groups(converted, capsys):
    from xstack.cli import main

    ours, theirs = converted["columns"]
    assert main(["info", str(theirs), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["format"] == "MSv4 processing set"
    assert d["written_by"] == ["xradio 1.3.0"]
    assert {"base", "corrected"} <= set(d["data_groups"])
    assert main(["info", str(ours), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["written_by"] == [f"xstack {xstack.__version__}"] and d["data_groups"] == ["base"]


def test_cli_data_group_in_image_subtract_noise(converted, mss, tmp_path, capsys):
    """image, subtract and noise read xradio's 'corrected' group as xstack's conversion of
    CORRECTED_DATA: the same image pixels, the same residual flux, the same noise."""
    from astropy.io import fits

    from xstack.cli import main

    _, theirs = converted["columns"]
    ours = xstack.convert_ms(mss["columns"], tmp_path / "corr.zarr", datacolumn="CORRECTED_DATA")
    cat = _catalog(ours, n=4)
    cat.write(tmp_path / "cat.ecsv")
    bright = cat[:1].copy()
    bright["flux"] = [0.3]
    bright.write(tmp_path / "bright.ecsv")
    grp = ["--data-group", "corrected"]
    img = ["--size", "64", "--cell", "1arcsec", "-q"]
    assert main(["image", str(ours), str(tmp_path / "a.fits"), *img]) == 0
    assert main(["image", str(theirs), str(tmp_path / "b.fits"), *img, *grp]) == 0
    np.testing.assert_allclose(fits.getdata(tmp_path / "b.fits"), fits.getdata(tmp_path / "a.fits"),
                               rtol=0, atol=1e-6 * np.abs(fits.getdata(tmp_path / "a.fits")).max())
    assert main(["subtract", str(ours), str(tmp_path / "bright.ecsv"), str(tmp_path / "ra.zarr"),
                 "-q"]) == 0
    assert main(["subtract", str(theirs), str(tmp_path / "bright.ecsv"), str(tmp_path / "rb.zarr"),
                 "-q", *grp]) == 0
    assert xstack.stack_uv(tmp_path / "rb.zarr", cat).flux_jy == pytest.approx(
        xstack.stack_uv(tmp_path / "ra.zarr", cat).flux_jy, rel=1e-9, abs=0)
    capsys.readouterr()
    noise = []
    for data, extra in ((ours, []), (theirs, grp)):
        assert main(["noise", str(data), str(tmp_path / "cat.ecsv"), "--method", "analytic",
                     "--json", *extra]) == 0
        noise.append(json.loads(capsys.readouterr().out)["noise_jy"])
    assert noise[1] == pytest.approx(noise[0], rel=1e-9)


def test_foreign_store_missing_parts_is_one_line_error(converted, tmp_path):
    """An MSv4 partition without its antenna table or field table: a one-line SchemaError
    naming what is missing, not a KeyError deep inside a stage (on disk zarr's metadata still
    lists the node and reports it missing; in a tree, xstack's reader does)."""
    import shutil

    _, theirs = converted["single"]
    for child, match in (("antenna_xds", "no antenna_xds"),
                         ("field_and_source_base_xds", "no field_and_source_xds")):
        bad = tmp_path / f"no_{child}.ps.zarr"
        shutil.copytree(theirs, bad)
        (part,) = [p for p in bad.iterdir() if (p / child).is_dir()]
        shutil.rmtree(part / child)
        with pytest.raises(SchemaError, match=f"{part.name}.*{child}"):
            open_store(bad)
        # read as a tree (no zarr metadata listing the node): xstack's own message
        import xarray as xr

        tree = xr.open_datatree(theirs, engine="zarr")
        node = tree[part.name].copy()
        del node[child]
        with pytest.raises(SchemaError, match=f"{part.name}: {match}"):
            xstack.stack_uv(xr.DataTree.from_dict({part.name: node}), _catalog(theirs))
