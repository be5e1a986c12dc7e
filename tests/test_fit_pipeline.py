"""End to end (slow): simulate scaled paper type 7 -> uvstack -> fit_uv recovers the targets."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.slow
def test_type7_scaled_uvstack_then_fit():
    sim = pytest.importorskip("xstack.sim.simulate")
    presets = pytest.importorskip("xstack.sim.presets")
    stack_uv = pytest.importorskip("xstack.uvstack.stack").stack_uv
    import xarray as xr

    from xstack.fit.uvfit import fit_uv

    scene = presets.preset_dict("paper-7")
    scene["populations"] = [p for p in scene["populations"] if p["name"] == "targets"]
    scene["effects"]["noise"]["sigma"] = 2e-4  # 50x below Table 1: a high-S/N stack
    parts, cats = sim.simulate_partitions(scene, seed=3, scale=0.05)
    targets = cats["targets"]
    res = stack_uv(xr.DataTree.from_dict(parts), targets, weighting="pb")
    fit = fit_uv(res, model="gaussian")
    truth_flux = float(np.mean(targets["flux"]))
    truth_fwhm = float(np.mean(targets["fwhm_arcsec"]))
    assert abs(fit.flux_jy - truth_flux) < 3 * fit.flux_err_jy + 0.02 * truth_flux
    assert abs(fit.fwhm_arcsec - truth_fwhm) < 3 * fit.fwhm_err_arcsec + 0.03 * truth_fwhm
    assert fit.resolved
    point = fit_uv(res, model="point")
    assert point.flux_jy < fit.flux_jy  # an extended source looks fainter on average
