"""What each ingredient of a paper type's sky does to its image and uv stacks (issue 12).

``xstack reproduce``'s chain (:func:`xstack.reproduce.run.run_realization`: simulate, CLEAN
the bright sources to the paper's threshold, subtract, image the residual, uv- and
image-stack the targets, for type 7 fit Gaussians in both domains) run on the type's own
scene and on the same scene with ingredients taken out, one seed at a time:

* ``targets``: the targets alone, no thermal noise, no bright sources (the bright population
  is kept with no sources, so the targets are the same as in the full scene);
* ``targets+noise``: the targets with the thermal noise, no bright sources;
* ``targets+bright``: the targets and the bright sources, CLEANed and subtracted as in the
  full run, no thermal noise;
* ``full``: the preset as ``xstack reproduce`` runs it.

Without noise a realisation measures a bias with no scatter but the targets' own sidelobes
(and, with the bright sources, what CLEAN leaves of them), so a few seeds say which
ingredient makes the image stack differ from the uv stack, where the Monte Carlo of the full
scene measures it only to its scatter (type 7: image / uv 0.926 ± 0.06 from 20
realisations, the paper's 1.017).

Run time ~3-4 min per variant and seed at full size on the 2-core machine; at scale 0.02
(18 targets) ~25 s.

``--confusion`` instead runs one variant of one seed with its intermediates kept (the
residual store and map) and prints what the bright sources' CLEAN residuals put at the
targets: each target's residual-map pixel minus its true flux (noiseless with
``--variants targets+bright``: the residuals of the bright sources and the other targets
only), binned by the distance to the nearest bright source above 100 µJy, and the image and
uv stacks with and without weights and the uv cut.

``--clean casa`` (with ``--confusion``) CLEANs with CASA's ``tclean`` instead (w-projection,
``--deconvolver``, ``--wprojplanes``; the ``casa`` extra), the model subtracted and everything
after it done by xstack, so that two runs differ by the CLEAN model alone; ``--integration``
replaces the preset's integration time (noiseless type 6 at 60 s: CASA's Clark CLEAN 586 s
and 5.9 GB on the 2-core machine).

Measured 2026-12-07 (docs/reproduction.md, "What the image stack's deficit is made of" and
"CASA's CLEAN in place of xstack's"): CASA's Clark and Högbom CLEANs leave type 6's image
stack at 0.815 of the uv stack, xstack's at 0.823, multiscale at 0.881;
type 7's targets alone (seed 0, noiseless) uv fit 2.959 µJy / 1.500″, image fit 2.969 µJy /
1.499″ for 2.96 µJy / 1.5″; type 6's seeds 0-3 without the bright sources image - uv
-0.007 µJy, with them -0.143 µJy.

Usage::

    python benchmarks/diagnose_sky_effects.py --type 7 --seeds 0 1 [--variants ...]
                                              [--scale 1] [--workdir DIR] [--json]
    python benchmarks/diagnose_sky_effects.py --type 6 --seeds 0 --variants targets+bright \
                                              --confusion
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

import xstack
from xstack.reproduce import run as rr

VARIANTS = ("targets", "targets+noise", "targets+bright", "full")


def variant_scene(n: int, scale: float, variant: str, integration: float | None = None) -> Any:
    """Type ``n``'s preset scene at ``scale`` with the ingredients ``variant`` leaves out
    (and, if ``integration`` is given, integrations of that many seconds)."""
    scene = xstack.preset_scene(f"paper-{n}", scale=scale)
    if integration is not None:
        scene = dataclasses.replace(scene, observation=dataclasses.replace(
            scene.observation, integration=float(integration)))
    if variant == "full":
        return scene
    keep_bright = "bright" in variant
    keep_noise = "noise" in variant
    # population i draws from its own random stream (simulate's SeedSequence(seed, (1, i))):
    # emptying a population, not removing it, keeps the targets' positions and fluxes
    pops = [p if p.name == "targets" or keep_bright else dataclasses.replace(p, count=0)
            for p in scene.populations]
    effects = dataclasses.replace(scene.effects,
                                  noise=scene.effects.noise if keep_noise else None)
    return dataclasses.replace(scene, populations=pops, effects=effects)


#: the record's keys each table row shows (µJy, arcsec or counts)
COLUMNS = {
    "uv_flux_jy": "uv", "image_flux_jy": "image", "image_flux_subpixel_jy": "image sub-px",
    "image_flux_filtered_jy": "image filtered", "uv_fwhm_arcsec": "uv FWHM",
    "image_fwhm_arcsec": "image FWHM", "clean_components": "CLEAN comps",
}


def casa_clean_subtract(store: Path, proc: Any, threshold: float, work: Path,
                        deconvolver: str = "clark", wprojplanes: int = 128,
                        timeout: float = 4 * 3600) -> dict[str, Any]:
    """CASA's ``tclean`` in place of :func:`xstack.reproduce.run.clean_subtract`: the store
    exported to an MS, CLEANed by CASA (w-projection, natural weighting, the procedure's
    size, cell and ``threshold``, niter 100 000, gain 0.1) in its own process, and CASA's
    model subtracted from the same store with :func:`xstack.subtract` into
    ``work/residual.zarr``. Everything after (the residual map, the stacks) is xstack's, so
    two runs differ by the CLEAN model alone. Needs the ``casa`` extra."""
    import sys

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import bench_clean_casa as bcc

    ms = xstack.export_ms(store, work / "sim.ms")
    casa = bcc.Casa(work)
    prefix = casa.work / f"wproject_{deconvolver}"
    opts = bcc.tclean_options(proc, threshold, "wproject", deconvolver, wprojplanes)
    if deconvolver == "multiscale":
        # point components, and Gaussians of 3" and 10" (the bright sources' 0.5-5" FWHM
        # convolved with the ~1.4" beam)
        opts["scales"] = [0, 6, 20]
    info = bcc.run_child(bcc.CASA_CLEAN, [ms, prefix, json.dumps(opts)], casa.env, casa.work,
                         timeout)
    model, note = bcc.subtract_ready(Path(str(prefix) + ".model.fits"),
                                     work / "casa_model.xstack.fits")
    xstack.subtract(store, model, work / "residual.zarr")
    scales = f" (scales {opts['scales']} pixels)" if "scales" in opts else ""
    return {"clean": f"CASA tclean wproject ({wprojplanes} planes) {deconvolver}{scales}",
            "clean_seconds": info["seconds"], "clean_peak_rss_mb": info["peak_rss_mb"],
            "clean_iterations": info["iterations"], "clean_major_cycles": info["major_cycles"],
            "clean_stopcode": info["stopcode"], "model_note": note, "model": str(model)}


def xstack_clean_subtract(store: Path, proc: Any, threshold: float, work: Path) -> dict[str, Any]:
    """:func:`xstack.reproduce.run.clean_subtract`, timed, in the same terms as
    :func:`casa_clean_subtract`."""
    t0 = time.perf_counter()
    _, stats = rr.clean_subtract(store, proc, threshold, work)
    seconds = time.perf_counter() - t0  # the subtraction included (CASA's is not)
    return {"clean": "xstack clean_data clark", "clean_seconds_with_subtract": seconds,
            "clean_iterations": int(stats["clean_components"]),
            "model": str(work / "model.fits")}


def confusion(n: int, seed: int, scale: float, variant: str, work: Path, clean: str = "xstack",
              integration: float | None = None, deconvolver: str = "clark",
              wprojplanes: int = 128) -> dict[str, Any]:
    """The residual map's value at each target minus its true flux, by distance to the
    nearest bright source, and the stacks of the same residual (fluxes in Jy).

    ``clean="casa"`` CLEANs with CASA's ``tclean`` instead of xstack's
    (:func:`casa_clean_subtract`); ``integration`` (s) replaces the preset's integration
    time, which makes a noiseless data set small enough for CASA's gridder."""
    from astropy.io import fits
    from astropy.table import Table
    from astropy.wcs import WCS

    from xstack.reproduce.paper import PROCEDURES

    proc = PROCEDURES[n]
    scene = variant_scene(n, scale, variant, integration)
    work.mkdir(parents=True, exist_ok=True)
    made = work / "clean.json"
    if not (work / "residual.fits").exists():
        sim = xstack.simulate(scene, work / "sim.zarr", seed=seed)
        threshold = rr.clean_threshold(proc, scale)
        if clean == "casa":
            info = casa_clean_subtract(sim.store, proc, threshold, work, deconvolver, wprojplanes)
        else:
            info = xstack_clean_subtract(sim.store, proc, threshold, work)
        for name, cat in sim.catalogs.items():
            cat.write(work / f"{name}.ecsv", overwrite=True)
        rr.residual_images(work / "residual.zarr", proc, work)
        made.write_text(json.dumps(info))
    info = json.loads(made.read_text()) if made.exists() else {"clean": "xstack clean_data clark"}
    info.update(_model_sums(Path(info.get("model", work / "model.fits"))))
    targets, bright = Table.read(work / "targets.ecsv"), Table.read(work / "bright.ecsv")
    with fits.open(work / "residual.fits") as hdul:
        data = np.squeeze(hdul[0].data).astype(float)
        wcs = WCS(hdul[0].header).celestial
    x, y = wcs.world_to_pixel_values(np.asarray(targets["ra"], float),
                                     np.asarray(targets["dec"], float))
    ix, iy = np.round(x).astype(int), np.round(y).astype(int)
    inside = (ix >= 0) & (iy >= 0) & (ix < data.shape[1]) & (iy < data.shape[0])
    value = np.full(len(targets), np.nan)
    value[inside] = data[iy[inside], ix[inside]]
    d = value - np.asarray(targets["flux"], float)
    good = np.isfinite(d)
    strong = np.asarray(bright["flux"], float) > STRONG_JY
    sep = nearest_arcsec(targets, bright[strong])
    bins = distance_bins(d, sep)
    fin = np.isfinite(data)
    # the same map at uniformly random positions of the targets' box: what a stack expects
    # over realisations, unweighted and with 1/sigma_k^2 (sigma_k the clipped local noise of
    # this map and a thermal noise of the type's map in quadrature, ~1/A corrected)
    from xstack.uvstack.localnoise import measure_local_noise

    rng = np.random.default_rng(2)
    box = next(p for p in scene.populations if p.name == "targets").positions.size_arcsec
    half = int(round(0.5 * min(box) / proc.cell_arcsec))
    cy, cx = data.shape[0] // 2, data.shape[1] // 2
    ry = rng.integers(cy - half, cy + half, 20000)
    rx = rng.integers(cx - half, cx + half, 20000)
    keep = np.isfinite(data[ry, rx])
    ry, rx = ry[keep], rx[keep]
    rv = data[ry, rx]
    rra, rdec = wcs.pixel_to_world_values(rx, ry)
    sigma = np.asarray(measure_local_noise(work / "residual.fits", np.c_[rra, rdec]).sigma,
                       float)
    with fits.open(work / "residual.pb.fits") as hdul:
        beam = np.squeeze(hdul[0].data).astype(float)[ry, rx]
    random = {"n": int(rv.size), "mean_jy": float(rv.mean()), "median_jy": float(np.median(rv)),
              "fraction_above_10ujy": float(np.mean(rv > 1e-5)),
              "mean_from_above_10ujy_jy": float(rv[rv > 1e-5].sum() / rv.size)}
    for thermal in (0.0, proc.thermal_noise_jy):
        w = 1.0 / (sigma**2 + (thermal / beam) ** 2)
        ok = np.isfinite(w)
        random[f"weighted_mean_thermal_{thermal * 1e6:g}ujy_jy"] = float(
            np.sum(w[ok] * rv[ok]) / np.sum(w[ok]))
    stacks = {}
    for weighting in ("none", "sigma2"):
        stacks[f"image sub-pixel, {weighting}"] = float(xstack.stack_images(
            [work / "residual.fits"], targets, weighting=weighting, subpixel="fourier",
            psf=[work / "residual.psf.fits"], plot=False).flux_jy)
        for cut in (proc.uvmin_m, None):
            label = f"> {cut:g} m" if cut else "all baselines"
            stacks[f"uv {label}, {weighting}"] = float(
                xstack.stack_uv(work / "residual.zarr", targets, weighting=weighting, uvmin=cut,
                                noise_image=work / "residual.fits" if weighting == "sigma2"
                                else None).flux_jy)
    # what the model left of the bright sources in the data (no imager): the residual
    # uv-stacked at their true positions, pb weights, all baselines and beyond the uv cut
    # (nothing to stack in a variant without bright sources: no numbers rather than NaN)
    strong_cat = bright[strong]
    left = {}
    for cut in (None, proc.uvmin_m) if len(strong_cat) else ():
        label = f"> {cut:g} m" if cut else "all baselines"
        left[label] = float(xstack.stack_uv(work / "residual.zarr", strong_cat, weighting="pb",
                                            uvmin=cut).flux_jy)
    return {"type": n, "seed": seed, "variant": variant, "integration_s": integration,
            "scene_sha256": scene.digest(), **info, "bright_left_mean_jy": left,
            "bright_true_mean_jy": float(np.mean(strong_cat["flux"])) if left else None,
            "true_flux_jy": float(np.mean(targets["flux"])),
            "target_minus_true_mean_jy": float(d[good].mean()),
            "target_minus_true_se_jy": float(d[good].std(ddof=1) / np.sqrt(good.sum())),
            "target_minus_true_percentiles_jy": dict(zip(
                ("1", "5", "25", "50", "75", "95", "99"),
                np.percentile(d[good], [1, 5, 25, 50, 75, 95, 99]).tolist())),
            "map_mean_jy_per_beam": float(data[fin].mean()),
            "map_median_jy_per_beam": float(np.median(data[fin])),
            "random_positions": random,
            "by_distance_to_bright": bins, "stacks_jy": stacks}


