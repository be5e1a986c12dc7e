"""``xstack uvstack``: stack visibilities at catalog positions (paper section 3.3)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from xstack import _vocabulary as V
from xstack._fs import is_url
from xstack.cli._data import add_data_group, with_data_group
from xstack.cli._storage import add_storage_options, cli_path
from xstack.errors import XstackError


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    from xstack.cli import _types

    p = subparsers.add_parser(
        "uvstack", help="uv-stack visibilities at the positions of a catalog",
        usage="xstack uvstack [options] DATA [DATA ...] CATALOG OUT.zarr",
        description="Phase-rotate every visibility to the catalog positions and average them "
                    "(Lindroos et al. 2015, eq. 4): each pointing about its own phase center, "
                    "primary-beam corrected, visibility weights scaled by the sum of the "
                    "position weights of the pointing. Writes the stacked store OUT.zarr, its "
                    "uv-profile (OUT_uvprofile.ecsv, OUT_uvprofile.png) and prints the stacked "
                    "point-source flux: the weighted mean of Re V over the unflagged parallel "
                    "hands in the uv range. DATA are xstack stores or MeasurementSets; several "
                    "are stacked together.")
    p.add_argument("inputs", nargs="+", metavar="DATA... CATALOG OUT.zarr",
                   help="input stores or MSs, then the catalog (ra, dec in degrees or "
                        "sexagesimal; optional weight, sigma), then the output store")
    p.add_argument("--weighting", default="pb", choices=V.UVSTACK_WEIGHTINGS,
                   help="position weights: none, pb (A^2, default), sigma2 (1/sigma^2 from "
                        "--noise-image, else the catalog's sigma column, else analytic 1/A "
                        "noise), column (weight column)")
    p.add_argument("--noise-image", default=None, metavar="RESIDUAL.fits",
                   help="with --weighting sigma2: measure sigma_k as the clipped rms of this "
                        "residual image (Jy/beam, primary-beam corrected) in a stamp of ~300 "
                        "beam areas around each position, outside a circle of radius BMAJ "
                        "(paper 3.2)")
    p.add_argument("--primary-beam", default="auto", metavar="MODEL",
                   help="auto (telescope standard, default), airy, gaussian, none, or PB.fits")
    p.add_argument("--pb-cutoff", type=float, default=V.DEFAULT_PB_CUTOFF, metavar="X",
                   help="positions with attenuation below X in any channel do not enter a "
                        f"pointing (default {V.DEFAULT_PB_CUTOFF:g})")
    p.add_argument("--uvmin", type=_types.uv_distance, default=None, metavar="DIST",
                   help=f"smallest uv distance in the flux ({_types.DIST_HELP})")
    p.add_argument("--uvmax", type=_types.uv_distance, default=None, metavar="DIST",
                   help="largest uv distance in the flux (as --uvmin)")
    p.add_argument("--polarizations", default="parallel",
                   help="parallel (Stokes I, default), all, or a comma list such as RR,LL")
    p.add_argument("--engine", default="auto", choices=V.UVSTACK_ENGINES,
                   help="phasor engine, float64 phases (default auto: per-antenna phasors where "
                   "the UVW factorise to 1e-9 rad, else per-row numba)")
    p.add_argument("--smearing", default="auto", choices=V.SMEARING_MODES,
                   help="correct each position for bandwidth and time-average smearing: auto "
                   "(default: data that carry it, i.e. real data and simulations that asked for "
                   "it), correct (always), none")
    p.add_argument("--errors", default="auto", choices=V.UVSTACK_ERRORS,
                   help="which flux error to print first: weights (from WEIGHT as 1/sigma^2), "
                        "empirical (from the visibility scatter between neighbouring channels) "
                        "or auto (default: empirical when the two differ by more than 20%%, "
                        "i.e. when WEIGHT is not 1/sigma^2 of the data, else weights); "
                        "--json carries both")
    p.add_argument("--profile-bins", type=int, default=20, metavar="N",
                   help="number of uv-distance bins of the profile (default 20)")
    p.add_argument("--profile-png", default=None, metavar="P",
                   help="uv-profile plot (default OUT_uvprofile.png next to OUT.zarr)")
    p.add_argument("--no-png", action="store_true",
                   help="do not draw the uv-profile plot (the ECSV table is still written)")
    add_data_group(p)
    p.add_argument("--autocorrelations", action="store_true",
                   help="stack autocorrelations too (default: left out; they measure system power, "
                        "not the sky)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from xstack.cli._cluster import add_cluster_options

    add_cluster_options(p)
    add_storage_options(p)
    return p


def _stem(out: Path | str) -> Path | str:
    return cli_path(str(out)[:-5] if str(out).endswith(".zarr") else str(out))  # a URL too


def first_error(res: Any, errors: str) -> str:
    """Which error the human output leads with: ``weights`` or ``empirical`` (``--errors``).

    ``auto`` takes the empirical error when it exists and differs from the weight-based one by
    more than :data:`xstack._scatter.EMPIRICAL_TOLERANCE` (the weights are then not
    1/sigma^2 of the data, while the scatter of the data is measured), else the weights.
    """
    import math

    from xstack._scatter import EMPIRICAL_TOLERANCE

    emp = res.flux_err_empirical_jy
    if errors == "weights" or not math.isfinite(emp):
        return "weights"
    if errors == "empirical":
        return "empirical"
    return "empirical" if abs(emp / res.flux_err_jy - 1) > EMPIRICAL_TOLERANCE else "weights"


def run(args: argparse.Namespace) -> int:
    import contextlib

    from xstack.cli._plotter import BackgroundPlotter

    with (BackgroundPlotter(preload=("astropy.table", "xstack.uvstack.plot"))
          if not args.no_png else contextlib.nullcontext()) as plotter:
        # the plot's imports run in a second process while this one stacks (_plotter.py)
        return _run(args, plotter)


def _run(args: argparse.Namespace, plotter: Any) -> int:
    from xstack._atomic import atomic_output, check_output
    from xstack._inputs import Positions
    from xstack.cli import emit_json
    from xstack.uvstack.stack import stack_uv

    if len(args.inputs) < 3:
        raise XstackError("need DATA... CATALOG OUT.zarr (at least three arguments)")
    data, catalog, out = args.inputs[:-2], args.inputs[-2], cli_path(args.inputs[-1])
    stem = _stem(out)
    ecsv = cli_path(f"{stem}_uvprofile.ecsv")
    png = None if args.no_png else cli_path(args.profile_png) if args.profile_png \
        else cli_path(f"{stem}_uvprofile.png")
    if args.no_png and args.profile_png:
        raise XstackError("--profile-png and --no-png contradict each other")
    # everything that can be checked is checked before any computation
    for path in (out, ecsv, png):
        if path is not None:
            check_output(path, args.overwrite)
    for d in data:
        if not is_url(d) and not Path(d).exists():  # a URL: checked when opened
            raise XstackError(f"{d}: no such store or MeasurementSet")
    if args.profile_bins < 1:
        raise XstackError("--profile-bins must be >= 1")
    if args.noise_image is not None:
        if args.weighting != "sigma2":
            raise XstackError("--noise-image needs --weighting sigma2")
        if not Path(args.noise_image).is_file():
            raise XstackError(f"{args.noise_image}: no such noise image (a FITS file)")
    data = [with_data_group(d, args.data_group) for d in data]
    positions = Positions.from_any(catalog)
    pols: Any = args.polarizations
    if pols not in ("parallel", "all"):
        pols = [p.strip() for p in pols.split(",") if p.strip()]
    progress = not args.no_progress
    t0 = time.perf_counter()
    res = stack_uv(data if len(data) > 1 else data[0], positions, weighting=args.weighting,
                  primary_beam=args.primary_beam, pb_cutoff=args.pb_cutoff, uvmin=args.uvmin,
                  uvmax=args.uvmax, noise_image=args.noise_image, polarizations=pols,
                  engine=args.engine, out=out, smearing=args.smearing,
                  autocorrelations=args.autocorrelations, profile_bins=args.profile_bins,
                  overwrite=args.overwrite, progress=progress)
    table = res.profile  # made in the stack's pass: the store is not read again
    first = first_error(res, args.errors)
    table.meta.update({"flux_jy": res.flux_jy, "flux_err_jy": res.flux_err_jy,
                       "flux_err_empirical_jy": res.flux_err_empirical_jy,
                       "n_positions": res.n_positions})
    with atomic_output(ecsv, overwrite=args.overwrite) as tmp:
        table.write(str(tmp), format="ascii.ecsv")
    if png is not None:
        image = plotter.render("xstack.uvstack.plot:uv_profile_figure", table,
                               flux_jy=res.flux_jy, title=f"uv-stack of {res.n_positions} positions")
        with atomic_output(png, overwrite=args.overwrite) as tmp:
            Path(tmp).write_bytes(image)
    seconds = time.perf_counter() - t0
    if args.json:
        emit_json({**res.to_dict(), "errors": args.errors, "errors_first": first,
                   "output": str(out), "profile_table": str(ecsv),
                   "profile_png": None if png is None else str(png),
                   "seconds": round(seconds, 3)})
    else:
        from xstack.cli._output import count, detail, figure, result

        errs = {"weights": (res.flux_err_jy, "from WEIGHT"),
                "empirical": (res.flux_err_empirical_jy, "from the visibility scatter")}
        other = "empirical" if first == "weights" else "weights"
        line = (res.flux_jy, res.flux_err_jy, res.flux_err_empirical_jy)
        other_err = figure(errs[other][0], unit="Jy", like=line).split(" ", 1)
        result(f"stacked flux {figure(res.flux_jy, errs[first][0], 'Jy', like=line)} "
               f"({errs[first][1]}; {errs[other][1]}: ± {other_err[0]} {other_err[1]}) from "
               f"{count(res.n_positions, 'position')}, "
               f"{count(res.n_visibilities, 'visibility')}")
        result(f"  wrote {out}, {ecsv}" + (f", {png}" if png is not None else ""))
        detail(f"weighting {args.weighting}, primary beam {args.primary_beam}, "
               f"engine {args.engine}, {count(len(res.stacked), 'partition')}: "
               f"{', '.join(sorted(map(str, res.stacked)))}")
    return 0
