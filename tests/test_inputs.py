"""One input normaliser and one positions type for every stage (issue 11, item 9).

Truth: the partitions written into a store by :func:`xstack.write_store` (and read back
with :func:`xstack.open_store`), and positions given in degrees by the test itself. Every
stage must see the same partitions and positions whatever kind of input carries them, and
every stage must refuse the same bad input with the same one-line error.
"""

from __future__ import annotations

import numpy as np
import pytest
from astropy.table import Table

import xstack
from xstack._inputs import Positions
from xstack.errors import XstackError
from xstack.fit._data import as_partitions
from xstack.imaging.image import select_partitions
from xstack.imstack.stack import _positions as imstack_positions
from xstack.noise.estimate import _positions_from as noise_positions
from xstack.schema import write_store
from xstack.uvstack.profile import _partitions as profile_partitions
from xstack.uvstack.stack import _load_datasets, _positions_table

RA0, DEC0 = np.degrees(0.9), np.degrees(-0.5)


def _stage_partitions(data) -> dict[str, list[str]]:
    """Partition names (or VISIBILITY shapes, where a stage keeps no names) per stage."""
    (_, uv), = _load_datasets(data)
    return {
        "uvstack": [n for n, _ in uv],
        "fit/noise": [n for n, _ in as_partitions(data, autocorrelations=True)],
        "image": [n for n, _ in select_partitions(data, allow_mosaic=True)],
        "profile": [ds["VISIBILITY"].shape for ds in profile_partitions(data)],
    }


class _Stacked:  # a result object carrying its partitions, as StackResult does
    def __init__(self, stacked):
        self.stacked = stacked


@pytest.fixture
def store(tmp_path):
    from conftest import make_partition

    parts = {"spw0_field0": make_partition(seed=1), "spw1_field0": make_partition(seed=2)}
    return write_store(parts, tmp_path / "data.zarr"), parts


def test_every_stage_accepts_the_same_input_kinds(store):
    path, parts = store
    tree = xstack.open_store(path)
    names = sorted(parts)
    shapes = [parts[n]["VISIBILITY"].shape for n in names]
    kinds = {
        "path": path, "str": str(path), "tree": tree, "dict": parts,
        "pairs": [(n, parts[n]) for n in names], "stacked": _Stacked(parts),
    }
    for kind, data in kinds.items():
        got = _stage_partitions(data)
        for stage in ("uvstack", "fit/noise", "image"):
            assert got[stage] == names, (kind, stage)
        assert got["profile"] == shapes, kind
    one = _stage_partitions(parts["spw0_field0"])
    assert one == {"uvstack": ["partition"], "fit/noise": ["partition"],
                   "image": ["partition"], "profile": [shapes[0]]}


def test_every_stage_reads_a_measurementset(tmp_path):
    from xstack.testing import make_test_ms

    ms = make_test_ms(tmp_path / "t.ms", n_antennas=4, n_times=3, n_channels=2)
    got = _stage_partitions(ms)
    assert got["uvstack"] == got["fit/noise"] == got["image"]
    assert len(got["uvstack"]) == len(got["profile"]) >= 1


def _entry_points(data, tmp_path):
    cat = Table({"ra": [RA0], "dec": [DEC0]})
    model = Table({"ra": [RA0], "dec": [DEC0], "flux": [1e-3]})
    return {
        "uvstack": lambda: xstack.stack_uv(data, cat),
        "make_image": lambda: xstack.make_image(data, size=32, cell_arcsec=0.1),
        "subtract": lambda: xstack.subtract(data, model, tmp_path / "out.zarr"),
        "fit_uv": lambda: xstack.fit_uv(data),
        "estimate_noise": lambda: xstack.estimate_noise(data, cat),
        "uv_profile": lambda: xstack.uv_profile(data),
    }


@pytest.mark.parametrize("bad, message", [
    (42, "cannot read visibilities from a int: give a store path, a MeasurementSet path, "
         "an xarray DataTree or Dataset, or a dict or list of (name, Dataset) partitions"),
    ("missing.zarr", "missing.zarr: no such store or MeasurementSet"),
])
def test_every_stage_rejects_bad_data_with_one_error(tmp_path, bad, message):
    if isinstance(bad, str):
        bad = str(tmp_path / bad)
        message = f"{tmp_path}/{message}"
    for stage, call in _entry_points(bad, tmp_path).items():
        with pytest.raises(XstackError) as info:
            call()
        assert str(info.value) == message, stage
        assert "\n" not in str(info.value)
    assert not (tmp_path / "out.zarr").exists()


def test_one_positions_type(tmp_path):
    ra = np.array([RA0, RA0 + 0.01, 359.99])
    dec = np.array([DEC0, DEC0 - 0.02, 10.0])
    path = tmp_path / "cat.csv"
    Table({"ra": ra, "dec": dec}).write(path)
    kinds = {"path": path, "str": str(path), "table": Table({"ra": ra, "dec": dec}),
             "tuple": (ra, dec), "rows": np.column_stack([ra, dec]),
             "list": [[r, d] for r, d in zip(ra, dec)]}
    for kind, obj in kinds.items():
        pos = Positions.from_any(obj)
        np.testing.assert_allclose(pos.ra, np.radians(ra), rtol=0, atol=1e-15, err_msg=kind)
        np.testing.assert_allclose(pos.dec, np.radians(dec), rtol=0, atol=1e-15, err_msg=kind)
        # every stage sees the same positions
        n_ra, n_dec, _ = noise_positions(obj)
        i_ra, i_dec, _ = imstack_positions(obj)
        table = _positions_table(obj)
        np.testing.assert_allclose(np.degrees(n_ra), ra, atol=1e-12, err_msg=kind)
        np.testing.assert_allclose(i_ra, ra, atol=1e-12, err_msg=kind)
        np.testing.assert_allclose(np.asarray(table["ra"]), ra, atol=1e-12, err_msg=kind)
        np.testing.assert_allclose(np.degrees(n_dec), dec, atol=1e-12, err_msg=kind)
        np.testing.assert_allclose(i_dec, dec, atol=1e-12, err_msg=kind)
        np.testing.assert_allclose(np.asarray(table["dec"]), dec, atol=1e-12, err_msg=kind)
    weighted = Positions.from_any(Table({"ra": ra, "dec": dec, "weight": [1.0, 2.0, 3.0]}))
    np.testing.assert_array_equal(weighted.weight, [1.0, 2.0, 3.0])
    assert Positions.from_any(weighted) is weighted and len(weighted) == 3


@pytest.mark.parametrize("bad, message", [
    ("abc", None),
    ({"ra": 1.0}, "positions: give a catalog path, an astropy Table, (ra_deg, dec_deg) arrays "
                  "or an (N, 2) array of (ra, dec) in degrees"),
    (([10.0, 11.0], [5.0]), "positions: ra and dec must be non-empty arrays of equal length"),
    (([10.0], [95.0]), "positions: non-finite value or |dec| > 90 deg"),
])
def test_every_stage_rejects_bad_positions_with_one_error(bad, message):
    errors = []
    for parse in (Positions.from_any, noise_positions, imstack_positions, _positions_table):
        with pytest.raises(XstackError) as info:
            parse(bad)
        errors.append(str(info.value))
    assert len(set(errors)) == 1 and "\n" not in errors[0]
    if message is not None:
        assert errors[0] == message
