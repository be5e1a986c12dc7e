"""Why the image stack of paper type 6 is below its uv stack: the position weights (issue 12).

One realisation of ``xstack reproduce``'s chain for type 6 at full size (simulate, CLEAN the
bright sources to the paper's 50 µJy/beam, subtract, image the residual), its intermediates
kept in ``--workdir``; then the same residual stacked seven ways. The two stacks are the same
linear operation on the same data, so with the same position weights they must agree (to
the pixelisation of nearest-pixel alignment, which sub-pixel alignment removes):

* ``uv_cut``, ``uv_all``: ``stack_uv`` with sigma_k from the residual map (its 3-sigma
  clipped local noise), with and without the 5000 m cut;
* ``im_nearest``, ``im_sub``: ``stack_images`` with its own default sigma_k (since
  2026-12-06 the uv stack's: 3-sigma clipped on ~300 beam areas), nearest-pixel and sub-pixel;
* ``im_nearest_std64``, ``im_sub_std64``: the same with the paper's plain standard deviation
  on the 64-pixel stamp (``noise_estimator="std", noise_stamp_size=64``; the default before);
* ``im_sub_uvweights``: the image stack with the uv stack's own position weights;
* ``uv_all_noweights``, ``im_sub_noweights``: both with no position weights.

Measured 2026-12-05 on seed 2 (2-core machine, ~8 min), when ``im_sub`` was today's
``im_sub_std64``: uv_all 0.938, im_sub 0.715,
im_sub_uvweights 0.932, uv_all_noweights 0.880, im_sub_noweights 0.883 µJy (true 1.014):
on seed 5 1.049 (0.864 on all baselines), 0.688, 0.853, 0.917, 0.903: the image deficit
is the plain standard deviation's weights (docs/reproduction.md, type 6).

A second table image-stacks the same map (sub-pixel) with ``stack_images``' own
``noise_estimator`` (clipped, mad, std) on its default stamp (~300 beam areas) and on the
64-pixel stamp: only the clipped estimator on the larger stamp gives the uv value (seed 2:
0.932; std on 64 px: 0.717).

Usage::

    python benchmarks/diagnose_image_weights.py [--seed 2] [--workdir DIR] [--json]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from astropy.table import Table

import xstack
from xstack.imstack.kernels import NOISE_ESTIMATORS as ESTIMATORS
from xstack.reproduce import run as rr
from xstack.reproduce.paper import PROCEDURES

#: the paper's sigma_k as stack_images measured it before 2026-12-06
STD64 = {"noise_estimator": "std", "noise_stamp_size": 64}

TYPE = 6


def prepare(seed: int, work: Path) -> tuple[Path, Path, Path, Table]:
    """The residual store, its map and PSF, and the targets (made once per work directory)."""
    proc = PROCEDURES[TYPE]
    if not (work / "residual.zarr").exists():
        scene = xstack.preset_scene(f"paper-{TYPE}", scale=1)
        sim = xstack.simulate(scene, work / "sim.zarr", seed=seed)
        rr.clean_subtract(sim.store, proc, rr.clean_threshold(proc, 1), work)
        sim.catalogs["targets"].write(work / "targets.ecsv", overwrite=True)
        rr.residual_images(work / "residual.zarr", proc, work)
    return (work / "residual.zarr", work / "residual.fits", work / "residual.psf.fits",
            Table.read(work / "targets.ecsv"))


def stacks(res: Path, image: Path, psf: Path, targets: Table) -> dict[str, tuple[float, float]]:
    """(flux, error) in Jy of each way of stacking the residual."""
    proc = PROCEDURES[TYPE]
    im = lambda t, **kw: xstack.stack_images([image], t, psf=[psf], plot=False, **kw)  # noqa: E731
    uv = xstack.stack_uv(res, targets, weighting="sigma2", uvmin=proc.uvmin_m, noise_image=image)
    w = np.asarray(uv.positions["weight_used"], dtype=float)
    weighted = targets.copy()
    weighted["weight"] = w.max(axis=1) if w.ndim == 2 else w
    out = {
        "uv_cut": uv,
        "uv_all": xstack.stack_uv(res, targets, weighting="sigma2", noise_image=image),
        "im_nearest": im(targets, weighting="sigma2"),
        "im_sub": im(targets, weighting="sigma2", subpixel="fourier"),
        "im_nearest_std64": im(targets, weighting="sigma2", **STD64),
        "im_sub_std64": im(targets, weighting="sigma2", subpixel="fourier", **STD64),
        "im_sub_uvweights": im(weighted, weighting="column", subpixel="fourier"),
        "uv_all_noweights": xstack.stack_uv(res, targets, weighting="none"),
        "im_sub_noweights": im(targets, weighting="none", subpixel="fourier"),
    }
    return {k: (float(v.flux_jy), float(v.flux_err_jy)) for k, v in out.items()}


def estimators(image: Path, psf: Path, targets: Table) -> dict[str, float]:
    """Sub-pixel image-stacked flux (Jy) with 1/sigma_k^2 weights of each local-noise
    estimator, on its default stamp and on 64 pixels."""
    out = {}
    for est in ESTIMATORS:
        for stamp in (None, 64):
            res = xstack.stack_images([image], targets, weighting="sigma2", psf=[psf],
                                      plot=False, subpixel="fourier", noise_estimator=est,
                                      noise_stamp_size=stamp)
            out[f"{est}, {'~300 beams' if stamp is None else f'{stamp} px'}"] = float(res.flux_jy)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--workdir", type=Path, default=Path("diagnose-image-weights"))
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    work = a.workdir / f"seed{a.seed}"
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    res, image, psf, targets = prepare(a.seed, work)
    result = stacks(res, image, psf, targets)
    by_estimator = estimators(image, psf, targets)
    true = float(np.mean(np.asarray(targets["flux"], dtype=float)))
    if a.json:
        print(json.dumps({"seed": a.seed, "true_flux_jy": true, "stacks": result,
                          "image_stack_by_sigma_estimator_jy": by_estimator,
                          "seconds": time.perf_counter() - t0}))
        return
    print(f"type {TYPE}, seed {a.seed}: true mean flux {true * 1e6:.3f} µJy "
          f"({time.perf_counter() - t0:.0f} s)")
    print(f"{'stack':20s} {'flux (µJy)':>11s} {'error':>7s}")
    for k, (f, e) in result.items():
        print(f"{k:20s} {f * 1e6:11.3f} {e * 1e6:7.3f}")
    print(f"\n{'sigma_k estimator, stamp':24s} {'image stack (µJy)':>18s}")
    for k, f in by_estimator.items():
        print(f"{k:24s} {f * 1e6:18.3f}")


if __name__ == "__main__":
    main()
