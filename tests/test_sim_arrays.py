"""Antenna configurations and uvw geometry, including a real CASA-written MeasurementSet."""

from __future__ import annotations

import math

import numpy as np
import pytest

from xstack.errors import XstackError
from xstack.sim import arrays
from xstack.testing import require_real_ms


def test_packaged_arrays_have_the_papers_layout():
    vla = arrays.packaged_array("vla.a")
    alma = arrays.packaged_array("alma.cycle1.2")
    assert vla.n_antennas == 27 and alma.n_antennas == 32
    assert np.all(vla.diameters == 25.0) and np.all(alma.diameters == 12.0)

    def longest(p):
        d = p[:, None, :] - p[None, :, :]
        return np.sqrt((d**2).sum(-1)).max()

    assert 35e3 < longest(vla.positions) < 37e3  # "baselines up to 36 km"
    assert 290 < longest(alma.positions) < 310  # "maximum baseline of 300 m"
    # LOC -> ITRF puts the ALMA antennas on the Earth's surface near the observatory
    r = np.linalg.norm(alma.positions - np.array(arrays.OBSERVATORIES["ALMA"]), axis=1)
    assert r.max() < 400


def test_loc_conversion_preserves_distances_and_up(tmp_path):
    site = np.array(arrays.OBSERVATORIES["VLA"])
    enu = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 0.0, 50.0]])
    xyz = arrays.enu_to_itrf(enu, site)
    assert np.linalg.norm(xyz[1] - xyz[0]) == pytest.approx(100.0, abs=1e-9)
    up = (xyz[2] - xyz[0]) / 50.0
    lon, lat, _ = arrays.geodetic(site)
    expect = np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)])
    assert np.allclose(up, expect, atol=1e-12)
    cfg = tmp_path / "x.cfg"
    cfg.write_text("# observatory=VLA\n# coordsys=LOC\n0 0 0 25 A\n100 0 0 25 B\n#0 0 0 25 C\n")
    a = arrays.read_cfg(cfg)
    assert a.names == ["A", "B"] and np.allclose(a.positions, xyz[:2])


def test_bad_configs(tmp_path):
    with pytest.raises(XstackError, match="array.config"):
        arrays.packaged_array("vla.z")
    cfg = tmp_path / "bad.cfg"
    cfg.write_text("# observatory=VLA\n1 2 three 25 A\n")
    with pytest.raises(XstackError, match="bad.cfg:2"):
        arrays.read_cfg(cfg)
    with pytest.raises(XstackError, match="no antenna named"):
        arrays.packaged_array("vla.a").subset(["W08", "X99"])


def test_uvw_is_the_standard_hour_angle_formula():
    """Without precession (epoch of date) the projection reduces to the textbook formula
    u = sin H X + cos H Y, v = -sin d cos H X + sin d sin H Y + cos d Z, w = ...; check the
    ERFA-based geometry against it for an apparent-place direction, to 1e-6 of |b|."""
    vla = arrays.packaged_array("vla.a")
    t = np.array([5.0e9, 5.0e9 + 3600.0, 5.0e9 + 7200.0])
    ra, dec = 1.0, -0.5
    a1, a2 = np.array([0, 3, 20]), np.array([9, 17, 26])
    got = arrays.baseline_uvw(vla.positions, a1, a2, t, ra, dec)
    # textbook: Greenwich hour angle of the apparent (true-of-date) direction
    c2t = arrays.celestial_to_terrestrial(t)
    s_itrf = np.einsum("tij,j->ti", c2t, arrays.uvw_basis(ra, dec)[2])
    b = vla.positions[a1] - vla.positions[a2]
    for k in range(t.size):
        x, y, z = s_itrf[k]
        h = -math.atan2(y, x)  # Greenwich hour angle of the direction
        d = math.asin(z)
        sh, ch, sd, cd = math.sin(h), math.cos(h), math.sin(d), math.cos(d)
        mat = np.array([[sh, ch, 0.0], [-sd * ch, sd * sh, cd], [cd * ch, -cd * sh, sd]])
        ref = b @ mat.T
        # u, v axes differ only by the rotation of the celestial pole (precession/nutation
        # since J2000): compare w exactly and the length of (u, v)
        assert np.allclose(got[k, :, 2], ref[:, 2], atol=1e-6 * np.abs(b).max())
        assert np.allclose(np.hypot(got[k, :, 0], got[k, :, 1]), np.hypot(ref[:, 0], ref[:, 1]),
                           atol=1e-6 * np.abs(b).max())


@pytest.mark.realdata
def test_uvw_match_real_casa_alma_ms(tmp_path):
    """The ALMA MS written by CASA's importasdm: recompute UVW from its antenna positions,
    times and phase center. Agreement is ~1e-4 of the baseline (we neglect annual aberration
    and UT1-UTC); the opposite baseline order would be off by 2|b|."""
    from casacore.tables import table

    ms = require_real_ms("alma", tmp_path)
    with table(str(ms), ack=False) as t:
        uvw = t.getcol("UVW")
        a1, a2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
        times, fid = t.getcol("TIME"), t.getcol("FIELD_ID")
    with table(str(ms / "ANTENNA"), ack=False) as t:
        pos = t.getcol("POSITION")
    with table(str(ms / "FIELD"), ack=False) as t:
        pdir = t.getcol("PHASE_DIR")[:, 0]
    got = np.array([arrays.baseline_uvw(pos, a1[r:r + 1], a2[r:r + 1], times[r], *pdir[fid[r]])[0, 0]
                    for r in range(len(uvw))])
    blen = np.linalg.norm(uvw, axis=1)[:, None]
    assert np.all(np.abs(got - uvw) < 1.5e-4 * blen)
    assert np.all(np.abs(-got - uvw).max(axis=1) > 0.5 * blen[:, 0])


def test_time_of_hour_angle_and_elevation():
    vla = arrays.packaged_array("vla.a")
    lon, lat, _ = arrays.geodetic(vla.site)
    ra, dec = math.radians(57.2958), math.radians(-30.0)
    t = arrays.time_of_hour_angle(0.0, ra, lon, 56658.0)
    assert 56658.0 * 86400 <= t < 56659.0 * 86400
    lst = arrays.greenwich_sidereal_angle(t)[0] + lon
    assert abs(((lst - ra + math.pi) % (2 * math.pi)) - math.pi) < 1e-9
    # at transit the elevation is 90 - |lat - dec|
    el = arrays.elevation(vla.site, t, ra, dec)[0]
    assert math.degrees(el) == pytest.approx(90 - abs(math.degrees(lat) + 30.0), abs=0.3)


def test_shadowing_geometry():
    ant = np.zeros((1, 3, 3))
    ant[0, 1] = [5.0, 0.0, 10.0]  # 5 m away in projection, in front of antenna 0
    ant[0, 2] = [100.0, 0.0, 0.0]
    sh = arrays.shadowed_antennas(ant, np.array([12.0, 12.0, 12.0]))
    assert sh.tolist() == [[True, False, False]]
