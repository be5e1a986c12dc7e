"""uv-stacking gives the same bits whatever the number of threads (issue 14).

A laptop's threaded run and a cluster's single-threaded workers must agree to the last bit, so
a survey can be re-run anywhere and compared with ``==``. The flux sums used to be a numba
``prange`` reduction, which splits the rows by thread count; they are now fixed-size row
blocks added in order. Truth: the same call with another thread count, and the plain-numpy
twin of the kernel (to rounding)."""

from __future__ import annotations

import dask
import numba
import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.table import Table

import xstack
from xstack.coords import lm_to_radec
from xstack.schema import write_store
from xstack.uvstack.kernels import SUM_BLOCK_ROWS, stack_sums, stack_sums_numpy


def _with_threads(n: int, fn, *args, **kwargs):
    """``fn`` with numba's thread count of *this* thread set to ``n`` (it is per thread)."""
    old = numba.get_num_threads()
    numba.set_num_threads(n)
    try:
        return fn(*args, **kwargs)
    finally:
        numba.set_num_threads(old)


@pytest.fixture(scope="module")
def chunk():
    """A chunk of 20 blocks' worth of rows with every feature the kernel sums: a phasor, a
    uv mask, flags, zero and NaN weights, NaN visibilities under flags, a noise model."""
    rng = np.random.default_rng(4)
    nrow, nchan, npol, nbl = 20 * SUM_BLOCK_ROWS + 37, 5, 2, 21
    nrow -= nrow % nbl
    vis = (rng.normal(size=(nrow, nchan, npol)) + 1j * rng.normal(size=(nrow, nchan, npol))) * 1e3
    weight = rng.uniform(0.1, 3.0, (nrow, nchan, npol))
    weight[rng.random(weight.shape) < 0.05] = 0.0
    flag = rng.random(vis.shape) < 0.1
    vis[flag & (rng.random(vis.shape) < 0.5)] = np.nan
    phasor = np.exp(1j * rng.uniform(0, 2 * np.pi, (nrow, nchan))) * rng.uniform(0.5, 1, (nrow, nchan))
    uv_mask = rng.random((nrow, nchan)) < 0.9
    noise = np.stack([rng.uniform(0.5, 2, (nbl, npol)), rng.uniform(0, 1, (nbl, npol)),
                      rng.integers(1, 3, (nbl, npol)).astype(float)], axis=-1)
    return vis, weight, flag, phasor, None, uv_mask, noise


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs 2 numba threads")
def test_stack_sums_same_bits_for_any_thread_count(chunk):
    one = _with_threads(1, stack_sums, *chunk)
    two = _with_threads(2, stack_sums, *chunk)
    np.testing.assert_array_equal(one, two)
    # and they are the sums: the plain-numpy twin agrees to rounding
    np.testing.assert_allclose(one, stack_sums_numpy(*chunk), rtol=1e-12)


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs 2 numba threads")
def test_stack_uv_same_bits_for_any_thread_count(tmp_path):
    """End to end: flux, error and weights of ``stack_uv`` on a chunked store, with the kernels
    on 1 and on 2 numba threads (dask's synchronous scheduler: the tasks run in this thread,
    whose numba thread count is the one set)."""
    ds = make_stack_partition(n_time=40, n_ant=12, n_chan=6, sigma=1.0, seed=3, flag_frac=0.05)
    store = tmp_path / "data.zarr"
    write_store({"p": ds.chunk({"time": 10})}, store)
    rng = np.random.default_rng(2)
    ra, dec = lm_to_radec(rng.uniform(-3e-3, 3e-3, 25), rng.uniform(-3e-3, 3e-3, 25), *VLA_CENTER)
    cat = Table({"ra": np.degrees(ra), "dec": np.degrees(dec)})
    with dask.config.set(scheduler="sync"):
        one = _with_threads(1, xstack.stack_uv, store, cat).to_dict()
        two = _with_threads(2, xstack.stack_uv, store, cat).to_dict()
    assert one == two
