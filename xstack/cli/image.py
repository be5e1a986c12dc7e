"""``xstack image``: dirty or CLEANed image of a store, with PSF, residual and model FITS."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from xstack import _vocabulary as V
from xstack.cli._data import add_data_group, with_data_group
from xstack.cli._storage import add_storage_options, path_exists
from xstack.errors import XstackError


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    from xstack.cli import _types

    p = subparsers.add_parser(
        "image", help="make a (CLEANed) Stokes I image of a store",
        description="Image a store with ducc0 (multi-frequency synthesis, Stokes I from the "
                    "parallel hands). Writes OUT.fits (restored image if --niter > 0, else the "
                    "dirty image) beside OUT.psf.fits, OUT.residual.fits, OUT.model.fits and "
                    "OUT.pb.fits (the image's primary beam, named in its header: XSPBFILE; "
                    "XSPBCOR says whether the image is corrected). Partitions with different "
                    "phase centers (a mosaic) give a primary-beam corrected linear mosaic of "
                    "dirty images (no CLEAN) whose OUT.pb.fits is the mosaic's effective beam.")
    p.add_argument("data", help="input store (.zarr)")
    p.add_argument("out", help="output image (.fits)")
    p.add_argument("--size", type=int, required=True, help="image size in pixels (even, >= 32)")
    p.add_argument("--cell", type=_types.angle_arcsec, required=True, metavar="ANGLE",
                   help=f"pixel size ({_types.ANGLE_HELP})")
    p.add_argument("--niter", type=int, default=0, help="CLEAN components (0: dirty image only)")
    p.add_argument("--threshold", type=_types.threshold_jy, default="0", metavar="FLUX",
                   help="CLEAN threshold, Jy/beam (50uJy, 50uJy/beam, 0.05mJy; a plain number is "
                        "Jy; default 0)")
    p.add_argument("--gain", type=float, default=0.1, help="CLEAN loop gain (default 0.1)")
    p.add_argument("--algorithm", choices=V.CLEAN_ALGORITHMS, default="hogbom",
                   help="CLEAN minor-cycle algorithm (default hogbom)")
    p.add_argument("--mask", default=None, metavar="MASK.fits",
                   help="CLEAN mask: FITS image of the output's size, non-zero where components "
                        "may be placed")
    p.add_argument("--weighting", choices=V.IMAGE_WEIGHTINGS, default="natural")
    p.add_argument("--robust", type=float, default=0.0, help="Briggs robustness (default 0)")
    p.add_argument("--pbcor", action="store_true",
                   help="divide the image by the primary beam (NaN below the beam cutoff)")
    p.add_argument("--no-wterm", action="store_true", help="ignore the w-term (narrow fields)")
    p.add_argument("--epsilon", type=float, default=1e-6, help="gridder accuracy (default 1e-6)")
    p.add_argument("--threaded-gridding", action="store_true",
                   help="grid each image with all threads: ~1.3x faster on two cores, but the "
                        "image's last bits, and so CLEAN's components, vary from run to run "
                        "(default: one thread per image, the same data give the same image)")
    p.add_argument("--partition", action="append", default=None, metavar="NAME",
                   help="partition name or glob pattern to image (repeatable; default all; "
                        "CLEAN needs a single pointing)")
    p.add_argument("--pb-cutoff", type=float, default=None,
                   help="mosaic: NaN where no pointing's primary beam reaches this power "
                        f"(default the beam's cutoff, {V.DEFAULT_PB_CUTOFF:g})")
    p.add_argument("--cube", action="store_true",
                   help="write a dirty image cube OUT.fits instead: one Stokes I plane per "
                        "channel (or per --channels N), FREQ axis in the store's frame "
                        "(SPECSYS), a restoring beam per plane (BEAMS table); no CLEAN, one "
                        "pointing, no PSF/model/pb files")
    p.add_argument("--channels", type=int, default=1, metavar="N",
                   help="with --cube: consecutive channels imaged together per plane "
                        "(default 1)")
    from xstack.cli.linestack import VELOCITY_HELP, line_frequency

    p.add_argument("--velocity-resolution", type=_types.velocity_kms, default=None, metavar="V",
                   help="with --cube and --line-frequency: planes V wide in radio velocity "
                        "about the rest frequency instead of channels (each the overlap-"
                        f"weighted mean of the channels it covers; {VELOCITY_HELP})")
    p.add_argument("--line-frequency", type=line_frequency, default=None, metavar="F",
                   help="with --velocity-resolution: the rest frequency (HI, CO(1-0), "
                        "1420.405751786MHz, ...)")
    p.add_argument("--frame", choices=V.LINE_FRAMES, default=None,
                   help="with --velocity-resolution: frame of the velocity grid (default lsrk; "
                        "TOPO data are converted per integration)")
    p.add_argument("--png", action="store_true", help="also write OUT.png (quick-look)")
    p.add_argument("--autocorrelations", action="store_true",
                   help="image autocorrelations too (default: left out; they measure system "
                        "power, not the sky)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    add_data_group(p)
    p.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from xstack.cli._cluster import add_cluster_options

    add_cluster_options(p)
    add_storage_options(p)
    return p


def output_names(out: str | Path) -> dict[str, Path]:
    """File names written beside ``OUT.fits``: image, psf, residual, model, pb (and png)."""
    out = Path(out)
    stem = out.name[:-5] if out.name.lower().endswith(".fits") else out.name
    base = out.parent
    return {"image": out, "psf": base / f"{stem}.psf.fits",
            "residual": base / f"{stem}.residual.fits", "model": base / f"{stem}.model.fits",
            "pb": base / f"{stem}.pb.fits", "png": base / f"{stem}.png"}


def robust_rms(values: np.ndarray) -> float:
    """1.4826 x median absolute deviation of the finite values (robust to sources)."""
    v = values[np.isfinite(values)]
    if v.size == 0:
        return float("nan")
    return float(1.4826 * np.median(np.abs(v - np.median(v))))


def write_png(path: Path, image: np.ndarray, wcs: Any, beam: tuple[float, float, float],
              title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from xstack._atomic import atomic_output

    finite = image[np.isfinite(image)]
    rms = robust_rms(image)
    vmin = -3 * rms if np.isfinite(rms) else None
    vmax = float(np.max(finite)) if finite.size else None
    fig = plt.figure(figsize=(6.5, 6))
    ax = fig.add_subplot(projection=wcs)
    im = ax.imshow(image, origin="lower", cmap="inferno", vmin=vmin, vmax=vmax)
    ax.set_xlabel("RA (ICRS)")
    ax.set_ylabel("Dec (ICRS)")
    ax.set_title(f"{title}\nbeam {beam[0]:.2f}\" x {beam[1]:.2f}\", PA {beam[2]:.0f} deg")
    fig.colorbar(im, ax=ax, label="Jy/beam")
    with atomic_output(path, overwrite=True) as tmp:
        fig.savefig(tmp, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    from xstack._atomic import check_output
    from xstack.cli import emit_json
    from xstack.coords import parse_flux
    from xstack.imaging.clean import clean_data
    from xstack.imaging.image import make_image

    if not str(args.out).lower().endswith(".fits"):
        raise XstackError(f"{args.out}: output image name must end in .fits")
    if args.cube:
        return _run_cube(args)
    if args.channels != 1:
        raise XstackError("--channels needs --cube")
    for flag, given in (("--velocity-resolution", args.velocity_resolution),
                        ("--line-frequency", args.line_frequency), ("--frame", args.frame)):
        if given is not None:
            raise XstackError(f"{flag} needs --cube")
    names = output_names(args.out)
    if not args.png:
        names.pop("png")
    for path in names.values():  # fail before any work
        check_output(path, args.overwrite)
    if args.niter < 0:
        raise XstackError("--niter must be >= 0")
    threshold = parse_flux(args.threshold)
    common = dict(size=args.size, cell_arcsec=args.cell, weighting=args.weighting,
                  robust=args.robust, wterm=not args.no_wterm, pbcor=args.pbcor,
                  epsilon=args.epsilon, partitions=args.partition,
                  reproducible=not args.threaded_gridding,
                  progress=not args.no_progress, autocorrelations=args.autocorrelations)
    if args.pb_cutoff is not None and not 0 < args.pb_cutoff < 1:
        raise XstackError("--pb-cutoff must be between 0 and 1")
    if not path_exists(args.data):
        raise XstackError(f"{args.data}: no such store")
    mask = None
    if args.mask is not None:
        from xstack.imaging.fitsio import read_image

        mdata = read_image(args.mask)[0]
        if mdata.shape != (args.size, args.size):
            raise XstackError(f"{args.mask}: mask shape {mdata.shape} differs from the image "
                              f"({args.size}, {args.size})")
        mask = np.isfinite(mdata) & (mdata != 0)
    if args.niter > 0:
        result, cres = clean_data(with_data_group(args.data, args.data_group), niter=args.niter,
                                  threshold=threshold, gain=args.gain, algorithm=args.algorithm,
                                  mask=mask, **common)
        residual, model = cres.residual, cres.model
        n_components = cres.n_components
    else:
        result = make_image(with_data_group(args.data, args.data_group), pb_cutoff=args.pb_cutoff, **common)
        # the residual of a dirty image is the (primary-beam uncorrected) dirty image
        residual = result.extra.get("uncorrected", result.image)
        model = np.zeros_like(residual)
        n_components = 0
    # the beam first: the image and residual name it (XSPBFILE) and are written after it
    pb_name = names["pb"].name
    result.write(names["pb"], result.primary_beam, kind="pb", overwrite=args.overwrite)
    result.write(names["psf"], result.psf, kind="psf", overwrite=args.overwrite)
    result.write(names["residual"], residual, kind="residual", overwrite=args.overwrite,
                 pb_file=pb_name)
    result.write(names["model"], model, kind="model", overwrite=args.overwrite)
    result.write(names["image"], result.image, kind="image", overwrite=args.overwrite,
                 pb_file=pb_name)
    if args.png:
        write_png(names["png"], result.image, result.wcs, result.beam, Path(args.out).name)
    rms = robust_rms(residual)
    finite = result.image[np.isfinite(result.image)]
    peak = float(finite.max()) if finite.size else float("nan")
    if args.json:
        emit_json({
            "rms_jy_per_beam": rms, "peak_jy_per_beam": peak,
            "beam_arcsec": [result.beam[0], result.beam[1]], "beam_pa_deg": result.beam[2],
            "files": {k: str(v) for k, v in names.items()},
            "n_components": n_components, "sum_weights": result.sum_weights,
            "frequency_hz": result.frequency, "n_visibilities": result.n_visibilities,
            "partitions": list(result.partitions), "weighting": result.weighting,
            "cell_arcsec": result.cell_arcsec, "size": [result.image.shape[1], result.image.shape[0]],
            "n_pointings": int(result.header.get("XSMOSAIC", 1)),
            "pb_corrected": bool(result.header.get("XSPBCOR", False)),
        })
        return 0
    from xstack.cli._output import count, detail, figure
    from xstack.cli._output import result as say_result

    n_point = int(result.header.get("XSMOSAIC", 1))
    kind = ("restored image" if n_components else
            ("linear mosaic" if n_point > 1 else "dirty image"))
    pbcor = "primary-beam corrected" if result.header.get("XSPBCOR", False) else "not pb-corrected"
    say_result(f"wrote {names['image']}: {kind} {result.image.shape[1]} x {result.image.shape[0]}"
               f" px of {result.cell_arcsec:g} arcsec, {result.weighting} weighting, {pbcor}"
               + (f", {count(n_point, 'pointing')}" if n_point > 1 else "")
               + (f", {count(n_components, 'CLEAN component')}" if n_components else ""))
    say_result(f"  peak {figure(peak, unit='Jy/beam', like=[rms])}, residual rms "
               f"{figure(rms, unit='Jy/beam', like=[peak])}, beam {result.beam[0]:.2f} x "
               f"{result.beam[1]:.2f} arcsec, PA {result.beam[2]:.0f} deg")
    say_result("  beside it: " + ", ".join(str(v) for k, v in names.items() if k != "image"))
    detail(f"{count(result.n_visibilities, 'visibility')} from "
           f"{count(len(result.partitions), 'partition')} ({', '.join(result.partitions)}), "
           f"frequency {figure(result.frequency, unit='Hz')}")
    return 0


def _run_cube(args: argparse.Namespace) -> int:
    """``--cube``: a dirty cube streamed plane by plane to OUT.fits (xstack.imaging.cube)."""
    from xstack._atomic import check_output
    from xstack.cli import emit_json
    from xstack.imaging.cube import make_cube

    for flag, bad in (("--niter", args.niter > 0), ("--mask", args.mask is not None),
                      ("--png", args.png), ("--pb-cutoff", args.pb_cutoff is not None)):
        if bad:
            raise XstackError(f"{flag} does not go with --cube (cubes are dirty images of one "
                              "pointing)")
    if args.channels < 1:
        raise XstackError("--channels must be >= 1")
    velocity = args.velocity_resolution is not None
    if velocity != (args.line_frequency is not None):
        raise XstackError("--velocity-resolution and --line-frequency go together (a cube on a "
                          "velocity grid about the line's rest frequency)")
    if args.frame is not None and not velocity:
        raise XstackError("--frame needs --velocity-resolution and --line-frequency")
    if velocity and args.channels != 1:
        raise XstackError("--channels does not go with --velocity-resolution")
    if velocity and not args.velocity_resolution > 0:
        raise XstackError(f"--velocity-resolution must be > 0 km/s, got "
                          f"{args.velocity_resolution:g}")
    check_output(args.out, args.overwrite)
    if not path_exists(args.data):
        raise XstackError(f"{args.data}: no such store")
    cube = make_cube(with_data_group(args.data, args.data_group), size=args.size,
                     cell_arcsec=args.cell, channels=args.channels, weighting=args.weighting,
                     robust=args.robust, wterm=not args.no_wterm, pbcor=args.pbcor,
                     epsilon=args.epsilon, partitions=args.partition,
                     reproducible=not args.threaded_gridding,
                     progress=not args.no_progress, autocorrelations=args.autocorrelations,
                     out=args.out, overwrite=args.overwrite, keep=False,
                     velocity_resolution=args.velocity_resolution,
                     line_frequency=args.line_frequency, frame=args.frame or "lsrk")
    if args.json:
        emit_json({**cube.to_dict(), "files": {"image": str(args.out)},
                   "cell_arcsec": args.cell, "size": [args.size, args.size],
                   "weighting": args.weighting,
                   "pb_corrected": bool(cube.header.get("XSPBCOR", False))})
        return 0
    from xstack.cli._output import figure
    from xstack.cli._output import result as say_result

    f = cube.frequency_hz
    per = (f"{args.velocity_resolution:g} km/s each" if velocity else
           f"{args.channels} channel{'s' if args.channels > 1 else ''} each")
    say_result(f"wrote {args.out}: dirty cube of {f.size} planes ({per}), "
               f"{args.size} x {args.size} px of "
               f"{args.cell:g} arcsec, {figure(f[0], unit='Hz')} to {figure(f[-1], unit='Hz')} "
               f"({cube.frame}), {args.weighting} weighting")
    return 0
