"""Run the paper's procedure over Monte Carlo realisations: :func:`reproduce`.

One realisation of data-set type N with seed r is the full chain with the public API:
``preset_scene("paper-N", scale)`` → ``simulate(seed=r)`` → image and CLEAN the bright
sources to the paper's threshold → subtract the CLEAN model → ``stack_uv`` (with the paper's
uv cut) and ``stack_images`` on the targets → for type 7 ``fit_uv`` and ``fit_image``
(Gaussian; the image fit convolved with the stacked PSF) → ``estimate_noise(method="analytic")``.
The ALMA mosaics (8-10) are CLEANed and subtracted one pointing at a time
(:func:`clean_subtract_mosaic`) and uv-stacked over all pointings together; type 9's
pointings are image-stacked from one image each, types 8 and 10 from their linear mosaic
(:func:`residual_images`).

One JSON line per realisation (fluxes in Jy, times in s): ``seed``, ``type``, ``scale``,
``procedure`` (the :class:`~xstack.reproduce.paper.Procedure` used), ``true_flux_jy`` (mean
injected target flux), ``n_targets``, ``uv_flux_jy`` and ``image_flux_jy`` (the numbers of
Table 2: the stacked fluxes, for type 7 those of the fits), ``uv_stack_flux_jy``,
``uv_stack_flux_err_jy``, ``image_stack_flux_jy``, ``image_stack_flux_err_jy``,
``expected_noise_jy``, ``clean_components``, ``clean_peak_residual_jy``, ``profile``
(``re_jy`` and ``sum_weight`` on :data:`PROFILE_EDGES_KLAMBDA`), ``seconds``; type 7 adds
``{uv,image}_fit_flux_jy``, ``{uv,image}_fwhm_arcsec`` (None when a fit failed, with
``{uv,image}_fit_error``). ``image_stack_flux_err_jy`` is the paper's expected noise
(:data:`MAP_NOISE_KEY`), ``expected_noise_jy`` the thermal one. Added later (older lines
lack them; readers treat a missing key as absent):

* ``pointings`` (types 8-10): the number of pointings CLEANed one by one.
* ``uv_flux_subsets_jy`` (types 5 and 6, :data:`SUBSET_TYPES`): ``{"N": flux}``, the
  uv-stacked flux of the first N targets of the catalog, N from :func:`subset_sizes`
  (10, 30, 100, 300, ... and all; nested subsets of the same residual data): Fig. 1, noise
  against the number of targets. ``"<n_targets>"`` is ``uv_flux_jy`` itself.
* ``image_flux_filtered_jy`` (types with a uv cut, 5-7 and 11): the image-stacked flux with the
  §5.3 uv-plane filter at the cut (``filter_lowfreq="5000m"``): Fig. 12. With
  ``image_filter_response`` (added later) it is the filtered peak divided by that response
  (``ImstackResult.filter_response``), a flux density; older lines hold the filtered peak.
* ``image_flux_subpixel_jy`` (every type but 7): the image-stacked flux of the same maps
  with the stamps aligned by a Fourier shift (``subpixel="fourier"``) instead of to the
  nearest pixel: how much of image-stacking's deficit is pixelisation.

Resumable: every finished realisation appends one JSON line to
``OUTDIR/type{N}/realizations.jsonl`` (then flush and fsync); a new run reads the valid lines
made with the same scale and procedure, ignores a truncated last line and runs only the
missing seeds. Intermediate stores live in a
temporary directory ``OUTDIR/type{N}/seed{r}-*`` removed after each realisation, also when
the run is interrupted (Ctrl-C, SIGTERM); one found when a run starts (a run killed outright,
or one going on now in the same outdir) gets a warning naming it and its size. The first
realisation also keeps ``profile_seed{r}.npz`` (uv-profile) and ``stamp_seed{r}.npz``
(stacked image stamp ``stamp``, its ``psf``, ``pixel_arcsec``; for type 7 also
``stamp_filtered``, the stamp with the uv-plane filter) for figures.

Time per realisation of the ALMA mosaics at scale 0.05 with the paper's procedures (10
targets, 3 integrations per pointing; 2 cores shared with other work, load ~5): type 8
(22 pointings) 46 s, type 9 (10 pointings) 23 s, type 10 (22 pointings) 37 s.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
import warnings
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from xstack._atomic import discard
from xstack._result import Result, json_ready
from xstack.errors import OptionError, WeightsWarning, XstackError, XstackWarning
from xstack.reproduce.paper import PROCEDURES, TYPES, Procedure, paper_row

#: Types whose procedure the runner implements: all eleven (the ALMA mosaics 8-10 CLEANed per
#: pointing, see :func:`clean_subtract_mosaic`).
SUPPORTED_TYPES = tuple(range(1, 12))

#: The realisation line's field that holds the paper's "expected noise" (Table 2's caption:
#: its eq. 9 with sigma_k "calculated from the cleaned residual map"): the image stack's
#: noise propagated from the stamps' local sigma_k and the weights (eq. 5; eq. 9 for
#: W_k = 1/sigma_k^2, as the VLA types use). ``expected_noise_jy`` is instead the uv stack's
#: thermal noise from the visibility weights, which knows nothing of CLEAN's residuals.
MAP_NOISE_KEY = "image_stack_flux_err_jy"

#: Types whose records carry ``uv_flux_subsets_jy`` (Fig. 1: noise against number of targets).
SUBSET_TYPES = (5, 6)

#: The nested subsets of ``uv_flux_subsets_jy``: the first N targets, N = 10, 30, 100, 300, ...
#: below the number of targets, and all of them.
def subset_sizes(n_targets: int) -> list[int]:
    """``[10, 30, 100, 300, ...]`` below ``n_targets``, then ``n_targets`` itself."""
    sizes, k = [], 0
    while True:
        n = (10, 30)[k % 2] * 10 ** (k // 2)
        if n >= n_targets:
            return [*sizes, int(n_targets)]
        sizes.append(n)
        k += 1

JSONL = "realizations.jsonl"

#: uv-profile bin edges of every realisation (kilo-wavelengths): 36 km of VLA A at 1.4 GHz is
#: 170 klambda; 5000 m (the paper's cut) is 23.3 klambda, a bin edge near 24.
PROFILE_EDGES_KLAMBDA = np.linspace(0.0, 180.0, 31)


@dataclass(kw_only=True)
class TypeSummary(Result):
    """The realisations of one data-set type summarised beside the paper's row."""

    type: int
    realizations: int
    scale: float
    true_flux_jy: float
    uv_flux_mean_jy: float
    uv_flux_scatter_jy: float
    image_flux_mean_jy: float
    image_flux_scatter_jy: float
    expected_noise_jy: float
    expected_map_noise_jy: float
    paper: dict[str, Any]
    seconds: float
    seconds_per_realization: float
    wall_seconds: float = 0.0
    sizes: dict[str, Any] | None = None
    records: list[dict[str, Any]] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict[str, Any]:
        d = {k: getattr(self, k) for k in (
            "type", "realizations", "scale", "true_flux_jy", "uv_flux_mean_jy",
            "uv_flux_scatter_jy", "image_flux_mean_jy", "image_flux_scatter_jy",
            "expected_noise_jy", "expected_map_noise_jy", "paper", "seconds",
            "seconds_per_realization",
            "wall_seconds")}
        if self.sizes is not None:
            d["sizes"] = self.sizes
        return json_ready(d)


