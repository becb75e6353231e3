"""One episode driven by the privileged expert, rendered for people: MP4, a PNG strip of the pass, a bird's-eye plot."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

STRIP_FRAMES = 6


def render_episode(
    task: str,
    world: Path,
    meshes: Path | None,
    out: Path,
    seed: int,
    mcap: bool = False,
    env_config: dict[str, Any] | None = None,
    size_px: tuple[int, int] | None = None,
    policy: Any = None,
) -> dict[str, Any]:
    """Drive one episode of `task` with the expert or `policy`; write the whole camera image as the MP4, the strip
    and the bird's-eye plot, and with `mcap` the episode for Foxglove as `episode.mcap` (sim/episode_mcap.py).

    :param env_config: env keys over the task's own settings (`default_config()`); a policy's own training env
        config (its view) belongs here.
    :param size_px: (width, height) of the written frames; default: the recording's (`recording_size_px`).
    :param policy: who drives: None, the privileged expert; else an object with `initial_state(n)` and
        `predict(obs, state, episode_start, deterministic)` (a run's `LoadedPolicy`, an `OnnxPolicy`) that sees its
        own observation while the written frames show the whole image.
    """
    from drivesim.sim.envs.registry import task_spec
    from drivesim.sim.episode_mcap import EpisodeCapture, Road, write_episode_mcap
    from drivesim.sim.world import World

    w = World.load(world)
    width_px, height_px = size_px or recording_size_px(world, w.width_px, w.height_px)
    if width_px < 16 or height_px < 16:
        raise ValueError(f"size {width_px}x{height_px}: frames must be at least 16x16 pixels")
    full_image = {"roi_px": (0, 0, w.width_px, w.height_px)}
    display = {**full_image, "observation_width_px": width_px, "observation_height_px": height_px}
    config = {**(env_config or {}), **(display if policy is None else {})}
    env = task_spec(task).env_class()(
        world=w, meshes=None if meshes is None else str(meshes), mode="eval", config=config
    )
    viewer = None if policy is None else _display_renderer(env, w, width_px, height_px)
    capture = EpisodeCapture(seed, task) if mcap else None
    frames, states, info = _drive(env, seed, capture, policy, viewer)
    outcome = "success" if info["success"] else ",".join(k for k, v in info["termination"].items() if v)
    out.mkdir(parents=True, exist_ok=True)
    _write_video(frames, out / "episode.mp4")
    _write_strip(frames, states, out / "strip.png")
    _plot_birdseye(w.path, states, env._episode, f"{task}, seed {seed}: {outcome}", out / "birdseye.png")
    clearance = min(s["clearance_m"] for s in states)
    summary = {"task": task, "seed": seed, "steps": len(states) - 1, "outcome": outcome, "min_clearance_m": clearance}
    summary["size_px"] = [int(width_px), int(height_px)]
    (out / "summary.json").write_text(json.dumps({**summary, "min_clearance_m": _finite(clearance)}))
    if capture is not None:
        road = Road.from_world(world, env.config.max_lateral_m)
        write_episode_mcap(capture, road, out / "episode.mcap", f"{task} seed {seed}")
    return summary


def recording_size_px(world: Path, width_px: int, height_px: int) -> tuple[int, int]:
    """The recording's image size (camera.json's source_width_px, source_height_px) of the world folder `world`;
    (width_px, height_px), the world's own, where camera.json does not say it."""
    camera = json.loads((Path(world) / "camera.json").read_text())
    source = camera.get("source_width_px"), camera.get("source_height_px")
    if all(isinstance(v, int) and v > 0 for v in source):
        return int(source[0]), int(source[1])
    return width_px, height_px


def _display_renderer(env: Any, world: Any, width_px: int, height_px: int) -> Any:
    """A view synthesizer of the world's whole image at width_px x height_px, with the env's render settings."""
    from drivesim.sim.simulator import make_view_synthesizer

    c = env.config
    roi = (0, 0, world.width_px, world.height_px)
    return make_view_synthesizer(
        world, roi, width_px, height_px, device=c.render_device, render_threads=c.render_threads,
        harmonizer=c.harmonizer,
    )  # fmt: skip


