"""``xstack info`` (issue 11 item 5): what listobs/imhead tell, checked against outside truth.

Truth comes from python-casacore reads of the real MSs in the pyuvdata wheel (never through
xstack's reader), from the simulator's known scene (phase center, band, array, noise sigma),
and from an image written by ``xstack image`` with known options.
"""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest

import xstack
from xstack.cli import main
from xstack.testing import require_real_ms

# casacore Stokes codes (casacore Stokes.h), independent of xstack's table
STOKES = {5: "RR", 6: "RL", 7: "LR", 8: "LL", 9: "XX", 10: "XY", 11: "YX", 12: "YY"}


def _quiet_info(path, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        d = xstack.info(path, **kw)
    return d, [str(w.message) for w in caught if issubclass(w.category, UserWarning)]


def _casacore_truth(ms) -> dict:
    """listobs-like facts read directly with python-casacore."""
    import casacore.tables as pt

    ms = str(ms)
    with pt.table(ms, ack=False) as t:
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        time, interval = t.getcol("TIME"), t.getcol("INTERVAL")
        fid = t.getcol("FIELD_ID")
        data = t.getcol("DATA")
        flag = t.getcol("FLAG") | t.getcol("FLAG_ROW")[:, None, None]
        if "WEIGHT_SPECTRUM" in t.colnames() and t.iscelldefined("WEIGHT_SPECTRUM", 0):
            weight = t.getcol("WEIGHT_SPECTRUM")
        else:
            weight = np.broadcast_to(t.getcol("WEIGHT")[:, None, :], data.shape)
    with pt.table(f"{ms}/FIELD", ack=False) as f:
        names = list(f.getcol("NAME"))
        pdir = f.getcol("PHASE_DIR")[:, 0, :]
    with pt.table(f"{ms}/SPECTRAL_WINDOW", ack=False) as s:
        freq = s.getcell("CHAN_FREQ", 0)
        width = s.getcell("CHAN_WIDTH", 0)
    with pt.table(f"{ms}/POLARIZATION", ack=False) as p:
        corr = [STOKES[int(c)] for c in p.getcell("CORR_TYPE", 0)]
    with pt.table(f"{ms}/ANTENNA", ack=False) as a:
        pos = a.getcol("POSITION")
        n_ant = a.nrows()
    pairs = {(min(i, j), max(i, j)) for i, j in zip(a1, a2) if i != j}
    lengths = [float(np.linalg.norm(pos[i] - pos[j])) for i, j in pairs]
    good = ~flag & (weight > 0) & np.isfinite(data.real) & np.isfinite(data.imag)
    return {"n_rows": a1.size, "cells": data.size, "flagged_fraction": 1 - good.mean(),
            "start": float(np.min(time - interval / 2)), "end": float(np.max(time + interval / 2)),
            "integration": float(np.median(interval)), "field_names": names, "phase_dir": pdir,
            "rows_per_field": np.bincount(fid, minlength=len(names)), "freq": freq,
            "width": width, "corr": corr, "n_ant": n_ant, "n_baselines": len(pairs),
            "longest": max(lengths), "shortest": min(lengths), "auto": bool(np.any(a1 == a2))}


def _check_against_truth(d: dict, truth: dict, kind: str) -> None:
    assert d["kind"] == kind
    assert d["real_cells"] == truth["cells"]  # every MS cell, no grid padding
    assert d["flagged_fraction"] == pytest.approx(truth["flagged_fraction"], abs=1e-12)
    assert d["time"]["start_mjd_s"] == pytest.approx(truth["start"], abs=1e-3)
    assert d["time"]["end_mjd_s"] == pytest.approx(truth["end"], abs=1e-3)
    assert d["antennas"]["count"] == truth["n_ant"]
    assert d["baselines"]["count"] == truth["n_baselines"]
    assert d["baselines"]["longest_m"] == pytest.approx(truth["longest"], rel=1e-12)
    assert d["baselines"]["shortest_m"] == pytest.approx(truth["shortest"], rel=1e-12)
    assert d["autocorrelations"] == truth["auto"]
    (spw,) = d["spectral_windows"]
    assert spw["n_channels"] == truth["freq"].size
    assert spw["first_channel_hz"] == truth["freq"][0]
    assert spw["last_channel_hz"] == truth["freq"][-1]
    assert spw["channel_width_hz"] == pytest.approx(float(np.median(truth["width"])))
    assert spw["total_bandwidth_hz"] == pytest.approx(float(np.sum(np.abs(truth["width"]))))
    assert spw["correlations"] == truth["corr"]
    assert d["correlations"] == truth["corr"]
    fields = {f["name"]: f for f in d["fields"]}
    for k, name in enumerate(truth["field_names"]):
        if kind == "store" and truth["rows_per_field"][k] == 0:
            assert name not in fields  # a store holds only fields with data
            continue
        f = fields[name]
        assert f["ra_deg"] == pytest.approx(math.degrees(truth["phase_dir"][k, 0]) % 360, abs=1e-9)
        assert f["dec_deg"] == pytest.approx(math.degrees(truth["phase_dir"][k, 1]), abs=1e-9)
        if kind == "ms":
            assert f["n_rows"] == truth["rows_per_field"][k]


@pytest.mark.realdata
@pytest.mark.parametrize("name", ["evla", "alma", "ovro-lwa"])
def test_real_ms_and_its_store_tell_what_casacore_reads(tmp_path, name):
    ms = require_real_ms(name, tmp_path)
    if name == "evla":
        # flag a random tenth of the cells, so the flagged fraction is not trivially 0
        import casacore.tables as pt

        with pt.table(str(ms), readonly=False, ack=False) as t:
            flag = t.getcol("FLAG")
            flag |= np.random.default_rng(5).uniform(size=flag.shape) < 0.1
            t.putcol("FLAG", flag)
    truth = _casacore_truth(ms)
    d, _ = _quiet_info(ms)
    _check_against_truth(d, truth, "ms")
    assert d["n_rows"] == truth["n_rows"]
    store = xstack.convert_ms(ms, tmp_path / "s.zarr")
    s, _ = _quiet_info(store)
    _check_against_truth(s, truth, "store")
    if name == "evla":
        # the EVLA grid is irregular (missing baselines, jittered times): padding exists but
        # is not counted (the old example printed "40.7 % flagged" for it)
        assert s["padding_cells"] > 0.3 * (s["padding_cells"] + s["real_cells"])
        assert 0.09 < s["flagged_fraction"] < 0.11


def test_evla_sexagesimal_phase_center(tmp_path):
    ms = require_real_ms("evla", tmp_path)
    d, _ = _quiet_info(ms)
    (f,) = d["fields"]
    # J1008+0730 as listobs prints it: 10:08:00.016000 +07.30.16.55200
    assert f["ra_hms"] == "10:08:00.0160"
    assert f["dec_dms"] == "+07:30:16.552"


def _sim_scene(sigma: float) -> dict:
    from xstack.sim.scene import PAPER_FIELD_CENTER

    ra0, dec0 = PAPER_FIELD_CENTER
    return {
        "name": "info", "array": {"config": "alma.cycle1.2"},
        "observation": {"hour_angle": [-0.5, 0.5], "integration": 6.0, "time_per_pointing": 60.0},
        "spectral": {"center": 230e9, "bandwidth": 2e9, "channels": 16,
                     "polarizations": ["XX", "YY"]},
        "pointings": {"mode": "single", "center": [ra0, dec0]},
        "effects": {"noise": {"sigma": sigma}},
        "populations": [{"name": "p", "count": 1, "flux": {"kind": "fixed", "value": 1e-3},
                         "positions": {"kind": "list", "ra": [ra0], "dec": [dec0]},
                         "shape": {"kind": "point"}}],
    }


@pytest.fixture(scope="module")
def sim_store(tmp_path_factory):
    d = tmp_path_factory.mktemp("siminfo")
    sigma = 0.05
    xstack.simulate(_sim_scene(sigma), d / "sim.zarr", seed=7)
    return d, d / "sim.zarr", sigma


def test_simulated_store_matches_its_scene(sim_store):
    from xstack.sim.arrays import packaged_array
    from xstack.sim.scene import PAPER_FIELD_CENTER

    _, store, _ = sim_store
    d, msgs = _quiet_info(store)
    assert msgs == []  # weights are 1/sigma^2 of the simulated noise: nothing to warn about
    (f,) = d["fields"]
    assert f["ra_deg"] == pytest.approx(PAPER_FIELD_CENTER[0], abs=1e-9)
    assert f["dec_deg"] == pytest.approx(PAPER_FIELD_CENTER[1], abs=1e-9)
    assert f["ra_hms"].startswith("03:49:10.99") and f["dec_dms"] == "-30:00:00.000"
    (spw,) = d["spectral_windows"]
    assert spw["n_channels"] == 16
    assert spw["total_bandwidth_hz"] == pytest.approx(2e9)
    assert spw["center_hz"] == pytest.approx(230e9)
    assert d["time"]["integration_s"] == 6.0
    assert d["time"]["duration_s"] == pytest.approx(60.0)
    n_ant = packaged_array("alma.cycle1.2").n_antennas
    assert d["antennas"]["count"] == n_ant
    assert d["baselines"]["count"] == n_ant * (n_ant - 1) // 2
    assert d["flagged_fraction"] == 0.0 and d["padding_cells"] == 0
    assert d["weights"]["sigma_ratio"] == pytest.approx(1.0, abs=0.05)
    assert d["weights"]["consistent"] is True


def test_misscaled_weights_are_warned_about(sim_store):
    from xstack.schema import iter_partitions, open_store, write_store

    d, store, _ = sim_store
    parts = {n: ds.assign(WEIGHT=ds.WEIGHT * 4.0) for n, ds in iter_partitions(open_store(store))}
    out = write_store(parts, d / "w4.zarr", overwrite=True)
    info, msgs = _quiet_info(out)
    # WEIGHT claims sigma^2 / 4: the data scatter is 2x the sigma the weights claim
    assert info["weights"]["variance_ratio"] == pytest.approx(4.0, rel=0.1)
    assert info["weights"]["sigma_ratio"] == pytest.approx(2.0, rel=0.05)
    assert info["weights"]["consistent"] is False
    assert len(msgs) == 1 and "not 1/sigma^2" in msgs[0] and "uvstack --errors" in msgs[0]


def test_image_written_by_xstack_image(sim_store, capsys):
    d, store, _ = sim_store
    out = d / "img.fits"
    assert main(["image", str(store), str(out), "--size", "64", "--cell", "0.5", "--pbcor",
                 "--no-progress", "--overwrite"]) == 0
    capsys.readouterr()
    assert main(["info", str(out), "--json"]) == 0
    cap = capsys.readouterr()
    info = json.loads(cap.out)
    from xstack.sim.scene import PAPER_FIELD_CENTER

    assert info["kind"] == "fits"
    assert info["size"] == [64, 64]
    assert info["cell_arcsec"] == pytest.approx([0.5, 0.5])
    assert info["bunit"] == "Jy/beam"
    assert info["reference"]["ra_deg"] == pytest.approx(PAPER_FIELD_CENTER[0], abs=1e-9)
    assert info["reference"]["dec_deg"] == pytest.approx(PAPER_FIELD_CENTER[1], abs=1e-9)
    assert info["frequency_hz"] == pytest.approx(230e9, rel=0.01)
    assert info["primary_beam"]["corrected"] is True
    assert info["primary_beam"]["file_exists"] is True
    assert info["mosaic"] is False and info["uv_dimensions"] == 2
    # ALMA at 230 GHz, <= ~300 m baselines: a beam of about 1", not a degenerate one
    assert 0.3 < info["beam"]["minor_arcsec"] <= info["beam"]["major_arcsec"] < 5
    assert cap.err == ""


def test_cli_text_and_one_line_errors(tmp_path, capsys):
    ms = require_real_ms("evla", tmp_path)
    assert main(["info", str(ms)]) == 0
    cap = capsys.readouterr()
    assert "10:08:00.0160 +07:30:16.552" in cap.out
    assert "0.0% flagged" in cap.out and "153 cross-correlations" in cap.out
    # the real EVLA weights are not 1/sigma^2 of its scatter: one warning line on stderr
    warn = [ln for ln in cap.err.splitlines() if ln]
    assert len(warn) == 1 and warn[0].startswith("warning: ") and "--errors" in warn[0]
    assert main(["info", str(tmp_path / "nothing.ms")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "no such" in err[0]
    (tmp_path / "x.txt").write_text("hello")
    assert main(["info", str(tmp_path / "x.txt")]) == 1
    assert "not a FITS image" in capsys.readouterr().err


def test_fits_header_facts_from_a_hand_written_image(tmp_path):
    from astropy.io import fits

    h = fits.Header()
    for k, v in {"CTYPE1": "RA---SIN", "CRVAL1": 150.0, "CDELT1": -1 / 3600, "CRPIX1": 17.0,
                 "CTYPE2": "DEC--SIN", "CRVAL2": -30.0, "CDELT2": 1 / 3600, "CRPIX2": 17.0,
                 "CTYPE3": "FREQ", "CRVAL3": 1.4e9, "CDELT3": 1e8, "CRPIX3": 1.0,
                 "BUNIT": "Jy/beam", "BMAJ": 5 / 3600, "BMIN": 4 / 3600, "BPA": 30.0,
                 "OBSRA": 150.01, "OBSDEC": -30.02, "XSMOSAIC": 3, "XSPBFILE": "gone.pb.fits",
                 "XSUVDIM": 1}.items():
        h[k] = v
    data = np.full((1, 32, 32), 1.0, np.float32)
    data[0, :4] = np.nan
    fits.PrimaryHDU(data, header=h).writeto(tmp_path / "m.fits")
    d, msgs = _quiet_info(tmp_path / "m.fits")
    assert d["size"] == [32, 32] and d["cell_arcsec"] == pytest.approx([1.0, 1.0])
    assert d["beam"] == pytest.approx({"major_arcsec": 5.0, "minor_arcsec": 4.0, "pa_deg": 30.0})
    assert d["frequency_hz"] == 1.4e9 and d["bandwidth_hz"] == 1e8
    assert d["reference"]["ra_hms"] == "10:00:00.0000" and d["reference"]["dec_dms"] == "-30:00:00.000"
    assert d["pointing"]["ra_deg"] == pytest.approx(150.01) and d["pointing_from"] == "OBSRA/OBSDEC"
    assert d["mosaic"] is True and d["n_pointings"] == 3
    assert d["primary_beam"]["corrected"] is None  # no XSPBCOR: the header does not say
    assert d["primary_beam"]["file_exists"] is False
    assert d["blanked_fraction"] == pytest.approx(4 / 32)
    assert len(msgs) == 2
    assert any("one-dimensional" in m for m in msgs) and any("gone.pb.fits" in m for m in msgs)
