"""Units on every command-line option that is a physical quantity (issue 11 item 3).

Truth: astropy's own conversion of the same quantity (``u.Quantity("0.4 arcsec")``) and
worked examples by hand (2 arcmin = 120 arcsec, 23.8 klambda = 23800 wavelengths).
"""

from __future__ import annotations

import argparse
import json

import pytest
from astropy import units as u

from xstack.cli import _types, build_parser, main
from xstack.coords import (
    parse_angle,
    parse_distance,
    parse_flux,
    parse_frequency,
    parse_velocity,
)
from xstack.errors import XstackError

# (command, positional arguments) that let the parser accept an option
POSITIONALS = {
    "image": ["d.zarr", "o.fits", "--size", "64", "--cell", "1"],
    "imstack": ["i.fits", "c.csv", "o.fits"],
    "noise": ["d.zarr", "c.csv"],
    "fit": ["s.zarr"],
    "uvstack": ["d.zarr", "c.csv", "o.zarr"],
}
#: every option that is a physical quantity, and the type that reads it
QUANTITY_OPTIONS = {
    ("image", "--cell"): _types.angle_arcsec,
    ("image", "--threshold"): _types.threshold_jy,
    ("imstack", "--mask-radius"): _types.angle_arcsec,
    ("imstack", "--filter"): _types.filter_cells_or_distance,
    ("noise", "--flux"): _types.flux_jy,
    ("noise", "--line-flux"): _types.line_flux_jy_kms,
    ("noise", "--min-separation"): _types.separation_arcsec,
    ("noise", "--field-radius"): _types.angle_arcsec,
    ("noise", "--uvmin"): _types.uv_distance,
    ("noise", "--uvmax"): _types.uv_distance,
    ("fit", "--uvmin"): _types.uv_distance,
    ("fit", "--uvmax"): _types.uv_distance,
    ("fit", "--fit-radius"): _types.angle_arcsec,
    ("uvstack", "--uvmin"): _types.uv_distance,
    ("uvstack", "--uvmax"): _types.uv_distance,
}


def _parse(command: str, option: str, value: str) -> argparse.Namespace:
    argv = [command, *POSITIONALS[command]]
    if option in argv:
        i = argv.index(option)
        del argv[i:i + 2]
    argv += [f"{option}={value}"]  # with "=": a negative value is not taken for an option
    return build_parser().parse_args(argv)


def _dest(option: str) -> str:
    # imstack's flags store under the library's parameter names (errors then name the flag)
    renamed = {"--mask-radius": "beam_mask_arcsec", "--filter": "filter_lowfreq"}
    return renamed.get(option, option.lstrip("-").replace("-", "_"))


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


# ------------------------------------------------------------------------- every option

def test_every_quantity_option_uses_a_unit_type_and_names_its_default_unit():
    subs = _subparsers()
    for (command, option), kind in QUANTITY_OPTIONS.items():
        action = next(a for a in subs[command]._actions if option in a.option_strings)
        assert action.type is kind, (command, option)
        assert "plain number" in (action.help or "") or "as --uvmin" in (action.help or "") \
            or option == "--filter", (command, option, action.help)


def test_no_other_option_reads_a_quantity_as_a_bare_float():
    # a number option whose help names a unit, or a text option whose help shows a quantity
    # (20uJy, 5000m), must read units with a type of xstack.cli._types
    import re

    unit_words = ("arcsec", "arcmin", " jy", "klambda", "metres", "degrees")
    example = re.compile(r"\d(?:ujy|mjy|jy|arcsec|arcmin|deg|klambda|lambda|km|m)\b")
    for command, sub in _subparsers().items():
        for action in sub._actions:
            if not action.option_strings or (command, action.option_strings[-1]) in QUANTITY_OPTIONS:
                continue
            text = f"{action.help or ''} {action.metavar or ''}".lower()
            where = (command, action.option_strings, action.help)
            if action.type in (float, int):
                assert not any(w in text for w in unit_words), where
            if action.type is None and action.nargs != 0:
                assert not example.search(text), where
            assert action.metavar not in ("ARCSEC", "JY", "DEG"), where


# ------------------------------------------------------------------------- values

ANGLES = ["0.4arcsec", "0.4 arcsec", "2arcmin", "1e-4deg", "5mas", "0.4ARCSEC", "2Arcmin", '3"',
          "0.4"]