#: the bright sources (Jy) whose distance bins the targets and whose leftovers are stacked
STRONG_JY = 1e-4


def nearest_arcsec(targets: Any, sources: Any) -> np.ndarray:
    """Each target's distance (arcsec) to the nearest of ``sources`` (tables with ``ra``,
    ``dec`` in degrees); infinite for all targets when ``sources`` is empty, so that they
    fall in the farthest bin rather than failing the match."""
    from astropy.coordinates import SkyCoord

    if len(sources) == 0:
        return np.full(len(targets), np.inf)
    _, sep, _ = SkyCoord(targets["ra"], targets["dec"], unit="deg").match_to_catalog_sky(
        SkyCoord(sources["ra"], sources["dec"], unit="deg"))
    return np.asarray(sep.arcsec, float)


def distance_bins(values: np.ndarray, sep: np.ndarray,
                  edges: tuple[float, ...] = (0, 10, 30, 60, 120, np.inf)) -> list[dict[str, Any]]:
    """Mean and median of the finite ``values`` (Jy) in bins of ``sep`` (arcsec) between
    ``edges``; the last bin is closed above, so an infinite distance (no source at all)
    counts in it."""
    good = np.isfinite(values)
    bins = []
    for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        upper = sep <= hi if i == len(edges) - 2 else sep < hi
        m = good & (sep >= lo) & upper
        bins.append({"from_arcsec": lo, "to_arcsec": hi, "n": int(m.sum()),
                     "mean_jy": float(values[m].mean()) if m.any() else None,
                     "median_jy": float(np.median(values[m])) if m.any() else None})
    return bins


