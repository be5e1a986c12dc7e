"""``xstack subtract``: subtract a component catalog or CLEAN model image from a store."""

from __future__ import annotations

import argparse
from typing import Any

from xstack import _vocabulary as V
from xstack.cli._data import add_data_group, with_data_group
from xstack.cli._storage import add_storage_options


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "subtract", help="subtract a model (catalog or CLEAN model image) from a store",
        description="Write a residual store: DATA minus MODEL on the parallel hands. MODEL is "
                    "a component catalog (ra, dec, flux [Jy], optional fwhm_arcsec; predicted "
                    "exactly with equation 1 and the primary beam) or a CLEAN model FITS image "
                    "(Jy/pixel, e.g. OUT.model.fits of xstack image; predicted with ducc0).")
    p.add_argument("data", help="input store (.zarr)")
    p.add_argument("model", help="component catalog or CLEAN model image (.fits)")
    p.add_argument("out", help="output residual store (.zarr)")
    p.add_argument("--primary-beam", choices=V.SUBTRACT_PRIMARY_BEAMS,
                   default="auto",
                   help="catalog models: primary beam applied to the components (default: the "
                        "telescope's standard beam)")
    p.add_argument("--autocorrelations", action="store_true",
                   help="subtract the model from autocorrelations too (default: left out; "
                        "they measure system power, not the sky)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_data_group(p)
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from xstack.cli._cluster import add_cluster_options

    add_cluster_options(p)
    add_storage_options(p)
    return p


def run(args: argparse.Namespace) -> int:
    from xstack.cli import emit_json
    from xstack.imaging.subtract import subtract

    pb = args.primary_beam
    out = subtract(with_data_group(args.data, args.data_group), args.model, args.out,
                   overwrite=args.overwrite,
                   progress=not args.no_progress, primary_beam=pb,
                   autocorrelations=args.autocorrelations)
    if args.json:
        emit_json({"output": str(out), "model": str(args.model)})
        return 0
    from xstack.cli._output import count, result
    from xstack.cli.convert import store_summary

    summary = store_summary(out)
    result(f"wrote {out}: {args.data} minus the model {args.model} "
           f"({count(len(summary['partitions']), 'partition')}, "
           f"{count(summary['n_visibilities'], 'visibility')})")
    return 0
