"""Benchmark of image-stacking: 900 stamps of 64 x 64 from a 4000 x 4000 image.

Prints a Markdown table (time, throughput, peak memory, accuracy) for nearest-pixel and
sub-pixel (Fourier, spline) alignment, mean and median, measured in the same run; then a
second table for the local-noise estimator and the stamp sigma_k is measured on.

    python benchmarks/bench_imstack.py [--size 4000] [--n 900] [--stamp 64] [--repeat 3]

The image is synthetic: point sources of flux 1 with a 3.2" x 1.6" Gaussian beam on a
0.5" SIN grid (the paper's type-2/3 pixelisation) at random sub-pixel positions, plus white
Gaussian noise of 0.01 per pixel, so the stacking noise (3e-4) is far below the effects of
alignment being measured.
"""

from __future__ import annotations

import argparse
import platform
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
from astropy.io import fits
from astropy.wcs import WCS

from xstack.imstack import kernels
from xstack.imstack.io import read_image
from xstack.imstack.stack import stack_images

BEAM = (3.2, 1.6, 0.0)


def make_image(path: Path, size: int, n: int, cell: float, seed: int = 1,
               residual_jy: float = 0.0, residual_offset_pix: int = 8):
    rng = np.random.default_rng(seed)
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---SIN", "DEC--SIN"]
    w.wcs.crval = [57.2957917, -30.0]
    w.wcs.crpix = [size // 2 + 1, size // 2 + 1]
    w.wcs.cdelt = [-cell / 3600, cell / 3600]
    img = rng.normal(0.0, 0.01, (size, size)).astype(np.float32)
    side = int(np.ceil(np.sqrt(n)))
    spacing = (size - 200) / side
    g = 100 + spacing * (np.arange(side) + 0.5)
    gx, gy = np.meshgrid(g, g)
    px = gx.ravel()[:n] + rng.uniform(-0.5, 0.5, n)
    py = gy.ravel()[:n] + rng.uniform(-0.5, 0.5, n)
    half = int(4 * BEAM[0] / cell)
    ln2 = np.log(2)
    for x0, y0 in zip(px, py):
        i0, j0 = int(round(x0)), int(round(y0))
        xs = np.arange(i0 - half, i0 + half + 1)
        ys = np.arange(j0 - half, j0 + half + 1)
        east = -(xs[None, :] - x0) * cell
        north = (ys[:, None] - y0) * cell
        img[ys[0]:ys[-1] + 1, xs[0]:xs[-1] + 1] += np.exp(
            -4 * ln2 * ((north / BEAM[0]) ** 2 + (east / BEAM[1]) ** 2)).astype(np.float32)
    if residual_jy:
        # a CLEAN residual beside every other target: a point of residual_jy at the pixel
        # residual_offset_pix east of it, convolved with the beam
        for x0, y0 in zip(np.round(px[::2]) + residual_offset_pix, np.round(py[::2])):
            i0, j0 = int(x0), int(y0)
            xs = np.arange(i0 - half, i0 + half + 1)
            ys = np.arange(j0 - half, j0 + half + 1)
            east = -(xs[None, :] - x0) * cell
            north = (ys[:, None] - y0) * cell
            img[ys[0]:ys[-1] + 1, xs[0]:xs[-1] + 1] += residual_jy * np.exp(
                -4 * ln2 * ((north / BEAM[0]) ** 2 + (east / BEAM[1]) ** 2)).astype(np.float32)
    h = w.to_header()
    h["BMAJ"], h["BMIN"], h["BPA"], h["BUNIT"] = BEAM[0] / 3600, BEAM[1] / 3600, BEAM[2], "Jy/beam"
    fits.PrimaryHDU(img, header=h).writeto(path)
    ra, dec = w.pixel_to_world_values(px, py)
    return np.c_[ra, dec]


def timed(fn, repeat):
    """Best wall time, CPU time of that run, peak traced memory (MiB) and the result."""
    best, cpu = np.inf, np.inf
    out = None
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        t1, c1 = time.perf_counter(), time.process_time()
        if t1 - t0 < best:
            best, cpu = t1 - t0, c1 - c0
    tracemalloc.start()
    fn()
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return best, peak / 2**20, out, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=4000)
    ap.add_argument("--n", type=int, default=900)
    ap.add_argument("--stamp", type=int, default=64)
    ap.add_argument("--cell", type=float, default=0.5)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "big.fits"
        pos = make_image(path, args.size, args.n, args.cell)
        t_read, mem_read, info, _ = timed(lambda: read_image(path), 1)
        factor = kernels.pixelisation_factor(*BEAM, args.cell, args.cell)
        print(f"# imstack benchmark: {args.n} stamps of {args.stamp}x{args.stamp} from a "
              f"{args.size}x{args.size} image, {args.cell}\" pixels, beam {BEAM[0]}\"x{BEAM[1]}\"")
        print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}")
        print(f"reading the FITS image ({path.stat().st_size / 2**20:.0f} MiB): {t_read:.3f} s, "
              f"peak {mem_read:.0f} MiB")
        print(f"expected nearest-pixel factor for a Gaussian beam: {factor:.4f}\n")
        print("| alignment | method | weighting | wall (s) | CPU (s) | stamps/s | peak mem (MiB) "
              "| flux / true | expected | flux_err | loss vs truth |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        rows = [(False, "mean", "sigma2"), ("fourier", "mean", "sigma2"), ("spline", "mean", "sigma2"),
                (False, "median", "none"), ("fourier", "median", "none"), (False, "mean", "none")]
        for sub, method, wt in rows:
            t, mem, res, cpu = timed(lambda s=sub, m=method, w=wt: stack_images(
                info, pos, stamp_size=args.stamp, method=m, weighting=w, subpixel=s), args.repeat)
            # exact expectation for these positions: the beam at each one's sub-pixel offset
            fx, fy = res.cube.frac_x.values, res.cube.frac_y.values
            expect = 1.0 if sub else float(np.mean(np.exp(-4 * np.log(2) * (
                (fy * args.cell / BEAM[0]) ** 2 + (fx * args.cell / BEAM[1]) ** 2))))
            print(f"| {sub or 'nearest'} | {method} | {wt} | {t:.3f} | {cpu:.3f} | {args.n / t:,.0f} "
                  f"| {mem:.0f} | {res.flux_jy:.4f} | {expect:.4f} | {res.flux_err_jy:.1e} "
                  f"| {100 * (1 - res.flux_jy):+.2f} % |")
        # kernel-only timings
        print("\nkernels alone (best of repeats):")
        x, y = info.wcs.world_to_pixel_values(pos[:, 0], pos[:, 1])
        for sub in (False, "fourier", "spline"):
            t, _, _, _ = timed(lambda s=sub: kernels.align_stamps(info.data, x, y, args.stamp, s),
                               args.repeat)
            print(f"  align_stamps {sub or 'nearest'}: {t * 1e3:.1f} ms")
        st, _, _ = kernels.align_stamps(info.data, x, y, args.stamp, False)
        t, _, _, _ = timed(lambda: kernels.weighted_nanmean(st, np.ones(len(st))), args.repeat)
        print(f"  weighted_nanmean: {t * 1e3:.1f} ms")
        t, _, _, _ = timed(lambda: kernels.nanmedian_stack(st), args.repeat)
        print(f"  nanmedian_stack: {t * 1e3:.1f} ms")
        mask = kernels.central_mask(args.stamp, BEAM[0] / args.cell)
        t, _, _, _ = timed(lambda: kernels.local_sigma(st, mask), args.repeat)
        print(f"  local_sigma: {t * 1e3:.1f} ms")

        noise_table(Path(d), args)


