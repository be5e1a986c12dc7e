"""``xstack linestack``: the command line around the uv line stack and the line fit.

Fast tests run the command on a stack result made here (``stack_lines`` monkeypatched: a
Gaussian line averaged over the bins analytically, with a known covariance): the JSON against
:func:`xstack.fit.line.fit_line` on the same spectrum, the ECSV round trip, the PNG, the refusal
to overwrite, one-line errors and warnings. The end-to-end test stacks a tiny store into which
a line was injected with plain numpy at three positions and redshifts, and checks the command
against the library call and the injected truth.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from astropy.table import Table
from scipy.special import erf

from xstack.cli import main
from xstack.spectral import LINES, SPEED_OF_LIGHT_KMS

PEAK, CENTRE, FWHM = 3e-3, 25.0, 160.0  # Jy, km/s, km/s
SIGMA = FWHM / (2 * math.sqrt(2 * math.log(2)))


def _bin_average(edges, peak=PEAK, centre=CENTRE, sigma=SIGMA):
    a = (edges[1:] - centre) / (math.sqrt(2) * sigma)
    b = (edges[:-1] - centre) / (math.sqrt(2) * sigma)
    return peak * sigma * math.sqrt(math.pi / 2) * (erf(a) - erf(b)) / np.diff(edges)


def _fake_result(flux=None, seed=1):
    from xstack.uvstack.line import LineStackResult

    edges = np.arange(-500.0, 500.1, 20.0)
    n = edges.size - 1
    # neighbouring bins correlated as when they share channels
    cov = (1e-4) ** 2 * (np.eye(n) + 0.3 * (np.eye(n, k=1) + np.eye(n, k=-1)))
    rng = np.random.default_rng(seed)
    if flux is None:
        flux = _bin_average(edges) + np.linalg.cholesky(cov) @ rng.normal(size=n)
    counts = np.full(n, 4)
    counts[:5] = 3
    return LineStackResult(
        velocity_edges_kms=edges, velocity_kms=0.5 * (edges[1:] + edges[:-1]), flux_jy=flux,
        flux_err_jy=np.sqrt(np.diag(cov)), flux_cov_jy2=cov, n_targets_per_bin=counts,
        n_positions=4, n_visibilities=1234, positions=Table({"ra": [1.0], "dec": [2.0]}),
        rest_frequency_hz=LINES["HI"], frame="lsrk", options={"weighting": "pb"}, out=None)


@pytest.fixture
def fake(tmp_path, monkeypatch):
    """Inputs for the command and ``stack_lines`` replaced by one returning a fixed result."""
    import xstack.uvstack.line as line

    data = tmp_path / "data.zarr"
    data.mkdir()
    cat = tmp_path / "cat.csv"
    cat.write_text("ra,dec,z\n150.0,2.0,0.1\n")
    calls = []
    state = {"result": _fake_result()}

    def stack_lines(data, positions, **kwargs):
        calls.append(kwargs)
        return state["result"]

    monkeypatch.setattr(line, "stack_lines", stack_lines)
    return {"data": data, "cat": cat, "out": tmp_path / "out.zarr", "calls": calls,
            "state": state, "tmp": tmp_path}


def _argv(f, *extra):
    return ["linestack", str(f["data"]), str(f["cat"]), str(f["out"]), "--line-frequency", "HI",
            *extra]


def test_json_is_the_library_fit(fake, capsys):
    from xstack.fit.line import fit_line

    assert main(_argv(fake, "--json", "--velocity-range=-500,500km/s",
                      "--velocity-resolution", "20000m/s")) == 0
    out, err = capsys.readouterr()
    got = json.loads(out)
    kwargs = fake["calls"][0]
    assert kwargs["line_frequency"] == LINES["HI"]
    assert kwargs["velocity_range"] == (-500.0, 500.0)
    assert kwargs["velocity_resolution"] == pytest.approx(20.0)
    res = fake["state"]["result"]
    fit = fit_line(res.velocity_kms, res.flux_jy, res.flux_cov_jy2,
                   velocity_edges_kms=res.velocity_edges_kms)
    assert fit.converged
    for key in ("velocity_kms", "flux_jy", "flux_err_jy", "integrated_flux_jy_kms",
                "integrated_flux_err_jy_kms", "line_fwhm_kms", "line_centre_kms",
                "n_positions", "n_visibilities"):
        assert key in got, key  # DESIGN.md section 2
    assert got["velocity_kms"] == pytest.approx(res.velocity_kms.tolist())
    assert got["flux_jy"] == pytest.approx(res.flux_jy.tolist(), rel=1e-12)
    assert got["line_centre_kms"] == pytest.approx(fit.centre_kms, rel=1e-12)
    assert got["line_fwhm_kms"] == pytest.approx(fit.fwhm_kms, rel=1e-12)
    assert got["line_fwhm_err_kms"] == pytest.approx(fit.fwhm_err_kms, rel=1e-12)
    assert got["integrated_flux_jy_kms"] == pytest.approx(fit.integrated_flux_jy_kms, rel=1e-12)
    assert got["integrated_flux_err_jy_kms"] == pytest.approx(fit.integrated_flux_err_jy_kms,
                                                              rel=1e-12)
    assert got["line_window_kms"] == pytest.approx([fit.centre_kms - fit.fwhm_kms,
                                                    fit.centre_kms + fit.fwhm_kms])
    assert (got["n_positions"], got["n_visibilities"]) == (4, 1234)
    # and the fit finds the injected line
    assert abs(got["line_centre_kms"] - CENTRE) < 4 * got["line_centre_err_kms"]
    assert abs(got["line_fwhm_kms"] - FWHM) < 4 * got["line_fwhm_err_kms"]
    assert all(x.startswith("warning: ") for x in err.splitlines()), err


def test_ecsv_round_trip_and_png(fake, capsys):
    window = (-100.0, 150.0)
    assert main(_argv(fake, "--line-window=-100,150km/s")) == 0
    out, _ = capsys.readouterr()
    assert out.startswith("line integral ") and "wrote " in out
    table = Table.read(fake["tmp"] / "out_spectrum.ecsv")
    res = fake["state"]["result"]
    np.testing.assert_array_equal(table["velocity_kms"], res.velocity_kms)
    np.testing.assert_array_equal(table["velocity_lo_kms"], res.velocity_edges_kms[:-1])
    np.testing.assert_array_equal(table["velocity_hi_kms"], res.velocity_edges_kms[1:])
    np.testing.assert_array_equal(table["flux_jy"], res.flux_jy)
    np.testing.assert_array_equal(table["flux_err_jy"], res.flux_err_jy)
    np.testing.assert_array_equal(table["flux_cov_jy2"], res.flux_cov_jy2)
    np.testing.assert_array_equal(table["n_targets"], res.n_targets_per_bin)
    assert str(table["flux_jy"].unit) == "Jy" and str(table["velocity_kms"].unit) == "km / s"
    fit = table.meta["fit"]
    assert fit["window_kms"] == list(window)
    # the integral of the table itself: overlap lengths times flux, by hand
    lo, hi = np.asarray(table["velocity_lo_kms"]), np.asarray(table["velocity_hi_kms"])
    a = np.clip(np.minimum(hi, window[1]) - np.maximum(lo, window[0]), 0, None)
    assert fit["integrated_flux_jy_kms"] == pytest.approx(a @ res.flux_jy, rel=1e-12)
    assert fit["integrated_flux_err_jy_kms"] == pytest.approx(
        math.sqrt(a @ res.flux_cov_jy2 @ a), rel=1e-12)
    # the model column is the fitted Gaussian averaged over the bins
    np.testing.assert_allclose(table["model_jy"],
                               _bin_average(np.append(lo, hi[-1]), fit["peak_jy"],
                                            fit["centre_kms"],
                                            fit["fwhm_kms"] / (2 * math.sqrt(2 * math.log(2)))),
                               rtol=1e-9, atol=1e-15)
    png = fake["tmp"] / "out_spectrum.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_png_figure_has_its_parts():
    from xstack.fit.line import fit_line, line_spectrum_figure, spectrum_table

    res = _fake_result()
    fit = fit_line(res.velocity_kms, res.flux_jy, res.flux_cov_jy2,
                   velocity_edges_kms=res.velocity_edges_kms)
    fig = line_spectrum_figure(spectrum_table(res, fit), title="t")
    gids = {a.get_gid() for ax in fig.axes for a in ax.get_children()}
    assert {"spectrum", "error", "model", "window", "n_targets"} <= gids


def test_existing_outputs_are_refused_without_overwrite(fake, capsys):
    assert main(_argv(fake)) == 0
    capsys.readouterr()
    fake["out"].mkdir()  # what stack_lines would have written
    before = (fake["tmp"] / "out_spectrum.ecsv").read_bytes()
    fake["state"]["result"] = _fake_result(seed=2)
    assert main(_argv(fake)) == 1
    _, err = capsys.readouterr()
    assert len(err.splitlines()) == 1 and err.startswith("error: ") and "--overwrite" in err
    assert (fake["tmp"] / "out_spectrum.ecsv").read_bytes() == before
    assert len(fake["calls"]) == 1  # refused before any work
    assert main([*_argv(fake), "--overwrite"]) == 0
    assert (fake["tmp"] / "out_spectrum.ecsv").read_bytes() != before


@pytest.mark.parametrize("argv, words", [
    (["--line-frequency", "CO(9-8)"], "neither a known line"),
    (["--line-frequency", "-5GHz"], "argument --line-frequency"),
    (["--velocity-range", "600,-600km/s"], "needs A < B"),
    (["--line-window", "100"], "two velocities"),
    (["--velocity-resolution", "20Jy"], "--velocity-resolution"),
])
def test_bad_values_are_one_line_errors(fake, capsys, argv, words):
    base = ["linestack", str(fake["data"]), str(fake["cat"]), str(fake["out"])]
    if argv[0] != "--line-frequency":
        base += ["--line-frequency", "HI"]
    with pytest.raises(SystemExit) as exit_:
        main([*base, *argv])
    assert exit_.value.code == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert len(err.splitlines()) == 1 and err.startswith("error: linestack: ") and words in err
    assert fake["calls"] == []


def test_velocity_pairs_take_units():
    from xstack.cli.linestack import velocity_pair

    assert velocity_pair("-600,600km/s") == (-600.0, 600.0)
    assert velocity_pair("-600,600") == (-600.0, 600.0)
    assert velocity_pair("-0.3e3km/s, 450000m/s") == pytest.approx((-300.0, 450.0))
    assert velocity_pair("-1e5m/s,100") == pytest.approx((-100.0, 100.0))


def test_no_line_is_a_warning_and_null_numbers(fake, capsys):
    res = _fake_result(flux=np.zeros(50))
    fake["state"]["result"] = res
    assert main(_argv(fake, "--json")) == 0
    out, err = capsys.readouterr()
    got = json.loads(out)
    assert got["line_centre_kms"] is None and got["integrated_flux_jy_kms"] is None
    assert got["fit"]["converged"] is False and got["fit"]["message"]
    (line,) = err.splitlines()
    assert line.startswith("warning: no line fitted") and "--line-window" in line
    # with a window the integral is there all the same
    fake["out"] = fake["tmp"] / "again.zarr"
    assert main(_argv(fake, "--json", "--line-window=-50,50")) == 0
    got = json.loads(capsys.readouterr()[0])
    assert got["integrated_flux_jy_kms"] == 0.0 and got["integrated_flux_err_jy_kms"] > 0


# --- end to end -------------------------------------------------------------------------

N_CHAN, F0, DF = 48, 1.3990e9, 100e3  # Hz: channels of 21.4 km/s
E2E_PEAK, E2E_FWHM = 0.05, 150.0  # Jy, km/s


@pytest.fixture(scope="module")
def line_store(tmp_path_factory):
    """A tiny LSRK store with a Gaussian line (channel-averaged with erf) injected with plain
    numpy at three positions, each at its own redshift, plus noise."""
    from _uvstack_helpers import VLA_CENTER, make_stack_partition, point_source_vis

    from xstack.coords import lm_to_radec
    from xstack.schema import write_store

    d = tmp_path_factory.mktemp("linestack")
    ds = make_stack_partition(n_time=8, n_ant=6, n_chan=N_CHAN, freq0=F0, dfreq=DF, sigma=0.02,
                              seed=5)
    freq = np.asarray(ds["frequency"].values)
    uvw = np.asarray(ds["UVW"].values)
    vis = np.asarray(ds["VISIBILITY"].values).astype(np.complex128)
    sigma = E2E_FWHM / (2 * math.sqrt(2 * math.log(2)))
    rows = []
    for (l, m), chan in zip([(2e-3, -1e-3), (-1.5e-3, 2e-3), (1e-3, 1e-3)], (20.3, 24.8, 27.1)):
        centre = F0 + DF * chan
        ra, dec = lm_to_radec(l, m, *VLA_CENTER)
        v_lo = SPEED_OF_LIGHT_KMS * (centre - (freq + DF / 2)) / centre
        v_hi = SPEED_OF_LIGHT_KMS * (centre - (freq - DF / 2)) / centre
        profile = (E2E_PEAK * sigma * math.sqrt(math.pi / 2)
                   * (erf(v_hi / (math.sqrt(2) * sigma)) - erf(v_lo / (math.sqrt(2) * sigma)))
                   / (v_hi - v_lo))
        vis += (point_source_vis(uvw, freq, ra, dec, 1.0, VLA_CENTER, vis.shape[-1])
                * profile[None, None, :, None])
        rows.append(f"{math.degrees(ra)!r},{math.degrees(dec)!r},"
                    f"{float(LINES['HI'] / centre - 1)!r}")
    ds["VISIBILITY"] = (ds["VISIBILITY"].dims, vis.astype(ds["VISIBILITY"].dtype))
    ds["frequency"].attrs["observer"] = "lsrk"  # the catalog's frame: no Doppler track
    store = write_store({"spw0_field0": ds}, d / "data.zarr")
    cat = d / "cat.csv"
    cat.write_text("ra,dec,z\n" + "\n".join(rows) + "\n")
    return {"data": store, "cat": cat, "dir": d}


def test_end_to_end_against_the_library_and_the_truth(line_store, tmp_path, capsys):
    from xstack.fit.line import fit_line
    from xstack.uvstack.line import stack_lines

    opts = ["--line-frequency", "1420.405751768MHz", "--velocity-resolution", "30km/s",
            "--velocity-range=-450,450km/s", "--primary-beam", "none", "--weighting", "none",
            "--line-window=-300,300km/s"]
    out = tmp_path / "stack.zarr"
    assert main(["linestack", str(line_store["data"]), str(line_store["cat"]), str(out),
                 *opts, "--json"]) == 0
    got = json.loads(capsys.readouterr()[0])
    res = stack_lines(line_store["data"], str(line_store["cat"]), line_frequency="HI",
                      velocity_resolution=30.0, velocity_range=(-450, 450), primary_beam="none",
                      weighting="none")
    fit = fit_line(res.velocity_kms, res.flux_jy, res.flux_cov_jy2,
                   velocity_edges_kms=res.velocity_edges_kms, window_kms=(-300, 300))
    np.testing.assert_allclose(got["flux_jy"], res.flux_jy, rtol=1e-9)
    np.testing.assert_allclose(got["flux_err_jy"], res.flux_err_jy, rtol=1e-9)
    assert got["line_centre_kms"] == pytest.approx(fit.centre_kms, rel=1e-9, abs=1e-9)
    assert got["line_fwhm_kms"] == pytest.approx(fit.fwhm_kms, rel=1e-9)
    assert got["integrated_flux_jy_kms"] == pytest.approx(fit.integrated_flux_jy_kms, rel=1e-9)
    assert (got["n_positions"], got["n_visibilities"]) == (res.n_positions, res.n_visibilities)
    assert got["n_positions"] == 3
    # the injected line: all of it lies in the window (+-4.7 sigma), the regridding keeps flux
    truth = E2E_PEAK * E2E_FWHM / (2 * math.sqrt(2 * math.log(2))) * math.sqrt(2 * math.pi)
    err = got["integrated_flux_err_jy_kms"]
    assert abs(got["integrated_flux_jy_kms"] - truth) < 4 * err, (got["integrated_flux_jy_kms"],
                                                                   truth, err)
    assert abs(got["line_centre_kms"]) < 4 * got["line_centre_err_kms"]
    # channels (21 km/s) and bins (30 km/s) widen the line a little: sqrt(150^2 + ...) < 1 %
    assert got["line_fwhm_kms"] == pytest.approx(E2E_FWHM, rel=0.01, abs=4 * got["line_fwhm_err_kms"])
    assert (tmp_path / "stack_spectrum.ecsv").is_file()
    assert (tmp_path / "stack_spectrum.png").is_file()
    assert out.is_dir()


def test_verbose_and_quiet(fake, capsys):
    assert main(_argv(fake, "-v")) == 0
    out_v, err_v = capsys.readouterr()
    assert err_v.splitlines()[-1].startswith("xstack linestack: done in ")
    assert any("bins of 20 km/s" in x for x in err_v.splitlines())
    fake["out"] = fake["tmp"] / "quiet.zarr"
    assert main(_argv(fake, "-q")) == 0
    out_q, err_q = capsys.readouterr()
    assert err_q == "" and out_q.count("\n") == out_v.count("\n") == 2


def test_catalog_without_redshifts_is_a_one_line_error(line_store, tmp_path, capsys):
    cat = tmp_path / "noz.csv"
    cat.write_text(line_store["cat"].read_text().replace(",z\n", ",zz\n", 1))
    assert main(["linestack", str(line_store["data"]), str(cat), str(tmp_path / "o.zarr"),
                 "--line-frequency", "HI", "--primary-beam", "none"]) == 1
    out, err = capsys.readouterr()
    assert out == "" and len(err.splitlines()) == 1 and err.startswith("error: ")
    assert not (tmp_path / "o.zarr").exists() and not (tmp_path / "o_spectrum.ecsv").exists()


@pytest.mark.slow
def test_workers_give_the_threaded_json(line_store, tmp_path, capsys):
    """--workers 1 (a local cluster for the run) prints the threaded run's numbers."""
    opts = ["--line-frequency", "HI", "--velocity-resolution", "30km/s",
            "--velocity-range=-450,450km/s", "--primary-beam", "none", "--no-png", "--json"]
    runs = []
    for name, extra in (("threads", []), ("cluster", ["--workers", "1"])):
        assert main(["linestack", str(line_store["data"]), str(line_store["cat"]),
                     str(tmp_path / f"{name}.zarr"), *opts, *extra]) == 0
        runs.append(json.loads(capsys.readouterr()[0]))
    names = ("out", "output", "spectrum_table", "seconds")
    assert {k: v for k, v in runs[0].items() if k not in names} == \
        {k: v for k, v in runs[1].items() if k not in names}
