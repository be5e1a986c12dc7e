"""Benchmark of the simulator: model-visibility time vs sources and visibilities, per path,
with each path's accuracy against the float64 direct sum; and one full-size paper type 6.

Paths
-----
numpy-direct     plain numpy, one complex exponential per (row, channel, source): the truth
row-f64          ``kernels.model_visibilities`` (numba, float64, channel recurrence), 1 thread
antenna-f64      ``kernels.model_visibilities_antenna`` (per-antenna phasors; what the
                 simulator uses), 1 thread
row-f32          ``kernels.model_visibilities_float32`` (float32 phases, no w-term)
ducc0-grid       ``ducc0.wgridder.experimental.dirty2vis`` of the sources put on the nearest
                 pixel of a 0.1" grid (epsilon 1e-7): accuracy is limited by the pixel grid

Usage::

    python benchmarks/bench_simulate.py [--full-type6] [--quick]

Prints Markdown tables (time in s, throughput in million source-visibilities per second,
max |error| / sum |S|, peak RSS). Accuracy is measured against numpy-direct where that is
affordable, otherwise against row-f64 (itself checked against numpy-direct to 1e-9 in the
tests).
"""

from __future__ import annotations

import argparse
import math
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from xstack.schema import baseline_pairs  # noqa: E402
from xstack.sim import arrays, kernels  # noqa: E402

ARCSEC = math.pi / 180 / 3600


def _setup(ntime: int, nsrc: int, extended: bool, seed: int = 0):
    rng = np.random.default_rng(seed)
    vla = arrays.packaged_array("vla.a")
    a1, a2 = baseline_pairs(vla.n_antennas)
    t = 4.9e9 + 10.0 * np.arange(ntime)
    ra0, dec0 = math.radians(57.3), math.radians(-30.0)
    ant = arrays.antenna_uvw(vla.positions, t, ra0, dec0)
    uvw = (ant[:, a1] - ant[:, a2]).reshape(-1, 3)
    freq = 1.4e9 + 25e6 * (np.arange(10) - 4.5)
    # positions on a 0.1" grid within +-90" so that the ducc0 path can be exact in position
    pix = 0.1 * ARCSEC
    l = np.round(rng.uniform(-90, 90, nsrc) / 0.1) * pix
    m = np.round(rng.uniform(-90, 90, nsrc) / 0.1) * pix
    nm1 = -(l**2 + m**2) / (1 + np.sqrt(1 - l**2 - m**2))
    flux = rng.uniform(1e-6, 1e-3, nsrc)
    fwhm = rng.uniform(0.5, 5.0, nsrc) * ARCSEC if extended else None
    return ant, a1, a2, uvw, freq, l, m, nm1, flux, fwhm


def _timed(fn, *a, **k):
    t0 = time.perf_counter()
    out = fn(*a, **k)
    return out, time.perf_counter() - t0


def _ducc(uvw, freq, l, m, flux, pix=0.1 * ARCSEC, npix=2048):
    from ducc0.wgridder.experimental import dirty2vis

    img = np.zeros((npix, npix))
    ix = np.round(l / pix).astype(int) + npix // 2
    iy = np.round(m / pix).astype(int) + npix // 2
    np.add.at(img, (ix, iy), flux)
    return dirty2vis(uvw=uvw, freq=freq, dirty=img, pixsize_x=pix, pixsize_y=pix,
                     epsilon=1e-7, do_wgridding=False, nthreads=1, divide_by_n=False)


