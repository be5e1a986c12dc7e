"""xstack's CLEAN against CASA's tclean on the reproduction chain (issue 12).

Run ``python benchmarks/bench_clean_casa.py [--scene paper-2 --scene paper-3] [--scale 0.05]
[--seed 1] [--casa GRIDDER:DECONVOLVER ...]`` (default ``wproject:hogbom`` and
``standard:hogbom``); prints Markdown tables (``docs/bench/clean-casa.md``).
Needs the ``casa`` extra (casatools, casatasks, casadata; run offline).

For each scene (a paper preset at ``--scale`` with a fixed seed):

1. ``xstack.simulate`` into a temporary directory under /tmp, ``xstack.export_ms`` to an MS.
2. xstack: ``clean_data`` exactly as :func:`xstack.reproduce.run.run_realization` calls it
   (the procedure's size, cell and epsilon, ``threshold=clean_threshold(PROCEDURES[n],
   scale)``, ``algorithm="clark"``, ``niter=100_000``), model and residual written with
   ``img.write``.
3. CASA: ``tclean`` on the exported MS with the same image size, cell, threshold and niter,
   natural weighting, Stokes I, MFS, for every ``GRIDDER:DECONVOLVER`` of ``--casa``
   (``wproject`` with ``--wprojplanes``, default -1: CASA chooses); ``exportfits`` of
   ``.model`` and ``.residual``.
   Every CLEAN (xstack's too) runs in its own python process, which reports the wall time of
   the CLEAN call alone and its peak RSS (``ru_maxrss``; the process's imports included).
   CASA runs offline (site config with ``casadata.datapath``, private HOME) with
   ``OMP_NUM_THREADS=2``; xstack uses all threads (2).
4. The two grids are compared (CTYPE, CRVAL, CRPIX, CDELT of the model FITS files); the
   CLEANed flux of each bright source is the model summed within ``--radius`` beams of its
   true position, against its true *apparent* flux (catalog flux times the primary beam,
   ``xstack.beams.standard_beam``, averaged over the channels: the CLEAN model of an image
   made without primary-beam correction is the attenuated sky); the residual image rms
   (1.4826 MAD) against the expected thermal noise ``1/sqrt(sum of weights)``.
5. Each model is subtracted from the same store (``xstack.subtract``; CASA's model FITS is
   checked against subtract's rules first and converted with astropy if it breaks them), the
   bright-source catalog itself too (the perfect model), and the targets are uv-stacked on
   each residual (``xstack.stack_uv``, the procedure's uvmin, ``weighting="pb"`` for all:
   the procedure's ``sigma2`` needs a residual image per model, and ``pb`` weights the same
   positions alike in every residual, so the differences are those of the models alone).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path
from typing import Any

import numpy as np

ARCSEC = math.pi / 180 / 3600

XSTACK_CLEAN = textwrap.dedent("""\
    import json, resource, sys, time
    from xstack.imaging.clean import clean_data
    store, prefix = sys.argv[1], sys.argv[2]
    size, cell, threshold, epsilon = int(sys.argv[3]), *map(float, sys.argv[4:7])
    t0 = time.perf_counter()
    img, cres = clean_data(store, size=size, cell_arcsec=cell, niter=100_000,
                           threshold=threshold, algorithm="clark", epsilon=epsilon)
    seconds = time.perf_counter() - t0
    img.write(prefix + ".model.fits", cres.model, kind="model")
    img.write(prefix + ".residual.fits", cres.residual, kind="residual")
    print(json.dumps({"seconds": seconds, "iterations": int(cres.n_components),
                      "major_cycles": int(cres.n_major), "converged": bool(cres.converged),
                      "peak_residual_jy": float(cres.peak_residual),
                      "sum_weights": float(img.header.get("XSSUMW", float("nan"))),
                      "beam_arcsec": [float(b) for b in img.beam],
                      "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
    """)

CASA_CLEAN = textwrap.dedent("""\
    import json, resource, sys, time
    from casatasks import exportfits, tclean
    vis, prefix, opts = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
    t0 = time.perf_counter()
    summ = tclean(vis=vis, imagename=prefix, specmode="mfs", weighting="natural", stokes="I",
                  datacolumn="data", niter=100000, gain=0.1, interactive=False,
                  savemodel="none", **opts)
    seconds = time.perf_counter() - t0
    for ext in ("model", "residual"):
        exportfits(imagename=prefix + "." + ext, fitsimage=prefix + "." + ext + ".fits",
                   overwrite=True)
    summ = summ if isinstance(summ, dict) else {}
    print(json.dumps({"seconds": seconds, "iterations": int(summ.get("iterdone", -1)),
                      "major_cycles": int(summ.get("nmajordone", -1)),
                      "stopcode": int(summ.get("stopcode", -1)),
                      "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
    """)


class Casa:
    """An offline CASA 6 set-up in ``root``: site config pointing at casadata, private HOME."""

    def __init__(self, root: Path, threads: int = 2):
        import casadata  # only its path: importing it starts nothing

        self.work = root / "casa"
        home = root / "casa_home"
        self.work.mkdir(parents=True, exist_ok=True)
        home.mkdir(parents=True, exist_ok=True)
        site = root / "casasiteconfig.py"
        data = str(casadata.datapath)
        site.write_text(f"measurespath = {data!r}\ndatapath = [{data!r}]\n"
                        "measures_auto_update = False\ndata_auto_update = False\nnogui = True\n")
        self.env = dict(os.environ, HOME=str(home), CASASITECONFIG=str(site), MPLBACKEND="Agg",
                        OMP_NUM_THREADS=str(threads))


def run_child(code: str, args: list[Any], env: dict[str, str] | None, cwd: Path,
              timeout: float) -> dict[str, Any]:
    """Run ``code`` in a new python process; its last stdout line is a JSON object."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", code, *map(str, args)], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        tail = "\n".join((proc.stdout + proc.stderr).strip().splitlines()[-20:])
        raise RuntimeError(f"child failed (exit {proc.returncode}):\n{tail}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["process_seconds"] = time.perf_counter() - t0
    return out


# ------------------------------------------------------------------------------ grids
GRID_KEYS = ("CTYPE1", "CTYPE2", "CRVAL1", "CRVAL2", "CRPIX1", "CRPIX2", "CDELT1", "CDELT2",
             "NAXIS1", "NAXIS2", "BUNIT", "RADESYS", "EQUINOX", "LONPOLE", "LATPOLE")


def grid_header(path: Path) -> dict[str, Any]:
    from astropy.io import fits

    h = fits.getheader(path)
    return {k: h.get(k) for k in GRID_KEYS}


def compare_grids(ref: dict[str, Any], other: dict[str, Any], cell_deg: float) -> list[str]:
    """Differences between two model grids; empty if the pixel grids coincide."""
    out = []
    for k in GRID_KEYS:
        a, b = ref.get(k), other.get(k)
        if k.startswith("CRVAL"):
            # degrees: must agree to 1e-3 pixel
            if a is None or b is None or abs(float(a) - float(b)) > 1e-3 * cell_deg:
                out.append(f"{k}: {a} vs {b}")
        elif k.startswith(("CRPIX", "CDELT")):
            if a is None or b is None or abs(float(a) - float(b)) > 1e-9 * max(abs(float(a)), 1):
                out.append(f"{k}: {a} vs {b}")
        elif k in ("CTYPE1", "CTYPE2", "NAXIS1", "NAXIS2"):
            if str(a).strip() != str(b).strip():
                out.append(f"{k}: {a} vs {b}")
    return out


def subtract_ready(path: Path, out: Path) -> tuple[Path, str]:
    """``path`` if it passes :func:`xstack.subtract`'s checks of a model image (SIN grid,
    Jy/pixel, even sizes, reference pixel at the center, finite pixels), else a converted copy
    at ``out`` (the celestial plane, its WCS keywords, ``BUNIT = Jy/pixel``); with a note of
    what was done."""
    from astropy.io import fits

    from xstack.errors import XstackError
    from xstack.imaging.subtract import _load_image

    try:
        _load_image(path)
        return path, "accepted as written by exportfits"
    except XstackError as exc:
        note = f"refused ({exc}); "
    with fits.open(path) as hdul:
        h = hdul[0].header.copy()
        data = np.asarray(hdul[0].data, dtype=np.float32)
    plane = np.nan_to_num(data.reshape(data.shape[-2:]))
    hdr = fits.Header()
    for k in ("CTYPE1", "CTYPE2", "CRVAL1", "CRVAL2", "CRPIX1", "CRPIX2", "CDELT1", "CDELT2",
              "CUNIT1", "CUNIT2", "RADESYS", "EQUINOX", "LONPOLE", "LATPOLE"):
        if k in h:
            hdr[k] = h[k]
    hdr["BUNIT"] = "Jy/pixel"
    fits.writeto(out, plane, hdr, overwrite=True)
    return out, note + "converted with astropy (celestial plane, NaN -> 0, BUNIT Jy/pixel)"


# ------------------------------------------------------------------------------ accuracy
def apparent_flux(catalog: Any, store: Path) -> np.ndarray:
    """Catalog flux times the standard primary beam, averaged over the store's channels."""
    from xstack._inputs import partitions
    from xstack.beams import dish_diameter, standard_beam
    from xstack.coords import angular_separation

    name, ds = next(iter(partitions(store)))
    del name
    freq = np.asarray(ds["frequency"].values, dtype=float)
    ra0, dec0 = phase_center_rad(store)
    beam = standard_beam(str(ds.attrs.get("telescope_name", "")), dish_diameter(ds))
    sep = angular_separation(ra0, dec0, np.deg2rad(np.asarray(catalog["ra"], float)),
                             np.deg2rad(np.asarray(catalog["dec"], float)))
    att = beam(sep[:, None], freq[None, :]).mean(axis=1)
    return np.asarray(catalog["flux"], float) * att


def phase_center_rad(store: Path) -> tuple[float, float]:
    from xstack._inputs import partitions

    _, ds = next(iter(partitions(store)))
    ra0, dec0 = (float(x) for x in ds.attrs["phase_center"])
    return ra0, dec0


def model_stats(model: Path, residual: Path, catalog: Any, true_apparent: np.ndarray,
                radius_arcsec: float) -> dict[str, Any]:
    """Components, total flux, flux within ``radius_arcsec`` of each bright source, and the
    residual image's rms (1.4826 MAD) and largest |value| near the sources."""
    from xstack.imaging.fitsio import read_image

    m, wcs, _ = read_image(model)
    r, rwcs, _ = read_image(residual)
    cell = abs(wcs.wcs.cdelt[0]) * 3600
    # the catalog's numbers on the image's grid, without a frame transformation: CASA labels
    # its grid FK5 and xstack ICRS, but both grids are the MS's phase-center numbers (an
    # ICRS -> FK5 transformation would move the positions by ~0.02")
    x, y = wcs.wcs_world2pix(np.asarray(catalog["ra"], float), np.asarray(catalog["dec"], float), 0)
    yy, xx = np.indices(m.shape)
    near = np.zeros(m.shape, bool)
    fluxes, resid_peak = [], []
    for xi, yi in zip(np.atleast_1d(x), np.atleast_1d(y)):
        rad = radius_arcsec / cell
        x0, x1 = int(max(xi - rad - 1, 0)), int(min(xi + rad + 2, m.shape[1]))
        y0, y1 = int(max(yi - rad - 1, 0)), int(min(yi + rad + 2, m.shape[0]))
        disc = (xx[y0:y1, x0:x1] - xi) ** 2 + (yy[y0:y1, x0:x1] - yi) ** 2 <= rad ** 2
        near[y0:y1, x0:x1] |= disc
        fluxes.append(float(m[y0:y1, x0:x1][disc].sum()))
        resid_peak.append(float(np.abs(r[y0:y1, x0:x1][disc]).max()))
    fluxes = np.asarray(fluxes)
    rv = r[np.isfinite(r)]
    return {
        "components": int(np.count_nonzero(m)),
        "model_total_jy": float(m.sum()),
        "model_outside_jy": float(m[~near].sum()),
        "components_outside": int(np.count_nonzero(m[~near])),
        "source_flux_jy": fluxes.tolist(),
        "source_ratio": (fluxes / true_apparent).tolist(),
        "ratio_mean": float(np.mean(fluxes / true_apparent)),
        "ratio_min": float(np.min(fluxes / true_apparent)),
        "ratio_max": float(np.max(fluxes / true_apparent)),
        "residual_rms_jy": float(1.4826 * np.median(np.abs(rv - np.median(rv)))),
        "residual_peak_near_jy": float(max(resid_peak)),
        "pixel_x": np.atleast_1d(x).tolist(), "pixel_y": np.atleast_1d(y).tolist(),
    }


# ------------------------------------------------------------------------------ one scene
def tclean_options(proc: Any, threshold: float, gridder: str, deconvolver: str,
                   wprojplanes: int) -> dict[str, Any]:
    """``tclean`` keywords for a procedure's grid and CLEAN threshold (Jy/beam)."""
    opts: dict[str, Any] = {"imsize": [proc.size, proc.size], "cell": f"{proc.cell_arcsec}arcsec",
                            "threshold": f"{threshold}Jy", "gridder": gridder,
                            "deconvolver": deconvolver}
    if gridder in ("wproject", "widefield"):
        opts["wprojplanes"] = wprojplanes
    return opts


def run_scene(preset: str, scale: float, seed: int, casa_runs: list[tuple[str, str]],
              root: Path, radius_beams: float, timeout: float, wprojplanes: int = -1
              ) -> dict[str, Any]:
    import xstack
    from xstack.reproduce.paper import PROCEDURES
    from xstack.reproduce.run import clean_threshold

    n = int(preset.split("-")[1])
    proc = PROCEDURES[n]
    threshold = clean_threshold(proc, scale)
    work = root / f"{preset}_s{scale:g}_seed{seed}"
    work.mkdir(parents=True, exist_ok=True)
    rec: dict[str, Any] = {"preset": preset, "scale": scale, "seed": seed, "size": proc.size,
                           "cell_arcsec": proc.cell_arcsec, "threshold_jy": threshold,
                           "epsilon": proc.epsilon, "uvmin_m": proc.uvmin_m, "cleans": {}}
    t = time.perf_counter()
    sim = xstack.simulate(xstack.preset_scene(preset, scale=scale), work / "sim.zarr", seed=seed)
    rec["simulate_seconds"] = time.perf_counter() - t
    t = time.perf_counter()
    ms = xstack.export_ms(sim.store, work / "sim.ms")
    rec["export_seconds"] = time.perf_counter() - t
    bright, targets = sim.catalogs["bright"], sim.catalogs["targets"]
    rec["n_bright"], rec["n_targets"] = len(bright), len(targets)
    rec["true_target_flux_jy"] = float(np.mean(np.asarray(targets["flux"], float)))
    true_app = apparent_flux(bright, sim.store)
    rec["bright_true_jy"] = np.asarray(bright["flux"], float).tolist()
    rec["bright_apparent_jy"] = true_app.tolist()
    print(f"[{preset}] simulated {rec['simulate_seconds']:.0f} s, exported {rec['export_seconds']:.0f} s",
          file=sys.stderr, flush=True)

    models: dict[str, Path] = {}
    residual_images: dict[str, Path] = {}
    # xstack's CLEAN, as run_realization calls it
    prefix = work / "xstack"
    info = run_child(XSTACK_CLEAN, [sim.store, prefix, proc.size, proc.cell_arcsec, threshold,
                                    proc.epsilon], None, work, timeout)
    rec["cleans"]["xstack clark"] = info
    models["xstack clark"] = Path(str(prefix) + ".model.fits")
    residual_images["xstack clark"] = Path(str(prefix) + ".residual.fits")
    beam = info["beam_arcsec"]
    rec["beam_arcsec"] = beam
    rec["expected_noise_jy"] = 1.0 / math.sqrt(info["sum_weights"])
    print(f"[{preset}] xstack clark {info['seconds']:.0f} s", file=sys.stderr, flush=True)

    casa = Casa(work) if casa_runs else None
    for gridder, deconvolver in casa_runs:
        label = f"CASA {gridder} {deconvolver}"
        if gridder in ("wproject", "widefield"):
            label += f" (wprojplanes {wprojplanes})"
        prefix = casa.work / f"{gridder}_{deconvolver}"
        opts = tclean_options(proc, threshold, gridder, deconvolver, wprojplanes)
        try:
            info = run_child(CASA_CLEAN, [ms, prefix, json.dumps(opts)], casa.env, casa.work, timeout)
        except (RuntimeError, subprocess.TimeoutExpired) as exc:
            rec["cleans"][label] = {"error": str(exc)[-2000:]}
            print(f"[{preset}] {label} failed: {exc}", file=sys.stderr, flush=True)
            continue
        rec["cleans"][label] = info
        models[label] = Path(str(prefix) + ".model.fits")
        residual_images[label] = Path(str(prefix) + ".residual.fits")
        print(f"[{preset}] {label} {info['seconds']:.0f} s", file=sys.stderr, flush=True)

    cell_deg = proc.cell_arcsec / 3600
    ref_grid = grid_header(models["xstack clark"])
    rec["grid_xstack"] = ref_grid
    radius = radius_beams * float(beam[0])
    rec["radius_arcsec"] = radius
    for label, model in models.items():
        c = rec["cleans"][label]
        c["grid_differences"] = compare_grids(ref_grid, grid_header(model), cell_deg)
        if label != "xstack clark":
            c["grid"] = grid_header(model)
            model, note = subtract_ready(model, model.with_suffix(".xstack.fits"))
            c["subtract_model_note"] = note
            models[label] = model
        c.update(model_stats(model, residual_images[label], bright, true_app, radius))

    # subtract each model (and the perfect catalog), uv-stack the targets with pb weights
    stacks: dict[str, Any] = {}
    for label, model in [("perfect (catalog)", bright), *models.items()]:
        out = work / f"resid_{label.replace(' ', '_').replace('(', '').replace(')', '')}.zarr"
        t = time.perf_counter()
        xstack.subtract(sim.store, model, out)
        t_sub = time.perf_counter() - t
        st = xstack.stack_uv(out, targets, weighting="pb", uvmin=proc.uvmin_m)
        # what the model left of the bright sources, seen by the data themselves (no imager):
        # the uv-stacked residual at their true positions, all baselines
        left = xstack.stack_uv(out, bright, weighting="pb")
        stacks[label] = {"flux_jy": float(st.flux_jy), "flux_err_jy": float(st.flux_err_jy),
                         "subtract_seconds": t_sub, "bright_left_jy": float(left.flux_jy),
                         "bright_left_err_jy": float(left.flux_err_jy)}
        shutil.rmtree(out, ignore_errors=True)
    st = xstack.stack_uv(sim.store, targets, weighting="pb", uvmin=proc.uvmin_m)
    left = xstack.stack_uv(sim.store, bright, weighting="pb")
    stacks["nothing subtracted"] = {"flux_jy": float(st.flux_jy), "flux_err_jy": float(st.flux_err_jy),
                                    "bright_left_jy": float(left.flux_jy),
                                    "bright_left_err_jy": float(left.flux_err_jy)}
    rec["stacks"] = stacks
    return rec


# ------------------------------------------------------------------------------ tables
def fmt_uj(x: float, nd: int = 2) -> str:
    return f"{x * 1e6:.{nd}f}"


def tables(rec: dict[str, Any]) -> str:
    lines = [f"### {rec['preset']} at scale {rec['scale']:g}, seed {rec['seed']}", "",
             f"{rec['size']} x {rec['size']} pixels of {rec['cell_arcsec']}\", threshold "
             f"{fmt_uj(rec['threshold_jy'], 1)} µJy, {rec['n_bright']} bright source(s), "
             f"{rec['n_targets']} targets of {fmt_uj(rec['true_target_flux_jy'])} µJy; beam "
             f"{rec['beam_arcsec'][0]:.2f}\" x {rec['beam_arcsec'][1]:.2f}\"; expected thermal "
             f"noise 1/sqrt(sum w) = {fmt_uj(rec['expected_noise_jy'])} µJy/beam; source flux "
             f"summed within {rec['radius_arcsec']:.1f}\" ({rec['radius_arcsec'] / rec['beam_arcsec'][0]:.0f}"
             " beam major axes) of the true position. Simulate "
             f"{rec['simulate_seconds']:.0f} s, export {rec['export_seconds']:.0f} s.", ""]
    lines += ["| CLEAN | wall time (s) | peak RSS (MB) | iterations | major cycles | "
              "components (nonzero pixels) | grid = xstack's |",
              "|---|---|---|---|---|---|---|"]
    for label, c in rec["cleans"].items():
        if "error" in c:
            lines.append(f"| {label} | failed | | | | | |")
            continue
        lines.append(f"| {label} | {c['seconds']:.1f} | {c['peak_rss_mb']:.0f} | {c['iterations']} | "
                     f"{c['major_cycles']} | {c['components']} | "
                     f"{'yes' if not c['grid_differences'] else '; '.join(c['grid_differences'])} |")
    lines += ["", "| CLEAN | CLEANed / true apparent flux: mean (min–max) | model total (mJy) | "
              "model flux away from the sources (µJy, components) | residual rms (µJy/beam) "
              "/ expected | max abs residual near a source (µJy/beam) |",
              "|---|---|---|---|---|---|"]
    app = np.asarray(rec["bright_apparent_jy"])
    for label, c in rec["cleans"].items():
        if "error" in c:
            continue
        lines.append(f"| {label} | {c['ratio_mean']:.4f} ({c['ratio_min']:.4f}–{c['ratio_max']:.4f}) | "
                     f"{c['model_total_jy'] * 1e3:.4f} | {fmt_uj(c['model_outside_jy'], 1)} "
                     f"({c['components_outside']}) | {fmt_uj(c['residual_rms_jy'])} / "
                     f"{fmt_uj(rec['expected_noise_jy'])} = "
                     f"{c['residual_rms_jy'] / rec['expected_noise_jy']:.3f} | "
                     f"{fmt_uj(c['residual_peak_near_jy'], 1)} |")
    lines += ["", "True apparent flux of the bright sources (mJy): "
              + ", ".join(f"{a * 1e3:.3f}" for a in app) + f"; their sum {app.sum() * 1e3:.3f} mJy.", ""]
    st = rec["stacks"]
    ref = st["perfect (catalog)"]["flux_jy"]
    xs = st.get("xstack clark", {}).get("flux_jy", float("nan"))
    bright_true = float(np.mean(rec["bright_true_jy"]))
    lines += [f"uv-stacked targets (weighting pb, uvmin {rec['uvmin_m']}) on the data minus each "
              "model; *bright left*: the same residual uv-stacked on the bright sources' true "
              f"positions (pb weights, all baselines; mean true flux {bright_true * 1e3:.2f} mJy):", "",
              "| model subtracted | stacked flux (µJy) | error (µJy) | − perfect (µJy) | − xstack's (µJy) "
              "| − true mean (µJy) | bright left (µJy) | bright left / true |",
              "|---|---|---|---|---|---|---|---|"]
    for label, s in st.items():
        lines.append(f"| {label} | {fmt_uj(s['flux_jy'], 3)} | {fmt_uj(s['flux_err_jy'], 3)} | "
                     f"{fmt_uj(s['flux_jy'] - ref, 3)} | {fmt_uj(s['flux_jy'] - xs, 3)} | "
                     f"{fmt_uj(s['flux_jy'] - rec['true_target_flux_jy'], 3)} | "
                     f"{fmt_uj(s['bright_left_jy'], 1)} ± {fmt_uj(s['bright_left_err_jy'], 1)} | "
                     f"{s['bright_left_jy'] / bright_true:+.4f} |")
    lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", action="append", help="paper preset (repeatable); default paper-2, paper-3")
    p.add_argument("--scale", type=float, default=0.05)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--casa", action="append",
                   help="GRIDDER:DECONVOLVER of a tclean run (repeatable); default "
                        "wproject:hogbom and standard:hogbom")
    p.add_argument("--wprojplanes", type=int, default=-1,
                   help="tclean wprojplanes of the wproject runs (-1: CASA chooses)")
    p.add_argument("--radius-beams", type=float, default=3.0,
                   help="source flux: model summed within this many beam major axes")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds per CLEAN process")
    p.add_argument("--json", type=Path, help="also write the measured numbers here")
    p.add_argument("--keep", action="store_true", help="keep the scratch directory")
    a = p.parse_args(argv)
    scenes = a.scene or ["paper-2", "paper-3"]
    casa_runs = [tuple(s.split(":")) for s in (a.casa or ["wproject:hogbom", "standard:hogbom"])]
    root = Path(tempfile.mkdtemp(prefix="bench_clean_casa-", dir="/tmp"))
    t0 = time.perf_counter()
    records = []
    try:
        for s in scenes:
            rec = run_scene(s, a.scale, a.seed, casa_runs, root, a.radius_beams, a.timeout,
                            a.wprojplanes)
            records.append(rec)
            print(tables(rec), flush=True)
            if a.json:
                a.json.write_text(json.dumps(records, indent=1, default=str))
    finally:
        if not a.keep:
            shutil.rmtree(root, ignore_errors=True)
        else:
            print(f"scratch kept in {root}", file=sys.stderr)
    print(f"Whole run {time.perf_counter() - t0:.0f} s; load average at the end "
          f"{os.getloadavg()[0]:.1f}.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
