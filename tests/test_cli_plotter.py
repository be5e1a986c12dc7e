"""The command line's PNGs drawn in a second process (xstack/cli/_plotter.py): the same picture
as drawn in the command's own process, a fallback when the child cannot run, no child left
behind, and ``xstack uvstack --no-png``."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.table import Table

from xstack.cli import main
from xstack.cli._plotter import BackgroundPlotter, render_png
from xstack.coords import lm_to_radec
from xstack.schema import write_store

FIGURE = "xstack.uvstack.plot:uv_profile_figure"


def _table() -> Table:
    rng = np.random.default_rng(3)
    edges = np.linspace(1.0, 30.0, 7)
    return Table({"uvdist_lo_klambda": edges[:-1], "uvdist_hi_klambda": edges[1:],
                  "uvdist_klambda": 0.5 * (edges[:-1] + edges[1:]),
                  "re_jy": 5e-6 + rng.normal(0, 1e-6, 6), "re_err_jy": np.full(6, 1e-6),
                  "im_jy": rng.normal(0, 1e-6, 6), "im_err_jy": np.full(6, 1e-6),
                  "n_vis": np.full(6, 1000)})


def _png_from_a_fresh_process(table_path, tmp_path) -> bytes:
    """The reference picture: drawn by plain matplotlib calls in an unrelated process."""
    code = ("import sys, matplotlib; matplotlib.use('Agg'); from astropy.table import Table; "
            "from xstack.uvstack.plot import plot_uv_profile; "
            "plot_uv_profile(Table.read(sys.argv[1]), sys.argv[2], title='t', flux_jy=5e-6)")
    out = tmp_path / "ref.png"
    subprocess.run([sys.executable, "-c", code, str(table_path), str(out)], check=True)
    return out.read_bytes()


def test_child_draws_the_same_png_as_the_commands_own_process(tmp_path):
    table = _table()
    table.write(tmp_path / "p.ecsv", format="ascii.ecsv")
    reference = _png_from_a_fresh_process(tmp_path / "p.ecsv", tmp_path)
    with BackgroundPlotter(preload=("xstack.uvstack.plot",)) as plotter:
        assert plotter._proc is not None  # a child really runs
        child = plotter.render(FIGURE, table, title="t", flux_jy=5e-6)
    assert child[:8] == b"\x89PNG\r\n\x1a\n"
    assert child == reference
    assert render_png(FIGURE, (table,), {"title": "t", "flux_jy": 5e-6}) == reference


def test_without_a_child_the_figure_is_drawn_here(tmp_path, monkeypatch):
    table = _table()
    monkeypatch.setattr(sys, "executable", str(tmp_path / "no-such-python"))
    with BackgroundPlotter() as plotter:
        assert plotter._proc is None
        png = plotter.render(FIGURE, table, title="t")
    assert png == render_png(FIGURE, (table,), {"title": "t"})


def test_a_failing_child_falls_back_and_a_real_error_surfaces(tmp_path):
    with BackgroundPlotter() as plotter:
        # the child cannot render it (no such function) - nor can this process: the error
        # the user sees is this process's own, not a silent empty file
        with pytest.raises(AttributeError):
            plotter.render("xstack.uvstack.plot:no_such_figure")


def test_no_child_is_left_running():
    with BackgroundPlotter() as plotter:
        proc = plotter._proc
        assert proc is not None and proc.poll() is None
    assert proc.poll() is not None  # ended on leaving the block, without rendering
    with pytest.raises(RuntimeError):
        with BackgroundPlotter() as plotter:
            proc = plotter._proc
            raise RuntimeError("the command failed")
    assert proc.poll() is not None


@pytest.fixture
def store(tmp_path):
    ra, dec = lm_to_radec(2e-3, -1e-3, *VLA_CENTER)
    ds = make_stack_partition(n_time=10, n_ant=7, n_chan=3, sigma=0.01, seed=21,
                              sources=[(ra, dec, 0.05)], dtype=np.complex64)
    write_store({"spw0_field0": ds}, tmp_path / "data.zarr")
    cat = tmp_path / "cat.csv"
    cat.write_text(f"ra,dec\n{float(np.degrees(ra))!r},{float(np.degrees(dec))!r}\n")
    return tmp_path / "data.zarr", cat


def test_uvstack_png_is_the_profile_it_writes(tmp_path, store, capsys):
    data, cat = store
    assert main(["uvstack", str(data), str(cat), str(tmp_path / "st.zarr"), "--json",
                 "--no-progress", "--profile-bins", "5", "--primary-beam", "none"]) == 0
    doc = json.loads(capsys.readouterr().out)
    table = Table.read(tmp_path / "st_uvprofile.ecsv")
    expected = render_png(FIGURE, (table,), {"flux_jy": doc["flux_jy"],
                                             "title": "uv-stack of 1 positions"})
    assert (tmp_path / "st_uvprofile.png").read_bytes() == expected


def test_uvstack_no_png(tmp_path, store, capsys):
    data, cat = store
    assert main(["uvstack", str(data), str(cat), str(tmp_path / "st.zarr"), "--json",
                 "--no-progress", "--no-png"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["profile_png"] is None
    assert (tmp_path / "st_uvprofile.ecsv").exists()
    assert not list(tmp_path.glob("*.png"))
    rc = main(["uvstack", str(data), str(cat), str(tmp_path / "x.zarr"), "--no-png",
               "--profile-png", str(tmp_path / "p.png")])
    assert rc != 0 and "--no-png" in capsys.readouterr().err
    assert not (tmp_path / "x.zarr").exists()
