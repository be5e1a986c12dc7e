"""Imaging benchmarks: gridder accuracy vs time, a 4000 x 4000 image, CLEAN time vs components.

Run ``python benchmarks/bench_imaging.py [--time-step S] [--skip-big]``; prints Markdown tables.

1. Accuracy of ducc0 (``vis2dirty`` via :func:`xstack.imaging.image.grid_visibilities`) against
   an independent direct Fourier sum (small case), and time vs epsilon on a larger case.
2. Paper type 3 geometry: VLA A, 1.4 GHz, 10 channels, 9.4 h, 4000 x 4000 pixels of 0.45"
   (30' field), dirty image + PSF with w-term, streamed from an in-memory partition in
   ~128 MB chunks.
3. CLEAN (image plane, Högbom vs Clark) time vs number of components.
4. ``--clark-update``: one Clark residual update at 4000 x 4000, scipy's ``fftconvolve`` (as
   before) against :class:`xstack.imaging.clean.PsfConvolver` (the PSF's transform kept).
5. ``--only reproducible``: reproducible (one thread per gridding and prediction, the
   default) against threaded ducc0 (``reproducible=False``, ``xstack image
   --threaded-gridding``): time of the dirty image + PSF and of a major/minor-cycle CLEAN of
   the type-3 bright sources, each run twice, and whether the second run gave the same bits.
6. ``--only cluster``: the same scene written to a zarr store and imaged and CLEANed from it
   locally (dask's threaded scheduler) and on a 2-process ``LocalCluster`` (1 thread each):
   time of each, the cluster's planning pass (a task per chunk counting its visibilities, so
   that the cluster cuts the local path's batches) and whether the two give the same bits.
"""

from __future__ import annotations

import argparse
import math
import resource
import time

import numpy as np

from xstack.imaging import kernels
from xstack.imaging.clean import clean
from xstack.imaging.image import grid_visibilities, make_image

ARCSEC = math.pi / 180 / 3600
FIELD = (math.radians(57.29579), math.radians(-30.0))  # 3h49m10.99s, -30 deg


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def vla_uvw(n_time: int, hours: float = 9.4) -> tuple[np.ndarray, np.ndarray, np.ndarray, object]:
    from xstack.schema import baseline_pairs
    from xstack.sim.arrays import baseline_uvw, packaged_array, time_of_hour_angle

    arr = packaged_array("vla.a")
    a1, a2 = baseline_pairs(arr.n_antennas)
    t0 = time_of_hour_angle(-hours / 2 * 15 * math.pi / 180, FIELD[0],
                            math.atan2(arr.site[1], arr.site[0]), 60000.0)
    times = t0 + np.linspace(0, hours * 3600, n_time)
    return baseline_uvw(arr.positions, a1, a2, times, *FIELD), a1, a2, (arr, times)


def bench_accuracy(rows: list[str]) -> None:
    rng = np.random.default_rng(1)
    uvw = vla_uvw(24)[0].reshape(-1, 3)[::3]
    freq = np.linspace(1.3e9, 1.5e9, 4)
    vis = rng.normal(size=(uvw.shape[0], 4)) + 1j * rng.normal(size=(uvw.shape[0], 4))
    wgt = np.ones(vis.shape)
    n, cell = 128, 2.0 * ARCSEC  # 4.3' field, w-term on
    t = time.perf_counter()
    ref = kernels.direct_dirty_image(uvw, freq, vis, wgt, n, n, cell)
    t_dft = time.perf_counter() - t
    rows.append(f"Direct Fourier sum reference: {uvw.shape[0]} rows x 4 channels, {n}x{n} pixels, "
                f"{t_dft:.1f} s.\n")
    rows.append("| epsilon | max error / max abs (vs DFT) | ducc0 time small (s) |")
    rows.append("|---|---|---|")
    for eps in (1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-8, 1e-10):
        t = time.perf_counter()
        img = grid_visibilities(uvw, freq, vis, wgt, n, n, cell, epsilon=eps)
        dt = time.perf_counter() - t
        err = np.max(np.abs(img - ref)) / np.max(np.abs(ref))
        rows.append(f"| {eps:g} | {err:.2e} | {dt:.3f} |")


