"""Compiled kernels are never cached inside the installed package (issue 11, item 1).

numba's default writes ``__pycache__/*.nbi`` beside the modules; after ``xstack demo`` from a
``pip install .`` those files outlived ``pip install -e '.[test]'`` and the leftover directory
shadowed the editable install (every command: ImportError). Run in a fresh interpreter, so
that the configuration is the one a user's first ``import xstack`` makes.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import xstack

PACKAGE = Path(xstack.__file__).parent

_SNIPPET = """
import numpy as np
import xstack
from xstack.uvstack.kernels import stack_sums
stack_sums(np.ones((3, 2, 2), complex), np.ones((3, 2, 2)), np.zeros((3, 2, 2), bool), None)
print(xstack.numba_cache_dir())
"""


def _index_files() -> set[Path]:
    return set(PACKAGE.rglob("*.nbi")) | set(PACKAGE.rglob("*.nbc"))


def _run(env_extra: dict[str, str]) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XSTACK_CACHE_DIR")}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", _SNIPPET], env=env, capture_output=True,
                         text=True, timeout=300, check=True)
    return out.stdout.strip().splitlines()[-1]


def test_kernel_cache_goes_to_the_user_cache_directory(tmp_path):
    before = _index_files()
    where = _run({"XDG_CACHE_HOME": str(tmp_path)})
    assert Path(where) == tmp_path / "xstack" / "numba"
    assert list((tmp_path / "xstack" / "numba").rglob("*.nbi")), "nothing was cached"
    assert _index_files() <= before, "numba wrote its cache inside the installed package"


def test_cache_directory_can_be_chosen(tmp_path):
    where = _run({"XSTACK_CACHE_DIR": str(tmp_path / "mine")})
    assert Path(where) == tmp_path / "mine" / "numba"
    assert list((tmp_path / "mine" / "numba").rglob("*.nbi"))
    where = _run({"NUMBA_CACHE_DIR": str(tmp_path / "numba-own")})
    assert Path(where) == tmp_path / "numba-own"
