"""Simulate a scene into an xstack store, lazily, as dask tasks over (time, baseline) chunks.

Steps (each runs only when the scene asks for it; :attr:`SimulationResult.steps_run` lists
the ones in the graph and :func:`xstack.sim.kernels.record_steps` counts those executed):

``model``         equation 1 for the sources of each pointing (kernel :mod:`xstack.sim.kernels`)
``phase``         off-center sources (point sources at the phase center need no phasors)
``w_term``        ``effects.w_term``
``extent``        Gaussian sources (a population with ``shape.kind = "gaussian"``)
``primary_beam``  ``effects.primary_beam`` (per channel and pointing, :mod:`xstack.beams`)
``noise``         ``effects.noise`` (random numbers are drawn only here and in flagging)
``bandwidth_smearing``, ``time_smearing``  ``effects.bandwidth_smearing`` / ``time_smearing``
                  (channel / integration averages, :mod:`xstack.smearing`)
``flag_random``, ``flag_shadow``, ``flag_elevation``  ``effects.flagging``

Reproducibility: the catalog of population i is drawn from ``SeedSequence(seed,
spawn_key=(1, i))``; the noise of integration t of pointing p from ``SeedSequence(seed,
spawn_key=(2, p, t))`` and its random flags from ``(3, p, t)``, each for the full set of
baselines, so the data are the same bit for bit whatever the chunking or the number of
dask workers.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import dask
import dask.array as da
import numpy as np
import xarray as xr
from astropy.table import Table

from xstack._result import Result
from xstack._select import parallel_hand_mask
from xstack.beams import PrimaryBeam, standard_beam
from xstack.coords import SPEED_OF_LIGHT, angular_separation, lm_to_radec, radec_to_lmn
from xstack.errors import XstackError
from xstack.schema import baseline_pairs, new_partition, partition_name, write_store
from xstack.sim import arrays as arr
from xstack.sim import kernels
from xstack.sim.scene import FlaggingSpec, Scene, angle_pair, load_scene

ARCSEC = math.pi / (180.0 * 3600.0)
BOLTZMANN = 1.380649e-23
#: Target bytes of one VISIBILITY chunk (complex128 work arrays are twice that).
CHUNK_BYTES = 32 * 1024**2
#: Rounds of redrawing the sources of a random population that fall outside every pointing.
_MAX_REDRAWS = 200


@dataclass(kw_only=True)
class SimulationResult(Result):
    """What :func:`simulate` wrote.

    Attributes
    ----------
    store
        The ``.zarr`` store.
    catalogs
        True source list of each population (astropy Tables: ra, dec in deg, flux in Jy,
        fwhm_arcsec for Gaussian sources, pointing).
    catalog_paths
        ECSV file of each population, ``OUT.<population>.ecsv``.
    steps_run
        The simulation steps in the graph (see the module docstring).
    n_visibilities
        Number of complex visibilities written (all polarizations).
    """

    store: Path
    catalogs: dict[str, Table]
    catalog_paths: dict[str, Path]
    steps_run: frozenset[str] = frozenset()
    n_visibilities: int = 0
    seed: int = 0
    scale: float = 1.0
    pointings: list[tuple[float, float]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary: the store, catalogs (paths and source counts), steps, seed,
        scale and pointing centers (deg)."""
        return {"store": str(self.store), "seed": int(self.seed), "scale": float(self.scale),
                "n_visibilities": int(self.n_visibilities), "steps_run": sorted(self.steps_run),
                "catalogs": {name: {"path": str(self.catalog_paths.get(name, "")),
                                    "n_sources": len(table)}
                             for name, table in self.catalogs.items()},
                "pointings_deg": [[math.degrees(a), math.degrees(d)] for a, d in self.pointings]}


@dataclass
class _Plan:
    scene: Scene
    array: arr.AntennaArray
    freq: np.ndarray
    width: np.ndarray
    pols: list[str]
    pointings: np.ndarray  # (np, 2) rad
    times: list[np.ndarray]  # per pointing, MJD seconds
    catalogs: dict[str, Table]
    ra: np.ndarray  # all sources, rad
    dec: np.ndarray
    flux: np.ndarray
    fwhm: np.ndarray  # rad, 0 for points
    beam: PrimaryBeam | None  # None: no primary-beam step
    sigma: np.ndarray | None  # (nbl, nchan) Jy, None: no noise
    steps: set[str]
    lines: dict[str, Any] | None = None  # the line sources (_line_sources), None: no lines


def _seed_rng(seed: int, *key: int) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(int(seed), spawn_key=key)))


def _array(scene: Scene) -> arr.AntennaArray:
    a = scene.array
    if a.positions:
        pos = np.asarray(a.positions, dtype=float)
        names = list(a.names) or [f"A{i:02d}" for i in range(len(pos))]
        out = arr.AntennaArray(a.telescope, names, pos, np.asarray(a.diameters, float),
                               "scene", pos.mean(axis=0))
    elif a.config.lower().removesuffix(".cfg") in arr.PACKAGED:
        out = arr.packaged_array(a.config)
    else:
        out = arr.read_cfg(a.config)
    if a.antennas:
        out = out.subset(list(a.antennas))
    return out


