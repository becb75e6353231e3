"""The evaluation's figures, like the paper's: breakdown bars (Fig. 4), clearance analysis (Fig. 5), intervention
rate and deviation along the track, relative trajectories with the final polygons of intervention episodes (Fig. 6),
and, for car following, the tracking error by track position. Each function writes one PNG (matplotlib, Agg)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from drivesim.stages.evaluate.metrics import (
    LEVELS,
    EpisodeResult,
    LevelBreakdown,
    clearance_recall,
    relative_to_other,
    step_clearances,
)

FACTOR_LABELS = {
    "road_curvature": "road curvature",
    "front_car_speed": "front car speed",
    "initial_lateral": "initial lateral difference",
}
DPI = 110


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_breakdowns(items: Sequence[LevelBreakdown], path: Path) -> Path:
    """Fig. 4: intervention rate (left) and mean maximum deviation (right) per level, one bar group per factor,
    with 95 % confidence intervals as error bars."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), layout="constrained")
    x = np.arange(len(LEVELS))
    width = 0.8 / max(len(items), 1)
    for ax, attr, label in zip(
        axes, ("intervention", "max_deviation_m"), ("intervention rate", "max deviation (m)"), strict=True
    ):
        for k, item in enumerate(items):
            estimates = getattr(item, attr)
            values = np.array([e.value for e in estimates], dtype=float)
            low = np.array([e.ci_low for e in estimates], dtype=float)
            high = np.array([e.ci_high for e in estimates], dtype=float)
            err = np.nan_to_num(np.stack([values - low, high - values]), nan=0.0)
            offset = (k - (len(items) - 1) / 2) * width
            ax.bar(x + offset, np.nan_to_num(values), width, yerr=err, capsize=2, label=FACTOR_LABELS[item.factor])
        ax.set_xticks(x, [level.capitalize() for level in LEVELS])
        ax.set_ylabel(label)
        ax.grid(axis="y", linestyle="--", alpha=0.5)
    axes[0].set_ylim(bottom=0)
    axes[0].legend(fontsize=8)
    axes[0].set_title("intervention by trial difficulty", fontsize=10)
    axes[1].set_title("maximum deviation by trial difficulty", fontsize=10)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def plot_clearance(results: Sequence[EpisodeResult], path: Path, below_m: float = 2.0) -> Path:
    """Fig. 5: histogram of the per-step clearance below `below_m` (left) and the fraction of trials whose minimum
    clearance is at most c (right)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6), layout="constrained")
    steps = step_clearances(results, below_m)
    axes[0].hist(steps, bins=np.linspace(0.0, below_m, 41), color="tab:blue")
    axes[0].set_xlabel("clearance (m)")
    axes[0].set_ylabel("steps")
    axes[0].set_title(f"clearance of the steps below {below_m:g} m ({steps.size} steps)", fontsize=10)
    thresholds = np.linspace(0.0, below_m, 201)
    mins = np.array([r.metrics.min_clearance_m for r in results], dtype=float)
    recall = clearance_recall(mins, thresholds)
    axes[1].plot(thresholds, recall, color="tab:orange")
    axes[1].set_xlabel("clearance c (m)")
    axes[1].set_ylabel("trials with min clearance <= c")
    axes[1].set_ylim(0, 1.02)
    axes[1].set_title("cumulative recall of trials", fontsize=10)
    for ax in axes:
        ax.grid(linestyle="--", alpha=0.5)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def plot_track(
    x_m: np.ndarray, y_m: np.ndarray, along: dict[str, np.ndarray], path: Path, tracking: bool = False
) -> Path:
    """Fig. 6 left and middle: the world's path from above, each frame coloured by the intervention rate of the
    episodes visiting it and by the mean |deviation| there (grey: no episode visited); with `tracking`, a third
    panel with the mean tracking error (car following)."""
    plt = _plt()
    panels = [
        ("intervention_rate", "intervention rate", "viridis"),
        ("deviation_m", "deviation from centre (m)", "magma"),
    ]
    if tracking:
        panels.append(("tracking_error_m", "tracking error (m)", "plasma"))
    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.4), layout="constrained", squeeze=False)
    for ax, (key, title, cmap) in zip(axes[0], panels, strict=True):
        values = along[key]
        seen = np.isfinite(values)
        ax.plot(x_m, y_m, color="0.8", linewidth=4, zorder=1)
        if seen.any():
            sc = ax.scatter(x_m[seen], y_m[seen], c=values[seen], cmap=cmap, s=10, zorder=2, vmin=0)
            fig.colorbar(sc, ax=ax, shrink=0.8)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def plot_relative(results: Sequence[EpisodeResult], path: Path, max_episodes: int = 200) -> Path:
    """Fig. 6 right: the ego's trajectory relative to the front car (front car at the origin, heading up) and both
    footprints at the last step, for the episodes with an intervention (all episodes, faintly, when none had one)."""
    from matplotlib.patches import Polygon as PolygonPatch

    from drivesim.sim.footprint import footprint

    plt = _plt()
    with_car = [r for r in results if np.isfinite(r.metrics.min_clearance_m)]
    chosen = [r for r in with_car if r.metrics.intervention]
    title = f"relative trajectories, {len(chosen)} intervention episodes"
    faint = not chosen
    if faint:
        chosen = with_car
        title = f"relative trajectories, no interventions ({len(chosen)} episodes)"
    chosen = chosen[:max_episodes]
    fig, ax = plt.subplots(figsize=(4.8, 7.0), layout="constrained")
    alpha = 0.15 if faint else 0.5
    for r in chosen:
        rel = relative_to_other(r.record)
        ok = np.all(np.isfinite(rel), axis=1)
        rel = rel[ok]
        if rel.size == 0:
            continue
        # Plot with the front car's forward axis up: screen x = -y_left (right), screen y = x_forward.
        ax.plot(-rel[:, 1], rel[:, 0], color="tab:blue", alpha=alpha, linewidth=0.8)
        if not faint:
            ep = r.record.episode
            ego = footprint(rel[-1, 0], rel[-1, 1], rel[-1, 2], ep["ego_length_m"], ep["ego_width_m"])
            other = footprint(0.0, 0.0, 0.0, ep["other_length_m"], ep["other_width_m"])
            for poly, color in ((other, "tab:orange"), (ego, "tab:blue")):
                xy = np.asarray(poly.exterior.coords)
                ax.add_patch(PolygonPatch(np.c_[-xy[:, 1], xy[:, 0]], closed=True, fc=color, ec=color, alpha=0.25))
    ep0 = chosen[0].record.episode if chosen else {"other_length_m": 4.5, "other_width_m": 1.8}
    front = footprint(0.0, 0.0, 0.0, ep0["other_length_m"], ep0["other_width_m"])
    xy = np.asarray(front.exterior.coords)
    ax.add_patch(PolygonPatch(np.c_[-xy[:, 1], xy[:, 0]], closed=True, fc="none", ec="tab:orange", lw=1.5))
    ax.set_xlim(-6, 6)
    ax.set_ylim(-20, 10)
    ax.set_aspect("equal")
    ax.set_xlabel("lateral (m, right +)")
    ax.set_ylabel("longitudinal (m, ahead of the front car +)")
    ax.set_title(title, fontsize=10)
    ax.grid(linestyle="--", alpha=0.4)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def plot_tracking(arc_length_m: np.ndarray, along: dict[str, np.ndarray], path: Path) -> Path:
    """Car following: the mean tracking error at every position of the track (paper §IV-B, car following)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 3.2), layout="constrained")
    err = along["tracking_error_m"]
    ok = np.isfinite(err)
    ax.plot(arc_length_m[ok], err[ok], ".-", markersize=3)
    ax.set_xlabel("track position (m along the recorded path)")
    ax.set_ylabel("mean tracking error (m)")
    ax.set_title("tracking error by track position", fontsize=10)
    ax.grid(linestyle="--", alpha=0.5)
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path
