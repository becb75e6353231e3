"""Pictures of a synthetic drive for people: a contact sheet of frames and a bird's-eye map of the world."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.axes import Axes  # noqa: E402
from matplotlib.patches import Circle, FancyArrow, Patch, Polygon, Rectangle  # noqa: E402

from drivesim.stages.synth import textures  # noqa: E402
from drivesim.stages.synth.drive import Trajectory  # noqa: E402
from drivesim.stages.synth.scenery import CURB_TOP_WIDTH_M, road_half_width_m, sidewalk_outer_m  # noqa: E402
from drivesim.stages.synth.world import SynthWorld  # noqa: E402

GRASS = "#7f9a5a"
ASPHALT = "#5b5d61"
PAVING = "#c9c6bf"
CURB = "#e4e2dc"


def write_contact_sheet(thumbs: list[tuple[float, np.ndarray]], path: Path, title: str) -> None:
    """A grid (3 columns) of frames, each labelled with its time since the start of the drive."""
    cols = 3
    rows = max(1, int(np.ceil(len(thumbs) / cols)))
    h, w = thumbs[0][1].shape[:2] if thumbs else (200, 320)
    fig_w = 13.0
    fig_h = fig_w * rows * h / (cols * w) + 0.6
    fig, axes = plt.subplots(rows, cols, figsize=(fig_w, fig_h), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (t, img) in zip(axes.ravel(), thumbs, strict=False):
        ax.imshow(img)
        ax.text(
            0.02,
            0.96,
            f"t = {t:5.1f} s",
            transform=ax.transAxes,
            va="top",
            ha="left",
            fontsize=10,
            color="white",
            bbox={"facecolor": "black", "alpha": 0.55, "pad": 2, "edgecolor": "none"},
        )
    fig.suptitle(title, fontsize=13)
    fig.subplots_adjust(left=0.005, right=0.995, bottom=0.005, top=1 - 0.45 / fig_h, wspace=0.01, hspace=0.01)
    fig.savefig(path, format="png", dpi=100)
    plt.close(fig)


def _band(world: SynthWorld, lat_a: float, lat_b: float, s0: float, s1: float) -> np.ndarray:
    s = np.arange(s0, s1, 1.0)
    pts, _, n = world.road.frames(s)
    return np.concatenate([pts + lat_a * n, (pts + lat_b * n)[::-1]])


def write_map(
    world: SynthWorld, traj: Trajectory, duration_s: float, gps: dict[str, np.ndarray] | None, path: Path
) -> None:
    """Bird's-eye map around the drive: road, lane lines, sidewalks, buildings, trees, parked cars, the driven path,
    GPS fixes, a north arrow and a scale bar."""
    t = np.linspace(0.0, duration_s, 200)
    st = traj.state(t)
    margin = 45.0
    x0, x1 = st["x_m"].min() - margin, st["x_m"].max() + margin
    y0, y1 = st["y_m"].min() - margin, st["y_m"].max() + margin
    span = max(x1 - x0, y1 - y0, 120.0)
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    x0, x1, y0, y1 = cx - span / 2, cx + span / 2, cy - span / 2, cy + span / 2

    fig, ax = plt.subplots(figsize=(9, 9))
    ax.set_facecolor(GRASS)
    _draw_road(ax, world, span)
    _draw_layout(ax, world)
    if gps is not None:
        ax.plot(
            gps["true_enu_m"][:, 0] + gps["error_enu_m"][:, 0],
            gps["true_enu_m"][:, 1] + gps["error_enu_m"][:, 1],
            ".",
            color="#ffd23f",
            ms=3,
            label="GPS fixes",
        )
    ax.plot(st["x_m"], st["y_m"], color="#e8412c", lw=2.2, label="driven path (right lane centre)")
    ax.plot(st["x_m"][0], st["y_m"][0], "o", color="#e8412c", ms=8, mec="white", label="start")
    ax.annotate(
        "",
        xy=(st["x_m"][-1], st["y_m"][-1]),
        xytext=(st["x_m"][-5], st["y_m"][-5]),
        arrowprops={"arrowstyle": "-|>", "color": "#e8412c", "lw": 2.2, "mutation_scale": 18},
    )
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    _draw_north_and_scale(ax, (x0, x1, y0, y1), span)
    handles, _ = ax.get_legend_handles_labels()
    handles += [
        Patch(facecolor=(0.75, 0.7, 0.64), edgecolor="#4a4038", label="buildings"),
        Patch(facecolor="#2f5e24", label="trees"),
        Patch(facecolor=(0.55, 0.06, 0.06), edgecolor="black", label="parked cars"),
        Patch(facecolor=ASPHALT, label="road (two lanes + parking)"),
        Patch(facecolor=PAVING, label="sidewalks"),
    ]
    ax.legend(handles=handles, loc="upper left", fontsize=9, framealpha=0.85)
    ax.set_title(
        f"synthetic world, seed {world.seed}: {world.road.length_m:.0f} m of road, "
        f"{len(world.layout.buildings)} buildings, {len(world.layout.trees)} trees, "
        f"{len(world.layout.cars)} parked cars",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=110)
    plt.close(fig)


def _draw_road(ax: Axes, world: SynthWorld, span: float) -> None:
    """Sidewalks, curbs, asphalt, the edge lines and the dashed centre line, on a map `span` metres wide."""
    road_cfg = world.config.road
    s0, s1 = 0.0, world.road.length_m
    half = road_half_width_m(road_cfg)
    outer = sidewalk_outer_m(road_cfg)
    for side in (1.0, -1.0):
        ax.add_patch(Polygon(_band(world, side * (half + CURB_TOP_WIDTH_M), side * outer, s0, s1), color=PAVING, lw=0))
        ax.add_patch(Polygon(_band(world, side * half, side * (half + CURB_TOP_WIDTH_M), s0, s1), color=CURB, lw=0))
    ax.add_patch(Polygon(_band(world, half, -half, s0, s1), color=ASPHALT, lw=0))
    s = np.arange(s0, s1, 0.5)
    pts, _, n = world.road.frames(s)
    lw = 72.0 * textures.LINE_WIDTH_M * 9.0 / span * 4  # line width in points, roughly to scale
    for side in (1.0, -1.0) if road_cfg.edge_lines else ():
        edge = pts + side * road_cfg.lane_width_m * n
        ax.plot(edge[:, 0], edge[:, 1], color="white", lw=max(lw, 0.6), solid_capstyle="butt")
    dash_on = (s % textures.DASH_PERIOD_M) < textures.DASH_LENGTH_M
    centre = pts.copy()
    centre[~dash_on] = np.nan
    ax.plot(centre[:, 0], centre[:, 1], color="white", lw=max(lw, 0.6), solid_capstyle="butt")


def _draw_layout(ax: Axes, world: SynthWorld) -> None:
    """The buildings (shaded by height), trees and parked cars seen from above."""
    for b in world.layout.buildings:
        corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * [b.length_m / 2, b.depth_m / 2]
        c, sn = np.cos(b.yaw_rad), np.sin(b.yaw_rad)
        xy = corners @ np.array([[c, sn], [-sn, c]]) + [b.x_m, b.y_m]
        shade = 0.55 + 0.35 * (b.height_m - 6.0) / 16.0
        ax.add_patch(Polygon(xy, facecolor=(shade * 0.95, shade * 0.88, shade * 0.8), edgecolor="#4a4038", lw=0.8))
    for tree in world.layout.trees:
        ax.add_patch(
            Circle(
                (tree.x_m, tree.y_m), tree.crown_radius_m, facecolor="#2f5e24", edgecolor="#1f3f18", lw=0.5, alpha=0.9
            )
        )
    for car in world.layout.cars:
        rect = Rectangle(
            (-car.length_m / 2, -car.width_m / 2),
            car.length_m,
            car.width_m,
            facecolor=car.rgb,
            edgecolor="black",
            lw=0.5,
        )
        tr = matplotlib.transforms.Affine2D().rotate(car.yaw_rad).translate(car.x_m, car.y_m) + ax.transData
        rect.set_transform(tr)
        ax.add_patch(rect)


def _draw_north_and_scale(ax: Axes, limits: tuple[float, float, float, float], span: float) -> None:
    """A north arrow in the top-right corner and a scale bar in the bottom-left one of the map `limits`."""
    x0, x1, y0, y1 = limits
    ax.add_patch(
        FancyArrow(
            x1 - 0.07 * span,
            y1 - 0.16 * span,
            0,
            0.09 * span,
            width=0.012 * span,
            head_width=0.035 * span,
            head_length=0.03 * span,
            color="black",
            length_includes_head=True,
        )
    )
    ax.text(x1 - 0.07 * span, y1 - 0.19 * span, "N", ha="center", va="center", fontsize=13, weight="bold")
    bar = _nice_length(span / 5)
    bx, by = x0 + 0.05 * span, y0 + 0.05 * span
    ax.add_patch(Rectangle((bx, by), bar, 0.008 * span, color="black"))
    ax.add_patch(Rectangle((bx, by), bar / 2, 0.008 * span, color="white", ec="black", lw=0.8))
    ax.text(
        bx + bar / 2,
        by + 0.02 * span,
        f"{bar:g} m",
        ha="center",
        va="bottom",
        fontsize=10,
        bbox={"facecolor": "white", "alpha": 0.7, "edgecolor": "none", "pad": 1},
    )


def _nice_length(length_m: float) -> float:
    """The largest 1-2-5 number not above `length_m`."""
    exp = 10 ** np.floor(np.log10(length_m))
    for m in (5, 2, 1):
        if m * exp <= length_m:
            return float(m * exp)
    return float(exp)
