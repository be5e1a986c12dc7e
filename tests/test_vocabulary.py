"""One home for shared vocabulary (issue 11, item 9): dish diameters from the data, the
primary-beam cutoff, the speed of light, the CLI's choices, and ``xstack.__all__``."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest
from _uvstack_helpers import make_stack_partition

import xstack
from xstack import _vocabulary
from xstack.beams import DEFAULT_PB_CUTOFF, dish_diameter, standard_beam
from xstack.errors import SchemaError

PACKAGE = Path(xstack.__file__).parent
SOURCES = sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def _code_lines(path: Path) -> list[tuple[int, str]]:
    """(line number, code) of a module with docstrings and comments left out."""
    text = path.read_text(encoding="utf-8")
    doc_lines: set[int] = set()
    for node in ast.walk(ast.parse(text)):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) \
                and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
            doc_lines.update(range(body[0].lineno, body[0].end_lineno + 1))
    return [(i, line.split("#")[0]) for i, line in enumerate(text.splitlines(), 1)
            if i not in doc_lines]


def _hits(pattern: str, allowed: set[str]) -> list[str]:
    rx = re.compile(pattern)
    out = []
    for path in SOURCES:
        rel = path.relative_to(PACKAGE).as_posix()
        if rel in allowed:
            continue
        out += [f"{rel}:{i}: {code.strip()}" for i, code in _code_lines(path) if rx.search(code)]
    return out


def test_speed_of_light_has_one_home():
    assert _hits(r"299_?792_?458|2\.99792458e8", {"coords.py"}) == []


def test_no_dish_diameter_fallback_outside_beams():
    # no "else 25.0" guesses, no reading DISH_DIAMETER by hand where a beam is made
    assert _hits(r"else 25\.0|dish_diameter: float = 25", set()) == []
    assert _hits(r"median\(.*DISH_DIAMETER", {"beams.py"}) == []


def test_pb_cutoff_default_has_one_home():
    found = _hits(r"cutoff\w*\s*(:\s*float\s*)?=\s*0\.1\b|--pb-cutoff.*default=0\.1", {"_vocabulary.py"})
    assert found == []
    assert DEFAULT_PB_CUTOFF is _vocabulary.DEFAULT_PB_CUTOFF
    import inspect

    from xstack.noise.estimate import estimate_noise
    from xstack.sim.scene import Effects
    from xstack.uvstack.stack import stack_uv

    for func in (stack_uv, estimate_noise):
        assert inspect.signature(func).parameters["pb_cutoff"].default == DEFAULT_PB_CUTOFF
    assert Effects().pb_cutoff == DEFAULT_PB_CUTOFF


def _choice_actions():
    from xstack.cli import build_parser

    top = build_parser()
    sub = next(a for a in top._actions if a.choices and isinstance(a.choices, dict))
    for name, parser in sub.choices.items():
        for action in parser._actions:
            if action.option_strings and action.choices is not None:
                yield name, action


def test_cli_choices_are_the_library_tuples():
    homes = [v for k, v in vars(_vocabulary).items() if isinstance(v, tuple) and k.isupper()]
    retyped = []
    for name, action in _choice_actions():
        if tuple(action.choices) == ("yes", "no"):  # a plain switch spelled out
            continue
        if not any(action.choices is home for home in homes):
            retyped.append(f"xstack {name} {action.option_strings[-1]}: {action.choices}")
    assert retyped == []


def test_cli_pb_cutoff_defaults_are_the_library_default():
    from xstack.cli import build_parser

    top = build_parser()
    for command in ("uvstack", "noise"):
        args = top.parse_args([command, "a", "b", "c"][: 4 if command == "uvstack" else 3])
        assert args.pb_cutoff == DEFAULT_PB_CUTOFF


def test_stage_constants_are_the_vocabulary():
    from xstack.imaging import image
    from xstack.imstack import stack as imstack
    from xstack.noise import estimate
    from xstack.uvstack import smearing
    from xstack.uvstack import stack as uvstack

    assert uvstack.WEIGHTINGS is _vocabulary.UVSTACK_WEIGHTINGS
    assert uvstack.ENGINES is _vocabulary.UVSTACK_ENGINES
    assert smearing.MODES is _vocabulary.SMEARING_MODES
    assert imstack.METHODS is _vocabulary.IMSTACK_METHODS
    assert imstack.WEIGHTINGS is _vocabulary.IMSTACK_WEIGHTINGS
    assert estimate.METHODS is _vocabulary.NOISE_METHODS
    assert image.WEIGHTINGS is _vocabulary.IMAGE_WEIGHTINGS


# --- dish diameters from the data ---------------------------------------------------------

def test_dish_diameter_is_read_from_the_data():
    ds = make_stack_partition(n_ant=4, n_time=2, n_chan=1, telescope="VLA", dish=13.5)
    assert dish_diameter(ds) == 13.5  # the data's, not the telescope's 25 m


def test_dish_diameter_without_data_comes_from_the_telescope_or_is_an_error():
    ds = make_stack_partition(n_ant=4, n_time=2, n_chan=1, telescope="ALMA", dish=12.0)
    bare = ds.drop_vars("DISH_DIAMETER")
    assert dish_diameter(bare) == 12.0  # ALMA's antennas are 12 m (not a 25 m guess)
    zero = ds.assign(DISH_DIAMETER=ds["DISH_DIAMETER"] * 0)
    assert dish_diameter(zero) == 12.0
    unknown = bare.assign_attrs(telescope_name="MYDISH")
    with pytest.raises(SchemaError, match="MYDISH"):
        dish_diameter(unknown)


def test_beams_of_the_stages_follow_the_data_dish():
    """An ALMA partition without DISH_DIAMETER: the uv-stack beam is ALMA's (12 m dish, the
    10.7 m + blockage model), not a 25 m dish's; and an unknown telescope is an error."""
    from xstack.uvstack.stack import _beam_for

    ds = make_stack_partition(n_ant=4, n_time=2, n_chan=1, telescope="ALMA", dish=12.0)
    bare = ds.drop_vars("DISH_DIAMETER")
    theta = np.radians(np.array([5.0, 15.0, 25.0]) / 3600)
    freq = np.array([100e9])
    want = standard_beam("ALMA", 12.0).main_lobe(theta[:, None], freq[None, :])
    got = _beam_for("auto", bare, DEFAULT_PB_CUTOFF)(theta, None, None, freq)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    with pytest.raises(SchemaError):
        _beam_for("auto", bare.assign_attrs(telescope_name="MYDISH"), DEFAULT_PB_CUTOFF)


