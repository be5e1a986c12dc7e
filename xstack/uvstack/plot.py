"""Pictures of uv-profiles (the paper's Figs 5, 7, 9 and 10): Re V and Im V against uv distance.

Light on purpose: numpy and, when a figure is drawn, matplotlib - no dask, xarray or numba -
so a command's plotting process (:mod:`xstack.cli._plotter`) starts in a fraction of a
second. The profiles themselves are made in :mod:`xstack.uvstack.profile`.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from astropy.table import Table


def profile_scale(table: Table) -> tuple[float, str]:
    """Plot scale and unit for a profile's visibilities: (1e6, "µJy"), or (1e3, "mJy") above 1 mJy."""
    re = np.asarray(table["re_jy"])
    if np.nanmax(np.abs(np.concatenate([re, [0.0]]))) > 1e-3:
        return 1e3, "mJy"
    return 1e6, "µJy"


def draw_uv_profile(ax: Any, table: Table, *, scale: float, unit: str) -> None:
    """Draw a :func:`uv_profile` table on matplotlib Axes ``ax``.

    Re V (circles, data line ``gid="re"``) and Im V (squares, ``gid="im"``) with 1σ errors
    against the bin center in kλ, a zero line, and the axis labels. The visibilities are
    multiplied by ``scale`` (e.g. 1e6 for µJy; ``unit`` is its label).
    """
    x = np.asarray(table["uvdist_klambda"])
    re = ax.errorbar(x, np.asarray(table["re_jy"]) * scale,
                     yerr=np.asarray(table["re_err_jy"]) * scale, fmt="o", ms=4, color="C0",
                     label="Re V")
    im = ax.errorbar(x, np.asarray(table["im_jy"]) * scale,
                     yerr=np.asarray(table["im_err_jy"]) * scale, fmt="s", ms=3, color="C3",
                     alpha=0.6, label="Im V")
    re.lines[0].set_gid("re")
    im.lines[0].set_gid("im")
    ax.axhline(0.0, color="0.5", lw=0.8)
    ax.set_xlabel("uv distance [kλ]")
    ax.set_ylabel(f"visibility [{unit}]")


def save_png(fig: Any, path: str | os.PathLike, *, overwrite: bool) -> str:
    """Write a matplotlib Figure to ``path`` as PNG atomically; returns ``path`` as str."""
    from xstack._atomic import atomic_output

    path = os.fspath(path)
    with atomic_output(path, overwrite=overwrite) as tmp:
        fig.savefig(str(tmp), format="png")
    return path


def uv_profile_figure(table: Table, *, title: str | None = None,
                      flux_jy: float | None = None) -> Any:
    """A matplotlib Figure of Re V and Im V with error bars against uv distance (kλ), drawn
    without pyplot (no display needed); ``flux_jy`` adds the stacked flux as a dashed line."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.2), dpi=110)
    ax = fig.add_subplot(111)
    scale, unit = profile_scale(table)
    draw_uv_profile(ax, table, scale=scale, unit=unit)
    if flux_jy is not None:
        ax.axhline(flux_jy * scale, color="C0", ls="--", lw=0.8, label="stacked flux")
    if title:
        ax.set_title(title)
    ax.legend(frameon=False)
    fig.tight_layout()
    return fig


def plot_uv_profile(table: Table, path: str | os.PathLike, *, title: str | None = None,
                    overwrite: bool = True, flux_jy: float | None = None) -> str:
    """Plot Re V and Im V with error bars against uv distance (kλ) to a PNG (Agg backend),
    atomically; returns ``path`` as str (:func:`uv_profile_figure`)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    fig = uv_profile_figure(table, title=title, flux_jy=flux_jy)
    return save_png(fig, path, overwrite=overwrite)