@dataclass(kw_only=True)
class ReproduceResult(Result):
    """Result of :func:`reproduce`: one :class:`TypeSummary` per data-set type."""

    types: list[TypeSummary]
    outdir: Path

    def to_dict(self) -> dict[str, Any]:
        return {"types": [t.to_dict() for t in self.types]}

    def table(self) -> Any:
        """One row per type: its numbers and the paper's (``paper.*``), units from the names."""
        from astropy.table import vstack

        from xstack._result import summary_table

        if not self.types:
            return summary_table({})
        return vstack([summary_table(t.to_dict()) for t in self.types])


def parse_types(types: int | str | Iterable[int | str]) -> list[int]:
    """``3``, ``"3"``, ``"all"`` or a list of them -> sorted list of supported type numbers."""
    if isinstance(types, (int, str)):
        types = [types]
    out: set[int] = set()
    for t in types:
        if str(t).lower() == "all":
            out.update(SUPPORTED_TYPES)
            continue
        try:
            n = int(t)
        except ValueError:
            raise OptionError(f"unknown data-set type {t!r} (1-11 or all)", option="types") from None
        if n not in TYPES:
            raise OptionError(f"unknown data-set type {n} (1-11 or all)", option="types")
        out.add(n)
    return sorted(out)


#: CLEAN never goes below this many times the thermal noise (below it, it cleans noise).
CLEAN_FLOOR_SIGMA = 5.0


def clean_threshold(proc: Procedure, scale: float) -> float:
    """The CLEAN threshold at ``scale``: the paper's, but at least
    :data:`CLEAN_FLOOR_SIGMA` times the thermal noise, which grows as 1/sqrt(scale).

    At scale 1 this is the paper's threshold (5 x 2.1 µJy is below every VLA threshold).
    Scaling the threshold with the noise instead would leave bright sources the paper
    CLEANs (e.g. 150 µJy ones in type 7 at scale 0.05) in the residual.
    """
    return max(proc.clean_threshold_jy,
               CLEAN_FLOOR_SIGMA * proc.thermal_noise_jy / math.sqrt(scale))


