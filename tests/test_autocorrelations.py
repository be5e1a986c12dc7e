"""Autocorrelations are left out of every stage that measures the sky (issue 10, item 6).

Truth: python-casacore reads of the real OVRO-LWA MeasurementSet shipped in the pyuvdata wheel
(20 of its 210 rows are autocorrelations), and the same data with the autocorrelation
baselines removed from the dataset altogether.
"""

from __future__ import annotations

import numpy as np
import pytest
from astropy.table import Table

import xstack
from xstack._select import autocorrelation_mask, parallel_hand_mask
from xstack.fit._data import as_partitions, stokes_i_blocks
from xstack.schema import iter_partitions, open_store
from xstack.testing import require_real_ms

pytestmark = pytest.mark.realdata


@pytest.fixture(scope="module")
def lwa(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("lwa")
    ms = require_real_ms("ovro-lwa", tmp)
    store = xstack.convert_ms(ms, tmp / "lwa.zarr")
    return ms, store


def _casacore_mean(ms, cross_only: bool) -> float:
    """Weighted mean of Re(DATA) over unflagged XX and YY, read with python-casacore."""
    from casacore.tables import table

    with table(str(ms), ack=False, readonly=True) as t:
        data = t.getcol("DATA")
        flag = t.getcol("FLAG") | t.getcol("FLAG_ROW")[:, None, None]
        wt = t.getcol("WEIGHT_SPECTRUM")
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
    with table(str(ms) + "/POLARIZATION", ack=False, readonly=True) as p:
        corr = p.getcol("CORR_TYPE")[0]
    par = np.isin(corr, [9, 12])           # XX, YY (casacore Stokes enum)
    rows = (a1 != a2) if cross_only else np.ones(a1.size, bool)
    w = np.where(flag, 0.0, wt)[rows][:, :, par]
    return float(np.sum(w * data[rows][:, :, par].real) / np.sum(w))


def _phase_center_catalog(store):
    ds = next(iter_partitions(open_store(store)))[1]
    ra, dec = np.degrees(ds.attrs["phase_center"])
    return Table({"ra": [ra], "dec": [dec]})


def test_real_ms_has_autocorrelations(lwa):
    _, store = lwa
    ds = next(iter_partitions(open_store(store)))[1]
    assert autocorrelation_mask(ds).sum() == 20
    assert list(parallel_hand_mask(ds["polarization"].values)) == [True, True, False, False]


def test_uvstack_at_the_phase_center_uses_cross_correlations_only(lwa):
    ms, store = lwa
    cat = _phase_center_catalog(store)
    res = xstack.stack_uv(store, cat, weighting="none", primary_beam="none")
    truth = _casacore_mean(ms, cross_only=True)
    with_auto = _casacore_mean(ms, cross_only=False)
    assert abs(with_auto / truth) > 10          # autocorrelations would dominate
    assert res.flux_jy == pytest.approx(truth, rel=1e-5)
    res_all = xstack.stack_uv(store, cat, weighting="none", primary_beam="none",
                             autocorrelations=True)
    assert res_all.flux_jy == pytest.approx(with_auto, rel=1e-5)
    assert res.options["autocorrelations"] is False


def test_fit_and_noise_readers_skip_autocorrelations(lwa):
    _, store = lwa
    (name, ds), = as_partitions(store)
    auto = autocorrelation_mask(ds)
    for _uvw, _vis, wt in stokes_i_blocks(ds, name):
        per_row = wt.reshape(ds.sizes["time"], ds.sizes["baseline_id"], -1).sum(axis=-1)
        assert np.all(per_row[:, auto] == 0)
        assert np.any(per_row[:, ~auto] > 0)
    (_, ds_all), = as_partitions(store, autocorrelations=True)
    assert not bool(ds_all["FLAG"].values[:, auto].all())


def test_image_equals_image_of_cross_correlations(lwa):
    from xstack.imaging.image import make_image

    _, store = lwa
    (name, ds), = list(iter_partitions(open_store(store)))
    cross = ds.isel(baseline_id=np.flatnonzero(~autocorrelation_mask(ds))).load()
    kw = dict(size=64, cell_arcsec=1800.0, wterm=False)
    a = make_image(ds, **kw)
    b = make_image(cross, **kw)
    np.testing.assert_allclose(a.image, b.image, rtol=1e-6, atol=1e-6 * np.abs(b.image).max())


def test_subtract_leaves_autocorrelations_alone(lwa, tmp_path):
    _, store = lwa
    cat = _phase_center_catalog(store)
    cat["flux"] = [1000.0]
    out = xstack.subtract(store, cat, tmp_path / "res.zarr", primary_beam="none")
    (_, before), = list(iter_partitions(open_store(store)))
    (_, after), = list(iter_partitions(open_store(out)))
    auto = autocorrelation_mask(before)
    vb, va = before["VISIBILITY"].values, after["VISIBILITY"].values
    np.testing.assert_array_equal(va[:, auto], vb[:, auto])
    # a 1000 Jy point source at the phase center is 1000 + 0j on every cross-correlation
    # (complex64 data of amplitude up to ~1e8: compare to its rounding)
    diff = (vb.astype(np.complex128) - va)[:, ~auto][..., :2]
    tol = 2 * np.finfo(np.float32).eps * np.abs(vb[:, ~auto]).max()
    np.testing.assert_allclose(diff, 1000.0, atol=tol)
    assert np.median(np.abs(diff - 1000.0)) < 1e-3


def test_cli_leaves_autocorrelations_out_unless_asked(lwa, tmp_path, capsys):
    import json

    from xstack.cli import main

    ms, store = lwa
    cat = _phase_center_catalog(store)
    cat_path = tmp_path / "center.ecsv"
    cat.write(cat_path)
    args = ["uvstack", str(store), str(cat_path), None, "--weighting", "none",
            "--primary-beam", "none", "--json", "--no-progress"]
    got = {}
    for flag in ([], ["--autocorrelations"]):
        out = tmp_path / f"s{len(flag)}.zarr"
        assert main([str(out) if a is None else a for a in args] + flag) == 0
        cap = capsys.readouterr()
        got[bool(flag)] = json.loads(cap.out)["flux_jy"]
        # warnings (here: WEIGHT = 1 against the data's own scatter) as one-line messages
        assert "UserWarning" not in cap.err and "warnings.warn" not in cap.err
        assert any(line.startswith("warning: ") and "--errors" in line
                   for line in cap.err.splitlines())
    assert got[False] == pytest.approx(_casacore_mean(ms, cross_only=True), rel=1e-5)
    assert got[True] == pytest.approx(_casacore_mean(ms, cross_only=False), rel=1e-5)
