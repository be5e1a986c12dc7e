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
    p.add_argument("--filter", type=_types.filter_cells_or_distance, default=None,
                   dest="filter_lowfreq",
                   metavar="N|DIST",
                   help="low-spatial-frequency FFT filter of the stack (paper §5.3): an odd N "
                        "zeroes the central N x N Fourier cells; a uv distance (4500m, "
                        "20klambda; a number with a decimal point is metres) zeroes every cell "
                        "below it")
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
    result = stack_images(images, catalog, stamp_size=args.stamp_size, method=args.method,
                          weighting=args.weighting, subpixel=args.subpixel or False,
                          primary_beam=_one_or_list(args.primary_beam), pbcor=args.pbcor,
                          psf=_one_or_list(args.psf),
                          image_corrected=_corrected(args.image_corrected),
                          beam_mask_arcsec=args.beam_mask_arcsec,
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
