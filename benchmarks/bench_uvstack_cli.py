"""What the command line pays for the stacked store it writes (issue 14).

The paper's type-6 data set (``--scale 1``: 2.4e7 visibilities; 900 target positions) is
simulated once; then, alternately, each in a fresh process with its start-up included:

* ``flux``: ``python -c "xstack.stack_uv(DATA, CATALOG)"`` -- the flux alone, nothing written;
* ``cli``: ``xstack uvstack DATA CATALOG OUT.zarr --json`` -- the flux, the stacked store
  written in the same pass, its uv-profile (ECSV and PNG) and the JSON;
* ``cli --no-png``: the same without the PNG (the store and the ECSV profile).

Printed: wall and CPU seconds of every run, the best of each, and their ratio (goal of issue
14: the command line at most 1.3x the flux alone), plus the two fluxes (equal bit for bit).

Usage::

    python benchmarks/bench_uvstack_cli.py [--scale 1] [--repeat 3] [--workdir DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

_FLUX = ("import json, sys, xstack; r = xstack.stack_uv(sys.argv[1], sys.argv[2]); "
         "print(json.dumps({'flux_jy': r.flux_jy}))")


def run(argv: list[str]) -> tuple[float, float, dict]:
    """Wall and CPU seconds (the child's, start-up included) and the JSON it printed."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    res = subprocess.run(argv, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode:
        raise RuntimeError(res.stderr[-2000:])
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, json.loads(res.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--workdir", default=None)
    args = ap.parse_args()
    work = Path(args.workdir or tempfile.mkdtemp(prefix="xstack-uvcli-"))
    work.mkdir(parents=True, exist_ok=True)
    store = work / "type6.zarr"
    if not store.exists():
        print(f"simulating paper-6 at scale {args.scale} ...", file=sys.stderr, flush=True)
        subprocess.run([sys.executable, "-c", "import sys, xstack; xstack.simulate(xstack.preset_scene("
                        "'paper-6', scale=float(sys.argv[2])), sys.argv[1], seed=3)", str(store),
                        str(args.scale)], check=True)
    cat = work / "type6.targets.ecsv"
    xstack_cli = shutil.which("xstack") or "xstack"
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
          f"load average before {' / '.join(f'{x:.1f}' for x in os.getloadavg())}\n")
    print("| run | flux alone: wall / CPU (s) | command line with store + PNG: wall / CPU (s) "
          "| ratio (wall) | `--no-png`: wall / CPU (s) | ratio (wall) |")
    print("|---|---|---|---|---|---|")
    best = {"flux": [float("inf"), 0.0], "cli": [float("inf"), 0.0], "nopng": [float("inf"), 0.0]}
    fluxes = {}
    for i in range(args.repeat):
        w1, c1, j1 = run([sys.executable, "-c", _FLUX, str(store), str(cat)])
        out = work / "stacked.zarr"
        cli = [xstack_cli, "uvstack", str(store), str(cat), str(out), "--json", "--no-progress",
               "--overwrite"]
        w2, c2, j2 = run(cli)
        w3, c3, j3 = run([*cli, "--no-png"])
        fluxes = {"flux": j1["flux_jy"], "cli": j2["flux_jy"], "nopng": j3["flux_jy"]}
        for key, (w, c) in (("flux", (w1, c1)), ("cli", (w2, c2)), ("nopng", (w3, c3))):
            if w < best[key][0]:
                best[key] = [w, c]
        print(f"| {i + 1} | {w1:.2f} / {c1:.2f} | {w2:.2f} / {c2:.2f} | {w2 / w1:.2f} "
              f"| {w3:.2f} / {c3:.2f} | {w3 / w1:.2f} |", flush=True)
    b = best
    print(f"| best | {b['flux'][0]:.2f} / {b['flux'][1]:.2f} | {b['cli'][0]:.2f} / "
          f"{b['cli'][1]:.2f} | **{b['cli'][0] / b['flux'][0]:.2f}** | {b['nopng'][0]:.2f} / "
          f"{b['nopng'][1]:.2f} | **{b['nopng'][0] / b['flux'][0]:.2f}** |")
    same = len(set(fluxes.values())) == 1
    print(f"\nflux alone {fluxes['flux']!r} Jy, command line {fluxes['cli']!r} Jy, --no-png "
          f"{fluxes['nopng']!r} Jy ({'equal' if same else 'DIFFERENT'}); "
          f"load average after {' / '.join(f'{x:.1f}' for x in os.getloadavg())}")
    if args.workdir is None:
        shutil.rmtree(work)


if __name__ == "__main__":
    main()
