"""``xstack imstack``: image-stacking of FITS images at catalog positions (paper §3.2)."""

from __future__ import annotations

import argparse
from typing import Any

from xstack import _vocabulary as V
from xstack.errors import XstackError


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    from xstack.cli import _types

    p = subparsers.add_parser(
        "imstack", help="stack image stamps at catalog positions",
        description="Cut a stamp around every catalog position in one or more FITS images "
                    "(any celestial WCS; mosaic pointings together) and stack them per pixel "
                    "(weighted mean or median, NaN off the image ignored). Writes OUT.fits "
                    "(stacked stamp, PSF and WEIGHTS extensions), OUT.cube.zarr (all stamps) "
                    "and OUT.png. The flux is the stacked value at the center pixel.",
        epilog="example: xstack imstack field.fits targets.ecsv stack.fits --subpixel fourier --json")
    p.add_argument("inputs", nargs="+", metavar="IMAGE.fits ... CATALOG OUT.fits",
                   help="one or more images, then the catalog (ra, dec [deg], optional weight), "
                        "then the output FITS name")
    p.add_argument("--method", choices=V.IMSTACK_METHODS, default="mean",
                   help="per-pixel weighted mean (default) or median")
    p.add_argument("--weighting", choices=V.IMSTACK_WEIGHTINGS, default="sigma2",
                   help="stamp weights: 1/sigma_k^2 from the stamp outside the beam (default), "
                        "primary beam A^2, none, or the catalog's weight column")
    p.add_argument("--stamp-size", type=int, default=64, help="stamp size in pixels (default 64)")
    p.add_argument("--subpixel", choices=V.SUBPIXEL_METHODS, default=None,
                   help="align each stamp on the exact position (default: nearest pixel, as in "
                        "the paper)")
    p.add_argument("--psf", action="append", default=None, metavar="PSF.fits",
                   help="PSF image (once, or once per image; default X.psf.fits beside X.fits)")
    p.add_argument("--primary-beam", action="append", default=None, metavar="PB",
                   help="primary beam: airy|gaussian|vla|none or a PB FITS image (once, or once "
                        "per image; default: the beam file the image names (XSPBFILE, "
                        "X.pb.fits from xstack image), else the telescope's standard beam)")
    p.add_argument("--image-corrected", action="append", default=None, choices=("yes", "no"),
                   help="whether the image is primary-beam corrected (once, or once per image; "
                        "default: its header's XSPBCOR). The stack always measures corrected "
                        "fluxes: an uncorrected image is divided by the beam")
    p.add_argument("--pbcor", action="store_true",
                   help="same as --image-corrected no (divide each stamp by the primary beam)")
    p.add_argument("--mask-radius", type=_types.angle_arcsec, default=None, metavar="ANGLE",
                   dest="beam_mask_arcsec",
                   help=f"radius of the central mask for sigma_k ({_types.ANGLE_HELP}; "
                        "default: BMAJ)")
    p.add_argument("--noise-estimator", choices=V.LOCAL_NOISE_ESTIMATORS, default="clipped",
                   help="sigma_k of the 1/sigma_k^2 weights: 3-sigma clipped std (default, as "
                        "uvstack --noise-image), median absolute deviation, or the paper's "
                        "plain std (counts CLEAN residuals near a target as noise)")
    p.add_argument("--noise-stamp-size", type=int, default=None, metavar="PIXELS",
                   help="side of the square sigma_k is measured on (default: ~300 beam areas, "
                        "paper section 3.2; the stamp size for an image without a beam)")
    p.add_argument("--filter", type=_types.filter_cells_or_distance, default=None,
                   dest="filter_lowfreq",
                   metavar="N|DIST",
                   help="low-spatial-frequency FFT filter of the stack (paper §5.3): an odd N "
                        "zeroes the central N x N Fourier cells; a uv distance (4500m, "
                        "20klambda; a number with a decimal point is metres) zeroes every cell "
                        "below it")
    from xstack.cli.linestack import (
        VELOCITY_HELP,
        add_continuum_options,
        line_frequency,
        velocity_pair,
    )

    line = p.add_argument_group(
        "spectral lines (image cubes)",
        "with --line-frequency the input is one image cube (xstack image --cube): 3-D stamps "
        "aligned in velocity about each target's line centre (catalog z or freq), regridded "
        "by channel overlap; writes OUT.fits (stacked cube, VRAD km/s), OUT_spectrum.ecsv, "
        "OUT_spectrum.png and OUT_mom0.png; JSON as xstack linestack (docs/linestack.md)")
    line.add_argument("--line-frequency", type=line_frequency, default=None, metavar="F",
                      help="rest frequency: a name (HI, CO(1-0), [CII], ...) or 1420.4MHz")
    line.add_argument("--velocity-resolution", type=_types.velocity_kms, default=20.0,
                      metavar="V", help=f"velocity bin width (default 20km/s; {VELOCITY_HELP})")
    line.add_argument("--velocity-range", type=velocity_pair, default=(-600.0, 600.0),
                      metavar="A,B", help="velocity range about each line centre (default "
                      f"-600,600km/s; write --velocity-range=-600,600km/s; {VELOCITY_HELP})")
    line.add_argument("--line-window", type=velocity_pair, default=None, metavar="A,B",
                      help="velocities the integrated flux and the moment-0 stamp sum over "
                           "(default: the fitted centre ± FWHM)")
    line.add_argument("--frame", choices=V.CUBE_LINE_FRAMES, default=None,
                      help="frame of the catalog's redshifts (default lsrk): a cube in another "
                           "frame (TOPOCENT from xstack image --cube) is converted with its "
                           "DATE-OBS/MJD-AVG and OBSGEO keywords; cube: no conversion")
    add_continuum_options(line)
    p.add_argument("--cube-format", choices=V.CUBE_FORMATS, default="zarr",
                   help="format of OUT.cube.* (default zarr)")
    p.add_argument("--no-png", action="store_true", help="do not write OUT.png")
    p.add_argument("--skip-outside", action="store_true",
                   help="skip positions outside every image instead of failing")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from xstack.cli._cluster import add_cluster_options

    add_cluster_options(p)
    return p


