"""``xstack uvstack`` command line: outputs, JSON, and clear errors with nothing written."""

from __future__ import annotations

import json

import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, make_stack_partition

from xstack.cli import main
from xstack.coords import lm_to_radec
from xstack.schema import open_store, write_store
from xstack.uvstack.profile import uv_profile


@pytest.fixture
def store(tmp_path):
    ra, dec = lm_to_radec(2e-3, -1e-3, *VLA_CENTER)
    ds = make_stack_partition(n_time=10, n_ant=7, n_chan=3, sigma=0.01, seed=21,
                              sources=[(ra, dec, 0.05)], dtype=np.complex64)
    path = tmp_path / "data.zarr"
    write_store({"spw0_field0": ds}, path)
    cat = tmp_path / "cat.csv"
    cat.write_text(f"ra,dec\n{float(np.degrees(ra))!r},{float(np.degrees(dec))!r}\n")
    return path, cat


def test_cli_json_and_outputs(tmp_path, store, capsys):
    data, cat = store
    out = tmp_path / "st.zarr"
    rc = main(["uvstack", str(data), str(cat), str(out), "--primary-beam", "none", "--json",
               "--no-progress", "--profile-bins", "5"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) >= {"flux_jy", "flux_err_jy", "n_positions", "n_visibilities", "options"}
    assert doc["flux_jy"] == pytest.approx(0.05, abs=5 * doc["flux_err_jy"])
    assert doc["n_positions"] == 1 and doc["options"]["primary_beam"] == "none"
    assert open_store(out).attrs["xstack_kind"] == "stacked"
    from astropy.table import Table

    prof = Table.read(tmp_path / "st_uvprofile.ecsv")
    assert len(prof) == 5
    assert (tmp_path / "st_uvprofile.png").stat().st_size > 1000
    # the point source at the stack position: flat profile at the flux in every bin
    assert np.all(np.abs(prof["re_jy"] - 0.05) < 5 * prof["re_err_jy"])
    assert np.all(np.abs(prof["im_jy"]) < 5 * prof["im_err_jy"])


def test_cli_uvmin_uvmax_and_two_datasets(tmp_path, store, capsys):
    data, cat = store
    out = tmp_path / "two.zarr"
    rc = main(["uvstack", str(data), str(data), str(cat), str(out), "--uvmin", "1klambda",
               "--uvmax", "3000m", "--json", "--no-progress"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["options"]["uvmin"] == "1klambda" and len(doc["partitions"]) == 2


@pytest.mark.parametrize("content,msg", [
    ("x,y\n1,2\n", "missing column"),
    ("ra,dec\n57.3,-30\nabc,-30.0\n", "row 2"),
    ("ra,dec\n10.0,45.0\n", "none of the 1 positions"),
])
def test_cli_bad_catalog_writes_nothing(tmp_path, store, capsys, content, msg):
    data, _ = store
    cat = tmp_path / "bad.csv"
    cat.write_text(content)
    out = tmp_path / "o.zarr"
    rc = main(["uvstack", str(data), str(cat), str(out), "--no-progress"])
    assert rc == 1
    err = capsys.readouterr().err
    assert msg in err and "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["bad.csv", "cat.csv", "data.zarr"])


def test_cli_existing_output(tmp_path, store, capsys):
    data, cat = store
    out = tmp_path / "o.zarr"
    out.mkdir()
    rc = main(["uvstack", str(data), str(cat), str(out), "--no-progress"])
    assert rc == 1 and "exists" in capsys.readouterr().err
    assert not (tmp_path / "o_uvprofile.ecsv").exists()
    rc = main(["uvstack", str(data), str(cat), str(out), "--no-progress", "--overwrite"])
    assert rc == 0 and (tmp_path / "o_uvprofile.ecsv").exists()


def test_uv_profile_of_gaussian_source():
    """An extended (Gaussian) source at the stack position: the profile falls as
    exp(-(pi r q)^2) with r = FWHM / (2 sqrt(ln 2)), q in wavelengths."""
    fwhm = np.radians(2.0 / 3600)
    r = fwhm / (2 * np.sqrt(np.log(2)))
    ds = make_stack_partition(n_time=30, n_ant=10, n_chan=2, extent_m=6000.0, weight_scale=1.0,
                              sources=[(*VLA_CENTER, 1.0)], seed=3)
    from xstack.coords import SPEED_OF_LIGHT

    q = np.hypot(ds["UVW"][..., 0], ds["UVW"][..., 1]).values[..., None] * (
        ds["frequency"].values / SPEED_OF_LIGHT)
    ds["VISIBILITY"] = ds["VISIBILITY"] * np.exp(-(np.pi * r * q) ** 2)[..., None]
    prof = uv_profile({"p": ds}, bins=8)
    want = np.exp(-(np.pi * r * prof["uvdist_klambda"] * 1e3) ** 2)
    # bins are finite: compare the mean of the model over each bin's visibilities
    ok = prof["count"] > 20
    assert np.all(np.abs(prof["re_jy"][ok] - want[ok]) < 0.05)
    assert np.all(np.diff(prof["re_jy"][ok]) < 0)


def test_top_level_api_callable_after_subpackage_import(store):
    import xstack
    import xstack.uvstack.stack  # noqa: F401  (shadows the lazy function by the sub-package)

    data, cat = store
    res = xstack.stack_uv(str(data), str(cat), primary_beam="none")
    assert res.flux_jy == pytest.approx(0.05, abs=5 * res.flux_err_jy)
    assert xstack.uv_profile(res, bins=3)["count"].sum() == res.n_visibilities


def test_stacked_store_exports_to_ms_and_back(tmp_path):
    """The stacked store is a valid store for ``xstack export``: MS round trip keeps the stack."""
    from astropy.table import Table

    from xstack.io.convert import convert_ms
    from xstack.io.export import export_ms

    src = lm_to_radec(1e-3, 5e-4, *VLA_CENTER)
    ds = make_stack_partition(n_time=6, n_ant=6, n_chan=3, sources=[(*src, 1.0)], weight_scale=1.0)
    cat = Table({"ra": [np.degrees(src[0])], "dec": [np.degrees(src[1])]})
    import xarray as xr

    from xstack.uvstack.stack import stack_uv

    res = stack_uv(xr.DataTree.from_dict({"spw0_field0": ds}), cat, primary_beam="none",
                  out=tmp_path / "s.zarr")
    export_ms(tmp_path / "s.zarr", tmp_path / "s.ms")
    back = open_store(convert_ms(tmp_path / "s.ms", tmp_path / "back.zarr"))
    (name,) = list(back.children)
    b = back[name].to_dataset()
    assert np.degrees(b.attrs["phase_center"]) == pytest.approx(res.options["stack_center_deg"])
    np.testing.assert_allclose(b["VISIBILITY"].values, 1.0, atol=1e-6)
