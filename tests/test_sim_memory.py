"""Peak memory of the simulator does not grow with the length of the observation (slow)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

_CHILD = """
import json, resource, sys
import dask.array, xarray, zarr
from xstack.sim.simulate import simulate
n_int = int(sys.argv[2])
scene = {
    "name": "memory", "time_chunk": 16,
    "array": {"config": "vla.a"},
    "observation": {"date": "2014-01-01", "hour_angle": [-6, 6], "integration": 10.0,
                    "time_per_pointing": 10.0 * n_int},
    "spectral": {"center": 1.4e9, "bandwidth": 64e6, "channels": 32,
                 "polarizations": ["RR", "LL"]},
    "pointings": {"mode": "single"},
    "effects": {"primary_beam": "auto", "w_term": True, "noise": {"sigma": 0.01}},
    "populations": [{"name": "t", "count": 50, "flux": {"kind": "fixed", "value": "1mJy"},
                     "positions": {"kind": "box", "size_arcsec": [600, 600]}}],
}
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
res = simulate(scene, sys.argv[1], seed=1)
print(json.dumps({"base_mb": base / 1024, "n_vis": res.n_visibilities,
                  "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def _run(out, n_int):
    res = subprocess.run([sys.executable, "-c", _CHILD, str(out), str(n_int)],
                         capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_peak_memory_independent_of_observation_length(tmp_path):
    # 351 baselines x 32 channels x 2 hands, chunks of 16 integrations (~2.9 MB complex64):
    # 200 integrations hold ~36 MB of visibilities, 1600 hold ~288 MB
    small = _run(tmp_path / "s.zarr", 200)
    large = _run(tmp_path / "l.zarr", 1600)
    assert large["n_vis"] == 8 * small["n_vis"]
    grow_small = small["peak_mb"] - small["base_mb"]
    grow_large = large["peak_mb"] - large["base_mb"]
    # eight times the data, (nearly) the same extra memory: bounded by a few chunks
    assert grow_large < grow_small + 40, (small, large)
    assert grow_large < 0.5 * large["n_vis"] * 8 / 2**20, (small, large)  # half the data set
