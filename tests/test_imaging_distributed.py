"""``make_image`` and CLEAN on a dask.distributed cluster (issue 14): each batch of store chunks
is read and gridded by a task on a worker, the partial images summed by a chain of tasks.

One ``LocalCluster`` of 2 worker processes with 1 thread each serves the module; its
scheduler runs in this process, so a scheduler plugin records the keys of the tasks that ran
there (the proof that the gridding ran on the workers). The reference everywhere is the same
call on dask's threaded scheduler (no client), in this process.

Tolerance: none. The cluster cuts the chunks into the local path's batches, grids each with
one thread (reproducible gridding, the default) and adds the partial images in the local
path's order (a chain, not a tree), so every image, weight sum, CLEAN model, restoring beam
and file is the local one to the bit (issue 12; before, a tree of sums and batches counted
after flagging made images 1e-16 of the peak apart and CLEAN residuals 3e-14). The data
below are cut into several batches, some of them wholly flagged, so that both the order of
the sums and the skipping of empty batches are exercised.
"""

from __future__ import annotations

import json

import cloudpickle
import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.io import fits

import xstack
from xstack._cluster import active_client, use_cluster
from xstack.cli import main
from xstack.coords import lm_to_radec
from xstack.imaging import image as image_mod
from xstack.imaging.clean import clean_data
from xstack.schema import write_store

distributed = pytest.importorskip("distributed")
from _cluster_helpers import TaskCounter, local_cluster  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore::xstack.errors.XstackWarning")

#: key prefix of the gridding tasks (xstack.imaging.image.GRID_TASK), spelled out so the
#: test also runs (and fails) against code that has no such constant
GRID = "xstack-image-grid"
SUM = "xstack-image-sum"
COUNT = "xstack-image-count"


class GridCounter(TaskCounter):
    """The scheduler's tasks, and the pickled size of each gridding task's spec."""

    def __init__(self) -> None:
        super().__init__()
        self.spec_bytes: dict[str, int] = {}

    def on_finished(self, key) -> None:
        if str(key).startswith(GRID):
            self.spec_bytes[str(key)] = len(cloudpickle.dumps(self.scheduler.tasks[key].run_spec))


@pytest.fixture(scope="module")
def cluster():
    with local_cluster(GridCounter()) as cluster:
        yield cluster


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """8 chunks of 2 integrations x 21 baselines x 3 channels x 2 hands (252 visibilities
    each), two point sources (50 and 30 mJy) and noise; the third and the last chunk wholly
    flagged, the fifth with 192 of its 252 visibilities left."""
    tmp = tmp_path_factory.mktemp("imaging_distributed")
    sources = [(*lm_to_radec(2e-4, -1e-4, *VLA_CENTER), 0.05),
               (*lm_to_radec(-1e-4, 2e-4, *VLA_CENTER), 0.03)]
    ds = make_stack_partition(n_time=16, n_ant=7, n_chan=3, sigma=0.002, seed=21,
                              sources=sources)
    flag = ds["FLAG"].values.copy()
    flag[4:6] = True
    flag[14:16] = True
    flag[8, :10] = True
    ds["FLAG"] = (ds["FLAG"].dims, flag)
    path = tmp / "data.zarr"
    write_store({"spw0_field0": ds.chunk({"time": 2})}, path)
    return path


def _ran(cluster, before: int, prefix: str) -> list[str]:
    """Keys of the tasks since ``before`` whose name starts with ``prefix``."""
    return [k for k in cluster.counter.keys[before:] if k.startswith(prefix)]


def _same(got: np.ndarray, ref: np.ndarray) -> None:
    """The same bits (NaNs in the same places)."""
    got, ref = np.asarray(got), np.asarray(ref)
    assert got.dtype == ref.dtype and got.shape == ref.shape
    np.testing.assert_array_equal(np.ascontiguousarray(got).view(np.uint8),
                                  np.ascontiguousarray(ref).view(np.uint8))


def _same_image(got, ref) -> None:
    _same(got.image, ref.image)
    _same(got.psf, ref.psf)
    _same(got.primary_beam, ref.primary_beam)
    assert got.n_visibilities == ref.n_visibilities
    for name in ("sum_weights", "frequency", "bandwidth"):
        assert getattr(got, name) == getattr(ref, name)
    assert tuple(got.beam) == tuple(ref.beam)


def test_make_image_natural_grids_on_the_workers(cluster, store):
    """One batch (the store is far below 2^24 visibilities): one gridding task, no sum."""
    ref = xstack.make_image(store, size=64, cell_arcsec=4.0)
    before = len(cluster.counter.keys)
    with use_cluster(cluster.scheduler_address):
        got = xstack.make_image(store, size=64, cell_arcsec=4.0)
    assert len(_ran(cluster, before, f"{GRID}-dirty")) == 1
    _same_image(got, ref)
    assert active_client() is None


