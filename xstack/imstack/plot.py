"""PNG of a stacked stamp in the style of the paper's Fig. 3 (matplotlib, Agg backend).

Left: the stacked stamp with contours; right: the same with the central mask blanked (what
the local noise is measured on). Axes are arcsec offsets (east to the left), the restoring
beam is drawn in the lower-left corner.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np


def unit_scale(values: np.ndarray) -> tuple[float, str]:
    """Display scale and unit label (Jy, mJy, uJy, nJy) for values in Jy."""
    peak = float(np.nanmax(np.abs(values))) if np.isfinite(values).any() else 1.0
    for scale, label in ((1.0, "Jy"), (1e-3, "mJy"), (1e-6, r"$\mu$Jy"), (1e-9, "nJy")):
        if peak >= scale:
            return scale, label
    return 1e-9, "nJy"


def plot_stack(result: Any, path: str | os.PathLike) -> None:
    """Write a PNG of ``result.stacked`` (an :class:`~xstack.imstack.stack.ImstackResult`)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure
    from matplotlib.patches import Ellipse

    stacked = result.stacked
    data = np.asarray(stacked.values, dtype=np.float64)
    x = np.asarray(stacked.x.values)
    y = np.asarray(stacked.y.values)
    dx = (x[1] - x[0]) if x.size > 1 else 1.0
    dy = (y[1] - y[0]) if y.size > 1 else 1.0
    extent = (x[0] - dx / 2, x[-1] + dx / 2, y[0] - dy / 2, y[-1] + dy / 2)
    scale, unit = unit_scale(data)
    rms = result.stamp_rms_jy
    radius = result.mask_radius_arcsec
    xx, yy = np.meshgrid(x, y)
    masked = np.where(np.hypot(xx, yy) <= radius, np.nan, data)

    fig = Figure(figsize=(10, 4.6), dpi=100)
    axes = fig.subplots(1, 2)
    vmin, vmax = np.nanmin(data) / scale, np.nanmax(data) / scale
    for ax, img, title in ((axes[0], data, "stacked stamp"),
                           (axes[1], masked, "central mask blanked")):
        im = ax.imshow(img / scale, origin="lower", extent=extent, cmap="viridis", vmin=vmin,
                       vmax=vmax, interpolation="nearest")
        if np.isfinite(rms) and rms > 0:
            pos = [k * rms / scale for k in (3, 5, 10, 20, 50) if k * rms < np.nanmax(data)]
            neg = [-k * rms / scale for k in (5, 3) if -k * rms > np.nanmin(data)]
            if pos:
                ax.contour(x, y, img / scale, levels=pos, colors="white", linewidths=0.8)
            if neg:
                ax.contour(x, y, img / scale, levels=neg, colors="white", linewidths=0.8,
                           linestyles="dashed")
        if result.beam_arcsec:
            bmaj, bmin, bpa = result.beam_arcsec
            # matplotlib angle is counter-clockwise from +x; with east to the left (x decreasing)
            # a position angle east of north is an angle of 90 + bpa from the +x axis on screen
            sign = -1.0 if dx < 0 else 1.0
            cx = extent[0] + 0.12 * (extent[1] - extent[0])
            cy = extent[2] + 0.12 * (extent[3] - extent[2])
            ax.add_patch(Ellipse((cx, cy), bmin, bmaj, angle=-sign * bpa, facecolor="none",
                                 edgecolor="white", linewidth=1.2))
        ax.set_xlabel("offset east (arcsec)" if dx < 0 else "x offset (arcsec)")
        ax.set_ylabel("offset north (arcsec)")
        ax.set_title(title)
        fig.colorbar(im, ax=ax, label=f"{unit}/beam", shrink=0.85)
    subtitle = (f"{result.method}, weighting {result.weighting}, "
                f"{result.subpixel or 'nearest-pixel'} alignment, N = {result.n_positions}: "
                f"{result.flux_jy / scale:.4g} ± {result.flux_err_jy / scale:.2g} {unit}/beam")
    fig.suptitle(subtitle, fontsize=10)
    fig.tight_layout()
    with open(path, "wb") as fh:
        fig.savefig(fh, format="png")