def test_standard_beam_without_a_dish_uses_the_telescope():
    assert standard_beam("VLA").model == "vla"
    assert standard_beam("ALMA").dish_diameter == 10.7  # ALMA's effective aperture
    with pytest.raises(SchemaError):
        standard_beam("MYDISH")


# --- the public API -----------------------------------------------------------------------

def test_every_public_name_resolves():
    missing = [name for name in xstack.__all__ if getattr(xstack, name, None) is None]
    assert missing == []


def test_no_subpackage_shares_a_public_function_name():
    """``xstack.uvstack`` is the sub-package, plainly a module, never swapped for a callable;
    the functions are ``xstack.stack_uv`` / ``xstack.stack_images``."""
    import importlib
    import types

    import xstack

    for sub in ("io", "sim", "uvstack", "imaging", "imstack", "fit", "noise", "cli"):
        module = importlib.import_module(f"xstack.{sub}")
        assert type(module) is types.ModuleType, sub
        assert sub not in xstack.__all__, sub
        assert getattr(xstack, sub) is module
    # no public name is also a module: importing it would replace the function on the package
    import importlib.util

    for name in xstack.__all__:
        assert importlib.util.find_spec(f"xstack.{name}") is None, name
    assert callable(xstack.stack_uv) and xstack.stack_uv.__module__ == "xstack.uvstack.stack"
    assert xstack.stack_images.__module__ == "xstack.imstack.stack"
