"""``xstack convert``: MeasurementSet -> xstack zarr store."""

from __future__ import annotations

import argparse
import time
from typing import Any

from xstack.cli._storage import add_storage_options


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "convert", help="convert a MeasurementSet into an xstack zarr store",
        description="Stream a MeasurementSet into a zarr (v3) store with one partition per "
                    "spectral window x field (and scan where the time grid needs it). WEIGHT "
                    "comes from WEIGHT_SPECTRUM, else WEIGHT, else 1/SIGMA^2; FLAG honours "
                    "FLAG_ROW; missing (time, baseline) cells are NaN and flagged. The output "
                    "is written under a temporary name and renamed when complete.")
    p.add_argument("ms", help="input MeasurementSet (read only)")
    p.add_argument("out", help="output store (.zarr)")
    p.add_argument("--datacolumn", default="DATA", metavar="COLUMN",
                   help="visibility column: DATA (default), CORRECTED_DATA or MODEL_DATA")
    p.add_argument("--chunks", default=None, metavar="time=N,baseline_id=M",
                   help="chunk sizes of the output (default: ~128 MB of visibilities per chunk, "
                        "frequency and polarization whole)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from xstack.cli._cluster import add_cluster_options

    add_cluster_options(p)
    add_storage_options(p)
    return p


def store_summary(path: Any) -> dict[str, Any]:
    """Partition names, shapes and visibility counts of a store (metadata only)."""
    from xstack.schema import iter_partitions, open_store

    tree = open_store(path)
    parts = {}
    n_vis = 0
    for name, ds in iter_partitions(tree):
        sizes = {d: int(ds.sizes[d]) for d in ("time", "baseline_id", "frequency", "polarization")}
        parts[name] = {**sizes, "field_name": ds.attrs["field_name"],
                       "polarization": [str(p) for p in ds["polarization"].values],
                       "chunks": {"time": int(ds["VISIBILITY"].data.chunksize[0]),
                                  "baseline_id": int(ds["VISIBILITY"].data.chunksize[1])}}
        n_vis += int(ds["VISIBILITY"].size)
    return {"output": str(path), "partitions": parts, "n_visibilities": n_vis}


def run(args: argparse.Namespace) -> int:
    from xstack.cli import emit_json
    from xstack.io.convert import convert_ms, parse_chunks

    chunks = parse_chunks(args.chunks)
    t0 = time.perf_counter()
    out = convert_ms(args.ms, args.out, datacolumn=args.datacolumn, chunks=chunks,
                     overwrite=args.overwrite, progress=not args.no_progress)
    seconds = time.perf_counter() - t0
    summary = store_summary(out)
    if args.json:
        emit_json({**summary, "source_ms": str(args.ms),
                   "data_column": args.datacolumn.upper(), "seconds": round(seconds, 3)})
        return 0
    from xstack.cli._output import count, detail, result
    from xstack.cli._output import seconds as fmt_seconds

    parts = summary["partitions"]
    result(f"wrote {out}: {count(len(parts), 'partition')}, "
           f"{count(summary['n_visibilities'], 'visibility')} from the "
           f"{args.datacolumn.upper()} column of {args.ms} in {fmt_seconds(seconds)}")
    for name, p in parts.items():
        detail(f"  {name}: field {p['field_name']}, {p['time']} times x {p['baseline_id']} "
               f"baselines x {p['frequency']} channels x {'/'.join(p['polarization'])}; chunks "
               f"time={p['chunks']['time']}, baseline_id={p['chunks']['baseline_id']}")
    return 0
