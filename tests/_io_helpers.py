"""Independent plain-numpy readers for the io tests: an MS read directly with python-casacore,
and a store flattened back to its cells, so conversions can be compared cell by cell."""

from __future__ import annotations

import casacore.tables as pt
import numpy as np

from xstack.schema import iter_partitions, open_store

STOKES = {5: "RR", 6: "RL", 7: "LR", 8: "LL", 9: "XX", 10: "XY", 11: "YX", 12: "YY"}


def ms_cells(ms, datacolumn="DATA"):
    """{(spw, field, time, a1, a2): dict(vis, weight, flag, uvw)} read row by row from an MS.

    WEIGHT follows the documented rule: WEIGHT_SPECTRUM if present, else WEIGHT broadcast,
    else 1/SIGMA^2; FLAG = FLAG | FLAG_ROW.
    """
    out = {}
    with pt.table(str(ms), ack=False) as t:
        dd = pt.table(f"{ms}/DATA_DESCRIPTION", ack=False)
        spw_of = dd.getcol("SPECTRAL_WINDOW_ID")
        dd.close()
        cols = t.colnames()
        for r in range(t.nrows()):
            row = t.getcell
            vis = row(datacolumn, r)
            if "WEIGHT_SPECTRUM" in cols and t.iscelldefined("WEIGHT_SPECTRUM", r):
                w = row("WEIGHT_SPECTRUM", r).astype(np.float32)
            elif t.iscelldefined("WEIGHT", r):
                w = np.broadcast_to(row("WEIGHT", r)[None, :], vis.shape).astype(np.float32)
            else:
                s = row("SIGMA", r).astype(np.float64)
                w = np.broadcast_to((1.0 / s**2)[None, :], vis.shape).astype(np.float32)
            flag = row("FLAG", r) | bool(row("FLAG_ROW", r))
            key = (int(spw_of[row("DATA_DESC_ID", r)]), int(row("FIELD_ID", r)), float(row("TIME", r)),
                   int(row("ANTENNA1", r)), int(row("ANTENNA2", r)))
            assert key not in out, f"duplicate row {key}"
            out[key] = {"vis": vis, "weight": w, "flag": flag, "uvw": row("UVW", r)}
    return out


def store_cells(store):
    """Flatten a store to {(spw, field, time, a1, a2): ...} for non-padding cells, and check
    that every padding cell is NaN, zero-weight and flagged. Returns (cells, n_padding)."""
    out = {}
    n_pad = 0
    for name, ds in iter_partitions(open_store(store)):
        vis, w, f, uvw = (ds[v].values for v in ("VISIBILITY", "WEIGHT", "FLAG", "UVW"))
        times = ds["time"].values
        a1, a2 = ds["baseline_antenna1_id"].values, ds["baseline_antenna2_id"].values
        spw, fid = ds.attrs["spectral_window_id"], ds.attrs["field_id"]
        nan = np.isnan(vis).all(axis=(2, 3))
        for ti in range(times.size):
            for bi in range(a1.size):
                if nan[ti, bi] and f[ti, bi].all() and (w[ti, bi] == 0).all():
                    n_pad += 1
                    assert np.all(uvw[ti, bi] == 0), name
                    continue
                key = (int(spw), int(fid), float(times[ti]), int(a1[bi]), int(a2[bi]))
                assert key not in out, f"{name}: duplicate cell {key}"
                out[key] = {"vis": vis[ti, bi], "weight": w[ti, bi], "flag": f[ti, bi],
                            "uvw": uvw[ti, bi], "partition": name}
    return out, n_pad


def assert_cells_equal(expected, got, *, check_partition=False):
    """Exact, cell by cell (NaN == NaN for visibilities)."""
    assert set(expected) == set(got), (
        f"{len(set(expected) - set(got))} MS rows missing from the store, "
        f"{len(set(got) - set(expected))} extra")
    for key, e in expected.items():
        g = got[key]
        assert g["vis"].dtype == e["vis"].dtype or e["vis"].dtype == np.complex64
        np.testing.assert_array_equal(g["vis"], e["vis"], err_msg=str(key))
        np.testing.assert_array_equal(g["weight"], e["weight"], err_msg=str(key))
        np.testing.assert_array_equal(g["flag"], e["flag"], err_msg=str(key))
        np.testing.assert_array_equal(g["uvw"], e["uvw"], err_msg=str(key))


def assert_stores_identical(a, b, variables=("VISIBILITY", "WEIGHT", "FLAG", "UVW")):
    """Two stores hold the same partitions with identical arrays and coordinates."""
    pa = dict(iter_partitions(open_store(a)))
    pb = dict(iter_partitions(open_store(b)))
    assert sorted(pa) == sorted(pb)
    for name in pa:
        for v in (*variables, "time", "baseline_antenna1_id", "baseline_antenna2_id", "frequency",
                  "channel_width", "polarization", "antenna_name", "ANTENNA_POSITION"):
            x, y = pa[name][v].values, pb[name][v].values
            assert x.dtype == y.dtype, (name, v, x.dtype, y.dtype)
            if x.dtype.kind in "fc":
                np.testing.assert_array_equal(x, y, err_msg=f"{name}/{v}")
            else:
                assert np.array_equal(x, y), (name, v)
        for attr in ("phase_center", "field_id", "spectral_window_id", "telescope_name", "field_name"):
            assert pa[name].attrs[attr] == pb[name].attrs[attr], (name, attr)


def tree_listing(path):
    """Sorted relative paths under a directory (to show nothing was written)."""
    import os

    out = []
    for root, dirs, files in os.walk(path):
        for n in dirs + files:
            out.append(os.path.relpath(os.path.join(root, n), path))
    return sorted(out)
