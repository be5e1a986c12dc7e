"""``xstack linestack``: stack the spectra of catalog targets at their own redshifts in the
uv-domain, fit the stacked line and integrate it (issue 15; DESIGN.md section 2)."""

from __future__ import annotations

import argparse
import math
import re
import time
from pathlib import Path
from typing import Any

from xstack import _vocabulary as V
from xstack._fs import is_url
from xstack.cli._data import add_data_group, with_data_group
from xstack.cli._storage import add_storage_options, cli_path
from xstack.errors import XstackError

VELOCITY_HELP = "velocities: 20km/s, 2e4m/s; a plain number is km/s"

_NUMBER = re.compile(r"\s*[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?\s*")


def line_frequency(text: str) -> float:
    """argparse type of ``--line-frequency``: a line name or a frequency -> Hz."""
    from xstack.spectral import rest_frequency

    try:
        return rest_frequency(text)
    except XstackError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


line_frequency.__name__ = "line frequency"  # argparse names the type in its errors


def velocity_pair(text: str) -> tuple[float, float]:
    """argparse type of ``A,B`` velocity ranges -> (low, high) km/s.

    ``-600,600km/s``: a unit after the second value applies to a first value without one;
    ``-0.6e3km/s,600000m/s`` has one each; plain numbers are km/s.
    """
    from xstack.coords import parse_velocity

    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 2 or not all(parts):
        raise argparse.ArgumentTypeError(f"{text!r} is not two velocities A,B (e.g. "
                                         "-600,600km/s)")
    first, second = parts
    number = _NUMBER.match(second)
    unit = second[number.end():] if number else ""
    if _NUMBER.fullmatch(first) and unit:
        first += unit
    try:
        lo, hi = parse_velocity(first, "km/s"), parse_velocity(second, "km/s")
    except XstackError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
        raise argparse.ArgumentTypeError(f"{text!r}: needs A < B")
    return lo, hi


velocity_pair.__name__ = "velocity range"


def velocity_ranges(text: str) -> tuple[tuple[float, float], ...]:
    """argparse type of ``--line-free``: ``A,B[;C,D...]`` -> ((low, high), ...) km/s, each
    range as :func:`velocity_pair` reads it."""
    parts = [p for p in str(text).split(";") if p.strip()]
    if not parts:
        raise argparse.ArgumentTypeError(f"{text!r} is not velocity ranges A,B[;C,D...]")
    return tuple(velocity_pair(p) for p in parts)


velocity_ranges.__name__ = "velocity ranges"

CONTINUUM_HELP = ("fit a polynomial of degree ORDER (0: a constant, 1: a straight line) to the "
                  "bins wholly inside the --line-free ranges, by least squares with the bins' "
                  "covariance, and subtract it from the spectrum before the fit and the "
                  "integral (the covariance propagated exactly); needs --line-free")
LINE_FREE_HELP = ("velocity ranges free of line emission for --continuum-subtract, "
                  "A,B[;C,D...] (quote the ';'): e.g. --line-free='-600,-300;300,600km/s'; "
                  "they must not overlap --line-window")


def add_continuum_options(p: Any) -> None:
    """``--continuum-subtract ORDER`` and ``--line-free RANGES`` (linestack, imstack)."""
    p.add_argument("--continuum-subtract", type=int, default=None, metavar="ORDER",
                   help=CONTINUUM_HELP)
    p.add_argument("--line-free", type=velocity_ranges, default=None, metavar="A,B[;C,D...]",
                   help=LINE_FREE_HELP)


def check_continuum_options(args: argparse.Namespace) -> None:
    """One-line errors for ``--continuum-subtract``/``--line-free`` before any computation."""
    order, free = args.continuum_subtract, args.line_free
    if order is None and free is None:
        return
    if free is None:
        raise XstackError("--continuum-subtract needs --line-free A,B[;C,D...]: the velocity "
                          "ranges free of line emission the continuum is fitted on")
    if order is None:
        raise XstackError("--line-free needs --continuum-subtract ORDER (the polynomial's "
                          "degree)")
    if order < 0:
        raise XstackError(f"--continuum-subtract must be a degree >= 0, got {order}")
    window = args.line_window
    if window is not None:
        for lo, hi in free:
            if lo < window[1] and hi > window[0]:
                raise XstackError(f"--line-free range {lo:g},{hi:g} km/s overlaps --line-window "
                                  f"{window[0]:g},{window[1]:g} km/s")


