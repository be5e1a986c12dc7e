"""The real MeasurementSets shipped in the pyuvdata wheel, located without importing pyuvdata."""

from __future__ import annotations

import importlib.util
import os
import shutil
import tarfile
from pathlib import Path

#: name -> (file in pyuvdata/data, MS directory it holds or unpacks to)
REAL_MS = {
    "evla": ("day2_TDEM0003_10s_norx_1src_1spw.ms", "day2_TDEM0003_10s_norx_1src_1spw.ms"),
    "alma": ("X5707_1spw_1scan_10chan_1time_1bl_noatm.ms.tar.gz",
             "X5707_1spw_1scan_10chan_1time_1bl_noatm.ms"),
    "ovro-lwa": ("2018-03-21-01_26_33_0004384620257280_000000_downselected.ms",
                 "2018-03-21-01_26_33_0004384620257280_000000_downselected.ms"),
    "mwa": ("1090008640_birli_pyuvdata.ms", "1090008640_birli_pyuvdata.ms"),
    "mwa-small": ("1102865728_small.ms", "1102865728_small.ms"),
    "hera": ("zen.2456865.60537.xy.uvcRREAAM.ms", "zen.2456865.60537.xy.uvcRREAAM.ms"),
}


class RealDataUnavailable(RuntimeError):
    """pyuvdata (the test extra that ships the real MSs) is not installed."""


def pyuvdata_data_dir() -> Path:
    """The ``data`` directory of the installed pyuvdata package (found, not imported).

    Raises
    ------
    RealDataUnavailable
        If pyuvdata is not installed.
    """
    spec = importlib.util.find_spec("pyuvdata")  # locating a top-level package runs no code
    if spec is None or not spec.submodule_search_locations:
        raise RealDataUnavailable("pyuvdata is not installed (pip install -e '.[test]')")
    for loc in spec.submodule_search_locations:
        data = Path(loc) / "data"
        if data.is_dir():
            return data
    raise RealDataUnavailable("pyuvdata has no data directory")


def real_ms(name: str, dest_dir: str | os.PathLike) -> Path:
    """Copy a real MS shipped with pyuvdata into ``dest_dir``; return the MS path.

    Parameters
    ----------
    name
        ``"evla"`` (day2_TDEM0003_10s_norx_1src_1spw.ms: EVLA, 64 channels, RR/RL/LR/LL,
        missing baselines, jittered time stamps) or ``"alma"``
        (X5707_1spw_1scan_10chan_1time_1bl_noatm.ms: ALMA, three fields in the FIELD table,
        one baseline, 10 channels) or ``"ovro-lwa"`` (OVRO-LWA, one integration, 109
        channels, XX/YY/XY/YX, 210 rows of which 20 are autocorrelations), ``"mwa"``
        (1090008640_birli_pyuvdata.ms), ``"mwa-small"`` (1102865728_small.ms) or ``"hera"``
        (zen.2456865.60537.xy.uvcRREAAM.ms, XY only).
    dest_dir
        Existing directory to copy (or unpack) into; the original is never opened.

    Raises
    ------
    RealDataUnavailable
        If pyuvdata is not installed (use :func:`require_real_ms` in tests to skip).
    """
    key = name.lower()
    if key not in REAL_MS:
        raise ValueError(f"unknown real MS {name!r}; choose from {sorted(REAL_MS)}")
    src_name, ms_name = REAL_MS[key]
    src = pyuvdata_data_dir() / src_name
    if not src.exists():
        raise RealDataUnavailable(f"{src} is missing from the pyuvdata installation")
    dest_dir = Path(dest_dir)
    dest_dir.mkdir(parents=True, exist_ok=True)
    out = dest_dir / ms_name
    if out.exists():
        return out
    if src.is_dir():
        shutil.copytree(src, out)
    else:
        with tarfile.open(src, "r:gz") as tar:
            members = [m for m in tar.getmembers() if m.name.split("/")[0] == ms_name]
            tar.extractall(dest_dir, members=members, filter="data")
    if not out.is_dir():
        raise RealDataUnavailable(f"{src} did not contain {ms_name}")
    return out


def require_real_ms(name: str, dest_dir: str | os.PathLike) -> Path:
    """Like :func:`real_ms`, but skip the calling pytest test if pyuvdata is not installed."""
    try:
        return real_ms(name, dest_dir)
    except RealDataUnavailable as exc:
        import pytest

        pytest.skip(str(exc))
        raise  # pragma: no cover  (pytest.skip raises)
