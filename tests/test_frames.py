"""Spectral frames (xstack.frames): the Doppler factor between frames against astropy's
SpectralCoord (an independent computation: xstack uses radial_velocity_correction and the LSR
solar motion), and the frame a store records through convert, open and export."""

from __future__ import annotations

import warnings

import casacore.tables as pt
import numpy as np
import pytest

from xstack._vocabulary import LINE_FRAMES
from xstack.errors import OptionError
from xstack.frames import (
    frame_from_meas_freq_ref,
    frame_name,
    frame_ratio,
    frequency_frame,
    meas_freq_ref,
    msv4_observer,
)
from xstack.io.convert import convert_ms
from xstack.io.export import export_ms
from xstack.schema import finish_store, iter_partitions, open_store
from xstack.testing import make_test_ms

C_KMS = 299_792.458
#: the VLA's array centre, ITRF metres
VLA = np.array([-1601185.4, -5041977.5, 3554875.9])
T0 = 60000.0 * 86400.0  # MJD seconds


def _spectralcoord_ratio(t_mjd_s, ra, dec, loc, frame):
    """nu_frame / nu_topo from astropy's SpectralCoord, one time at a time."""
    import astropy.units as u
    from astropy.coordinates import EarthLocation, SkyCoord, SpectralCoord
    from astropy.time import Time

    site = EarthLocation.from_geocentric(*loc, unit=u.m)
    target = SkyCoord(ra * u.deg, dec * u.deg, frame="icrs")
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no velocity defined on the target": at rest
        for t in np.atleast_1d(t_mjd_s):
            observer = site.get_gcrs(Time(t / 86400.0, format="mjd", scale="utc"))
            sc = SpectralCoord(1e9 * u.Hz, observer=observer, target=target)
            out.append(sc.with_observer_stationary_relative_to(frame).to_value(u.Hz) / 1e9)
    return np.asarray(out)


@pytest.mark.parametrize("frame, astropy_frame", [("BARY", "icrs"), ("LSRK", "lsrk"),
                                                  ("LSRD", "lsrd"), ("GEO", "gcrs")])
def test_frame_ratio_against_spectralcoord(frame, astropy_frame):
    t = T0 + np.linspace(0.0, 10 * 3600.0, 6)
    r = frame_ratio(t, 150.1, 2.2, VLA, to_frame=frame)
    ref = _spectralcoord_ratio(t, 150.1, 2.2, VLA, astropy_frame)
    # SpectralCoord applies the relativistic Doppler of the radial velocity only; the exact
    # moving-observer factor gamma (1 + beta.n) differs by the transverse term, beta^2/2
    # <= 5e-9 (1.5 m/s): far below any channel
    np.testing.assert_allclose(r, ref, rtol=0, atol=1e-8)
    # and the inverse
    back = frame_ratio(t, 150.1, 2.2, VLA, to_frame="TOPO", from_frame=frame)
    np.testing.assert_allclose(r * back, 1.0, rtol=0, atol=1e-15)


def test_frame_ratio_sizes_and_variation():
    # a year, once a week, at several hour angles: the barycentric correction is < 35 km/s
    # (Earth's orbit 29.8 km/s + rotation 0.46 km/s) and swings by ~2 x 30 cos(beta) km/s
    # over a year for a source near the ecliptic
    t = T0 + np.arange(0, 365) * 86400.0 + 0.3 * 86400.0
    v_bary = C_KMS * (1.0 - frame_ratio(t, 150.0, 12.0, VLA, to_frame="bary"))
    assert np.abs(v_bary).max() < 35.0
    assert np.ptp(v_bary) > 45.0
    # within a day the Earth's rotation (TOPO -> GEO): the site's speed omega * R_perp swings
    # by 2 omega R_perp cos(dec) (sidereal day), analytic
    day = T0 + np.linspace(0, 86400.0, 193)
    v_day = C_KMS * (1.0 - frame_ratio(day, 150.0, 12.0, VLA, to_frame="GEO"))
    swing = 2 * 7.2921150e-5 * np.hypot(VLA[0], VLA[1]) / 1e3 * np.cos(np.radians(12.0))
    np.testing.assert_allclose(np.ptp(v_day), swing, rtol=2e-3)
    # BARY over a day: the rotation plus the orbit's slow change (< 0.6 km/s a day)
    v_bday = C_KMS * (1.0 - frame_ratio(day, 150.0, 12.0, VLA, to_frame="BARY"))
    assert np.ptp(v_bday) < swing + 0.6
    # LSRK - BARY is the Sun's motion, 20 km/s towards (270, +30) B1900 ~ (270.5, 29.7) ICRS:
    # a source at the apex is blue-shifted at the Sun by 20 km/s (nu_lsrk = nu_bary / 1.0000667),
    # one opposite it red-shifted, one at right angles not at all; at every time
    for (ra, dec), expect in (((270.5, 29.7), 20.0), ((90.5, -29.7), -20.0),
                              ((90.0, 60.0), 0.0)):
        r_l = frame_ratio(t[:3], ra, dec, VLA, to_frame="LSRK", from_frame="BARY")
        np.testing.assert_allclose(C_KMS * (1.0 - r_l), expect, atol=0.1)
    # same frame: exactly 1
    assert np.all(frame_ratio(t, 150.0, 12.0, VLA, to_frame="lsrk", from_frame="LSRK") == 1.0)
    assert frame_ratio(t, 150.0, 12.0, VLA, to_frame="TOPO").dtype == np.float64
    # broadcasting over directions
    r = frame_ratio(t[:4, None], np.array([10.0, 200.0]), 5.0, VLA, to_frame="BARY")
    assert r.shape == (4, 2)
    np.testing.assert_array_equal(r[:, 1], frame_ratio(t[:4], 200.0, 5.0, VLA, to_frame="BARY"))


