"""The measuring helpers of ``benchmarks/bench_clean_casa.py`` (no CASA needed): grid
comparison, the model check/conversion before ``xstack.subtract``, and the per-source
CLEANed flux read from a model image."""

from __future__ import annotations

import numpy as np
import pytest
from _bench_helpers import load_benchmark
from astropy.io import fits
from astropy.table import Table


@pytest.fixture(scope="module")
def bench():
    return load_benchmark("bench_clean_casa")


def _header(n: int = 64, cell_arcsec: float = 0.5, crpix: float | None = None,
            bunit: str = "Jy/pixel") -> fits.Header:
    """CASA's exportfits layout: RA, Dec, then STOKES and FREQ degenerate axes."""
    h = fits.Header()
    c = n // 2 + 1 if crpix is None else crpix
    for k, v in {"CTYPE1": "RA---SIN", "CTYPE2": "DEC--SIN", "CRVAL1": 57.29579166667,
                 "CRVAL2": -30.0, "CRPIX1": c, "CRPIX2": c, "CDELT1": -cell_arcsec / 3600,
                 "CDELT2": cell_arcsec / 3600, "CUNIT1": "deg", "CUNIT2": "deg",
                 "CTYPE3": "STOKES", "CRVAL3": 1.0, "CRPIX3": 1.0, "CDELT3": 1.0,
                 "CTYPE4": "FREQ", "CRVAL4": 1.4e9, "CRPIX4": 1.0, "CDELT4": 2.5e8,
                 "RADESYS": "FK5", "EQUINOX": 2000.0, "BUNIT": bunit}.items():
        h[k] = v
    return h


def test_compare_grids(bench, tmp_path):
    a = tmp_path / "a.fits"
    fits.writeto(a, np.zeros((1, 1, 64, 64), np.float32), _header())
    ref = bench.grid_header(a)
    assert bench.compare_grids(ref, dict(ref), 0.5 / 3600) == []
    shifted = dict(ref, CRPIX1=ref["CRPIX1"] + 1, CRVAL2=ref["CRVAL2"] + 0.01 * 0.5 / 3600)
    diff = bench.compare_grids(ref, shifted, 0.5 / 3600)
    assert any(d.startswith("CRPIX1") for d in diff) and any(d.startswith("CRVAL2") for d in diff)
    # a 1e-4-pixel CRVAL difference (rounding in exportfits) is the same grid
    assert bench.compare_grids(ref, dict(ref, CRVAL1=ref["CRVAL1"] + 1e-4 * 0.5 / 3600),
                               0.5 / 3600) == []


def test_subtract_ready_accepts_good_and_converts_fixable_models(bench, tmp_path):
    good = tmp_path / "good.fits"
    fits.writeto(good, np.zeros((1, 1, 64, 64), np.float32), _header())
    path, note = bench.subtract_ready(good, tmp_path / "conv.fits")
    assert path == good and note.startswith("accepted")
    # NaN pixels (what a masked CASA image holds) are refused by subtract, converted to 0
    data = np.zeros((1, 1, 64, 64), np.float32)
    data[0, 0, 0, :] = np.nan
    data[0, 0, 40, 30] = 2e-3
    bad = tmp_path / "bad.fits"
    fits.writeto(bad, data, _header())
    path, note = bench.subtract_ready(bad, tmp_path / "conv.fits")
    assert path == tmp_path / "conv.fits" and note.startswith("refused")
    from xstack.imaging.subtract import _load_image

    spec = _load_image(path)
    assert spec["data"][40, 30] == pytest.approx(2e-3) and np.isfinite(spec["data"]).all()


def test_model_stats_sums_components_near_each_source(bench, tmp_path):
    from astropy.wcs import WCS

    n = 64
    h = _header(n)
    wcs = WCS(h).celestial
    model = np.zeros((1, 1, n, n), np.float32)
    # source 1 split over two pixels, source 2 one pixel, one spurious component far away
    model[0, 0, 40, 30], model[0, 0, 40, 31] = 3e-3, 1e-3
    model[0, 0, 20, 12] = 2e-3
    model[0, 0, 5, 60] = 1e-5
    resid = np.zeros_like(model)
    resid[0, 0, 40, 30] = 7e-5
    mpath, rpath = tmp_path / "m.fits", tmp_path / "r.fits"
    fits.writeto(mpath, model, h)
    fits.writeto(rpath, resid, _header(n, bunit="Jy/beam"))
    sky = wcs.pixel_to_world([30.3, 12.0], [40.0, 20.0])
    cat = Table({"ra": sky.ra.deg, "dec": sky.dec.deg, "flux": [4e-3, 2e-3]})
    st = bench.model_stats(mpath, rpath, cat, np.array([4e-3, 2.5e-3]), radius_arcsec=2.0)
    assert st["components"] == 4 and st["components_outside"] == 1
    np.testing.assert_allclose(st["source_flux_jy"], [4e-3, 2e-3], rtol=1e-6)
    np.testing.assert_allclose(st["source_ratio"], [1.0, 0.8], rtol=1e-6)
    assert st["model_outside_jy"] == pytest.approx(1e-5, rel=1e-5)
    assert st["residual_peak_near_jy"] == pytest.approx(7e-5, rel=1e-5)
    np.testing.assert_allclose(st["pixel_x"], [30.3, 12.0], atol=1e-6)
