"""Every ``xstack noise`` method against the brute-force truth (issue 10).

The truth is the scatter of the stacked flux AT THE ACTUAL TARGETS over independent noise
realisations, computed in plain numpy (``tests/test_noise_truth.py``: the stack is linear,
F_r = sum_p sum_vis W Re(N_r Q_p) / D with N_r drawn with the data's own weights). Geometry
and weights come from ``xstack.sim`` scenes; the one data set the estimators see is a
further numpy noise draw with the same weights.

Cases: (1) 300 targets in a disc of radius 15' on one VLA-A pointing (1.4 GHz); (2) 300
targets in a 30'x30' box on the same pointing (paper types 3-6); (3) 50 targets in the
100"x100" box of the paper-8 ALMA mosaic (22 pointings, 230 GHz; 20 of its 100 channels, so
the truth's draws stay cheap). Each with weighting none and pb. For each method the table
gives noise / truth and the 1-sigma sampling error of that ratio (truth's and estimate's
combined; for random and mc also the spread of the exact noise between individual random
position sets, computed in numpy for 30 of them: those methods estimate the noise of a
typical set in the region, the targets are one set), the number of sigmas, and the wall
time.

Usage::

    python benchmarks/bench_noise_truth.py [--vla-scale 0.01] [--alma-scale 0.05]
        [--truth-realizations 1000] [--realizations 300] [--cases disc,box,mosaic]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from test_noise_truth import (  # noqa: E402
    alma_mosaic_scene,
    box_catalog,
    brute_force_truth,
    compare,
    disc_catalog,
    load_geometry,
    set_spread,
    vla_scene,
    with_noise,
)

METHODS = ("analytic", "mc", "random", "bootstrap")


def run_case(name: str, parts: dict, ra: np.ndarray, dec: np.ndarray, weighting: str,
             r_truth: int, r_est: int, seed: int = 7, n_sets: int = 30) -> list[dict]:
    from xstack.noise.estimate import estimate_noise

    t0 = time.perf_counter()
    tr = brute_force_truth(parts, ra, dec, weighting, realizations=r_truth)
    t_truth = time.perf_counter() - t0
    data = with_noise(parts, seed)
    pos = (np.degrees(ra), np.degrees(dec))
    rows = []
    spread = None
    for i, method in enumerate(METHODS):
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = estimate_noise(data, pos, method=method, realizations=r_est,
                                 weighting=weighting, seed=100 + i,
                                 flux=1e-9 if method == "mc" else None)
        dt = time.perf_counter() - t0
        if method in ("mc", "random") and spread is None:
            t1 = time.perf_counter()
            spread = set_spread(parts, res.positions_deg, weighting, sets=n_sets)
            print(f"  {name} {weighting}: exact noise of {n_sets} random sets: relative "
                  f"spread {spread:.3f} ({time.perf_counter() - t1:.0f} s)", flush=True)
        ratio, err = compare(res, tr, spread or 0.0)
        rows.append({"case": name, "weighting": weighting, "method": method,
                     "truth_ujy": tr["truth"] * 1e6, "truth_err_ujy": tr["err"] * 1e6,
                     "exact_ujy": tr["exact"] * 1e6, "noise_ujy": res.noise_jy * 1e6,
                     "ratio": ratio, "err": err, "nsigma": (ratio - 1) / err, "time_s": dt,
                     "truth_time_s": t_truth, "region": res.extra.get("region", ""),
                     "spread": spread if method in ("mc", "random") else 0.0,
                     "optimal_ujy": res.extra.get("optimal_noise_jy", np.nan) * 1e6})
        print(f"  {name:7s} {weighting:4s} {method:9s} noise {res.noise_jy * 1e6:8.4f} uJy  "
              f"truth {tr['truth'] * 1e6:8.4f} +- {tr['err'] * 1e6:.4f}  ratio {ratio:6.3f} "
              f"+- {err:.3f} ({(ratio - 1) / err:+.1f} sigma)  {dt:6.1f} s", flush=True)
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vla-scale", type=float, default=0.01)
    ap.add_argument("--alma-scale", type=float, default=0.05)
    ap.add_argument("--alma-channels", type=int, default=20)
    ap.add_argument("--truth-realizations", type=int, default=1000)
    ap.add_argument("--realizations", type=int, default=300)
    ap.add_argument("--cases", default="disc,box,mosaic")
    ap.add_argument("--weightings", default="none,pb")
    a = ap.parse_args(argv)
    cases = a.cases.split(",")
    print(f"# {platform.machine()} {os.cpu_count()} cores, python {platform.python_version()}, "
          f"load {os.getloadavg()[0]:.1f}; command: python benchmarks/bench_noise_truth.py "
          + " ".join(sys.argv[1:] if argv is None else argv), flush=True)
    rows = []
    if "disc" in cases or "box" in cases:
        parts = load_geometry(vla_scene(), a.vla_scale)
        ds = next(iter(parts.values()))
        center = tuple(float(x) for x in ds.attrs["phase_center"])
        print(f"# VLA: {dict(ds.sizes)}", flush=True)
        cats = {}
        if "disc" in cases:
            cats["disc"] = disc_catalog(center, 15.0, 300, seed=3)
        if "box" in cases:
            cats["box"] = box_catalog(center, 30.0, 300, seed=3)
        for name, (ra, dec) in cats.items():
            for wt in a.weightings.split(","):
                rows += run_case(name, parts, ra, dec, wt, a.truth_realizations, a.realizations)
    if "mosaic" in cases:
        scene = alma_mosaic_scene()
        scene["spectral"]["channels"] = a.alma_channels
        parts = load_geometry(scene, a.alma_scale)
        ds = next(iter(parts.values()))
        print(f"# ALMA paper-8 mosaic: {len(parts)} pointings x {dict(ds.sizes)}", flush=True)
        from xstack.sim.scene import PAPER_FIELD_CENTER

        center = tuple(np.radians(PAPER_FIELD_CENTER))
        ra, dec = box_catalog(center, 100.0 / 60.0, 50, seed=3)
        for wt in a.weightings.split(","):
            rows += run_case("mosaic", parts, ra, dec, wt, a.truth_realizations, a.realizations)
    print("\n| case | weighting | truth (µJy) | set spread | analytic | mc | random | bootstrap |")
    print("|---|---|---|---|---|---|---|---|")
    keys = []
    for r in rows:
        if (r["case"], r["weighting"]) not in keys:
            keys.append((r["case"], r["weighting"]))
    for case, wt in keys:
        sel = {r["method"]: r for r in rows if r["case"] == case and r["weighting"] == wt}
        any_r = next(iter(sel.values()))
        cells = [f"{sel[m]['ratio']:.3f} ± {sel[m]['err']:.3f} ({sel[m]['time_s']:.1f} s)"
                 for m in METHODS]
        print(f"| {case} | {wt} | {any_r['truth_ujy']:.4g} ± {any_r['truth_err_ujy']:.2g} | "
              f"{sel['random']['spread']:.3f} | " + " | ".join(cells) + " |")
    print("\nratio = noise / truth ± 1-sigma sampling error (truth, estimate and, for mc "
          "and random, the set-to-set spread); time = wall time of the estimate")
    for case, wt in keys:
        r = next(r for r in rows if r["case"] == case and r["weighting"] == wt
                 and r["region"])
        print(f"# {case} {wt}: region {r['region']}; truth draws {r['truth_time_s']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
