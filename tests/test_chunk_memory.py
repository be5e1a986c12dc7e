"""Memory per chunk (issue 14): a store's chunk is read into its own array, and the uv-stack's
phasor is evaluated in steps of a fixed size in bytes, whatever the number of channels.

Truth: zarr's own read of the same arrays (values to the bit) and tracemalloc's peak against
the chunk's size (zarr's read holds a chunk ~3 times; a whole 256-channel chunk's phasor is
the chunk's size again)."""

from __future__ import annotations

import shutil
import tracemalloc

import numpy as np
import pytest
import zarr
from _uvstack_helpers import make_stack_partition

from xstack.schema import open_store, write_store
from xstack.uvstack import stack as st


def _zarr_values(store, name, var):
    group = zarr.open_group(str(store), mode="r")
    return group[name][var][...]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Edge chunks in time (50 = 3 x 16 + 2) and baseline (45 = 2 x 20 + 5)."""
    ds = make_stack_partition(n_time=50, n_ant=10, n_chan=16, sigma=1.0, seed=2, flag_frac=0.1,
                              dtype=np.complex64)
    path = tmp_path_factory.mktemp("chunks") / "data.zarr"
    write_store({"p": ds.chunk({"time": 16, "baseline_id": 20})}, path)
    return path


def test_blocks_read_from_their_files_equal_zarrs_read(store, tmp_path):
    tree = open_store(store)
    name = next(iter(tree.children))
    group = zarr.open_group(str(store), mode="r")[name]
    checked = 0
    for var in ("VISIBILITY", "WEIGHT", "FLAG", "UVW"):
        if var not in group:
            continue
        got = tree[name].ds[var].values
        np.testing.assert_array_equal(got, group[var][...], err_msg=var)
        checked += 1
    assert checked >= 3
    # a chunk file never written reads as the fill value, as zarr reads it
    copy = tmp_path / "copy.zarr"
    shutil.copytree(store, copy)
    chunk = next((copy / name / "VISIBILITY" / "c").rglob("*"))
    while chunk.is_dir():
        chunk = next(chunk.iterdir())
    chunk.unlink()
    got = open_store(copy)[name].ds["VISIBILITY"].values
    np.testing.assert_array_equal(got, _zarr_values(copy, name, "VISIBILITY"))


def test_reading_a_chunk_holds_it_about_once(tmp_path):
    ds = make_stack_partition(n_time=32, n_ant=24, n_chan=64, sigma=1.0, seed=4,
                              dtype=np.complex64)
    path = tmp_path / "big.zarr"
    write_store({"p": ds.chunk({"time": 16})}, path)
    tree = open_store(path)
    vis = tree["p"].ds["VISIBILITY"].data
    block = vis.blocks[0, 0]
    nbytes = int(np.prod(block.shape)) * vis.dtype.itemsize
    assert nbytes > 2**22  # 4.5 MB: large against the fixed costs of a read
    block.compute(scheduler="sync")  # imports and codecs loaded before measuring
    tracemalloc.start()
    try:
        out = block.compute(scheduler="sync")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert out.nbytes == nbytes
    # the block plus at most its compressed bytes (zarr's own path holds ~3 blocks)
    assert peak < 2.2 * nbytes, (peak, nbytes)


@pytest.mark.parametrize("nb, nchan", [(66, 256), (351, 10), (351, 4096), (27, 1)])
def test_phasor_steps_are_bounded_in_bytes_not_rows(nb, nchan):
    """The flux pass evaluates the phasor (complex128 per row and channel) in steps of
    ``_STEP_BYTES`` (whole integrations when one fits), so its temporaries do not grow with
    the chunk or the channels: a fixed 65536 rows made a whole 256-channel chunk's phasor
    at once (1x the chunk). The steps cover every row exactly once."""
    nt = 500
    seen = np.zeros((nt, nb), dtype=int)
    for tsl, bsl in st._steps(nt, nb, nchan):
        rows = len(range(*tsl.indices(nt))) * len(range(*bsl.indices(nb)))
        whole_integrations = bsl == slice(None)
        assert rows * nchan * 16 <= max(st._STEP_BYTES, nb * nchan * 16 if whole_integrations
                                        else 16 * nchan), (tsl, bsl)
        seen[tsl, bsl] += 1
    assert (seen == 1).all()
