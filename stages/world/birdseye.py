"""The bird's-eye PNG of the reference path, coloured by curvature, for people to look at."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_birdseye(
    path: Path,
    x_m: np.ndarray,
    y_m: np.ndarray,
    yaw_rad: np.ndarray,
    curvature_1pm: np.ndarray,
    lane_width_m: float,
    title: str,
) -> None:
    """Plot the path from above (east/north, equal aspect) coloured by curvature, on its lane drawn to scale, with
    start and end markers, a colour bar in 1/m and a scale bar in metres."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection
    from matplotlib.colors import TwoSlopeNorm
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    x = np.asarray(x_m, dtype=float)
    y = np.asarray(y_m, dtype=float)
    k = np.asarray(curvature_1pm, dtype=float)
    span_m = max(float(np.ptp(x)), float(np.ptp(y)), 10.0)
    limit = max(float(np.max(np.abs(k))), 1e-3)

    fig, ax = plt.subplots(figsize=(7.0, 6.0), layout="constrained")
    segments = np.stack([np.column_stack([x[:-1], y[:-1]]), np.column_stack([x[1:], y[1:]])], axis=1)
    lines = LineCollection(
        segments, cmap="coolwarm_r", norm=TwoSlopeNorm(vcenter=0.0, vmin=-limit, vmax=limit), linewidths=3.0
    )
    lines.set_array(0.5 * (k[:-1] + k[1:]))
    # The ego lane as a band in data units under the path, so its width is to scale.
    yaw = np.asarray(yaw_rad, dtype=float)
    left = np.column_stack([-np.sin(yaw), np.cos(yaw)]) * (0.5 * lane_width_m)
    outline = np.vstack([np.column_stack([x, y]) + left, (np.column_stack([x, y]) - left)[::-1]])
    ax.fill(outline[:, 0], outline[:, 1], color="0.88", zorder=0, label=f"lane ({lane_width_m:g} m)")
    ax.add_collection(lines)
    ax.plot(x[0], y[0], "o", color="tab:green", markersize=9, label="start", zorder=3)
    ax.plot(x[-1], y[-1], "s", color="black", markersize=8, label="end", zorder=3)
    # An arrow from the start along the first tenth of the view's span shows the driving direction.
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    tip = int(min(np.searchsorted(travelled, 0.1 * span_m), len(x) - 1))
    if tip > 0:
        ax.annotate(
            "",
            xy=(x[tip], y[tip]),
            xytext=(x[0], y[0]),
            arrowprops={"arrowstyle": "-|>", "color": "tab:green", "lw": 2.0, "shrinkA": 6},
            zorder=4,
        )
    pad = 0.08 * span_m + lane_width_m
    cx, cy = 0.5 * (x.min() + x.max()), 0.5 * (y.min() + y.max())
    half = 0.5 * span_m + pad
    ax.set_xlim(cx - half, cx + half)
    ax.set_ylim(cy - half, cy + half)
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.grid(True, color="0.92")
    bar_m = _round_length(0.2 * span_m)
    ax.add_artist(
        AnchoredSizeBar(ax.transData, bar_m, f"{bar_m:g} m", "lower right", pad=0.6, frameon=False, size_vertical=0)
    )
    colorbar = fig.colorbar(lines, ax=ax, shrink=0.85)
    colorbar.set_label("curvature (1/m), + = left turn")
    ax.legend(loc="best", framealpha=0.9)
    ax.set_title(title, fontsize=10)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _round_length(length_m: float) -> float:
    """The largest 1, 2 or 5 times a power of ten not above `length_m`."""
    power = 10.0 ** np.floor(np.log10(max(length_m, 1e-3)))
    for step in (5.0, 2.0, 1.0):
        if step * power <= length_m:
            return step * power
    return power
