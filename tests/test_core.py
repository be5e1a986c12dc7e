"""Tests of the shared core: schema, atomic outputs, coordinates, catalogs, primary beams."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import xarray as xr
from astropy import units as u
from astropy.coordinates import SkyCoord
from astropy.table import Table

import xstack
from xstack.beams import PrimaryBeam, standard_beam
from xstack.coords import (
    angular_separation,
    lm_to_radec,
    parse_distance,
    parse_flux,
    radec_to_lmn,
    read_catalog,
)
from xstack.errors import SchemaError, XstackError
from xstack.schema import open_store, validate_partition, validate_store, write_store

# ---------------------------------------------------------------- schema and stores


def test_store_round_trip_is_identical(tmp_path, small_partition):
    ds = small_partition.chunk({"time": 2, "baseline_id": 4})
    write_store({"spw0_field0": ds}, tmp_path / "a.zarr")
    from xstack.schema import iter_partitions

    tree = open_store(tmp_path / "a.zarr")
    # the stages' view of the MSv4 partition on disk is the partition that was written
    back = dict(iter_partitions(tree))["spw0_field0"]
    assert back.VISIBILITY.chunks[0] == (2, 2, 2)
    xr.testing.assert_identical(back.compute(), small_partition)


def test_partitions_come_in_sorted_order(tmp_path):
    from conftest import make_partition

    from xstack.schema import iter_partitions

    names = ["spw1_field0", "spw0_field2", "spw0_field10", "spw0_field1"]
    parts = {name: make_partition(seed=i) for i, name in enumerate(names)}
    tree = xr.DataTree.from_dict(parts)  # insertion order, not sorted
    assert [n for n, _ in iter_partitions(tree)] == sorted(names)
    write_store(parts, tmp_path / "a.zarr")
    assert [n for n, _ in iter_partitions(open_store(tmp_path / "a.zarr"))] == sorted(names)


def test_store_holds_no_object_or_pickle_codecs(tmp_path, small_partition):
    write_store({"p": small_partition}, tmp_path / "a.zarr")
    for root, _, files in os.walk(tmp_path / "a.zarr"):
        if "zarr.json" in files:
            text = open(os.path.join(root, "zarr.json")).read()
            assert "pickle" not in text.lower()
            assert '"object"' not in text
            meta = json.loads(text)
            if meta["node_type"] == "array":
                dtype = meta["data_type"]
                # strings are MSv4's fixed-width unicode (a name with its length)
                name = dtype["name"] if isinstance(dtype, dict) else dtype
                assert name in ("complex64", "complex128", "float32", "float64", "bool",
                                "int32", "int64", "fixed_length_utf32")


class _Payload:
    """Unpickling this touches a marker file: proof that code ran."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        import pathlib

        return (pathlib.Path.touch, (pathlib.Path(self.marker),))


def _poison(store, array, codecs=None, data_type=None):
    """Rewrite one array's metadata as a hostile store would (chunks left as they are)."""
    meta_file = store / "p" / array / "zarr.json"
    meta = json.loads(meta_file.read_text())
    if codecs is not None:
        meta["codecs"] = codecs
    if data_type is not None:
        meta["data_type"] = data_type
    meta_file.write_text(json.dumps(meta))


