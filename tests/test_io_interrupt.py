"""A conversion killed mid-way leaves no store that opens as valid."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from xstack.errors import SchemaError, XstackError
from xstack.io.convert import convert_ms
from xstack.schema import open_store, validate_store
from xstack.testing import make_test_ms


def _chunk_files(partial_dirs):
    n = 0
    for d in partial_dirs:
        for _, _, files in os.walk(d):
            n += sum(1 for f in files if f != "zarr.json")
    return n


def test_killed_conversion_leaves_no_valid_store(tmp_path):
    ms = make_test_ms(tmp_path / "big.ms", n_antennas=16, n_times=300, n_channels=32, seed=5)
    out = tmp_path / "out.zarr"
    code = ("import sys; from xstack.io.convert import convert_ms; "
            "convert_ms(sys.argv[1], sys.argv[2], chunks={'time': 1})")
    proc = subprocess.Popen([sys.executable, "-c", code, str(ms), str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    partial = []
    try:
        # wait until the child is writing array chunks into its temporary store
        while time.monotonic() < deadline:
            partial = [p for p in tmp_path.iterdir() if p.name.startswith(".out.zarr.partial-")]
            if partial and _chunk_files(partial) > 20:
                break
            assert proc.poll() is None, f"conversion ended before it could be killed: {proc.stderr.read()}"
            time.sleep(0.02)
        assert proc.poll() is None, "conversion finished too early to test an interruption"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists()
    assert partial, "the child never wrote anything"
    for p in partial:
        assert p.exists()  # SIGKILL leaves the hidden temporary behind ...
        with pytest.raises(SchemaError, match="incomplete store"):
            validate_store(p)  # ... but it never validates
        with pytest.raises(XstackError):
            open_store(p)
    # the leftover does not block a new conversion of the same output
    convert_ms(ms, out)
    assert validate_store(out)["xstack_complete"] is True
