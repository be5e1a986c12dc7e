"""Benchmark of uv-stacking: time, throughput, accuracy and peak memory, in one run.

The headline case is the paper's full-size type-6 data set: VLA A (27 antennas, 351
baselines), 3384 integrations of 10 s, 10 channels of 25 MHz at 1.4 GHz, 2 polarizations
(2.4e7 visibilities), 900 positions in a 30' x 30' field. STACKER (the paper's code) needed
292 s on 6 CPU cores and 9.1 s on a GPU for it.

Sections (all in one run, same machine state):

1. end-to-end ``xstack.uvstack.stack.stack_uv`` (flux pass over the lazy dask graph);
2. the phasor kernel alone per engine and precision (numba float64 = production per row,
   the antenna-factorised kernel (``engine="antenna"``, the ``auto`` choice), numba with
   float32 phases, plain numpy reference measured on a slice and extrapolated, ducc0 type-3
   NUFFT where its grid fits), with the phase/phasor error against an extended-precision
   (long double) truth on a subset of rows;
3. time vs number of positions (10 ... 1e5) and vs number of visibilities;
4. the channel-recurrence error vs re-seeding interval.

Usage: ``python benchmarks/bench_uvstack.py [--scale F] [--markdown OUT.md]``; ``--scale``
shrinks the number of integrations (1 = full size).
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from xstack.coords import SPEED_OF_LIGHT, lm_to_radec, radec_to_lmn
from xstack.uvstack import kernels as K

CENTER = (np.radians(15 * (3 + 49 / 60 + 10.99 / 3600)), np.radians(-30.0))
LINES: list[str] = []


def out(line: str = "") -> None:
    print(line, flush=True)
    LINES.append(line)


def timed(fn, *args, repeat: int = 1, **kw):
    best = np.inf
    result = None
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn(*args, **kw)
        best = min(best, time.perf_counter() - t0)
    return best, result


CPU: dict[str, float] = {}


def traced_peak(fn, *args, **kw):
    """Wall time, python-allocation peak (tracemalloc) and result; CPU seconds in CPU['last']."""
    tracemalloc.start()
    t0 = time.perf_counter()
    c0 = time.process_time()
    result = fn(*args, **kw)
    dt = time.perf_counter() - t0
    CPU["last"] = time.process_time() - c0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return dt, peak, result


def vla_uvw(n_time: int, config: str = "vla.a", dec=CENTER[1], ra=CENTER[0], dt=10.0):
    from xstack.schema import baseline_pairs
    from xstack.sim.arrays import baseline_uvw, packaged_array

    arr = packaged_array(config)
    a1, a2 = baseline_pairs(arr.n_antennas)
    # transit at the middle of the track: MJD seconds chosen so the hour angle spans +-4.7 h
    t = 5.0e9 + dt * np.arange(n_time)
    return baseline_uvw(arr.positions, a1, a2, t, ra, dec), arr, a1, a2, t


def positions(n: int, half_width_rad: float, rng) -> tuple[np.ndarray, ...]:
    l = rng.uniform(-half_width_rad, half_width_rad, n)
    m = rng.uniform(-half_width_rad, half_width_rad, n)
    ra, dec = lm_to_radec(l, m, *CENTER)
    return ra, dec


def truth_phasor(uvw, freq, l, m, n1, coef):
    """Extended-precision phases (long double turns), exact reduction, float64 exp."""
    lmn = np.stack([l, m, n1]).astype(np.longdouble)
    d = uvw.astype(np.longdouble) @ lmn  # (rows, nsrc)
    outp = np.empty((uvw.shape[0], len(freq)), dtype=np.complex128)
    for c, nu in enumerate(freq):
        turns = d * (np.longdouble(nu) / np.longdouble(SPEED_OF_LIGHT))
        frac = (turns - np.round(turns)).astype(np.float64)
        outp[:, c] = np.exp(-2j * np.pi * frac) @ coef[:, c]
    return outp


def type6_data(n_time: int, n_pos: int, rng):
    """The paper's type-6 layout with unit noise: (dataset, tree, catalog, uvw, a1, a2, ...)."""
    import xarray as xr
    from astropy.table import Table

    from xstack.schema import new_partition

    uvw, arr, a1, a2, t = vla_uvw(n_time)
    nbl = a1.size
    freq = 1.4e9 + 25e6 * np.arange(10)
    shape = (n_time, nbl, 10, 2)
    vis = (rng.standard_normal(shape, dtype=np.float32)
           + 1j * rng.standard_normal(shape, dtype=np.float32)).astype(np.complex64)
    ds = new_partition(visibility=vis, weight=np.ones(shape, np.float32),
                       flag=np.zeros(shape, bool), uvw=uvw, time=t, antenna1=a1, antenna2=a2,
                       antenna_names=arr.names, antenna_positions=arr.positions,
                       dish_diameters=arr.diameters, frequency=freq,
                       channel_width=np.full(10, 25e6), polarization=["RR", "LL"],
                       phase_center=CENTER, telescope_name="VLA",
                       # noise at channel centers, like the paper's type 6: nothing to
                       # un-smear (the smearing correction has its own benchmark)
                       attrs={"smearing": {"bandwidth": False, "time": False}})
    tree = xr.DataTree.from_dict({"spw0_field0": ds})
    ra, dec = positions(n_pos, np.radians(15 / 60), rng)
    cat = Table({"ra": np.degrees(ra), "dec": np.degrees(dec)})
    nvis = int(np.prod(shape))
    out(f"data: {n_time} integrations x {nbl} baselines x 10 channels x 2 pols = {nvis:.3e} "
        f"visibilities ({vis.nbytes / 2**20:.0f} MiB complex64), {n_pos} positions, "
        f"{nbl * n_time * n_pos:.3e} (row, position) pairs")
    return ds, tree, cat, uvw, a1, a2, freq, ra, dec, nvis