@pytest.mark.parametrize("codecs, data_type, match", [
    ([{"name": "numcodecs.pickle", "configuration": {"protocol": 5}}], None,
     "codec 'numcodecs.pickle' is not allowed"),
    ([{"name": "sharding_indexed", "configuration": {
        "chunk_shape": [1, 1, 1, 1], "codecs": [{"name": "bytes"}, {"name": "pickle"}],
        "index_codecs": [{"name": "bytes"}]}}], None, "codec 'pickle' is not allowed"),
    (None, "object", "data type 'object' is not allowed"),
    (None, {"name": "variable_length_bytes"}, "data type 'variable_length_bytes'"),
])
def test_store_with_unsafe_codec_or_dtype_refused_before_decoding(tmp_path, small_partition,
                                                                  codecs, data_type, match):
    import pickle

    store = write_store({"p": small_partition}, tmp_path / "a.zarr")
    marker = tmp_path / "code-ran"
    # every VISIBILITY chunk replaced by a payload that runs code when unpickled
    payload = pickle.dumps(_Payload(marker))
    chunks = [f for f in (store / "p" / "VISIBILITY").rglob("*") if f.is_file() and f.name != "zarr.json"]
    assert chunks
    for f in chunks:
        f.write_bytes(payload)
    _poison(store, "VISIBILITY", codecs, data_type)
    with pytest.raises(SchemaError, match=f"p/VISIBILITY: {match}"):
        validate_store(store)
    with pytest.raises(SchemaError, match="VISIBILITY"):
        open_store(store)
    assert not marker.exists()
    pickle.loads(payload)  # the payload is live: the check above could have failed
    assert marker.exists()


def test_zarr_v2_metadata_refused(tmp_path, small_partition):
    store = write_store({"p": small_partition}, tmp_path / "a.zarr")
    (store / "p" / ".zarray").write_text("{}")
    with pytest.raises(SchemaError, match="zarr v2 metadata"):
        open_store(store)


def test_opening_and_reading_never_unpickles(tmp_path, small_partition, monkeypatch):
    """Nothing read from the store is ever unpickled. (dask pickles and unpickles its own
    objects while tokenizing, so only bytes this process pickled itself may be unpickled.)"""
    import pickle

    import cloudpickle

    store = write_store({"p": small_partition.chunk({"time": 2})}, tmp_path / "a.zarr")
    ours: set[bytes] = set()
    foreign: list[bytes] = []
    real_loads, real_dumps, real_cdumps = pickle.loads, pickle.dumps, cloudpickle.dumps

    def dumps(*args, **kwargs):
        out = real_dumps(*args, **kwargs)
        ours.add(bytes(out))
        return out

    def cdumps(*args, **kwargs):
        out = real_cdumps(*args, **kwargs)
        ours.add(bytes(out))
        return out

    def loads(data, *args, **kwargs):
        if bytes(data) not in ours:
            foreign.append(bytes(data))
            raise AssertionError("unpickled bytes this process did not pickle")
        return real_loads(data, *args, **kwargs)

    def forbidden(*args, **kwargs):
        foreign.append(b"load/Unpickler")
        raise AssertionError("pickle.load / Unpickler used")

    monkeypatch.setattr(pickle, "dumps", dumps)
    monkeypatch.setattr(cloudpickle, "dumps", cdumps)
    monkeypatch.setattr(pickle, "loads", loads)
    monkeypatch.setattr(pickle, "load", forbidden)
    monkeypatch.setattr(pickle, "Unpickler", forbidden)
    from xstack.schema import iter_partitions

    ds = dict(iter_partitions(open_store(store)))["p"].compute(scheduler="synchronous")
    assert foreign == []
    xr.testing.assert_identical(ds, small_partition)


def test_existing_output_needs_overwrite(tmp_path, small_partition):
    out = tmp_path / "a.zarr"
    write_store({"p": small_partition}, out)
    with pytest.raises(XstackError, match="exists"):
        write_store({"p": small_partition}, out)
    write_store({"q": small_partition}, out, overwrite=True)
    assert list(open_store(out).children) == ["q"]


def test_failed_write_leaves_nothing(tmp_path, small_partition):
    bad = small_partition.copy()
    import dask.array as da

    def explode(block):
        raise RuntimeError("boom")

    vis = bad.VISIBILITY.data
    bad["VISIBILITY"] = (bad.VISIBILITY.dims,
                         da.from_array(vis, chunks=(1, -1, -1, -1)).map_blocks(explode, dtype=vis.dtype))
    with pytest.raises(RuntimeError, match="boom"):
        write_store({"p": bad}, tmp_path / "a.zarr")
    assert os.listdir(tmp_path) == []