def subtract_continuum_of(res: Any, args: argparse.Namespace) -> tuple[Any, Any]:
    """(the stack result with its spectrum continuum-subtracted, the
    :class:`~xstack.fit.line.ContinuumBaseline`) with ``--continuum-subtract``, else
    (``res``, None)."""
    import dataclasses

    import numpy as np

    from xstack.errors import OptionError
    from xstack.fit.line import subtract_continuum

    if args.continuum_subtract is None:
        return res, None
    try:
        flux, cov, baseline = subtract_continuum(
            res.velocity_edges_kms, res.flux_jy, res.flux_cov_jy2,
            order=args.continuum_subtract, line_free_kms=args.line_free,
            line_window_kms=args.line_window)
    except OptionError as exc:
        text = str(exc).replace("line_free_kms", "--line-free").replace(
            "order=", "--continuum-subtract ").replace("line window", "--line-window")
        raise XstackError(text) from None
    err = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    err[~np.isfinite(flux)] = np.nan
    return dataclasses.replace(res, flux_jy=flux, flux_err_jy=err, flux_cov_jy2=cov), baseline


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    from xstack.cli import _types

    p = subparsers.add_parser(
        "linestack", help="uv-stack the spectral lines of catalog targets at their redshifts",
        usage="xstack linestack [options] DATA [DATA ...] CATALOG OUT.zarr --line-frequency F",
        description="Phase-rotate every visibility to each catalog target (Lindroos et al. "
                    "2015, eq. 4) and average its channels, by their overlap, onto a common "
                    "velocity grid about the target's own observed line centre "
                    "nu_c = nu_rest / (1 + z) (catalog column z) or nu_c = freq (column freq), "
                    "v = c (nu_c - nu) / nu_c; TOPO data are converted per integration to "
                    "--frame. Fits a Gaussian to the stacked spectrum with the bins' "
                    "covariance (neighbouring bins share channels) and integrates it over "
                    "--line-window (default: the fitted centre ± FWHM). Writes the stacked "
                    "store OUT.zarr (channels = velocity bins), the spectrum "
                    "OUT_spectrum.ecsv (with the covariance) and OUT_spectrum.png. "
                    "Write a range that starts with a minus sign with '=': "
                    "--velocity-range=-600,600km/s. See docs/linestack.md.")
    p.add_argument("inputs", nargs="+", metavar="DATA... CATALOG OUT.zarr",
                   help="input stores or MSs, then the catalog (ra, dec in degrees or "
                        "sexagesimal; z or freq; optional weight, sigma), then the output store")
    p.add_argument("--line-frequency", type=line_frequency, required=True, metavar="F",
                   help="the line's rest frequency: a name (HI, CO(1-0), CO(2-1), [CII], ...) "
                        "or a frequency such as 1420.405751786MHz (a plain number is Hz)")
    p.add_argument("--velocity-resolution", type=_types.velocity_kms, default=20.0,
                   metavar="V", help=f"width of the velocity bins (default 20km/s; {VELOCITY_HELP})")
    p.add_argument("--velocity-range", type=velocity_pair, default=(-600.0, 600.0),
                   metavar="A,B", help="velocity range of the stack about each target's line "
                   f"centre (default -600,600km/s; {VELOCITY_HELP})")
    p.add_argument("--line-window", type=velocity_pair, default=None, metavar="A,B",
                   help="velocities the integrated flux sums over (default: the fitted centre "
                        f"± FWHM; {VELOCITY_HELP})")
    p.add_argument("--frame", default="lsrk", choices=V.LINE_FRAMES,
                   help="frame of the catalog's redshifts; TOPO data are converted to it per "
                        "integration, data in it are used as they are (default lsrk)")
    p.add_argument("--weighting", default="pb", choices=V.UVSTACK_WEIGHTINGS,
                   help="position weights as in uvstack: none, pb (A^2, default), sigma2 "
                        "(1/sigma^2 from the catalog's sigma column, else analytic 1/A noise), "
                        "column (weight column)")
    p.add_argument("--primary-beam", default="auto", metavar="MODEL",
                   help="auto (telescope standard, default), airy, gaussian, none, or PB.fits")
    p.add_argument("--pb-cutoff", type=float, default=V.DEFAULT_PB_CUTOFF, metavar="X",
                   help="positions with attenuation below X in any channel do not enter a "
                        f"pointing (default {V.DEFAULT_PB_CUTOFF:g})")
    p.add_argument("--uvmin", type=_types.uv_distance, default=None, metavar="DIST",
                   help=f"smallest uv distance stacked ({_types.DIST_HELP})")
    p.add_argument("--uvmax", type=_types.uv_distance, default=None, metavar="DIST",
                   help="largest uv distance stacked (as --uvmin)")
    p.add_argument("--polarizations", default="parallel",
                   help="parallel (Stokes I, default), all, or a comma list such as RR,LL")
    add_continuum_options(p)
    p.add_argument("--spectrum-png", default=None, metavar="P",
                   help="spectrum plot (default OUT_spectrum.png next to OUT.zarr)")
    p.add_argument("--no-png", action="store_true",
                   help="do not draw the spectrum plot (the ECSV table is still written)")
    add_data_group(p)
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from xstack.cli._cluster import add_cluster_options

    add_cluster_options(p)
    add_storage_options(p)
    return p


