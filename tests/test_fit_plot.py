"""Pictures of fits: ``xstack.fit.plot`` and ``xstack fit --png``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _fit_helpers import ARCSEC, GK, StampSimulator, gaussian_stack, write_stamp_fits

from xstack.cli import main
from xstack.errors import XstackError
from xstack.fit.imfit import fit_image, read_stamp_fits
from xstack.fit.plot import (
    _image_fit_figure,
    _uv_fit_figure,
    image_model,
    plot_image_fit,
    plot_uv_fit,
)
from xstack.fit.result import FitResult
from xstack.fit.uvfit import fit_uv
from xstack.schema import write_store
from xstack.uvstack.profile import uv_profile

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _assert_png(path):
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC
    assert len(data) > 10_000  # axes, points and text, not an empty canvas


def _no_partials(directory):
    assert not [p.name for p in directory.iterdir() if ".partial-" in p.name]


@pytest.fixture(scope="module")
def gauss_ds():
    return gaussian_stack(2e-3, 1.5, 1e-3, seed=1, n_time=6)


@pytest.fixture(scope="module")
def stamp_fits(tmp_path_factory):

    sim = StampSimulator()
    img = sim.stamp(1.0, 1.5, 3)
    path = tmp_path_factory.mktemp("stamp") / "stack.fits"
    write_stamp_fits(sim, img, path)
    return path, sim, img


def _errorbar(ax, gid):
    (cont,) = [c for c in ax.containers if c.lines[0].get_gid() == gid]
    return cont


def _model_line(ax):
    (line,) = [ln for ln in ax.get_lines() if ln.get_gid() == "model"]
    return line


@pytest.mark.parametrize("model", ["gaussian", "point"])
def test_uv_fit_figure_curve_is_the_fitted_model(gauss_ds, model):
    res = fit_uv(gauss_ds, model=model)
    table = uv_profile(gauss_ds, bins=12)
    fig, ax, scale = _uv_fit_figure(table, res)
    assert scale == 1e3  # a 2 mJy source is drawn in mJy
    # the curve: the model evaluated with the fitted parameters, written out independently
    line = _model_line(ax)
    q = np.asarray(line.get_xdata()) * 1e3  # wavelengths
    if model == "gaussian":
        theta2 = res.values[1] * ARCSEC**2  # fitted FWHM^2, arcsec^2 -> rad^2
        expect = res.flux_jy * np.exp(-GK * theta2 * q**2)
        assert res.fwhm_arcsec == pytest.approx(1.5, abs=4 * res.fwhm_err_arcsec)
    else:
        expect = np.full(q.size, res.flux_jy)
    np.testing.assert_allclose(np.asarray(line.get_ydata()) / scale, expect, rtol=1e-12)
    # it spans the profile's uv range
    assert q.min() / 1e3 == pytest.approx(table["bin_lo_klambda"][0])
    assert q.max() / 1e3 == pytest.approx(table["bin_hi_klambda"][-1])
    # the error-bar points are uv_profile's table: centers, means and 1-sigma errors
    for gid, col in (("re", "re"), ("im", "im")):
        cont = _errorbar(ax, gid)
        x, y = cont.lines[0].get_data()
        np.testing.assert_allclose(x, table["uvdist_klambda"], rtol=1e-12)
        np.testing.assert_allclose(np.asarray(y) / scale, table[f"{col}_jy"], rtol=1e-12)
        segs = cont.lines[2][0].get_segments()
        half = np.array([(s[1][1] - s[0][1]) / 2 for s in segs]) / scale
        np.testing.assert_allclose(half, table[f"{col}_err_jy"], rtol=1e-9)
    # the fitted values are in the legend
    label = line.get_label()
    assert f"{res.flux_jy * 1e3:.4g}" in label and f"{res.flux_err_jy * 1e3:.2g}" in label
    assert ("FWHM" in label) == (model == "gaussian")


def test_uv_fit_legend_gives_upper_limit_when_unresolved():
    ds = gaussian_stack(30e-6, 0.0, 5e-5, seed=2, n_time=6)
    res = fit_uv(ds, model="gaussian")
    assert not res.resolved
    _, ax, scale = _uv_fit_figure(uv_profile(ds, bins=10), res)
    assert scale == 1e6
    label = _model_line(ax).get_label()
    assert f"FWHM < {res.fwhm_upper_limit_arcsec:.3g}" in label and "µJy" in label


def test_plot_uv_fit_writes_and_refuses_to_overwrite(tmp_path, gauss_ds):
    store = write_store({"spw0_field0": gauss_ds}, tmp_path / "st.zarr", kind="stacked")
    res = fit_uv(store, model="gaussian")
    png = tmp_path / "fit.png"
    assert plot_uv_fit(store, res, png, bins=15) == str(png)
    _assert_png(png)
    before = png.read_bytes()
    with pytest.raises(XstackError, match="overwrite=True"):
        plot_uv_fit(store, res, png)
    assert png.read_bytes() == before
    plot_uv_fit(store, res, png, bins=8, overwrite=True)
    _assert_png(png)
    assert png.read_bytes() != before
    _no_partials(tmp_path)
    with pytest.raises(XstackError, match="uv-domain"):
        _uv_fit_figure(uv_profile(store, bins=5), FitResult(model="point", domain="image",
                                                            flux_jy=1.0, flux_err_jy=0.1))


def test_image_fit_figure_panels(stamp_fits):
    path, sim, img = stamp_fits
    res = fit_image(path, model="gaussian")
    model = image_model(img.shape, sim.psf, res)
    # the drawn model is the fitted one: its residuals give the fit's chi^2
    sigma = res.extra["sigma_jy_per_beam"]
    assert np.sum((img - model) ** 2) / sigma**2 == pytest.approx(res.chi2, rel=1e-8)
    fig, axes = _image_fit_figure(img, model, res, east_left=True)
    ims = {ax.images[0].get_gid(): ax.images[0] for ax in axes}
    assert set(ims) == {"stamp", "model", "residual"}
    # panels are scaled to mJy/beam by the same factor; ratios are scale-free
    k = np.asarray(ims["stamp"].get_array())[16, 16] / img[16, 16]
    np.testing.assert_allclose(np.asarray(ims["stamp"].get_array()) / k, img, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(ims["model"].get_array()) / k, model, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(ims["residual"].get_array()) / k, img - model,
                               rtol=1e-9, atol=1e-12)
    assert ims["stamp"].get_clim() == ims["model"].get_clim()
    lo, hi = ims["residual"].get_clim()
    assert lo == -hi
    # arcsec axes centered on the stacking position, east to the left
    left, right, bottom, top = ims["stamp"].get_extent()
    assert left == pytest.approx(16.5 * 0.5) and right == pytest.approx(-16.5 * 0.5)
    assert bottom == pytest.approx(-16.5 * 0.5) and top == pytest.approx(16.5 * 0.5)
    title = fig._suptitle.get_text()
    assert "FWHM" in title and f"{res.fwhm_arcsec:.3g}" in title


def test_image_model_point_is_scaled_psf(stamp_fits):
    """Point model: S PSF + c, with the PSF cut around its peak (independent of the FFTs)."""
    path, sim, img = stamp_fits
    res = fit_image(path, model="point")
    n, h = sim.size, sim.size // 2
    crop = sim.psf[n - h:n + h + 1, n - h:n + h + 1] / sim.psf.max()
    expect = res.flux_jy * crop + res.extra["background_jy_per_beam"]
    np.testing.assert_allclose(image_model(img.shape, sim.psf, res), expect, atol=1e-12)


def test_plot_image_fit_writes_and_refuses_to_overwrite(tmp_path, stamp_fits):
    path, sim, _ = stamp_fits
    res = fit_image(path, model="gaussian", fit_radius_arcsec=6.0)
    png = tmp_path / "im.png"
    assert plot_image_fit(path, res, png, fit_radius_arcsec=6.0) == str(png)
    _assert_png(png)
    before = png.read_bytes()
    with pytest.raises(XstackError, match="overwrite=True"):
        plot_image_fit(path, res, png)
    assert png.read_bytes() == before
    # arrays work too, given the PSF
    plot_image_fit(read_stamp_fits(path)["stamp"], res, tmp_path / "arr.png", psf=sim.psf)
    _assert_png(tmp_path / "arr.png")
    with pytest.raises(XstackError, match="PSF"):
        plot_image_fit(np.zeros((33, 33)), res, tmp_path / "nopsf.png")
    _no_partials(tmp_path)


def test_cli_fit_png_uv_and_image(tmp_path, capsys, gauss_ds, stamp_fits):
    store = write_store({"spw0_field0": gauss_ds}, tmp_path / "st.zarr", kind="stacked")
    png = tmp_path / "uv.png"
    assert main(["fit", str(store), "--model", "gaussian", "--png", str(png), "--json",
                 "--nbins", "10"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["png"] == str(png)
    _assert_png(png)
    # an existing file: refused before the fit, left untouched; replaced with --overwrite
    png.write_bytes(b"keep me")
    assert main(["fit", str(store), "--png", str(png)]) == 1
    err = capsys.readouterr().err
    assert "exists" in err and "--overwrite" in err
    assert png.read_bytes() == b"keep me"
    assert main(["fit", str(store), "--png", str(png), "--overwrite"]) == 0
    assert "picture" in capsys.readouterr().out
    _assert_png(png)
    assert main(["fit", str(store), "--png", str(tmp_path / "nodir" / "x.png")]) == 1
    assert "does not exist" in capsys.readouterr().err
    # image domain
    fits_path = stamp_fits[0]
    ipng = tmp_path / "im.png"
    assert main(["fit", str(fits_path), "--model", "gaussian", "--fit-radius", "6",
                 "--png", str(ipng), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["png"] == str(ipng) and d["domain"] == "image"
    _assert_png(ipng)
    before = ipng.read_bytes()
    assert main(["fit", str(fits_path), "--png", str(ipng)]) == 1
    assert ipng.read_bytes() == before
    _no_partials(tmp_path)