def scene_digest(n: int, scale: float) -> str:
    """:meth:`~xstack.sim.scene.Scene.digest` of the scene type ``n`` simulates at ``scale``."""
    import xstack

    return xstack.preset_scene(f"paper-{n}", scale=scale).digest()


def run_realization(n: int, seed: int, scale: float, workdir: str | os.PathLike,
                    keep_figures: bool = False, procedure: Procedure | None = None,
                    scene: Any = None) -> dict[str, Any]:
    """One realisation of type ``n`` with ``seed``: the paper's chain; returns its record.

    Intermediate stores and images are written to a temporary directory inside ``workdir``
    that is removed on return. With ``keep_figures`` the uv-profile and the stacked stamp are
    kept in ``workdir`` as ``profile_seed{seed}.npz`` and ``stamp_seed{seed}.npz``.
    ``procedure`` replaces the paper's (:data:`~xstack.reproduce.paper.PROCEDURES`);
    ``scene`` (a :class:`~xstack.sim.scene.Scene`, already scaled) replaces the preset's, e.g.
    to run the same chain on the type's sky without one of its ingredients (its noise, its
    bright sources: ``benchmarks/diagnose_sky_effects.py``).
    """
    import xstack

    t0 = time.perf_counter()
    proc = procedure or PROCEDURES[n]
    workdir = Path(workdir)
    tmp = Path(tempfile.mkdtemp(prefix=f"seed{seed}-", dir=workdir))
    try:
        if scene is None:
            scene = xstack.preset_scene(f"paper-{n}", scale=scale)
        sim = xstack.simulate(scene, tmp / "sim.zarr", seed=seed)
        targets = sim.catalogs["targets"]
        true_flux = float(np.mean(np.asarray(targets["flux"], dtype=float)))
        threshold = clean_threshold(proc, scale)
        residual: Any
        if proc.mosaic:
            residual, clean_stats = clean_subtract_mosaic(sim.store, proc, threshold, tmp)
        else:
            residual, clean_stats = clean_subtract(sim.store, proc, threshold, tmp)
        uvmin = proc.uvmin_m
        # the residual map(s): image-stacked, and the local noise sigma_k of both stacks' weights
        maps = residual_images(residual, proc, tmp)
        uv_options = {"weighting": proc.uv_weighting, "uvmin": uvmin,
                      "noise_image": maps[0][0] if proc.uv_weighting == "sigma2" else None}
        uv = xstack.stack_uv(residual, targets, out=tmp / "stacked.zarr", **uv_options)

        def image_stack(**kw: Any) -> Any:
            # a mosaic's targets near its edge may lie outside every map (as stack_uv leaves
            # out positions in no pointing); one pointing's image covers all its targets
            return xstack.stack_images([m for m, _ in maps], targets,
                                       weighting=proc.image_weighting,
                                       noise_estimator=proc.image_noise_estimator,
                                       psf=[p for _, p in maps], plot=False,
                                       skip_outside=bool(proc.mosaic), **kw)

        ims = image_stack()
        noise_targets, noise_weighting = _stack_weighting(uv, targets, proc)
        noise = xstack.estimate_noise(residual, noise_targets, method="analytic", uvmin=uvmin,
                                      **noise_weighting)
        rec: dict[str, Any] = {
            "seed": seed, "true_flux_jy": true_flux, "n_targets": len(targets),
            "uv_stack_flux_jy": uv.flux_jy, "uv_stack_flux_err_jy": uv.flux_err_jy,
            "image_stack_flux_jy": ims.flux_jy, "image_stack_flux_err_jy": ims.flux_err_jy,
            "expected_noise_jy": noise.noise_jy, **clean_stats,
        }
        if not proc.fit_size:
            # the paper's pixelisation loss of image-stacking (types 1-2, §4.1.1-4.1.2) is
            # from aligning stamps to the nearest pixel; the same maps aligned by a Fourier
            # shift show how much of the image-stacked deficit it explains
            rec["image_flux_subpixel_jy"] = image_stack(subpixel="fourier").flux_jy
        ims_filtered = None
        if uvmin is not None:
            # Fig. 12: the stacked stamp with the paper's uv-plane filter at the uv cut (§5.3)
            ims_filtered = image_stack(filter_lowfreq=f"{uvmin:g}m")
            rec["image_flux_filtered_jy"] = ims_filtered.flux_jy
            # the filtered flux is the filtered peak divided by this (the stacked PSF's
            # filtered / unfiltered peak); records without it hold the bare filtered peak
            rec["image_filter_response"] = ims_filtered.filter_response
        if n in SUBSET_TYPES:
            # Fig. 1: the same residual data stacked on the first N targets (nested subsets)
            subsets = {}
            for size in subset_sizes(len(targets)):
                if size == len(targets):
                    subsets[str(size)] = uv.flux_jy
                    continue
                with warnings.catch_warnings():
                    # the subsets are of the same residual data as the full stack above,
                    # whose weights-against-scatter warning said it once (a batch log showed
                    # it again for every subset, 4 more near-identical lines per realisation)
                    warnings.simplefilter("ignore", WeightsWarning)
                    sub = xstack.stack_uv(residual, targets[:size], **uv_options)
                subsets[str(size)] = sub.flux_jy
            rec["uv_flux_subsets_jy"] = subsets
        # every realisation's uv-profile on the same bins, so figures can average them
        # (paper Figs 5, 7: the mean over realisations, the error its scatter / sqrt(R))
        prof = xstack.uv_profile(tmp / "stacked.zarr", bins=PROFILE_EDGES_KLAMBDA)
        rec["profile"] = {"re_jy": np.asarray(prof["re_jy"]),
                          "sum_weight": np.asarray(prof["sum_weight"])}
        if proc.fit_size:
            fits = {
                "uv": lambda: xstack.fit_uv(tmp / "stacked.zarr", model="gaussian", uvmin=uvmin),
                # the PSF stamp as a DataArray: its attrs say it holds the nearest-pixel
                # smear, whose peak (< 1) the fit keeps (until 2026-12-07 an array, divided
                # by its peak: the image fit 2.6 % low, noiseless)
                "image": lambda: xstack.fit_image(np.asarray(ims.stacked.values),
                                                  psf=ims.psf_stamp,
                                                  pixel_arcsec=ims.pixel_arcsec,
                                                  model="gaussian")}
            for domain, fit in fits.items():
                try:
                    f = fit()
                    flux, fwhm = f.flux_jy, f.fwhm_arcsec
                except XstackError as exc:
                    # a noisy realisation the Gaussian cannot describe (e.g. a negative
                    # flux): recorded as missing with the reason, the run goes on
                    flux = fwhm = None
                    rec[f"{domain}_fit_error"] = str(exc)
                rec[f"{domain}_fit_flux_jy"], rec[f"{domain}_fwhm_arcsec"] = flux, fwhm
                # the paper's type-7 fluxes are those of the fits (§4.1.7)
                rec[f"{domain}_flux_jy"] = flux
        else:
            rec["uv_flux_jy"], rec["image_flux_jy"] = uv.flux_jy, ims.flux_jy
        if keep_figures:
            np.savez_compressed(workdir / f"profile_seed{seed}.npz",
                                **{c: np.asarray(prof[c]) for c in prof.colnames})
            stamp = ims.stacked
            extra = {} if ims_filtered is None or not proc.fit_size else {
                "stamp_filtered": np.asarray(ims_filtered.stacked.values)}
            np.savez_compressed(workdir / f"stamp_seed{seed}.npz",
                                stamp=np.asarray(stamp.values),
                                psf=np.asarray(ims.psf_stamp.values)
                                if ims.psf_stamp is not None else np.zeros(0),
                                pixel_arcsec=np.asarray(ims.pixel_arcsec, dtype=float),
                                **extra)
        rec["seconds"] = time.perf_counter() - t0
        return json_ready(rec)
    except BaseException:
        discard(tmp)  # interrupted: its threads may still write into it
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _stack_weighting(uv: Any, targets: Any, proc: Procedure) -> tuple[Any, dict[str, str]]:
    """The targets and noise weighting that give ``estimate_noise`` the position weights
    W_k the uv-stack used.

    With ``sigma2`` weights on one pointing, W_k = 1/sigma_k^2 from the residual map: the
    stack's own W_k (``uv.positions["weight_used"]``) are passed as a ``weight`` column, so the
    expected noise is the analytic noise of the estimator that made the flux (eq. 9 with
    these weights), not of the A^2-weighted one. Other weightings are passed by name.
    """
    if proc.uv_weighting != "sigma2":
        return targets, {"weighting": proc.uv_weighting}
    w = np.asarray(uv.positions["weight_used"], dtype=np.float64)
    if w.ndim == 2:
        # one pointing: every partition (spectral window) weighs a position alike
        w = w.max(axis=1)
    weighted = targets.copy()
    weighted["weight"] = w
    return weighted, {"weighting": "column"}