def _one_or_list(values: list[str] | None) -> Any:
    if not values:
        return None
    return values[0] if len(values) == 1 else values


def _corrected(values: list[str] | None) -> Any:
    if not values:
        return None
    flags = [v == "yes" for v in values]
    return flags[0] if len(flags) == 1 else flags


def run(args: argparse.Namespace) -> int:
    from xstack.cli import emit_json
    from xstack.imstack.stack import stack_images

    if len(args.inputs) < 3:
        raise XstackError("give IMAGE.fits [IMAGE.fits ...] CATALOG OUT.fits")
    *images, catalog, out = args.inputs
    if not out.lower().endswith(".fits"):
        raise XstackError(f"{out}: the output must be a .fits file name (got the arguments in "
                          "the wrong order?)")
    if args.line_frequency is not None:
        if args.noise_stamp_size is not None:
            raise XstackError("--noise-stamp-size is for continuum stacks (a line stack "
                              "measures each channel's noise on its stamp)")
        return _run_line(args, images, catalog, out)
    for flag, given in (("--continuum-subtract", args.continuum_subtract),
                        ("--line-free", args.line_free), ("--frame", args.frame)):
        if given is not None:
            raise XstackError(f"{flag} goes with --line-frequency (a cube's line stack)")
    result = stack_images(images, catalog, stamp_size=args.stamp_size, method=args.method,
                          weighting=args.weighting, subpixel=args.subpixel or False,
                          primary_beam=_one_or_list(args.primary_beam), pbcor=args.pbcor,
                          psf=_one_or_list(args.psf),
                          image_corrected=_corrected(args.image_corrected),
                          beam_mask_arcsec=args.beam_mask_arcsec,
                          noise_estimator=args.noise_estimator,
                          noise_stamp_size=args.noise_stamp_size,
                          filter_lowfreq=args.filter_lowfreq,
                          skip_outside=args.skip_outside, out=out, cube_format=args.cube_format,
                          plot=not args.no_png, overwrite=args.overwrite,
                          progress=not args.no_progress and not args.json)
    summary = result.to_dict()
    if args.json:
        emit_json(summary)
    else:
        from xstack.cli._output import count, figure
        from xstack.cli._output import result as say_result

        unit = str(result.stacked.attrs.get("units", "Jy/beam")).replace(" ", "")
        say_result(f"stacked flux {figure(result.flux_jy, result.flux_err_jy, unit)} at the "
                   f"stacking position from {count(summary['n_positions'], 'position')} "
                   f"({count(summary['n_stamps'], 'stamp')}, {args.method}, weighting "
                   f"{args.weighting}, {summary['subpixel']} alignment)")
        for kind, path in result.outputs.items():
            say_result(f"  wrote {kind}: {path}")
    return 0


