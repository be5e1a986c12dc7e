"""``xstack fit``: fit a point or circular-Gaussian model to a stack (uv store or FITS stamp)."""

from __future__ import annotations

import argparse
from pathlib import Path

from xstack import _vocabulary as V
from xstack.cli._storage import add_storage_options, cli_path, path_exists
from xstack.errors import XstackError


def add_parser(subparsers) -> argparse.ArgumentParser:
    from xstack.cli import _types

    p = subparsers.add_parser(
        "fit", help="fit flux (and size) of a stacked source, uv- or image-domain",
        description="Fit a point or circular Gaussian model to a uv-stacked store (weighted "
                    "least squares on the visibilities) or to a stacked FITS stamp (Gaussian "
                    "convolved with the dirty beam plus a constant). Paper section 3.4.")
    p.add_argument("stacked", help="stacked store (.zarr, from xstack uvstack) or stamp (.fits, "
                                   "from xstack imstack)")
    p.add_argument("--model", choices=V.FIT_MODELS, default="point")
    p.add_argument("--uvmin", type=_types.uv_distance, metavar="DIST",
                   help=f"uv fit: minimum uv distance ({_types.DIST_HELP})")
    p.add_argument("--uvmax", type=_types.uv_distance, metavar="DIST",
                   help="uv fit: maximum uv distance (as --uvmin)")
    p.add_argument("--binned", action="store_true", help="uv fit: fit the binned uv-profile")
    p.add_argument("--nbins", type=int, default=30,
                   help="uv fit: bins for --binned and the --png uv-profile (30)")
    p.add_argument("--psf", help="image fit: dirty beam FITS (default: the stamp's PSF extension)")
    p.add_argument("--fit-radius", type=_types.angle_arcsec, metavar="ANGLE",
                   help=f"image fit: use pixels within this radius of the center "
                        f"({_types.ANGLE_HELP})")
    p.add_argument("--noise-correlation", choices=V.NOISE_CORRELATIONS, default="psf",
                   help="image fit: pixel-noise correlation used for the errors (psf)")
    p.add_argument("--png", metavar="PATH",
                   help="picture of the fit: uv-profile with the model curve (uv store) or "
                        "stamp / model / residual panels (FITS stamp)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --png")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    from xstack.cli._cluster import add_cluster_options

    add_cluster_options(p)
    add_storage_options(p)
    return p


def _is_fits(path: Path | str) -> bool:
    return (isinstance(path, Path) and path.is_file()
            and path.suffix.lower() in (".fits", ".fit", ".fts", ".gz"))


def run(args: argparse.Namespace) -> int:
    from xstack.cli import emit_json

    path = cli_path(args.stacked)  # a store URL stays a URL
    if not path_exists(path):
        raise XstackError(f"{path}: no such file or store")
    if args.png:
        from xstack._atomic import check_output

        check_output(args.png, args.overwrite)  # fail before the fit, not after it
        if args.nbins < 1:
            raise XstackError("--nbins must be >= 1")
    if _is_fits(path):
        if args.uvmin or args.uvmax or args.binned:
            raise XstackError("--uvmin/--uvmax/--binned apply to uv-stacked stores, not FITS stamps")
        from xstack.fit.imfit import fit_image

        res = fit_image(path, psf=args.psf, model=args.model, fit_radius_arcsec=args.fit_radius,
                        noise_correlation=args.noise_correlation)
    else:
        if args.psf or args.fit_radius is not None:
            raise XstackError("--psf/--fit-radius apply to FITS stamps, not uv stores")
        from xstack.fit.uvfit import fit_uv

        res = fit_uv(path, model=args.model, uvmin=args.uvmin, uvmax=args.uvmax,
                     binned=args.binned, nbins=args.nbins)
    out = res.to_dict()
    out["input"] = str(path)
    if args.png:
        if res.domain == "uv":
            from xstack.fit.plot import plot_uv_fit

            out["png"] = plot_uv_fit(path, res, args.png, bins=args.nbins, uvmin=args.uvmin,
                                     uvmax=args.uvmax, title=f"{path.name}: uv-domain "
                                     f"{res.model} fit", overwrite=args.overwrite)
        else:
            from xstack.fit.plot import plot_image_fit

            out["png"] = plot_image_fit(path, res, args.png, psf=args.psf,
                                        fit_radius_arcsec=args.fit_radius,
                                        title=f"{path.name}: image-domain {res.model} fit",
                                        overwrite=args.overwrite)
    if args.json:
        emit_json(out)
        return 0
    from xstack.cli._output import figure, result

    result(f"{res.domain}-domain {res.model} fit of {path}")
    result(f"  flux      = {figure(res.flux_jy, res.flux_err_jy, 'Jy')}")
    if res.model == "gaussian":
        result(f"  FWHM      = {figure(res.fwhm_arcsec, res.fwhm_err_arcsec, 'arcsec')} "
               f"({'resolved' if res.resolved else 'unresolved'}; 95% upper limit "
               f"{figure(res.fwhm_upper_limit_arcsec, unit='arcsec')})")
    if "background_jy_per_beam" in res.extra:
        bg = figure(res.extra["background_jy_per_beam"], res.extra["background_err_jy_per_beam"],
                    "Jy/beam")
        result(f"  constant  = {bg}")
    what = "visibilities" if res.domain == "uv" else "pixels"
    result(f"  chi2/dof  = {res.chi2_reduced:.4g} ({res.n_data:,} {what})")
    if args.png:
        result(f"  picture   = {out['png']}")
    return 0
