"""Benchmark of ``xstack convert`` (MS -> zarr) against a plain python-casacore read.

For generated MSs of a few sizes (27 antennas, 64 channels, 4 correlations, WEIGHT_SPECTRUM)
this measures, each in a fresh child process so peak memory is that run's alone:

* the floor: a plain python-casacore ``getcol`` of the same columns (DATA, FLAG,
  WEIGHT_SPECTRUM, UVW, TIME, ANTENNA1/2, FLAG_ROW, TIME_CENTROID, EXPOSURE) in row blocks
  of ~32 MB, data discarded;
* ``xstack.convert_ms`` of the same MS with default chunks (~128 MB);
* the output floor: writing as many bytes as the store holds with ``numpy.tofile`` in
  128 MB files (convert cannot beat read + write);
* optionally ``xstack.export_ms`` of the store back to an MS (``--export``);
* optionally xradio's converter (``--xradio``: ``convert_msv2_to_processing_set`` of xradio
  1.3.0, the test extra, with its defaults) of the same MS in the same run, and the ratios
  xstack / xradio of wall time, CPU time and peak memory, both within the call (imports
  before the clock) and for the whole process (imports included: what a user waits for).

Wall time, CPU time (user + system, all threads), throughput (MB of MS per second of wall
time, visibilities per second) and peak resident memory (``ru_maxrss`` of the child) are
printed as a Markdown table. Library imports happen before the clock starts in every child.

Usage::

    python benchmarks/bench_convert.py --sizes 0.1,1,4 --workdir /tmp/xstack-bench
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

N_ANT = 27
N_CHAN = 64
POLS = ("XX", "XY", "YX", "YY")
ROW_BYTES = N_CHAN * len(POLS) * (8 + 4 + 1) + 3 * 8 + 40  # DATA + WEIGHT_SPECTRUM + FLAG + UVW + scalars

_GENERATE = """
import json, sys
from xstack.testing import make_test_ms
make_test_ms(sys.argv[1], n_antennas={n_ant}, n_times=int(sys.argv[2]), n_channels={n_chan},
             pols={pols!r}, weight_spectrum=True, flag_fraction=0.05, seed=1)
"""

_PLAIN = """
import json, resource, sys, time
import casacore.tables as pt
cols = ["DATA", "FLAG", "WEIGHT_SPECTRUM", "UVW", "TIME", "ANTENNA1", "ANTENNA2", "FLAG_ROW",
        "TIME_CENTROID", "EXPOSURE"]
