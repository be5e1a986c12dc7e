"""``make_image`` and CLEAN on a dask.distributed cluster (issue 14): each batch of store chunks
is read and gridded by a task on a worker, the partial images summed by a tree of tasks.

One ``LocalCluster`` of 2 worker processes with 1 thread each serves the module; its
scheduler runs in this process, so a scheduler plugin records the keys of the tasks that ran
there (the proof that the gridding ran on the workers). The reference everywhere is the same
call on dask's threaded scheduler (no client), in this process.

Tolerance: the cluster adds the partial images in another order (a tree instead of a running
sum) and ducc0 adds its threads' tiles in the order they finish, so images agree to rounding,
not bitwise. Measured on this data (batches of one chunk, 8 tasks): dirty image and PSF
1.1e-16 to 1.5e-16 of the peak (natural and Briggs); CLEAN model 4e-16 of its peak, residual
2.9e-14 of the dirty image's peak (bitwise equal with one batch). The tests allow 1e-12. The
restoring beam is a least-squares fit to the PSF and moves by 2.5e-10 relative, so restored
images are compared to 1e-6 (as the beam in ``tests/test_cluster.py``).
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
REL = 1e-12


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
    each), two point sources (50 and 30 mJy) and noise."""
    tmp = tmp_path_factory.mktemp("imaging_distributed")
    sources = [(*lm_to_radec(2e-4, -1e-4, *VLA_CENTER), 0.05),
               (*lm_to_radec(-1e-4, 2e-4, *VLA_CENTER), 0.03)]
    ds = make_stack_partition(n_time=16, n_ant=7, n_chan=3, sigma=0.002, seed=21,
                              sources=sources)
    path = tmp / "data.zarr"
    write_store({"spw0_field0": ds.chunk({"time": 2})}, path)
    return path


def _ran(cluster, before: int, prefix: str) -> list[str]:
    """Keys of the tasks since ``before`` whose name starts with ``prefix``."""
    return [k for k in cluster.counter.keys[before:] if k.startswith(prefix)]


def _close(got: np.ndarray, ref: np.ndarray, rel: float = REL, peak: float | None = None) -> None:
    """Equal to ``rel`` of ``peak`` (default: the reference's own peak), NaNs in place."""
    finite = np.isfinite(ref)
    np.testing.assert_array_equal(np.isfinite(got), finite)
    peak = np.abs(ref[finite]).max() if peak is None else peak
    np.testing.assert_allclose(got[finite], ref[finite], rtol=0, atol=rel * peak)


def _same_image(got, ref) -> None:
    _close(got.image, ref.image)
    _close(got.psf, ref.psf)
    assert got.n_visibilities == ref.n_visibilities
    for name in ("sum_weights", "frequency", "bandwidth"):
        assert getattr(got, name) == pytest.approx(getattr(ref, name), rel=REL, abs=0)
    # the beam is a least-squares fit to the PSF: rounding of the PSF moves it within the
    # fit's own tolerance
    np.testing.assert_allclose(got.beam, ref.beam, rtol=1e-6, atol=1e-6)


def test_make_image_natural_grids_on_the_workers(cluster, store):
    """One batch (the store is far below 2^24 visibilities): one gridding task, no sum."""
    ref = xstack.make_image(store, size=64, cell_arcsec=4.0)
    before = len(cluster.counter.keys)
    with use_cluster(cluster.scheduler_address):
        got = xstack.make_image(store, size=64, cell_arcsec=4.0)
    assert len(_ran(cluster, before, f"{GRID}-dirty")) == 1
    _same_image(got, ref)
    assert active_client() is None


def test_make_image_briggs_batches_and_tree_sum(cluster, store, monkeypatch):
    """Batches of one chunk: 8 density tasks and 8 gridding tasks, summed by a tree of
    fan-in 4 (2 + 1 sum tasks per pass)."""
    monkeypatch.setattr(image_mod, "BATCH_VISIBILITIES", 200, raising=False)
    ref = xstack.make_image(store, size=64, cell_arcsec=4.0, weighting="briggs", robust=0.5)
    before = len(cluster.counter.keys)
    with use_cluster(cluster.scheduler_address):
        got = xstack.make_image(store, size=64, cell_arcsec=4.0, weighting="briggs", robust=0.5)
    assert len(_ran(cluster, before, f"{GRID}-density")) == 8
    assert len(_ran(cluster, before, f"{GRID}-dirty")) == 8
    assert len(_ran(cluster, before, f"{SUM}-dirty")) == 3
    # no chunk was read as a task of its own: each gridding task reads its chunks itself
    assert not [k for k in cluster.counter.keys[before:] if "VISIBILITY" in k]
    _same_image(got, ref)


def test_clean_on_the_workers_equals_threaded(cluster, store, monkeypatch):
    """Major cycles predict and grid the model on the workers (one task per batch).

    The residual's rounding is the dirty image's (residual = dirty - image of the model), so
    it is compared on the dirty image's scale. The restored image adds the restoring beam, a
    least-squares fit to the PSF that rounding of the PSF moves within the fit's tolerance
    (2.8e-10 of the peak measured): compared to 1e-6, as the beam is.
    """
    monkeypatch.setattr(image_mod, "BATCH_VISIBILITIES", 200, raising=False)  # a task per chunk: 8 tasks
    kw = dict(size=64, cell_arcsec=4.0, niter=40, threshold=0.0, gain=0.2)
    ref_img, ref = clean_data(store, **kw)
    before = len(cluster.counter.keys)
    with use_cluster(cluster.scheduler_address):
        got_img, got = clean_data(store, **kw)
    assert got.n_major == ref.n_major >= 1
    assert got.n_components == ref.n_components
    model_tasks = _ran(cluster, before, f"{GRID}-model")
    assert len(model_tasks) == 8 * ref.n_major
    # the model image (32 kB) went to the cluster once per major cycle, not inside each task
    assert max(cluster.counter.spec_bytes[k] for k in model_tasks) < ref.model.nbytes / 2
    dirty_peak = np.abs(ref_img.extra["dirty"]).max()
    _close(got_img.extra["dirty"], ref_img.extra["dirty"])
    _close(got.model, ref.model)
    _close(got.residual, ref.residual, peak=dirty_peak)
    np.testing.assert_allclose(got.beam_pixels, ref.beam_pixels, rtol=1e-6, atol=1e-6)
    _close(got.restored, ref.restored, rel=1e-6)
    _close(got_img.image, ref_img.image, rel=1e-6)


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
    assert len(bars) == 1
    bar = bars[0]
    # 8 gridding tasks and 3 sum tasks, every one counted
    assert bar.total == 11 and bar.n == bar.total and bar.closed


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
    assert got["n_components"] == ref["n_components"]
    assert got["n_visibilities"] == ref["n_visibilities"]
    assert got["sum_weights"] == pytest.approx(ref["sum_weights"], rel=REL)
    for kind in ("", ".psf", ".residual", ".model", ".pb"):
        a = fits.getdata(tmp_path / f"got{kind}.fits").astype(np.float64)
        b = fits.getdata(tmp_path / f"ref{kind}.fits").astype(np.float64)
        if kind == "":
            # the restored image: its restoring beam is a least-squares fit to the PSF
            _close(a, b, rel=1e-6)
        elif kind == ".residual":
            # float32 files: one unit in the last place of the restored image's peak
            _close(a, b, rel=2.0**-23, peak=float(ref["peak_jy_per_beam"]))
        else:
            _close(a, b, rel=2.0**-23)
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
    _close(got_mosaic.primary_beam, ref_mosaic.primary_beam)


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