def section_empirical(n_time: int, n_pos: int, rng, repeat: int = 3) -> None:
    """Flux pass with and without the measured-noise sums (``flux_err_empirical_jy``),
    interleaved in the same run: what measuring the noise in the flux's pass costs."""
    import xarray as xr

    from xstack.uvstack import stack as S

    ds, tree, cat, *_ = type6_data(n_time, n_pos, rng)
    small = xr.DataTree.from_dict({"spw0_field0": ds.isel(time=slice(0, 2))})
    S.stack_uv(small, cat)  # JIT warm-up (both paths)
    S._EMPIRICAL_SUMS = False
    S.stack_uv(small, cat)
    out("")
    out("| flux pass (engine auto) | run | wall [s] | CPU [s] | flux_err_jy | "
        "flux_err_empirical_jy |")
    out("|---|---|---|---|---|---|")
    times: dict[bool, list[float]] = {True: [], False: []}
    cpus: dict[bool, list[float]] = {True: [], False: []}
    for i in range(repeat):
        for emp in (False, True):
            S._EMPIRICAL_SUMS = emp
            dt, _, res = traced_peak(S.uvstack, tree, cat, weighting="pb")
            times[emp].append(dt)
            cpus[emp].append(CPU["last"])
            label = "with measured noise" if emp else "without (weights only)"
            out(f"| {label} | {i + 1} | {dt:.2f} | {CPU['last']:.2f} | {res.flux_err_jy:.4g} | "
                f"{res.flux_err_empirical_jy:.4g} |")
    S._EMPIRICAL_SUMS = True
    best = {k: min(v) for k, v in times.items()}
    out(f"best of {repeat}: {best[False]:.2f} s without, {best[True]:.2f} s with the measured "
        f"noise (+{100 * (best[True] / best[False] - 1):.0f} %); CPU best "
        f"{min(cpus[False]):.2f} vs {min(cpus[True]):.2f} s")