def _pointing_names(store: Any) -> list[list[str]]:
    """The partition names of each pointing of ``store`` (partitions sharing a phase center)."""
    from xstack._inputs import partitions
    from xstack.imaging.image import group_pointings

    return [[name for name, _ in members] for _, members in group_pointings(partitions(store))]


def clean_subtract(store: Any, proc: Procedure, threshold: float, tmp: Path
                   ) -> tuple[Path, dict[str, Any]]:
    """CLEAN one pointing's bright sources to ``threshold`` (Jy/beam) and subtract the model
    from its visibilities: ``tmp/model.fits`` and the residual store ``tmp/residual.zarr``.

    Returns the residual store's path and ``clean_components``, ``clean_peak_residual_jy``.
    Clark minor cycles: Hogbom's O(npix) per component is too slow on the 4000 x 4000 images
    of the wide-field types.
    """
    import xstack
    from xstack.imaging.clean import clean_data

    img, cres = clean_data(store, size=proc.size, cell_arcsec=proc.cell_arcsec, niter=100_000,
                           threshold=threshold, algorithm="clark", epsilon=proc.epsilon)
    img.write(tmp / "model.fits", cres.model, kind="model")
    xstack.subtract(store, tmp / "model.fits", tmp / "residual.zarr")
    return tmp / "residual.zarr", {"clean_components": cres.n_components,
                                   "clean_peak_residual_jy": cres.peak_residual}


