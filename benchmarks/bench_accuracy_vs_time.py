"""Accuracy against time for every knob of xstack that trades one for the other, in one run.

Knobs (each setting: wall and CPU seconds, python peak allocation, and an error against a
truth computed here with plain numpy, outside the code under test):

1. ``phase``    uv-stacking phasor kernel and precision (``xstack.uvstack.kernels``: plain
               numpy, numba per row float64 / float32 phases, antenna-factorised, ducc0
               NUFFT); error = max |P - P_true|, P_true = paper eq. 4 with long-double phases.
2. ``gridder``  ``xstack.make_image(epsilon=...)``; error = max |I - I_dft| / max |I_dft| at
               a few pixels, I_dft = direct Fourier sum of the same visibilities and weights.
3. ``pixel``    image-stacking of a noise-free simulated scene imaged with cell = beam/3, /5,
               /8, ``subpixel`` False / "fourier" / "spline"; error = |S_stack - S_dft| / S_true
               where S_dft is the mean of the direct Fourier sum at the exact target positions
               (what perfect alignment measures; it differs from S_true only by the other
               sources' sidelobes, printed too).
4. ``mc``       ``xstack.estimate_noise(method="mc"/"random", realizations=R)``; error = relative
               spread of the R-realisation estimate, measured over independent blocks of R
               of one long run (for Gaussian values sqrt(1/(2(R-1))), printed beside it).
5. ``binning``  ``xstack.fit_uv(model="gaussian", binned=..., nbins=...)`` on a stacked
               Gaussian of known flux and size (plain-numpy visibilities, S/N ~ 1e4); error =
               max(|dS|/S, |dFWHM|/FWHM).
6. ``chunk``    ``xstack.stack_uv`` over a simulated store rechunked in time: the flux must be
               identical (relative difference printed); time and peak memory.
7. ``sim``      the simulator's model kernels (``xstack.sim.kernels``: per row, per antenna,
               float32 phases without w) and the w-term switched off; error = max |V - V_true|
               / sum S with V_true = paper eq. 1 in plain numpy.
8. ``threads``  ``xstack.imaging.clean.clean_data(reproducible=True/False)`` deep into the
               noise of a crowded field, run twice on the same data: one thread per ducc0
               gridding and prediction against all threads; error = max |R_2 - R_1| / rms(R_1)
               of the two runs' residual images (0: the same bits), components in the note.

Output: one Markdown table per knob and a summary table, printed and (``--markdown``) written;
a Pareto plot (``--plot``, x = time, y = error, log-log).

Usage::

    python benchmarks/bench_accuracy_vs_time.py [--quick] [--markdown OUT.md] [--plot OUT.png]

``--quick`` runs every knob at a tiny size (well under a minute); without it the sizes are
the documented ones (run it on a quiet machine).
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import resource
import shutil
import tempfile
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

C = 299_792_458.0
ARCSEC = math.pi / 180 / 3600
CENTER = (math.radians(57.2957916666667), math.radians(-30.0))
KNOBS = ("phase", "gridder", "pixel", "mc", "binning", "chunk", "sim", "threads")
LINES: list[str] = []


def out(line: str = "") -> None:
    print(line, flush=True)
    LINES.append(line)


# ------------------------------------------------------------------------------- sizes
@dataclass
class Sizes:
    """Problem sizes of one run (``full``, ``quick`` or ``tiny`` for the test)."""

    phase_ntime: int = 200
    phase_npos: int = 900
    nufft_eps: tuple[float, ...] = (1e-6, 1e-12)
    grid_ntime: int = 120
    grid_size: int = 512
    grid_eps: tuple[float, ...] = (1e-2, 1e-4, 1e-6, 1e-8, 1e-10)
    pix_ntime: int = 60
    pix_nsrc: int = 25
    pix_div: tuple[int, ...] = (3, 5, 8)
    mc_ntime: int = 60
    mc_npos: int = 50
    mc_r: tuple[int, ...] = (10, 30, 100, 300)
    mc_pool: int = 3000
    fit_ntime: int = 200
    fit_nbins: tuple[int, ...] = (10, 30, 100)
    chunk_ntime: int = 240
    chunk_sizes: tuple[int, ...] = (1, 8, 60, 240)
    sim_ntime: int = 40
    sim_nsrc: int = 300
    threads_ntime: int = 240
    threads_size: int = 2048


SIZES = {
    "full": Sizes(),
    "quick": Sizes(phase_ntime=20, phase_npos=200, grid_ntime=20, grid_size=256,
                   pix_ntime=20, pix_nsrc=16, mc_ntime=8, mc_npos=20, mc_r=(10, 30, 100),
                   mc_pool=1000, fit_ntime=40, chunk_ntime=40, chunk_sizes=(2, 10, 40),
                   sim_ntime=8, sim_nsrc=100, threads_ntime=40, threads_size=512),
    "tiny": Sizes(phase_ntime=4, phase_npos=30, nufft_eps=(), grid_ntime=4, grid_size=128,
                  grid_eps=(1e-2, 1e-5, 1e-9), pix_ntime=8, pix_nsrc=9, pix_div=(3, 8),
                  mc_ntime=4, mc_npos=10, mc_r=(10, 40), mc_pool=400, fit_ntime=12,
                  fit_nbins=(10, 40), chunk_ntime=8, chunk_sizes=(2, 8), sim_ntime=3,
                  sim_nsrc=20, threads_ntime=6, threads_size=256),
}


# ------------------------------------------------------------------------ measurement
@dataclass
class Row:
    knob: str
    setting: str
    wall: float
    cpu: float
    peak_mib: float
    error: float
    note: str = ""
    default: bool = False


def measure(fn, *args, **kw) -> tuple[float, float, float, Any]:
    """Wall s, CPU s (all threads), python peak allocation MiB (tracemalloc), result."""
    tracemalloc.start()
    t0, c0 = time.perf_counter(), time.process_time()
    result = fn(*args, **kw)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return wall, cpu, peak / 2**20, result


def lmn(ra, dec, ra0=CENTER[0], dec0=CENTER[1]):
    """Direction cosines and n - 1, written out here (independent of xstack.coords)."""
    l = np.cos(dec) * np.sin(ra - ra0)
    m = np.sin(dec) * np.cos(dec0) - np.cos(dec) * np.sin(dec0) * np.cos(ra - ra0)
    r2 = l**2 + m**2
    return l, m, -r2 / (1 + np.sqrt(1 - r2))


def array_uvw(n_time: int, config: str, hours: float = 8.0):
    """(n_time, nbl, 3) UVW of a packaged array over ``hours`` around transit, a1, a2, array."""
    from xstack.schema import baseline_pairs
    from xstack.sim.arrays import baseline_uvw, packaged_array, time_of_hour_angle

    arr = packaged_array(config)
    a1, a2 = baseline_pairs(arr.n_antennas)
    lon = np.arctan2(arr.site[1], arr.site[0]) if np.any(arr.site) else -1.878
    t0 = time_of_hour_angle(-hours / 24 * np.pi, CENTER[0], lon, 60000.0)
    times = t0 + np.linspace(0.0, hours * 3600.0, n_time)
    return baseline_uvw(arr.positions, a1, a2, times, *CENTER), a1, a2, arr, times


def partition(vis, weight, uvw, a1, a2, arr, times, freq, width=1e6):
    from xstack.schema import new_partition

    return new_partition(
        visibility=vis, weight=weight.astype(np.float32), flag=np.zeros(vis.shape, bool),
        uvw=uvw, time=times, antenna1=a1, antenna2=a2, antenna_names=arr.names,
        antenna_positions=arr.positions, dish_diameters=arr.diameters, frequency=freq,
        channel_width=np.full(freq.size, width), polarization=["RR", "LL"],
        phase_center=CENTER, telescope_name="VLA", integration_time=10.0,
        # the knobs here are not smearing; its correction has its own benchmark
        attrs={"smearing": {"bandwidth": False, "time": False}})


def box_positions(n: int, half_arcsec: float, rng):
    """RA, Dec (radians) uniform in a box of +-half_arcsec around the center (tangent plane)."""
    x = rng.uniform(-half_arcsec, half_arcsec, n) * ARCSEC
    y = rng.uniform(-half_arcsec, half_arcsec, n) * ARCSEC
    dec = CENTER[1] + y
    ra = CENTER[0] + x / np.cos(dec)
    return ra, dec


# ------------------------------------------------------------------------------ knobs
def knob_phase(sz: Sizes, rng) -> list[Row]:
    """uv-stacking phasor: engine and precision against long-double eq. 4."""
    from xstack.uvstack import kernels as K

    uvw3, a1, a2, *_ = array_uvw(sz.phase_ntime, "vla.a")
    uvw = uvw3.reshape(-1, 3)
    freq = 1.4e9 + 25e6 * np.arange(10)
    # a 1' x 1' field: the NUFFT's grid grows with baseline x field and is refused (over
    # 2 GiB) for VLA A x 30' (docs/bench/uvstack.md); here every engine runs the same problem
    ra, dec = box_positions(sz.phase_npos, 30, rng)
    l, m, n1 = lmn(ra, dec)
    w, ia = np.ones(l.size), np.ones((l.size, freq.size))
    coef = np.ones((l.size, freq.size)) / l.size
    sub = rng.choice(uvw.shape[0], size=min(uvw.shape[0], 200), replace=False)
    lmn_ld = np.stack([l, m, n1]).astype(np.longdouble)
    d = uvw[sub].astype(np.longdouble) @ lmn_ld
    truth = np.empty((sub.size, freq.size), complex)
    for c, nu in enumerate(freq):
        turns = d * (np.longdouble(nu) / np.longdouble(C))
        frac = (turns - np.round(turns)).astype(np.float64)  # exact reduction, then float64
        truth[:, c] = np.exp(-2j * np.pi * frac) @ coef[:, c]
    f32 = [x.astype(np.float32) for x in (uvw, freq, l, m, n1)]
    # JIT warm-up so compile time is not counted
    K.stack_phasor(uvw[:5], freq, l, m, n1, w, ia)
    K.stack_phasor(f32[0][:5], *f32[1:], w, ia)
    K.phasor_antenna(uvw[:2 * a1.size], freq, l, m, n1, coef, a1, a2)
    runs = [
        ("numpy, float64 (reference)", lambda: K.stack_phasor_numpy(uvw, freq, l, m, n1, coef),
         False),
        ("numba per row, float64", lambda: K.stack_phasor(uvw, freq, l, m, n1, w, ia), False),
        ("numba per row, float32 phases", lambda: K.stack_phasor(*f32, w, ia), False),
        ("antenna-factorised, float64", lambda: K.phasor_antenna(uvw, freq, l, m, n1, coef,
                                                                 a1, a2)[0], True),
    ]
    for eps in sz.nufft_eps:
        runs.append((f"ducc0 NUFFT, eps {eps:g}", lambda e=eps: K.stack_phasor_nufft(
            uvw, freq, l, m, n1, coef, epsilon=e), False))
    rows = []
    for name, fn, default in runs:
        try:
            wall, cpu, peak, p = measure(fn)
        except MemoryError as exc:
            rows.append(Row("phase", name, np.nan, np.nan, np.nan, np.nan, f"refused: {exc}"))
            continue
        rows.append(Row("phase", name, wall, cpu, peak, float(np.max(np.abs(p[sub] - truth))),
                        "engine auto" if default else "", default))
    return rows


def knob_gridder(sz: Sizes, rng) -> list[Row]:
    """make_image epsilon against a direct Fourier sum at a few pixels."""
    import xstack

    uvw3, a1, a2, arr, times = array_uvw(sz.grid_ntime, "vla.a")
    freq = np.array([1.3e9, 1.4e9, 1.5e9])
    cell = 0.3
    ra, dec = box_positions(5, 0.3 * cell * sz.grid_size, rng)
    l, m, n1 = lmn(ra, dec)
    flux = rng.uniform(0.5, 1.0, l.size)
    u, v, w_ = (uvw3[..., k][..., None] * freq / C for k in range(3))
    vis = np.zeros(u.shape, complex)
    for k in range(l.size):  # paper eq. 1 with the w-term
        vis += flux[k] * np.exp(2j * np.pi * (u * l[k] + v * m[k] + w_ * n1[k]))
    wt = rng.uniform(0.5, 1.5, u.shape)
    shape = u.shape + (2,)
    ds = partition(np.broadcast_to(vis[..., None], shape).astype(np.complex64),
                   np.broadcast_to(wt[..., None], shape), uvw3, a1, a2, arr, times, freq)
    vis64 = ds.VISIBILITY.values[..., 0].astype(complex)  # what the imager sees (complex64)
    wt32 = ds.WEIGHT.values[..., 0].astype(float)
    xstack.make_image(ds, size=64, cell_arcsec=cell, epsilon=1e-4)  # warm-up
    rows, first = [], None
    for eps in sz.grid_eps:
        wall, cpu, peak, res = measure(xstack.make_image, ds, size=sz.grid_size,
                                       cell_arcsec=cell, epsilon=eps)
        img = np.asarray(res.image).squeeze()
        if first is None:
            # the direct sum at the source pixels and random pixels (same for every epsilon)
            first = res
            ny, nx = img.shape
            cel = res.wcs.celestial
            px, py = cel.world_to_pixel_values(np.degrees(ra), np.degrees(dec))
            iy = np.r_[np.round(py).astype(int), rng.integers(0, ny, 15)]
            ix = np.r_[np.round(px).astype(int), rng.integers(0, nx, 15)]
            pra, pdec = np.radians(cel.pixel_to_world_values(ix, iy))
            pl, pm, pn1 = lmn(pra, pdec)
            direct = np.zeros(ix.size)
            for c in range(freq.size):
                ph = -2j * np.pi * (np.outer(u[..., c].ravel(), pl) + np.outer(
                    v[..., c].ravel(), pm) + np.outer(w_[..., c].ravel(), pn1))
                direct += np.real((wt32[..., c].ravel() * vis64[..., c].ravel()) @ np.exp(ph))
            direct /= wt32.sum()
        err = float(np.max(np.abs(img[iy, ix] - direct)) / np.max(np.abs(direct)))
        rows.append(Row("gridder", f"epsilon {eps:g}", wall, cpu, peak, err,
                        f"{sz.grid_size}^2, {vis.size * 2:,} vis", eps == 1e-6))
    return rows


def _simulate(tmp: Path, name: str, ntime: int, nsrc: int, half: float, sigma: float | None,
              seed: int = 1, channels: int = 4, hours: float = 0.0, time_chunk: int = 0):
    import xstack

    # ``hours``: spread the integrations over a long track (without time smearing the
    # integration length changes nothing else): a fuller uv-coverage, lower sidelobes
    integration = 3600.0 * hours / ntime if hours else 10.0
    scene = {
        "name": name,
        "time_chunk": time_chunk,
        "array": {"config": "vla.a"},
        "observation": {"time_per_pointing": integration * ntime, "integration": integration},
        "spectral": {"center": 1.4e9, "bandwidth": 100e6 * channels / 4, "channels": channels},
        "effects": {"primary_beam": "none", "w_term": False}
        | ({"noise": {"sigma": sigma}} if sigma else {}),
        "populations": [{"name": "targets", "count": nsrc,
                         "flux": {"kind": "fixed", "value": "1mJy"},
                         "positions": {"kind": "box", "size_arcsec": [2 * half, 2 * half]}}],
    }
    return xstack.simulate(scene, tmp / f"{name}.zarr", seed=seed)


def knob_pixel(sz: Sizes, rng, tmp: Path) -> list[Row]:
    """Image-stacking flux vs cell size and sub-pixel alignment on a noise-free scene."""
    import xstack

    half = 40.0
    sim = _simulate(tmp, "pixel", sz.pix_ntime, sz.pix_nsrc, half, None, channels=8, hours=8.0)
    cat = sim.catalogs["targets"]
    ra, dec = np.radians(cat["ra"]), np.radians(cat["dec"])
    pos = np.c_[cat["ra"], cat["dec"]]
    true = float(np.mean(cat["flux"]))
    tree = xstack.open_store(sim.store)
    # direct Fourier sum at the exact target positions (no w: the scene has none)
    sdft, wsum = np.zeros(ra.size), 0.0
    for node in tree.subtree:
        if "VISIBILITY" not in node.dataset:
            continue
        ds = node.dataset
        vis = ds.VISIBILITY.values.astype(complex).mean(axis=-1)
        wt = ds.WEIGHT.values.astype(float).mean(axis=-1) * ~ds.FLAG.values.any(axis=-1)
        uvw = ds.UVW.values
        freq = ds.frequency.values if "frequency" in ds else ds.chan_freq.values
        l, m, _ = lmn(ra, dec)
        for c, nu in enumerate(freq):
            ph = -2j * np.pi * (np.outer(uvw[..., 0].ravel(), l) + np.outer(
                uvw[..., 1].ravel(), m)) * nu / C
            sdft += np.real((wt[..., c].ravel() * vis[..., c].ravel()) @ np.exp(ph))
        wsum += wt.sum()
    sdft = float(np.mean(sdft / wsum))
    probe = xstack.make_image(sim.store, size=256, cell_arcsec=0.1, wterm=False)
    beam = math.sqrt(probe.beam[0] * probe.beam[1])
    beam = beam * 3600 if beam < 0.01 else beam  # degrees or arcsec, whichever it is
    rows = []
    for div in sz.pix_div:
        cell = beam / div
        size = int(2 ** math.ceil(math.log2((2 * half + 40 * beam) / cell)))
        t_img, c_img, p_img, img = measure(xstack.make_image, sim.store, size=size,
                                           cell_arcsec=cell, wterm=False)
        path = tmp / f"pixel{div}.fits"
        img.write(path)
        for sub in (False, "fourier", "spline"):
            wall, cpu, peak, res = measure(xstack.stack_images, path, pos, stamp_size=32,
                                           weighting="none", subpixel=sub, plot=False)
            # the time is imaging + stacking: a finer cell costs in the imaging. The cell has
            # no default (the user's); nearest pixel is the default alignment (the paper's)
            rows.append(Row("pixel", f"cell beam/{div}, {sub or 'nearest'}", t_img + wall,
                            c_img + cpu, max(p_img, peak), abs(res.flux_jy - sdft) / true,
                            f"image {size}^2 {t_img:.2f} s + stack {wall:.3f} s; "
                            f"S/S_true {res.flux_jy / true:.4f}", sub is False))
    out(f"pixel knob: beam {beam:.2f}\", true flux {true * 1e3:.3f} mJy, direct sum at the "
        f"targets {sdft * 1e3:.4f} mJy (others' sidelobes {100 * (sdft / true - 1):+.2f} %)")
    return rows


def knob_mc(sz: Sizes, rng, tmp: Path) -> list[Row]:
    """Spread of the Monte Carlo noise estimate vs realisations R.

    The estimate is the standard deviation of R realisation fluxes. Its spread is measured
    on one long run of ``mc_pool`` realisations cut into independent blocks of R (plain
    numpy on the returned values); the time is that of a call with R realisations.
    """
    import xstack

    sim = _simulate(tmp, "mc", sz.mc_ntime, sz.mc_npos, 120.0, 0.01, channels=2)
    cat = sim.catalogs["targets"]
    pos = np.c_[cat["ra"], cat["dec"]]
    # in memory: the knob is R, not the store's opening (a fixed ~0.2 s per call)
    data = xstack.open_store(sim.store).load()
    xstack.estimate_noise(data, pos, method="mc", realizations=2, seed=99)  # warm-up
    rows = []
    for method in ("mc", "random"):
        pool = xstack.estimate_noise(data, pos, method=method, realizations=sz.mc_pool,
                                     seed=1).values
        for r in sz.mc_r:
            wall, cpu, peak, res = measure(xstack.estimate_noise, data, pos, method=method,
                                           realizations=r, seed=2)
            nblock = pool.size // r
            est = np.std(pool[:nblock * r].reshape(nblock, r), axis=1, ddof=1)
            spread = float(np.std(est, ddof=1) / np.mean(est))
            rows.append(Row("mc", f"{method}, R={r}", wall, cpu, peak, spread,
                            f"expected {math.sqrt(1 / (2 * (r - 1))):.3f} (Gaussian); "
                            f"{nblock} blocks of one {sz.mc_pool}-realisation run",
                            method == "mc" and r == 100))
    return rows


def knob_binning(sz: Sizes, rng) -> list[Row]:
    """fit_uv of a stacked Gaussian of known flux and size, binned vs unbinned."""
    import xstack

    flux, fwhm = 1e-3, 1.5
    uvw3, a1, a2, arr, times = array_uvw(sz.fit_ntime, "vla.a")
    freq = np.array([1.3e9, 1.4e9, 1.5e9, 1.6e9])
    q2 = (uvw3[..., 0] ** 2 + uvw3[..., 1] ** 2)[..., None] * (freq / C) ** 2
    model = flux * np.exp(-np.pi**2 / (4 * np.log(2)) * (fwhm * ARCSEC) ** 2 * q2)
    sigma = 1e-4 * flux * math.sqrt(q2.size)  # S/N of the whole set ~ 1e4
    shape = q2.shape + (2,)
    noise = sigma * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))
    ds = partition((model[..., None] + noise).astype(np.complex64), np.full(shape, sigma**-2),
                   uvw3, a1, a2, arr, times, freq)
    xstack.fit_uv(ds, model="gaussian")  # warm-up
    rows = []
    for binned, nb in [(False, 0)] + [(True, n) for n in sz.fit_nbins]:
        wall, cpu, peak, res = measure(xstack.fit_uv, ds, model="gaussian", binned=binned,
                                       nbins=nb or 30)
        err = max(abs(res.flux_jy / flux - 1), abs(res.fwhm_arcsec / fwhm - 1))
        rows.append(Row("binning", f"binned, {nb} bins" if binned else "unbinned", wall, cpu,
                        peak, err, f"S {res.flux_jy / flux:.5f}, FWHM {res.fwhm_arcsec / fwhm:.5f}"
                        " x true", not binned))
    return rows


def knob_chunk(sz: Sizes, rng, tmp: Path) -> list[Row]:
    """stack_uv over the same store rechunked in time: identical flux, time and memory."""
    import xstack

    fluxes, rows = [], []
    for i, tc in enumerate(sz.chunk_sizes):
        # the same scene and seed written with tc integrations per chunk on disk (the
        # simulator's data are the same bit for bit whatever the chunking)
        t_sim = time.perf_counter()
        sim = _simulate(tmp, f"chunk{tc}", sz.chunk_ntime, 30, 120.0, 0.01, channels=4,
                        time_chunk=tc)
        t_sim = time.perf_counter() - t_sim
        cat = sim.catalogs["targets"]
        pos = np.c_[cat["ra"], cat["dec"]]
        if i == 0:
            xstack.stack_uv(sim.store, pos)  # warm-up
        wall, cpu, peak, res = measure(xstack.stack_uv, sim.store, pos)
        fluxes.append(res.flux_jy)
        rows.append(Row("chunk", f"{tc} integrations per chunk", wall, cpu, peak, np.nan,
                        f"flux {res.flux_jy:.15e} Jy; simulate {t_sim:.2f} s",
                        tc == sz.chunk_sizes[-1]))
    diff = float(np.max(np.abs(np.array(fluxes) - fluxes[0])) / abs(fluxes[0]))
    for r in rows:
        # every chunking gives the same number: the "error" is the spread between them
        r.error = diff
    out(f"chunk knob: max relative flux difference between chunkings {diff:.1e}")
    return rows


def knob_sim(sz: Sizes, rng) -> list[Row]:
    """Simulator model kernels against plain-numpy eq. 1."""
    from xstack.schema import baseline_pairs
    from xstack.sim import arrays, kernels

    vla = arrays.packaged_array("vla.a")
    a1, a2 = baseline_pairs(vla.n_antennas)
    t = 4.9e9 + 10.0 * np.arange(sz.sim_ntime)
    ant = arrays.antenna_uvw(vla.positions, t, *CENTER)
    uvw = (ant[:, a1] - ant[:, a2]).reshape(-1, 3)
    freq = 1.4e9 + 25e6 * (np.arange(10) - 4.5)
    # a 4' x 4' field, where leaving out the w-term is a small but visible error
    ra, dec = box_positions(sz.sim_nsrc, 120, rng)
    l, m, n1 = lmn(ra, dec)
    flux = rng.uniform(1e-6, 1e-3, l.size)
    sub = rng.choice(uvw.shape[0], size=min(uvw.shape[0], 300), replace=False)
    lam = C / freq
    ph = 2 * np.pi * (uvw[sub, 0, None, None] * l + uvw[sub, 1, None, None] * m
                      + uvw[sub, 2, None, None] * n1) / lam[None, :, None]
    truth = (flux * np.exp(1j * ph)).sum(axis=-1)  # (rows, chan)
    ph0 = 2 * np.pi * (uvw[sub, 0, None, None] * l + uvw[sub, 1, None, None] * m) / lam[None, :, None]
    truth_now = (flux * np.exp(1j * ph0)).sum(axis=-1)  # the same without the w-term
    kernels.model_visibilities(uvw[:5], freq, l, m, n1, flux)  # warm-up
    kernels.model_visibilities(uvw[:5], freq, l, m, None, flux)
    kernels.model_visibilities_antenna(ant[:1], a1, a2, freq, l, m, n1, flux)
    kernels.model_visibilities_float32(uvw[:5], freq, l, m, flux)
    runs = [
        ("per row, float64", lambda: kernels.model_visibilities(uvw, freq, l, m, n1, flux),
         False),
        ("per antenna, float64", lambda: kernels.model_visibilities_antenna(
            ant, a1, a2, freq, l, m, n1, flux).reshape(uvw.shape[0], -1), True),
        ("per row, w-term off", lambda: kernels.model_visibilities(uvw, freq, l, m, None, flux),
         False),
        ("per row, float32 phases, no w", lambda: kernels.model_visibilities_float32(
            uvw, freq, l, m, flux), False),
    ]
    rows = []
    for name, fn, default in runs:
        wall, cpu, peak, v = measure(fn)
        err = float(np.max(np.abs(v[sub] - truth)) / flux.sum())
        err_now = float(np.max(np.abs(v[sub] - truth_now)) / flux.sum())
        note = "simulator's path" if default else ""
        if "no w" in name or "w-term off" in name:
            note = f"vs eq. 1 without w: {err_now:.1e}"
        rows.append(Row("sim", name, wall, cpu, peak, err, note, default))
    return rows


# ---------------------------------------------------------------------------- output
def knob_threads(sz: Sizes, rng) -> list[Row]:
    """CLEAN run twice, reproducible (one thread per ducc0 call) against threaded."""
    from xstack.imaging.clean import clean_data

    uvw3, a1, a2, arr, times = array_uvw(sz.threads_ntime, "vla.a")
    freq = np.array([1.35e9, 1.45e9])
    cell = 0.4
    ra, dec = box_positions(60, 0.4 * cell * sz.threads_size, rng)
    l, m, n1 = lmn(ra, dec)
    sigma = 1.0  # Jy per real/imaginary part per visibility
    shape = uvw3.shape[:2] + (freq.size, 2)
    thermal = sigma / math.sqrt(np.prod(shape))
    flux = rng.uniform(3, 30, l.size) * thermal  # sources of 3 to 30 image sigma
    u, v, w_ = (uvw3[..., k][..., None] * freq / C for k in range(3))
    vis = np.zeros(u.shape, complex)
    for k in range(l.size):  # paper eq. 1 with the w-term
        vis += flux[k] * np.exp(2j * np.pi * (u * l[k] + v * m[k] + w_ * n1[k]))
    noisy = vis[..., None] + sigma * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))
    ds = partition(noisy.astype(np.complex64), np.full(shape, 1 / sigma**2), uvw3, a1, a2, arr,
                   times, freq)
    kw = dict(size=sz.threads_size, cell_arcsec=cell, niter=50_000, threshold=2 * thermal,
              algorithm="clark", epsilon=1e-4)
    clean_data(ds, **dict(kw, size=64, niter=10))  # warm-up
    rows = []
    for reproducible in (True, False):
        runs = [measure(clean_data, ds, reproducible=reproducible, **kw) for _ in range(2)]
        (wall, cpu, peak, (_, c1)), (_, _, _, (_, c2)) = runs
        err = float(np.max(np.abs(c2.residual - c1.residual)) / np.std(c1.residual))
        rows.append(Row("threads", "one thread per ducc0 call" if reproducible else
                        "threaded ducc0", wall, cpu, peak, err,
                        f"{sz.threads_size}^2, {np.prod(shape):,} vis; components "
                        f"{c1.n_components} / {c2.n_components}, {c1.n_major} major cycles; "
                        f"second run {runs[1][0]:.2f} s", reproducible))
    return rows


def _fmt(x: float, spec: str) -> str:
    return "-" if not np.isfinite(x) else format(x, spec)


def print_tables(rows: list[Row]) -> None:
    for knob in KNOBS:
        sel = [r for r in rows if r.knob == knob]
        if not sel:
            continue
        out("")
        out(f"## {knob}")
        out("")
        out("| setting | wall [s] | CPU [s] | peak alloc [MiB] | error | note |")
        out("|---|---|---|---|---|---|")
        for r in sel:
            out(f"| {r.setting}{' (default)' if r.default else ''} | {_fmt(r.wall, '.3f')} | "
                f"{_fmt(r.cpu, '.3f')} | {_fmt(r.peak_mib, '.1f')} | {_fmt(r.error, '.1e')} | "
                f"{r.note} |")
    out("")
    out("## Summary")
    out("")
    out("| knob | setting | wall [s] | error |")
    out("|---|---|---|---|")
    for r in rows:
        out(f"| {r.knob} | {r.setting}{' (default)' if r.default else ''} | "
            f"{_fmt(r.wall, '.3f')} | {_fmt(r.error, '.1e')} |")


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats in both time and error, by time."""
    idx = [i for i, (t, e) in enumerate(points) if np.isfinite(t) and np.isfinite(e)]
    front = [i for i in idx if not any(
        points[j][0] <= points[i][0] and points[j][1] <= points[i][1] and points[j] != points[i]
        for j in idx)]
    return sorted(front, key=lambda i: points[i][0])


