"""Figures of noise estimates: histogram of realisations (paper Fig. 8 style) and uv-profiles
of the Monte Carlo stacks (paper Fig. 9 style)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from xstack._atomic import atomic_output
from xstack.errors import XstackError


def _figure():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def plot_histogram(result: Any, path: str | os.PathLike, *, overwrite: bool = False,
                   unit: str = "uJy") -> Path:
    """Histogram of the per-realisation stacked fluxes with the Gaussian of the estimated
    noise; dashed line: the injected flux (mc) or zero (random), dotted: the target stack."""
    if result.values is None or len(result.values) < 2:
        raise XstackError(f"no realisations to plot for method {result.method!r}")
    scale = {"Jy": 1.0, "mJy": 1e3, "uJy": 1e6}[unit]
    label = unit.replace("uJy", "µJy")
    plt = _figure()
    vals = np.asarray(result.values) * scale
    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    nb = int(np.clip(np.sqrt(vals.size) * 1.5, 8, 60))
    ax.hist(vals, bins=nb, density=True, color="0.75", edgecolor="0.3", label="realisations")
    mu = float(np.mean(vals))
    sig = result.noise_jy * scale
    x = np.linspace(vals.min() - sig, vals.max() + sig, 400)
    ax.plot(x, np.exp(-0.5 * ((x - mu) / sig) ** 2) / (sig * np.sqrt(2 * np.pi)), "k-",
            label=f"noise {sig:.3g} {label}")
    ref = 0.0
    if result.injected is not None:
        ref = float(np.mean(result.injected)) * scale
    ax.axvline(ref, color="k", ls="--", label="injected" if result.injected is not None else "zero")
    if result.target_flux_jy is not None and np.isfinite(result.target_flux_jy):
        ax.axvline(result.target_flux_jy * scale, color="C3", ls=":", label="targets")
    bias = result.bias_jy * scale if result.bias_jy is not None else float("nan")
    ax.set_xlabel(f"stacked flux density [{label}]")
    ax.set_ylabel("probability density")
    ax.set_title(f"{result.method}: R={result.realizations}, N={result.n_positions}, "
                 f"bias {bias:.3g} {label}", fontsize=9)
    ax.legend(fontsize=8)
    return _save(fig, path, overwrite)


def plot_profiles(result: Any, path: str | os.PathLike, *, overwrite: bool = False,
                  unit: str = "uJy") -> Path:
    """Stacked Re V against uv distance for every realisation (thin lines), their mean and
    the injected flux: baselines where the mean departs from the injected flux are the ones
    corrupted by residuals (paper Fig. 9)."""
    prof = result.profile
    if not prof:
        raise XstackError("no uv-profiles in this result (run with profile_bins > 0, mc or random)")
    scale = {"Jy": 1.0, "mJy": 1e3, "uJy": 1e6}[unit]
    plt = _figure()
    q = np.asarray(prof["q_klambda"])
    vals = np.asarray(prof["values"]) * scale
    fig, ax = plt.subplots(figsize=(6.0, 4.0))
    for row in vals[: min(len(vals), 50)]:
        ax.plot(q, row, color="0.7", lw=0.6)
    ax.plot(q, np.nanmean(vals, axis=0), "k-", lw=2, label="mean of realisations")
    if prof.get("injected") is not None:
        ax.axhline(float(np.mean(prof["injected"])) * scale, color="C0", ls="--", label="injected")
    else:
        ax.axhline(0.0, color="C0", ls="--")
    ax.set_xlabel("uv distance [kλ]")
    ax.set_ylabel(f"stacked Re V [{unit.replace('uJy', 'µJy')}]")
    ax.set_title(f"uv-profiles of {len(vals)} {result.method} stacks", fontsize=9)
    ax.legend(fontsize=8)
    return _save(fig, path, overwrite)


def _save(fig: Any, path: str | os.PathLike, overwrite: bool) -> Path:
    """Lay out ``fig``, write it as a PNG atomically, and free it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    with atomic_output(path, overwrite=overwrite) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)
    return Path(path)
