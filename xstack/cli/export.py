"""``xstack export``: xstack zarr store -> MeasurementSet."""

from __future__ import annotations

import argparse
import time
from typing import Any

from xstack.cli._storage import add_storage_options


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "export", help="write an xstack store as a MeasurementSet",
        description="Write a MeasurementSet that CASA reads (listobs, tclean): DATA, FLAG, "
                    "WEIGHT, WEIGHT_SPECTRUM, SIGMA, UVW, TIME..., and the ANTENNA, FEED, FIELD, "
                    "OBSERVATION, POLARIZATION, SPECTRAL_WINDOW and DATA_DESCRIPTION subtables. "
                    "Cells that only pad an irregular grid are left out.")
    p.add_argument("store", help="input xstack store (.zarr)")
    p.add_argument("out", help="output MeasurementSet (.ms)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from xstack.cli._cluster import add_cluster_options

    add_cluster_options(p)
    add_storage_options(p)
    return p


def run(args: argparse.Namespace) -> int:
    from xstack.cli import emit_json
    from xstack.io.export import export_ms

    t0 = time.perf_counter()
    out = export_ms(args.store, args.out, overwrite=args.overwrite, progress=not args.no_progress)
    seconds = time.perf_counter() - t0
    import casacore.tables as pt

    with pt.table(str(out), ack=False) as tab:
        nrows = tab.nrows()
    if args.json:
        emit_json({"output": str(out), "store": str(args.store), "n_rows": int(nrows),
                   "seconds": round(seconds, 3)})
        return 0
    from xstack.cli._output import count, result
    from xstack.cli._output import seconds as fmt_seconds

    result(f"wrote {out}: {count(nrows, 'row')} from {args.store} in {fmt_seconds(seconds)}")
    return 0
