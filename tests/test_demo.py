"""The end-to-end demo: every stage chained, checked against the injected truth."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


def test_demo_recovers_injected_flux(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.run([sys.executable, "-m", "xstack", "demo", "--outdir", str(out), "--json"],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    summary = json.loads(proc.stdout)
    truth = summary["injected_mean_flux_jy"]
    assert summary["roundtrip_identical"] is True
    # each estimate within 4 sigma of the injected mean flux, and the stack is a detection
    for key in ("uvstack", "imstack", "uvfit"):
        flux, err = summary[f"{key}_flux_jy"], summary[f"{key}_flux_err_jy"]
        assert err > 0
        assert abs(flux - truth) < 4 * err, (key, flux, err, truth)
        assert flux / err > 3
    # the Monte Carlo noise agrees with the analytic uv-stacking error within a factor 1.5
    assert summary["mc_noise_jy"] == pytest.approx(summary["uvstack_flux_err_jy"], rel=0.5)
    for name in ("image.png", "imstack.png", "stacked_uvprofile.png", "noise_mc.png", "fit_uv.png",
                 "imstack.fits", "stacked.zarr"):
        assert (out / name).exists(), name


def test_demo_refuses_existing_outdir(tmp_path):
    (tmp_path / "demo").mkdir()
    proc = subprocess.run([sys.executable, "-m", "xstack", "demo", "--outdir",
                           str(tmp_path / "demo")], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1
    assert proc.stderr.strip().startswith("error:") and "--overwrite" in proc.stderr