def bench_epsilon_time(rows: list[str], n_time: int) -> None:
    rng = np.random.default_rng(2)
    uvw = vla_uvw(n_time)[0].reshape(-1, 3)
    freq = 1.4e9 + 25e6 * np.arange(10) - 112.5e6
    vis = (rng.normal(size=(uvw.shape[0], 10)) + 1j * rng.normal(size=(uvw.shape[0], 10)))
    wgt = np.ones(vis.shape)
    n, cell = 2048, 0.45 * ARCSEC
    ref = grid_visibilities(uvw, freq, vis, wgt, n, n, cell, epsilon=1e-10)
    rows.append(f"\n{uvw.shape[0] * 10 / 1e6:.1f} M visibilities (VLA A, 10 channels), {n}x{n} "
                "pixels of 0.45\", w-term; error vs epsilon=1e-10:\n")
    rows.append("| epsilon | precision | time (s) | Mvis/s | max error / max abs |")
    rows.append("|---|---|---|---|---|")
    for eps in (1e-2, 1e-4, 1e-5, 1e-6, 1e-8):
        t = time.perf_counter()
        img = grid_visibilities(uvw, freq, vis, wgt, n, n, cell, epsilon=eps)
        dt = time.perf_counter() - t
        err = np.max(np.abs(img - ref)) / np.max(np.abs(ref))
        prec = "single" if eps >= 1e-4 else "double"
        rows.append(f"| {eps:g} | {prec} | {dt:.2f} | {uvw.shape[0] * 10 / dt / 1e6:.1f} | {err:.1e} |")


def big_partition(time_step: float):
    from xstack.schema import new_partition

    n_time = int(round(9.4 * 3600 / time_step))
    uvw, a1, a2, (arr, times) = vla_uvw(n_time)
    freq = 1.4e9 - 112.5e6 + 25e6 * np.arange(10)
    shape = (n_time, a1.size, 10, 2)
    rng = np.random.default_rng(3)
    vis = np.empty(shape, dtype=np.complex64)
    vis.real = rng.standard_normal(shape, dtype=np.float32)
    vis.imag = rng.standard_normal(shape, dtype=np.float32)
    vis += 1.0  # a 1 Jy source at the phase center
    ds = new_partition(visibility=vis, weight=np.ones(shape, np.float32),
                       flag=np.zeros(shape, bool), uvw=uvw, time=times, antenna1=a1,
                       antenna2=a2, antenna_names=arr.names, antenna_positions=arr.positions,
                       dish_diameters=arr.diameters, frequency=freq,
                       channel_width=np.full(10, 25e6), polarization=["RR", "LL"],
                       phase_center=FIELD, telescope_name="VLA", integration_time=time_step)
    return ds


def bench_big(rows: list[str], time_step: float, size: int, epsilon: float) -> np.ndarray:
    t = time.perf_counter()
    ds = big_partition(time_step)
    t_build = time.perf_counter() - t
    nvis = ds.VISIBILITY.size
    t = time.perf_counter()
    res = make_image(ds, size=size, cell_arcsec=0.45, epsilon=epsilon)
    dt = time.perf_counter() - t
    rows.append(f"| {size}x{size} | {time_step:g} s | {nvis / 1e6:.1f} | {epsilon:g} | {dt:.1f} | "
                f"{res.image[size // 2, size // 2]:.4f} | {res.beam[0]:.2f}x{res.beam[1]:.2f} | "
                f"{peak_rss_mb():.0f} |")
    print(f"(built data in {t_build:.1f} s)")
    return res


