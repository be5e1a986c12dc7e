"""Benchmark of the smearing-loss estimate of uv-stacking: accuracy vs subsample size and time.

The paper's type-1..7 layout (VLA A, 1.4 GHz, 10 channels; 10 s integrations; ``--hours`` of
track, default 9.4 h) as a zarr store on disk, 900 positions uniform in 30'x30'. For row
budgets from 1 000 to all rows, :func:`xstack.uvstack.smearing.loss_factors` (plan time:
reads UVW, WEIGHT and FLAG of the sampled rows) is timed, and its factors L_k(nu) are compared
with those from all rows: max and rms |L_sub - L_all| over positions and channels. The
uv-stack flux pass of the same store (``smearing="none"``) is timed for scale. Two channel
widths: the paper's 25 MHz (huge bandwidth smearing off axis) and 1 MHz.

Usage::

    python benchmarks/bench_smearing.py [--hours 9.4] [--out docs/bench/smearing.md]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from xstack.coords import lm_to_radec, radec_to_lmn
from xstack.schema import iter_partitions, open_store
from xstack.sim.simulate import simulate
from xstack.uvstack import smearing as usm

ARCMIN = math.pi / 180 / 60
CENTER = (57.2957916666667, -30.0)


def _scene(hours: float, width_hz: float) -> dict:
    return {
        "name": "bench-smearing",
        "array": {"config": "vla.a"},
        "observation": {"integration": 10.0, "time_per_pointing": hours * 3600.0,
                        "hour_angle": [-4.7, 4.7]},
        "spectral": {"center": 1.4e9, "bandwidth": 10 * width_hz, "channels": 10,
                     "polarizations": ["RR", "LL"]},
        "pointings": {"mode": "single", "center": list(CENTER)},
        "effects": {"primary_beam": "auto", "w_term": True, "bandwidth_smearing": True,
                    "time_smearing": True},
        "populations": [],  # geometry only: no model, zero visibilities (the loss reads none)
    }


def _timed(fn, *a, **kw):
    t0 = time.perf_counter()
    c0 = time.process_time()
    r = fn(*a, **kw)
    return time.perf_counter() - t0, time.process_time() - c0, r


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--hours", type=float, default=9.4)
    p.add_argument("--positions", type=int, default=900)
    p.add_argument("--out", default=None, help="also write the Markdown report here")
    args = p.parse_args(argv)
    lines: list[str] = []

    def out(s: str = "") -> None:
        print(s, flush=True)
        lines.append(s)

    out(f"# smearing-loss subsample: `python benchmarks/bench_smearing.py --hours {args.hours}`")
    out()
    out(f"load average at start: {os.getloadavg()[0]:.1f}")
    rng = np.random.default_rng(5)
    half = 15 * ARCMIN
    ra0, dec0 = math.radians(CENTER[0]), math.radians(CENTER[1])
    ra, dec = lm_to_radec(rng.uniform(-half, half, args.positions),
                          rng.uniform(-half, half, args.positions), ra0, dec0)
    from astropy.table import Table

    cat = Table({"ra": np.degrees(ra), "dec": np.degrees(dec)})
    with tempfile.TemporaryDirectory(prefix="bench-smearing-") as tmp:
        for width in (25e6, 1e6):
            store = Path(tmp) / f"w{int(width)}.zarr"
            t_sim, _, _ = _timed(simulate, _scene(args.hours, width), store)
            (_, ds), = list(iter_partitions(open_store(store)))
            nrow = ds.sizes["time"] * ds.sizes["baseline_id"]
            out()
            out(f"## channel width {width / 1e6:g} MHz: {ds.sizes['time']} integrations x "
                f"{ds.sizes['baseline_id']} baselines = {nrow} rows, 10 channels, "
                f"{args.positions} positions (store written in {t_sim:.1f} s)")
            out()
            l, m, _, n1 = radec_to_lmn(ra, dec, *ds.attrs["phase_center"])
            pm = np.array([True, True])
            kw = dict(bandwidth=True, time=True, pol_mask=pm)
            # warm-up (numba compilation) on a tiny budget
            usm.loss_factors(ds, l[:2], m[:2], n1[:2], max_rows=100, **kw)
            t_all, c_all, (full, full_ref) = _timed(usm.loss_factors, ds, l, m, n1,
                                                    max_rows=nrow, **kw)
            loss = 1 - full_ref
            out(f"loss 1 - L_k at the mean frequency over the {args.positions} positions: "
                f"median {np.median(loss):.4f}, max {loss.max():.4f}; "
                f"positions above 10 %: {int(np.sum(loss > 0.1))}")
            out()
            out("| rows sampled | wall s | CPU s | max abs(L_sub - L_all) | rms |")
            out("|---:|---:|---:|---:|---:|")
            for rows in (1000, 2000, 5000, 10000, 20000, 50000, 100000):
                if rows >= nrow:
                    break
                t, c, (sub, _) = _timed(usm.loss_factors, ds, l, m, n1, max_rows=rows, **kw)
                err = np.abs(sub - full)
                out(f"| {rows} | {t:.2f} | {c:.2f} | {err.max():.2e} | "
                    f"{np.sqrt(np.mean(err**2)):.2e} |")
            out(f"| all {nrow} | {t_all:.2f} | {c_all:.2f} | 0 | 0 |")

            from xstack.uvstack.stack import stack_uv

            t_st, c_st, _ = _timed(stack_uv, store, cat, smearing="none", weighting="none")
            t_co, c_co, _ = _timed(stack_uv, store, cat, smearing="auto", weighting="none")
            out()
            out(f"uv-stack flux pass of the same store: {t_st:.2f} s wall ({c_st:.2f} s CPU) "
                f"with smearing='none', {t_co:.2f} s ({c_co:.2f} s CPU) with 'auto' "
                f"(default {usm.MAX_ROWS} rows)")
    out()
    out(f"load average at end: {os.getloadavg()[0]:.1f}")
    if args.out:
        Path(args.out).write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
