"""``xstack fit`` command line."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _fit_helpers import StampSimulator, gaussian_stack, write_stamp_fits

from xstack.cli import main
from xstack.fit.uvfit import fit_uv
from xstack.schema import write_store


def _run(capsys, argv):
    status = main(argv)
    out, err = capsys.readouterr()
    return status, out, err


def test_fit_uv_store_json(tmp_path, capsys):
    ds = gaussian_stack(1e-3, 1.5, 5e-4, seed=1, n_time=6)
    path = write_store({"spw0_field0": ds}, tmp_path / "st.zarr", kind="stacked")
    status, out, _ = _run(capsys, ["fit", str(path), "--model", "gaussian", "--json"])
    assert status == 0
    d = json.loads(out)
    ref = fit_uv(ds, model="gaussian")
    assert d["flux_jy"] == pytest.approx(ref.flux_jy, rel=1e-6)
    assert d["fwhm_arcsec"] == pytest.approx(ref.fwhm_arcsec, rel=1e-5)
    assert {"flux_err_jy", "fwhm_err_arcsec"} <= set(d)
    status, out, _ = _run(capsys, ["fit", str(path), "--uvmax", "30klambda"])
    assert status == 0 and "flux" in out
    status, _, err = _run(capsys, ["fit", str(path), "--uvmin", "1e9lambda"])
    assert status == 1 and "no visibilities left in the uv range" in err
    status, _, err = _run(capsys, ["fit", str(tmp_path / "missing.zarr")])
    assert status == 1 and "no such" in err


def test_fit_fits_stamp(tmp_path, capsys):
    from astropy.io import fits

    sim = StampSimulator()
    img = sim.stamp(1.0, 1.5, 3)
    path = tmp_path / "stack.fits"
    write_stamp_fits(sim, img, path)
    status, out, _ = _run(capsys, ["fit", str(path), "--model", "gaussian", "--json"])
    assert status == 0
    d = json.loads(out)
    assert d["domain"] == "image" and np.isfinite(d["fwhm_arcsec"])
    assert abs(d["flux_jy"] - 1.0) < 4 * d["flux_err_jy"]
    psf_path = tmp_path / "psf.fits"
    fits.PrimaryHDU(sim.psf).writeto(psf_path)
    fits.PrimaryHDU(img, header=fits.getheader(path)).writeto(tmp_path / "bare.fits")
    status, out, _ = _run(capsys, ["fit", str(tmp_path / "bare.fits"), "--psf", str(psf_path),
                                   "--model", "gaussian", "--json"])
    assert status == 0 and json.loads(out)["flux_jy"] == pytest.approx(d["flux_jy"], rel=1e-9)
    status, _, err = _run(capsys, ["fit", str(tmp_path / "bare.fits")])
    assert status == 1 and "PSF" in err
