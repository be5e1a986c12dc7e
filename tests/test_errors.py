"""Typed errors, warnings that name the option, one-line command-line errors (issue 11,
items 4 and 9)."""

from __future__ import annotations

import ast
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.table import Table

import xstack
from xstack.cli import build_parser, main, name_flags
from xstack.errors import (
    NoDataError,
    OptionError,
    OutputExistsError,
    WeightsWarning,
    XstackError,
    XstackWarning,
)
from xstack.schema import write_store

PACKAGE = Path(xstack.__file__).parent


# --- typed errors ---------------------------------------------------------------------------

def test_existing_output_is_a_file_exists_error(tmp_path):
    from xstack._atomic import atomic_output, check_output

    out = tmp_path / "out.zarr"
    out.mkdir()
    for attempt in (lambda: check_output(out, False), lambda: atomic_output(out).__enter__()):
        with pytest.raises(FileExistsError) as exc:
            attempt()
        assert isinstance(exc.value, XstackError) and isinstance(exc.value, OutputExistsError)
        assert "--" not in str(exc.value)  # the library names the parameter, not the flag
        assert exc.value.option == "overwrite"


def _catalog(n=3, offset_deg=0.0):
    ra, dec = np.degrees(VLA_CENTER)
    return Table({"ra": ra + offset_deg + 1e-3 * np.arange(n), "dec": np.full(n, dec)})


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    path = tmp_path_factory.mktemp("err") / "s.zarr"
    write_store({"spw0_field0": make_stack_partition(n_ant=5, n_time=4, n_chan=2, sigma=1.0)},
                path)
    return path


@pytest.mark.parametrize("call", [
    lambda s: xstack.stack_uv(s, _catalog(), weighting="optimal"),
    lambda s: xstack.stack_uv(s, _catalog(), engine="gpu"),
    lambda s: xstack.stack_uv(s, _catalog(), pb_cutoff=1.5),
    lambda s: xstack.stack_uv(s, _catalog(), smearing="maybe"),
    lambda s: xstack.estimate_noise(s, _catalog(), method="jackknife"),
    lambda s: xstack.estimate_noise(s, _catalog(), weighting="optimal"),
    lambda s: xstack.stack_images("x.fits", _catalog(), method="mode"),
    lambda s: xstack.make_image(s, size=64, cell_arcsec=1.0, weighting="robust"),
    lambda s: xstack.PrimaryBeam("square"),
])
def test_bad_options_are_value_errors(call, store):
    with pytest.raises(ValueError) as exc:
        call(store)
    assert isinstance(exc.value, OptionError) and isinstance(exc.value, XstackError)


def test_no_data_is_a_no_data_error(store):
    far = _catalog(offset_deg=30.0)  # 30 deg from the pointing: outside every beam
    with pytest.raises(NoDataError) as exc:
        xstack.stack_uv(store, far)
    assert isinstance(exc.value, XstackError)


def test_no_recovery_by_matching_message_strings():
    rx = re.compile(r"""["'][^"']*["']\s+(not\s+)?in\s+str\((exc|e|err|error)\)""")
    hits = [f"{p.relative_to(PACKAGE)}:{i}" for p in PACKAGE.rglob("*.py")
            for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
            if rx.search(line)]
    assert hits == []


# --- warnings name the API parameter in the library, the flag on the command line -----------

def _warn_texts(path: Path) -> list[tuple[int, str]]:
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "warn" \
                and getattr(node.func.value, "id", None) == "warnings":
            parts = [n.value for n in ast.walk(node)
                     if isinstance(n, ast.Constant) and isinstance(n.value, str)]
            out.append((node.lineno, " ".join(parts)))
    return out


def test_library_warnings_never_name_command_line_flags():
    flag = re.compile(r"(?<![\w-])--[a-z][a-z-]+")
    found = [f"{p.relative_to(PACKAGE)}:{line}: {text[:80]}"
             for p in sorted(PACKAGE.rglob("*.py")) if "cli" not in p.relative_to(PACKAGE).parts
             for line, text in _warn_texts(p) if flag.search(text)]
    assert found == []


def test_library_errors_never_name_command_line_flags():
    flag = re.compile(r"(?<![\w-])--[a-z][a-z-]+")
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if "cli" in path.relative_to(PACKAGE).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Raise) and node.exc is not None:
                text = " ".join(n.value for n in ast.walk(node.exc)
                                if isinstance(n, ast.Constant) and isinstance(n.value, str))
                if flag.search(text):
                    found.append(f"{path.relative_to(PACKAGE)}:{node.lineno}: {text[:80]}")
    assert found == []


