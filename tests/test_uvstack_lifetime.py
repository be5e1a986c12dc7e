"""A stack never outlives its data (issue 10, item 7).

``stack_uv(MS path)`` converts into a temporary directory. The stacked datasets are lazy: they
read that directory when computed. Keeping ``res.stacked[name]`` and dropping ``res`` used to
free the directory and the stack read NaN visibilities and False flags without an error.
Truth: the same stack computed while the result was alive, and a python-casacore read of the
MS for the unflagged data.
"""

from __future__ import annotations

import gc
import tempfile
from pathlib import Path

import numpy as np
from astropy.table import Table

import xstack
from xstack.testing import require_real_ms


def _temporary_stores() -> set[str]:
    return {str(p) for p in Path(tempfile.gettempdir()).glob("xstack-uvstack-*")}


def test_stacked_data_outlive_the_result(tmp_path):
    from casacore.tables import table

    ms = require_real_ms("evla", tmp_path)
    with table(str(ms) + "/FIELD", ack=False, readonly=True) as f:
        ra, dec = np.degrees(f.getcol("PHASE_DIR")[0, 0])
    cat = Table({"ra": [ra + 0.001], "dec": [dec]})
    before = _temporary_stores()
    res = xstack.stack_uv(ms, cat, weighting="none")
    name = next(iter(res.stacked))
    ds = res.stacked[name]
    tmpdirs = _temporary_stores() - before
    assert tmpdirs, "stack_uv(MS) should convert into a temporary directory"
    expected = ds["VISIBILITY"].values.copy()
    expected_flag = ds["FLAG"].values.copy()
    assert np.isfinite(expected[~expected_flag]).all() and (~expected_flag).any()
    del res
    gc.collect()
    got = ds["VISIBILITY"].values
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(ds["FLAG"].values, expected_flag)
    assert np.isfinite(ds["WEIGHT"].values[~expected_flag]).all()
    # the number of unflagged cells agrees with the MS itself
    with table(str(ms), ack=False, readonly=True) as t:
        n_good = int((~(t.getcol("FLAG") | t.getcol("FLAG_ROW")[:, None, None])).sum())
    assert int((~expected_flag).sum()) == n_good
    # and the temporary directory goes when the last lazy object does
    del ds
    gc.collect()
    assert not (_temporary_stores() & tmpdirs)
