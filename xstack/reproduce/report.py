"""The reproduction report: Table 2 beside the paper's and figures in the paper's style.

:func:`write_report` reads what a :func:`~xstack.reproduce.run.reproduce` run left in its
output directory — the JSON lines ``type{N}/realizations.jsonl`` (one per realisation) and the
``profile_seed{r}.npz`` / ``stamp_seed{r}.npz`` of the first realisation — and writes a
markdown page with the table and PNG figures (matplotlib, Agg). Everything is computed from the
lines, not from a run's summary, so the report can be made again at any time (also while a run
is still appending). Figures whose data a run did not record are skipped with a note.
"""

from __future__ import annotations

import math
import os
import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from xstack.coords import SPEED_OF_LIGHT
from xstack.errors import NoDataError
from xstack.reproduce.paper import MJY, PAPER_TYPE7_SIZES, PROCEDURES, TYPES, UJY, paper_row
from xstack.reproduce.run import (
    JSONL,
    MAP_NOISE_KEY,
    PROFILE_EDGES_KLAMBDA,
    made_the_same_way,
    read_records,
)

#: Display unit of each type, as Table 2: µJy for the VLA types, mJy for the ALMA ones (8-10).
UNITS: dict[int, tuple[float, str]] = {n: (MJY, "mJy") if n in (8, 9, 10) else (UJY, "µJy")
                                       for n in TYPES}

#: Center frequency of the VLA presets (paper-1 ... paper-7, paper-11), Hz: converts the 5000 m
#: uv cut to kilo-wavelengths when the run kept no uv-profile file to read the wavelength from.
VLA_CENTER_HZ = 1.4e9

#: The paper's figure numbers of each kind of figure (Lindroos et al. 2015).
_FLUX_FIGS, _STAMP_FIG, _PROFILE_FIGS, _SIZE_FIG, _NOISE_FIG, _FILTER_FIG = (
    "2, 6", "3", "5, 7, 9, 10", "8", "1", "12")


# ---------------------------------------------------------------------------- the numbers


def _values(records: Sequence[dict[str, Any]], key: str) -> np.ndarray:
    """The finite values of ``key`` over ``records`` (a failed fit's None is left out)."""
    v = [r.get(key) for r in records]
    a = np.asarray([x for x in v if isinstance(x, (int, float)) and not isinstance(x, bool)],
                   dtype=float)
    return a[np.isfinite(a)]


def _stats(a: np.ndarray) -> tuple[int, float, float]:
    """(count, mean, standard deviation with ddof=1) — NaN where undefined."""
    n = int(a.size)
    mean = float(np.mean(a)) if n else float("nan")
    std = float(np.std(a, ddof=1)) if n > 1 else float("nan")
    return n, mean, std


def _ratio(a: float, b: float) -> float:
    return a / b if (math.isfinite(a) and math.isfinite(b) and b != 0) else float("nan")


def load_type(outdir: str | os.PathLike, n: int) -> tuple[list[dict[str, Any]], str]:
    """The realisations of type ``n`` in ``outdir`` the report uses, and a note on the others.

    The lines made the way the last line was (same scale, procedure and scene: a resumed run
    only reuses those), one per seed (the first), in seed order.
    """
    records = read_records(Path(outdir) / f"type{n}" / JSONL)
    if not records:
        return [], ""
    last = records[-1]
    same = [r for r in records if made_the_same_way(r, last)]
    by_seed: dict[int, dict[str, Any]] = {}
    for r in same:
        by_seed.setdefault(int(r["seed"]), r)
    note = ""
    if len(same) < len(records):
        note = (f"{len(records) - len(same)} line(s) made at another scale, with another "
                "procedure or from another scene left out")
    return [by_seed[s] for s in sorted(by_seed)], note


