"""Benchmark of the one-pass Monte Carlo noise estimate (xstack.noise).

Paper data-set type 6 at full size: VLA A configuration (27 antennas, 351 baselines),
1.4 GHz, 10 channels of 25 MHz, 2 parallel hands, 10 s integrations over 9.4 h (3384
integrations): 1.19e6 rows, 2.38e7 visibilities; 100 Monte Carlo realisations of 900 fake
sources each (paper section 3.5; STACKER: ~8 h on a CPU, 135 s on a GPU).

The kernel's cost is independent of the visibility values, so the timing runs on noise
visibilities with the real uv-tracks. By default it runs on a fraction of the integrations
(evenly spread over the 9.4 h, so the uv-coverage and phase ranges are the full ones) and
extrapolates linearly in the number of rows (the cost is exactly proportional to rows x
positions). ``--full`` adds the full-size run.

Both kernels are measured on the same fraction in the same session (``--engines``):
``antenna`` (per-antenna phasors, the default path for such data) and ``row`` (one phasor
per baseline row, the fallback).

Usage::

    python benchmarks/bench_noise.py [--fraction 0.03125] [--engines antenna,row] [--full]
        [--write docs/bench/noise.md]
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import time

import numpy as np

ARCSEC = np.pi / 180 / 3600
FIELD = (np.radians(15 * (3 + 49 / 60 + 10.99 / 3600)), np.radians(-30.0))
C = 299_792_458.0


def type6_partition(n_time: int, seed: int = 0):
    """Noise partition with VLA-A uv-tracks: n_time integrations spread over 9.4 h."""
    from xstack.schema import baseline_pairs, new_partition
    from xstack.sim.arrays import baseline_uvw, packaged_array, time_of_hour_angle

    arr = packaged_array("vla.a")
    a1, a2 = baseline_pairs(arr.n_antennas)
    lon = np.arctan2(arr.site[1], arr.site[0]) if np.any(arr.site) else -1.878
    t0 = time_of_hour_angle(-4.7 / 12 * np.pi, FIELD[0], lon, 60000.0)
    times = t0 + np.linspace(0.0, 9.4 * 3600.0, n_time)
    uvw = baseline_uvw(arr.positions, a1, a2, times, *FIELD)
    freq = 1.4e9 - 112.5e6 + 25e6 * np.arange(10)
    rng = np.random.default_rng(seed)
    shape = (n_time, a1.size, 10, 2)
    sigma = 10e-3  # Jy per visibility (Table 1)
    vis = (sigma * (rng.normal(size=shape) + 1j * rng.normal(size=shape))).astype(np.complex64)
    return new_partition(
        visibility=vis, weight=np.full(shape, 1 / sigma**2, np.float32),
        flag=np.zeros(shape, bool), uvw=uvw, time=times, antenna1=a1, antenna2=a2,
        antenna_names=arr.names, antenna_positions=arr.positions,
        dish_diameters=arr.diameters, frequency=freq, channel_width=np.full(10, 25e6),
        polarization=["RR", "LL"], phase_center=FIELD, telescope_name="VLA",
        integration_time=10.0)


def targets(n: int = 900, seed: int = 1):
    """n positions uniform in the 30' x 30' field (degrees)."""
    from xstack.coords import lm_to_radec

    rng = np.random.default_rng(seed)
    half = np.radians(15 / 60)
    ra, dec = lm_to_radec(rng.uniform(-half, half, n), rng.uniform(-half, half, n), *FIELD)
    return np.degrees(ra), np.degrees(dec)


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def bench_full(fraction: float, realizations: int, npos: int, engine: str = "auto") -> dict:
    from xstack.noise.estimate import estimate_noise

    n_time_full = 3384
    n_time = max(2, int(round(n_time_full * fraction)))
    ds = type6_partition(n_time)
    ra, dec = targets(npos)
    nrow = ds.sizes["time"] * ds.sizes["baseline_id"]
    nvis = ds["VISIBILITY"].size
    # warm-up: compile the numba kernels outside the timing
    estimate_noise(ds.isel(time=slice(0, 2)), (ra[:20], dec[:20]), method="mc", realizations=2,
                   flux=1e-6, engine=engine)
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    c0 = time.process_time()
    res = estimate_noise(ds, (ra, dec), method="mc", realizations=realizations, flux=2.96e-6,
                         seed=3, engine=engine)
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    full_rows = 351 * n_time_full
    import numba

    threads = numba.get_num_threads()
    return {"cpu_extrapolated_full_s": cpu * full_rows / nrow / threads,
            "cpu_ns_per_row_position": cpu / (nrow * realizations * res.n_positions) * 1e9,
            "n_time": n_time, "rows": nrow, "visibilities": nvis, "wall_s": wall, "cpu_s": cpu,
            "positions_per_realisation": res.n_positions, "realizations": realizations,
            "ns_per_row_position": wall / (nrow * realizations * res.n_positions) * 1e9,
            "extrapolated_full_s": wall * full_rows / nrow, "noise_jy": res.noise_jy,
            "bias_jy": res.bias_jy, "peak_rss_mib": peak_rss_mib(), "load": load,
            "engine": res.extra["engine"],
            "phase_error_rad": res.extra.get("antenna_phase_error_rad")}


def bench_accuracy(rs=(10, 30, 100, 300), n_sets: int = 6) -> list[dict]:
    """Relative error of the mc noise estimate against the exact scatter, vs R."""
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
    from _fit_helpers import noise_field

    from xstack.beams import standard_beam
    from xstack.coords import angular_separation, radec_to_lmn
    from xstack.noise.estimate import estimate_noise
    from xstack.noise.positions import random_positions

    center = (1.0, -0.5236)
    ra, dec = random_positions(60, 1, np.array([center]), np.array([np.radians(10 / 60)]),
                               avoid_ra=np.zeros(0), avoid_dec=np.zeros(0),
                               min_separation=np.radians(60 / 3600), rng=np.random.default_rng(0))
    ra, dec = ra[0], dec[0]
    _, uvw, freq = noise_field(0, n_ant=20, extent_m=20e3)
    A = standard_beam("VLA", 25.0)(angular_separation(ra, dec, *center)[:, None], freq[None])
    l, m, _, n1 = radec_to_lmn(ra, dec, *center)
    P = np.zeros(uvw.shape[:2] + (freq.size,), complex)
    for k in range(ra.size):
        d = uvw[..., 0] * l[k] + uvw[..., 1] * m[k] + uvw[..., 2] * n1[k]
        P += np.exp(-2j * np.pi * d[..., None] * freq / C) / A[k]
    P /= ra.size
    truth = float(np.sqrt(2 * np.sum(np.abs(P) ** 2)) / (2 * P.size))
    out = []
    sets = [noise_field(100 + s, n_ant=20, extent_m=20e3)[0] for s in range(n_sets)]
    estimate_noise(sets[0], (np.degrees(ra), np.degrees(dec)), method="mc", realizations=2,
                   weighting="none", flux=1e-3)
    for R in rs:
        errs, times = [], []
        for s, ds in enumerate(sets):
            t0 = time.perf_counter()
            res = estimate_noise(ds, (np.degrees(ra), np.degrees(dec)), method="mc",
                                 realizations=R, weighting="none", flux=1e-3, seed=s)
            times.append(time.perf_counter() - t0)
            errs.append(res.noise_jy / truth - 1.0)
        errs = np.array(errs)
        out.append({"R": R, "rms_rel_error": float(np.sqrt(np.mean(errs**2))),
                    "mean_rel_error": float(np.mean(errs)),
                    "expected_1_over_sqrt_2R": float(1 / np.sqrt(2 * (R - 1))),
                    "time_s": float(np.mean(times))})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fraction", type=float, default=1 / 32,
                    help="fraction of the 3384 integrations to run (1 = full size)")
    ap.add_argument("--engines", default="antenna,row",
                    help="engines timed at --fraction, in this order")
    ap.add_argument("--full", action="store_true",
                    help="also run the full size (all 3384 integrations, engine auto)")
    ap.add_argument("--realizations", type=int, default=100)
    ap.add_argument("--positions", type=int, default=900)
    ap.add_argument("--skip-accuracy", action="store_true")
    ap.add_argument("--write", help="write the Markdown tables to this file")
    args = ap.parse_args()
    import numba

    lines = ["# Benchmark: Monte Carlo noise estimate (`xstack noise --method mc`)", "",
             f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
             f"numba {numba.__version__} with {numba.get_num_threads()} threads. Other engineers' "
             "jobs were running on the same 2 cores at the same time (load average "
             f"{os.getloadavg()[0]:.1f} at the start), so wall times are pessimistic.", ""]
    runs = [(args.fraction, e) for e in args.engines.split(",") if e]
    if args.full:
        runs.append((1.0, "auto"))
    lines += [
        f"## {args.realizations} realisations x {args.positions} positions, paper type 6 (VLA A, "
        "10 ch, 2 pols, 9.4 h)", "",
        "| engine | integrations | rows | visibilities | realisations x positions | load avg "
        "at start | wall [s] | CPU [s] | CPU ns per row x position | full size from CPU time "
        "/ threads (uncontended) | full size from wall | peak RSS [MiB] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    results = []
    for fraction, engine in runs:
        r = bench_full(fraction, args.realizations, args.positions, engine)
        results.append(r)
        row = (f"| {r['engine']} | {r['n_time']} of 3384 | {r['rows']:,} | "
               f"{r['visibilities']:,} | {r['realizations']} x {r['positions_per_realisation']} | "
               f"{r['load']:.1f} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
               f"{r['cpu_ns_per_row_position']:.2f} | {r['cpu_extrapolated_full_s']:.0f} s "
               f"({r['cpu_extrapolated_full_s'] / 60:.1f} min) | {r['extrapolated_full_s']:.0f} s "
               f"({r['extrapolated_full_s'] / 60:.1f} min) | {r['peak_rss_mib']:.0f} |")
        print(row, flush=True)
        lines.append(row)
    lines += ["", "STACKER (paper): ~8 h on a CPU, 135 s on a GPU for the same problem.", ""]
    for r in results:
        pe = r["phase_error_rad"]
        lines.append(f"* {r['engine']}, {r['n_time']} integrations: noise "
                     f"{r['noise_jy'] * 1e6:.4f} uJy, bias {r['bias_jy'] * 1e6:.4f} uJy"
                     + (f", factorisation phase-error bound {pe:.1e} rad" if pe else ""))
    lines.append("")
    if not args.skip_accuracy:
        acc = bench_accuracy()
        tab = ["## Accuracy of the noise estimate vs number of realisations", "",
               "60 targets, 20-antenna array, 3 channels; truth = exact scatter of the stacked "
               "flux over independent noise (sum W|P|^2 / (sum W)^2); 6 independent data sets.",
               "", "| R | rms relative error | mean relative error | 1/sqrt(2(R-1)) | time per "
               "estimate [s] |", "|---|---|---|---|---|"]
        for a in acc:
            tab.append(f"| {a['R']} | {a['rms_rel_error']:.3f} | {a['mean_rel_error']:+.3f} | "
                       f"{a['expected_1_over_sqrt_2R']:.3f} | {a['time_s']:.2f} |")
        print("\n".join(tab), flush=True)
        lines += tab + [""]
    if args.write:
        with open(args.write, "w") as fh:
            fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
