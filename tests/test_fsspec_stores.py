"""Stores at fsspec URLs (issue 14): ``memory://``, ``s3://`` (moto's S3 server), ``file://``.

Truth: the same conversion and stack on the local disk (the code paths that existed before),
compared bitwise; the files on the server listed with s3fs itself.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import uuid

import fsspec
import numpy as np
import pytest
from fsspec.implementations.memory import MemoryFileSystem

import xstack
from xstack.errors import OutputExistsError, SchemaError, XstackError
from xstack.io.convert import convert_ms
from xstack.schema import open_store
from xstack.testing import make_test_ms

s3fs = pytest.importorskip("s3fs")
moto_server = pytest.importorskip("moto.server")

BUCKET = "xstack-test"
VARS = ("VISIBILITY", "WEIGHT", "FLAG", "UVW")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def s3():
    """A local S3 server (moto) with one bucket; the endpoint is given the standard way
    (``AWS_ENDPOINT_URL``), with dummy credentials. Yields the endpoint URL."""
    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # one line per request otherwise
    port = _free_port()
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    endpoint = f"http://127.0.0.1:{port}"
    mp = pytest.MonkeyPatch()
    try:
        for var in ("AWS_PROFILE", "AWS_SESSION_TOKEN", "AWS_CONFIG_FILE", "FSSPEC_S3_ENDPOINT_URL"):
            mp.delenv(var, raising=False)
        mp.setenv("AWS_ACCESS_KEY_ID", "testing")
        mp.setenv("AWS_SECRET_ACCESS_KEY", "testing")
        mp.setenv("AWS_DEFAULT_REGION", "us-east-1")
        mp.setenv("AWS_ENDPOINT_URL", endpoint)
        s3fs.S3FileSystem.clear_instance_cache()
        s3fs.S3FileSystem().mkdir(BUCKET)
        yield endpoint
    finally:
        s3fs.S3FileSystem.clear_instance_cache()
        mp.undo()
        server.stop()


@pytest.fixture(scope="module")
def ms(tmp_path_factory):
    """A small MS with a 1 Jy source at the phase center (two partitions: two windows)."""
    from xstack.testing._ms import DEFAULT_PHASE_CENTER

    ra, dec = np.degrees(DEFAULT_PHASE_CENTER)
    path = make_test_ms(tmp_path_factory.mktemp("fsspec") / "t.ms", n_times=12, n_spws=2,
                        sources=[(ra + 2 / 3600, dec + 1 / 3600, 1.0)], noise_jy=0.1)
    return path, (float(ra + 2 / 3600), float(dec + 1 / 3600))


@pytest.fixture(scope="module")
def local(ms, tmp_path_factory):
    """The reference: conversion, stack and stacked store on the local disk."""
    path, pos = ms
    d = tmp_path_factory.mktemp("local")
    store = convert_ms(path, d / "in.zarr", chunks={"time": 5})
    res = xstack.stack_uv(store, pos, out=d / "out.zarr")
    return store, res, d / "out.zarr"


def _url(protocol: str) -> str:
    root = f"s3://{BUCKET}" if protocol == "s3" else "memory://xstack-test"
    return f"{root}/{uuid.uuid4().hex[:8]}"


def _same(a, b) -> None:
    """Two opened stores hold bitwise the same data in every partition."""
    assert sorted(a.children) == sorted(b.children)
    for name in a.children:
        for var in VARS:
            x, y = np.asarray(a[name][var].values), np.asarray(b[name][var].values)
            assert x.dtype == y.dtype and x.shape == y.shape
            assert x.tobytes() == y.tobytes(), (name, var)


@pytest.fixture(scope="module")
def s3_store(s3, ms):
    """The MS converted to s3:// (the URL)."""
    url = f"{_url('s3')}/in.zarr"
    assert convert_ms(ms[0], url, chunks={"time": 5}) == url
    return url