def type_numbers(n: int, records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Table-2 numbers of type ``n`` from its realisation lines (Jy, arcsec, seconds).

    Means and scatters (standard deviation, ddof=1) over the realisations; SNR = mean /
    scatter; ``uv_offset_se`` = (uv mean - true mean) / (uv scatter / sqrt(R)), R the
    realisations with a uv flux.
    """
    true_flux = _stats(_values(records, "true_flux_jy"))[1]
    r_uv, uv_mean, uv_std = _stats(_values(records, "uv_flux_jy"))
    r_im, im_mean, im_std = _stats(_values(records, "image_flux_jy"))
    secs = _values(records, "seconds")
    out: dict[str, Any] = {
        "type": n, "realizations": len(records),
        "scale": records[0].get("scale") if records else None,
        "true_flux_jy": true_flux,
        "expected_noise_jy": _stats(_values(records, "expected_noise_jy"))[1],
        "expected_map_noise_jy": _stats(_values(records, MAP_NOISE_KEY))[1],
        "uv_count": r_uv, "uv_flux_mean_jy": uv_mean, "uv_flux_scatter_jy": uv_std,
        "uv_snr": _ratio(uv_mean, uv_std),
        "image_count": r_im, "image_flux_mean_jy": im_mean, "image_flux_scatter_jy": im_std,
        "image_snr": _ratio(im_mean, im_std),
        "uv_offset_se": _ratio(uv_mean - true_flux, uv_std / math.sqrt(max(r_uv, 1))),
        "seconds": float(secs.sum()),
        "seconds_per_realization": float(secs.mean()) if secs.size else float("nan"),
        "paper": paper_row(n),
    }
    if n in PROCEDURES and PROCEDURES[n].fit_size:
        for dom in ("uv", "image"):
            c, m, s = _stats(_values(records, f"{dom}_fwhm_arcsec"))
            out[f"{dom}_fwhm_count"] = c
            out[f"{dom}_fwhm_mean_arcsec"], out[f"{dom}_fwhm_scatter_arcsec"] = m, s
    return out


def paired_numbers(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Image- against uv-stacking on the same realisations (Jy).

    For the nearest-pixel image stack (``image``) and, where recorded, the sub-pixel
    aligned one (``subpixel``): ``{key}_count`` realisations with both fluxes,
    ``{key}_minus_uv_jy`` the mean of (image - uv) per realisation, ``{key}_minus_uv_se_jy``
    its standard error (the noise the two stacks share cancels in the difference) and
    ``{key}_over_uv`` the ratio of the two means over those realisations.
    """
    out: dict[str, Any] = {}
    for key, field_name in (("image", "image_flux_jy"), ("subpixel", "image_flux_subpixel_jy")):
        pairs = np.array([(r["uv_flux_jy"], r[field_name]) for r in records
                          if r.get("uv_flux_jy") is not None
                          and r.get(field_name) is not None], dtype=float).reshape(-1, 2)
        pairs = pairs[np.all(np.isfinite(pairs), axis=1)]
        c, d_mean, d_std = _stats(pairs[:, 1] - pairs[:, 0])
        out[f"{key}_count"] = c
        out[f"{key}_minus_uv_jy"] = d_mean
        out[f"{key}_minus_uv_se_jy"] = d_std / math.sqrt(c) if c > 1 else float("nan")
        out[f"{key}_over_uv"] = (_ratio(float(pairs[:, 1].mean()), float(pairs[:, 0].mean()))
                                 if c else float("nan"))
    return out


# ---------------------------------------------------------------------------- formatting

def _num(v: float | None, digits: int = 2) -> str:
    if v is None or not math.isfinite(v):
        return "n/a"
    return f"{v:.{digits}f}"


def _pm(mean: float | None, scatter: float | None, unit: float, snr: float | None = None,
        digits: int = 2) -> str:
    """``6.02 ± 0.38 (15.8)`` in the display unit; ``n/a`` where undefined."""
    if mean is None or not math.isfinite(mean):
        return "n/a"
    s = _num(mean / unit, digits)
    if scatter is not None and math.isfinite(scatter):
        s += f" ± {_num(scatter / unit, digits)}"
    if snr is not None:
        s += f" ({_num(snr, 1)})"
    return s


def _table(rows: Sequence[dict[str, Any]]) -> list[str]:
    lines = [
        "| type | R | scale | unit | expected | uv-stacking (SNR) | image-stacking (SNR) "
        "| paper: expected | paper: uv (SNR) | paper: image (SNR) | uv offset (SE) "
        "| s / realisation |",
        "|---:|---:|---:|:--|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for t in rows:
        unit, label = UNITS[t["type"]]
        p = t["paper"]
        off = t["uv_offset_se"]
        lines.append(
            f"| {t['type']} | {t['realizations']} | {t['scale']:g} | {label} "
            f"| {_pm(t['true_flux_jy'], t['expected_noise_jy'], unit)} "
            f"| {_pm(t['uv_flux_mean_jy'], t['uv_flux_scatter_jy'], unit, t['uv_snr'])} "
            f"| {_pm(t['image_flux_mean_jy'], t['image_flux_scatter_jy'], unit, t['image_snr'])} "
            f"| {_pm(p['expected_flux_jy'], p['expected_noise_jy'], unit)} "
            f"| {_pm(p['uv_flux_jy'], p['uv_scatter_jy'], unit, p['uv_snr'])} "
            f"| {_pm(p['image_flux_jy'], p['image_scatter_jy'], unit, p['image_snr'])} "
            f"| {'n/a' if not math.isfinite(off) else f'{off:+.1f}'} "
            f"| {_num(t['seconds_per_realization'], 1)} |")
    return lines


def _paired_table(data: dict[int, Sequence[dict[str, Any]]]) -> list[str]:
    """Image- against uv-stacking, realisation by realisation, nearest pixel and sub-pixel."""
    lines = ["| type | unit | R | image − uv (SE) | image / uv | R | sub-pixel image − uv (SE) "
             "| sub-pixel image / uv |", "|---:|:--|---:|--:|--:|---:|--:|--:|"]
    for n, recs in data.items():
        unit, label = UNITS[n]
        p = paired_numbers(recs)
        cells = []
        for key in ("image", "subpixel"):
            if not p[f"{key}_count"]:
                cells += ["0", "n/a", "n/a"]
                continue
            diff, se = p[f"{key}_minus_uv_jy"] / unit, p[f"{key}_minus_uv_se_jy"] / unit
            cells += [str(p[f"{key}_count"]),
                      f"{diff:+.3f} ({'n/a' if not math.isfinite(se) else f'{se:.3f}'})",
                      _num(p[f"{key}_over_uv"], 4)]
        lines.append(f"| {n} | {label} | " + " | ".join(cells) + " |")
    return lines


def _ratios_table(rows: Sequence[dict[str, Any]],
                  data: dict[int, Sequence[dict[str, Any]]]) -> list[str]:
    """The paper's findings as ratios, xstack's beside the paper's, one row per type."""
    lines = ["| type | R | uv offset (SE) | uv scatter / paper's | image / uv | paper: image / uv "
             "| sub-pixel image / uv | uv SNR / image SNR | paper: uv SNR / image SNR |",
             "|---:|---:|--:|--:|--:|--:|--:|--:|--:|"]
    for t in rows:
        p, pair = t["paper"], paired_numbers(data[t["type"]])
        off = t["uv_offset_se"]
        cells = [f"{off:+.1f}" if math.isfinite(off) else "n/a",
                 _num(_ratio(t["uv_flux_scatter_jy"], p["uv_scatter_jy"])),
                 _num(pair["image_over_uv"], 3), _num(_ratio(p["image_flux_jy"], p["uv_flux_jy"]), 3),
                 _num(pair["subpixel_over_uv"], 3),
                 _num(_ratio(t["uv_snr"], t["image_snr"])), _num(_ratio(p["uv_snr"], p["image_snr"]))]
        lines.append(f"| {t['type']} | {t['realizations']} | " + " | ".join(cells) + " |")
    return lines


def _noise_table(rows: Sequence[dict[str, Any]]) -> list[str]:
    """Expected noise two ways beside the paper's and the measured scatters."""
    lines = ["| type | R | unit | expected: thermal | expected: map (eq. 9) | paper: expected "
             "| uv scatter | image scatter | uv scatter / map | uv scatter / thermal |",
             "|---:|---:|:--|--:|--:|--:|--:|--:|--:|--:|"]
    for t in rows:
        unit, label = UNITS[t["type"]]
        cells = [t["expected_noise_jy"], t["expected_map_noise_jy"],
                 t["paper"]["expected_noise_jy"], t["uv_flux_scatter_jy"],
                 t["image_flux_scatter_jy"]]
        cells = [_num(None if v is None else v / unit, 3) for v in cells]
        # a fit's flux (type 7) has neither noise: its ratios would say nothing
        fit = t["type"] in PROCEDURES and PROCEDURES[t["type"]].fit_size
        ratios = [_num(float("nan") if fit else _ratio(t["uv_flux_scatter_jy"], t[k]))
                  for k in ("expected_map_noise_jy", "expected_noise_jy")]
        lines.append(f"| {t['type']} | {t['realizations']} | {label} | "
                     + " | ".join(cells + ratios) + " |")
    return lines


def _sizes_table(t: dict[str, Any]) -> list[str]:
    lines = ["| type 7 FWHM (arcsec) | fits | xstack | paper |", "|:--|--:|--:|--:|"]
    for dom, name in (("uv", "uv fit"), ("image", "image fit (PSF-convolved)")):
        pm = f"{_num(t[f'{dom}_fwhm_mean_arcsec'])} ± {_num(t[f'{dom}_fwhm_scatter_arcsec'])}"
        paper = (f"{PAPER_TYPE7_SIZES[f'{dom}_fwhm_arcsec']:.2f} ± "
                 f"{PAPER_TYPE7_SIZES[f'{dom}_fwhm_scatter_arcsec']:.2f}")
        lines.append(f"| {name} | {t[f'{dom}_fwhm_count']} of {t['realizations']} "
                     f"| {pm} | {paper} |")
    lines.append(f"| true | | {PAPER_TYPE7_SIZES['true_fwhm_arcsec']:.2f} "
                 f"| {PAPER_TYPE7_SIZES['true_fwhm_arcsec']:.2f} |")
    return lines


# ---------------------------------------------------------------------------- figures

def _figure(figsize: tuple[float, float]) -> Any:
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    return Figure(figsize=figsize, dpi=100)


def _save(fig: Any, path: Path) -> Path:
    fig.tight_layout()
    with open(path, "wb") as fh:
        fig.savefig(fh, format="png")
    return path


def _gauss_counts(ax: Any, mean: float, std: float, count: int, width: float, lo: float,
                  hi: float, **style: Any) -> None:
    """The Gaussian of ``mean`` and ``std`` scaled to a histogram of ``count`` values."""
    if not (math.isfinite(mean) and math.isfinite(std) and std > 0):
        return
    x = np.linspace(lo, hi, 300)
    ax.plot(x, count * width * np.exp(-0.5 * ((x - mean) / std) ** 2)
            / (std * math.sqrt(2 * math.pi)), **style)


def _bins(values: Sequence[np.ndarray], floor: float | None = None) -> np.ndarray:
    """Histogram edges padding the values' range by 15 % on each side, not below ``floor``
    (a fitted size is never negative: its histogram has no bin below 0)."""
    allv = np.concatenate([v for v in values if v.size]) if any(v.size for v in values) \
        else np.zeros(1)
    lo, hi = float(allv.min()), float(allv.max())
    if hi <= lo:
        lo, hi = lo - 0.5 * abs(lo or 1.0), hi + 0.5 * abs(hi or 1.0)
    nb = int(np.clip(round(math.sqrt(allv.size)) + 2, 5, 25))
    pad = 0.15 * (hi - lo)
    start = lo - pad if floor is None else max(lo - pad, floor)
    return np.linspace(start, hi + pad, nb + 1)


def fig_flux(n: int, records: Sequence[dict[str, Any]], path: Path) -> Path:
    """Figs 2, 6: uv- and image-stacked flux of every realisation with the Gaussian of their
    mean and standard deviation (red) and the true mean flux (dashed)."""
    unit, label = UNITS[n]
    true = _stats(_values(records, "true_flux_jy"))[1] / unit
    data = {d: _values(records, f"{d}_flux_jy") / unit for d in ("uv", "image")}
    edges = _bins(list(data.values()) + [np.array([true])])
    fig = _figure((5.5, 6.5))
    axes = fig.subplots(2, 1, sharex=True)
    for ax, (dom, v) in zip(axes, data.items()):
        c, m, s = _stats(v)
        ax.hist(v, bins=edges, color="0.7", edgecolor="0.3")
        _gauss_counts(ax, m, s, c, edges[1] - edges[0], edges[0], edges[-1], color="red",
                      label=f"mean {_num(m)} ± {_num(s)} {label}")
        if math.isfinite(true):
            ax.axvline(true, color="k", ls="--", label=f"true {_num(true)} {label}")
        ax.set_ylabel("realisations")
        ax.set_title(f"type {n}: {dom}-stacking ({c} realisations)", fontsize=10)
        ax.legend(fontsize=8)
    axes[-1].set_xlabel(f"stacked flux density ({label})")
    return _save(fig, path)


def _first_npz(workdir: Path, stem: str) -> Path | None:
    found = []
    for p in workdir.glob(f"{stem}_seed*.npz"):
        m = re.fullmatch(rf"{stem}_seed(\d+)\.npz", p.name)
        if m:
            found.append((int(m.group(1)), p))
    return min(found)[1] if found else None


def psf_mask_radius(psf: np.ndarray, pixel_arcsec: float) -> float:
    """Radius (arcsec) of the image-stacking central mask estimated from a PSF stamp: the
    beam's major FWHM (the default mask radius), as twice the farthest distance from the
    peak of the connected pixels above half the peak. NaN without a PSF."""
    from scipy import ndimage

    psf = np.asarray(psf, dtype=float)
    if psf.ndim != 2 or not np.isfinite(psf).any():
        return float("nan")
    peak = np.unravel_index(np.nanargmax(psf), psf.shape)
    labels, _ = ndimage.label(np.nan_to_num(psf) >= 0.5 * psf[peak])
    yy, xx = np.nonzero(labels == labels[peak])
    return float(2.0 * np.max(np.hypot(yy - peak[0], xx - peak[1])) * pixel_arcsec)


def fig_stamp(n: int, npz: Path, path: Path) -> tuple[Path, float, str]:
    """Fig 3: the stacked stamp of the first realisation with the central-mask outline, the
    stamp with the mask blanked, and (type 7) the low-frequency-filtered stamp."""
    from matplotlib.patches import Circle

    with np.load(npz) as z:
        arrays = {k: np.asarray(z[k]) for k in z.files}
    stamp = arrays["stamp"].astype(float)
    # pixel size (x, y) in arcsec, or one number for both
    px, py = np.abs(np.broadcast_to(np.asarray(arrays.get("pixel_arcsec", 1.0), float),
                                    (2,)))
    pix = float(math.sqrt(px * py))
    if "mask_radius_arcsec" in arrays:
        radius, how = float(arrays["mask_radius_arcsec"]), "the run's mask radius"
    else:
        radius = psf_mask_radius(arrays.get("psf", np.zeros(0)), pix)
        how = "the PSF's major FWHM (half-maximum extent of the stacked PSF)"
    filtered = next((arrays[k].astype(float) for k in sorted(arrays)
                     if "filter" in k and arrays[k].ndim == 2), None)
    ny, nx = stamp.shape
    x = (np.arange(nx) - (nx - 1) / 2) * px
    y = (np.arange(ny) - (ny - 1) / 2) * py
    extent = (x[0] - px / 2, x[-1] + px / 2, y[0] - py / 2, y[-1] + py / 2)
    inside = np.hypot(*np.meshgrid(x, y)) <= radius if math.isfinite(radius) \
        else np.zeros_like(stamp, dtype=bool)
    panels = [(stamp, "stacked stamp", True), (np.where(inside, np.nan, stamp),
                                                 "central pixels masked", False)]
    if filtered is not None:
        panels.append((np.where(inside, np.nan, filtered), "masked, short baselines filtered",
                       False))
    unit, label = UNITS[n]
    fig = _figure((4.2 * len(panels), 4.0))
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    for ax, (img, title, outline) in zip(axes, panels):
        outside = img[~inside & np.isfinite(img)]
        rms = float(np.std(outside)) if outside.size > 1 else float("nan")
        im = ax.imshow(img / unit, origin="lower", extent=extent, cmap="viridis",
                       interpolation="nearest")
        if math.isfinite(rms) and rms > 0:
            levels = [k * rms / unit for k in (3, 5) if k * rms < np.nanmax(img)]
            if levels:
                ax.contour(x, y, img / unit, levels=levels, colors="white", linewidths=0.8)
        if outline and math.isfinite(radius):
            ax.add_patch(Circle((0, 0), radius, fill=False, edgecolor="red", ls="--", lw=1.0))
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("offset (arcsec)")
        fig.colorbar(im, ax=ax, label=f"{label}/beam", shrink=0.8)
    axes[0].set_ylabel("offset (arcsec)")
    return _save(fig, path), radius, how


def _wavelength_m(workdir: Path, n: int) -> float:
    """Wavelength (m) of the uv-profile: from the run's profile file, else the VLA center."""
    npz = _first_npz(workdir, "profile")
    if npz is not None:
        with np.load(npz) as z:
            if "uvdist_m" in z.files and "uvdist_klambda" in z.files:
                m, k = np.asarray(z["uvdist_m"], float), np.asarray(z["uvdist_klambda"], float)
                ok = np.isfinite(m) & np.isfinite(k) & (k > 0)
                if ok.any():
                    return float(np.median(m[ok] / (k[ok] * 1e3)))
    return SPEED_OF_LIGHT / VLA_CENTER_HZ


def profile_edges(workdir: Path) -> np.ndarray:
    """Bin edges (kλ) of the realisations' uv-profiles: those of the run's profile file when
    it has them (contiguous bins), else :data:`~xstack.reproduce.run.PROFILE_EDGES_KLAMBDA`."""
    npz = _first_npz(workdir, "profile")
    if npz is not None:
        with np.load(npz) as z:
            if "bin_lo_klambda" in z.files and "bin_hi_klambda" in z.files:
                lo, hi = np.asarray(z["bin_lo_klambda"], float), np.asarray(z["bin_hi_klambda"],
                                                                             float)
                if lo.size and np.allclose(lo[1:], hi[:-1]):
                    return np.append(lo, hi[-1])
    return np.asarray(PROFILE_EDGES_KLAMBDA, float)


def profile_matrix(records: Sequence[dict[str, Any]], nb: int | None = None) -> np.ndarray:
    """(R, bins) real parts of the realisations' uv-profiles on the shared ``nb`` bins (NaN:
    empty bin); a realisation with another number of bins is left out."""
    nb = len(PROFILE_EDGES_KLAMBDA) - 1 if nb is None else nb
    rows = []
    for r in records:
        re_ = (r.get("profile") or {}).get("re_jy")
        if re_ is not None and len(re_) == nb:
            rows.append([np.nan if v is None else float(v) for v in re_])
    return np.asarray(rows, dtype=float).reshape(-1, nb)


def profile_stats(prof: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per bin of a :func:`profile_matrix`: the mean over realisations, its error (standard
    deviation, ddof=1, over the square root of the realisations with that bin) and that
    number of realisations."""
    counts = np.isfinite(prof).sum(axis=0)
    # an empty bin (or one seen once) is NaN, not a warning
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(prof, axis=0)
        err = np.nanstd(prof, axis=0, ddof=1) / np.sqrt(counts)
    return mean, err, counts


def fig_profile(n: int, records: Sequence[dict[str, Any]], workdir: Path, path: Path
                ) -> tuple[Path, int]:
    """Figs 5, 7, 9, 10: the uv-profile averaged over realisations, error bars std/sqrt(R),
    the uv cut dashed and (red) the mean uv-stacked flux — type 7: the mean fitted Gaussian —
    over the baselines used."""
    unit, label = UNITS[n]
    edges = profile_edges(workdir)
    prof = profile_matrix(records, len(edges) - 1)
    centers = 0.5 * (edges[1:] + edges[:-1])
    mean, err, counts = profile_stats(prof)
    ok = counts > 0
    fig = _figure((6.0, 4.2))
    ax = fig.subplots()
    ax.errorbar(centers[ok], mean[ok] / unit, yerr=np.nan_to_num(err[ok]) / unit, fmt="o",
                ms=3, color="k", ecolor="0.4", capsize=2, label="mean over realisations")
    proc = PROCEDURES.get(n)
    cut_kl = (proc.uvmin_m / _wavelength_m(workdir, n) / 1e3
              if proc is not None and proc.uvmin_m else None)
    lo = cut_kl if cut_kl is not None else 0.0
    q = np.linspace(lo, edges[-1], 200)
    if proc is not None and proc.fit_size:
        flux = _stats(_values(records, "uv_flux_jy"))[1]
        fwhm = _stats(_values(records, "uv_fwhm_arcsec"))[1]
        if math.isfinite(flux) and math.isfinite(fwhm):
            theta = math.radians(fwhm / 3600.0)
            # visibility of a circular Gaussian of FWHM theta at uv distance q (wavelengths)
            model = flux * np.exp(-(math.pi * theta * q * 1e3) ** 2 / (4 * math.log(2)))
            ax.plot(q, model / unit, color="red", label="mean Gaussian fit")
    else:
        flux = _stats(_values(records, "uv_flux_jy"))[1]
        if math.isfinite(flux):
            ax.plot(q, np.full_like(q, flux / unit), color="red", label="mean uv-stacked flux")
    if cut_kl is not None:
        ax.axvline(cut_kl, color="k", ls="--", lw=1,
                   label=f"uv cut {proc.uvmin_m:g} m ({cut_kl:.1f} kλ)")
    true = _stats(_values(records, "true_flux_jy"))[1]
    if math.isfinite(true):
        ax.axhline(true / unit, color="0.5", ls=":", lw=1, label="true mean flux")
    ax.set_xlabel("uv distance (kλ)")
    ax.set_ylabel(f"mean real part ({label})")
    ax.set_title(f"type {n}: uv-stacked visibilities, {prof.shape[0]} realisations",
                 fontsize=10)
    ax.legend(fontsize=8)
    return _save(fig, path), prof.shape[0]


def fig_sizes(records: Sequence[dict[str, Any]], path: Path) -> Path:
    """Fig 8: type 7's fitted FWHM of every realisation, uv against image."""
    data = {"uv": _values(records, "uv_fwhm_arcsec"),
            "image": _values(records, "image_fwhm_arcsec")}
    edges = _bins(list(data.values()) + [np.array([PAPER_TYPE7_SIZES["true_fwhm_arcsec"]])],
                  floor=0.0)
    fig = _figure((6.0, 4.2))
    ax = fig.subplots()
    for (dom, v), color in zip(data.items(), ("tab:blue", "tab:orange")):
        c, m, s = _stats(v)
        ax.hist(v, bins=edges, histtype="step", lw=1.5, color=color,
                label=f"{dom}-stacking: {_num(m)} ± {_num(s)} arcsec ({c})")
    ax.axvline(PAPER_TYPE7_SIZES["true_fwhm_arcsec"], color="k", ls="--", label="true FWHM")
    ax.set_xlabel("fitted FWHM (arcsec)")
    ax.set_ylabel("realisations")
    ax.set_title("type 7: fitted sizes", fontsize=10)
    ax.legend(fontsize=8)
    return _save(fig, path)


def noise_by_count(records: Sequence[dict[str, Any]]) -> dict[int, tuple[int, float]]:
    """From ``uv_flux_subsets_jy`` ({N: flux} per realisation): N -> (realisations, scatter
    (ddof=1) of the flux stacked on N targets)."""
    per: dict[int, list[float]] = {}
    for r in records:
        for k, v in (r.get("uv_flux_subsets_jy") or {}).items():
            if v is not None and math.isfinite(float(v)):
                per.setdefault(int(k), []).append(float(v))
    return {k: (len(v), _stats(np.asarray(v))[2]) for k, v in sorted(per.items())
            if len(v) > 1}


def fig_noise(by_type: dict[int, dict[int, tuple[int, float]]], path: Path) -> tuple[Path, str]:
    """Fig 1: scatter of the stacked flux against the number of targets N (log-log) with a
    1/sqrt(N) line through the points (least squares in log with the slope fixed)."""
    fig = _figure((6.0, 4.2))
    ax = fig.subplots()
    logs, allN = [], []
    for n, series in by_type.items():
        unit, label = UNITS[n]
        N = np.asarray(list(series), float)
        s = np.asarray([v[1] for v in series.values()], float)
        ok = np.isfinite(s) & (s > 0)
        ax.plot(N[ok], s[ok] / UJY, "o", label=f"type {n}")
        logs += list(np.log(s[ok]) + 0.5 * np.log(N[ok]))
        allN += list(N[ok])
    text = ""
    if logs:
        amp = float(np.exp(np.mean(logs)))
        N = np.geomspace(min(allN), max(allN), 100)
        ax.plot(N, amp / np.sqrt(N) / UJY, color="red",
                label=rf"{amp / UJY:.3g} µJy / $\sqrt{{N}}$")
        text = f"{amp / UJY:.3g} µJy / √N"
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("number of targets N")
    ax.set_ylabel("scatter of the uv-stacked flux (µJy)")
    ax.legend(fontsize=8)
    return _save(fig, path), text


def fig_filtered(n: int, records: Sequence[dict[str, Any]], path: Path) -> Path:
    """Fig 12: image-stacked flux with the low-frequency filter (histogram, red Gaussian),
    the unfiltered distribution's Gaussian dashed, the true mean flux black dashed."""
    unit, label = UNITS[n]
    filt = _values(records, "image_flux_filtered_jy") / unit
    plain = _values(records, "image_flux_jy") / unit
    true = _stats(_values(records, "true_flux_jy"))[1] / unit
    edges = _bins([filt, plain, np.array([true])])
    w = edges[1] - edges[0]
    fig = _figure((6.0, 4.2))
    ax = fig.subplots()
    c, m, s = _stats(filt)
    ax.hist(filt, bins=edges, color="0.7", edgecolor="0.3")
    _gauss_counts(ax, m, s, c, w, edges[0], edges[-1], color="red",
                  label=f"filtered: {_num(m)} ± {_num(s)} {label}")
    c2, m2, s2 = _stats(plain)
    _gauss_counts(ax, m2, s2, c2, w, edges[0], edges[-1], color="tab:blue", ls="--",
                  label=f"not filtered: {_num(m2)} ± {_num(s2)} {label}")
    if math.isfinite(true):
        ax.axvline(true, color="k", ls="--", label=f"true {_num(true)} {label}")
    ax.set_xlabel(f"image-stacked flux density ({label})")
    ax.set_ylabel("realisations")
    ax.set_title(f"type {n}: low-frequency filter ({c} realisations)", fontsize=10)
    ax.legend(fontsize=8)
    return _save(fig, path)


# ---------------------------------------------------------------------------- the page

def write_report(outdir: str | os.PathLike, out_md: str | os.PathLike | None = None,
                 figures_dir: str | os.PathLike | None = None) -> Path:
    """Write the reproduction report of a :func:`~xstack.reproduce.run.reproduce` run.

    Parameters
    ----------
    outdir
        The run's output directory (``type{N}/realizations.jsonl`` and the first
        realisation's ``profile_seed{r}.npz`` / ``stamp_seed{r}.npz``). Only read.
    out_md
        Markdown file to write; default ``outdir/report.md``.
    figures_dir
        Directory of the PNG figures (made if missing); default ``figures/`` beside
        ``out_md``. The markdown links them relative to its own directory.

    Returns
    -------
    Path
        The markdown file written.

    Raises
    ------
    NoDataError
        ``outdir`` holds no realisation of any type.
    """
    outdir = Path(outdir)
    data = {}
    notes = {}
    for n in TYPES:
        recs, note = load_type(outdir, n)
        if recs:
            data[n], notes[n] = recs, note
    if not data:
        raise NoDataError(f"no realisations in {outdir}: no type<N>/{JSONL} with a valid line "
                          "(run the reproduction first)")
    out_md = Path(out_md) if out_md is not None else outdir / "report.md"
    figdir = Path(figures_dir) if figures_dir is not None else out_md.parent / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    out_md.parent.mkdir(parents=True, exist_ok=True)
    rel = lambda p: Path(os.path.relpath(p, out_md.parent)).as_posix()  # noqa: E731

    rows = [type_numbers(n, recs) for n, recs in data.items()]
    from xstack import __version__

    md = ["# Reproduction of Table 2 (Lindroos et al. 2015)", "",
          f"Made by xstack {__version__} from the realisation lines in `{outdir}` "
          "(`type<N>/realizations.jsonl`); redo it with "
          f"`xstack reproduce --report-only --outdir {outdir}`.", "",
          "## Stacked flux densities beside the paper's Table 2", "",
          *_table(rows), "",
          "R: realisations; scale: the presets' observing time and large populations times "
          "this (1: the paper's size). *expected*: mean true flux of the targets ± the "
          "expected noise (analytic, mean over realisations). *uv-* and *image-stacking*: "
          "mean ± scatter (standard deviation, ddof=1) of the stacked flux over the "
          "realisations, SNR = mean / scatter in brackets (type 7: the fluxes of the Gaussian "
          "fits). *paper*: Table 2 of the paper (100 realisations at scale 1). *uv offset*: "
          "(uv mean - true mean) / (scatter / √R), the uv mean's distance from the truth in "
          "standard errors. *s / realisation*: computing seconds of one realisation (mean).",
          ""]
    for n, note in notes.items():
        if note:
            md.append(f"Type {n}: {note}.")
    md += ["### The paper's findings as ratios", "", *_ratios_table(rows, data), "",
           "*uv scatter / paper's*: the uv stack's scatter over the paper's (a scatter from R "
           "realisations is known to ±1/√(2(R−1))). *image / uv*: the ratio of the two means "
           "over the realisations with both (nearest pixel; *sub-pixel*: Fourier-aligned "
           "stamps). *uv SNR / image SNR*: above 1 where uv-stacking does better.", "",
           "### Expected noise: thermal and from the residual map", "",
           *_noise_table(rows), "",
           "*thermal*: the uv stack's noise from the visibility weights (the table above's "
           "*expected*). *map (eq. 9)*: the paper's definition of its expected noise, eq. 9 "
           "with σ_k from the CLEANed residual map — the image stack's noise propagated from "
           "the stamps' local σ_k and its weights, mean over the realisations; it includes "
           "what CLEAN left. *uv scatter / map*: near 1 where the expected noise predicts the "
           "uv stack's; with R realisations a scatter is known to ±1/√(2(R−1)) (±24 % for "
           "R = 10). Type 7's fluxes are fits, whose noise neither column is (its ratios n/a).", "",
           "### Image-stacking against uv-stacking on the same realisations", "",
           *_paired_table(data), "",
           "Per realisation, the image-stacked flux minus the uv-stacked one, averaged over "
           "the realisations with both (SE: their scatter / √R; the noise the two stacks "
           "share cancels, so the difference is measured better than either flux), and the "
           "ratio of the two means. *sub-pixel*: the same residual maps image-stacked with "
           "the stamps aligned by a Fourier shift instead of to the nearest pixel "
           "(`image_flux_subpixel_jy`; not recorded for type 7, whose fluxes are fits, nor "
           "by runs made before it was added).", ""]
    t7 = next((t for t in rows if t["type"] == 7 and "uv_fwhm_count" in t), None)
    if t7 is not None:
        md += ["", "### Type 7: fitted sizes", "", *_sizes_table(t7), "",
               "Mean ± scatter of the fitted FWHM over the realisations whose fit succeeded "
               "(*fits*); the paper's from §4.1.7 and Fig. 8.", ""]

    figs: list[tuple[str, str]] = []   # (markdown image line, caption)
    skipped: list[str] = []

    def add(path: Path, alt: str, caption: str) -> None:
        figs.append((f"![{alt}]({rel(path)})", caption))

    for n, recs in data.items():
        unit, label = UNITS[n]
        add(fig_flux(n, recs, figdir / f"flux_type{n}.png"), f"flux histograms, type {n}",
            f"Type {n} (as the paper's Figs {_FLUX_FIGS}): the uv-stacked (top) and "
            f"image-stacked (bottom) mean flux density of each of the {len(recs)} "
            "realisations; red: the Gaussian of their mean and standard deviation; dashed: "
            "the true mean flux of the targets.")
    for n in data:
        npz = _first_npz(outdir / f"type{n}", "stamp")
        if npz is None:
            skipped.append(f"The paper's Fig. {_STAMP_FIG} (stacked stamp), type {n}: no "
                           "`stamp_seed<r>.npz` in the run's directory.")
            continue
        path, radius, how = fig_stamp(n, npz, figdir / f"stamp_type{n}.png")
        add(path, f"stacked stamp, type {n}",
            f"Type {n} (as the paper's Fig. {_STAMP_FIG}): the image-stacked stamp of the "
            f"first realisation ({npz.name}); left with the central mask outlined (red dashed, "
            f"radius {_num(radius)} arcsec: {how}), then with the central pixels masked"
            + (", then also with the short baselines filtered out (low-frequency FFT filter)"
               if "filter" in _npz_keys(npz) else "")
            + "; white contours at 3 and 5 times the rms outside the mask.")
    for n, recs in data.items():
        if not profile_matrix(recs, len(profile_edges(outdir / f"type{n}")) - 1).shape[0]:
            skipped.append(f"The paper's Figs {_PROFILE_FIGS} (uv-profile), type {n}: "
                           "no realisation "
                           "line has a uv-profile on the shared bins.")
            continue
        path, r = fig_profile(n, recs, outdir / f"type{n}", figdir / f"uvprofile_type{n}.png")
        proc = PROCEDURES.get(n)
        add(path, f"uv-profile, type {n}",
            f"Type {n} (as the paper's Figs {_PROFILE_FIGS}): the real part of the "
            "uv-stacked visibilities in bins of uv distance, averaged over "
            f"{r} realisations; error bars: the standard deviation of the realisations' "
            "bin means divided by the square root of their number. "
            + ("Dashed: the uv cut (shorter baselines are not used). " if proc and proc.uvmin_m
               else "")
            + ("Red: the visibility of the mean fitted Gaussian (flux and FWHM)"
               if proc and proc.fit_size else "Red: the mean uv-stacked flux")
            + (" over the baselines used" if proc and proc.uvmin_m else "")
            + "; dotted: the true mean flux.")
    if t7 is not None:
        if t7["uv_fwhm_count"] or t7["image_fwhm_count"]:
            add(fig_sizes(data[7], figdir / "sizes_type7.png"), "type 7 sizes",
                f"Type 7 (as the paper's Fig. {_SIZE_FIG}): the fitted FWHM of each "
                "realisation, uv fit against the PSF-convolved image fit; dashed: the true "
                "1.5 arcsec.")
        else:
            skipped.append(f"The paper's Fig. {_SIZE_FIG} (type 7 sizes): no realisation "
                           "has a fitted "
                           "FWHM.")
    noise = {n: s for n, recs in data.items() if (s := noise_by_count(recs))}
    if noise:
        path, law = fig_noise(noise, figdir / "noise_vs_targets.png")
        add(path, "noise against number of targets",
            f"As the paper's Fig. {_NOISE_FIG}: the scatter over realisations of the "
            "uv-stacked flux on the first N targets, against N (type(s) "
            f"{', '.join(map(str, noise))}); red: {law}, the fall of independent positions "
            "(amplitude fitted with the slope fixed at -1/2).")
    else:
        skipped.append(f"The paper's Fig. {_NOISE_FIG} (noise against number of targets): "
                       "no realisation "
                       "has `uv_flux_subsets_jy` (target subsets of types 5-6).")
    filt = [n for n, recs in data.items() if _values(recs, "image_flux_filtered_jy").size]
    for n in filt:
        with_response = all(r.get("image_filter_response") is not None for r in data[n]
                            if r.get("image_flux_filtered_jy") is not None)
        how = ("divided by the filter response (the stacked PSF's filtered / unfiltered "
               "peak)" if with_response else
               "the bare filtered peak, not divided by the filter response (records made "
               "before it was recorded: lower than a flux by the short spacings' share of "
               "the peak)")
        add(fig_filtered(n, data[n], figdir / f"filtered_type{n}.png"),
            f"low-frequency filter, type {n}",
            f"Type {n} (as the paper's Fig. {_FILTER_FIG}): the image-stacked flux density "
            f"with the short spacings filtered out of the stamps, {how} (histogram, red: its "
            "Gaussian) against the unfiltered one (blue dashed: its Gaussian); black dashed: "
            "the true mean flux.")
    if not filt:
        skipped.append(f"The paper's Fig. {_FILTER_FIG} (filtered image stacks): no realisation has "
                       "`image_flux_filtered_jy`.")

    md += ["## Figures", ""]
    for i, (img, caption) in enumerate(figs, 1):
        md += [img, "", f"*Figure {i}.* {caption}", ""]
    if skipped:
        md += ["Figures skipped (their data are not in this run):", ""]
        md += [f"- {s}" for s in skipped] + [""]
    out_md.write_text("\n".join(md), encoding="utf-8")
    return out_md


def _npz_keys(npz: Path) -> str:
    with np.load(npz) as z:
        return " ".join(z.files)
