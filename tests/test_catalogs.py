"""Catalogs as astronomers write them (issue 11 item 3): formats, sexagesimal, units, refusals.

Truth: positions worked out by hand (h + m/60 + s/3600, x 15 for hours) and astropy's own
SkyCoord parsing of the same strings; never read_catalog itself.
"""

from __future__ import annotations

import numpy as np
import pytest
from astropy import units as u
from astropy.coordinates import SkyCoord
from astropy.table import QTable, Table

from xstack.coords import read_catalog
from xstack.errors import XstackError

# the issue's example: 10h08m00.016s +07d30m16.55s, by hand
RA1 = 15 * (10 + 8 / 60 + 0.016 / 3600)  # 152.0000666... deg (0.016 s of time = 0.24")
DEC1 = 7 + 30 / 60 + 16.55 / 3600  # 7.5045972... deg
# a southern one just below 0 deg, where the sign sits on a zero degree field
RA2 = 15 * (23 + 59 / 60 + 59.9 / 3600)
DEC2 = -(0 + 30 / 60 + 0.0 / 3600)
TRUE_RA, TRUE_DEC = np.array([RA1, RA2]), np.array([DEC1, DEC2])
TOL = 1e-9  # deg


def _check(cat: Table) -> None:
    assert cat["ra"].dtype == np.float64 and cat["dec"].dtype == np.float64
    np.testing.assert_allclose(cat["ra"], TRUE_RA, rtol=0, atol=TOL)
    np.testing.assert_allclose(cat["dec"], TRUE_DEC, rtol=0, atol=TOL)


def test_truth_agrees_with_astropy():
    sc = SkyCoord(["10 08 00.016 +07 30 16.55", "23 59 59.9 -00 30 00"],
                  unit=(u.hourangle, u.deg))
    np.testing.assert_allclose(sc.ra.deg, TRUE_RA, atol=1e-10)
    np.testing.assert_allclose(sc.dec.deg, TRUE_DEC, atol=1e-10)


def test_issue_example_sexagesimal_with_spaces_is_hours(tmp_path):
    # today read as degrees: ra = 10.13
    path = tmp_path / "targets.csv"
    path.write_text('ra,dec\n"10 08 00.016","+07 30 16.55"\n"23 59 59.9","-00 30 00"\n')
    cat = read_catalog(path)
    _check(cat)
    assert cat["ra"][0] == pytest.approx(152.0000667, abs=1e-7)


@pytest.mark.parametrize("ra, dec", [
    (["10 08 00.016", "23 59 59.9"], ["+07 30 16.55", "-00 30 00"]),
    (["10:08:00.016", "23:59:59.9"], ["+07:30:16.55", "-00:30:00"]),
    (["10h08m00.016s", "23h59m59.9s"], ["+07d30m16.55s", "-00d30m00s"]),
    (["10h08m00.016s", "23h59m59.9s"], ["+07°30′16.55″", "-00°30′00″"]),
    (["152.00006666666667d", "359.99958333333333deg"], ["7.504597222222222", "-0.5"]),
    ([f"{RA1:.14f}", f"{RA2:.14f}"], [f"{DEC1:.14f}", f"{DEC2:.14f}"]),
])
def test_text_forms(tmp_path, ra, dec):
    path = tmp_path / "c.csv"
    lines = ["ra,dec"] + [f'"{r}","{d}"' for r, d in zip(ra, dec)]
    path.write_text("\n".join(lines) + "\n")
    _check(read_catalog(path))


def test_whitespace_and_tab_separated(tmp_path):
    # today: "missing column(s) ra, dec (found: ra dec)"
    (tmp_path / "ws.txt").write_text(f"ra dec flux\n{RA1!r} {DEC1!r} 1e-3\n{RA2!r} {DEC2!r} 2e-3\n")
    cat = read_catalog(tmp_path / "ws.txt")
    _check(cat)
    assert list(cat["flux"]) == [1e-3, 2e-3]
    (tmp_path / "hdr.dat").write_text(f"# ra dec\n{RA1!r} {DEC1!r}\n{RA2!r} {DEC2!r}\n")
    _check(read_catalog(tmp_path / "hdr.dat"))
    (tmp_path / "q.txt").write_text('ra dec\n"10 08 00.016" "+07 30 16.55"\n'
                                    '"23 59 59.9" "-00 30 00"\n')
    _check(read_catalog(tmp_path / "q.txt"))
    (tmp_path / "t.tsv").write_text("ra\tdec\n10 08 00.016\t+07 30 16.55\n23 59 59.9\t-00 30 00\n")
    _check(read_catalog(tmp_path / "t.tsv"))