def _grid_offsets(mode: str, size: list[float], spacing: float) -> np.ndarray:
    """(x, y) offsets (arcsec) of a mosaic grid strictly inside the size box, centered."""
    w, h = size
    pts = []
    if mode == "rectangular":
        nx = int(math.floor(w / spacing + 1e-9)) + 1
        ny = int(math.floor(h / spacing + 1e-9)) + 1
        for j in range(ny):
            for i in range(nx):
                pts.append(((i - (nx - 1) / 2) * spacing, (j - (ny - 1) / 2) * spacing))
        return np.array(pts)
    # hexagonal: rows sqrt(3)/2 spacing apart; the central row is offset by half a spacing
    dy = spacing * math.sqrt(3.0) / 2.0
    kmax = int(math.ceil(h / 2 / dy)) + 1
    for k in range(-kmax, kmax + 1):
        y = k * dy
        if not abs(y) < h / 2 - 1e-9:
            continue
        off = 0.5 * spacing if k % 2 == 0 else 0.0
        imax = int(math.ceil(w / 2 / spacing)) + 1
        for i in range(-imax - 1, imax + 1):
            x = i * spacing + off
            if abs(x) < w / 2 - 1e-9:
                pts.append((x, y))
    return np.array(sorted(pts, key=lambda p: (p[1], p[0])))