@pytest.mark.parametrize("protocol", ["memory", "s3"])
def test_convert_and_stack_at_url(protocol, ms, local, request):
    path, pos = ms
    ref_store, ref, ref_out = local
    base = _url(protocol)
    if protocol == "s3":
        store = request.getfixturevalue("s3_store")
    else:
        store = convert_ms(path, f"{base}/in.zarr", chunks={"time": 5})
        assert store == f"{base}/in.zarr"
    _same(open_store(store), open_store(ref_store))

    res = xstack.stack_uv(store, pos, out=f"{base}/out.zarr")
    assert res.flux_jy == ref.flux_jy and res.flux_err_jy == ref.flux_err_jy
    assert abs(ref.flux_jy - 1.0) < 0.1  # the source is there
    stacked = open_store(f"{base}/out.zarr")
    assert stacked.attrs["xstack_kind"] == "stacked" and stacked.attrs["xstack_complete"]
    _same(stacked, open_store(ref_out))

    if protocol == "s3":
        # the objects on the server, listed by s3fs itself: a complete store with its
        # consolidated metadata and the completion flag in the root zarr.json
        fs = s3fs.S3FileSystem()
        key = f"{base.removeprefix('s3://')}/out.zarr"
        root = json.loads(fs.cat(f"{key}/zarr.json"))
        assert root["attributes"]["xstack_complete"] is True
        assert root["consolidated_metadata"]["metadata"]
        # another MSv4 reader: xradio's, which finds the endpoint the standard way too
        from xradio.measurement_set import open_processing_set

        try:
            ps = open_processing_set(f"{base}/out.zarr")
        except Exception as exc:  # pragma: no cover - depends on xradio's s3 support
            pytest.skip(f"xradio cannot open s3:// stores here: {exc}")
        assert sorted(ps.children) == sorted(open_store(ref_out).children)


def test_output_url_exists(ms):
    path, _ = ms
    url = f"{_url('memory')}/in.zarr"
    convert_ms(path, url)
    with pytest.raises(OutputExistsError, match="exists"):
        convert_ms(path, url)
    convert_ms(path, url, overwrite=True, chunks={"time": 4})
    assert open_store(url)["spw0_field0"].VISIBILITY.chunks[0][0] == 4


_KILLED = """
import sys, time
import xstack.io._store as store

def stall(*args, **kwargs):  # every chunk is written; the completion flag would be next
    print("READY", flush=True)
    time.sleep(600)

store.finish_store = stall
from xstack.io.convert import convert_ms
convert_ms(sys.argv[1], sys.argv[2], chunks={"time": 3})
"""


