"""``docs/cli.md`` is generated from the argument parsers and cannot drift from them."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from xstack.cli import COMMANDS, build_parser
from xstack.cli.docs import default_path, render

DOC = Path(__file__).resolve().parents[1] / "docs" / "cli.md"


def test_committed_page_is_the_generated_one():
    assert default_path() == DOC
    assert DOC.read_text(encoding="utf-8") == render(), (
        "docs/cli.md is out of date: run `python -m xstack.cli.docs`")


def test_page_lists_every_command_and_option():
    """Independent of the renderer: every sub-command and every option string of the parsers
    appears in the page."""
    text = DOC.read_text(encoding="utf-8")
    top = build_parser()
    (sub,) = [a for a in top._actions if isinstance(a, argparse._SubParsersAction)]
    assert set(sub.choices) <= set(COMMANDS)
    for name, parser in sub.choices.items():
        section = text.split(f"\n## xstack {name}\n", 1)[1].split("\n## xstack ", 1)[0]
        for action in parser._actions:
            for flag in action.option_strings:
                if flag not in ("-h", "--help"):
                    assert f"`{flag}`" in section, (name, flag)


def test_check_mode(tmp_path):
    stale = tmp_path / "cli.md"
    stale.write_text("# old\n")
    run = [sys.executable, "-m", "xstack.cli.docs"]
    assert subprocess.run([*run, str(stale), "--check"], capture_output=True).returncode == 1
    assert subprocess.run([*run, str(stale)], capture_output=True).returncode == 0
    assert stale.read_text(encoding="utf-8") == DOC.read_text(encoding="utf-8")
    assert subprocess.run([*run, str(stale), "--check"], capture_output=True).returncode == 0