def _run_line(args: argparse.Namespace, images: list[str], catalog: str, out: str) -> int:
    """``--line-frequency``: stack a cube's 3-D stamps in velocity (xstack.imstack.line)."""
    import math
    import time
    from pathlib import Path

    import numpy as np

    from xstack._atomic import atomic_output, check_output
    from xstack.cli import emit_json
    from xstack.cli._output import warn
    from xstack.cli.linestack import check_continuum_options, subtract_continuum_of, summary
    from xstack.fit.line import fit_line, line_spectrum_figure, spectrum_table
    from xstack.imstack.line import stack_line_cube

    if len(images) != 1:
        raise XstackError("--line-frequency stacks one image cube: give CUBE.fits CATALOG "
                          "OUT.fits")
    for flag, bad in (("--subpixel", args.subpixel), ("--filter", args.filter_lowfreq),
                      ("--psf", args.psf), ("--image-corrected", args.image_corrected),
                      ("--pbcor", args.pbcor), ("--skip-outside", args.skip_outside)):
        if bad:
            raise XstackError(f"{flag} does not go with --line-frequency")
    if args.primary_beam and len(args.primary_beam) > 1:
        raise XstackError("--primary-beam: give it once with --line-frequency")
    check_continuum_options(args)
    stem = out[:-5]
    names = {"ecsv": Path(f"{stem}_spectrum.ecsv"), "png": Path(f"{stem}_spectrum.png"),
             "mom0": Path(f"{stem}_mom0.png")}
    if args.no_png:
        names.pop("png")
        names.pop("mom0")
    for path in (out, *names.values()):
        check_output(path, args.overwrite)
    t0 = time.perf_counter()
    res = stack_line_cube(images[0], catalog, line_frequency=args.line_frequency,
                          velocity_resolution=args.velocity_resolution,
                          velocity_range=args.velocity_range, method=args.method,
                          weighting=args.weighting, stamp_size=args.stamp_size,
                          beam_mask_arcsec=args.beam_mask_arcsec,
                          noise_estimator=args.noise_estimator,
                          primary_beam=(args.primary_beam or ["auto"])[0],
                          frame=args.frame or "lsrk", out=out, overwrite=args.overwrite)
    res, baseline = subtract_continuum_of(res, args)
    if baseline is not None:
        # the moment-0 stamp without continuum: the same linear map on every pixel's spectrum
        # (weights from the centre pixel's covariance; removes any per-pixel polynomial of
        # the order exactly). OUT.fits keeps the cube as stacked.
        import dataclasses

        cube = np.asarray(res.stacked, dtype=np.float64)
        sub = np.tensordot(baseline.matrix, np.nan_to_num(cube, nan=0.0), axes=(1, 0))
        sub[~np.isfinite(cube)] = np.nan
        res = dataclasses.replace(res, stacked=sub)
    fit = fit_line(res.velocity_kms, res.flux_jy, res.flux_cov_jy2,
                   velocity_edges_kms=res.velocity_edges_kms, window_kms=args.line_window)
    if not fit.converged:
        needs = "" if args.line_window is not None else \
            "; for an integrated flux give --line-window A,B"
        warn(f"no line fitted: {fit.message.replace('window_kms', '--line-window')}{needs}")
    table = spectrum_table(res, fit, baseline)
    with atomic_output(names["ecsv"], overwrite=args.overwrite) as tmp:
        table.write(str(tmp), format="ascii.ecsv")
    if not args.no_png:
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        title = (f"image line stack of {res.n_positions} positions ({res.frame.upper()}, "
                 f"{args.method}, rest {res.rest_frequency_hz / 1e9:.6g} GHz)")
        fig = line_spectrum_figure(table, title=title)
        with atomic_output(names["png"], overwrite=args.overwrite) as tmp:
            fig.savefig(tmp, format="png", dpi=100, bbox_inches="tight")
        plt.close(fig)
        window = fit.window_kms if all(map(math.isfinite, fit.window_kms)) else \
            (res.velocity_edges_kms[0], res.velocity_edges_kms[-1])
        mom0 = res.moment0(window)
        fig, ax = plt.subplots(figsize=(5.5, 5))
        off = (np.arange(mom0.shape[0]) - mom0.shape[0] // 2) * abs(float(
            res.header.get("CDELT2", res.header.get("CD2_2", 0.0)))) * 3600.0
        im = ax.imshow(mom0, origin="lower", cmap="inferno",
                       extent=(off[0], off[-1], off[0], off[-1]))
        ax.set_xlabel("offset (arcsec)")
        ax.set_ylabel("offset (arcsec)")
        ax.set_title(f"moment 0 over {window[0]:.4g}..{window[1]:.4g} km/s")
        fig.colorbar(im, ax=ax, label="Jy/beam km/s")
        with atomic_output(names["mom0"], overwrite=args.overwrite) as tmp:
            fig.savefig(tmp, format="png", dpi=100, bbox_inches="tight")
        plt.close(fig)
    seconds = time.perf_counter() - t0
    if args.json:
        emit_json({**summary(res, fit, baseline), "output": str(out),
                   "spectrum_table": str(names["ecsv"]),
                   "spectrum_png": str(names["png"]) if "png" in names else None,
                   "moment0_png": str(names["mom0"]) if "mom0" in names else None,
                   "seconds": round(seconds, 3)})
        return 0
    from xstack.cli._output import count
    from xstack.cli._output import result as say_result
    from xstack.cli.linestack import continuum_text, fit_text

    say_result(f"{fit_text(fit)}; from {count(res.n_positions, 'position')} ({args.method})")
    if baseline is not None:
        say_result(f"  continuum subtracted: {continuum_text(baseline)}")
    say_result("  wrote " + ", ".join([out, *map(str, names.values())]))
    return 0
