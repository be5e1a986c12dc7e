"""Test helpers: a generator of realistic MeasurementSets and the real MSs shipped by pyuvdata.

``make_test_ms(path, ...)`` writes a small MS with python-casacore (several fields, spectral
windows, scans, flags, WEIGHT_SPECTRUM present or absent, missing baselines).
``real_ms(name, dest_dir)`` copies one of the real observations shipped in the
``pyuvdata==3.2.3`` wheel (an optional test dependency; pyuvdata itself is never imported)
to ``dest_dir`` and returns its path.
"""

from __future__ import annotations

from xstack.testing._ms import DEFAULT_PHASE_CENTER, make_test_ms, uvw_from_itrf
from xstack.testing._real import REAL_MS, RealDataUnavailable, pyuvdata_data_dir, real_ms, require_real_ms

__all__ = ["DEFAULT_PHASE_CENTER", "REAL_MS", "RealDataUnavailable", "make_test_ms",
           "pyuvdata_data_dir", "real_ms", "require_real_ms", "uvw_from_itrf"]