def test_unquoted_spaces_in_whitespace_file_are_refused_with_a_reason(tmp_path):
    (tmp_path / "u.txt").write_text("ra dec\n10 08 00.016 +07 30 16.55\n")
    with pytest.raises(XstackError, match="quoted"):
        read_catalog(tmp_path / "u.txt")


def test_units_in_headers(tmp_path):
    # numbers in hours (ECSV unit hourangle), radians (FITS TUNIT), degrees (VOTable)
    t = Table({"RA": TRUE_RA / 15, "DEC": TRUE_DEC, "name": ["a", "b"]})
    t["RA"].unit, t["DEC"].unit = u.hourangle, u.deg
    t.write(tmp_path / "h.ecsv")
    cat = read_catalog(tmp_path / "h.ecsv")
    _check(cat)
    assert list(cat["name"]) == ["a", "b"]
    t = Table({"ra": np.radians(TRUE_RA), "dec": np.radians(TRUE_DEC)})
    t["ra"].unit = t["dec"].unit = u.rad
    t.write(tmp_path / "r.fits")
    _check(read_catalog(tmp_path / "r.fits"))
    t = Table({"RAJ2000": TRUE_RA, "DEJ2000": TRUE_DEC})
    t["RAJ2000"].unit = t["DEJ2000"].unit = u.deg
    t.write(tmp_path / "v.vot", format="votable")
    _check(read_catalog(tmp_path / "v.vot"))
    # FITS catalogs write hours of RA as TUNIT 'h'
    t = Table({"ra": TRUE_RA / 15, "dec": TRUE_DEC})
    t["ra"].unit = u.h
    t.write(tmp_path / "hours.fits")
    _check(read_catalog(tmp_path / "hours.fits"))


@pytest.mark.filterwarnings("ignore::astropy.io.votable.exceptions.VOWarning")
def test_vizier_style_votable_sexagesimal_strings(tmp_path):
    # VizieR: RAJ2000 "h:m:s", DEJ2000 "d:m:s" strings, plus computed _RAJ2000 in degrees
    t = Table({"RAJ2000": ["10 08 00.016", "23 59 59.9"], "DEJ2000": ["+07 30 16.55", "-00 30 00"]})
    t["RAJ2000"].unit = u.Unit('"h:m:s"', parse_strict="silent")
    t["DEJ2000"].unit = u.Unit('"d:m:s"', parse_strict="silent")
    t.write(tmp_path / "viz.xml", format="votable")
    _check(read_catalog(tmp_path / "viz.xml"))


def test_quantity_skycoord_and_split_columns(tmp_path):
    q = QTable({"ra": (TRUE_RA * u.deg).to(u.arcmin), "dec": (TRUE_DEC * u.deg).to(u.arcsec)})
    _check(read_catalog(q))
    sc = Table({"pos": SkyCoord(TRUE_RA * u.deg, TRUE_DEC * u.deg), "weight": [1.0, 2.0]})
    sc.write(tmp_path / "sc.ecsv")
    cat = read_catalog(tmp_path / "sc.ecsv")
    _check(cat)
    assert list(cat["weight"]) == [1.0, 2.0]
    # CDS / VizieR ReadMe split columns
    split = Table({"RAh": [10, 23], "RAm": [8, 59], "RAs": [0.016, 59.9], "DE-": ["+", "-"],
                   "DEd": [7, 0], "DEm": [30, 30], "DEs": [16.55, 0.0]})
    _check(read_catalog(split))


def test_column_names_and_name_units(tmp_path):
    for ra_name, dec_name, scale in (("RA_ICRS", "DE_ICRS", 1.0), ("ALPHA_J2000", "DELTA_J2000", 1.0),
                                     ("_RAJ2000", "_DEJ2000", 1.0), ("ra_deg", "dec_deg", 1.0),
                                     ("ra_hours", "dec", 1 / 15)):
        cat = read_catalog(Table({ra_name: TRUE_RA * scale, dec_name: TRUE_DEC}))
        _check(cat)


def test_flux_unit_is_converted_and_other_columns_kept(tmp_path):
    t = Table({"ra": TRUE_RA, "dec": TRUE_DEC, "Flux": [20.0, 50.0], "z": [1.5, 2.0]})
    t["Flux"].unit = u.uJy
    t.write(tmp_path / "f.ecsv")
    cat = read_catalog(tmp_path / "f.ecsv")
    np.testing.assert_allclose(cat["flux"], [20e-6, 50e-6], rtol=1e-12)
    assert list(cat["z"]) == [1.5, 2.0]
    t["Flux"].unit = u.mJy / u.beam  # a point source's peak
    t.write(tmp_path / "p.ecsv")
    np.testing.assert_allclose(read_catalog(tmp_path / "p.ecsv")["flux"], [0.02, 0.05], rtol=1e-12)
    t["Flux"].unit = u.arcsec
    t.write(tmp_path / "g.ecsv")
    with pytest.raises(XstackError, match="flux"):
        read_catalog(tmp_path / "g.ecsv")