@pytest.mark.parametrize("text", ANGLES)
@pytest.mark.parametrize("command, option", [("image", "--cell"), ("imstack", "--mask-radius"),
                                             ("noise", "--field-radius"),
                                             ("noise", "--min-separation"),
                                             ("fit", "--fit-radius")])
def test_angle_options(command, option, text):
    value = getattr(_parse(command, option, text), _dest(option))
    # astropy's conversion of the same quantity (canonical spelling; a plain number is arcsec)
    canonical = {"0.4ARCSEC": "0.4arcsec", "2Arcmin": "2arcmin", '3"': "3arcsec",
                 "0.4": "0.4arcsec"}.get(text, text)
    assert value == pytest.approx(u.Quantity(canonical).to_value(u.arcsec), rel=1e-12)


def test_angle_worked_examples():
    assert _parse("image", "--cell", "2arcmin").cell == pytest.approx(120.0)
    assert _parse("image", "--cell", "1e-4deg").cell == pytest.approx(0.36)
    assert _parse("fit", "--fit-radius", "0.5arcmin").fit_radius == pytest.approx(30.0)


@pytest.mark.parametrize("text, jy", [("5mJy", 5e-3), ("50uJy", 50e-6), ("50µJy", 50e-6),
                                      ("50μJy", 50e-6), ("50UJY", 50e-6), ("50uJy/beam", 50e-6),
                                      ("0.05mJy/beam", 50e-6), ("0.001", 1e-3), ("2e-3Jy", 2e-3),
                                      ("5MJy", 5e6), ("0", 0.0)])
def test_threshold(text, jy):
    assert _parse("image", "--threshold", text).threshold == pytest.approx(jy, rel=1e-12)


@pytest.mark.parametrize("text", ["20uJy", "2mJy", "1.5e-3 Jy", "3nJy"])
def test_flux_option_against_astropy(text):
    assert _parse("noise", "--flux", text).flux == pytest.approx(
        u.Quantity(text).to_value(u.Jy), rel=1e-12)


@pytest.mark.parametrize("text, jykms", [("0.2", 0.2), ("0.2Jy km/s", 0.2),
                                         ("200mJy km/s", 0.2), ("200 Jy m / s", 0.2)])
def test_line_flux_option(text, jykms):
    assert _parse("noise", "--line-flux", text).line_flux_jy_kms == pytest.approx(jykms,
                                                                                  rel=1e-12)


@pytest.mark.parametrize("command", ["noise", "fit", "uvstack"])
@pytest.mark.parametrize("text, expected", [("23.8klambda", (23800.0, "lambda")),
                                            ("23.8KLAMBDA", (23800.0, "lambda")),
                                            ("1e5lambda", (1e5, "lambda")),
                                            ("0.5Mlambda", (5e5, "lambda")),
                                            ("5000m", (5000.0, "m")), ("5km", (5000.0, "m")),
                                            ("5KM", (5000.0, "m")), ("5000", (5000.0, "m"))])
def test_uv_distance_options(command, text, expected):
    args = _parse(command, "--uvmin", text)
    # the option keeps the text; the library reads it with parse_distance
    value, unit = parse_distance(args.uvmin)
    assert unit == expected[1]
    assert value == pytest.approx(expected[0], rel=1e-12)


def test_filter_cells_or_distance():
    assert _parse("imstack", "--filter", "3").filter_lowfreq == 3
    assert _parse("imstack", "--filter", "20klambda").filter_lowfreq == "20klambda"


# ------------------------------------------------------------------------- refusals

