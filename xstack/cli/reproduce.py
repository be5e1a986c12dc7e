"""``xstack reproduce``: the paper's Table 2 end to end, beside the paper's numbers."""

from __future__ import annotations

import argparse
import math
import shutil
from pathlib import Path
from typing import Any

from xstack.errors import XstackError


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "reproduce", help="reproduce the paper's Table 2 (simulate, CLEAN, subtract, stack)",
        description="Run the paper's procedure (Lindroos et al. 2015, sections 2-4) for "
                    "data-set types over Monte Carlo realisations: simulate, image and CLEAN "
                    "the bright sources to the paper's threshold, subtract the CLEAN model, "
                    "uv-stack (5000 m cut for types 5-7 and 11) and image-stack the targets, fit "
                    "flux and size for type 7, and compare mean and scatter with the paper's "
                    "Table 2. Resumable: each realisation is appended to "
                    "OUTDIR/typeN/realizations.jsonl and a new run does only the missing "
                    "ones; a work directory OUTDIR/typeN/seedR-* left by a run killed "
                    "outright is named in a warning. The ALMA mosaics (types 8-10) CLEAN "
                    "and subtract each pointing on its own (the paper jointly for 8 and "
                    "10).")
    p.add_argument("--type", dest="types", action="append", default=None, metavar="N|all",
                   help="data-set type 1-11, or all (the supported ones); repeatable; "
                        "required unless --report-only")
    p.add_argument("--realizations", type=int, default=100, metavar="R",
                   help="realisations (seeds 0..R-1) per type (default 100, as the paper)")
    p.add_argument("--scale", type=float, default=1.0, metavar="F",
                   help="observing time and large populations times F, 0 < F <= 1 "
                        "(default 1: the paper's size)")
    p.add_argument("--outdir", default="xstack-reproduce", metavar="DIR",
                   help="directory of the per-realisation results (default ./xstack-reproduce)")
    p.add_argument("--overwrite", action="store_true",
                   help="forget earlier realisations of these types in --outdir and run all "
                        "again (default: resume)")
    p.add_argument("--report-only", action="store_true",
                   help="run nothing: (re)write DIR/report.md (the table beside the paper's) "
                        "and DIR/figures/ from the realisations already in --outdir (a normal "
                        "run writes them at its end too)")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from xstack.cli._cluster import add_cluster_options

    # on a cluster (--scheduler, --workers, DASK_SCHEDULER_ADDRESS) realisations run as tasks
    add_cluster_options(p)
    return p


def run(args: argparse.Namespace) -> int:
    from xstack.cli import emit_json
    from xstack.cli._output import detail, progress_enabled, result, say
    from xstack.reproduce.report import write_report
    from xstack.reproduce.run import parse_types, reproduce

    if args.report_only:
        path = write_report(Path(args.outdir))
        if args.json:
            emit_json({"report": str(path)})
        else:
            result(f"report: {path} (figures in {path.parent / 'figures'}/)")
        return 0
    if not args.types:
        raise XstackError("--type is required (unless --report-only)")
    types = parse_types(args.types)
    if args.realizations < 1:
        raise XstackError("--realizations must be >= 1")
    if not 0 < args.scale <= 1:
        raise XstackError("--scale must be in (0, 1]")
    outdir = Path(args.outdir)
    if args.overwrite:
        for n in types:
            shutil.rmtree(outdir / f"type{n}", ignore_errors=True)
    from xstack._cluster import active_client

    client = active_client()  # main() connected --scheduler/--workers (xstack._cluster)
    say(f"reproducing type(s) {', '.join(map(str, types))}: {args.realizations} "
        f"realisation(s) at scale {args.scale:g} in {outdir}/")
    bar = progress_enabled() and not args.no_progress
    res = reproduce(types, realizations=args.realizations, scale=args.scale,
                    outdir=outdir, progress=bar, client=client,
                    # a line per realisation where no bar shows it (a batch job's log);
                    # beside a bar only with -v
                    on_realization=lambda line, k, m: (detail if bar else say)(
                        realization_line(line, k, m)))
    # the report covers every type in the directory, also those of earlier runs
    payload = {**res.to_dict(), "report": str(write_report(outdir))}
    say(f"report: {payload['report']}")
    if args.json:
        emit_json(payload)
    else:
        print_tables(payload)
    return 0


