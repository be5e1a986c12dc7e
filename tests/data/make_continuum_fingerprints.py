"""Write ``continuum_fingerprints.json`` for ``tests/test_sim_lines.py``.

Run from a checkout of the simulator whose data are the reference (the references held were
made at git 28699e2, before line sources; HEAD then gave the same sha256 of every array on
the same machine)::

    python tests/data/make_continuum_fingerprints.py tests/data/continuum_fingerprints.json
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from test_sim_lines import CONTINUUM_PRESETS, _arrays, _fingerprint, _unflagged  # noqa: E402

from xstack.sim.presets import preset_scene  # noqa: E402
from xstack.sim.simulate import simulate  # noqa: E402


def main(path: str) -> None:
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, scale in CONTINUUM_PRESETS:
            res = simulate(_unflagged(preset_scene(name)), Path(tmp) / f"{name}.zarr", seed=3, scale=scale)
            out[f"{name}@{scale}"] = _fingerprint(_arrays(res.store, res.catalog_paths))
    Path(path).write_text(json.dumps(out, indent=1, sort_keys=True))


if __name__ == "__main__":
    main(sys.argv[1])
