"""Benchmark of the uv-domain line stack beside the continuum stack, and of regridding choices.

The headline case is the paper's type-6 data set with 256 channels: VLA A (27 antennas, 351
baselines), 3384 integrations of 10 s, 256 channels of 100 kHz at 1.30 GHz (HI at
z ~ 0.09; ~23 km/s channels), 2 polarizations (6.1e8 visibilities, 4.9 GB of complex64), and
1000 targets in a 30' field at redshifts whose lines fall in the band. A store is written
once (noise and the targets' Gaussian lines of 0.2 Jy km/s, sigma 50 km/s); then, each in a
fresh child process (same data, same machine state), ``xstack.stack_uv`` (continuum) and
``xstack.uvstack.line.stack_lines`` (20 km/s bins over +-600 km/s) with their wall and CPU
time and peak resident memory above the start (sampled every 5 ms). Goal: line <= 2x
continuum time.

Then the regridding choices on one target's spectrum (plain numpy, 1000 targets): exact
overlap lengths (what the stack uses), nearest bin of the channel centre, and linear
interpolation of the channel values at the bin centres; for each the error of the line
integral and of the width, and the time.

Usage::

    python benchmarks/bench_linestack.py [--scale F] [--workdir DIR] [--targets N]

``--scale`` shrinks the number of integrations (1 = full size; 0.002 runs in seconds).
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
import time
from pathlib import Path

import numpy as np
from scipy.special import erf

HI = 1_420_405_751.768
C_KMS = 299_792.458
CENTER_DEG = (15 * (3 + 49 / 60 + 10.99 / 3600), -30.0)
N_ANT, N_TIME, N_CHAN, FREQ0, DFREQ = 27, 3384, 256, 1.30e9, 100e3
LINE_FLUX, LINE_SIGMA = 0.2, 50.0

_CHILD = r"""
import json, os, sys, threading, time, warnings
import numpy as np
store, kind, cat_path = sys.argv[1:4]
import xstack
from astropy.table import Table
from xstack.schema import open_store
from xstack.uvstack.line import stack_lines
warnings.simplefilter("ignore")
page = os.sysconf("SC_PAGE_SIZE")
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * page / 2**20
tree = open_store(store)
cat = Table.read(cat_path, format="ascii.ecsv")
name = next(n for n in tree.children if "VISIBILITY" in tree[n].ds)
small = {name: tree[name].ds.isel(time=slice(0, 2))}
def run(data):
    if kind == "continuum":
        return xstack.stack_uv(data, cat, primary_beam="none", smearing="none")
    return stack_lines(data, cat, line_frequency="HI", velocity_resolution=20.0,
                       velocity_range=(-600, 600), primary_beam="none")
run(small)  # warm-up: imports and numba kernels loaded
peak, stop = [0.0], [False]
def sample():
    while not stop[0]:
        peak[0] = max(peak[0], rss())
        time.sleep(0.005)
base = rss()
th = threading.Thread(target=sample, daemon=True)
th.start()
t0, c0 = time.perf_counter(), time.process_time()
res = run(tree)
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
stop[0] = True
th.join()
vis = tree[name].ds["VISIBILITY"].data
extra = {}
if kind == "line":
    ok = np.isfinite(res.flux_jy)
    dv = 20.0
    win = ok & (np.abs(res.velocity_kms) < 150)
    extra = {"integral": float(np.sum(res.flux_jy[win]) * dv),
             "integral_err": float(dv * np.sqrt(res.flux_cov_jy2[np.ix_(win, win)].sum()))}
print(json.dumps({"wall": wall, "cpu": cpu, "base_mb": base, "peak_mb": peak[0],
                  "chunk_mb": vis.nbytes / vis.npartitions / 2**20, "n_chunks": vis.npartitions,
                  "n_vis": int(res.n_visibilities), **extra}))