def test_killed_convert_to_s3_never_opens(s3, ms):
    """A conversion to s3:// killed (SIGKILL) after writing every chunk but before its
    completion flag leaves objects that do not open as a store; overwrite=True replaces them."""
    path, _ = ms
    url = f"{_url('s3')}/in.zarr"
    proc = subprocess.Popen([sys.executable, "-c", _KILLED, str(path), url],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        assert line.strip() == "READY", proc.stderr.read()
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
        proc.stdout.close()
        proc.stderr.close()
    fs = s3fs.S3FileSystem()
    fs.invalidate_cache()
    key = url.removeprefix("s3://")
    assert any(k.endswith("/VISIBILITY/c/0/0/0/0") for k in fs.find(key))  # data were written
    with pytest.raises(SchemaError) as err:
        open_store(url)
    assert "incomplete store" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(OutputExistsError):
        convert_ms(path, url)
    convert_ms(path, url, overwrite=True)
    assert sorted(open_store(url).children) == ["spw0_field0", "spw1_field0"]


def test_failed_write_leaves_nothing(ms, monkeypatch):
    """An error while chunks are written (here the third chunk write) removes what was
    written: the URL holds nothing, and nothing opens."""
    import zarr

    path, _ = ms
    url = f"{_url('memory')}/in.zarr"
    calls = []
    setitem = zarr.Array.__setitem__

    def failing(self, key, value):
        calls.append(key)
        if len(calls) == 3:
            raise OSError("disk on fire")
        return setitem(self, key, value)

    monkeypatch.setattr(zarr.Array, "__setitem__", failing)
    with pytest.raises(OSError, match="disk on fire"):
        convert_ms(path, url, chunks={"time": 3})
    monkeypatch.undo()
    assert len(calls) == 3
    from xstack._fs import locate

    assert not locate(url).exists()
    with pytest.raises(XstackError, match="no such store"):
        open_store(url)


def test_incomplete_store_at_url_refused():
    """A store whose root says it is not complete (as every store is until its last write)
    is refused at a URL exactly as on disk."""
    import zarr
    from conftest import make_partition

    from xstack.schema import quiet_zarr_warnings, write_store

    url = f"{_url('memory')}/a.zarr"
    write_store({"spw0_field0": make_partition()}, url)
    assert open_store(url).attrs["xstack_complete"] is True
    with quiet_zarr_warnings():  # MSv4's fixed-width strings, in the consolidated metadata
        root = zarr.open_group(zarr.storage.FsspecStore.from_url(url), mode="r+", zarr_format=3)
        root.attrs["xstack_complete"] = False
    with pytest.raises(SchemaError, match="incomplete store"):
        open_store(url)


def test_storage_options(s3, s3_store, monkeypatch):
    """The endpoint from explicit storage_options, from use_storage_options, or from fsspec's
    own configuration variable (FSSPEC_S3_ENDPOINT_URL), with AWS_ENDPOINT_URL unset."""
    url = s3_store
    monkeypatch.delenv("AWS_ENDPOINT_URL")
    ref = open_store(url, storage_options={"endpoint_url": s3})
    with xstack.use_storage_options({"endpoint_url": s3}):
        _same(open_store(url), ref)
    monkeypatch.setenv("FSSPEC_S3_ENDPOINT_URL", s3)
    _same(open_store(url), ref)
    with pytest.raises(XstackError, match="storage_options"):
        open_store(url, storage_options=["endpoint_url"])


def test_cli_at_s3_with_storage_options(s3, s3_store, ms, local, monkeypatch, capsys, tmp_path):
    """``xstack uvstack`` from and to s3:// with --storage-options (the endpoint given only
    there); a --storage-options that is no JSON object is a one-line usage error."""
    from xstack.cli import main

    path, pos = ms
    _, ref, ref_out = local
    base = _url("s3")
    catalog = tmp_path / "cat.csv"
    catalog.write_text(f"ra,dec\n{pos[0]!r},{pos[1]!r}\n")
    monkeypatch.delenv("AWS_ENDPOINT_URL")
    opts = json.dumps({"endpoint_url": s3})
    assert main(["uvstack", s3_store, str(catalog), f"{base}/out.zarr",
                 "--storage-options", opts, "--json", "-q", "--no-progress"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["flux_jy"] == ref.flux_jy
    _same(open_store(f"{base}/out.zarr", storage_options={"endpoint_url": s3}), open_store(ref_out))
    # the uv-profile table and plot beside the store, uploaded whole
    fs = s3fs.S3FileSystem(endpoint_url=s3)
    assert fs.exists(f"{base.removeprefix('s3://')}/out_uvprofile.ecsv")
    assert fs.exists(f"{base.removeprefix('s3://')}/out_uvprofile.png")
    for bad in ("{nope", "[1]"):
        with pytest.raises(SystemExit) as exit_:
            main(["convert", str(path), f"{base}/x.zarr", "--storage-options", bad])
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith("error: convert: argument --storage-options") and err.count("\n") == 1


def test_file_url_is_a_path(ms, local, tmp_path):
    path, pos = ms
    ref_store, ref, _ = local
    url = (tmp_path / "in.zarr").as_uri()
    assert url.startswith("file://")
    out = convert_ms(path, url, chunks={"time": 5})
    assert out == tmp_path / "in.zarr"  # a plain local store, renamed into place
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    _same(open_store(url), open_store(ref_store))
    res = xstack.stack_uv(url, pos, out=(tmp_path / "out.zarr").as_uri())
    assert res.flux_jy == ref.flux_jy
    assert (tmp_path / "out.zarr" / "zarr.json").is_file()
    with pytest.raises(OutputExistsError):
        convert_ms(path, url)


def test_unknown_protocol_is_one_line(ms, monkeypatch, tmp_path):
    with pytest.raises(XstackError) as err:
        open_store("nosuchprotocol://bucket/a.zarr")
    text = str(err.value)
    assert "nosuchprotocol" in text and "\n" not in text
    # gs:// without gcsfs (made unimportable if it is installed), as input and as output
    monkeypatch.setitem(sys.modules, "gcsfs", None)
    monkeypatch.delitem(sys.modules["fsspec.registry"]._registry, "gs", raising=False)
    need = r"^gs://bucket/a\.zarr: gs:// URLs need the package gcsfs \(pip install gcsfs\)$"
    for call in (lambda: open_store("gs://bucket/a.zarr"),
                 lambda: convert_ms(ms[0], "gs://bucket/a.zarr"),
                 lambda: xstack.stack_uv(tmp_path / "nothing.zarr", ms[1],
                                         out="gs://bucket/a.zarr", compute=False)):
        with pytest.raises(XstackError, match=need):
            call()


def test_chunk_writer_only_for_local_stores(tmp_path):
    """xstack's direct chunk-file writer takes arrays of local stores only; an array at a
    URL is written through zarr (ChunkFiles.for_array gives None)."""
    import zarr

    from xstack.io._store import ChunkFiles

    local = zarr.open_group(str(tmp_path / "a.zarr"), mode="w", zarr_format=3)
    remote = zarr.open_group(zarr.storage.FsspecStore.from_url(f"{_url('memory')}/a.zarr"),
                             mode="w", zarr_format=3)
    for group, expected in ((local, True), (remote, False)):
        arr = group.create_array("x", shape=(8, 4), chunks=(4, 4), dtype="f4", compressors=None)
        assert (ChunkFiles.for_array(arr) is not None) is expected


def test_simulate_to_url(tmp_path):
    """simulate() to memory://: the store and its catalog beside it, equal to the local run."""
    from astropy.table import Table

    from xstack.sim.scene import PAPER_FIELD_CENTER

    ra, dec = PAPER_FIELD_CENTER
    scene = {"name": "t", "array": {"config": "alma.cycle1.2"},
             "observation": {"hour_angle": [-0.1, 0.1], "integration": 6.0,
                             "time_per_pointing": 30.0},
             "spectral": {"center": 230e9, "bandwidth": 4e9, "channels": 2,
                          "polarizations": ["XX", "YY"]},
             "pointings": {"mode": "single", "center": [ra, dec]},
             "effects": {"noise": {"sigma": 0.1}}, "visibility_dtype": "complex64",
             "populations": [{"name": "p", "count": 1, "flux": {"kind": "fixed", "value": 1e-3},
                              "positions": {"kind": "list", "ra": [ra], "dec": [dec]},
                              "shape": {"kind": "point"}}]}
    ref = xstack.simulate(scene, tmp_path / "sim.zarr", seed=2)
    base = _url("memory")
    res = xstack.simulate(scene, f"{base}/sim.zarr", seed=2)
    assert res.store == f"{base}/sim.zarr" and res.catalog_paths["p"] == f"{base}/sim.p.ecsv"
    _same(open_store(res.store), open_store(ref.store))
    from xstack._fs import locate

    table = Table.read(locate(res.catalog_paths["p"]).read_bytes().decode(), format="ascii.ecsv")
    assert list(table["ra"]) == list(Table.read(ref.catalog_paths["p"], format="ascii.ecsv")["ra"])


@pytest.fixture(scope="module")
def memory_store(ms):
    """The MS converted to memory:// (the URL)."""
    return convert_ms(ms[0], f"{_url('memory')}/in.zarr", chunks={"time": 5})


def test_export_from_url(memory_store, local, tmp_path):
    """export_ms reads a store URL: the same MeasurementSet as from the local store."""
    import casacore.tables as pt

    a = xstack.export_ms(local[0], tmp_path / "a.ms")
    b = xstack.export_ms(memory_store, tmp_path / "b.ms")
    with pt.table(str(a), ack=False) as ta, pt.table(str(b), ack=False) as tb:
        for col in ("DATA", "WEIGHT_SPECTRUM", "FLAG", "UVW", "TIME"):
            assert ta.getcol(col).tobytes() == tb.getcol(col).tobytes(), col
    with pt.table(f"{b}::HISTORY", ack=False) as hist:
        assert memory_store in " ".join(hist.getcol("MESSAGE"))


def test_info_and_fit_cli_read_store_urls(memory_store, ms, local, capsys):
    """``xstack info`` and ``xstack fit`` take a store URL where they take a store path."""
    from xstack.cli import main

    ref_store, _, ref_out = local
    base = memory_store.rsplit("/", 1)[0]
    xstack.stack_uv(memory_store, ms[1], out=f"{base}/out.zarr")
    capsys.readouterr()
    for args in (["info"], ["fit"]):
        assert main([*args, str(ref_store if args == ["info"] else ref_out), "--json"]) == 0
        want = json.loads(capsys.readouterr().out)
        url = memory_store if args == ["info"] else f"{base}/out.zarr"
        assert main([*args, url, "--json"]) == 0
        got = json.loads(capsys.readouterr().out)
        for key in ("path", "stacked", "seconds", "input"):
            want.pop(key, None)
            got.pop(key, None)
        assert got == want


@pytest.mark.slow
def test_stack_s3_on_a_local_cluster(s3, s3_store, ms, local):
    """uv-stacking from and to s3:// on a LocalCluster of 2 worker processes (they find the
    endpoint the standard way, in the environment they inherit): the stacked store bitwise
    equal to the local threaded run's, the flux equal up to the order of the sums."""
    from distributed import Client, LocalCluster

    _, ref, ref_out = local
    url = f"{_url('s3')}/out.zarr"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster, Client(cluster):
        res = xstack.stack_uv(s3_store, ms[1], out=url)
    assert res.flux_jy == pytest.approx(ref.flux_jy, rel=1e-12, abs=0)
    _same(open_store(url), open_store(ref_out))


# --------------------------------------------------------------------------- any protocol
class _NoRenameFS(MemoryFileSystem):
    """A fake object store under its own protocol: a MemoryFileSystem (own storage) whose
    moves and renames fail, as on an object store, and that records the files written, in
    order. xstack knows nothing of it: no s3- or memory-specific code can apply."""

    protocol = ("xstacktest",)
    store: dict = {}  # noqa: RUF012 - fsspec's own layout: class-level storage
    pseudo_dirs = [""]  # noqa: RUF012
    written: list = []  # noqa: RUF012

    @classmethod
    def _strip_protocol(cls, path):
        return super()._strip_protocol(str(path).removeprefix("xstacktest://"))

    def mv(self, *args, **kwargs):
        raise NotImplementedError("xstacktest:// has no rename")

    rename = move = mv

    def _open(self, path, mode="rb", *args, **kwargs):
        # every write (pipe_file too) opens here; the file is visible from the open on
        f = super()._open(path, mode, *args, **kwargs)
        if "w" in mode or "x" in mode:
            self.written.append((self._strip_protocol(path), f))
        return f


@pytest.fixture
def xstacktest():
    fsspec.register_implementation("xstacktest", _NoRenameFS, clobber=True)
    _NoRenameFS.clear_instance_cache()
    _NoRenameFS.written.clear()
    try:
        yield _NoRenameFS
    finally:
        _NoRenameFS.store.clear()
        _NoRenameFS.pseudo_dirs[:] = [""]
        _NoRenameFS.clear_instance_cache()
        # fsspec has no public unregister
        sys.modules["fsspec.registry"]._registry.pop("xstacktest", None)


def _root_flag(data) -> bool | None:
    """The completion flag in a root ``zarr.json`` (a written MemoryFile)."""
    return json.loads(data.getvalue()).get("attributes", {}).get("xstack_complete")


@pytest.mark.parametrize("lazy", [False, True])
def test_any_fsspec_protocol(xstacktest, ms, local, lazy):
    """convert -> uvstack -> open_store through a protocol xstack has never heard of, with no
    rename: the same data and flux as on the local disk, each store's completion flag its
    very last write, nothing else left under the URL."""
    path, pos = ms
    ref_store, ref, ref_out = local
    base = "xstacktest://bucket/run"
    store = convert_ms(path, f"{base}/in.zarr", chunks={"time": 5})
    assert store == f"{base}/in.zarr"
    _same(open_store(store), open_store(ref_store))
    xstacktest.written.clear()
    if lazy:
        pending = xstack.stack_uv(store, pos, out=f"{base}/out.zarr", compute=False)
        with pytest.raises(SchemaError, match="incomplete store"):
            open_store(f"{base}/out.zarr")
        (res,) = xstack.compute(pending)
    else:
        res = xstack.stack_uv(store, pos, out=f"{base}/out.zarr")
    assert res.flux_jy == ref.flux_jy and res.flux_err_jy == ref.flux_err_jy
    stacked = open_store(f"{base}/out.zarr")
    assert stacked.attrs["xstack_complete"] is True
    _same(stacked, open_store(ref_out))
    # the completion flag: in the last object written, and in no root written before it
    root = "/bucket/run/out.zarr/zarr.json"
    writes = [(p, d) for p, d in xstacktest.written if p.startswith("/bucket/run/out.zarr")]
    assert writes and writes[-1][0] == root and _root_flag(writes[-1][1]) is True
    assert all(_root_flag(d) is not True for p, d in writes[:-1] if p == root)
    assert any("/VISIBILITY/c/" in p for p, _ in writes)
    fs = xstacktest()
    assert sorted(p.rsplit("/", 1)[-1] for p in fs.ls("/bucket/run", detail=False)) == \
        ["in.zarr", "out.zarr"]
    with pytest.raises(NotImplementedError):  # really no rename
        fs.mv("/bucket/run/out.zarr", "/bucket/run/moved.zarr", recursive=True)
