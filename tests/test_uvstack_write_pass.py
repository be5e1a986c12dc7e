"""Writing the stack (``out=``) and the flux share one pass: one task per chunk makes both
(issue 14: the written stack costs one output chunk, no chunk-sized phasor)."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import xarray as xr
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.table import Table

from xstack.coords import lm_to_radec
from xstack.schema import open_store
from xstack.uvstack import stack as st
from xstack.uvstack.reference import reference_uvstack


def test_write_pass_evaluates_each_chunk_once_and_matches_flux_only(tmp_path, monkeypatch):
    rng = np.random.default_rng(5)
    ds = make_stack_partition(n_time=12, n_ant=7, n_chan=3, sigma=1.0, seed=4, flag_frac=0.1)
    ra, dec = lm_to_radec(rng.uniform(-3e-3, 3e-3, 8), rng.uniform(-3e-3, 3e-3, 8), *VLA_CENTER)
    cat = Table({"ra": np.degrees(ra), "dec": np.degrees(dec)})
    tree = xr.DataTree.from_dict({"p": ds.chunk({"time": 5, "baseline_id": 11})})
    n_chunks = 3 * 2
    calls = []
    lock = threading.Lock()
    real = st._block_stack_and_sums

    def counted(*args, **kwargs):
        with lock:
            calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(st, "_block_stack_and_sums", counted)
    written = st.stack_uv(tree, cat, out=tmp_path / "s.zarr")
    assert len(calls) == n_chunks  # not once per consumer (the stacked data and the sums)
    flux_only = st.stack_uv(tree, cat)
    # the same row steps in the same order: the same flux to the last bit
    assert written.flux_jy == flux_only.flux_jy
    assert written.flux_err_jy == flux_only.flux_err_jy
    ref = reference_uvstack([("p", ds)], cat["ra"], cat["dec"], weighting="pb", primary_beam="auto")
    assert written.flux_jy == pytest.approx(ref["flux_jy"], rel=1e-10)
    got = open_store(tmp_path / "s.zarr")["p"].ds["VISIBILITY"].values
    ok = np.isfinite(ref["stacked"]["p"])
    np.testing.assert_allclose(got[ok], ref["stacked"]["p"][ok], rtol=0, atol=1e-6)
