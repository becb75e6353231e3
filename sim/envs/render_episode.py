"""One episode driven by the privileged expert, rendered for people: MP4, a PNG strip of the pass, a bird's-eye plot."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

STRIP_FRAMES = 6


def render_episode(
    task: str, world: Path, meshes: Path | None, out: Path, seed: int, mcap: bool = False
) -> dict[str, Any]:
    """Drive one episode of `task` with the expert at the world's full image size; write the three files, and with
    `mcap` the episode for Foxglove as `episode.mcap` (sim/episode_mcap.py)."""
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drivesim.sim.envs.registry import task_spec
    from drivesim.sim.episode_mcap import EpisodeCapture, Road, write_episode_mcap
    from drivesim.sim.footprint import footprint
    from drivesim.sim.world import World

    w = World.load(world)
    config = {
        "roi_px": (0, 0, w.width_px, w.height_px),
        "observation_width_px": w.width_px,
        "observation_height_px": w.height_px,
    }
    env = task_spec(task).env_class()(
        world=w, meshes=None if meshes is None else str(meshes), mode="eval", config=config
    )
    obs, info = env.reset(seed=seed)
    frames, states = [np.ascontiguousarray(obs.transpose(1, 2, 0))], [info["state"]]
    capture = EpisodeCapture(seed, task) if mcap else None
    if capture is not None:
        capture.add(obs, info, 0.0)
    while True:
        action = env.expert_action()
        obs, _, terminated, truncated, info = env.step(action)
        if capture is not None:
            capture.add(obs, info, float(action[0]))
        frames.append(np.ascontiguousarray(obs.transpose(1, 2, 0)))
        states.append(info["state"])
        if terminated or truncated:
            break
    outcome = "success" if info["success"] else ",".join(k for k, v in info["termination"].items() if v)
    out.mkdir(parents=True, exist_ok=True)
    h, wd = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(out / "episode.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 10, (wd, h))
    for f in frames:
        writer.write(cv2.cvtColor(np.ascontiguousarray(f), cv2.COLOR_RGB2BGR))
    writer.release()
    # The strip: frames while the other car is between 25 m ahead and 5 m behind (the approach and the pass).
    rel = np.array([s["other_rel_x_m"] for s in states])
    near = np.flatnonzero((rel < 25.0) & (rel > -5.0)) if np.isfinite(rel).any() else np.arange(len(frames))
    near = near if len(near) else np.arange(len(frames))
    picks = near[np.linspace(0, len(near) - 1, min(STRIP_FRAMES, len(near))).round().astype(int)]
    strip = np.ascontiguousarray(np.concatenate([frames[i] for i in picks], axis=1))
    for k, i in enumerate(picks):
        cv2.putText(strip, f"t={states[i]['t_s']:.1f}s", (k * wd + 4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 0))
    cv2.imwrite(str(out / "strip.png"), cv2.cvtColor(strip, cv2.COLOR_RGB2BGR))
    # Bird's-eye: the recorded path, both trajectories, footprints every second.
    fig, ax = plt.subplots(figsize=(8, 8))
    path = w.path
    ax.plot(path["x_m"], path["y_m"], color="0.7", lw=6, label="recorded path (lane centre)", zorder=0)
    ex, ey = [s["ego_x_m"] for s in states], [s["ego_y_m"] for s in states]
    ax.plot(ex, ey, color="tab:blue", label="ego (expert)")
    has_other = np.isfinite(states[0]["other_x_m"])
    if has_other:
        ax.plot([s["other_x_m"] for s in states], [s["other_y_m"] for s in states], color="tab:red", label="other car")
    ep = info if "episode" in info else None
    sizes = env._episode if ep is None else ep["episode"]
    for i in range(0, len(states), 10):
        s = states[i]
        poly = footprint(s["ego_x_m"], s["ego_y_m"], s["ego_yaw_rad"], sizes["ego_length_m"], sizes["ego_width_m"])
        ax.fill(*poly.exterior.xy, color="tab:blue", alpha=0.25)
        if has_other:
            o = footprint(
                s["other_x_m"], s["other_y_m"], s["other_yaw_rad"], sizes["other_length_m"], sizes["other_width_m"]
            )
            ax.fill(*o.exterior.xy, color="tab:red", alpha=0.25)
            ax.plot([s["ego_x_m"], s["other_x_m"]], [s["ego_y_m"], s["other_y_m"]], color="0.5", lw=0.5, ls=":")
    pad = 10.0
    xs = ex + ([s["other_x_m"] for s in states] if has_other else [])
    ys = ey + ([s["other_y_m"] for s in states] if has_other else [])
    ax.set_xlim(min(xs) - pad, max(xs) + pad)
    ax.set_ylim(min(ys) - pad, max(ys) + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, east)")
    ax.set_ylabel("y (m, north)")
    ax.set_title(f"{task}, seed {seed}: {outcome}; footprints every 1 s")
    ax.legend(loc="best")
    fig.savefig(out / "birdseye.png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    clearance = min(s["clearance_m"] for s in states)
    summary = {"task": task, "seed": seed, "steps": len(states) - 1, "outcome": outcome, "min_clearance_m": clearance}
    (out / "summary.json").write_text(json.dumps({**summary, "min_clearance_m": _finite(clearance)}))
    if capture is not None:
        road = Road.from_world(world, env.config.max_lateral_m)
        write_episode_mcap(capture, road, out / "episode.mcap", f"{task} seed {seed}")
    return summary


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None
