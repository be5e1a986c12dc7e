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

Usage::

    python benchmarks/diagnose_sky_effects.py --type 7 --seeds 0 1 [--variants ...]
                                              [--scale 1] [--workdir DIR] [--json]
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


def variant_scene(n: int, scale: float, variant: str) -> Any:
    """Type ``n``'s preset scene at ``scale`` with the ingredients ``variant`` leaves out."""
    scene = xstack.preset_scene(f"paper-{n}", scale=scale)
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--type", type=int, default=7)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    ap.add_argument("--scale", type=float, default=1.0)
    ap.add_argument("--workdir", type=Path, default=Path("diagnose-sky-effects"))
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
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
                rec = rr.run_realization(a.type, seed, a.scale, work,
                                         scene=variant_scene(a.type, a.scale, variant))
                rec["seconds"] = time.perf_counter() - t0
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