def bench_clean(rows: list[str], size: int, psf: np.ndarray | None) -> None:
    rng = np.random.default_rng(4)
    if psf is None:
        psf = kernels.gaussian_image(size, size, 3.0, 2.5, 0.0)
    if psf.shape != (size, size):
        c = psf.shape[0] // 2
        psf = psf[c - size // 2:c + size // 2, c - size // 2:c + size // 2]
    from scipy.signal import fftconvolve

    truth = np.zeros((size, size))
    for _ in range(10):
        y, x = rng.integers(size // 4, 3 * size // 4, 2)
        truth[y, x] = rng.uniform(5e-3, 1e-2)  # paper type 3: 10 x 5-10 mJy
    dirty = fftconvolve(truth, psf, mode="same") + 1e-5 * rng.normal(size=truth.shape)
    for algorithm in ("hogbom", "clark"):
        for niter in (100, 1000):
            t = time.perf_counter()
            r = clean(dirty, psf, threshold=0.0, niter=niter, algorithm=algorithm)
            dt = time.perf_counter() - t
            rows.append(f"| {size}x{size} | {algorithm} | {r.n_components} | {dt:.2f} | "
                        f"{1e3 * dt / max(r.n_components, 1):.2f} |")


def _fftconvolve_update(delta: np.ndarray, psf: np.ndarray) -> np.ndarray:
    """Clark's residual update as xstack did it before the PSF transform was kept: scipy's
    ``fftconvolve`` of the components' bounding box with the PSF (three FFTs, one thread)."""
    from scipy.signal import fftconvolve

    ny, nx = delta.shape
    pcy, pcx = psf.shape[0] // 2, psf.shape[1] // 2
    ys, xs = np.nonzero(delta)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    full = fftconvolve(delta[y0:y1, x0:x1], psf, mode="full")
    out = np.zeros_like(delta)
    oy, ox = pcy - y0, pcx - x0
    ys0, ys1 = max(0, -oy), min(ny, full.shape[0] - oy)
    xs0, xs1 = max(0, -ox), min(nx, full.shape[1] - ox)
    out[ys0:ys1, xs0:xs1] = full[ys0 + oy:ys1 + oy, xs0 + ox:xs1 + ox]
    return out


def bench_clark_update(rows: list[str], size: int, repeats: int = 3) -> None:
    """Time of one Clark residual update (the PSF summed at a round's components) on a
    size x size image with a PSF of the same size: scipy fftconvolve of the bounding box
    against :class:`xstack.imaging.clean.PsfConvolver` (PSF transform kept, all cores)."""
    from xstack.imaging.clean import PsfConvolver

    rng = np.random.default_rng(7)
    psf = kernels.gaussian_image(size, size, 3.0, 2.5, 0.0) + 1e-3 * rng.normal(size=(size, size))
    for n_comp, spread in ((10, 0.1), (200, 0.8)):
        delta = np.zeros((size, size))
        lo, hi = int(size * (0.5 - spread / 2)), int(size * (0.5 + spread / 2))
        ys, xs = rng.integers(lo, hi, (2, n_comp))
        delta[ys, xs] = rng.uniform(1e-4, 1e-2, n_comp)
        t = time.perf_counter()
        conv = PsfConvolver(psf, delta.shape)
        t_setup = time.perf_counter() - t
        times = {}
        outs = {}
        for name, fn in (("fftconvolve", lambda d: _fftconvolve_update(d, psf)),
                         ("PsfConvolver", conv)):
            best = math.inf
            for _ in range(repeats):
                t = time.perf_counter()
                outs[name] = fn(delta)
                best = min(best, time.perf_counter() - t)
            times[name] = best
        err = np.abs(outs["PsfConvolver"] - outs["fftconvolve"]).max() / np.abs(
            outs["fftconvolve"]).max()
        rows.append(f"| {size}x{size} | {n_comp} in {spread:.0%} of the field | "
                    f"{times['fftconvolve']:.2f} | {times['PsfConvolver']:.2f} | {t_setup:.2f} | "
                    f"{times['fftconvolve'] / times['PsfConvolver']:.1f} | {err:.1e} |")


def _type3_bright(time_step: float, size: int):
    """The type-3 scene of :func:`bench_clean_data`: (partition, thermal noise, true flux)."""
    from xstack.coords import lm_to_radec, radec_to_lmn
    from xstack.sim.kernels import model_visibilities

    ds = big_partition(time_step)
    rng = np.random.default_rng(5)
    sigma = 10e-3
    vis = ds.VISIBILITY.values
    vis *= sigma
    vis -= sigma  # remove the 1 Jy source of big_partition (vis = sigma * (noise + 1))
    half = 0.4 * size * 0.45 * ARCSEC
    dl, dm = rng.uniform(-half, half, size=(2, 10))
    ra, dec = lm_to_radec(dl, dm, *FIELD)
    l, m, _, n1 = radec_to_lmn(ra, dec, *FIELD)
    flux = rng.uniform(5e-3, 10e-3, 10)
    model = model_visibilities(ds.UVW.values.reshape(-1, 3), ds.frequency.values, l, m, n1, flux)
    vis += model.reshape(vis.shape[:3])[..., None].astype(np.complex64)
    ds = ds.assign(VISIBILITY=(ds.VISIBILITY.dims, vis),
                   WEIGHT=(ds.WEIGHT.dims, np.full(vis.shape, 1 / sigma**2, np.float32)))
    return ds, sigma / math.sqrt(vis.size), float(flux.sum())


def bench_clean_data(rows: list[str], time_step: float, size: int, algorithm: str,
                     nsigma: float) -> None:
    """Paper type 3 bright sources (10 x 5-10 mJy, sigma = 10 mJy/vis): CLEAN to nsigma."""
    from xstack.imaging.clean import clean_data

    ds, thermal, total = _type3_bright(time_step, size)
    vis = ds.VISIBILITY
    t = time.perf_counter()
    result, cres = clean_data(ds, size=size, cell_arcsec=0.45, niter=5000, threshold=nsigma * thermal,
                              algorithm=algorithm, epsilon=1e-5)
    dt = time.perf_counter() - t
    rows.append(f"| {size}x{size} | {vis.size / 1e6:.1f} | {algorithm} | {nsigma:g} | {cres.n_components} | "
                f"{cres.n_major} | {dt:.0f} | {np.std(result.extra['dirty']) / thermal:.1f} | "
                f"{np.std(cres.residual) / thermal:.2f} | {cres.model.sum() / total:.3f} | "
                f"{peak_rss_mb():.0f} |")


def bench_reproducible(rows: list[str], time_step: float, size: int, nsigma: float,
                       epsilon: float) -> None:
    """Reproducible against threaded ducc0: time, and the same bits on a second run."""
    from xstack.imaging.clean import clean_data

    ds, thermal, total = _type3_bright(time_step, size)
    out: dict[bool, list] = {}
    for reproducible in (True, False):
        for _ in range(2):
            t = time.process_time(), time.perf_counter()
            img = make_image(ds, size=size, cell_arcsec=0.45, epsilon=epsilon,
                             reproducible=reproducible)
            t_img = time.process_time() - t[0], time.perf_counter() - t[1]
            t = time.process_time(), time.perf_counter()
            _, cres = clean_data(ds, size=size, cell_arcsec=0.45, niter=20000,
                                 threshold=nsigma * thermal, algorithm="clark", epsilon=epsilon,
                                 reproducible=reproducible)
            t_cl = time.process_time() - t[0], time.perf_counter() - t[1]
            out.setdefault(reproducible, []).append((img.image, cres, t_img, t_cl))
    ref = out[True][0][0]
    for reproducible, runs in out.items():
        (im1, c1, ti, tc), (im2, c2, ti2, tc2) = runs
        rows.append(
            f"| {'reproducible (default)' if reproducible else 'threaded'} | "
            f"{ds.VISIBILITY.size / 1e6:.1f} | {size} | {epsilon:g} | "
            f"{ti[1]:.1f} / {ti2[1]:.1f} | {tc[1]:.0f} / {tc2[1]:.0f} | {tc[0]:.0f} | "
            f"{c1.n_components} / {c2.n_components} | {c1.n_major} | "
            f"{'yes' if np.array_equal(im1, im2) else 'no'} | "
            f"{'yes' if np.array_equal(c1.model, c2.model) else 'no'} | "
            f"{np.abs(im1 - ref).max() / np.abs(ref).max():.1e} | "
            f"{c1.model.sum() / total:.4f} |")


def _task_span(stream: list[dict], prefix: str) -> tuple[int, float, float]:
    """Tasks of ``stream`` (``distributed.get_task_stream``) whose key starts with ``prefix``:
    (number, wall span from the first start to the last stop (s), summed compute time (s))."""
    spans = [ss for t in stream if str(t["key"]).startswith(prefix)
             for ss in t["startstops"] if ss["action"] == "compute"]
    if not spans:
        return 0, 0.0, 0.0
    tasks = {str(t["key"]) for t in stream if str(t["key"]).startswith(prefix)}
    return (len(tasks), max(s["stop"] for s in spans) - min(s["start"] for s in spans),
            sum(s["stop"] - s["start"] for s in spans))


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """The same shape, dtype and bytes (NaNs in the same places count as equal)."""
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def bench_cluster(rows: list[str], time_step: float, size: int, nsigma: float,
                  epsilon: float, chunk_times: int) -> None:
    """Local against a 2-process LocalCluster on a store: time, planning pass, same bits."""
    import tempfile
    from pathlib import Path

    from distributed import get_task_stream

    from xstack._cluster import use_cluster
    from xstack.imaging.clean import clean_data
    from xstack.imaging.image import COUNT_TASK, GRID_TASK
    from xstack.schema import write_store

    ds, thermal, total = _type3_bright(time_step, size)
    nvis = ds.VISIBILITY.size
    with tempfile.TemporaryDirectory(prefix="bench-imaging-cluster-") as tmp:
        store = Path(tmp) / "type3.zarr"
        write_store({"spw0_field0": ds.chunk({"time": chunk_times})}, store)
        n_chunks = -(-ds.sizes["time"] // chunk_times)
        del ds
        kw = dict(size=size, cell_arcsec=0.45, epsilon=epsilon)
        runs = {}
        for mode in ("local", "cluster"):
            with use_cluster(workers=2 if mode == "cluster" else None) as client:
                t = time.perf_counter()
                if client is not None:
                    with get_task_stream(client) as ts:
                        img = make_image(store, **kw)
                    stream = ts.data
                else:
                    img, stream = make_image(store, **kw), []
                t_img = time.perf_counter() - t
                t = time.perf_counter()
                _, cres = clean_data(store, niter=20000, threshold=nsigma * thermal,
                                     algorithm="clark", **kw)
                t_cl = time.perf_counter() - t
            n_count, plan_span, plan_cpu = _task_span(stream, COUNT_TASK)
            n_grid = _task_span(stream, f"{GRID_TASK}-dirty")[0]
            runs[mode] = (img, cres)
            ref_img, ref_cl = runs["local"]
            same_img = _same_bits(img.image, ref_img.image) and _same_bits(img.psf, ref_img.psf)
            same_model = (_same_bits(cres.model, ref_cl.model)
                          and _same_bits(cres.residual, ref_cl.residual))
            plan = (f"{plan_span:.1f} ({100 * plan_span / t_img:.0f} %; {n_count} tasks, "
                    f"{plan_cpu:.1f} s compute)" if n_count else "n/a")
            rows.append(
                f"| {mode} | {nvis / 1e6:.1f} | {n_chunks} | {n_grid or 'n/a'} | {size} | "
                f"{t_img:.1f} | {plan} | {t_cl:.0f} | {cres.n_components} | {cres.n_major} | "
                f"{'yes' if same_img else 'no'} | {'yes' if same_model else 'no'} | "
                f"{cres.model.sum() / total:.4f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--time-step", type=float, default=10.0,
                        help="integration time of the type-3 data set (paper: 10 s)")
    parser.add_argument("--size", type=int, default=4000)
    parser.add_argument("--skip-big", action="store_true")
    parser.add_argument("--clean-data", action="store_true",
                        help="only run the major/minor-cycle CLEAN of a type-3 scene")
    parser.add_argument("--algorithm", default="clark")
    parser.add_argument("--nsigma", type=float, default=5.0, help="CLEAN threshold / thermal")
    parser.add_argument("--clark-update", action="store_true",
                        help="only time Clark's residual update (old fftconvolve vs kept PSF "
                             "transform)")
    parser.add_argument("--only", choices=["reproducible", "cluster"], default=None,
                        help="reproducible: reproducible against threaded gridding; "
                             "cluster: a store imaged locally and on a LocalCluster")
    parser.add_argument("--chunk-times", type=int, default=400,
                        help="integrations per store chunk of --only cluster")
    parser.add_argument("--epsilon", type=float, default=1e-4,
                        help="gridder accuracy of --only reproducible (reproduce's 1e-4)")
    args = parser.parse_args()
    if args.only == "cluster":
        rows = ["## Local against a LocalCluster (type 3 bright sources from a store, Clark "
                "CLEAN)\n", "| scheduler | Mvis | chunks | gridding tasks | image "
                "| dirty + PSF (s) | planning (s) | CLEAN (s) | components | major cycles "
                "| same image bits | same model bits | CLEANed / true |",
                "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        bench_cluster(rows, args.time_step, args.size, args.nsigma, args.epsilon,
                      args.chunk_times)
        print("\n".join(rows))
        return
    if args.only == "reproducible":
        rows = ["## Reproducible against threaded gridding (type 3 bright sources, Clark CLEAN)"
                "\n", "| ducc0 | Mvis | image | epsilon | dirty + PSF, run 1 / 2 (s) "
                "| CLEAN, run 1 / 2 (s) | CLEAN CPU (s) | components, run 1 / 2 | major cycles "
                "| same image bits | same model bits | image vs reproducible / peak "
                "| CLEANed / true |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        bench_reproducible(rows, args.time_step, args.size, args.nsigma, args.epsilon)
        print("\n".join(rows))
        return
    if args.clark_update:
        rows = ["## Clark residual update: fftconvolve vs PsfConvolver\n",
                "| image | components | fftconvolve (s) | PsfConvolver (s) | its setup, once (s) "
                "| speed-up | max difference / max |", "|---|---|---|---|---|---|---|"]
        bench_clark_update(rows, args.size)
        print("\n".join(rows))
        return
    if args.clean_data:
        rows = ["## Major/minor-cycle CLEAN of paper type 3 bright sources\n",
                "| image | Mvis | algorithm | threshold (sigma) | components | major cycles | time (s) "
                "| dirty rms / thermal | residual rms / thermal | CLEANed flux / true | peak RSS (MB) |",
                "|---|---|---|---|---|---|---|---|---|---|---|"]
        bench_clean_data(rows, args.time_step, args.size, args.algorithm, args.nsigma)
        print("\n".join(rows))
        return
    rows: list[str] = ["## Gridder accuracy vs epsilon\n"]
    bench_accuracy(rows)
    bench_epsilon_time(rows, 180)
    print("\n".join(rows))
    rows = ["\n## Paper type 3 size: dirty image + PSF\n",
            "| image | integration | Mvis (both hands) | epsilon | time (s) | center (Jy/beam, true 1) "
            "| beam (\") | peak RSS (MB) |",
            "|---|---|---|---|---|---|---|---|"]
    psf = None
    if not args.skip_big:
        for eps in (1e-4, 1e-6):
            res = bench_big(rows, args.time_step, args.size, eps)
            psf = res.psf
            del res
    print("\n".join(rows))
    rows = ["\n## CLEAN (image plane) time vs components\n",
            "| image | algorithm | components | time (s) | ms / component |", "|---|---|---|---|---|"]
    bench_clean(rows, 1024, None if psf is None else psf)
    if psf is not None:
        bench_clean(rows, args.size, psf)
    print("\n".join(rows))
    print(f"\npeak RSS of the whole run: {peak_rss_mb():.0f} MB")


if __name__ == "__main__":
    main()