def clean_subtract_mosaic(store: Path, proc: Procedure, threshold: float, tmp: Path
                          ) -> tuple[dict[str, Any], dict[str, Any]]:
    """CLEAN each pointing of a mosaic on its own and subtract its model from its own
    partitions (one residual store per pointing in ``tmp``).

    Each pointing is imaged (``proc.pointing_size`` or ``proc.size`` pixels about its phase
    center) and CLEANed to ``threshold``; its CLEAN model is the sky as that pointing sees it
    (attenuated by its own primary beam), so it is subtracted from that pointing's
    visibilities only (:func:`xstack.subtract` wants a model centered on the data's phase
    center). This is the paper's procedure for type 9 (§2.3.2). For the contiguous mosaics 8
    and 10 the paper CLEANs the mosaic jointly (CASA's mosaic gridding, §2.3.1); xstack's
    CLEAN works on one pointing at a time (a joint CLEAN needs a mosaic PSF per position),
    so each pointing is CLEANed on its own data: a source in the overlap of pointings is
    CLEANed in each of them, against a single pointing's noise (sqrt(2-3) higher than the
    mosaic's where pointings overlap), and removed from each pointing's visibilities with
    that pointing's beam -- exact for the subtraction, only the depth differs.

    Returns
    -------
    residual : dict
        Partition name -> residual Dataset of every pointing (lazy, from the stores in
        ``tmp``): one data set for the stages, not copied into one store.
    stats : dict
        ``clean_components`` (summed over pointings), ``clean_peak_residual_jy`` (the
        largest), ``pointings`` (their number).
    """
    import xstack
    from xstack._inputs import partitions
    from xstack.imaging.clean import clean_data

    # the store is opened once: opening it costs ~1 s, a type-8 mosaic has 22 pointings
    parts = dict(partitions(store))
    residual: dict[str, Any] = {}
    n_comp, peak = 0, 0.0
    groups = _pointing_names(parts)
    for i, names in enumerate(groups):
        mine = {n: parts[n] for n in names}
        img, cres = clean_data(mine, size=proc.pointing_size or proc.size,
                               cell_arcsec=proc.cell_arcsec, niter=100_000, threshold=threshold,
                               algorithm="clark", epsilon=proc.epsilon)
        model = tmp / f"model_p{i}.fits"
        img.write(model, cres.model, kind="model")
        part_out = xstack.subtract(mine, model, tmp / f"residual_p{i}.zarr")
        residual.update(partitions(part_out))
        n_comp += cres.n_components
        peak = max(peak, cres.peak_residual)
    return residual, {"clean_components": n_comp, "clean_peak_residual_jy": peak,
                      "pointings": len(groups)}


