"""Tests of the MS generator and the real-MS helper (xstack.testing)."""

from __future__ import annotations

import casacore.tables as pt
import numpy as np
import pytest

from xstack.testing import make_test_ms, real_ms, require_real_ms


def _sub(ms, name):
    return pt.table(f"{ms}/{name}", ack=False)


def test_make_test_ms_structure(tmp_path):
    ms = make_test_ms(tmp_path / "a.ms", n_antennas=7, n_times=5, n_channels=[3, 5], n_spws=2,
                      n_fields=2, scans=3, missing_baselines=4, missing_rows=0.2,
                      flag_row_fraction=0.1, datacolumns=("DATA", "MODEL_DATA"), seed=3)
    with pt.table(str(ms), ack=False) as t:
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        pairs = set(zip(a1.tolist(), a2.tolist()))
        assert len(pairs) == 21 - 4  # 7 antennas, 4 baselines missing
        assert set(t.getcol("DATA_DESC_ID").tolist()) == {0, 1}
        assert t.getcol("SCAN_NUMBER").tolist() == sorted(t.getcol("SCAN_NUMBER").tolist())
        assert set(t.getcol("SCAN_NUMBER").tolist()) == {1, 2, 3}
        # scan k observes field k % 2
        scan, field = t.getcol("SCAN_NUMBER"), t.getcol("FIELD_ID")
        assert np.all(field == (scan - 1) % 2)
        # variable-shaped data (3 and 5 channels)
        ddid = t.getcol("DATA_DESC_ID")
        r0, r1 = int(np.flatnonzero(ddid == 0)[0]), int(np.flatnonzero(ddid == 1)[0])
        assert t.getcell("DATA", r0).shape == (3, 2)
        assert t.getcell("DATA", r1).shape == (5, 2)
        # missing rows: fewer than the full grid
        assert t.nrows() < 3 * 5 * 2 * 17
        assert 0 < t.getcol("FLAG_ROW").sum() < t.nrows()
        assert t.getcolkeywords("UVW")["MEASINFO"]["Ref"] == "J2000"
    assert _sub(ms, "FEED").nrows() == 7
    assert _sub(ms, "FIELD").nrows() == 2
    assert _sub(ms, "SPECTRAL_WINDOW").getcell("NUM_CHAN", 1) == 5
    assert _sub(ms, "OBSERVATION").getcell("TELESCOPE_NAME", 0) == "ALMA"
    assert list(_sub(ms, "POLARIZATION").getcell("CORR_TYPE", 0)) == [9, 12]


def test_make_test_ms_uvw_and_source_phase(tmp_path):
    """UVW are a rotation of the ITRF baselines; the model follows V = S exp(+2 pi i ...)."""
    from xstack.coords import radec_to_lmn

    ra_s, dec_s = 57.30, -29.99
    ms = make_test_ms(tmp_path / "b.ms", n_antennas=5, n_times=4, n_channels=3,
                      datacolumns=("MODEL_DATA",), sources=[(ra_s, dec_s, 2.5)], seed=1)
    with pt.table(str(ms), ack=False) as t:
        uvw = t.getcol("UVW")
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        model = t.getcol("MODEL_DATA")
    pos = _sub(ms, "ANTENNA").getcol("POSITION")
    np.testing.assert_allclose(np.linalg.norm(uvw, axis=1), np.linalg.norm(pos[a2] - pos[a1], axis=1),
                               rtol=1e-12)
    ra0, dec0 = _sub(ms, "FIELD").getcol("PHASE_DIR")[0, 0]
    freq = _sub(ms, "SPECTRAL_WINDOW").getcell("CHAN_FREQ", 0)
    l, m, n, _ = radec_to_lmn(np.deg2rad(ra_s), np.deg2rad(dec_s), ra0, dec0)
    # independent plain formula (n - 1 computed naively is accurate enough here)
    phase = 2 * np.pi * (uvw[:, 0, None] * l + uvw[:, 1, None] * m + uvw[:, 2, None] * (n - 1)) \
        * freq[None] / 299792458.0
    expect = 2.5 * np.exp(1j * phase)
    np.testing.assert_allclose(model[:, :, 0], expect, rtol=0, atol=1e-5)
    np.testing.assert_allclose(model[:, :, 1], expect, rtol=0, atol=1e-5)


def test_make_test_ms_weights(tmp_path):
    ms = make_test_ms(tmp_path / "w.ms", weight_spectrum=True, noise_jy=2.0, n_channels=6)
    with pt.table(str(ms), ack=False) as t:
        ws, w, s = t.getcol("WEIGHT_SPECTRUM"), t.getcol("WEIGHT"), t.getcol("SIGMA")
    assert ws.shape[1] == 6 and np.ptp(ws, axis=1).max() > 0  # varies with channel
    np.testing.assert_allclose(w, np.median(ws, axis=1), rtol=1e-6)
    np.testing.assert_allclose(s, 1 / np.sqrt(w), rtol=1e-6)
    assert 0.5 / 4 <= ws.min() and ws.max() <= 2.0 / 4
    ms2 = make_test_ms(tmp_path / "s.ms", weight_spectrum=False, write_weight=False)
    with pt.table(str(ms2), ack=False) as t:
        assert "WEIGHT_SPECTRUM" not in t.colnames()
        assert not t.iscelldefined("WEIGHT", 0)
        assert t.iscelldefined("SIGMA", 0)


def test_make_test_ms_refuses_existing(tmp_path):
    (tmp_path / "x.ms").mkdir()
    with pytest.raises(FileExistsError):
        make_test_ms(tmp_path / "x.ms")


@pytest.mark.realdata
@pytest.mark.parametrize("name,nrows,telescope", [("evla", 1360, "EVLA"), ("alma", 40, "ALMA")])
def test_real_ms(tmp_path, name, nrows, telescope):
    ms = require_real_ms(name, tmp_path)
    assert ms.parent == tmp_path
    with pt.table(str(ms), ack=False) as t:
        assert t.nrows() == nrows
    assert _sub(ms, "OBSERVATION").getcell("TELESCOPE_NAME", 0) == telescope
    assert real_ms(name, tmp_path) == ms  # second call reuses the copy


def test_real_ms_unknown_name(tmp_path):
    with pytest.raises(ValueError, match="unknown real MS"):
        real_ms("vlba", tmp_path)