def _stem(out: Path | str) -> Path | str:
    return cli_path(str(out)[:-5] if str(out).endswith(".zarr") else str(out))  # a URL too


def summary(res: Any, fit: Any, baseline: Any = None) -> dict[str, Any]:
    """The JSON object of a run (DESIGN.md section 2): the stack's summary, the fitted line
    (``line_centre_kms``, ``line_fwhm_kms``, ``line_peak_jy`` and their errors) and the
    integral over ``line_window_kms``; NaN as null. ``continuum_subtracted``: the baseline's
    order, line-free ranges and coefficients with errors, or null."""
    from xstack._result import json_ready

    return json_ready({
        "continuum_subtracted": baseline.to_dict() if baseline is not None else None,
        **res.to_dict(),
        "integrated_flux_jy_kms": fit.integrated_flux_jy_kms,
        "integrated_flux_err_jy_kms": fit.integrated_flux_err_jy_kms,
        "line_window_kms": list(fit.window_kms),
        "line_centre_kms": fit.centre_kms, "line_centre_err_kms": fit.centre_err_kms,
        "line_fwhm_kms": fit.fwhm_kms, "line_fwhm_err_kms": fit.fwhm_err_kms,
        "line_peak_jy": fit.peak_jy, "line_peak_err_jy": fit.peak_err_jy,
        "fit": fit.to_dict()})


def run(args: argparse.Namespace) -> int:
    import contextlib

    from xstack.cli._plotter import BackgroundPlotter

    with (BackgroundPlotter(preload=("astropy.table", "xstack.fit.line"))
          if not args.no_png else contextlib.nullcontext()) as plotter:
        # the plot's imports run in a second process while this one stacks (as uvstack)
        return _run(args, plotter)