@pytest.mark.parametrize("command, option, text, words", [
    ("image", "--threshold", "5MJY", ["--threshold", "mJy", "MJy", "ambiguous"]),
    ("image", "--threshold", "5mjy", ["ambiguous", "mJy", "MJy"]),
    ("noise", "--flux", "20MJY", ["--flux", "ambiguous"]),
    ("image", "--cell", "0.4mJy", ["--cell", "not an angle"]),
    ("image", "--cell", "0", ["--cell", "> 0"]),
    ("image", "--cell", "-1arcsec", ["--cell", "> 0"]),
    ("image", "--cell", "abc", ["--cell", "cannot read"]),
    ("image", "--threshold", "-1mJy", ["--threshold", ">= 0"]),
    ("noise", "--min-separation", "-1arcsec", [">= 0"]),
    ("noise", "--uvmin", "5parsec", ["--uvmin", "unknown unit 'parsec'"]),
    ("uvstack", "--uvmax", "-5m", ["--uvmax", ">= 0"]),
    ("fit", "--uvmin", "5 Jy", ["--uvmin", "unknown unit"]),
    ("imstack", "--filter", "20foo", ["--filter", "unknown unit"]),
    ("noise", "--field-radius", "2 pc", ["--field-radius", "not an angle"]),
])
def test_refusals(command, option, text, words, capsys):
    with pytest.raises(SystemExit) as exc:
        _parse(command, option, text)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    for word in words:
        assert word in err, (word, err)


# ------------------------------------------------------------------------- the parsers

@pytest.mark.parametrize("text, unit", [("0.4arcsec", "arcsec"), ("2arcmin", "arcsec"),
                                        ("1e-4deg", "arcsec"), ("0.5deg", "rad"),
                                        ("3.2 mas", "deg")])
def test_parse_angle_against_astropy(text, unit):
    assert parse_angle(text, unit) == pytest.approx(u.Quantity(text).to_value(unit), rel=1e-12)
    assert parse_angle(u.Quantity(text), unit) == pytest.approx(u.Quantity(text).to_value(unit))


def test_parse_frequency_and_velocity_against_astropy():
    assert parse_frequency("1420.405751786MHz") == pytest.approx(1420.405751786e6, rel=1e-15)
    assert parse_frequency("1.4GHZ") == pytest.approx(1.4e9)
    assert parse_frequency("1.4e9") == 1.4e9
    with pytest.raises(XstackError, match="MHz.*mHz|mHz.*MHz"):
        parse_frequency("1420mhz")
    assert parse_velocity("20km/s") == pytest.approx(20.0)
    assert parse_velocity("20KM/S") == pytest.approx(20.0)
    assert parse_velocity("2e4m/s") == pytest.approx(u.Quantity("2e4 m/s").to_value("km/s"))
    assert _types.frequency_hz("1.4GHz") == pytest.approx(1.4e9)
    assert _types.velocity_kms("20") == 20.0


def test_parse_flux_rules():
    assert parse_flux("5MJy") == pytest.approx(5e6)  # astropy's spelling: mega
    assert parse_flux("5mJy") == pytest.approx(5e-3)
    with pytest.raises(XstackError, match="ambiguous"):
        parse_flux("5MJY")
    with pytest.raises(XstackError, match="not a flux density"):
        parse_flux("50uJy/beam")  # per beam only where an image value is meant
    assert parse_flux("50uJy/beam", per_beam=True) == pytest.approx(50e-6)
    assert parse_flux(2 * u.mJy) == pytest.approx(2e-3)


# ------------------------------------------------------------------------- end to end

def test_image_cell_with_units_end_to_end(tmp_path, capsys):
    from _imaging_helpers import make_sky_partition

    from xstack.schema import write_store

    ds = make_sky_partition([], n_time=4, n_ant=6, noise=0.1, seed=1, n_chan=2)
    write_store({"spw0_field0": ds}, tmp_path / "d.zarr")
    cells = {}
    for name, cell in (("plain", "2"), ("arcsec", "2arcsec"), ("arcmin", "0.0333333333333333arcmin"),
                       ("deg", f"{2 / 3600!r}deg")):
        rc = main(["image", str(tmp_path / "d.zarr"), str(tmp_path / f"{name}.fits"), "--size",
                   "32", "--cell", cell, "--threshold", "1mJy", "--json", "--no-progress"])
        assert rc == 0
        cells[name] = json.loads(capsys.readouterr().out)["cell_arcsec"]
    for value in cells.values():
        assert value == pytest.approx(2.0, rel=1e-12)


def test_imstack_option_errors_name_the_flags(tmp_path, capsys):
    """A bad --filter (checked by the library) is reported with its flag, not the API name."""
    from xstack.cli import main

    rc = main(["imstack", str(tmp_path / "none.fits"), str(tmp_path / "none.csv"),
               str(tmp_path / "out.fits"), "--filter", "2"])
    err = capsys.readouterr().err
    assert rc != 0 and "--filter" in err, err
    assert "filter_lowfreq" not in err