def residual_images(residual: Any, proc: Procedure, tmp: Path) -> list[tuple[Path, Path]]:
    """The primary-beam corrected residual map(s) to image-stack, with their PSFs:
    ``[(image.fits, psf.fits), ...]``.

    One image of all the data (one pointing, or a linear mosaic of a contiguous mosaic's
    pointings, types 8 and 10); for ``mosaic="pointings"`` (type 9, §2.3.2) one image per
    pointing, ``proc.size`` pixels about its phase center.
    """
    import xstack
    from xstack._inputs import partitions

    if proc.mosaic == "pointings":
        parts = dict(partitions(residual))
        groups = [{n: parts[n] for n in names} for names in _pointing_names(parts)]
    else:
        groups = [residual]
    maps = []
    for i, data in enumerate(groups):
        stem = "residual" if len(groups) == 1 else f"residual_p{i}"
        image = xstack.make_image(data, size=proc.size, cell_arcsec=proc.cell_arcsec,
                                  pbcor=True, epsilon=proc.epsilon)
        image.write_with_pb(tmp / f"{stem}.fits")
        image.write(tmp / f"{stem}.psf.fits", image.psf, kind="psf")
        maps.append((tmp / f"{stem}.fits", tmp / f"{stem}.psf.fits"))
    return maps


#: The fields that say how a realisation line was made: a resumed run reuses, and the report
#: shows, only lines that agree on all of them.
MADE_BY = ("scale", "procedure", "scene_sha256")


def made_the_same_way(record: dict[str, Any], reference: dict[str, Any]) -> bool:
    """Whether ``record`` was made at the scale, with the procedure and from the scene of
    ``reference`` (the :data:`MADE_BY` fields)."""
    return all(record.get(key) == reference.get(key) for key in MADE_BY)


def made_differently(record: dict[str, Any], reference: dict[str, Any]) -> str:
    """What ``record`` was made with that ``reference`` is not, in words ("" if nothing):
    the scale, the procedure's changed fields (``name old -> new``), or the scene."""
    parts = []
    if record.get("scale") != reference.get("scale"):
        parts.append(f"scale {record.get('scale')} -> {reference.get('scale')}")
    old, new = record.get("procedure") or {}, reference.get("procedure") or {}
    if old != new:
        changed = [f"{k} {old.get(k, 'unset')} -> {new.get(k, 'unset')}"
                   for k in sorted(set(old) | set(new)) if old.get(k) != new.get(k)]
        # a line, not a page: the first three, then how many more
        more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
        parts.append("procedure " + ", ".join(changed[:3]) + more)
    if record.get("scene_sha256") != reference.get("scene_sha256"):
        parts.append("another scene (the preset has changed)")
    return "; ".join(parts)


def _warn_not_reused(n: int, path: Path, on_file: list[dict[str, Any]],
                     made_by: dict[str, Any], missing: Sequence[int]) -> None:
    """One line when earlier lines of seeds about to run were made another way: they are kept
    in the file but not reused, so those realisations run again (possibly hours)."""
    rerun = sorted({int(r["seed"]) for r in on_file if int(r["seed"]) in set(missing)
                    and not made_the_same_way(r, made_by)})
    if not rerun:
        return
    why = made_differently(next(r for r in on_file if int(r["seed"]) == rerun[0]
                                and not made_the_same_way(r, made_by)), made_by)
    seeds = ", ".join(map(str, rerun[:5])) + (", ..." if len(rerun) > 5 else "")
    warnings.warn(XstackWarning(
        f"type {n}: {len(rerun)} earlier realisation(s) in {path} (seeds {seeds}) were made "
        f"with {why}: they are run again, the old lines kept beside the new; use another "
        f"outdir to keep the runs apart", option="outdir"), stacklevel=3)


def read_records(path: Path) -> list[dict[str, Any]]:
    """The valid JSON lines of ``path`` (a truncated or damaged line is skipped)."""
    if not path.exists():
        return []
    records = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue  # an interrupted write: that realisation runs again
        if isinstance(rec, dict) and "seed" in rec:
            records.append(rec)
    return records


def _append(path: Path, rec: dict[str, Any]) -> None:
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(rec, allow_nan=False) + "\n")
        f.flush()
        os.fsync(f.fileno())


def _stale_workdirs(workdir: Path) -> list[Path]:
    """Work directories of realisations (``seed{r}-*``) left in ``workdir``: a run ends by
    removing its own (also on Ctrl-C and SIGTERM), so one found before a run starts is that
    of a run killed outright (SIGKILL, out of memory, a lost node) or of a run going on now."""
    return sorted(p for p in workdir.glob("seed*-*") if p.is_dir())