def kernel_table(quick: bool) -> None:
    from _sim_helpers import direct_eq1

    # warm-up (numba compilation)
    ant, a1, a2, uvw, freq, l, m, nm1, flux, _ = _setup(1, 3, False)
    kernels.model_visibilities(uvw, freq, l, m, nm1, flux, parallel=False)
    kernels.model_visibilities_antenna(ant, a1, a2, freq, l, m, nm1, flux, parallel=False)
    kernels.model_visibilities_antenna(ant, a1, a2, freq, l, m, nm1, flux, fwhm=np.ones(3) * 1e-6,
                                       parallel=False)
    kernels.model_visibilities_float32(uvw, freq, l, m, flux)
    # the ducc0 sign/axis convention, found once against the direct sum
    v0 = _ducc(uvw, freq, l[:1], m[:1], flux[:1])
    r0 = direct_eq1(uvw, freq, l[:1], m[:1], None, flux[:1])
    conj = np.abs(v0 - r0).max() > np.abs(np.conj(v0) - r0).max()

    print("\n### Model visibilities: time and accuracy per path (1 thread, VLA A, 10 channels)\n")
    print("| sources | rows (x10 ch) | kind | path | time (s) | M src-vis/s | max err / sum S |")
    print("|---:|---:|---|---|---:|---:|---:|")
    sizes = [(10, 20), (100, 20), (1000, 20), (100, 200)] if not quick else [(10, 5), (100, 5)]
    for nsrc, ntime in sizes:
        for extended in (False, True):
            ant, a1, a2, uvw, freq, l, m, nm1, flux, fwhm = _setup(ntime, nsrc, extended)
            nrow = uvw.shape[0]
            work = nrow * freq.size * nsrc
            res = {}
            if work <= 8e7:
                res["numpy-direct"] = _timed(direct_eq1, uvw, freq, l, m, nm1, flux, None, fwhm)
            res["row-f64"] = _timed(kernels.model_visibilities, uvw, freq, l, m, nm1, flux,
                                    None, fwhm, parallel=False)
            va, ta = _timed(kernels.model_visibilities_antenna, ant, a1, a2, freq, l, m, nm1,
                            flux, None, fwhm, parallel=False)
            res["antenna-f64"] = (va.reshape(nrow, -1), ta)
            if not extended:
                res["row-f32"] = _timed(kernels.model_visibilities_float32, uvw, freq, l, m, flux)
                vd, td = _timed(_ducc, uvw, freq, l, m, flux)
                res["ducc0-grid (no w)"] = (np.conj(vd) if conj else vd, td)
            ref = res.get("numpy-direct", res["row-f64"])[0]
            for name, (vis, dt) in res.items():
                err = np.abs(vis - ref).max() / flux.sum()
                # paths without the w-term are compared with a w-less reference
                if name in ("row-f32", "ducc0-grid (no w)"):
                    ref_now = kernels.model_visibilities(uvw, freq, l, m, None, flux)
                    err = np.abs(vis - ref_now).max() / flux.sum()
                print(f"| {nsrc} | {nrow} | {'gaussian' if extended else 'point'} | {name} | "
                      f"{dt:.3f} | {work / dt / 1e6:.1f} | {err:.1e} |")


def full_type6(scale: float) -> None:
    import shutil
    import tempfile

    from xstack.sim.presets import preset_scene
    from xstack.sim.simulate import simulate

    tmp = Path(tempfile.mkdtemp(prefix="xstack-bench-"))
    try:
        t0, c0 = time.perf_counter(), time.process_time()
        res = simulate(preset_scene("paper-6"), tmp / "t6.zarr", seed=0, scale=scale)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        size = sum(f.stat().st_size for f in (tmp / "t6.zarr").rglob("*") if f.is_file()) / 1e6
        print("\n### Paper type 6, one realisation, written to zarr (dask threads, 2 cores)\n")
        print("| scale | visibilities | sources | wall (s) | CPU (s) | peak RSS (MB) | store (MB) |")
        print("|---:|---:|---:|---:|---:|---:|---:|")
        nsrc = sum(len(t) for t in res.catalogs.values())
        print(f"| {scale} | {res.n_visibilities:,} | {nsrc} | {wall:.1f} | {cpu:.1f} | "
              f"{rss:.0f} | {size:.0f} |")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes only")
    ap.add_argument("--full-type6", action="store_true", help="also simulate full-size type 6")
    ap.add_argument("--type6-scale", type=float, default=1.0)
    ap.add_argument("--only-type6", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.only_type6:
        full_type6(args.type6_scale)
        return
    print(f"# bench_simulate ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())})")
    kernel_table(args.quick)
    if args.full_type6:
        # a fresh process, so that peak RSS is the simulation's own
        import subprocess

        sys.stdout.flush()
        subprocess.run([sys.executable, __file__, "--only-type6", "--type6-scale",
                        str(args.type6_scale)], check=True)


if __name__ == "__main__":
    main()