def _run(args: argparse.Namespace, plotter: Any) -> int:
    from xstack._atomic import atomic_output, check_output
    from xstack._inputs import Positions
    from xstack.cli import emit_json
    from xstack.cli._output import warn
    from xstack.fit.line import fit_line, spectrum_table
    from xstack.uvstack.line import stack_lines

    if len(args.inputs) < 3:
        raise XstackError("need DATA... CATALOG OUT.zarr (at least three arguments)")
    data, catalog, out = args.inputs[:-2], args.inputs[-2], cli_path(args.inputs[-1])
    stem = _stem(out)
    ecsv = cli_path(f"{stem}_spectrum.ecsv")
    if args.no_png and args.spectrum_png:
        raise XstackError("--spectrum-png and --no-png contradict each other")
    png = None if args.no_png else cli_path(args.spectrum_png) if args.spectrum_png \
        else cli_path(f"{stem}_spectrum.png")
    # everything that can be checked is checked before any computation
    for path in (out, ecsv, png):
        if path is not None:
            check_output(path, args.overwrite)
    for d in data:
        if not is_url(d) and not Path(d).exists():  # a URL: checked when opened
            raise XstackError(f"{d}: no such store or MeasurementSet")
    if args.velocity_resolution <= 0:
        raise XstackError(f"--velocity-resolution must be > 0 km/s, got "
                          f"{args.velocity_resolution:g}")
    check_continuum_options(args)
    window = args.line_window
    lo, hi = args.velocity_range
    if window is not None and (window[0] < lo or window[1] > hi):
        warn(f"--line-window {window[0]:g},{window[1]:g} km/s reaches beyond --velocity-range "
             f"{lo:g},{hi:g} km/s: the integral covers only the overlap")
    data = [with_data_group(d, args.data_group) for d in data]
    positions = Positions.from_any(catalog)
    pols: Any = args.polarizations
    if pols not in ("parallel", "all"):
        pols = [p.strip() for p in pols.split(",") if p.strip()]
    t0 = time.perf_counter()
    res = stack_lines(data if len(data) > 1 else data[0], positions,
                      line_frequency=args.line_frequency,
                      velocity_resolution=args.velocity_resolution,
                      velocity_range=args.velocity_range, frame=args.frame,
                      weighting=args.weighting, primary_beam=args.primary_beam,
                      pb_cutoff=args.pb_cutoff, uvmin=args.uvmin, uvmax=args.uvmax,
                      polarizations=pols, out=out, overwrite=args.overwrite,
                      progress=not args.no_progress)
    res, baseline = subtract_continuum_of(res, args)
    fit = fit_line(res.velocity_kms, res.flux_jy, res.flux_cov_jy2,
                   velocity_edges_kms=res.velocity_edges_kms, window_kms=window)
    if not fit.converged:
        needs = "" if window is not None else "; for an integrated flux give --line-window A,B"
        warn(f"no line fitted: {fit.message.replace('window_kms', '--line-window')}{needs}")
    table = spectrum_table(res, fit, baseline)
    with atomic_output(ecsv, overwrite=args.overwrite) as tmp:
        table.write(str(tmp), format="ascii.ecsv")
    if png is not None:
        title = (f"uv line stack of {res.n_positions} positions ({res.frame.upper()}, rest "
                 f"{res.rest_frequency_hz / 1e9:.6g} GHz)")
        image = plotter.render("xstack.fit.line:line_spectrum_figure", table, title=title)
        with atomic_output(png, overwrite=args.overwrite) as tmp:
            Path(tmp).write_bytes(image)
    seconds = time.perf_counter() - t0
    if args.json:
        emit_json({**summary(res, fit, baseline), "output": str(out), "spectrum_table": str(ecsv),
                   "spectrum_png": None if png is None else str(png),
                   "seconds": round(seconds, 3)})
        return 0
    from xstack.cli._output import count, detail, result

    line = fit_text(fit, peak=True)
    result(f"{line}; from {count(res.n_positions, 'position')}, "
           f"{count(res.n_visibilities, 'visibility')}")
    if baseline is not None:
        result(f"  continuum subtracted: {continuum_text(baseline)}")
    result(f"  wrote {out}, {ecsv}" + (f", {png}" if png is not None else ""))
    detail(f"{len(res.velocity_kms)} bins of {args.velocity_resolution:g} km/s from "
           f"{res.velocity_edges_kms[0]:g} to {res.velocity_edges_kms[-1]:g} km/s, frame "
           f"{res.frame}, weighting {args.weighting}, primary beam {args.primary_beam}; "
           f"fit chi2 {fit.chi2:.4g} for {fit.dof} degrees of freedom")
    return 0


def fit_text(fit: Any, peak: bool = False) -> str:
    """The line integral over its window and, for a converged fit, the centre, FWHM (and
    peak) with errors: the first result line of linestack and of imstack --line-frequency."""
    from xstack.cli._output import figure

    if math.isfinite(fit.integrated_flux_jy_kms):
        w = fit.window_kms
        value = figure(fit.integrated_flux_jy_kms, fit.integrated_flux_err_jy_kms, "Jy km/s")
        line = f"line integral {value} over {w[0]:.4g}..{w[1]:.4g} km/s"
    else:
        line = "line integral n/a (no line fitted, no --line-window)"
    if fit.converged:
        line += (f"; centre {figure(fit.centre_kms, fit.centre_err_kms, 'km/s')}, FWHM "
                 f"{figure(fit.fwhm_kms, fit.fwhm_err_kms, 'km/s')}")
        if peak:
            line += f", peak {figure(fit.peak_jy, fit.peak_err_jy, 'Jy')}"
    return line


def continuum_text(baseline: Any) -> str:
    """One line about the subtracted continuum: its order, ranges and coefficients."""
    from xstack.cli._output import figure

    ranges = "; ".join(f"{lo:g}..{hi:g}" for lo, hi in baseline.line_free_kms)
    terms = ", ".join(
        f"c{k} " + figure(c, e, "Jy" if k == 0 else f"Jy/(km/s)^{k}")
        for k, (c, e) in enumerate(zip(baseline.coefficients_jy, baseline.coefficient_errors)))
    return (f"order {baseline.order} over {ranges} km/s "
            f"({int(baseline.fit_bins.sum())} bins): {terms}")