def test_incomplete_store_does_not_validate(tmp_path, small_partition):
    out = tmp_path / "a.zarr"
    write_store({"p": small_partition}, out)
    meta = json.loads((out / "zarr.json").read_text())
    meta["attributes"]["xstack_complete"] = False
    (out / "zarr.json").write_text(json.dumps(meta))
    with pytest.raises(SchemaError, match="incomplete"):
        open_store(out)


@pytest.mark.parametrize("content", [None, "not json", '{"node_type": "array"}',
                                     '{"node_type": "group", "attributes": {}}'])
def test_non_xstack_or_corrupt_store_rejected(tmp_path, content):
    out = tmp_path / "x.zarr"
    out.mkdir()
    if content is not None:
        (out / "zarr.json").write_text(content)
    with pytest.raises(SchemaError):
        validate_store(out)


def test_validate_partition_names_the_problem(small_partition):
    with pytest.raises(SchemaError, match="missing variable FLAG"):
        validate_partition(small_partition.drop_vars("FLAG"))
    bad = small_partition.copy()
    bad.attrs = {k: v for k, v in bad.attrs.items() if k != "phase_center"}
    with pytest.raises(SchemaError, match="phase_center"):
        validate_partition(bad)
    bad = small_partition.copy()
    bad["UVW"] = bad.UVW.astype(np.float32)
    with pytest.raises(SchemaError, match="UVW"):
        validate_partition(bad)


def test_api_is_lazy_and_complete():
    assert xstack.open_store is open_store
    with pytest.raises(AttributeError):
        xstack.no_such_function  # noqa: B018


# ---------------------------------------------------------------- coordinates


def test_lmn_against_astropy_offset_frame():
    rng = np.random.default_rng(3)
    ra0, dec0 = np.radians(57.3), np.radians(-30.0)
    ra = ra0 + rng.uniform(-0.05, 0.05, 50)
    dec = dec0 + rng.uniform(-0.05, 0.05, 50)
    l, m, n, nm1 = radec_to_lmn(ra, dec, ra0, dec0)
    center = SkyCoord(ra0 * u.rad, dec0 * u.rad)
    off = SkyCoord(ra * u.rad, dec * u.rad).transform_to(center.skyoffset_frame())
    # astropy's offset frame: lon/lat on the sphere; direction cosines follow from them
    lat, lon = off.lat.rad, off.lon.rad
    np.testing.assert_allclose(l, np.cos(lat) * np.sin(lon), atol=1e-14)
    np.testing.assert_allclose(m, np.sin(lat), atol=1e-14)
    np.testing.assert_allclose(n, np.cos(lat) * np.cos(lon), atol=1e-14)
    np.testing.assert_allclose(nm1, n - 1, atol=1e-15)


def test_n_minus_one_keeps_precision_near_center():
    l, m, n, nm1 = radec_to_lmn(1e-9, 1e-9, 0.0, 0.0)
    assert nm1 != 0.0
    np.testing.assert_allclose(nm1, -(l**2 + m**2) / 2, rtol=1e-12)


@pytest.mark.parametrize("dec0", [np.radians(89.9), np.radians(-89.9), 0.0])
def test_lm_round_trip_at_poles_and_ra_wrap(dec0):
    ra0 = np.radians(359.99)
    ra = np.mod(ra0 + np.array([-0.01, 0.0, 0.01, 0.02]), 2 * np.pi)
    dec = np.clip(dec0 + np.array([0.001, -0.001, 0.0005, 0.0]), -np.pi / 2, np.pi / 2)
    l, m, _, _ = radec_to_lmn(ra, dec, ra0, dec0)
    ra2, dec2 = lm_to_radec(l, m, ra0, dec0)
    assert np.all(angular_separation(ra, dec, ra2, dec2) < 1e-12)