def section_end_to_end(n_time: int, n_pos: int, rng) -> dict:
    import xarray as xr

    from xstack.uvstack.stack import stack_uv

    ds, tree, cat, uvw, a1, a2, freq, ra, dec, nvis = type6_data(n_time, n_pos, rng)
    small = xr.DataTree.from_dict({"spw0_field0": ds.isel(time=slice(0, 2))})
    for engine in ("numba", "antenna"):  # JIT warm-up
        stack_uv(small, cat, engine=engine)
    out("")
    out("| stage | engine asked (ran) | wall [s] | CPU [s] (all threads) | throughput [vis/s wall] "
        "| python peak alloc [MiB] |")
    out("|---|---|---|---|---|---|")
    flux = {}
    for engine in ("numba", "auto"):
        dt, peak, res = traced_peak(stack_uv, tree, cat, weighting="pb", engine=engine)
        flux[engine] = res.flux_jy
        out(f"| stack_uv() end to end (flux pass, float64) | {engine} ({res.options['engine']}) | "
            f"{dt:.2f} | {CPU['last']:.2f} | {nvis / dt:.3e} | {peak / 2**20:.0f} |")
        with tempfile.TemporaryDirectory() as tmp:
            # the CLI always writes the stacked store: written in the flux's own pass
            dtw, peakw, resw = traced_peak(stack_uv, tree, cat, weighting="pb", engine=engine,
                                           out=Path(tmp) / "s.zarr")
            assert abs(resw.flux_jy - res.flux_jy) <= 1e-12 * abs(res.flux_jy)
        out(f"| stack_uv(out=...) end to end (stacked store written + flux, one pass) | {engine} "
            f"({resw.options['engine']}) | {dtw:.2f} | {CPU['last']:.2f} | {nvis / dtw:.3e} | "
            f"{peakw / 2**20:.0f} |")
    out(f"flux numba {flux['numba']:.15e}, auto {flux['auto']:.15e} Jy (relative difference "
        f"{abs(flux['auto'] - flux['numba']) / abs(flux['numba']):.1e})")
    return {"uvw": uvw.reshape(-1, 3), "freq": freq, "ra": ra, "dec": dec, "nvis": nvis,
            "e2e": dt, "flux": res.flux_jy, "ds": ds, "a1": a1, "a2": a2}


