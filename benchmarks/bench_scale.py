"""uv-stacking at survey scale: time and peak memory against data size (issue 14).

Stores of 1, 4 and 16 GB of VISIBILITY (VLA C configuration, 27 antennas, 256 channels, two
polarizations, complex64, the same chunking: ``--chunk-mb`` per VISIBILITY chunk) are simulated
-- thermal noise plus ``SOURCES`` point sources of 1 mJy, nothing else (the simulator computes
only the effects a scene asks for) -- and each is uv-stacked at ``--positions`` positions (the
sources first, then random ones: the expected stacked flux is sources / positions x 1 mJy)
twice, each time in a fresh child process:

* ``threads``: dask's threaded scheduler, 2 threads, the command line's bounded heap;
* ``cluster``: a ``distributed.LocalCluster`` of 2 worker processes x 1 thread, configured as
  ``--workers`` starts it (``xstack._cluster.LOCAL_CLUSTER_CONFIG``: worker-saturation 1.0,
  the bounded heap in the workers).

Printed per run: wall time, throughput, peak resident memory (threads: the process; cluster:
the largest worker, sampled every 10 ms from outside) above the process's start and as a
multiple of the chunk, the stacked flux (expected: sources / positions x 1 mJy plus the
sources' sidelobes at one another's positions, which short tracks leave at the per-cent level)
and the cluster's flux against the threaded one. Then a chunk-size sweep on the 1 GB data (stores
re-simulated with other chunk sizes): time and memory per chunk size.

Usage::

    python benchmarks/bench_scale.py [--sizes 1,4,16] [--sweep 8,32,128,512] [--chunk-mb 128]
                                     [--positions 100] [--workdir DIR] [--keep]

Disk: the largest store plus the next (each store is deleted after its runs unless ``--keep``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: antennas of the VLA C configuration and baselines between them
N_ANT, N_CHAN, N_POL, INTEGRATION_S = 27, 256, 2, 10.0
N_BL = N_ANT * (N_ANT - 1) // 2
VIS_BYTES = 8  # complex64
#: point sources of 1 mJy simulated in every store (stacked first)
SOURCES, SOURCE_JY = 10, 1e-3
NOISE_SIGMA_JY = 0.05  # per real and imaginary part of one visibility

#: the child that stacks, with its memory sampled every 10 ms
_CHILD = r"""
import json, os, sys, threading, time
mode, store, cat_path, nthreads = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
import numpy as np
import dask
import xstack
from astropy.table import Table
from xstack._memory import bound_heap
from xstack.schema import open_store

page = os.sysconf("SC_PAGE_SIZE")
def rss(pid):
    try:
        with open(f"/proc/{pid}/statm") as f:
            return int(f.read().split()[1]) * page / 2**20
    except OSError:
        return 0.0

cat = Table.read(cat_path)
tree = open_store(store)
name = next(n for n in tree.children if "VISIBILITY" in tree[n].ds)
vis = tree[name].ds["VISIBILITY"].data
chunk_mb = vis.nbytes / vis.npartitions / 2**20
client = cluster = None
if mode == "cluster":
    from distributed import Client, LocalCluster
    from xstack._cluster import LOCAL_CLUSTER_CONFIG
    with dask.config.set(LOCAL_CLUSTER_CONFIG):  # what `--workers N` starts
        cluster = LocalCluster(n_workers=nthreads, threads_per_worker=1, processes=True,
                               dashboard_address=None)
    client = Client(cluster)
    pids = list(client.run(os.getpid).values())
else:
    assert bound_heap()
    pids = [os.getpid()]
    dask.config.set(scheduler="threads", num_workers=nthreads)
# warm-up: kernels compiled and loaded, imports done (in every worker for the cluster)
small = {name: tree[name].ds.isel(time=slice(0, 4))}
for _ in range(2 if client else 1):
    xstack.stack_uv(small, cat[:2], weighting="none", primary_beam="none")
base = {p: rss(p) for p in pids}
peak = dict(base)
stop = [False]
def sample():
    while not stop[0]:
        for p in pids:
            peak[p] = max(peak[p], rss(p))
        time.sleep(0.01)
th = threading.Thread(target=sample, daemon=True)
th.start()
t0 = time.perf_counter()
res = xstack.stack_uv(tree, cat, weighting="none", primary_beam="none")
wall = time.perf_counter() - t0
stop[0] = True
th.join()
worst = max(pids, key=lambda p: peak[p] - base[p])
print(json.dumps({"chunk_mb": chunk_mb, "n_chunks": vis.npartitions, "vis_gb": vis.nbytes / 1e9,
                  "wall": wall, "peak_mb": peak[worst], "above_mb": peak[worst] - base[worst],
                  "flux": res.flux_jy, "error": res.flux_err_jy}))
if client is not None:
    client.close()
    cluster.close()