def _sub(command):
    top = build_parser()
    sub = next(a for a in top._actions if isinstance(a.choices, dict))
    return sub.choices[command]


def test_cli_names_the_flag_of_the_parameter():
    noise = _sub("noise")
    text = "give the area with region=POLYGON (a polygon file) or region='beam' (the region)"
    assert name_flags(text, "region", noise) == \
        "give the area with --region POLYGON (a polygon file) or --region beam (the region)"
    # a bare name with an underscore cannot be prose: translated; several parameters at once
    assert name_flags("lower min_separation_arcsec or a larger region=", ("min_separation_arcsec",
                      "region"), noise) == "lower --min-separation or a larger --region"
    # unit suffixes of API names are left out by the flags; a message that does not say
    # the parameter gets the flag appended
    assert name_flags("too close", "min_separation_arcsec", noise) == "too close (--min-separation)"
    # switches take no value; a value the flag does not take shows the flag's choices
    assert name_flags("x exists (pass overwrite=True to replace it)", "overwrite",
                      _sub("uvstack")) == "x exists (pass --overwrite to replace it)"
    assert name_flags("state it with image_corrected=True/False", "image_corrected",
                      _sub("noise")) == "state it with --image-corrected yes|no"
    # a parameter the command has no flag for: the text as it is
    assert name_flags("weights are odd", "no_such", noise) == "weights are odd"


def _x100_store(tmp_path):
    ds = make_stack_partition(n_time=8, n_ant=6, n_chan=8, sigma=1.0, seed=1)
    ds["WEIGHT"] = ds["WEIGHT"] * 100  # weights 100x too large: the two errors disagree
    path = tmp_path / "x100.zarr"
    write_store({"spw0_field0": ds}, path)
    cat = tmp_path / "cat.csv"
    _catalog(1).write(cat, format="ascii.csv")
    return path, cat


def test_cli_warning_is_one_line_naming_the_flag(tmp_path, capsys):
    store, cat = _x100_store(tmp_path)
    with pytest.warns(XstackWarning, match="errors='empirical'") as rec:
        xstack.stack_uv(store, str(cat), weighting="none", primary_beam="none")
    assert [w.message.option for w in rec if isinstance(w.message, XstackWarning)] == ["errors"]
    # its own kind: xstack reproduce silences the repeat of its Fig. 1 subsets by it
    assert [w.category for w in rec if isinstance(w.message, XstackWarning)] == [WeightsWarning]
    assert main(["uvstack", str(store), str(cat), str(tmp_path / "o.zarr"), "--weighting",
                 "none", "--primary-beam", "none", "-q"]) == 0
    err = capsys.readouterr().err.splitlines()
    lines = [ln for ln in err if "mis-scaled" in ln]
    assert len(lines) == 1 and lines[0].startswith("warning: ")
    assert "with --errors weights (flux_err_jy) or --errors empirical" in lines[0]
    assert "UserWarning" not in "\n".join(err) and ".py:" not in "\n".join(err)


def test_cli_error_names_the_flag(store, tmp_path, capsys):
    out = tmp_path / "exists.zarr"
    out.mkdir()
    assert main(["uvstack", str(store), str(tmp_path / "none.csv"), str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {out} exists (pass --overwrite to replace it)"]


# --- a bad command line: one line, no usage block ------------------------------------------

@pytest.mark.parametrize("argv, words", [
    (["uvstack", "a", "b", "c", "--bogus"], ["unrecognized arguments: --bogus"]),
    (["uvstack", "a", "b", "c", "--weighting", "optimal"], ["--weighting", "invalid choice"]),
    (["image", "a", "b", "--size", "64", "--cell", "1parsec"], ["--cell", "parsec"]),
    (["noise", "a", "b", "--realizations", "many"], ["--realizations", "invalid int"]),
    (["fit"], ["required"]),
])
def test_bad_command_line_is_one_error_line(argv, words, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith(f"error: {argv[0]}: ")
    assert "usage" not in captured.err
    for word in words:
        assert word in lines[0]


def test_unknown_command_is_one_line(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["stack-it"])
    assert exc.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: xstack: ")


def test_help_still_shows_usage(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["uvstack", "--help"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.startswith("usage: xstack uvstack")


def test_warnings_filter_sees_xstack_warning_as_user_warning():
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        warnings.warn(XstackWarning("x", option="errors"), stacklevel=1)
    assert issubclass(rec[0].category, UserWarning) and rec[0].message.option == "errors"
