"""Benchmark of image-stacking: 900 stamps of 64 x 64 from a 4000 x 4000 image.

Prints a Markdown table (time, throughput, peak memory, accuracy) for nearest-pixel and
sub-pixel (Fourier, spline) alignment, mean and median, measured in the same run; then a
second table for the local-noise estimator and the stamp sigma_k is measured on; a third
for sigma_k of a primary-beam corrected image measured on image x A ("flattened") or on the
image itself, for a wide and a narrow beam (the time it costs to evaluate a model beam on
every pixel beside the bias it removes).

    python benchmarks/bench_imstack.py [--size 4000] [--n 900] [--stamp 64] [--repeat 3]
                                       [--only align|noise|flat]

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
    ap.add_argument("--only", choices=("align", "noise", "flat"), default=None,
                    help="print only one of the three tables")
    args = ap.parse_args()
    if args.only in ("noise", "flat"):
        print(f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}")
        with tempfile.TemporaryDirectory() as d:
            (noise_table if args.only == "noise" else flat_table)(Path(d), args)
        return
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

        if args.only is None:
            noise_table(Path(d), args)
            flat_table(Path(d), args)


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


def flat_table(d: Path, args: argparse.Namespace, noise: float = 0.01,
               freq_hz: float = 1.4e9) -> None:
    """sigma_k of a corrected image, flattened (image x A) or not: time and accuracy.

    The image is white noise of ``noise`` divided by a Gaussian primary beam A (blanked below
    the cutoff 0.1), centered on the image, once wide (FWHM = half the image) and once narrow
    (FWHM = 1.5 sigma_k stamps, like an ALMA 12 m pointing at 230 GHz imaged with a 1"
    beam); targets on rings out to A = 0.3. The truth is noise / A_k. Rows: the beam as a
    model (``primary_beam=``; evaluated on the noise stamps' pixels only), the beam as an
    array on the image grid (no evaluation), and no beam (``primary_beam="none"``: the
    corrected map's own spread, as before). beam_on_grid times the model's evaluation alone (CPU),
    on every pixel (as at first) and on the stamps' footprint (the default).
    """
    from xstack.beams import PrimaryBeam
    from xstack.coords import SPEED_OF_LIGHT
    from xstack.imstack.io import beam_on_grid, image_beam

    size, cell = args.size, args.cell
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---SIN", "DEC--SIN"]
    w.wcs.crval = [57.2957917, -30.0]
    w.wcs.crpix = [size // 2 + 1, size // 2 + 1]
    w.wcs.cdelt = [-cell / 3600, cell / 3600]
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    r_pix = np.hypot(xx - size // 2, yy - size // 2) * (cell / 3600 * np.pi / 180)
    del xx, yy
    stamp_px = kernels.noise_stamp_size(BEAM[:2], cell, cell, BEAM[0], size)
    print(f"\n# sigma_k of a corrected image (noise {noise} / A), {size}x{size}, sigma_k "
          f"stamps of {stamp_px} px; truth noise / A_k")
    print("| beam FWHM | A from | flattened | beam_on_grid: every pixel (CPU s) "
          "| beam_on_grid: footprint (CPU s) | footprint / image | stack wall (s) | CPU (s) "
          "| sigma/true, median | worst | at A < 0.5 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    rng = np.random.default_rng(3)
    for label, fwhm_arcsec in (("wide", size * cell / 2), ("narrow", 1.5 * stamp_px * cell)):
        dish = 1.13 * SPEED_OF_LIGHT / (freq_hz * np.radians(fwhm_arcsec / 3600))
        pb = PrimaryBeam("gaussian", float(dish), cutoff=0.1)
        a_pix = pb(r_pix, freq_hz).astype(np.float32)
        with np.errstate(divide="ignore", over="ignore"):   # A underflows far out: blanked
            img = rng.normal(0.0, noise, (size, size)).astype(np.float32) / a_pix
        img[a_pix < 0.1] = np.nan
        h = w.to_header()
        h["BMAJ"], h["BMIN"], h["BPA"], h["BUNIT"] = BEAM[0] / 3600, BEAM[1] / 3600, BEAM[2], "Jy/beam"
        h["XSPBCOR"] = True
        h["NAXIS"] = 3
        h["CTYPE3"], h["CRVAL3"], h["CDELT3"], h["CRPIX3"], h["CUNIT3"] = "FREQ", freq_hz, 1e6, 1.0, "Hz"
        path = d / f"corrected_{label}.fits"
        fits.PrimaryHDU(img[None], header=h).writeto(path, overwrite=True)
        del img
        info = read_image(path)
        # targets on rings from the center out to A = 0.3 (Gaussian: r = FWHM sqrt(ln(1/A)/4ln2))
        r_max = fwhm_arcsec * np.sqrt(np.log(1 / 0.3) / (4 * np.log(2)))
        rad = np.sqrt(rng.uniform(0, 1, args.n)) * r_max / 3600
        ang = rng.uniform(0, 2 * np.pi, args.n)
        dec = -30.0 + rad * np.cos(ang)
        ra = 57.2957917 + rad * np.sin(ang) / np.cos(np.radians(-30.0))
        pos = np.c_[ra, dec]
        px, py = w.world_to_pixel_values(ra, dec)
        theta = np.hypot(px - size // 2, py - size // 2) * (cell / 3600 * np.pi / 180)
        a_k = pb(theta, freq_hz)
        truth = noise / a_k
        conv = image_beam(info, pb, image_corrected=True)
        foot = kernels.stamp_footprint(info.shape, px, py, stamp_px)
        _, _, whole, t_all = timed(lambda c=conv, i=info: beam_on_grid(c, i), 1)
        _, _, part, t_foot = timed(lambda c=conv, i=info, f=foot: beam_on_grid(c, i, f), 1)
        if not np.array_equal(part[foot], whole[foot], equal_nan=True):
            raise AssertionError("the footprint's beam differs from the whole grid's")
        del whole, part
        for source, beam_arg in (("model", pb), ("array on the grid", a_pix.astype(np.float64)),
                                 ("none", "none")):
            t, _, res, cpu = timed(lambda b=beam_arg, i=info, p=pos: stack_images(
                i, p, stamp_size=args.stamp, primary_beam=b, image_corrected=True),
                args.repeat)
            order = np.argsort(res.cube.position.values)
            r = res.cube.sigma.values[order] / truth[res.cube.position.values[order]]
            low = a_k[res.cube.position.values[order]] < 0.5
            model = source == "model"
            print(f"| {fwhm_arcsec:.0f}\" ({label}) | {source} | {res.noise_flattened} "
                  f"| {t_all if model else 0:.2f} | {t_foot if model else 0:.2f} "
                  f"| {foot.mean() if model else float('nan'):.3f} | {t:.2f} | {cpu:.2f} "
                  f"| {np.median(r):.4f} | {r[np.argmax(np.abs(r - 1))]:.3f} "
                  f"| {np.median(r[low]) if low.any() else float('nan'):.3f} |")


if __name__ == "__main__":
    main()