def _model_sums(model: Path) -> dict[str, Any]:
    """The CLEAN model's total flux (Jy) and number of nonzero pixels."""
    from astropy.io import fits

    if not model.exists():
        return {}
    with fits.open(model) as hdul:
        m = np.nan_to_num(np.asarray(hdul[0].data, dtype=float))
    return {"model_total_jy": float(m.sum()), "model_components": int(np.count_nonzero(m))}


def print_confusion(c: dict[str, Any]) -> None:
    """The :func:`confusion` dictionary as tables (µJy)."""
    u = 1e6
    print(f"CLEAN: {c.get('clean', 'xstack clean_data clark')}; integration "
          f"{c.get('integration_s') or 'as the preset'} s; model {c.get('model_total_jy', 0) * 1e3:.4f} mJy "
          f"in {c.get('model_components', 'n/a')} pixels")
    for k, v in c.get("bright_left_mean_jy", {}).items():
        print(f"bright sources > 100 µJy left in the data ({k}): {v * u:.3f} µJy of "
              f"{c['bright_true_mean_jy'] * u:.1f} µJy on average")
    print(f"type {c['type']} seed {c['seed']} {c['variant']}: true mean flux "
          f"{c['true_flux_jy'] * u:.3f} µJy; residual map mean {c['map_mean_jy_per_beam'] * u:.3f}, "
          f"median {c['map_median_jy_per_beam'] * u:.3f} µJy/beam")
    print(f"target pixel - true flux: mean {c['target_minus_true_mean_jy'] * u:.3f} ± "
          f"{c['target_minus_true_se_jy'] * u:.3f} µJy; percentiles "
          + ", ".join(f"{k}%: {v * u:.2f}" for k, v in c["target_minus_true_percentiles_jy"].items()))
    print(f"{'nearest bright > 100 µJy':>26s} {'n':>5s} {'mean':>8s} {'median':>8s}")
    for b in c["by_distance_to_bright"]:
        mean = "n/a" if b["mean_jy"] is None else f"{b['mean_jy'] * u:8.3f}"
        med = "n/a" if b["median_jy"] is None else f"{b['median_jy'] * u:8.3f}"
        print(f"{b['from_arcsec']:>11g}-{b['to_arcsec']:<8g} arcsec {b['n']:5d} {mean:>8s} {med:>8s}")
    r = c["random_positions"]
    print(f"{r['n']} random positions: mean {r['mean_jy'] * u:.3f}, median "
          f"{r['median_jy'] * u:.3f} µJy; {100 * r['fraction_above_10ujy']:.2f} % above 10 µJy "
          f"hold {r['mean_from_above_10ujy_jy'] * u:.3f} of the mean; weighted "
          + ", ".join(f"{k}: {v * u:.3f}" for k, v in r.items() if k.startswith("weighted")))
    for k, v in c["stacks_jy"].items():
        print(f"{k:32s} {v * u:8.3f} µJy")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--type", type=int, default=7)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--workdir", type=Path, default=Path("diagnose-sky-effects"))
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--confusion", action="store_true",
                    help="one seed and variant, intermediates kept: what is at the targets")
    ap.add_argument("--clean", choices=("xstack", "casa"), default="xstack",
                    help="with --confusion: whose CLEAN removes the bright sources (casa: "
                         "tclean, w-projection; needs the casa extra)")
    ap.add_argument("--deconvolver", default="clark", help="with --clean casa: tclean's")
    ap.add_argument("--wprojplanes", type=int, default=128, help="with --clean casa: tclean's")
    ap.add_argument("--integration", type=float,
                    help="with --confusion: integration time (s) in place of the preset's")
    a = ap.parse_args()
    if a.confusion:
        tag = f"{a.variants[0]}-maps"
        if a.clean == "casa":
            tag += f"-casa-{a.deconvolver}"
        if a.integration:
            tag += f"-int{a.integration:g}"
        c = confusion(a.type, a.seeds[0], a.scale, a.variants[0],
                      a.workdir / f"type{a.type}" / tag / f"seed{a.seeds[0]}", clean=a.clean,
                      integration=a.integration, deconvolver=a.deconvolver,
                      wprojplanes=a.wprojplanes)
        print(json.dumps(c)) if a.json else print_confusion(c)
        return
    rows = []
    for seed in a.seeds:
        for variant in a.variants:
            work = a.workdir / f"type{a.type}" / variant
            work.mkdir(parents=True, exist_ok=True)
            line = work / f"seed{seed}.json"
            if line.exists():  # resumable: a finished variant and seed is not run again
                rec = json.loads(line.read_text())
            else:
                t0 = time.perf_counter()
                scene = variant_scene(a.type, a.scale, variant)
                rec = rr.run_realization(a.type, seed, a.scale, work, scene=scene)
                rec["seconds"] = time.perf_counter() - t0
                rec.update(type=a.type, scale=a.scale, variant=variant,
                           scene_sha256=scene.digest())
                tmp = line.with_suffix(".tmp")
                tmp.write_text(json.dumps(rec))
                tmp.replace(line)
            rows.append({"seed": seed, "variant": variant, **rec})
            if not a.json:
                print(f"type {a.type} seed {seed} {variant}: done ({rec['seconds']:.0f} s)",
                      flush=True)
    if a.json:
        print(json.dumps({"type": a.type, "scale": a.scale, "rows": rows}))
        return
    true = rows[0]["true_flux_jy"]
    print(f"\ntype {a.type}, scale {a.scale}: true mean flux {true * 1e6:.3f} µJy")
    cols = [k for k in COLUMNS if any(r.get(k) is not None for r in rows)]
    print(f"{'seed':>4s} {'variant':15s} " + " ".join(f"{COLUMNS[k]:>14s}" for k in cols)
          + f" {'image / uv':>10s} {'s':>6s}")
    for r in rows:
        cells = []
        for k in cols:
            v = r.get(k)
            scale = 1e6 if k.endswith("_jy") else 1.0
            cells.append(f"{'n/a':>14s}" if v is None else
                         f"{v * scale:14.0f}" if k == "clean_components" else f"{v * scale:14.3f}")
        ratio = (r["image_flux_jy"] / r["uv_flux_jy"]
                 if r.get("image_flux_jy") is not None and r.get("uv_flux_jy") else np.nan)
        print(f"{r['seed']:4d} {r['variant']:15s} " + " ".join(cells)
              + f" {ratio:10.4f} {r['seconds']:6.0f}")


if __name__ == "__main__":
    main()