def test_frame_names():
    assert LINE_FRAMES == ("lsrk", "bary")
    assert frame_name("lsrk") == "LSRK" and frame_name("icrs") == "BARY"
    assert frame_name("gcrs") == "GEO" and frame_name("Topo") == "TOPO"
    assert msv4_observer("LSRK") == "lsrk" and msv4_observer("bary") == "BARY"
    assert [frame_from_meas_freq_ref(k) for k in range(9)] == [
        "REST", "LSRK", "LSRD", "BARY", "GEO", "TOPO", "GALACTO", "LGROUP", "CMB"]
    assert frame_from_meas_freq_ref(64) == "TOPO"
    assert meas_freq_ref("lsrk") == 1 and meas_freq_ref("TOPO") == 5
    with pytest.raises(OptionError):
        frame_name("nowhere")
    with pytest.raises(OptionError, match="cannot be converted"):
        frame_ratio([T0], 0.0, 0.0, VLA, to_frame="CMB")


def _set_frame(ms, code):
    with pt.table(f"{ms}/SPECTRAL_WINDOW", readonly=False, ack=False) as spw:
        spw.putcol("MEAS_FREQ_REF", np.full(spw.nrows(), code, dtype=np.int32))


def test_convert_records_frame_and_export_writes_it(tmp_path):
    ms = make_test_ms(tmp_path / "lsrk.ms", n_times=3, n_channels=2, n_antennas=4, n_spws=2)
    _set_frame(ms, 1)  # LSRK
    store = convert_ms(ms, tmp_path / "lsrk.zarr")
    parts = list(iter_partitions(open_store(store)))
    assert len(parts) == 2
    assert all(frequency_frame(ds) == "LSRK" for _, ds in parts)
    # on disk as xradio writes it
    import zarr

    root = zarr.open_group(str(store), mode="r")
    name = sorted(root.group_keys())[0]
    assert root[name]["frequency"].attrs["observer"] == "lsrk"
    out = export_ms(store, tmp_path / "back.ms")
    with pt.table(f"{out}/SPECTRAL_WINDOW", ack=False) as spw:
        np.testing.assert_array_equal(spw.getcol("MEAS_FREQ_REF"), [1, 1])


def test_bary_and_topo_round_trip(tmp_path):
    ms = make_test_ms(tmp_path / "bary.ms", n_times=2, n_channels=2, n_antennas=3)
    _set_frame(ms, 3)
    store = convert_ms(ms, tmp_path / "bary.zarr")
    (_, ds), = iter_partitions(open_store(store))
    assert frequency_frame(ds) == "BARY"
    out = export_ms(store, tmp_path / "bary_back.ms")
    with pt.table(f"{out}/SPECTRAL_WINDOW", ack=False) as spw:
        assert spw.getcol("MEAS_FREQ_REF").tolist() == [3]


def test_store_without_frame_is_topo(tmp_path):
    import zarr

    ms = make_test_ms(tmp_path / "old.ms", n_times=2, n_channels=2, n_antennas=3)
    _set_frame(ms, 1)
    store = convert_ms(ms, tmp_path / "old.zarr")
    # a store as xstack wrote it before it recorded frames... or another writer's without
    # the attribute at all
    root = zarr.open_group(str(store), mode="r+")
    for name in root.group_keys():
        attrs = root[name]["frequency"].attrs
        del attrs["observer"]
    finish_store(store)
    (_, ds), = iter_partitions(open_store(store))
    assert frequency_frame(ds) == "TOPO"
    out = export_ms(store, tmp_path / "old_back.ms")
    with pt.table(f"{out}/SPECTRAL_WINDOW", ack=False) as spw:
        assert spw.getcol("MEAS_FREQ_REF").tolist() == [5]


def test_xstack_writes_the_observer_as_xradio_does(tmp_path):
    """The same LSRK MS through xradio's converter and through xstack's: the same
    ``observer`` on disk, the same frame read back, and xradio's checker accepts ours."""
    import zarr
    from xradio import measurement_set as xradio_ms
    from xradio.schema.check import check_datatree

    ms = make_test_ms(tmp_path / "x.ms", n_times=2, n_channels=2, n_antennas=3)
    _set_frame(ms, 1)
    ours = convert_ms(ms, tmp_path / "ours.zarr")
    theirs = tmp_path / "theirs.ps.zarr"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        xradio_ms.convert_msv2_to_processing_set(str(ms), str(theirs), persistence_mode="w",
                                                 with_pointing=False)

    def observers(store):
        root = zarr.open_group(str(store), mode="r")
        return {str(root[k]["frequency"].attrs["observer"]) for k in root.group_keys()}

    assert observers(ours) == observers(theirs) == {"lsrk"}
    for store in (ours, theirs):
        assert {frequency_frame(ds) for _, ds in iter_partitions(open_store(store))} == {"LSRK"}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ps = xradio_ms.open_processing_set(str(ours))
        assert [str(p) for p in check_datatree(ps)] == []
