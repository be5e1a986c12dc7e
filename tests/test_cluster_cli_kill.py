"""The command line survives a killed worker (issue 14): ``xstack uvstack ... --scheduler ADDR``
run as its own process on a 2-worker ``LocalCluster``; one worker is SIGKILLed while it
processes the stack's tasks. Truth: the same command on dask's threaded scheduler (uv-stacking
is bitwise on any thread count), its JSON and its store.

No configuration is needed: distributed reruns the tasks of a lost worker (a task is given
up only after ``distributed.scheduler.allowed-failures``, default 3, workers died running it)
and the nanny restarts the worker.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from _uvstack_helpers import VLA_CENTER, make_stack_partition
from astropy.table import Table

from xstack.coords import lm_to_radec
from xstack.schema import open_store, write_store

distributed = pytest.importorskip("distributed")
from _cluster_helpers import TaskCounter  # noqa: E402

pytestmark = pytest.mark.slow


def _cli(store, cat, out, *extra) -> tuple[subprocess.CompletedProcess, dict]:
    """``xstack uvstack`` in a new process; its JSON without the timing fields."""
    proc = subprocess.run([sys.executable, "-m", "xstack", "uvstack", str(store), str(cat),
                           str(out), "--json", "--no-progress", "-q", *extra],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    for key in ("seconds", "elapsed_s", "output", "out", "profile_png"):
        doc.pop(key, None)
    return proc, doc


def _arrays(tree) -> dict[str, bytes]:
    return {f"{name}/{var}": np.ascontiguousarray(tree[name][var].values).tobytes()
            for name in tree.children for var in tree[name].to_dataset().variables}


def test_cli_survives_a_killed_worker(tmp_path):
    ds = make_stack_partition(n_time=96, n_ant=10, n_chan=8, sigma=0.01, seed=5,
                              sources=[(*lm_to_radec(2e-3, -1e-3, *VLA_CENTER), 0.05)])
    store = tmp_path / "data.zarr"
    write_store({"p": ds.chunk({"time": 1})}, store)  # 96 chunks: time to kill mid-stack
    rng = np.random.default_rng(3)
    ra, dec = lm_to_radec(rng.uniform(-3e-3, 3e-3, 40), rng.uniform(-3e-3, 3e-3, 40),
                          *VLA_CENTER)
    cat = tmp_path / "cat.csv"
    cat.write_text("ra,dec\n" + "".join(f"{float(np.degrees(a))!r},{float(np.degrees(d))!r}\n"
                                        for a, d in zip(ra, dec)))
    _, ref = _cli(store, cat, tmp_path / "ref.zarr")

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None, silence_logs=logging.ERROR) as lc:
        counter = TaskCounter()
        lc.scheduler.add_plugin(counter)
        with distributed.Client(lc, set_as_default=False) as client:
            pids = client.run(os.getpid)  # worker address -> pid
        killed: list[tuple[str, int]] = []
        stop = threading.Event()

        def kill_one() -> None:
            # once the stack is under way, the first worker seen processing one of its tasks
            while not stop.is_set():
                if counter.finished >= 20:
                    for addr, ws in list(lc.scheduler.workers.items()):
                        if ws.processing and addr in pids:
                            os.kill(pids[addr], signal.SIGKILL)
                            killed.append((addr, counter.finished))
                            return
                time.sleep(0.005)

        killer = threading.Thread(target=kill_one, daemon=True)
        killer.start()
        try:
            _, got = _cli(store, cat, tmp_path / "got.zarr", "--scheduler",
                          lc.scheduler_address)
        finally:
            stop.set()
            killer.join(5)
    assert killed, "no worker was killed"
    assert counter.finished > killed[0][1] + 10  # the stack went on after the kill
    got_profile, ref_profile = Table.read(got.pop("profile_table")), \
        Table.read(ref.pop("profile_table"))
    assert got == ref  # every number of the JSON, to the bit
    assert got_profile.colnames == ref_profile.colnames and len(got_profile) > 0
    for name in ref_profile.colnames:  # the uv-profile written beside the store, too
        np.testing.assert_array_equal(got_profile[name], ref_profile[name])
    a, b = open_store(tmp_path / "got.zarr"), open_store(tmp_path / "ref.zarr")
    assert a.attrs["xstack_complete"] is True
    assert a.attrs["uvstack"] == b.attrs["uvstack"]
    assert _arrays(a) == _arrays(b)
