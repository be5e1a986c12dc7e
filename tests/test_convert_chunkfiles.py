"""convert writes chunk files itself (xstack.io._store.ChunkFiles): the bytes must be zarr's."""

from __future__ import annotations

import numpy as np
import pytest
import zarr
from zarr.codecs import BloscCodec, ZstdCodec

from xstack.io._store import ChunkFiles
from xstack.io.convert import convert_ms
from xstack.testing import make_test_ms

CODECS = {
    "raw": None,
    "blosc-shuffle": BloscCodec(cname="lz4", clevel=5, shuffle="shuffle"),
    "blosc-bitshuffle": BloscCodec(cname="lz4", clevel=5, shuffle="bitshuffle"),
    "zstd": ZstdCodec(level=3, checksum=True),
}


def _files(path):
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*"))
            if p.is_file() and p.name != "zarr.json"}


@pytest.mark.parametrize("codec", sorted(CODECS))
@pytest.mark.parametrize("dtype", ["complex64", "complex128", "float32", "float64", "bool"])
def test_chunk_files_match_zarr(tmp_path, codec, dtype):
    rng = np.random.default_rng(3)
    shape, chunks = (10, 6, 3, 2), (4, 6, 3, 2)  # the last time chunk is an edge chunk
    if dtype == "bool":
        data = rng.uniform(size=shape) < 0.1
    else:
        data = np.round(rng.standard_normal(shape) * 4).astype(dtype)
    with zarr.config.set({"array.write_empty_chunks": True}):
        ref = zarr.create_array(tmp_path / "ref.zarr", shape=shape, chunks=chunks, dtype=dtype,
                                compressors=CODECS[codec])
        ref[...] = data
        ours = zarr.create_array(tmp_path / "ours.zarr", shape=shape, chunks=chunks, dtype=dtype,
                                 compressors=CODECS[codec])
    files = ChunkFiles.for_array(ours)
    assert files is not None and files.raw == (codec == "raw")
    for i in range(3):
        chunk = np.full(chunks, ours.fill_value, dtype=dtype)
        part = data[4 * i:4 * (i + 1)]
        chunk[:part.shape[0]] = part
        files.write((i, 0, 0, 0), chunk)
    assert _files(tmp_path / "ours.zarr") == _files(tmp_path / "ref.zarr")
    np.testing.assert_array_equal(zarr.open_array(tmp_path / "ours.zarr")[...], data)


def test_unsupported_layouts_fall_back(tmp_path):
    sharded = zarr.create_array(tmp_path / "s.zarr", shape=(8, 4), chunks=(2, 4), shards=(4, 4),
                                dtype="f4")
    assert ChunkFiles.for_array(sharded) is None
    big_endian = zarr.create_array(tmp_path / "b.zarr", shape=(8, 4), chunks=(2, 4), dtype=">f4")
    assert ChunkFiles.for_array(big_endian) is None


@pytest.mark.parametrize(("kw", "chunks"), [
    (dict(), {"time": 4}),  # rows fill the chunks in order: streamed batch by batch
    (dict(), {"time": 4, "baseline_id": 6}),  # whole chunks, and zarr for the baseline edge
    (dict(missing_rows=0.3, missing_baselines=2), {"time": 4}),  # padded chunks
])
def test_converted_chunk_files_are_zarrs(tmp_path, monkeypatch, kw, chunks):
    # small read batches, so a chunk is streamed in several pieces, and the edge chunk's
    # padding is written in several pieces too
    monkeypatch.setattr("xstack.io.msread.READ_BATCH_BYTES", 5000)
    monkeypatch.setattr("xstack.io.convert.FILL_PIECE_BYTES", 1000)
    ms = make_test_ms(tmp_path / "in.ms", n_antennas=6, n_times=11, seed=5, **kw)
    out = convert_ms(ms, tmp_path / "out.zarr", chunks=chunks)
    group = zarr.open_group(out, mode="r")
    for name in group.attrs["partitions"]:
        for var in ("VISIBILITY", "WEIGHT", "FLAG", "UVW", "TIME_CENTROID", "EFFECTIVE_INTEGRATION_TIME"):
            src = group[name][var]
            dst_path = tmp_path / "ref" / name / var
            with zarr.config.set({"array.write_empty_chunks": True}):
                dst = zarr.create_array(dst_path, shape=src.shape, chunks=src.chunks, dtype=src.dtype,
                                        compressors=src.compressors, fill_value=src.fill_value)
                dst[...] = src[...]
            assert _files(out / name / var) == _files(dst_path), (name, var)


@pytest.mark.parametrize(("kw", "n_sets"), [
    (dict(), 1),  # every chunk streamed: its WEIGHT/FLAG are written before the next is read
    (dict(missing_rows=0.3, missing_baselines=2), 2),  # padded chunks alternate two sets
])
def test_streamed_conversion_needs_one_buffer_set(tmp_path, monkeypatch, kw, n_sets):
    """The converter's memory: a regular MS (every chunk streamed) is converted through one
    chunk-sized buffer set of WEIGHT/FLAG/UVW (the peak-memory goal of issue 13), an
    irregular one through two; the store is the MS's either way."""
    from xstack.io import msread

    calls = []
    real = msread.block_buffers

    def counting(*args, **kwargs):
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(msread, "block_buffers", counting)
    monkeypatch.setattr("xstack.io.msread.READ_BATCH_BYTES", 5000)
    ms = make_test_ms(tmp_path / "in.ms", n_antennas=6, n_times=11, seed=5, **kw)
    out = convert_ms(ms, tmp_path / "out.zarr", chunks={"time": 3})
    group = zarr.open_group(out, mode="r")
    names = list(group.attrs["partitions"])
    assert len(calls) == n_sets * len(names)
    import casacore.tables as pt

    with pt.table(str(ms), ack=False) as tab:
        data = tab.getcol("DATA")
    got = np.concatenate([group[n]["VISIBILITY"][...].reshape(-1, *data.shape[1:]) for n in names])
    got = got[np.isfinite(got).all(axis=(1, 2))]
    assert got.shape == data.shape
    np.testing.assert_array_equal(np.sort_complex(got.ravel()), np.sort_complex(data.ravel()))