t0, c0 = time.perf_counter(), time.process_time()
t = pt.table(sys.argv[1], ack=False)
n = t.nrows()
block = max(1, 32 * 1024**2 // {row_bytes})
for r in range(0, n, block):
    for c in cols:
        t.getcol(c, startrow=r, nrow=min(block, n - r))
t.close()
print(json.dumps({{"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "rows": n}}))
"""

_WRITE = """
import json, os, resource, sys, time
import numpy as np
nbytes, out = int(sys.argv[1]), sys.argv[2]
piece = np.random.default_rng(0).integers(0, 255, size=128 * 1024**2, dtype=np.uint8)
t0, c0 = time.perf_counter(), time.process_time()
os.makedirs(out, exist_ok=True)
for k in range(0, nbytes, piece.size):
    piece[:min(piece.size, nbytes - k)].tofile(os.path.join(out, f"{k}.bin"))
print(json.dumps({"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""

_CONVERT = """
import json, resource, sys, time
import dask.array, xarray, zarr, casacore.tables  # imports before the clock starts
from xstack.io.convert import convert_ms
t0, c0 = time.perf_counter(), time.process_time()
convert_ms(sys.argv[1], sys.argv[2], overwrite=True)
print(json.dumps({"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""

_CONVERT_PROCESS = """
import time
t_start = time.perf_counter()
import json, resource, sys
from xstack.io.convert import convert_ms
t0, c0 = time.perf_counter(), time.process_time()
convert_ms(sys.argv[1], sys.argv[2], overwrite=True)
print(json.dumps({"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0,
                  "process_wall": time.perf_counter() - t_start,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""

_XRADIO = """
import time
t_start = time.perf_counter()
import json, resource, sys, warnings
warnings.simplefilter("ignore")
from xradio.measurement_set import convert_msv2_to_processing_set
t0, c0 = time.perf_counter(), time.process_time()
convert_msv2_to_processing_set(sys.argv[1], sys.argv[2], persistence_mode="w")
print(json.dumps({"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0,
                  "process_wall": time.perf_counter() - t_start,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""

_EXPORT = """
import json, resource, sys, time
import dask.array, xarray, zarr, casacore.tables
from xstack.io.export import export_ms
t0, c0 = time.perf_counter(), time.process_time()
export_ms(sys.argv[1], sys.argv[2], overwrite=True)
print(json.dumps({"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def _run(code: str, *args: str) -> dict:
    res = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(res.stderr)
    lines = [line for line in res.stdout.splitlines() if line.startswith("{")]
    return json.loads(lines[-1]) if lines else {}


def _load(avg: tuple[float, float, float]) -> str:
    return " / ".join(f"{x:.1f}" for x in avg)


def _du(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="0.1,1,4", help="MS sizes in GB (comma separated)")
    parser.add_argument("--workdir", default=None, help="where the MSs and stores go (default: a temp dir)")
    parser.add_argument("--repeat", type=int, default=1, help="runs per measurement (the fastest is kept)")
    parser.add_argument("--export", action="store_true", help="also time export_ms back to an MS")
    parser.add_argument("--keep", action="store_true", help="keep the generated MSs and stores")
    parser.add_argument("--xradio", action="store_true",
                        help="also run xradio's converter on the same MSs (xradio[casacore])")
    args = parser.parse_args()

    work = Path(args.workdir or tempfile.mkdtemp(prefix="xstack-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    n_bl = N_ANT * (N_ANT - 1) // 2
    results = []
    load_before = os.getloadavg()
    for size in (float(s) for s in args.sizes.split(",")):
        n_times = max(1, int(round(size * 1e9 / (n_bl * ROW_BYTES))))
        ms = work / f"bench_{size:g}GB.ms"
        if not ms.exists():
            print(f"generating {ms} ({n_times} integrations) ...", file=sys.stderr, flush=True)
            _run(_GENERATE.format(n_ant=N_ANT, n_chan=N_CHAN, pols=POLS), str(ms), str(n_times))
        ms_bytes = _du(ms)
        store = work / f"bench_{size:g}GB.zarr"
        best: dict[str, dict] = {}
        for _ in range(args.repeat):
            # the previous run's store goes first: deleting ~1 GB of files is not converting
            shutil.rmtree(store, ignore_errors=True)
            runs = {"plain": _run(_PLAIN.format(row_bytes=ROW_BYTES), str(ms)),
                    "convert": _run(_CONVERT, str(ms), str(store))}
            # the cost of writing the store's bytes with numpy.tofile: the output floor
            raw = work / "raw-write"
            runs["write"] = _run(_WRITE, str(_du(store)), str(raw))
            shutil.rmtree(raw, ignore_errors=True)
            if args.export:
                runs["export"] = _run(_EXPORT, str(store), str(work / f"bench_{size:g}GB.out.ms"))
            if args.xradio:
                # the two converters alternate in the same run, each a fresh process
                xr_store = work / f"bench_{size:g}GB.ps.zarr"
                shutil.rmtree(xr_store, ignore_errors=True)
                runs["xradio"] = _run(_XRADIO, str(ms), str(xr_store))
                runs["xradio_store"] = {"wall": 0.0, "mb": _du(xr_store) / 1e6}
                shutil.rmtree(xr_store, ignore_errors=True)
                shutil.rmtree(store, ignore_errors=True)
                runs["xstack_process"] = _run(_CONVERT_PROCESS, str(ms), str(store))
            for k, v in runs.items():
                if k not in best or v["wall"] < best[k]["wall"]:
                    best[k] = v
        rows = best["plain"]["rows"]
        n_vis = rows * N_CHAN * len(POLS)
        res = {"size_gb": size, "ms_mb": ms_bytes / 1e6, "store_mb": _du(store) / 1e6, "rows": rows,
               "n_vis": n_vis,
               **{f"{k}_{m}": v[m] for k, v in best.items()
                  for m in ("wall", "cpu", "rss_mb", "process_wall", "mb") if m in v}}
        results.append(res)
        print(json.dumps(res), file=sys.stderr, flush=True)
        if not args.keep:
            shutil.rmtree(store, ignore_errors=True)
            shutil.rmtree(work / f"bench_{size:g}GB.out.ms", ignore_errors=True)

    load_after = os.getloadavg()
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"MS: {N_ANT} antennas ({n_bl} baselines), {N_CHAN} channels, {len(POLS)} correlations, "
          f"WEIGHT_SPECTRUM; warm page cache (MS just written); best of {args.repeat} run(s); "
          f"load average (1, 5, 15 min) before {_load(load_before)}, after {_load(load_after)}\n")
    head = ("| MS size | rows | plain read wall / CPU (s) | raw write of the store's bytes wall / CPU (s) "
            "| convert wall / CPU (s) | convert MB/s | convert Mvis/s | convert / plain read, wall | "
            "convert / (read + write), wall | peak RSS plain / convert (MB) | store size (MB) |")
    print(head)
    print("|---" * (head.count("|") - 1) + "|")
    for r in results:
        floor = r["plain_wall"] + r["write_wall"]
        print(f"| {r['ms_mb'] / 1e3:.2f} GB | {r['rows']} | {r['plain_wall']:.2f} / {r['plain_cpu']:.2f} | "
              f"{r['write_wall']:.2f} / {r['write_cpu']:.2f} | "
              f"{r['convert_wall']:.2f} / {r['convert_cpu']:.2f} | {r['ms_mb'] / r['convert_wall']:.0f} | "
              f"{r['n_vis'] / r['convert_wall'] / 1e6:.1f} | {r['convert_wall'] / r['plain_wall']:.2f} | "
              f"{r['convert_wall'] / floor:.2f} | "
              f"{r['plain_rss_mb']:.0f} / {r['convert_rss_mb']:.0f} | "
              f"{r['store_mb']:.0f} |")
    if args.export:
        print("\n| MS size | export wall / CPU (s) | export MB/s | peak RSS (MB) |")
        print("|---|---|---|---|")
        for r in results:
            print(f"| {r['ms_mb'] / 1e3:.2f} GB | {r['export_wall']:.2f} / {r['export_cpu']:.2f} | "
                  f"{r['ms_mb'] / r['export_wall']:.0f} | {r['export_rss_mb']:.0f} |")
    if args.xradio:
        print("\n| MS size | xstack convert wall / CPU (s) | xradio wall / CPU (s) | xstack / xradio "
              "wall | xstack / xradio CPU | process wall, imports included: xstack / xradio (s) "
              "| ratio | peak RSS xstack / xradio (MB) | ratio | store size xstack / xradio (MB) |")
        print("|---|---|---|---|---|---|---|---|---|---|")
        for r in results:
            print(f"| {r['ms_mb'] / 1e3:.2f} GB | {r['convert_wall']:.2f} / {r['convert_cpu']:.2f} | "
                  f"{r['xradio_wall']:.2f} / {r['xradio_cpu']:.2f} | "
                  f"{r['convert_wall'] / r['xradio_wall']:.2f} | "
                  f"{r['convert_cpu'] / r['xradio_cpu']:.2f} | "
                  f"{r['xstack_process_process_wall']:.2f} / {r['xradio_process_wall']:.2f} | "
                  f"{r['xstack_process_process_wall'] / r['xradio_process_wall']:.2f} | "
                  f"{r['xstack_process_rss_mb']:.0f} / {r['xradio_rss_mb']:.0f} | "
                  f"{r['xstack_process_rss_mb'] / r['xradio_rss_mb']:.2f} | "
                  f"{r['store_mb']:.0f} / {r['xradio_store_mb']:.0f} |")
    if not args.keep and args.workdir is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
