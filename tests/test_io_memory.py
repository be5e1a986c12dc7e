"""Peak memory of convert and export does not grow with the size of the data (slow)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from xstack.testing import make_test_ms

_CHILD = """
import json, resource, sys
import dask.array, xarray, zarr, casacore.tables
from xstack.io.convert import convert_ms
from xstack.io.export import export_ms
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
if sys.argv[1] == "convert":
    convert_ms(sys.argv[2], sys.argv[3], chunks={"time": 8})
else:
    export_ms(sys.argv[2], sys.argv[3])
print(json.dumps({"base_mb": base / 1024,
                  "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def _peak(*args):
    res = subprocess.run([sys.executable, "-c", _CHILD, *map(str, args)], capture_output=True,
                         text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.slow
def test_peak_memory_independent_of_ms_size(tmp_path):
    # 120 baselines x 64 channels x 4 correlations: ~0.5 MB of DATA per integration,
    # chunks of 8 integrations (~4 MB); MSs of ~40 and ~160 MB of visibilities
    sizes = {}
    for n_times in (80, 320):
        ms = make_test_ms(tmp_path / f"m{n_times}.ms", n_antennas=16, n_times=n_times, n_channels=64,
                          pols=("XX", "XY", "YX", "YY"), seed=n_times)
        store = tmp_path / f"m{n_times}.zarr"
        conv = _peak("convert", ms, store)
        exp = _peak("export", store, tmp_path / f"m{n_times}.out.ms")
        sizes[n_times] = (conv["peak_mb"] - conv["base_mb"], exp["peak_mb"] - exp["base_mb"])
    small, large = sizes[80], sizes[320]
    # four times the data, (nearly) the same extra memory: bounded by the chunk size
    assert large[0] < small[0] + 40, sizes
    assert large[1] < small[1] + 40, sizes
    assert large[0] < 100 and large[1] < 150, sizes  # far below the ~250 MB of the large MS
