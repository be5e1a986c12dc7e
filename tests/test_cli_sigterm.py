"""SIGTERM (``kill``, a batch scheduler's time limit) unwinds a run as Ctrl-C does.

Each test starts the real program in a subprocess with one step replaced by a stall that
prints READY, sends SIGTERM while the run has its temporaries on disk, and checks the exit
status, the one-line error, and that nothing of the run is left: no output, no hidden
``.NAME.partial-*`` store, no work directory. Without the handler SIGTERM ends the process
at once (status -15) and the temporaries stay.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from _sim_helpers import TINY_SCENE

from xstack.cli import Terminated, main, sigterm_unwinds

_STALL = """
import sys, time

def stall(*args, **kwargs):
    print("READY", flush=True)
    time.sleep(600)

{patch}
from xstack.cli import main
sys.argv = ["xstack", *sys.argv[1:]]
sys.exit(main())
"""


def _terminate(patch: str, args: list[str], cwd: Path) -> tuple[int, str]:
    """Run xstack ``args`` with ``patch`` applied, SIGTERM it at READY; (status, stderr)."""
    script = _STALL.format(patch=textwrap.dedent(patch))
    proc = subprocess.Popen([sys.executable, "-c", script, *args], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)

    def at_the_stall() -> None:
        if proc.stdout.readline().strip() != "READY":
            proc.kill()
            pytest.fail(f"the run did not reach the stall: {proc.communicate()[1]}")

    return _sigterm_when(proc, at_the_stall)


def _sigterm_when(proc: subprocess.Popen, ready) -> tuple[int, str]:
    """SIGTERM ``proc`` once ``ready()`` returns; its (exit status, stderr)."""
    try:
        ready()
        os.kill(proc.pid, signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err


def _scene(tmp_path: Path) -> Path:
    scene = tmp_path / "scene.toml"
    scene.write_text(TINY_SCENE)
    return scene


#: A VLA A scene of 6 h in 10 s integrations and 16 channels: long enough to write that a
#: SIGTERM lands while dask's threads write its chunks.
_LONG_SCENE = """
        name = "sigterm"
        [array]
        config = "vla.a"
        [observation]
        date = "2014-01-01"
        hour_angle = [-3.0, 3.0]
        integration = 10.0
        time_per_pointing = 21600.0
        [spectral]
        center = 1.4e9
        bandwidth = 64e6
        channels = 16
        polarizations = ["RR", "LL"]
        [pointings]
        mode = "single"
        [effects]
        noise = { sigma = 0.01 }
        [[populations]]
        name = "targets"
        count = 5
        flux = { kind = "fixed", value = "100uJy" }
        positions = { kind = "box", size_arcsec = [60, 60] }
    """


def test_sigterm_during_simulate_leaves_nothing(tmp_path):
    """SIGTERM while the store is written (every chunk, not yet its completion flag): exit
    status 143, one line ``error: terminated (SIGTERM)``, and neither the store nor its
    hidden temporary is left."""
    scene = _scene(tmp_path)
    status, err = _terminate("import xstack.schema as schema\nschema.finish_store = stall\n",
                             ["simulate", str(scene), "out.zarr"], tmp_path)
    assert status == 143, err
    assert err.strip().splitlines()[-1] == "error: terminated (SIGTERM)"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml"]


def test_sigterm_during_reproduce_removes_the_work_directory(tmp_path):
    """A reproduce run terminated in a realisation (at its CLEAN) removes that realisation's
    work directory (its simulated store) and writes no line for it; the type's directory
    holds nothing a resumed run would mistake for a result."""
    status, err = _terminate(
        "import xstack.imaging.clean as clean\nclean.clean_data = stall\n",
        ["reproduce", "--type", "1", "--realizations", "1", "--scale", "0.05",
         "--outdir", "repro", "--no-progress"], tmp_path)
    assert status == 143, err
    assert err.strip().splitlines()[-1] == "error: terminated (SIGTERM)"
    left = sorted(p.name for p in (tmp_path / "repro" / "type1").iterdir())
    assert not [name for name in left if name.startswith("seed")], left
    lines = tmp_path / "repro" / "type1" / "realizations.jsonl"
    assert not lines.exists() or lines.read_text() == ""


def test_main_called_in_process_keeps_the_callers_handler(tmp_path):
    """A Python caller of ``main(argv)`` owns its process's signals: main leaves SIGTERM's
    handler as it found it (only the program installs its own)."""
    def mine(signum, frame):  # pragma: no cover - never delivered
        pass

    previous = signal.signal(signal.SIGTERM, mine)
    try:
        assert main(["simulate", str(_scene(tmp_path)), str(tmp_path / "o.zarr"), "-q"]) == 0
        assert signal.getsignal(signal.SIGTERM) is mine
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_sigterm_unwinds_raises_in_the_main_thread_and_restores():
    """Inside the block a SIGTERM raises Terminated (a KeyboardInterrupt, so clean-up written
    for Ctrl-C runs); afterwards the previous handler is back."""
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated), sigterm_unwinds():
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # the handler runs between bytecodes
            pass
    assert issubclass(Terminated, KeyboardInterrupt)
    assert signal.getsignal(signal.SIGTERM) is before


_LATE_WRITER = """
import sys, time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from xstack._atomic import atomic_output

pool = ThreadPoolExecutor(1)  # like dask's: joined when the interpreter exits

def late(tmp):
    time.sleep(1.0)  # still running when the interrupt unwinds the write
    tmp.mkdir(exist_ok=True)
    (tmp / "late.json").write_text("{}")

try:
    with atomic_output(Path(sys.argv[1]) / "out.zarr") as tmp:
        tmp.mkdir()
        pool.submit(late, tmp)
        raise KeyboardInterrupt
except KeyboardInterrupt:
    print("unwound", flush=True)
"""


def test_a_write_still_running_after_the_interrupt_leaves_nothing(tmp_path):
    """Ctrl-C or SIGTERM unwinds the main thread while a worker thread of the computation
    still has a task that writes into the temporary: it is removed once more after the
    threads are joined, at exit, so no hidden ``.out.zarr.partial-*`` outlives the process
    (the writer's late file proves the race happened)."""
    run = subprocess.run([sys.executable, "-c", _LATE_WRITER, str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "unwound", run.stderr
    assert list(tmp_path.iterdir()) == []


def test_sigterm_while_dask_writes_the_store(tmp_path):
    """The real thing: SIGTERM a simulation while dask's threads write its chunks (no
    stall); the store and its temporary are gone once the process has exited."""
    scene = tmp_path / "scene.toml"
    scene.write_text(textwrap.dedent(_LONG_SCENE))
    proc = subprocess.Popen([sys.executable, "-m", "xstack", "simulate", str(scene), "out.zarr"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    def chunks_on_disk() -> None:
        deadline = time.monotonic() + 120
        while not any(p.name.startswith(".out.zarr.partial-") and any(p.rglob("c/*"))
                      for p in tmp_path.iterdir()):
            assert proc.poll() is None, proc.communicate()[1]
            assert time.monotonic() < deadline, "no chunk was written in 120 s"
            time.sleep(0.05)

    status, err = _sigterm_when(proc, chunks_on_disk)
    assert status == 143, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml"]