"""


def scene(vis_gb: float, chunk_mb: float) -> dict:
    """A noise + point-source scene with ``vis_gb`` GB of VISIBILITY in ``chunk_mb`` MB chunks."""
    per_time = N_BL * N_CHAN * N_POL * VIS_BYTES
    n_time = max(1, round(vis_gb * 1e9 / per_time))
    time_chunk = max(1, round(chunk_mb * 2**20 / per_time))
    return {
        "name": f"scale-{vis_gb:g}gb",
        "visibility_dtype": "complex64",
        "time_chunk": time_chunk,
        "array": {"config": "vla.c"},
        "observation": {"date": "2014-01-01", "hour_angle": [-6.0, 6.0],
                        "integration": INTEGRATION_S,
                        "time_per_pointing": n_time * INTEGRATION_S},
        "spectral": {"center": 1.4e9, "bandwidth": 128e6, "channels": N_CHAN,
                     "polarizations": ["RR", "LL"]},
        "pointings": {"mode": "single", "center": [150.0, 2.2]},
        "effects": {"primary_beam": "none", "w_term": True,
                    "noise": {"sigma": NOISE_SIGMA_JY}},
        "populations": [{"name": "targets", "count": SOURCES,
                         "flux": {"kind": "fixed", "value": SOURCE_JY},
                         "positions": {"kind": "box", "size_arcsec": [600.0, 600.0]},
                         "shape": {"kind": "point"}}],
    }


def simulate(vis_gb: float, chunk_mb: float, work: Path) -> tuple[Path, float]:
    """Simulate the store in a child process; its path and the simulation's wall time."""
    store = work / f"scale-{vis_gb:g}gb-{chunk_mb:g}mb.zarr"
    spec = work / f"{store.stem}.json"
    spec.write_text(json.dumps(scene(vis_gb, chunk_mb)))
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c",
                    "import json, sys, xstack; xstack.simulate(json.load(open(sys.argv[1])), "
                    "sys.argv[2], seed=5, overwrite=True)", str(spec), str(store)], check=True)
    return store, time.perf_counter() - t0


def catalog(store: Path, positions: int, work: Path) -> Path:
    """The true sources first, then random positions in the same box (ECSV)."""
    import numpy as np
    from astropy.table import Table, vstack

    true = Table.read(str(store)[:-5] + ".targets.ecsv")[["ra", "dec"]]
    rng = np.random.default_rng(7)
    n = max(0, positions - len(true))
    half = 300.0 / 3600.0
    extra = Table({"ra": 150.0 + rng.uniform(-half, half, n) / np.cos(np.radians(2.2)),
                   "dec": 2.2 + rng.uniform(-half, half, n)})
    true["ra"].unit = true["dec"].unit = None
    path = work / "positions.ecsv"
    vstack([true, extra]).write(path, overwrite=True)
    return path


def stack(mode: str, store: Path, cat: Path, nthreads: int) -> dict:
    res = subprocess.run([sys.executable, "-c", _CHILD, mode, str(store), str(cat), str(nthreads)],
                         capture_output=True, text=True)
    if res.returncode:
        raise RuntimeError(res.stderr[-3000:])
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="1,4,16", help="VISIBILITY sizes in GB")
    parser.add_argument("--sweep", default="8,32,128,512",
                        help="chunk sizes (MB) of the sweep on the smallest size ('' for none)")
    parser.add_argument("--chunk-mb", type=float, default=128.0, help="VISIBILITY chunk (MB)")
    parser.add_argument("--positions", type=int, default=100)
    parser.add_argument("--threads", type=int, default=2, help="threads / worker processes")
    parser.add_argument("--workdir", default=None, help="where the stores go (default: a temp dir)")
    parser.add_argument("--keep", action="store_true", help="keep the stores")
    parser.add_argument("--schedulers", default="threads,cluster",
                        help="which of threads, cluster to run per size")
    args = parser.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="xstack-scale-"))
    work.mkdir(parents=True, exist_ok=True)
    sizes = [float(x) for x in args.sizes.split(",")]
    expected = min(SOURCES, args.positions) * SOURCE_JY / args.positions
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"load average before {' / '.join(f'{x:.1f}' for x in os.getloadavg())}")
    print(f"{args.positions} positions ({SOURCES} of them 1 mJy sources: expected "
          f"{expected * 1e3:.3f} mJy), {args.threads} threads / worker processes\n")

    def header() -> None:
        print("| VISIBILITY (GB) | chunk (MB) | chunks | simulate (s) | scheduler | stack (s) | GB/s | "
              "peak RSS (MB) | above start (MB) | × chunk | flux (mJy) | "
              "cluster − threads (rel.) |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")

    header()

    def row(size: float, chunk_mb: float, modes: tuple[str, ...]) -> None:
        store, sim_s = simulate(size, chunk_mb, work)
        cat = catalog(store, args.positions, work)
        flux = {}
        for mode in modes:
            r = stack(mode, store, cat, args.threads)
            flux[mode] = r["flux"]
            rel = "" if mode == "threads" or "threads" not in flux else \
                f"{abs(r['flux'] - flux['threads']) / abs(flux['threads']):.1e}"
            print(f"| {r['vis_gb']:.2f} | {r['chunk_mb']:.0f} | {r['n_chunks']} | {sim_s:.0f} | {mode} | "
                  f"{r['wall']:.1f} | {r['vis_gb'] / r['wall']:.2f} | {r['peak_mb']:.0f} | "
                  f"{r['above_mb']:.0f} | {r['above_mb'] / r['chunk_mb']:.1f} | "
                  f"{r['flux'] * 1e3:.4f} ± {r['error'] * 1e3:.4f} | {rel} |", flush=True)
        if not args.keep:
            shutil.rmtree(store)
            for extra in work.glob(f"{store.stem}.*"):  # its catalogs and scene
                extra.unlink()

    for size in sizes:
        row(size, args.chunk_mb, tuple(args.schedulers.split(",")))
    if args.sweep:
        print("\nchunk-size sweep:\n")
        header()
        for chunk_mb in [float(x) for x in args.sweep.split(",")]:
            row(min(sizes), chunk_mb, ("threads",))
    print(f"\nload average after {' / '.join(f'{x:.1f}' for x in os.getloadavg())}")
    if args.workdir is None and not args.keep:
        shutil.rmtree(work)


if __name__ == "__main__":
    main()