@pytest.mark.parametrize("batch, tasks, links", [(200, 6, 2), (600, 3, 1)])
def test_make_image_briggs_batches_and_chain_sum(cluster, store, monkeypatch, batch, tasks,
                                                 links):
    """Batches close at 200 unflagged visibilities: chunks [0], [1], [2, 3] (2 is flagged),
    [4, 5] (4 has 192), [6] and [7] (flagged: nothing to grid): 6 density and 6 gridding tasks
    summed by a chain of 2 links (batches 0-3, then the running sum and 4-5); at 600: [0-3],
    [4-6], [7], one link. A planning task per chunk counts its visibilities first."""
    monkeypatch.setattr(image_mod, "BATCH_VISIBILITIES", batch, raising=False)
    ref = xstack.make_image(store, size=64, cell_arcsec=4.0, weighting="briggs", robust=0.5)
    before = len(cluster.counter.keys)
    with use_cluster(cluster.scheduler_address):
        got = xstack.make_image(store, size=64, cell_arcsec=4.0, weighting="briggs", robust=0.5)
    assert len(_ran(cluster, before, f"{GRID}-density")) == tasks
    assert len(_ran(cluster, before, f"{GRID}-dirty")) == tasks
    assert len(_ran(cluster, before, f"{SUM}-dirty")) == links
    assert len(_ran(cluster, before, COUNT)) == 8
    # no chunk was read as a task of its own: each gridding task reads its chunks itself
    assert not [k for k in cluster.counter.keys[before:] if "VISIBILITY" in k]
    _same_image(got, ref)


def test_clean_on_the_workers_equals_threaded(cluster, store, monkeypatch):
    """Major cycles predict and grid the model on the workers (one task per batch): the same
    components, model, residual and restored image as in this process, to the bit."""
    monkeypatch.setattr(image_mod, "BATCH_VISIBILITIES", 200, raising=False)  # a task per chunk: 8 tasks
    kw = dict(size=64, cell_arcsec=4.0, niter=40, threshold=0.0, gain=0.2)
    ref_img, ref = clean_data(store, **kw)
    before = len(cluster.counter.keys)
    with use_cluster(cluster.scheduler_address):
        got_img, got = clean_data(store, **kw)
    assert got.n_major == ref.n_major >= 1
    assert got.n_components == ref.n_components
    model_tasks = _ran(cluster, before, f"{GRID}-model")
    assert len(model_tasks) == 6 * ref.n_major  # batches of test_make_image_briggs_...
    # the model image (32 kB) went to the cluster once per major cycle, not inside each task
    assert max(cluster.counter.spec_bytes[k] for k in model_tasks) < ref.model.nbytes / 2
    _same(got_img.extra["dirty"], ref_img.extra["dirty"])
    _same(got.model, ref.model)
    _same(got.residual, ref.residual)
    assert tuple(got.beam_pixels) == tuple(ref.beam_pixels)
    _same(got.restored, ref.restored)
    _same(got_img.image, ref_img.image)


def test_progress_bar_follows_the_gridding_tasks(cluster, store, monkeypatch):
    from xstack import _progress

    bars = []

    class Recorder:
        def __init__(self, iterable=None, total=None, **kwargs):
            self.total, self.n, self.closed = total, 0, False
            self.iterable = iterable
            bars.append(self)

        def __iter__(self):
            for x in self.iterable:
                self.n += 1
                yield x

        def update(self, n=1):
            self.n += n

        def close(self):
            self.closed = True

    monkeypatch.setattr(_progress, "tqdm", Recorder)
    monkeypatch.setattr(image_mod, "BATCH_VISIBILITIES", 200, raising=False)
    previous = _progress.set_allowed(True)
    try:
        with use_cluster(cluster.scheduler_address):
            xstack.make_image(store, size=64, cell_arcsec=4.0, progress=True)
    finally:
        _progress.set_allowed(previous)
    assert len(bars) == 2
    planning, imaging = bars
    # a planning task per chunk; then 6 gridding tasks and 2 sum tasks, every one counted
    assert planning.total == 8 and planning.n == planning.total and planning.closed
    assert imaging.total == 8 and imaging.n == imaging.total and imaging.closed


def test_cli_image_scheduler_same_fits(cluster, store, tmp_path, capsys):
    argv = ["image", str(store), str(tmp_path / "{}.fits"), "--size", "64", "--cell",
            "4arcsec", "--niter", "30", "--weighting", "briggs", "--json", "--no-progress"]
    assert main([a.format("ref") for a in argv]) == 0
    ref = json.loads(capsys.readouterr().out)
    before = len(cluster.counter.keys)
    assert main([a.format("got") for a in argv] + ["--scheduler", cluster.scheduler_address]) == 0
    got = json.loads(capsys.readouterr().out)
    for kind in ("dirty", "model", "density"):
        assert _ran(cluster, before, f"{GRID}-{kind}"), kind
    for key in ("n_components", "n_visibilities", "sum_weights", "peak_jy_per_beam"):
        assert got[key] == ref[key], key
    for kind in ("", ".psf", ".residual", ".model", ".pb"):
        _same(fits.getdata(tmp_path / f"got{kind}.fits"), fits.getdata(tmp_path / f"ref{kind}.fits"))
    assert active_client() is None