def _size_bytes(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def _warn_stale(workdir: Path) -> None:
    stale = _stale_workdirs(workdir)
    if not stale:
        return
    size = sum(_size_bytes(p) for p in stale)
    names = ", ".join(p.name for p in stale[:3]) + (", ..." if len(stale) > 3 else "")
    warnings.warn(XstackWarning(
        f"{workdir}: {len(stale)} work director{'y' if len(stale) == 1 else 'ies'} of a "
        f"killed or still running realisation ({names}; {size / 1e9:.2g} GB): remove "
        f"{'it' if len(stale) == 1 else 'them'} unless another run uses this outdir",
        option="outdir"), stacklevel=3)


def _repair(path: Path, records: list[dict[str, Any]]) -> None:
    """Rewrite ``path`` with only the valid records when it holds a broken line, so that new
    lines are never appended after a partial one."""
    if not path.exists():
        return
    text = path.read_text(encoding="utf-8")
    if text and (not text.endswith("\n") or len(text.splitlines()) != len(records)):
        tmp = path.with_suffix(".tmp")
        tmp.write_text("".join(json.dumps(r) + "\n" for r in records), encoding="utf-8")
        os.replace(tmp, path)


def _std(values: Sequence[float]) -> float:
    v = np.asarray([x for x in values if x is not None], dtype=float)
    return float(np.std(v, ddof=1)) if v.size > 1 else float("nan")


def _mean(values: Sequence[float | None]) -> float:
    v = np.asarray([x for x in values if x is not None], dtype=float)
    return float(np.mean(v)) if v.size else float("nan")


def summarize(n: int, records: list[dict[str, Any]], scale: float, seconds: float
              ) -> TypeSummary:
    """Mean and scatter (standard deviation, ddof=1) over the realisations, as Table 2.

    ``seconds`` is the computing time of the realisations (the sum of their own times, also
    of those an earlier run did); ``wall_seconds`` what this run took.
    """
    col = lambda k: [r.get(k) for r in records]  # noqa: E731
    sizes = None
    if PROCEDURES[n].fit_size:
        sizes = {"uv_fits_failed": sum(r.get("uv_fwhm_arcsec") is None for r in records),
                 "image_fits_failed": sum(r.get("image_fwhm_arcsec") is None for r in records),
                 "uv_fwhm_mean_arcsec": _mean(col("uv_fwhm_arcsec")),
                 "uv_fwhm_scatter_arcsec": _std(col("uv_fwhm_arcsec")),
                 "image_fwhm_mean_arcsec": _mean(col("image_fwhm_arcsec")),
                 "image_fwhm_scatter_arcsec": _std(col("image_fwhm_arcsec"))}
    times = [x for x in col("seconds") if x is not None]
    return TypeSummary(
        type=n, realizations=len(records), scale=scale,
        true_flux_jy=_mean(col("true_flux_jy")),
        uv_flux_mean_jy=_mean(col("uv_flux_jy")), uv_flux_scatter_jy=_std(col("uv_flux_jy")),
        image_flux_mean_jy=_mean(col("image_flux_jy")),
        image_flux_scatter_jy=_std(col("image_flux_jy")),
        expected_noise_jy=_mean(col("expected_noise_jy")),
        expected_map_noise_jy=_mean(col(MAP_NOISE_KEY)), paper=paper_row(n),
        seconds=float(sum(times)), seconds_per_realization=_mean(times), wall_seconds=seconds,
        sizes=sizes, records=records)


def _results(n: int, seeds: list[int], scale: float, workdir: Path, keep: bool,
             proc: Procedure | None, client: Any) -> Iterable[dict[str, Any]]:
    """Records of the realisations ``seeds`` as they finish: in this process one after the
    other, or as one task each on ``client``'s cluster (in the order they complete)."""
    if client is None:
        for i, seed in enumerate(seeds):
            yield run_realization(n, seed, scale, workdir, keep and i == 0, proc)
        return
    from distributed import as_completed

    futures = [client.submit(run_realization, n, seed, scale, str(workdir), keep and i == 0,
                             proc, pure=False) for i, seed in enumerate(seeds)]
    for fut in as_completed(futures):
        yield fut.result()


def _make_workdir(outdir: Path, workdir: Path) -> None:
    """Create a type's directory under ``outdir``, or say in one line why it cannot be."""
    for path in (outdir, workdir):
        if path.exists() and not path.is_dir():
            raise OptionError(f"{path} exists and is not a directory: give another outdir",
                              option="outdir")
    try:
        workdir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OptionError(f"cannot create {workdir}: {exc.strerror or exc}",
                          option="outdir") from None


def reproduce(types: int | str | Iterable[int | str], *, realizations: int = 100,
              scale: float = 1.0, outdir: str | os.PathLike = "xstack-reproduce",
              progress: bool = False, client: Any = None,
              on_type: Callable[[TypeSummary], None] | None = None,
              on_realization: Callable[[dict[str, Any], int, int], None] | None = None,
              procedures: dict[int, Procedure] | None = None) -> ReproduceResult:
    """Reproduce the paper's Table 2 for data-set ``types`` over Monte Carlo realisations.

    Parameters
    ----------
    types
        A type number 1-11, ``"all"`` (the supported types), or a list of them.
    realizations
        Number of realisations per type (seeds 0 … R-1); the paper used 100. Seed s of two
        types whose presets differ only in the imaging or in one property of a population
        (1 and 2, 3 and 4, 5 and 6) simulates the same observation (same noise and, where the
        populations agree, the same sources): their results are paired, not independent.
    scale
        Scale of the presets in (0, 1]: observing time and large populations times
        ``scale`` (:func:`xstack.preset_scene`); the CLEAN threshold is the paper's but
        never below 5 times the (scaled) thermal noise (:func:`clean_threshold`).
    outdir
        Directory of ``type{N}/realizations.jsonl`` (one JSON line per realisation) and the
        figure data; an earlier run's lines are reused (only missing seeds run) if they were
        made at the same scale, with the same procedure and from the same scene
        (``scene_sha256``, :meth:`~xstack.sim.scene.Scene.digest`).
    progress
        Progress bar over realisations on stderr.
    client
        A ``dask.distributed.Client``: realisations run as tasks on its cluster (one task
        each), their lines appended as they complete.
    on_type
        Called with each type's summary as soon as the type is done.
    on_realization
        Called as ``on_realization(line, k, m)`` with each new realisation's line as soon
        as it is appended, the k-th of the m this call runs for its type.
    procedures
        Per type, a :class:`~xstack.reproduce.paper.Procedure` that replaces the paper's
        (e.g. a smaller image for a quick check); the default is the paper's.

    Returns
    -------
    ReproduceResult
        ``to_dict()`` -> ``{"types": [{"type", "realizations", "scale", "true_flux_jy",
        "uv_flux_mean_jy", "uv_flux_scatter_jy", "image_flux_mean_jy",
        "image_flux_scatter_jy", "expected_noise_jy", "expected_map_noise_jy", "paper",
        "seconds", ...}]}`` (fluxes in Jy; ``expected_noise_jy`` thermal, from the visibility
        weights, ``expected_map_noise_jy`` the paper's eq. 9 from the residual map; type 7
        adds ``sizes``).

    Raises
    ------
    OptionError
        Unknown or unsupported type, realizations < 1, scale outside (0, 1].
    """
    from xstack._progress import progress_iter

    numbers = parse_types(types)
    if int(realizations) < 1:
        raise OptionError(f"realizations must be >= 1, got {realizations}", option="realizations")
    if not 0 < float(scale) <= 1:
        raise OptionError(f"scale must be in (0, 1], got {scale}", option="scale")
    outdir = Path(outdir)
    summaries = []
    for n in numbers:
        t0 = time.perf_counter()
        workdir = outdir / f"type{n}"
        _make_workdir(outdir, workdir)
        _warn_stale(workdir)
        path = workdir / JSONL
        proc = (procedures or {}).get(n)
        used = json_ready((proc or PROCEDURES[n]).to_dict())
        scene = scene_digest(n, float(scale))
        # an earlier realisation counts only if it was made the same way, from the same scene
        # (a record of a preset since changed, e.g. before the presets flagged, is rerun)
        made_by = {"scale": float(scale), "procedure": used, "scene_sha256": scene}
        on_file = read_records(path)
        _repair(path, on_file)
        records = [r for r in on_file if made_the_same_way(r, made_by)]
        done = {int(r["seed"]) for r in records}
        missing = [s for s in range(int(realizations)) if s not in done]
        _warn_not_reused(n, path, on_file, made_by, missing)
        keep = not any(workdir.glob("profile_seed*.npz"))
        # a bar (or its silent stand-in) advanced by hand: results arrive out of order
        bar = progress_iter(range(len(missing)), f"type {n}", enabled=progress,
                            total=len(missing))

        for k, rec in enumerate(_results(n, missing, float(scale), workdir, keep, proc,
                                         client), start=1):
            rec = dict(rec, type=n, **made_by)
            _append(path, rec)
            records.append(rec)
            if on_realization is not None:
                on_realization(rec, k, len(missing))
            if hasattr(bar, "update"):
                bar.update(1)
        if hasattr(bar, "close"):
            bar.close()
        # one record per seed (the first; a seed run twice, e.g. by two runs at once, counts once)
        by_seed: dict[int, dict[str, Any]] = {}
        for r in records:
            by_seed.setdefault(int(r["seed"]), r)
        wanted = [by_seed[s] for s in sorted(by_seed) if s < int(realizations)]
        summary = summarize(n, wanted, float(scale), time.perf_counter() - t0)
        summaries.append(summary)
        if on_type is not None:
            on_type(summary)
    return ReproduceResult(types=summaries, outdir=outdir)