def plot(rows: list[Row], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 7))
    markers = dict(zip(KNOBS, "osD^vPX*"))
    for knob in KNOBS:
        sel = [r for r in rows if r.knob == knob and np.isfinite(r.wall) and np.isfinite(r.error)]
        if not sel:
            continue
        # errors of exactly 0 (identical results) are drawn at a floor, so log axes work
        pts = [(r.wall, max(r.error, 1e-17)) for r in sel]
        (line,) = ax.plot(*zip(*pts), markers[knob], ls="none", label=knob, alpha=0.8)
        front = pareto(pts)
        ax.plot([pts[i][0] for i in front], [pts[i][1] for i in front], "-",
                color=line.get_color(), alpha=0.6)
        for r, (t, e) in zip(sel, pts):
            ax.annotate(r.setting, (t, e), fontsize=6, xytext=(3, 2),
                        textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wall time [s]")
    ax.set_ylabel("error (per knob: see docs/accuracy-vs-time.md)")
    ax.set_title("xstack: accuracy against time (lines join each knob's Pareto front)")
    ax.legend()
    ax.grid(True, which="both", alpha=0.2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(size: str = "quick", knobs: tuple[str, ...] = KNOBS, seed: int = 2015) -> list[Row]:
    """Measure the chosen knobs at the chosen size; returns the rows (also printed)."""
    sz = SIZES[size]
    rng = np.random.default_rng(seed)
    rows: list[Row] = []
    tmp = Path(tempfile.mkdtemp(prefix="xstack-avt-"))
    try:
        for knob in knobs:
            t0 = time.perf_counter()
            if knob in ("pixel", "mc", "chunk"):
                rows += globals()[f"knob_{knob}"](sz, rng, tmp)
            else:
                rows += globals()[f"knob_{knob}"](sz, rng)
            out(f"{knob}: measured in {time.perf_counter() - t0:.1f} s")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return rows


def main(argv: list[str] | None = None) -> list[Row]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="tiny sizes (development, < 1 min)")
    ap.add_argument("--size", choices=sorted(SIZES), default=None, help=argparse.SUPPRESS)
    ap.add_argument("--knobs", default=",".join(KNOBS), help="comma-separated subset")
    ap.add_argument("--markdown", default=None, help="also write the tables to this file")
    ap.add_argument("--plot", default=None, help="write the Pareto plot (PNG) here")
    args = ap.parse_args(argv)
    LINES.clear()
    size = args.size or ("quick" if args.quick else "full")
    from numba import get_num_threads

    out(f"# accuracy vs time ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
        f"size {size})")
    out("")
    out(f"load average at start: {os.getloadavg()[0]:.1f}; machine {platform.machine()}, "
        f"{os.cpu_count()} cores, python {platform.python_version()}, numba threads "
        f"{get_num_threads()}")
    rows = run(size, tuple(k for k in args.knobs.split(",") if k))
    print_tables(rows)
    out("")
    out(f"load average at end: {os.getloadavg()[0]:.1f}; process peak RSS "
        f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")
    if args.markdown:
        Path(args.markdown).write_text("\n".join(LINES) + "\n")
    if args.plot:
        plot(rows, args.plot)
    return rows


if __name__ == "__main__":
    main()
