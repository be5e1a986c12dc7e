"""The scripts in examples/ run and recover what they claim."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_uvstack_example_recovers_injected_flux(tmp_path, capsys):
    out = _load("uvstack_simulated").main(tmp_path)
    # 200 targets of 20 uJy in noise: the stack must find them within 3 sigma
    assert abs(out["flux"] - out["injected"]) < 3 * out["flux_err"]
    assert out["flux"] / out["flux_err"] > 10
    assert "uv-stacked flux" in capsys.readouterr().out


def test_image_stacking_example(tmp_path):
    out = _load("image_stacking").main(tmp_path)
    assert set(out) == {"mean-nearest", "mean-fourier", "median-nearest"}
    # every aggregation finds the 20 uJy targets (noise of the stack ~1.2-1.5 uJy)
    assert all(15e-6 < v < 25e-6 for v in out.values()), out
    assert (tmp_path / "stack-mean-fourier.fits").exists()


@pytest.mark.realdata
def test_real_vla_example(tmp_path):
    pytest.importorskip("casacore.tables")
    from xstack.testing import RealDataUnavailable

    try:
        out = _load("real_vla_ms").main(tmp_path)
    except RealDataUnavailable:
        pytest.skip("pyuvdata (test extra) not installed")
    from casacore.tables import table

    # the image's reference pixel is the phase center the MS's FIELD table gives
    with table(str(tmp_path / "day2_TDEM0003_10s_norx_1src_1spw.ms" / "FIELD"), ack=False) as field:
        ra, dec = np.degrees(field.getcol("PHASE_DIR")[0, 0])
    assert np.allclose(out["crval"], [ra % 360.0, dec], atol=1e-9)
    assert (tmp_path / "evla_roundtrip.ms").is_dir()
