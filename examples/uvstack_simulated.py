"""uv-stacking of simulated faint sources, checked against the injected flux.

Simulates the scene of ``faint_targets.toml`` (one VLA A pointing at 1.4 GHz, 200 point
sources of 20 uJy, each at ~0.7 sigma, invisible one by one), uv-stacks the data at their
true positions (paper eq. 4) and fits a point and a Gaussian model to the stacked visibilities.

Run: ``python examples/uvstack_simulated.py [OUTDIR]`` (about half a minute).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

import xstack

SCENE = Path(__file__).with_name("faint_targets.toml")  # the scene, as a TOML file


def main(outdir: Path) -> dict[str, float]:
    outdir.mkdir(parents=True, exist_ok=True)
    sim = xstack.simulate(xstack.load_scene(SCENE), outdir / "sim.zarr", seed=3, overwrite=True)
    targets = sim.catalogs["targets"]
    print(f"simulated {sim.n_visibilities:,} visibilities, {len(targets)} targets")

    # pb weighting: W_k = A_k^2, the inverse variance of each primary-beam corrected flux
    res = xstack.stack_uv(sim.store, targets, weighting="pb", out=outdir / "stacked.zarr",
                         overwrite=True)
    injected = float(np.mean(targets["flux"]))
    print(f"injected mean flux {injected * 1e6:.2f} uJy")
    print(f"uv-stacked flux    {res.flux_jy * 1e6:.2f} +- {res.flux_err_jy * 1e6:.2f} uJy "
          f"({res.n_positions} positions, {res.n_visibilities:,} visibilities)")

    point = xstack.fit_uv(outdir / "stacked.zarr", model="point")
    gauss = xstack.fit_uv(outdir / "stacked.zarr", model="gaussian")
    print(f"point fit:    S = {point.flux_jy * 1e6:.2f} +- {point.flux_err_jy * 1e6:.2f} uJy")
    size = (f"FWHM < {gauss.fwhm_upper_limit_arcsec:.2f} arcsec (unresolved)" if not gauss.resolved
            else f"FWHM = {gauss.fwhm_arcsec:.2f} +- {gauss.fwhm_err_arcsec:.2f} arcsec")
    print(f"Gaussian fit: S = {gauss.flux_jy * 1e6:.2f} +- {gauss.flux_err_jy * 1e6:.2f} uJy, {size}")
    return {"injected": injected, "flux": res.flux_jy, "flux_err": res.flux_err_jy}


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as tmp:  # OUTDIR on the command line keeps the files
        main(Path(sys.argv[1] if len(sys.argv) > 1 else tmp))
