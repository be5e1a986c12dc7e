"""``xstack simulate (SCENE.toml | --preset NAME) OUT.zarr [--seed N] [--scale F]``.

``xstack simulate --preset NAME --print-scene`` prints the preset as an editable TOML scene.
"""

from __future__ import annotations

import argparse
from typing import Any

from xstack.cli._storage import add_storage_options
from xstack.errors import XstackError


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "simulate",
        help="simulate a scene (or one of the paper's data-set types) into a store",
        description="Simulate visibilities of a scene (TOML file) or a preset of the paper "
                    "(paper-1 ... paper-11) into a zarr store, and write the true source "
                    "list of each population beside it as OUT.<population>.ecsv.")
    p.add_argument("scene", nargs="?", help="scene TOML file (or use --preset)")
    p.add_argument("out", nargs="?", help="output store OUT.zarr")
    p.add_argument("--preset", help="paper-1 ... paper-11 (the paper's data-set types) or a "
                   "spectral-line preset, hi-stack or co-stack, instead of a scene file")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--scale", type=float, default=1.0,
                   help="0 < F <= 1: shorten the observation and thin large populations "
                        "for a quick run (default 1)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--print-scene", action="store_true",
                   help="print the scene (e.g. a preset) as TOML on stdout and exit: a "
                        "starting point for your own scene file")
    from xstack.cli._cluster import add_cluster_options

    add_cluster_options(p)
    add_storage_options(p)
    return p


def run(args: argparse.Namespace) -> int:
    from xstack.sim.presets import preset_scene
    from xstack.sim.scene import load_scene
    from xstack.sim.simulate import simulate

    if args.preset is not None and args.scene is not None and args.out is None:
        args.scene, args.out = None, args.scene  # `--preset NAME OUT.zarr`
    if (args.scene is None) == (args.preset is None):
        raise XstackError("give either a scene file or --preset NAME (not both)")
    if not 0 < args.scale <= 1:
        raise XstackError(f"--scale must be in (0, 1], got {args.scale}")
    scene = preset_scene(args.preset) if args.preset else load_scene(args.scene)
    if args.print_scene:
        import sys

        from xstack.sim.scene import scene_to_toml

        sys.stdout.write(scene_to_toml(scene.scaled(args.scale)))
        return 0
    if args.out is None:
        raise XstackError("missing the output store OUT.zarr")
    result = simulate(scene, args.out, seed=args.seed, scale=args.scale,
                      overwrite=args.overwrite, progress=not args.no_progress)
    if args.json:
        from xstack.cli import emit_json

        emit_json({
            "store": str(result.store),
            "catalogs": {k: str(v) for k, v in result.catalog_paths.items()},
            "n_sources": {k: len(v) for k, v in result.catalogs.items()},
            "n_pointings": len(result.pointings),
            "n_visibilities": result.n_visibilities,
            "steps": sorted(result.steps_run),
            "seed": result.seed,
            "scale": result.scale,
        })
        return 0
    from xstack.cli._output import count, detail
    from xstack.cli._output import result as say_result

    say_result(f"wrote {result.store}: {count(len(result.pointings), 'pointing')}, "
               f"{count(result.n_visibilities, 'visibility')} (seed {result.seed}, "
               f"scale {result.scale:g})")
    for k, path in result.catalog_paths.items():
        say_result(f"wrote {path}: true {k} ({count(len(result.catalogs[k]), 'source')})")
    detail(f"steps: {', '.join(sorted(result.steps_run))}")
    return 0