def _drive(env: Any, seed: int, capture: Any, policy: Any, viewer: Any) -> tuple[list[np.ndarray], list[dict], dict]:
    """One episode, the expert's or `policy`'s: (h, w, 3) frames (the env's observation, or `viewer`'s render of
    the ego's view when a policy drives), info["state"] per step, the last info."""
    from drivesim.sim.simulator import render_requests

    def frame(obs: np.ndarray) -> np.ndarray:
        if viewer is None:
            return np.ascontiguousarray(obs.transpose(1, 2, 0))
        return render_requests(viewer, [env.view_request()], {})[0]

    obs, info = env.reset(seed=seed)
    frames, states = [frame(obs)], [info["state"]]
    if capture is not None:
        capture.add(np.ascontiguousarray(frames[-1].transpose(2, 0, 1)), info, 0.0)
    state = None if policy is None else policy.initial_state(1)
    episode_start = np.ones(1, dtype=bool)
    while True:
        if policy is None:
            action = env.expert_action()
        else:
            action, state = policy.predict(obs[None], state, episode_start, deterministic=True)
            action = np.asarray(action, dtype=np.float32).reshape(-1)
            episode_start = np.zeros(1, dtype=bool)
        obs, _, terminated, truncated, info = env.step(action)
        frames.append(frame(obs))
        states.append(info["state"])
        if capture is not None:
            capture.add(np.ascontiguousarray(frames[-1].transpose(2, 0, 1)), info, float(action[0]))
        if terminated or truncated:
            return frames, states, info


def _write_video(frames: list[np.ndarray], path: Path) -> None:
    """The frames as a 10 Hz MP4; an odd width or height gets one more column or row, a copy of the last (the codec
    takes even sizes only and would drop it)."""
    import cv2

    h, w = frames[0].shape[:2]
    pad = ((0, h % 2), (0, w % 2), (0, 0))
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (w + w % 2, h + h % 2))
    for f in frames:
        writer.write(cv2.cvtColor(np.pad(f, pad, mode="edge") if h % 2 or w % 2 else f, cv2.COLOR_RGB2BGR))
    writer.release()


def _write_strip(frames: list[np.ndarray], states: list[dict], path: Path) -> None:
    """STRIP_FRAMES frames side by side while the other car is between 25 m ahead and 5 m behind (the approach and
    the pass); the whole episode's when there is no other car."""
    import cv2

    wd = frames[0].shape[1]
    rel = np.array([s.get("other_rel_x_m", math.nan) for s in states])
    near = np.flatnonzero((rel < 25.0) & (rel > -5.0)) if np.isfinite(rel).any() else np.arange(len(frames))
    near = near if len(near) else np.arange(len(frames))
    picks = near[np.linspace(0, len(near) - 1, min(STRIP_FRAMES, len(near))).round().astype(int)]
    strip = np.ascontiguousarray(np.concatenate([frames[i] for i in picks], axis=1))
    for k, i in enumerate(picks):
        cv2.putText(strip, f"t={states[i]['t_s']:.1f}s", (k * wd + 4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 0))
    cv2.imwrite(str(path), cv2.cvtColor(strip, cv2.COLOR_RGB2BGR))


def _plot_birdseye(path_xy: dict, states: list[dict], sizes: dict, title: str, out: Path) -> None:
    """The recorded path, both trajectories and their footprints every second."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from drivesim.sim.footprint import footprint

    fig, ax = plt.subplots(figsize=(8, 8))
    ax.plot(path_xy["x_m"], path_xy["y_m"], color="0.7", lw=6, label="recorded path (lane centre)", zorder=0)
    ex, ey = [s["ego_x_m"] for s in states], [s["ego_y_m"] for s in states]
    ax.plot(ex, ey, color="tab:blue", label="ego (expert)")
    has_other = "other_x_m" in states[0]
    ox = [s["other_x_m"] for s in states] if has_other else []
    oy = [s["other_y_m"] for s in states] if has_other else []
    if has_other:
        ax.plot(ox, oy, color="tab:red", label="other car")
    for s in states[::10]:
        poly = footprint(s["ego_x_m"], s["ego_y_m"], s["ego_yaw_rad"], sizes["ego_length_m"], sizes["ego_width_m"])
        ax.fill(*poly.exterior.xy, color="tab:blue", alpha=0.25)
        if has_other:
            o = footprint(
                s["other_x_m"], s["other_y_m"], s["other_yaw_rad"], sizes["other_length_m"], sizes["other_width_m"]
            )
            ax.fill(*o.exterior.xy, color="tab:red", alpha=0.25)
            ax.plot([s["ego_x_m"], s["other_x_m"]], [s["ego_y_m"], s["other_y_m"]], color="0.5", lw=0.5, ls=":")
    pad = 10.0
    ax.set_xlim(min(ex + ox) - pad, max(ex + ox) + pad)
    ax.set_ylim(min(ey + oy) - pad, max(ey + oy) + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, east)")
    ax.set_ylabel("y (m, north)")
    ax.set_title(f"{title}; footprints every 1 s")
    ax.legend(loc="best")
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None