def realization_line(line: dict[str, Any], k: int, m: int) -> str:
    """``type 6 seed 3: uv 1.06 µJy, image 0.80 µJy (374 s; 4 of 12 new)``."""
    from xstack.cli._output import figure

    like = [line.get("uv_flux_jy"), line.get("image_flux_jy")]
    return (f"type {line['type']} seed {line['seed']}: "
            f"uv {figure(line.get('uv_flux_jy'), like=like)}, "
            f"image {figure(line.get('image_flux_jy'), like=like)} "
            f"({line.get('seconds', float('nan')):.0f} s; {k} of {m} new)")


def _snr(flux: float | None, scatter: float | None) -> str:
    if flux is None or scatter is None or not scatter or not math.isfinite(scatter):
        return "n/a"
    return f"{flux / scatter:.1f}"


def _arcsec(value: float | None, scatter: float | None) -> str:
    if value is None:
        return "n/a"
    return f"{value:.2f} ± {'n/a' if scatter is None else f'{scatter:.2f}'} arcsec"


def print_tables(payload: dict[str, Any]) -> None:
    """One table per type: xstack's mean ± scatter (SNR) beside the paper's row."""
    from xstack.cli._output import figure, result, seconds

    for t in payload["types"]:
        p = t["paper"]
        like = [t["true_flux_jy"], p["expected_flux_jy"]]

        def fig(v: Any, e: Any = None, like: list[Any] = like) -> str:
            return figure(v, e, "Jy", like=like)

        ours_uv = (f"{fig(t['uv_flux_mean_jy'], t['uv_flux_scatter_jy'])} "
                   f"({_snr(t['uv_flux_mean_jy'], t['uv_flux_scatter_jy'])})")
        ours_im = (f"{fig(t['image_flux_mean_jy'], t['image_flux_scatter_jy'])} "
                   f"({_snr(t['image_flux_mean_jy'], t['image_flux_scatter_jy'])})")
        result(f"type {t['type']}: {t['realizations']} realisation(s), scale {t['scale']:g}, "
               f"{seconds(t['seconds'])} of computing ({t['seconds_per_realization']:.1f} s each)",
               f"  {'':20s}{'xstack':<30s}paper (Table 2)",
               f"  {'expected':20s}{fig(t['true_flux_jy'], t['expected_noise_jy']):<30s}"
               f"{fig(p['expected_flux_jy'], p['expected_noise_jy'])}",
               # the paper's expected noise is this one (eq. 9, sigma_k from the residual map)
               f"  {'noise, map (eq. 9)':20s}"
               f"{fig(t.get('expected_map_noise_jy'), like=like):<30s}"
               f"{fig(p['expected_noise_jy'], like=like)}",
               f"  {'uv-stacking':20s}{ours_uv:<30s}"
               f"{fig(p['uv_flux_jy'], p['uv_scatter_jy'])} ({p['uv_snr']:.1f})",
               f"  {'image-stacking':20s}{ours_im:<30s}"
               f"{fig(p['image_flux_jy'], p['image_scatter_jy'])} ({p['image_snr']:.1f})")
        if t.get("sizes"):
            s, ps = t["sizes"], p["sizes"]
            for dom in ("uv", "image"):
                ours = _arcsec(s[dom + "_fwhm_mean_arcsec"], s[dom + "_fwhm_scatter_arcsec"])
                if s.get(dom + "_fits_failed"):
                    ours += f" ({s[dom + '_fits_failed']} failed)"
                result(f"  {dom + ' size (FWHM)':20s}{ours:<30s}"
                       f"{ps[dom + '_fwhm_arcsec']:.2f} ± {ps[dom + '_fwhm_scatter_arcsec']:.2f} arcsec")
