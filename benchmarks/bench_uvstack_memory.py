"""Peak memory of uv-stacking per VISIBILITY chunk (issue 14: memory bounded by the chunk).

A paper type-1 data set at full size (2.4e7 visibilities, 0.2 GB, 30 MB VISIBILITY chunks) is
simulated once; then, each in a fresh child process: ``stack_uv`` of 900 positions, the flux
alone or with the stacked store written (``out=``), on dask's threaded scheduler (2 threads)
or the synchronous one, with glibc's default heap or the bounded one
(:func:`xstack._memory.bound_heap`, what the command line uses). Every child first stacks a
few integrations (numba kernels loaded, imports done), then measures its resident memory
every 5 ms during the stack. Printed: peak above that start (MB) and as a multiple of the
chunk, wall and CPU time.

Usage::

    python benchmarks/bench_uvstack_memory.py [--workdir DIR] [--time-chunks 576,144]
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
from pathlib import Path

_CHILD = r"""
import json, os, sys, threading, time
import numpy as np
store, mode, scheduler, heap, ct = sys.argv[1:6]
import dask
import xstack
from astropy.table import Table
from xstack._memory import bound_heap
from xstack.schema import open_store
if heap == "bounded":
    assert bound_heap()
page = os.sysconf("SC_PAGE_SIZE")
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * page / 2**20
tree = open_store(store, chunks={"time": int(ct)} if int(ct) > 0 else None)
name = next(n for n in tree.children if "VISIBILITY" in tree[n].ds)
vis = tree[name].ds["VISIBILITY"].data
chunk_mb = vis.nbytes / vis.npartitions / 2**20
rng = np.random.default_rng(1)
ra0, dec0 = np.degrees(tree[name].ds.attrs["phase_center"])
cat = Table({"ra": ra0 + rng.uniform(-0.05, 0.05, 900), "dec": dec0 + rng.uniform(-0.05, 0.05, 900)})
xstack.stack_uv({name: tree[name].ds.isel(time=slice(0, 8))}, cat)  # warm-up
peak, stop = [0.0], [False]
def sample():
    while not stop[0]:
        peak[0] = max(peak[0], rss())
        time.sleep(0.005)
base = rss()
th = threading.Thread(target=sample, daemon=True)
th.start()
t0, c0 = time.perf_counter(), time.process_time()
out = None
if mode == "write":
    out = os.path.join(os.path.dirname(store), f"stacked-{os.getpid()}.zarr")
with dask.config.set(scheduler=scheduler, num_workers=2):
    res = xstack.stack_uv(tree, cat, out=out)
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
stop[0] = True
th.join()
print(json.dumps({"chunk_mb": chunk_mb, "n_chunks": vis.npartitions, "base_mb": base,
                  "peak_mb": peak[0], "wall": wall, "cpu": cpu, "flux": res.flux_jy}))
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--workdir", default=None, help="where the store goes (default: a temp dir)")
    parser.add_argument("--time-chunks", default="0,144",
                        help="integrations per chunk on opening (0: the store's own, 576)")
    args = parser.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="xstack-uvmem-"))
    work.mkdir(parents=True, exist_ok=True)
    store = work / "type1.zarr"
    if not store.exists():
        print("simulating paper-1 at full size ...", file=sys.stderr, flush=True)
        subprocess.run([sys.executable, "-c", "import sys, xstack; xstack.simulate("
                        "xstack.preset_scene('paper-1', scale=1.0), sys.argv[1], seed=3)", str(store)],
                       check=True)
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"load average before {' / '.join(f'{x:.1f}' for x in os.getloadavg())}\n")
    print("| chunk (MB) | chunks | pass | scheduler | heap | peak above start (MB) | × chunk | "
          "wall / CPU (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for ct in [int(x) for x in args.time_chunks.split(",")]:
        for mode in ("flux", "write"):
            for scheduler in ("threads", "sync"):
                for heap in ("default", "bounded"):
                    res = subprocess.run([sys.executable, "-c", _CHILD, str(store), mode, scheduler,
                                          heap, str(ct)], capture_output=True, text=True)
                    if res.returncode:
                        raise RuntimeError(res.stderr)
                    r = json.loads(res.stdout.strip().splitlines()[-1])
                    for p in work.glob("stacked-*.zarr"):
                        shutil.rmtree(p)
                    above = r["peak_mb"] - r["base_mb"]
                    print(f"| {r['chunk_mb']:.1f} | {r['n_chunks']} | {mode} | {scheduler} | {heap} | "
                          f"{above:.0f} | {above / r['chunk_mb']:.1f} | {r['wall']:.1f} / {r['cpu']:.1f} |",
                          flush=True)
    print(f"\nload average after {' / '.join(f'{x:.1f}' for x in os.getloadavg())}")
    if args.workdir is None:
        shutil.rmtree(work)


if __name__ == "__main__":
    main()
