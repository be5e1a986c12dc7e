"""The antenna-factorised uv-stacking phasor: equals the plain-numpy reference, falls back to
the per-row kernel where the baseline UVW do not factorise, and records the engine."""

from __future__ import annotations

import dask
import numpy as np
import pytest
import xarray as xr
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.table import Table

from xstack.coords import lm_to_radec
from xstack.errors import XstackError
from xstack.uvstack import kernels as K
from xstack.uvstack.reference import reference_uvstack
from xstack.uvstack.stack import stack_uv


def _random_block(rng, n_time=6, ids=(0, 2, 3, 5, 8, 9, 13), extent=5e3):
    """Rows (time, baseline) from random per-antenna UVW (w-term included), non-contiguous
    antenna ids, autocorrelations included."""
    ids = np.asarray(ids)
    a1, a2 = np.triu_indices(ids.size)
    ant = rng.uniform(-extent, extent, (n_time, ids.size, 3))
    uvw = (ant[:, a1] - ant[:, a2]).reshape(-1, 3)
    return uvw, ids[a1], ids[a2]


def _positions(rng, n=40, radius=2e-2):
    l, m = rng.uniform(-radius, radius, (2, n))
    return l, m, np.sqrt(1 - l * l - m * m) - 1


@pytest.mark.parametrize("freq", [1.4e9 + 1e6 * np.arange(37),  # even: recurrence, 3 re-seeds
                                  np.array([1.0e9, 1.013e9, 1.05e9, 1.3e9, 1.31e9])])  # uneven
def test_antenna_phasor_equals_numpy_reference(rng, freq):
    uvw, a1, a2 = _random_block(rng)
    nbl = a1.size
    # missing cells (zero UVW), NaN UVW, an antenna absent for a whole integration
    uvw[[3, nbl + 5]] = 0.0
    uvw[2 * nbl + 4] = np.nan
    gone = (a1[:nbl] == 8) | (a2[:nbl] == 8)
    uvw[3 * nbl:4 * nbl][gone & (a1[:nbl] != a2[:nbl])] = 0.0
    l, m, n1 = _positions(rng)
    coef = rng.uniform(0.1, 1.0, (l.size, freq.size))
    got, err = K.phasor_antenna(uvw, freq, l, m, n1, coef, a1[:nbl], a2[:nbl])
    want = K.stack_phasor_numpy(uvw, freq, l, m, n1, coef)
    assert err < 1e-11
    ok = np.all(np.isfinite(uvw), axis=1)
    np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-9)
    # phases reach ~1e4 rad here: both kernels are at float64 rounding of such phases
    per_row = K.phasor_from_coefficients(uvw, freq, l, m, n1, coef)
    assert np.max(np.abs(got[ok] - per_row[ok])) < 1e-10
    assert np.all(np.isnan(got[~ok]))  # NaN UVW: NaN phasor, as per row
    # rows not wanted are not evaluated
    rows = rng.uniform(size=uvw.shape[0]) < 0.5
    part, _ = K.phasor_antenna(uvw, freq, l, m, n1, coef, a1[:nbl], a2[:nbl], rows=rows)
    np.testing.assert_array_equal(part[~rows], 0)
    # (the fit over other rows rounds differently)
    np.testing.assert_allclose(part[rows], got[rows], rtol=0, atol=1e-10)


def test_inconsistent_uvw_refused(rng):
    uvw, a1, a2 = _random_block(rng)
    nbl = a1.size
    freq = np.array([1.4e9, 1.5e9])
    l, m, n1 = _positions(rng)
    coef = np.ones((l.size, 2)) / l.size
    bad = uvw.copy()
    bad[nbl + 1] += [1e-3, 0, 0]  # 1 mm: ~0.6 mrad at 2e-2 and 1.5 GHz
    with pytest.raises(K.FactorisationError, match="phase error"):
        K.phasor_antenna(bad, freq, l, m, n1, coef, a1[:nbl], a2[:nbl])
    with pytest.raises(K.FactorisationError, match="whole times"):
        K.phasor_antenna(uvw[:-1], freq, l, m, n1, coef, a1[:nbl], a2[:nbl])
    with pytest.raises(K.FactorisationError, match="no gain"):
        K.phasor_antenna(uvw, freq, l, m, n1, coef, a1[:nbl], a2[:nbl],
                         min_rows_per_antenna=100)


def _cat(ra, dec):
    return Table({"ra": np.degrees(np.atleast_1d(ra)), "dec": np.degrees(np.atleast_1d(dec))})


