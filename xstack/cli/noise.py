"""``xstack noise``: noise and bias of a stack (analytic, Monte Carlo, random, bootstrap)."""

from __future__ import annotations

import argparse
import warnings

from xstack import _vocabulary as V
from xstack.cli._data import add_data_group, with_data_group
from xstack.cli._storage import add_storage_options, cli_path
from xstack.errors import XstackError


def add_parser(subparsers) -> argparse.ArgumentParser:
    from xstack.cli import _types

    p = subparsers.add_parser(
        "noise", help="estimate the noise and bias of a uv-stack",
        description="Noise and bias of the uv-stacked flux at the catalog positions (paper "
                    "section 3.5): analytic (eq. 6), mc (inject fake sources of the targets' "
                    "flux and number at random positions into the residual data and stack, R "
                    "times, all in one pass over the data), random (stack R sets of random "
                    "empty positions) or bootstrap (resample the targets).")
    p.add_argument("data", help="(residual) visibilities, xstack store (.zarr); or a residual "
                                "image (.fits) for image-domain estimates")
    p.add_argument("catalog", help="target catalog (ra, dec [deg], optional flux [Jy], weight)")
    p.add_argument("--method", choices=V.NOISE_METHODS, default="mc")
    p.add_argument("--realizations", type=int, default=100, help="number of realisations (100)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--flux", type=_types.flux_jy, metavar="FLUX",
                   help=f"mc: injected flux ({_types.FLUX_HELP}); default: catalog flux column, "
                        "else the stacked target flux")
    p.add_argument("--min-separation", type=_types.separation_arcsec, metavar="ANGLE",
                   help="random positions: minimum distance to targets, --avoid sources and "
                        f"each other ({_types.ANGLE_HELP}; default: 3 synthesized beams)")
    p.add_argument("--avoid", help="catalog of further positions to avoid (bright sources)")
    p.add_argument("--weighting", choices=V.NOISE_WEIGHTINGS, default="pb")
    p.add_argument("--primary-beam", choices=V.NOISE_PRIMARY_BEAMS, default="auto")
    p.add_argument("--pb-cutoff", type=float, default=V.DEFAULT_PB_CUTOFF)
    p.add_argument("--uvmin", type=_types.uv_distance, metavar="DIST",
                   help=f"minimum uv distance ({_types.DIST_HELP})")
    p.add_argument("--uvmax", type=_types.uv_distance, metavar="DIST",
                   help="maximum uv distance (as --uvmin)")
    p.add_argument("--field-radius", type=_types.angle_arcsec, metavar="ANGLE",
                   help=f"radius around each pointing for random positions ({_types.ANGLE_HELP}; "
                        "default: the beam cutoff; --region applies as well)")
    p.add_argument("--region", default="hull", metavar="hull|beam|POLYGON|MASK.fits",
                   help="mc/random: where random positions go, inside the beams: hull (default: "
                        "the targets' footprint, convex hulls of their groups grown by half "
                        "their typical spacing), beam (the whole beam), a polygon file "
                        "(ECSV/CSV, ra dec vertices in deg) or a FITS mask (nonzero = inside)")
    p.add_argument("--psf", help="image domain: dirty beam FITS for --method mc "
                                 "(default: X.psf.fits beside the image)")
    p.add_argument("--engine", choices=V.NOISE_ENGINES, default="auto",
                   help="uv domain: per-antenna phasors where the UVW allow it (auto), always "
                   "(antenna: an error where they do not) or per-row phasors (row)")
    p.add_argument("--png", help="histogram of the realisations (PNG)")
    p.add_argument("--profile-png", help="uv-profiles of the realisations (PNG; mc/random)")
    p.add_argument("--profile-bins", type=int, default=20)
    p.add_argument("--table", help="per-realisation values (ECSV)")
    p.add_argument("--image-corrected", choices=("yes", "no"), default=None,
                   help="image domain: whether the image is primary-beam corrected (default: "
                        "its header's XSPBCOR); an uncorrected image is divided by its beam")
    g = p.add_argument_group(
        "line stacks", "with --line-frequency: the noise of the uv line stack per velocity bin "
        "(--method random: the targets at random positions with redshifts drawn from theirs; "
        "mc: Gaussian lines injected there and recovered; bootstrap); see docs/linestack.md")
    from xstack.cli.linestack import line_frequency, velocity_pair

    g.add_argument("--line-frequency", type=line_frequency, default=None, metavar="F",
                   help="rest frequency of the line (HI, CO(1-0), 1420.405751786MHz, ...)")
    g.add_argument("--velocity-resolution", type=_types.velocity_kms, default=20.0,
                   metavar="V", help="velocity bin width (20km/s)")
    g.add_argument("--velocity-range", type=velocity_pair, default=(-600.0, 600.0),
                   metavar="A,B", help="velocity range about each line (-600,600km/s)")
    g.add_argument("--frame", choices=V.LINE_FRAMES, default="lsrk",
                   help="frame of the catalog's redshifts (TOPO data are converted)")
    g.add_argument("--line-flux", dest="line_flux_jy_kms", type=_types.line_flux_jy_kms,
                   default=None, metavar="F", help="mc: integrated flux of the injected lines "
                   "(0.2Jy km/s, 200mJy km/s; a plain number is Jy km/s; default: the "
                   "catalog's line_flux_jy_kms column)")
    g.add_argument("--line-fwhm", dest="line_fwhm_kms", type=_types.velocity_kms, default=None,
                   metavar="V", help="mc: FWHM of the injected lines (default: the catalog's "
                   "line_fwhm_kms column)")
    g.add_argument("--redshifts", choices=V.REDSHIFT_DRAWS, default="permute",
                   help="random/mc: the targets' redshifts permuted (default) or resampled")
    p.add_argument("--autocorrelations", action="store_true",
                   help="include autocorrelations (default: left out; they measure system "
                        "power, not the sky)")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--no-progress", action="store_true")
    add_data_group(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    from xstack.cli._cluster import add_cluster_options

    add_cluster_options(p)
    add_storage_options(p)
    return p


def run(args: argparse.Namespace) -> int:
    import sys

    from xstack._atomic import atomic_output, check_output
    from xstack.cli import emit_json
    from xstack.noise.estimate import estimate_noise

    for out in (args.png, args.profile_png, args.table):
        if out:
            check_output(out, args.overwrite)
    if args.profile_png and args.method not in ("mc", "random"):
        raise XstackError("--profile-png needs --method mc or random")
    if args.realizations < 2 and args.method != "analytic":
        raise XstackError(f"need at least 2 realisations to estimate a scatter, got {args.realizations}")
    data = cli_path(args.data)  # a store URL stays a URL
    if args.line_frequency is not None:
        return _run_line(args, data)
    domain = "image" if str(data).lower().endswith((".fits", ".fit", ".fts")) else "uv"
    if domain == "image" and args.profile_png:
        raise XstackError("--profile-png needs visibilities (a .zarr store), not an image")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", UserWarning)
        res = estimate_noise(
            data if domain == "image" else with_data_group(data, args.data_group), args.catalog,
            domain=domain, psf=args.psf, method=args.method,
            realizations=args.realizations,
            flux=args.flux, min_separation_arcsec=args.min_separation, avoid=args.avoid,
            seed=args.seed, weighting=args.weighting,
            primary_beam=(("auto" if domain == "image" else None) if args.primary_beam == "auto"
                          else args.primary_beam),
            pb_cutoff=args.pb_cutoff, uvmin=args.uvmin, uvmax=args.uvmax,
            field_radius_arcsec=args.field_radius, engine=args.engine,
            profile_bins=args.profile_bins if args.profile_png else 0,
            progress=not args.no_progress and sys.stderr.isatty(), region=args.region,
            image_corrected=None if args.image_corrected is None else args.image_corrected == "yes",
            autocorrelations=args.autocorrelations)
    from xstack.cli._output import count, figure, result

    for w in caught:
        if issubclass(w.category, UserWarning):  # through the CLI's printer: names the flag
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    files = {}
    if args.png and res.realizations >= 2:
        from xstack.noise.plot import plot_histogram

        files["png"] = str(plot_histogram(res, args.png, overwrite=args.overwrite))
    if args.profile_png:
        from xstack.noise.plot import plot_profiles

        files["profile_png"] = str(plot_profiles(res, args.profile_png, overwrite=args.overwrite))
    if args.table:
        with atomic_output(args.table, overwrite=args.overwrite) as tmp:
            res.table().write(str(tmp), format="ascii.ecsv")
        files["table"] = str(args.table)
    out = res.to_dict()
    out.update(files)
    if args.json:
        emit_json(out)
        return 0
    keys = ("noise_empirical_jy", "optimal_noise_jy")
    like = [res.noise_jy, res.bias_jy, res.target_flux_jy, *(res.extra.get(k) for k in keys)]

    def jy(value: float | None) -> str:
        return figure(value, unit="Jy", like=like)

    result(f"noise estimate ({res.method}, {count(res.realizations, 'realisation')}, "
           f"{count(res.n_positions, 'position')})")
    result(f"  noise  = {jy(res.noise_jy)}")
    if "noise_empirical_jy" in res.extra:
        result(f"  noise from the visibilities' own scatter = {jy(res.extra['noise_empirical_jy'])}")
    if "optimal_noise_jy" in res.extra:
        result(f"  (optimal inverse-variance weights would give {jy(res.extra['optimal_noise_jy'])})")
    if res.bias_jy is not None:
        result(f"  bias   = {jy(res.bias_jy)}")
    if res.target_flux_jy is not None:
        result(f"  target stack = {jy(res.target_flux_jy)}")
    if "region" in res.extra:
        result(f"  region: {res.extra['region']}")
    for k, v in files.items():
        result(f"  {k}: {v}")
    return 0


def _run_line(args: argparse.Namespace, data) -> int:
    """``xstack noise DATA CATALOG --line-frequency F``: the line stack's noise per bin."""
    import sys

    import numpy as np

    from xstack._atomic import atomic_output
    from xstack.cli import emit_json
    from xstack.cli._output import figure, result
    from xstack.noise.line import estimate_line_noise, plot_line_noise

    if str(data).lower().endswith((".fits", ".fit", ".fts")):
        raise XstackError("--line-frequency needs visibilities (a .zarr store): the image-domain "
                          "line noise is not available yet")
    if args.profile_png:
        raise XstackError("--profile-png is for continuum stacks, not with --line-frequency")
    if args.method == "analytic":
        raise XstackError("--method analytic with --line-frequency: the analytic per-bin error "
                          "is xstack linestack's flux_err_jy; use random, mc or bootstrap")
    res = estimate_line_noise(
        with_data_group(data, args.data_group), args.catalog,
        line_frequency=args.line_frequency, method=args.method, realizations=args.realizations,
        seed=args.seed, redshifts=args.redshifts, line_flux_jy_kms=args.line_flux_jy_kms,
        line_fwhm_kms=args.line_fwhm_kms, min_separation_arcsec=args.min_separation,
        avoid=args.avoid, region=args.region, field_radius_arcsec=args.field_radius,
        velocity_resolution=args.velocity_resolution, velocity_range=args.velocity_range,
        frame=args.frame, weighting=args.weighting, primary_beam=args.primary_beam,
        pb_cutoff=args.pb_cutoff, uvmin=args.uvmin, uvmax=args.uvmax,
        progress=not args.no_progress and sys.stderr.isatty())
    files = {}
    if args.png:
        files["png"] = str(plot_line_noise(res, args.png, overwrite=args.overwrite))
    if args.table:
        with atomic_output(args.table, overwrite=args.overwrite) as tmp:
            res.table().write(str(tmp), format="ascii.ecsv")
        files["table"] = str(args.table)
    out = res.to_dict()
    out.update(files)
    if args.json:
        emit_json(out)
        return 0
    like = list(res.noise_jy[np.isfinite(res.noise_jy)])
    result(f"line noise estimate ({res.method}, {res.realizations} realisations, "
           f"{res.n_positions} positions per realisation)")
    result("  velocity [km/s]   noise            bias")
    for v, n, b in zip(res.velocity_kms, res.noise_jy, res.bias_jy):
        result(f"  {v:10.1f}   {figure(n, unit='Jy', like=like):>14}   "
               f"{figure(b, unit='Jy', like=like):>14}")
    if "region" in res.extra:
        result(f"  region: {res.extra['region']}")
    for k, v in files.items():
        result(f"  {k}: {v}")
    return 0