"""


def make_store(path: Path, n_time: int, n_targets: int, seed: int = 6) -> Path:
    """A VLA-A-like partition (noise 1 Jy per visibility, plus the targets' lines), written
    chunk by chunk; the catalog beside it (``path.with_suffix('.ecsv')``)."""
    import dask.array as da
    from astropy.table import Table

    from xstack.coords import SPEED_OF_LIGHT, radec_to_lmn
    from xstack.schema import baseline_pairs, default_time_chunk, new_partition, write_store

    rng = np.random.default_rng(seed)
    ra0, dec0 = np.radians(CENTER_DEG)
    enu = np.column_stack([rng.uniform(-18e3, 18e3, (N_ANT, 2)), rng.normal(0, 5, N_ANT)])
    a1, a2 = baseline_pairs(N_ANT)
    b = enu[a2] - enu[a1]
    lat = np.radians(34.08)
    x = -np.sin(lat) * b[:, 1] + np.cos(lat) * b[:, 2]
    y = b[:, 0]
    z = np.cos(lat) * b[:, 1] + np.sin(lat) * b[:, 2]
    ha = np.linspace(-4, 4, n_time) * np.pi / 12
    sh, ch = np.sin(ha)[:, None], np.cos(ha)[:, None]
    sd, cd = np.sin(dec0), np.cos(dec0)
    uvw = np.stack([sh * x + ch * y, -sd * ch * x + sd * sh * y + cd * z,
                    cd * ch * x - cd * sh * y + sd * z], axis=-1)
    freq = FREQ0 + DFREQ * np.arange(N_CHAN)
    # targets in a 30' field, lines at least 700 km/s inside the band
    half = np.radians(0.25)
    ra = ra0 + rng.uniform(-half, half, n_targets) / np.cos(dec0)
    dec = dec0 + rng.uniform(-half, half, n_targets)
    margin = 700 / C_KMS
    nu_c = rng.uniform(freq[0] * (1 + margin), freq[-1] * (1 - margin), n_targets)
    l, m, _n, n1 = radec_to_lmn(ra, dec, ra0, dec0)
    lmn = np.stack([l, m, n1])

    def block(block_info=None):
        t0, t1 = block_info[None]["array-location"][0]
        nt = t1 - t0
        r = np.random.default_rng([seed, t0])
        v = (r.normal(size=(nt, len(a1), N_CHAN, 2)) + 1j * r.normal(size=(nt, len(a1), N_CHAN, 2)))
        lo = C_KMS * (1 - (freq + DFREQ / 2)[:, None] / nu_c[None, :])
        hi = C_KMS * (1 - (freq - DFREQ / 2)[:, None] / nu_c[None, :])
        s2 = np.sqrt(2) * LINE_SIGMA
        prof = LINE_FLUX * 0.5 * (erf(hi / s2) - erf(lo / s2)) / (hi - lo)  # (chan, target)
        for c in range(N_CHAN):
            on = np.flatnonzero(prof[c] > 1e-9)  # the lines in this channel
            if on.size:
                d = uvw[t0:t1] @ lmn[:, on]
                ph = np.exp(2j * np.pi * d * freq[c] / SPEED_OF_LIGHT)
                v[:, :, c, :] += (ph @ prof[c, on])[..., None]
        return v.astype(np.complex64)

    ct = default_time_chunk(len(a1), N_CHAN, 2, 8)
    shape = (n_time, len(a1), N_CHAN, 2)
    chunks = ((ct,) * (n_time // ct) + ((n_time % ct,) if n_time % ct else ()), len(a1), N_CHAN, 2)
    vis = da.map_blocks(block, chunks=chunks, dtype=np.complex64, meta=np.empty((0,) * 4,
                                                                                np.complex64))
    ds = new_partition(
        visibility=vis, weight=da.ones(shape, chunks=chunks, dtype=np.float32),
        flag=da.zeros(shape, chunks=chunks, dtype=bool), uvw=uvw,
        time=4.9e9 + 10.0 * np.arange(n_time), antenna1=a1, antenna2=a2,
        antenna_names=[f"ea{i:02d}" for i in range(N_ANT)],
        antenna_positions=enu + np.array([-1601185.4, -5041977.5, 3554875.9]),
        dish_diameters=np.full(N_ANT, 25.0), frequency=freq,
        channel_width=np.full(N_CHAN, DFREQ), polarization=["RR", "LL"],
        phase_center=(ra0, dec0), telescope_name="VLA", integration_time=10.0,
        attrs={"smearing": {"bandwidth": False, "time": False}}, frequency_frame="LSRK")
    write_store({"type6_lines": ds}, path)
    Table({"ra": np.degrees(ra), "dec": np.degrees(dec), "freq": nu_c}).write(
        path.with_suffix(".ecsv"), format="ascii.ecsv", overwrite=True)
    return path


def regridding(n_targets: int = 1000, seed: int = 0) -> list[tuple[str, float, float, float]]:
    """(choice, max |integral error| / integral, rms width error km/s, ms per 1000 targets)
    of three ways of putting 256 channels of ~23 km/s onto 20 km/s bins."""
    from xstack.spectral import overlap_lengths, velocity_edges

    rng = np.random.default_rng(seed)
    freq = FREQ0 + DFREQ * np.arange(N_CHAN)
    edges = velocity_edges(20.0, (-600, 600))
    centres = 0.5 * (edges[1:] + edges[:-1])
    nu_c = rng.uniform(freq[40], freq[-40], n_targets)
    s2 = np.sqrt(2) * LINE_SIGMA
    rows = []

    def width(spec):
        mom0 = spec.sum()
        mu = (centres * spec).sum() / mom0
        return np.sqrt(max(((centres - mu) ** 2 * spec).sum() / mom0 - 20.0**2 / 12, 0.0))

    true_w = width(LINE_FLUX * 0.5 * (erf(edges[1:] / s2) - erf(edges[:-1] / s2)) / 20.0)
    for choice in ("overlap", "nearest", "linear"):
        errs, werr = [], []
        t0 = time.perf_counter()
        for nc in nu_c:
            lo = C_KMS * (1 - (freq + DFREQ / 2) / nc)
            hi = C_KMS * (1 - (freq - DFREQ / 2) / nc)
            s = LINE_FLUX * 0.5 * (erf(hi / s2) - erf(lo / s2)) / (hi - lo)
            if choice == "overlap":
                o = overlap_lengths(np.column_stack([lo, hi]), edges)
                cover = o.sum(axis=0)
                spec = np.where(cover > 0, (s @ o) / np.where(cover > 0, cover, 1), 0.0)
            elif choice == "nearest":
                mid = 0.5 * (lo + hi)
                j = np.floor((mid - edges[0]) / 20.0).astype(int)
                ok = (j >= 0) & (j < centres.size)
                num = np.bincount(j[ok], s[ok], centres.size)
                cnt = np.bincount(j[ok], minlength=centres.size)
                spec = np.where(cnt > 0, num / np.maximum(cnt, 1), 0.0)
            else:
                mid = 0.5 * (lo + hi)
                order = np.argsort(mid)
                spec = np.interp(centres, mid[order], s[order], left=0.0, right=0.0)
            errs.append(abs(spec.sum() * 20.0 - LINE_FLUX) / LINE_FLUX)
            werr.append(width(spec) - true_w)
        ms = 1e3 * (time.perf_counter() - t0) * 1000 / n_targets
        rows.append((choice, float(np.max(errs)), float(np.sqrt(np.mean(np.square(werr)))), ms))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scale", type=float, default=1.0,
                        help="fraction of the 3384 integrations (1 = full size)")
    parser.add_argument("--targets", type=int, default=1000)
    parser.add_argument("--workdir", default=None, help="where the store goes (default: temp)")
    args = parser.parse_args()
    n_time = max(2, int(round(N_TIME * args.scale)))
    work = Path(args.workdir or tempfile.mkdtemp(prefix="xstack-linebench-"))
    work.mkdir(parents=True, exist_ok=True)
    store = work / f"type6-lines-{n_time}-{args.targets}.zarr"
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()}; load average before "
          f"{' / '.join(f'{x:.1f}' for x in os.getloadavg())}")
    nvis = n_time * N_ANT * (N_ANT - 1) // 2 * N_CHAN * 2
    print(f"data: {n_time} integrations x 351 baselines x {N_CHAN} channels x 2 pols = "
          f"{nvis:.3g} visibilities; {args.targets} targets\n")
    if not store.exists():
        t0 = time.perf_counter()
        make_store(store, n_time, args.targets)
        print(f"store written in {time.perf_counter() - t0:.1f} s\n")
    print("| stack | wall (s) | CPU (s) | peak above start (MB) | x chunk | visibilities |")
    print("|---|---|---|---|---|---|")
    res = {}
    for kind in ("continuum", "line"):
        run = subprocess.run([sys.executable, "-c", _CHILD, str(store), kind,
                              str(store.with_suffix(".ecsv"))], capture_output=True, text=True)
        if run.returncode:
            raise RuntimeError(run.stderr)
        r = res[kind] = json.loads(run.stdout.strip().splitlines()[-1])
        above = r["peak_mb"] - r["base_mb"]
        print(f"| {kind} | {r['wall']:.2f} | {r['cpu']:.2f} | {above:.0f} | "
              f"{above / r['chunk_mb']:.1f} | {r['n_vis']:.3g} |", flush=True)
    ratio = res["line"]["wall"] / res["continuum"]["wall"]
    line = res["line"]
    print(f"\nline / continuum wall time: {ratio:.2f} (goal <= 2); stacked line integral "
          f"over |v| < 150 km/s: {line['integral']:.4f} +- {line['integral_err']:.4f} Jy km/s "
          f"(injected {LINE_FLUX * erf(150 / (np.sqrt(2) * LINE_SIGMA)):.4f})\n")
    print("| regridding | max integral error | rms width error (km/s) | ms per 1000 targets |")
    print("|---|---|---|---|")
    for choice, ierr, werr, ms in regridding(args.targets):
        print(f"| {choice} | {ierr:.2e} | {werr:.2f} | {ms:.1f} |")
    print(f"\nload average after {' / '.join(f'{x:.1f}' for x in os.getloadavg())}")
    if args.workdir is None:
        shutil.rmtree(work)


if __name__ == "__main__":
    main()