@pytest.fixture(scope="module")
def partition():
    rng = np.random.default_rng(21)
    ds = make_stack_partition(n_time=10, n_ant=8, n_chan=5, sigma=1.0, seed=4, flag_frac=0.15,
                              extent_m=8000.0)
    vis = ds["VISIBILITY"].values.copy()
    flag = ds["FLAG"].values.copy()
    weight = ds["WEIGHT"].values.copy()
    uvw = ds["UVW"].values.copy()
    vis[flag] = np.nan  # NaN under flags
    # missing cells of an irregular grid: NaN data, zero weight, flagged, zero UVW
    miss = np.zeros(uvw.shape[:2], dtype=bool)
    miss[2, :7] = True  # antenna 0 (in baselines 0..6) absent at time 2
    miss[6, [3, 11]] = True
    vis[miss], weight[miss], flag[miss], uvw[miss] = np.nan, 0.0, True, 0.0
    ds = ds.assign(VISIBILITY=(ds["VISIBILITY"].dims, vis), FLAG=(ds["FLAG"].dims, flag),
                   WEIGHT=(ds["WEIGHT"].dims, weight), UVW=(ds["UVW"].dims, uvw))
    ra, dec = lm_to_radec(rng.uniform(-4e-3, 4e-3, 12), rng.uniform(-4e-3, 4e-3, 12),
                          *VLA_CENTER)
    ref = reference_uvstack([("p", ds)], np.degrees(ra), np.degrees(dec), weighting="pb",
                            primary_beam="auto")
    return ds, _cat(ra, dec), ref


@pytest.mark.parametrize("chunks", [None, {"time": 3}, {"time": 4, "baseline_id": 14}])
@pytest.mark.parametrize("write", [False, True])
def test_uvstack_antenna_equals_reference(partition, chunks, write, tmp_path):
    ds, cat, ref = partition
    data = ds if chunks is None else ds.chunk(chunks)
    out = tmp_path / "o.zarr" if write else None
    res = stack_uv(xr.DataTree.from_dict({"p": data}), cat, engine="antenna", out=out)
    assert res.options["engine"] == "antenna"
    assert res.options["engine_rows"] == {"antenna": 10 * 28}
    assert res.flux_jy == pytest.approx(ref["flux_jy"], rel=1e-10)
    assert res.flux_err_jy == pytest.approx(ref["flux_err_jy"], rel=1e-10)
    ok = np.isfinite(ref["stacked"]["p"])
    np.testing.assert_allclose(res.stacked["p"]["VISIBILITY"].values[ok],
                               ref["stacked"]["p"][ok], rtol=0, atol=1e-9)
    numba = stack_uv(xr.DataTree.from_dict({"p": data}), cat, engine="numba", out=out and
                    tmp_path / "n.zarr")
    assert numba.options["engine"] == "numba"
    assert res.flux_jy == pytest.approx(numba.flux_jy, rel=1e-12)


def test_auto_falls_back_per_chunk_and_records_mixed(partition):
    ds, cat, _ = partition
    uvw = ds["UVW"].values.copy()
    uvw[:5, 9] += [0.01, 0.0, 0.0]  # 1 cm off in the first 5 integrations: not factorisable
    bad = ds.assign(UVW=(ds["UVW"].dims, uvw))
    with dask.config.set(scheduler="synchronous"):
        res = stack_uv(xr.DataTree.from_dict({"p": bad.chunk({"time": 5})}), cat)
        assert res.options["engine"] == "mixed"
        assert res.options["engine_rows"] == {"numba": 5 * 28, "antenna": 5 * 28}
        per_row = stack_uv(xr.DataTree.from_dict({"p": bad.chunk({"time": 5})}), cat,
                          engine="numba")
        assert res.flux_jy == pytest.approx(per_row.flux_jy, rel=1e-12)
        every = stack_uv(xr.DataTree.from_dict({"p": bad}), cat)  # one chunk
        assert every.options["engine"] == "numba"
        with pytest.raises(XstackError, match="engine='antenna' is not valid.*phase error"):
            stack_uv(xr.DataTree.from_dict({"p": bad}), cat, engine="antenna")
        # a looser tolerance accepts the factorisation
        loose = stack_uv(xr.DataTree.from_dict({"p": bad}), cat, antenna_tol_rad=10.0)
        assert loose.options["engine"] == "antenna"


def test_numpy_engine_records_itself(partition, tmp_path):
    ds, cat, ref = partition
    res = stack_uv(xr.DataTree.from_dict({"p": ds.chunk({"time": 5})}), cat, engine="numpy",
                  out=tmp_path / "o.zarr")
    assert res.options["engine"] == "numpy" and res.options["engine_rows"] == {"numpy": 280}
    assert res.flux_jy == pytest.approx(ref["flux_jy"], rel=1e-10)


def test_without_antenna_ids(partition):
    ds, cat, _ = partition
    bare = ds.drop_vars(["baseline_antenna1_id", "baseline_antenna2_id"])
    res = stack_uv(xr.DataTree.from_dict({"p": bare}), cat)
    assert res.options["engine"] == "numba"
    with pytest.raises(XstackError, match="no baseline antenna ids"):
        stack_uv(xr.DataTree.from_dict({"p": bare}), cat, engine="antenna")