def noise_table(d: Path, args: argparse.Namespace, noise: float = 0.01) -> None:
    """sigma_k estimator x noise stamp: time, and accuracy against the known noise.

    The image has, beside every other target, a 0.2 Jy/beam point (20 sigma) 8 pixels east
    of it, as CLEAN leaves near bright sources. Accuracy: the median of sigma_k / sigma_true
    over the targets without one (bias) and its relative scatter (precision), the same median
    beside a residual over that without, and the noise of the weighted stack with these
    weights over that of the optimal (here equal) weights, sqrt(sum W^2) / sum W x sqrt(N):
    the signal-to-noise the weights lose.
    """
    path = d / "resid.fits"
    pos = make_image(path, args.size, args.n, args.cell, seed=2, residual_jy=0.2)
    info = read_image(path)
    near = np.arange(len(pos)) % 2 == 0
    print(f"\n# local noise sigma_k: {args.n} targets, {args.stamp}-pixel stamps, noise "
          f"{noise} Jy/beam, a 0.2 Jy/beam residual 8 pixels from every other target")
    print("| estimator | sigma_k stamp (px) | wall (s) | CPU (s) | sigma/true, clean | scatter "
          "| sigma/true, beside a residual | S/N lost by the weights | flux / true |")
    print("|---|---|---|---|---|---|---|---|---|")
    for est in ("std", "mad", "clipped"):
        for size in (args.stamp, None):
            t, _, res, cpu = timed(lambda e=est, z=size: stack_images(
                info, pos, stamp_size=args.stamp, noise_estimator=e, noise_stamp_size=z),
                args.repeat)
            r = res.cube.sigma.values / noise
            w = res.cube.weight.values
            loss = np.sqrt(np.sum(w**2)) / np.sum(w) * np.sqrt(w.size) - 1.0
            label = f"{res.noise_stamp_size}" + (" (~300 beams)" if size is None else "")
            print(f"| {est} | {label} | {t:.3f} | {cpu:.3f} | {np.median(r[~near]):.4f} "
                  f"| {np.std(r[~near]) / np.median(r[~near]):.4f} | {np.median(r[near]):.3f} "
                  f"| {100 * loss:.1f} % | {res.flux_jy:.4f} |")


if __name__ == "__main__":
    main()