def test_in_memory_partition_and_mosaic_on_the_workers(cluster):
    """numpy-backed partitions (no store: the slices travel with the tasks) and a linear
    mosaic of two pointings (one cluster pass per pointing)."""
    centers = [VLA_CENTER, lm_to_radec(6e-4, 0.0, *VLA_CENTER)]
    src = (*lm_to_radec(3e-4, 1e-4, *VLA_CENTER), 0.04)
    parts = {f"spw0_field{i}": make_stack_partition(n_time=8, n_ant=6, n_chan=2, sigma=0.002,
                                                    seed=5 + i, sources=[src], phase_center=c,
                                                    field_id=i)
             for i, c in enumerate(centers)}
    one = parts["spw0_field0"]
    kw = dict(size=64, cell_arcsec=4.0)
    ref_one = xstack.make_image(one, **kw)
    ref_mosaic = xstack.make_image(parts, **kw)
    before = len(cluster.counter.keys)
    with use_cluster(cluster.scheduler_address):
        got_one = xstack.make_image(one, **kw)
        got_mosaic = xstack.make_image(parts, **kw)
    assert len(_ran(cluster, before, f"{GRID}-dirty")) == 1 + 2
    _same_image(got_one, ref_one)
    _same_image(got_mosaic, ref_mosaic)


def test_reads_follow_any_chunking(store):
    """Each column's slice is read from just the blocks covering it, whatever its chunking
    (UVW, FLAG and VISIBILITY chunked differently from the slices; frequency chunked too);
    from a store, a task's graph is its chunk's read and the store's handle."""
    from xstack.schema import open_store

    part = open_store(store)["spw0_field0"].to_dataset()
    columns = image_mod._Columns()
    for ts, bs in image_mod._blocks(part):
        r = columns.read(part, "VISIBILITY", ts, bs)
        np.testing.assert_array_equal(r.read(), part["VISIBILITY"].values[ts, bs])
        assert len(r.graph) == 2, list(r.graph)
    ds = make_stack_partition(n_time=12, n_ant=5, n_chan=4, sigma=0.01, seed=3)
    ds = ds.chunk({"time": 4, "baseline_id": 6})
    ds["UVW"] = ds["UVW"].chunk({"time": 3, "baseline_id": 4})
    ds["FLAG"] = ds["FLAG"].chunk({"time": 5, "frequency": 3})
    columns = image_mod._Columns()
    n_vis_blocks = 3 * 2
    blocks = image_mod._blocks(ds)
    assert len(blocks) == n_vis_blocks
    for ts, bs in blocks:
        for name in ("UVW", "WEIGHT", "FLAG", "VISIBILITY"):
            r = columns.read(ds, name, ts, bs)
            np.testing.assert_array_equal(r.read(), ds[name].values[ts, bs])


def test_batch_count_is_what_the_gridder_gets():
    """A chunk's count (what batches are cut by) is the visibilities ``rows_of_block`` hands
    the gridder, with flags, NaN and negative weights, NaN uvw and zero weights mixed in."""
    rng = np.random.default_rng(4)
    nt, nb, nf, npol = 6, 10, 4, 4
    uvw = rng.normal(size=(nt, nb, 3)) * 100
    uvw[1, 2, 0] = np.nan
    weight = rng.uniform(0, 2, (nt, nb, nf, npol))
    weight[0, :3] = 0.0
    weight[2, 4, :2, 0] = np.nan
    weight[3, 5, 1:, 3] = -1.0
    flag = rng.uniform(size=weight.shape) < 0.6
    flag[4] = True
    for pols in ([0, 3], [0], [1, 2]):
        _, w, _ = image_mod.rows_of_block(uvw, weight, flag, pols)
        assert image_mod.count_rows_of_block(uvw, weight, flag, pols) == w.size > 0
    assert image_mod.count_rows_of_block(uvw, weight, np.ones_like(flag), [0, 3]) == 0


def test_local_batches_are_the_cluster_ones(store, monkeypatch):
    """Without a cluster the same batches (test_make_image_briggs_batches_and_chain_sum):
    at 200 visibilities 5 with something to grid, a dirty image and a PSF each."""
    monkeypatch.setattr(image_mod, "BATCH_VISIBILITIES", 200, raising=False)
    calls = []
    real = image_mod.grid_visibilities
    monkeypatch.setattr(image_mod, "grid_visibilities",
                        lambda uvw, *a, **k: calls.append(uvw.shape[0]) or real(uvw, *a, **k))
    xstack.make_image(store, size=64, cell_arcsec=4.0)
    # rows (baselines x hands) per batch: chunks [0], [1], [2, 3], [4, 5], [6]; [7] is empty
    assert calls == [84, 84, 84, 84, 84, 84, 64 + 84, 64 + 84, 84, 84]