@pytest.mark.parametrize("text, match", [
    # mixed formats in one column: decimal degrees beside sexagesimal hours
    ('ra,dec\n"10 08 00.016",7.5\n152.0,7.5\n', r"row 2: ra='152.0'.*mixed formats"),
    ('ra,dec\n152.0,7.5\n10:08:00.016,7.5\n', r"row 2: .*mixed formats"),
    ('ra,dec\n10,+07:30:00\n10,7.5\n', r"row 2: dec.*mixed formats"),
    # neither a number nor sexagesimal
    ("ra,dec\n10,7\nabc,7\n", r"row 2: cannot read ra='abc'"),
    ("ra,dec\n10,7 30 00\n10,7 30 1 2\n", r"row 2: cannot read dec='7 30 1 2'"),
    # out of range
    ("ra,dec\n10,7\n360.5,7\n", r"row 2: ra=360.5 is outside \[0, 360\)"),
    ("ra,dec\n-0.5,7\n", r"row 1: ra=-0.5 is outside"),
    ("ra,dec\n10:00:00,7\n25:00:00,7\n", r"row 2: cannot read ra='25:00:00'.*hours"),
    ("ra,dec\n10,90.5\n", r"row 1: dec=90.5 is outside \[-90, 90\]"),
    ("ra,dec\n10:00:00,+95:00:00\n", r"row 1: dec='\+95:00:00' is outside"),
    ("ra,dec\n10:61:00,+05:00:00\n", r"row 1: cannot read ra='10:61:00'"),
    # declinations in hours
    ("ra,dec\n10:00:00,05h00m00s\n", r"row 1: dec='05h00m00s' is written in hours"),
    # empty and non-finite
    ("ra,dec\n10,7\n,7\n", r"row 2: column 'ra' is empty"),
    ("ra,dec\n10,nan\n", r"row 1: dec is not finite"),
])
def test_refusals_name_the_row_and_why(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(XstackError, match=match):
        read_catalog(path)


def test_refused_units(tmp_path):
    t = Table({"ra": TRUE_RA, "dec": TRUE_DEC})
    t["ra"].unit = u.Jy
    with pytest.raises(XstackError, match="not an angle"):
        read_catalog(t)
    t = Table({"ra": TRUE_RA, "dec": TRUE_DEC / 15})
    t["dec"].unit = u.hourangle
    with pytest.raises(XstackError, match="in hours"):
        read_catalog(t)


def test_tables_made_in_python_wrap_files_do_not(tmp_path):
    # positions computed across RA 0 in Python are wrapped; the same numbers in a file refused
    cat = read_catalog(Table({"ra": [360.004, -359.996, -0.5], "dec": [0.0] * 3}))
    np.testing.assert_allclose(cat["ra"], [0.004, 0.004, 359.5], atol=1e-9)
    with pytest.raises(XstackError, match="row 1: ra=720"):
        read_catalog(Table({"ra": [720.0], "dec": [0.0]}))  # arcmin? not wrapped
    Table({"ra": [360.004], "dec": [0.0]}).write(tmp_path / "c.fits")
    with pytest.raises(XstackError, match="row 1: ra=360.004 is outside"):
        read_catalog(tmp_path / "c.fits")


def test_rounding_at_360_wraps(tmp_path):
    cat = read_catalog(Table({"ra": [360.0 - 1e-12, 360.0 + 1e-12, -1e-12], "dec": [0.0] * 3}))
    assert np.all((cat["ra"] >= 0) & (cat["ra"] < 360))
    np.testing.assert_allclose(np.cos(np.radians(cat["ra"])), 1.0)


def test_large_sexagesimal_catalog_is_quick(tmp_path):
    import time

    rng = np.random.default_rng(1)
    n = 5000
    ra = rng.uniform(0, 360, n)
    dec = rng.uniform(-89, 89, n)
    sc = SkyCoord(ra * u.deg, dec * u.deg)
    rows = [f"{a},{d}" for a, d in zip(sc.ra.to_string(u.hourangle, sep=":", precision=4),
                                       sc.dec.to_string(u.deg, sep=":", precision=3,
                                                        alwayssign=True))]
    (tmp_path / "big.csv").write_text("ra,dec\n" + "\n".join(rows) + "\n")
    t0 = time.perf_counter()
    cat = read_catalog(tmp_path / "big.csv")
    assert time.perf_counter() - t0 < 10
    # 1e-4 s of time = 1.5 mas, 1e-3 arcsec: the precision written
    assert np.max(np.abs((cat["ra"] - ra + 180) % 360 - 180) * np.cos(np.radians(dec))) < 1e-6
    assert np.max(np.abs(cat["dec"] - dec)) < 1e-6
