"""``xstack demo``: the whole stacking chain on a small built-in scene, in a minute or two.

The demo runs the same sub-commands a user would type, prints each command line before it
runs, and ends with a table comparing the injected mean flux of the targets with what
uv-stacking and image-stacking recover:

1. ``simulate``  a VLA A-configuration scene: 3 bright 5 mJy sources + 60 faint targets
2. ``export`` / ``convert``  round trip through a MeasurementSet
3. ``image``     dirty image and CLEAN of the bright sources
4. ``subtract``  the CLEAN model, leaving the residual data set (paper §3.1)
5. ``uvstack``   the residual at the target positions (paper eq. 4), with a uv-profile
6. ``image`` + ``imstack``  the residual image, stamps stacked (paper §3.2)
7. ``fit`` and ``noise``  flux by model fitting; Monte Carlo noise and bias
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from xstack.errors import OutputExistsError, XstackError

#: The demo scene: small enough to run in about a minute on a laptop, faint enough that the
#: targets are invisible one by one (~0.5 sigma each) yet clearly detected in the stack.
DEMO_SCENE: dict[str, Any] = {
    "name": "xstack-demo",
    "description": "VLA A, 1.4 GHz, 1 h: 3 bright sources and 60 faint targets in 4' x 4'",
    "array": {"config": "vla.a"},
    # a 1 h track: 1 h of hour angle is 3590 s of time, so +-0.51 h holds all 60 integrations
    # on one day (+-0.5 h would put the last one on the next day)
    "observation": {"date": "2014-01-01", "hour_angle": [-0.51, 0.51], "integration": 60.0,
                    "time_per_pointing": 3600.0},
    "spectral": {"center": 1.4e9, "bandwidth": 128e6, "channels": 4,
                 "polarizations": ["RR", "LL"]},
    "pointings": {"mode": "single"},
    "effects": {"primary_beam": "auto", "w_term": True, "noise": {"sigma": 0.01}},
    "populations": [
        {"name": "bright", "count": 3, "flux": {"kind": "fixed", "value": "5mJy"},
         "positions": {"kind": "box", "size_arcsec": [200, 200]}},
        {"name": "targets", "count": 60, "flux": {"kind": "fixed", "value": "15uJy"},
         "positions": {"kind": "box", "size_arcsec": [240, 240]}},
    ],
}

IMAGE_SIZE = 1024
CELL_ARCSEC = 0.3


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo", help="run the whole chain on a small built-in scene",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--outdir", default="xstack-demo",
                   help="directory for every output (default: ./xstack-demo)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --outdir")
    p.add_argument("--seed", type=int, default=1, help="random seed of the scene")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    return p


def _xstack(argv: list[str]) -> dict[str, Any]:
    """Run one xstack sub-command in-process; return its --json output."""
    from xstack.cli import main
    from xstack.cli._output import say

    say("$ xstack " + " ".join(argv))
    argv = [*argv, "--no-progress"]  # the demo prints its own step lines instead of bars
    buffer = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(buffer):
        status = main([*argv, "--json"] if "--json" not in argv else argv)
    if status != 0:
        raise XstackError(f"demo step 'xstack {argv[0]}' failed (exit status {status})")
    text = buffer.getvalue().strip()
    result = json.loads(text) if text else {}
    say(f"  ({time.perf_counter() - t0:.1f} s)")
    return result


def run(args: argparse.Namespace) -> int:
    from xstack.sim.scene import load_scene

    out = Path(args.outdir)
    if out.exists():
        if not args.overwrite:
            raise OutputExistsError(f"{out} exists (use --overwrite to replace it)")
        shutil.rmtree(out)
    out.mkdir(parents=True)
    from xstack.cli._output import say

    # step lines are messages (stderr), the summary is the result (stdout)
    t_start = time.perf_counter()

    scene_path = out / "scene.toml"
    scene_path.write_text(_to_toml(load_scene(DEMO_SCENE).to_dict()))
    d = {name: str(out / name) for name in (
        "sim.zarr", "sim.ms", "sim2.zarr", "image.fits", "residual.zarr", "stacked.zarr",
        "residual_image.fits", "imstack.fits")}

    say("# 1. simulate a VLA scene: bright sources + faint targets")
    _xstack(["simulate", str(scene_path), d["sim.zarr"], "--seed", str(args.seed)])
    bright = str(out / "sim.bright.ecsv")
    targets = str(out / "sim.targets.ecsv")

    say("# 2. round trip through a MeasurementSet")
    _xstack(["export", d["sim.zarr"], d["sim.ms"]])
    _xstack(["convert", d["sim.ms"], d["sim2.zarr"]])
    identical = _stores_identical(d["sim.zarr"], d["sim2.zarr"])
    say(f"  zarr -> MS -> zarr identical: {identical}")

    say("# 3. image and CLEAN the bright sources")
    img = _xstack(["image", d["sim.zarr"], d["image.fits"], "--size", str(IMAGE_SIZE),
                   "--cell", str(CELL_ARCSEC), "--niter", "500", "--threshold", "0.1mJy", "--png"])

    say("# 4. subtract the CLEAN model: the residual data set")
    model = img.get("files", {}).get("model") or str(out / "image.model.fits")
    _xstack(["subtract", d["sim.zarr"], model, d["residual.zarr"]])

    say("# 5. uv-stack the residual at the target positions")
    uv = _xstack(["uvstack", d["residual.zarr"], targets, d["stacked.zarr"]])

    say("# 6. image the residual and stack image stamps")
    _xstack(["image", d["residual.zarr"], d["residual_image.fits"], "--size", str(IMAGE_SIZE),
             "--cell", str(CELL_ARCSEC)])
    im = _xstack(["imstack", d["residual_image.fits"], targets, d["imstack.fits"],
                  "--weighting", "sigma2"])

    say("# 7. model fit of the stacked visibilities; Monte Carlo noise and bias")
    fit = _xstack(["fit", d["stacked.zarr"], "--model", "point", "--png", str(out / "fit_uv.png")])
    noise = _xstack(["noise", d["residual.zarr"], targets, "--method", "mc",
                     "--realizations", "20", "--seed", str(args.seed),
                     "--avoid", bright, "--png", str(out / "noise_mc.png")])

    from astropy.table import Table

    true_mean = float(np.mean(Table.read(targets)["flux"]))
    summary = {
        "outdir": str(out),
        "injected_mean_flux_jy": true_mean,
        "uvstack_flux_jy": uv.get("flux_jy"), "uvstack_flux_err_jy": uv.get("flux_err_jy"),
        "imstack_flux_jy": im.get("flux_jy"), "imstack_flux_err_jy": im.get("flux_err_jy"),
        "uvfit_flux_jy": fit.get("flux_jy"), "uvfit_flux_err_jy": fit.get("flux_err_jy"),
        "mc_noise_jy": noise.get("noise_jy"), "mc_bias_jy": noise.get("bias_jy"),
        "n_positions": uv.get("n_positions"), "roundtrip_identical": identical,
        "elapsed_s": round(time.perf_counter() - t_start, 1),
    }
    if args.json:
        from xstack.cli import emit_json

        emit_json(summary)
    else:
        _print_summary(summary, out)
    return 0


def _stores_identical(a: str, b: str) -> bool:
    from xstack.schema import iter_partitions, open_store

    pa = dict(iter_partitions(open_store(a)))
    pb = dict(iter_partitions(open_store(b)))
    if sorted(pa) != sorted(pb):
        return False
    for name, ds in pa.items():
        other = pb[name]
        for var in ("VISIBILITY", "WEIGHT", "FLAG", "UVW"):
            if not np.array_equal(ds[var].values, other[var].values, equal_nan=var != "FLAG"):
                return False
        if not np.array_equal(ds.time.values, other.time.values):
            return False
    return True


def _print_summary(s: dict[str, Any], out: Path) -> None:
    from xstack.cli._output import count, figure, result

    like = [s["injected_mean_flux_jy"], s["uvstack_flux_jy"], s["uvstack_flux_err_jy"],
            s["uvfit_flux_jy"], s["imstack_flux_jy"], s["mc_noise_jy"], s["mc_bias_jy"]]

    def jy(v: Any, e: Any = None, unit: str = "Jy") -> str:
        return figure(v, e, unit, like=like)

    result(f"Injected mean target flux: {jy(s['injected_mean_flux_jy'])} "
           f"({count(s['n_positions'] or 0, 'position')})")
    result(f"  uv-stacking      {jy(s['uvstack_flux_jy'], s['uvstack_flux_err_jy'])}")
    result(f"  uv point fit     {jy(s['uvfit_flux_jy'], s['uvfit_flux_err_jy'])}")
    result(f"  image-stacking   "
           f"{jy(s['imstack_flux_jy'], s['imstack_flux_err_jy'], 'Jy/beam')}")
    result(f"  Monte Carlo      noise {jy(s['mc_noise_jy'])}, bias {jy(s['mc_bias_jy'])}")
    result(f"MS round trip identical: {s['roundtrip_identical']}; total {s['elapsed_s']} s")
    result(f"Outputs in {out}/ (images: *.fits, plots: *.png)")


def _to_toml(obj: dict[str, Any]) -> str:
    """Minimal TOML writer for the scene dictionary (strings, numbers, lists, tables)."""
    lines: list[str] = []

    def value(v: Any) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{k} = {value(x)}" for k, x in v.items() if x is not None) + "}"
        raise TypeError(type(v))

    scalars = {k: v for k, v in obj.items() if not isinstance(v, (dict, list))
               or (isinstance(v, list) and not any(isinstance(x, dict) for x in v))}
    for k, v in scalars.items():
        if v is not None:
            lines.append(f"{k} = {value(v)}")
    for k, v in obj.items():
        if isinstance(v, dict):
            lines.append(f"\n[{k}]")
            for kk, vv in v.items():
                if vv is not None:
                    lines.append(f"{kk} = {value(vv)}")
        elif isinstance(v, list) and any(isinstance(x, dict) for x in v):
            for item in v:
                lines.append(f"\n[[{k}]]")
                for kk, vv in item.items():
                    if vv is not None:
                        lines.append(f"{kk} = {value(vv)}")
    return "\n".join(lines) + "\n"