def _offsets_to_radec(x_arcsec: np.ndarray, y_arcsec: np.ndarray,
                      center: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    return lm_to_radec(np.asarray(x_arcsec) * ARCSEC, np.asarray(y_arcsec) * ARCSEC,
                       center[0], center[1])


def _draw_population(i: int, scene: Scene, seed: int, pointings: np.ndarray | None,
                     center: tuple[float, float], covered: Any = None) -> dict[str, np.ndarray]:
    """Positions, fluxes and sizes of population ``i``.

    ``covered(ra, dec) -> bool array``: where a source can be observed (inside some pointing's
    primary beam). Random positions (``box``, ``disc``) are drawn uniformly inside the region
    AND the coverage: a source that falls outside every pointing is drawn again from the same
    generator, so a seed whose first draw is covered gives the same sources as before.
    """
    q = scene.populations[i]
    rng = _seed_rng(seed, 1, i)
    n = q.count
    pos = q.positions
    c = tuple(np.radians(angle_pair(pos.center, f"populations[{i}].positions.center"))) \
        if pos.center else center
    if pos.kind == "list":
        ra, dec = np.radians(np.asarray(pos.ra, float)), np.radians(np.asarray(pos.dec, float))
    elif pos.kind in ("box", "disc"):
        if pos.kind == "box":
            w, h = pos.size_arcsec

            def draw(k: int) -> tuple[np.ndarray, np.ndarray]:
                return _offsets_to_radec(rng.uniform(-w / 2, w / 2, k), rng.uniform(-h / 2, h / 2, k), c)
        else:
            def draw(k: int) -> tuple[np.ndarray, np.ndarray]:
                r = pos.radius_arcsec * np.sqrt(rng.uniform(size=k))
                phi = rng.uniform(0, 2 * np.pi, k)
                return _offsets_to_radec(r * np.sin(phi), r * np.cos(phi), c)
        ra, dec = (np.atleast_1d(np.asarray(a, float)) for a in draw(n))
        if covered is not None and n:
            ok = covered(ra, dec)
            for _ in range(_MAX_REDRAWS):
                if ok.all():
                    break
                bad = np.flatnonzero(~ok)
                ra[bad], dec[bad] = draw(bad.size)
                ok[bad] = covered(ra[bad], dec[bad])
            else:
                raise XstackError(
                    f"populations[{i}].positions: the {pos.kind} hardly overlaps the pointings "
                    f"({int((~ok).sum())} of {n} sources still outside every pointing after "
                    f"{_MAX_REDRAWS} redraws): move or shrink it, or add pointings")
    else:  # around_pointings: a disc around a randomly chosen pointing (always covered)
        assert pointings is not None
        r = pos.radius_arcsec * np.sqrt(rng.uniform(size=n))
        phi = rng.uniform(0, 2 * np.pi, n)
        x, y = r * np.sin(phi), r * np.cos(phi)
        which = rng.integers(0, len(pointings), n)
        ra, dec = np.empty(n), np.empty(n)
        for k in range(n):
            ra[k], dec[k] = _offsets_to_radec(x[k], y[k], tuple(pointings[which[k]]))
    flux = q.flux.sample(n, rng)
    if q.shape.kind == "gaussian":
        f = q.shape.fwhm_arcsec
        fwhm = np.full(n, f[0]) if len(f) == 1 or f[0] == f[-1] else rng.uniform(f[0], f[-1], n)
    else:
        fwhm = np.zeros(n)
    out = {"ra": np.asarray(ra, float), "dec": np.asarray(dec, float), "flux": flux,
           "fwhm_arcsec": fwhm}
    if q.line is not None:
        out.update(_draw_line(q, rng, scene))
    return out


def _draw_line(q: Any, rng: np.random.Generator, scene: Scene) -> dict[str, np.ndarray]:
    """Line parameters of a population's sources (drawn after everything else)."""
    from xstack.spectral import observed_line_centre, rest_frequency

    ln, n = q.line, q.count

    def value(pair: list[float]) -> np.ndarray:
        return (np.full(n, float(pair[0])) if len(pair) == 1 or pair[0] == pair[-1]
                else rng.uniform(pair[0], pair[-1], n))

    line_flux, line_fwhm = value(ln.flux_jy_kms), value(ln.fwhm_kms)
    rest = rest_frequency(scene.spectral.line)
    if ln.centre_hz:
        centre = np.asarray(ln.centre_hz[:n], float)
        z = rest / centre - 1.0
    else:
        z = value(ln.z) if ln.z else np.asarray(ln.z_values[:n], float)
        centre = observed_line_centre(rest, z)
    return {"z": np.asarray(z, float), "line_flux": line_flux, "line_fwhm": line_fwhm,
            "line_centre": np.asarray(centre, float)}


def _times(scene: Scene, n_pointings: int, ra0: float, longitude: float) -> list[np.ndarray]:
    from astropy.time import Time

    o = scene.observation
    dt = float(o.integration)
    n_int = max(1, int(round(o.time_per_pointing / dt)))
    track = (o.hour_angle[1] - o.hour_angle[0]) * 3600.0 / arr.SIDEREAL_RATE
    per_track = max(1, int(math.floor(track / dt + 1e-9)))
    total = n_int * n_pointings
    offset = 0.5 * (track - total * dt) if total <= per_track else 0.0
    date = Time(o.date, scale="utc").mjd
    t0 = arr.time_of_hour_angle(math.radians(o.hour_angle[0] * 15.0), ra0, longitude,
                                math.floor(date))
    sidereal_day = arr.SECONDS_PER_DAY / arr.SIDEREAL_RATE
    j = np.arange(total)
    day, within = np.divmod(j, per_track)
    t = t0 + day * sidereal_day + offset + (within + 0.5) * dt
    return [t[p * n_int:(p + 1) * n_int] for p in range(n_pointings)]


def _plan(scene: Scene, seed: int, scale: float) -> _Plan:
    scene = load_scene(scene).scaled(scale)
    array = _array(scene)
    freq, width = scene.spectral.frequencies()
    steps: set[str] = set()
    center = tuple(np.radians(angle_pair(scene.pointings.center, "pointings.center")))
    telescope = array.telescope
    dish = float(np.mean(array.diameters))
    check_beam = standard_beam(telescope, dish, cutoff=scene.effects.pb_cutoff)

    # populations and pointings (the population defining the pointings goes first)
    pm = scene.pointings
    drawn: dict[int, dict[str, np.ndarray]] = {}
    names = [q.name for q in scene.populations]
    if pm.mode == "single":
        pointings = np.array([center])
    elif pm.mode in ("hexagonal", "rectangular"):
        off = _grid_offsets(pm.mode, pm.size_arcsec, pm.spacing_arcsec)
        pointings = np.column_stack(_offsets_to_radec(off[:, 0], off[:, 1], center))
    elif pm.mode == "list":
        pointings = np.radians(np.asarray(pm.positions, float))
    else:
        k = names.index(pm.population)
        drawn[k] = _draw_population(k, scene, seed, None, center)
        pointings = np.column_stack([drawn[k]["ra"], drawn[k]["dec"]])
        if len(pointings) == 0:
            raise XstackError(f"pointings.population: population {pm.population!r} is empty")
    def covered(ra: np.ndarray, dec: np.ndarray) -> np.ndarray:
        sep = angular_separation(ra[:, None], dec[:, None], pointings[None, :, 0],
                                 pointings[None, :, 1])
        return check_beam(sep, scene.spectral.center).max(axis=1) >= scene.effects.pb_cutoff

    for i in range(len(scene.populations)):
        if i not in drawn:
            drawn[i] = _draw_population(i, scene, seed, pointings, center, covered)

    # every source must be inside some pointing (standard beam, center frequency)
    fc = scene.spectral.center
    catalogs: dict[str, Table] = {}
    for i, q in enumerate(scene.populations):
        d = drawn[i]
        sep = angular_separation(d["ra"][:, None], d["dec"][:, None],
                                 pointings[None, :, 0], pointings[None, :, 1])
        resp = check_beam(sep, fc) if d["ra"].size else np.zeros((0, len(pointings)))
        best = resp.argmax(axis=1) if d["ra"].size else np.zeros(0, int)
        outside = resp.max(axis=1, initial=0.0) < scene.effects.pb_cutoff
        if outside.any():
            raise XstackError(
                f"populations[{i}].positions: {int(outside.sum())} of {q.count} sources of "
                f"{q.name!r} lie outside every pointing (primary-beam response below "
                f"{scene.effects.pb_cutoff} at {fc / 1e9:g} GHz)")
        cols = {"ra": np.degrees(d["ra"]) % 360.0, "dec": np.degrees(d["dec"]),
                "flux": d["flux"]}
        if q.shape.kind == "gaussian":
            cols["fwhm_arcsec"] = d["fwhm_arcsec"]
        cols["pointing"] = best.astype(np.int64)
        if q.line is not None:
            cols.update({"z": d["z"], "freq": d["line_centre"],
                         "line_flux_jy_kms": d["line_flux"], "line_fwhm_kms": d["line_fwhm"]})
        t = Table(cols)
        t["ra"].unit, t["dec"].unit, t["flux"].unit = "deg", "deg", "Jy"
        if "fwhm_arcsec" in t.colnames:
            t["fwhm_arcsec"].unit = "arcsec"
        t.meta.update({"population": q.name, "flux_distribution": q.flux.kind})
        if q.line is not None:
            from xstack.spectral import rest_frequency

            t["freq"].unit, t["line_flux_jy_kms"].unit = "Hz", "Jy km / s"
            t["line_fwhm_kms"].unit = "km / s"
            t.meta.update({"line_rest_frequency_hz": rest_frequency(scene.spectral.line),
                           "line_frame": str(scene.spectral.line_frame or "lsrk").upper(),
                           "line_profile": q.line.profile})
        catalogs[q.name] = t

    def cat(key: str) -> np.ndarray:
        return np.concatenate([drawn[i][key] for i in range(len(scene.populations))] or
                              [np.zeros(0)])

    ra, dec, flux, fwhm = cat("ra"), cat("dec"), cat("flux"), cat("fwhm_arcsec") * ARCSEC

    e = scene.effects
    beam = None
    if e.primary_beam != "none":
        beam = {"auto": lambda: standard_beam(telescope, dish, cutoff=e.pb_cutoff),
                "airy": lambda: PrimaryBeam("airy", dish, 0.0, e.pb_cutoff),
                "gaussian": lambda: PrimaryBeam("gaussian", dish, 0.0, e.pb_cutoff)
                }[e.primary_beam]()
    a1, _ = baseline_pairs(array.n_antennas)
    sigma = None
    if e.noise is not None:
        sigma = _noise_sigma(e.noise, array, width, float(scene.observation.integration))
    lon, _, _ = arr.geodetic(array.site)
    times = _times(scene, len(pointings), float(pointings[0, 0]), lon)

    if np.any(flux != 0):
        steps.add("model")
        if np.any(fwhm > 0):
            steps.add("extent")
        if beam is not None:
            steps.add("primary_beam")
        if e.w_term:
            steps.add("w_term")
        off_center = np.ones(flux.size, bool)
        if len(pointings) == 1:
            off_center = (ra != pointings[0, 0]) | (dec != pointings[0, 1])
        if np.any(off_center & (flux != 0)):
            steps.add("phase")
            # smearing factors are 1 for sources at the phase center: only with phases
            if e.bandwidth_smearing:
                steps.add("bandwidth_smearing")
            if e.time_smearing:
                steps.add("time_smearing")
    lines = _line_sources(scene, drawn, array)
    if lines is not None:
        steps.add("line")
        if beam is not None:
            steps.add("primary_beam")
        if e.w_term:
            steps.add("w_term")
        if np.any(lines["fwhm"] > 0):
            steps.add("extent")
        if len(pointings) > 1 or np.any((lines["ra"] != pointings[0, 0])
                                        | (lines["dec"] != pointings[0, 1])):
            steps.add("phase")
            if e.bandwidth_smearing:
                steps.add("bandwidth_smearing")
            if e.time_smearing:
                steps.add("time_smearing")
    if sigma is not None:
        steps.add("noise")
    if e.flagging is not None:
        if e.flagging.random_fraction > 0:
            steps.add("flag_random")
        if e.flagging.shadowing:
            steps.add("flag_shadow")
        if e.flagging.elevation_limit_deg is not None:
            steps.add("flag_elevation")
    return _Plan(scene, array, freq, width, list(scene.spectral.polarizations), pointings,
                 times, catalogs, ra, dec, flux, fwhm, beam, sigma, steps, lines)


def _line_sources(scene: Scene, drawn: dict[int, dict[str, np.ndarray]],
                  array: arr.AntennaArray) -> dict[str, Any] | None:
    """The sources with a line (non-zero line flux), or None when the scene has none."""
    from xstack.frames import frame_name

    keys = ("ra", "dec", "fwhm_arcsec", "line_centre", "line_flux", "line_fwhm")
    parts: dict[str, list[np.ndarray]] = {k: [] for k in (*keys, "profile")}
    for i, q in enumerate(scene.populations):
        if q.line is None:
            continue
        d = drawn[i]
        for k in keys:
            parts[k].append(np.asarray(d[k], float))
        parts["profile"].append(np.full(d["ra"].size, q.line.profile, dtype=object))
    if not parts["ra"]:
        return None
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    keep = cat["line_flux"] != 0
    if not keep.any():
        return None
    s = scene.spectral
    return {"ra": cat["ra"][keep], "dec": cat["dec"][keep],
            "fwhm": cat["fwhm_arcsec"][keep] * ARCSEC, "centre": cat["line_centre"][keep],
            "flux": cat["line_flux"][keep], "fwhm_kms": cat["line_fwhm"][keep],
            "profile": cat["profile"][keep],
            "channel_frame": frame_name(s.frame) if s.frame is not None else "TOPO",
            # the array centre, as the line stack (xstack.uvstack.line) takes it from a store
            "line_frame": frame_name(s.line_frame or "lsrk"),
            "site": np.asarray(array.positions, np.float64).mean(axis=0)}


def _noise_sigma(n: Any, array: arr.AntennaArray, width: np.ndarray, tau: float) -> np.ndarray:
    """(nbl, nchan) sigma (Jy) of the real and of the imaginary part of one visibility."""
    a1, a2 = baseline_pairs(array.n_antennas)
    if n.sigma is not None:
        return np.full((a1.size, width.size), float(n.sigma))
    if n.sefd is not None:
        sefd = np.full(array.n_antennas, float(n.sefd))
    else:
        area = np.pi * (array.diameters / 2.0) ** 2
        sefd = 2.0 * BOLTZMANN * n.tsys / (n.aperture_efficiency * area) * 1e26
    s_bl = np.sqrt(sefd[a1] * sefd[a2])
    return s_bl[:, None] / (n.efficiency * np.sqrt(2.0 * width[None, :] * tau))


# ----------------------------------------------------------------------- chunk functions

def _parallel_hands(pols: list[str]) -> np.ndarray:
    return parallel_hand_mask(pols)


def _vis_block(dummy: np.ndarray, *, ctx: dict[str, Any], block_info: Any = None) -> np.ndarray:
    (t0, t1), (b0, b1) = block_info[0]["array-location"][:2]
    a1, a2 = ctx["a1"][b0:b1], ctx["a2"][b0:b1]
    nt, nb = t1 - t0, b1 - b0
    nchan, npol = ctx["freq"].size, len(ctx["pols"])
    out = np.zeros((nt, nb, nchan, npol), dtype=np.complex128)
    if ctx["flux"].size:
        ant = arr.antenna_uvw(ctx["positions"], ctx["times"][t0:t1], *ctx["center"])
        # per-antenna phasors: one sincos pair per antenna (not per baseline) and source
        model = kernels.model_visibilities_antenna(
            ant, a1, a2, ctx["freq"], ctx["l"], ctx["m"], ctx["nm1"], ctx["flux"], ctx["att"],
            ctx["fwhm"] if ctx["extended"].any() else None, parallel=False,
            channel_width=ctx["smear_width"], integration_time=ctx["smear_time"],
            dec0=ctx["center"][1])
        out[..., ctx["parallel"]] = model[..., None]
    if ctx.get("lines") is not None:
        _add_lines(out, ctx, t0, t1, b0, b1)
    sigma = ctx["sigma"]
    if sigma is not None:
        kernels._count("noise")
        nbl_all = ctx["a1"].size
        for k, ti in enumerate(range(t0, t1)):
            z = _seed_rng(ctx["seed"], 2, ctx["pointing"], ti).standard_normal(
                (nbl_all, nchan, npol, 2))[b0:b1]
            out[k] += sigma[b0:b1, :, None] * (z[..., 0] + 1j * z[..., 1])
    return out.astype(ctx["dtype"], copy=False)


def _add_lines(out: np.ndarray, ctx: dict[str, Any], t0: int, t1: int, b0: int, b1: int
               ) -> None:
    """Add the line sources' visibilities to ``out`` (time, baseline, channel, pol).

    Each group of sources is evaluated on the channels its lines reach only. The profile of
    a channel is its average over the channel's edges converted to the lines' frame: once
    for the block when the channels are in that frame, per integration otherwise (the
    Doppler track of TOPO channels).
    """
    ln = ctx["lines"]
    kernels._count("line")
    a1, a2 = ctx["a1"][b0:b1], ctx["a2"][b0:b1]
    ant = arr.antenna_uvw(ctx["positions"], ctx["times"][t0:t1], *ctx["center"])
    freq, lo, hi = ctx["freq"], ln["lo"], ln["hi"]
    par = ctx["parallel"]
    for c0, c1, idx, profile in ln["groups"]:
        sub = slice(c0, c1)
        att = ln["att"][idx, sub] if ln["att"] is not None else 1.0

        def model(amp: np.ndarray, uvw: np.ndarray, idx: np.ndarray = idx,
                  sub: slice = sub) -> np.ndarray:
            return kernels.model_visibilities_antenna(
                uvw, a1, a2, freq[sub], ln["l"][idx], ln["m"][idx],
                ln["nm1"][idx] if ln["nm1"] is not None else None, np.ones(idx.size), amp,
                ln["fwhm"][idx] if ln["extended"][idx].any() else None, parallel=False,
                channel_width=(ctx["smear_width"][sub] if ctx["smear_width"] is not None
                               else None),
                integration_time=ctx["smear_time"], dec0=ctx["center"][1])

        args = (ln["centre"][idx], ln["flux"][idx], ln["fwhm_kms"][idx], profile)
        if ln["ratio"] is None:
            amp = kernels.line_channel_flux(lo[sub], hi[sub], *args) * att
            out[:, :, sub, :][..., par] += model(amp, ant)[..., None]
            continue
        for k in range(t1 - t0):
            r = ln["ratio"][t0 + k]
            amp = kernels.line_channel_flux(r * lo[sub], r * hi[sub], *args) * att
            out[k:k + 1, :, sub, :][..., par] += model(amp, ant[k:k + 1])[..., None]


def _line_context(plan: _Plan, p: int, center: tuple[float, float],
                  times: np.ndarray) -> dict[str, Any] | None:
    """What the chunks of pointing ``p`` need to add the line sources (None: nothing)."""
    from xstack.frames import frame_ratio
    from xstack.spectral import SPEED_OF_LIGHT_KMS

    ln = plan.lines
    if ln is None:
        return None
    scene = plan.scene
    l, m, _, nm1 = radec_to_lmn(ln["ra"], ln["dec"], *center)
    keep = np.ones(l.size, bool)
    att = None
    if plan.beam is not None:
        sep = angular_separation(ln["ra"], ln["dec"], *center)
        att = plan.beam(sep[:, None], plan.freq[None, :])
        keep &= att.max(axis=1, initial=0.0) > 0
    ratio = None
    if ln["channel_frame"] != ln["line_frame"]:
        # the pointing's direction for every source in it, as a correlator's (and CASA's)
        # frame conversion of a field uses its phase center
        ratio = frame_ratio(times, np.degrees(center[0]), np.degrees(center[1]), ln["site"],
                            to_frame=ln["line_frame"], from_frame=ln["channel_frame"])
    r_lo, r_hi = ((1.0, 1.0) if ratio is None or ratio.size == 0
                  else (float(ratio.min()), float(ratio.max())))
    lo = plan.freq - 0.5 * plan.width
    hi = plan.freq + 0.5 * plan.width
    # channels each line reaches (in the channel frame, over the whole track)
    groups = []
    for profile in sorted(set(ln["profile"].tolist())):
        half = kernels.line_half_width_kms(ln["fwhm_kms"], profile) / SPEED_OF_LIGHT_KMS
        f_lo = ln["centre"] * (1.0 - half) / r_hi
        f_hi = ln["centre"] * (1.0 + half) / r_lo
        c0 = np.searchsorted(hi, f_lo, side="right")
        c1 = np.searchsorted(lo, f_hi, side="left")
        mine = np.flatnonzero(keep & (ln["profile"] == profile) & (c1 > c0))
        groups += _channel_groups(mine, c0, c1, profile)
    if not groups:
        return None
    return {"l": l, "m": m, "nm1": nm1 if scene.effects.w_term else None,
            "att": np.ascontiguousarray(att) if att is not None else None,
            "fwhm": ln["fwhm"], "extended": ln["fwhm"] > 0, "centre": ln["centre"],
            "flux": ln["flux"], "fwhm_kms": ln["fwhm_kms"], "ratio": ratio,
            "lo": lo, "hi": hi, "groups": groups}


def _channel_groups(idx: np.ndarray, c0: np.ndarray, c1: np.ndarray, profile: str,
                    min_width: int = 64) -> list[tuple[int, int, np.ndarray, str]]:
    """Sources ``idx`` (channel ranges [c0, c1)) in groups sharing one channel window of at
    most max(min_width, 2 x the widest range) channels: a kernel call per group does at most
    twice the channels a call per source would, with far fewer calls."""
    out: list[tuple[int, int, np.ndarray, str]] = []
    if idx.size == 0:
        return out
    order = idx[np.argsort(c0[idx], kind="stable")]
    width = max(min_width, 2 * int((c1[idx] - c0[idx]).max()))
    start = 0
    while start < order.size:
        w0 = int(c0[order[start]])
        stop = start
        while stop < order.size and c1[order[stop]] <= w0 + width:
            stop += 1
        members = order[start:stop]
        out.append((w0, int(c1[members].max()), members, profile))
        start = stop
    return out


def _uvw_block(dummy: np.ndarray, *, ctx: dict[str, Any], block_info: Any = None) -> np.ndarray:
    (t0, t1), (b0, b1) = block_info[0]["array-location"][:2]
    return arr.baseline_uvw(ctx["positions"], ctx["a1"][b0:b1], ctx["a2"][b0:b1],
                            ctx["times"][t0:t1], *ctx["center"])


def _flag_block(dummy: np.ndarray, *, ctx: dict[str, Any], block_info: Any = None) -> np.ndarray:
    (t0, t1), (b0, b1) = block_info[0]["array-location"][:2]
    nchan, npol = ctx["freq"].size, len(ctx["pols"])
    out = np.zeros((t1 - t0, b1 - b0, nchan, npol), dtype=bool)
    frac = ctx["flag_fraction"]
    if frac > 0:
        kernels._count("flag_random")
        nbl_all = ctx["a1"].size
        for k, ti in enumerate(range(t0, t1)):
            u = _seed_rng(ctx["seed"], 3, ctx["pointing"], ti).uniform(size=(nbl_all, nchan, npol))
            out[k] |= u[b0:b1] < frac
    if ctx["shadowing"]:
        kernels._count("flag_shadow")
        ant = arr.antenna_uvw(ctx["positions"], ctx["times"][t0:t1], *ctx["center"])
        sh = arr.shadowed_antennas(ant, ctx["diameters"])
        bad = sh[:, ctx["a1"][b0:b1]] | sh[:, ctx["a2"][b0:b1]]
        out |= bad[:, :, None, None]
    if ctx["elevation_limit"] is not None:
        kernels._count("flag_elevation")
        low = arr.antenna_elevations(ctx["positions"], ctx["times"][t0:t1],
                                     *ctx["center"]) < ctx["elevation_limit"]
        bad = low[:, ctx["a1"][b0:b1]] | low[:, ctx["a2"][b0:b1]]
        out |= bad[:, :, None, None]
    return out


def _partition(plan: _Plan, p: int, seed: int, token: str) -> xr.Dataset:
    scene = plan.scene
    center = (float(plan.pointings[p, 0]), float(plan.pointings[p, 1]))
    times = plan.times[p]
    a1, a2 = baseline_pairs(plan.array.n_antennas)
    nt, nbl, nchan, npol = times.size, a1.size, plan.freq.size, len(plan.pols)
    dtype = np.dtype(scene.visibility_dtype)

    l, m, _, nm1 = radec_to_lmn(plan.ra, plan.dec, *center)
    att = None
    keep = plan.flux != 0
    if plan.beam is not None:
        sep = angular_separation(plan.ra, plan.dec, *center)
        att = plan.beam(sep[:, None], plan.freq[None, :])
        keep &= att.max(axis=1, initial=0.0) > 0
        att = np.ascontiguousarray(att[keep])
    fwhm = plan.fwhm[keep]
    flagging = scene.effects.flagging or FlaggingSpec()  # no flagging: the defaults flag nothing
    ctx = {
        "a1": a1, "a2": a2, "positions": plan.array.positions, "diameters": plan.array.diameters,
        "times": times, "center": center, "freq": plan.freq, "pols": plan.pols,
        "parallel": _parallel_hands(plan.pols), "l": l[keep], "m": m[keep],
        "nm1": nm1[keep] if scene.effects.w_term else None, "flux": plan.flux[keep],
        "att": att, "fwhm": fwhm, "extended": fwhm > 0, "sigma": plan.sigma,
        "seed": int(seed), "pointing": p, "dtype": dtype,
        "flag_fraction": flagging.random_fraction,
        "shadowing": flagging.shadowing,
        "elevation_limit": (None if flagging.elevation_limit_deg is None
                            else math.radians(flagging.elevation_limit_deg)),
        "smear_width": plan.width if scene.effects.bandwidth_smearing else None,
        "smear_time": (float(scene.observation.integration) if scene.effects.time_smearing
                       else None),
    }
    if plan.lines is not None:
        ctx["lines"] = _line_context(plan, p, center, times)
    tc = scene.time_chunk or max(1, CHUNK_BYTES // max(1, nbl * nchan * npol * dtype.itemsize))
    tc = min(tc, nt)
    bc = min(scene.baseline_chunk or nbl, nbl)
    dummy = da.zeros((nt, nbl), chunks=(tc, bc), dtype=np.int8)
    vis = da.map_blocks(_vis_block, dummy, ctx=ctx, dtype=dtype, new_axis=[2, 3],
                        chunks=(dummy.chunks[0], dummy.chunks[1], (nchan,), (npol,)),
                        name=f"xstack-sim-vis-{token}-{p}", meta=np.empty((0, 0, 0, 0), dtype))
    uvw = da.map_blocks(_uvw_block, dummy, ctx=ctx, dtype=np.float64, new_axis=[2],
                        chunks=(dummy.chunks[0], dummy.chunks[1], (3,)),
                        name=f"xstack-sim-uvw-{token}-{p}", meta=np.empty((0, 0, 0)))
    if ctx["flag_fraction"] > 0 or ctx["shadowing"] or ctx["elevation_limit"] is not None:
        flag = da.map_blocks(_flag_block, dummy, ctx=ctx, dtype=bool, new_axis=[2, 3],
                             chunks=(dummy.chunks[0], dummy.chunks[1], (nchan,), (npol,)),
                             name=f"xstack-sim-flag-{token}-{p}",
                             meta=np.empty((0, 0, 0, 0), bool))
    else:
        flag = da.zeros((nt, nbl, nchan, npol), chunks=vis.chunks, dtype=bool)
    if plan.sigma is not None:
        w = (1.0 / plan.sigma**2).astype(np.float32)
    else:
        w = np.ones((nbl, nchan), dtype=np.float32)
    weight = da.broadcast_to(da.from_array(w[None, :, :, None], chunks=(1, bc, nchan, 1)),
                             (nt, nbl, nchan, npol), chunks=vis.chunks)
    ds = new_partition(
        visibility=vis, weight=weight, flag=flag, uvw=uvw, time=times, antenna1=a1,
        antenna2=a2, antenna_names=plan.array.names, antenna_positions=plan.array.positions,
        dish_diameters=plan.array.diameters, frequency=plan.freq, channel_width=plan.width,
        polarization=plan.pols, phase_center=center, field_name=f"pointing{p}", field_id=p,
        spectral_window_id=0, telescope_name=plan.array.telescope,
        integration_time=float(scene.observation.integration),
        attrs={"source": "xstack simulate", "scene_name": scene.name,
               "simulation_seed": int(seed),
               "noise_sigma_jy": (float(np.mean(plan.sigma)) if plan.sigma is not None
                                  else 0.0),
               # which smearing the data carry (uvstack's smearing="auto" reads this)
               "smearing": {"bandwidth": bool(scene.effects.bandwidth_smearing),
                            "time": bool(scene.effects.time_smearing)}},
        frequency_frame=scene.spectral.frame)
    return ds


def simulate_partitions(scene: Scene | dict | str | os.PathLike, *, seed: int = 0,
                        scale: float = 1.0) -> tuple[dict[str, xr.Dataset], dict[str, Table]]:
    """Lazy partitions (one per pointing, dask-backed) and true catalogs, without writing.

    Returns
    -------
    partitions, catalogs
        ``{partition name: xarray.Dataset}`` and ``{population name: astropy Table}``.
    """
    parts, cats, _ = _simulate_lazy(scene, seed=seed, scale=scale)
    return parts, cats


def _simulate_lazy(scene: Any, *, seed: int, scale: float
                   ) -> tuple[dict[str, xr.Dataset], dict[str, Table], _Plan]:
    plan = _plan(load_scene(scene), int(seed), float(scale))
    token = dask.base.tokenize(plan.scene.to_dict(), int(seed), float(scale))
    parts = {partition_name(0, p): _partition(plan, p, int(seed), token)
             for p in range(len(plan.pointings))}
    return parts, plan.catalogs, plan


def catalog_path(store: str | os.PathLike, population: str) -> Path | str:
    """``OUT.zarr`` -> ``OUT.<population>.ecsv`` (beside the store; a URL for a store URL)."""
    from xstack._fs import is_url

    if is_url(store):  # Path would fold the // of s3://
        text = str(store).rstrip("/")
        return f"{text[:-5] if text.endswith('.zarr') else text}.{population}.ecsv"
    store = Path(store)
    stem = store.name[:-5] if store.name.endswith(".zarr") else store.name
    return store.parent / f"{stem}.{population}.ecsv"


def simulate(scene: Scene | dict | str | os.PathLike, out: str | os.PathLike, *, seed: int = 0,
             scale: float = 1.0, overwrite: bool = False, progress: bool = False
             ) -> SimulationResult:
    """Simulate ``scene`` and write the store ``out`` plus one true catalog per population.

    Parameters
    ----------
    scene
        A :class:`~xstack.sim.scene.Scene`, a dictionary or a TOML path.
    out
        Output ``.zarr`` store; catalogs go to ``OUT.<population>.ecsv``.
    seed
        Random seed: the same seed gives the same data bit for bit.
    scale
        In (0, 1]: shortens the observation and thins large populations
        (:meth:`Scene.scaled`).
    overwrite
        Replace existing outputs.
    progress
        Progress bar on stderr.

    Raises
    ------
    XstackError
        For a bad scene (naming the field) or existing outputs; nothing is written then.
    """
    from xstack._atomic import atomic_output, check_output
    from xstack._fs import output_path

    out = output_path(out)  # a Path, or a store URL as it is
    parts, cats, plan = _simulate_lazy(scene, seed=seed, scale=scale)
    paths = {name: catalog_path(out, name) for name in cats}
    check_output(out, overwrite)
    for p in paths.values():
        check_output(p, overwrite)
    attrs = {"simulation": {"scene": plan.scene.to_dict(), "seed": int(seed),
                            "scale": float(scale), "steps": sorted(plan.steps),
                            "catalogs": {k: str(v).rsplit("/", 1)[-1]
                                         for k, v in paths.items()}}}
    write_store(parts, out, overwrite=overwrite, attrs=attrs, progress=progress,
                description="simulating")
    for name, table in cats.items():
        with atomic_output(paths[name], overwrite=overwrite) as tmp:
            table.write(tmp, format="ascii.ecsv")
    nvis = sum(int(np.prod([ds.sizes[d] for d in ("time", "baseline_id", "frequency",
                                                   "polarization")])) for ds in parts.values())
    return SimulationResult(store=out, catalogs=cats, catalog_paths=paths,
                            steps_run=frozenset(plan.steps), n_visibilities=nvis,
                            seed=int(seed), scale=float(scale),
                            pointings=[(float(np.degrees(a)) % 360, float(np.degrees(b)))
                                       for a, b in plan.pointings])


def wavelength(frequency: Any) -> np.ndarray:
    """Wavelength (m) of a frequency (Hz)."""
    return SPEED_OF_LIGHT / np.asarray(frequency, dtype=np.float64)