def test_parse_distance_and_flux():
    assert parse_distance("5000m") == (5000.0, "m")
    assert parse_distance("2km") == (2000.0, "m")
    assert parse_distance("23.8klambda") == (23800.0, "lambda")
    assert parse_distance(12) == (12.0, "m")
    with pytest.raises(XstackError, match="unit"):
        parse_distance("5 parsec")
    assert parse_flux("20uJy") == pytest.approx(20e-6)
    assert parse_flux("2mJy") == pytest.approx(2e-3)
    with pytest.raises(XstackError):
        parse_flux("3 m")


def test_read_catalog_formats_and_errors(tmp_path):
    path = tmp_path / "cat.csv"
    path.write_text("RA,Dec,weight\n03:49:10.99,-30:00:00,1\n03:49:12,-30:06:00,2\n")
    cat = read_catalog(path)
    assert cat["ra"][0] == pytest.approx(15 * (3 + 49 / 60 + 10.99 / 3600))
    assert cat["dec"][1] == pytest.approx(-30.1)
    # decimal degrees and sexagesimal mixed in one column are refused (tests/test_catalogs.py)
    (tmp_path / "mixed.csv").write_text("RA,Dec\n03:49:10.99,-30:00:00\n57.3,-30.1\n")
    with pytest.raises(XstackError, match="row 2.*mixed"):
        read_catalog(tmp_path / "mixed.csv")
    Table({"ra": [359.5, 0.5], "dec": [0.0, 1.0]}).write(tmp_path / "c.fits")
    assert list(read_catalog(tmp_path / "c.fits")["ra"]) == pytest.approx([359.5, 0.5])
    (tmp_path / "bad.csv").write_text("ra,dec\n1,2\nx,3\n")
    with pytest.raises(XstackError, match="row 2"):
        read_catalog(tmp_path / "bad.csv")
    (tmp_path / "nodec.csv").write_text("ra,foo\n1,2\n")
    with pytest.raises(XstackError, match="missing column"):
        read_catalog(tmp_path / "nodec.csv")
    with pytest.raises(XstackError, match="no such"):
        read_catalog(tmp_path / "nothere.csv")


# ---------------------------------------------------------------- primary beams


def test_airy_beam_matches_analytic_values():
    beam = PrimaryBeam("airy", 12.0)
    freq = 230e9
    lam = 299_792_458.0 / freq
    # first null of an unblocked Airy pattern at sin(theta) = 1.21967 lambda / D
    assert beam(np.arcsin(1.219670 * lam / 12.0), freq) < 1e-10
    assert beam(0.0, freq) == pytest.approx(1.0)
    # half power at 1.02899 lambda / D full width
    assert np.degrees(beam.fwhm(freq)) == pytest.approx(np.degrees(1.028994 * lam / 12), 1e-4)


def test_alma_standard_beam_is_wider_than_naive_dish():
    alma = standard_beam("ALMA", 12.0)
    naive = PrimaryBeam("airy", 12.0)
    ratio = alma.fwhm(230e9) / naive.fwhm(230e9)
    assert 1.08 < ratio < 1.14  # DESIGN.md: naive 12 m Airy is ~10 % narrower


def test_vla_beam_polynomial():
    vla = standard_beam("EVLA", 25.0)
    assert vla.model == "vla"
    # EVLA memo 195: FWHM ~ 42 arcmin / nu[GHz]
    assert np.degrees(vla.fwhm(1.4e9)) * 60 == pytest.approx(42 / 1.4, rel=0.03)
    far = vla(np.radians(2.0), 1.4e9)  # beyond the first null
    assert far == 0.0
    values = vla(np.radians(np.linspace(0, 0.5, 50)), 1.4e9)
    assert np.all(np.diff(values) <= 0) and np.all(values >= 0)


def test_gaussian_beam_and_bad_models():
    g = PrimaryBeam("gaussian", 12.0)
    fwhm = 1.13 * 299_792_458.0 / 230e9 / 12.0
    assert g(fwhm / 2, 230e9) == pytest.approx(0.5)
    with pytest.raises(XstackError, match="unknown primary-beam"):
        PrimaryBeam("square")