def section_kernels(uvw, freq, ra, dec, rng, nvis, a1, a2) -> None:
    l, m, n, n1 = radec_to_lmn(ra, dec, *CENTER)
    w = np.ones(l.size)
    ia = np.ones((l.size, freq.size))
    coef = K.normalised_coefficients(w, ia, freq.size)
    nrow = uvw.shape[0]
    npol = 2
    sub = rng.choice(nrow, size=min(nrow, 400), replace=False)
    truth = truth_phasor(uvw[sub], freq, l, m, n1, coef)
    rows = []
    # numba float64 (production)
    dt, peak, ph = traced_peak(K.stack_phasor, uvw, freq, l, m, n1, w, ia)
    err64 = np.max(np.abs(ph[sub] - truth))
    rows.append(("numba, float64 phases (default)", dt, peak, err64,
                 f"CPU {CPU['last']:.1f} s"))
    del ph
    # antenna-factorised kernel (engine="antenna"; "auto" where the UVW factorise)
    K.phasor_antenna(uvw[:10 * a1.size], freq, l, m, n1, coef, a1, a2)  # JIT warm-up
    dta, peaka, (pha, bound) = traced_peak(K.phasor_antenna, uvw, freq, l, m, n1, coef, a1, a2)
    erra = np.max(np.abs(pha[sub] - truth))
    rows.append(("antenna-factorised, float64 phases (auto)", dta, peaka, erra,
                 f"CPU {CPU['last']:.1f} s; factorisation bound {bound:.1e} rad"))
    del pha
    # numba float32 phases
    args32 = [x.astype(np.float32) for x in (uvw, freq, l, m, n1)]
    K.stack_phasor(args32[0][:10], *args32[1:], w, ia)
    dt32, peak32, ph32 = traced_peak(K.stack_phasor, *args32, w, ia)
    err32 = np.max(np.abs(ph32[sub] - truth))
    rows.append(("numba, float32 phases", dt32, peak32, err32, f"CPU {CPU['last']:.1f} s"))
    del ph32
    # plain numpy on a slice, extrapolated
    nslice = max(1, nrow // 100)
    dtn, peakn, phn = traced_peak(K.stack_phasor_numpy, uvw[:nslice], freq, l, m, n1, coef)
    errn = np.max(np.abs(K.stack_phasor_numpy(uvw[sub], freq, l, m, n1, coef) - truth))
    rows.append(("plain numpy (reference)", dtn * nrow / nslice, peakn, errn,
                 f"measured on {nslice} rows, extrapolated"))
    # nufft: only where the grid fits
    lmn = np.stack([l, m, n1], axis=1)
    cells = K.nufft_grid_cells(uvw, freq, lmn)
    rows.append(("ducc0 type-3 NUFFT (eps 1e-12)", np.nan, np.nan, np.nan,
                 f"refused: needs a {cells * 16 / 2**30:.0f} GiB grid for VLA-A x 30' field"))
    out("")
    out("Phasor kernel alone (all rows, 10 channels; error = max |P - P_true| against long-double "
        "phases on 400 random rows; |P| <= 1):")
    out("")
    out("| engine / precision | time [s] | vis/s (x2 pols) | python peak alloc [MiB] | max error | note |")
    out("|---|---|---|---|---|---|")
    for name, dt_, pk, err, note in rows:
        tput = f"{nvis / dt_:.3e}" if np.isfinite(dt_) else "-"
        tstr = f"{dt_:.2f}" if np.isfinite(dt_) else "-"
        pstr = f"{pk / 2**20:.0f}" if np.isfinite(pk) else "-"
        estr = f"{err:.1e}" if np.isfinite(err) else "-"
        out(f"| {name} | {tstr} | {tput} | {pstr} | {estr} | {note} |")
    del npol


def section_scaling(rng) -> None:
    out("")
    out("Time vs number of positions (VLA A, 1.4 GHz, 30' field; 3510 rows = 10 integrations "
        "x 351 baselines, 10 channels), and a compact ALMA case (cycle 1 config 1, 230 GHz, "
        "100'' field) where the NUFFT grid is small. numpy is extrapolated above 1e3 positions.")
    out("")
    out("| array | positions | numba f64 [s] | numba f32 [s] | numpy [s] | nufft [s] | "
        "err f64 | err f32 | err nufft |")
    out("|---|---|---|---|---|---|---|---|---|")
    for label, config, freq0, half in (("VLA A", "vla.a", 1.4e9, np.radians(15 / 60)),
                                       ("ALMA c1.1", "alma.cycle1.1", 230e9, np.radians(50 / 3600))):
        uvw, *_ = vla_uvw(10, config)
        uvw = uvw.reshape(-1, 3)
        freq = freq0 + (25e6 if freq0 < 1e10 else 40e6) * np.arange(10)
        for npos in (10, 100, 1000, 10_000, 100_000):
            ra, dec = positions(npos, half, rng)
            l, m, n, n1 = radec_to_lmn(ra, dec, *CENTER)
            w = np.ones(npos)
            ia = np.ones((npos, freq.size))
            coef = K.normalised_coefficients(w, ia, freq.size)
            sub = np.arange(0, uvw.shape[0], max(1, uvw.shape[0] // 40))
            truth = truth_phasor(uvw[sub], freq, l, m, n1, coef) if npos <= 10_000 else None
            t64, p64 = timed(K.stack_phasor, uvw, freq, l, m, n1, w, ia)
            a32 = [x.astype(np.float32) for x in (uvw, freq, l, m, n1)]
            t32, p32 = timed(K.stack_phasor, *a32, w, ia)
            if npos <= 1000:
                tn, _ = timed(K.stack_phasor_numpy, uvw, freq, l, m, n1, coef)
                tn_s = f"{tn:.3f}"
            else:
                tn, _ = timed(K.stack_phasor_numpy, uvw[:20], freq, l, m, n1, coef)
                tn_s = f"~{tn * uvw.shape[0] / 20:.1f}"
            try:
                tf, pf = timed(K.stack_phasor_nufft, uvw, freq, l, m, n1, coef, epsilon=1e-12)
                tf_s = f"{tf:.3f}"
            except MemoryError:
                tf_s, pf = "refused (grid)", None

            def e(p, truth=truth, sub=sub):
                if truth is None or p is None:
                    return "-"
                return f"{np.max(np.abs(p[sub] - truth)):.1e}"

            out(f"| {label} | {npos} | {t64:.3f} | {t32:.3f} | {tn_s} | {tf_s} | {e(p64)} | "
                f"{e(p32)} | {e(pf)} |")
    out("")
    out("Time vs number of visibilities (VLA A, 900 positions, numba float64):")
    out("")
    out("| integrations | rows | visibilities (2 pols) | time [s] | vis/s |")
    out("|---|---|---|---|---|")
    freq = 1.4e9 + 25e6 * np.arange(10)
    ra, dec = positions(900, np.radians(15 / 60), rng)
    l, m, n, n1 = radec_to_lmn(ra, dec, *CENTER)
    for nt in (10, 100, 1000):
        uvw, *_ = vla_uvw(nt)
        uvw = uvw.reshape(-1, 3)
        t, _ = timed(K.stack_phasor, uvw, freq, l, m, n1, np.ones(900), np.ones((900, 10)))
        nv = uvw.shape[0] * 10 * 2
        out(f"| {nt} | {uvw.shape[0]} | {nv:.2e} | {t:.3f} | {nv / t:.3e} |")


def section_recurrence(rng) -> None:
    out("")
    out("Channel recurrence error (64 evenly spaced channels, VLA A rows, 50 positions over a "
        "2 deg field; error = max |P_reseed - P_reseed=1|, i.e. on top of the exact per-channel "
        "float64 evaluation):")
    out("")
    out("| reseed every | max error | time [s] |")
    out("|---|---|---|")
    uvw, *_ = vla_uvw(20)
    uvw = uvw.reshape(-1, 3)
    freq = 1.0e9 + 16e6 * np.arange(64)
    ra, dec = positions(50, np.radians(1.0), rng)
    l, m, n, n1 = radec_to_lmn(ra, dec, *CENTER)
    w, ia = np.ones(50), np.ones((50, 64))
    t1, exact = timed(K.stack_phasor, uvw, freq, l, m, n1, w, ia, reseed=1)
    out(f"| 1 (exact seeds) | 0 | {t1:.3f} |")
    for r in (4, 16, 64):
        t, p = timed(K.stack_phasor, uvw, freq, l, m, n1, w, ia, reseed=r)
        out(f"| {r} | {np.max(np.abs(p - exact)):.1e} | {t:.3f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scale", type=float, default=1.0, help="fraction of the 3384 integrations")
    ap.add_argument("--positions", type=int, default=900)
    ap.add_argument("--markdown", default=None, help="also write the tables to this file")
    ap.add_argument("--skip-scaling", action="store_true")
    ap.add_argument("--only-e2e", action="store_true", help="only the end-to-end headline run")
    ap.add_argument("--empirical", action="store_true",
                    help="only the flux pass with and without the measured-noise sums "
                         "(flux_err_empirical_jy), interleaved, best of 3")
    args = ap.parse_args()
    rng = np.random.default_rng(2015)
    n_time = max(2, int(round(3384 * args.scale)))
    out(f"load average at start: {os.getloadavg()[0]:.1f}")
    out(f"machine: {platform.machine()}, {os.cpu_count()} cores, "
        f"{os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES') / 2**30:.0f} GiB; "
        f"python {platform.python_version()}; numba threads {K.numba.get_num_threads()}; "
        "other work was running on the machine at the same time")
    out("")
    if args.empirical:
        section_empirical(n_time, args.positions, rng)
        out(f"load average at end: {os.getloadavg()[0]:.1f}")
        if args.markdown:
            with open(args.markdown, "w") as fh:
                fh.write("\n".join(LINES) + "\n")
        return
    e2e = section_end_to_end(n_time, args.positions, rng)
    if args.only_e2e:
        out(f"load average at end: {os.getloadavg()[0]:.1f}")
        return
    section_kernels(e2e["uvw"], e2e["freq"], e2e["ra"], e2e["dec"], rng, e2e["nvis"], e2e["a1"],
                    e2e["a2"])
    del e2e
    if not args.skip_scaling:
        section_scaling(rng)
        section_recurrence(rng)
    out("")
    out(f"load average at end: {os.getloadavg()[0]:.1f}")
    out(f"process peak RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")
    if args.markdown:
        with open(args.markdown, "w") as fh:
            fh.write("\n".join(LINES) + "\n")


if __name__ == "__main__":
    main()
