"""MP4s of chosen evaluation episodes: the policy's view beside a top-down sketch of both cars (OpenCV).

An episode depends only on its seed, so it is replayed (same env, same policy, same seed) rather than stored frame by
frame during the evaluation; the replay's metrics are the episode file's.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from drivesim.stages.evaluate.metrics import EpisodeResult
from drivesim.stages.evaluate.rollout import EnvFactory, PolicySpec

VIEW_SCALE = 4
SKETCH_M_PER_PX = 0.1
FPS = 10


def choose_episodes(results: Sequence[EpisodeResult], count: int) -> list[tuple[str, int]]:
    """(label, seed) of the `count` episodes to film: alternately the worst (interventions first, then the smallest
    clearance) and the best (successes first, then the largest clearance), without repeats."""

    def clearance(r: EpisodeResult) -> float:
        c = r.metrics.min_clearance_m
        return c if np.isfinite(c) else 1e9

    worst = sorted(results, key=lambda r: (not r.metrics.intervention, clearance(r), r.metrics.seed))
    best = sorted(results, key=lambda r: (not r.metrics.success, -clearance(r), r.metrics.max_deviation_m))
    chosen: list[tuple[str, int]] = []
    seen: set[int] = set()
    for i in range(len(results)):
        for label, ranked in (("worst", worst), ("best", best)):
            if len(chosen) < count and i < len(ranked) and ranked[i].metrics.seed not in seen:
                chosen.append((label, ranked[i].metrics.seed))
                seen.add(ranked[i].metrics.seed)
    return chosen


def render_episode(env: Any, policy: Any, seed: int, path: Path, title: str) -> int:
    """Replay episode `seed` and write it as an MP4 at `path`; returns the number of frames."""
    import cv2

    obs, info = env.reset(seed=seed)
    ep = info.get("episode", {})
    state = policy.initial_state(1)
    start = np.ones(1, dtype=bool)
    frames = [_frame(obs, info.get("state", {}), ep, title, 0)]
    step = 0
    while True:
        action, state = policy.predict(obs[None], state, start, deterministic=True)
        start = np.zeros(1, dtype=bool)
        obs, _, terminated, truncated, step_info = env.step(np.asarray(action, dtype=np.float32).reshape(-1))
        step += 1
        frames.append(_frame(obs, step_info.get("state", {}), ep, title, step))
        if terminated or truncated:
            break
    h, w = frames[0].shape[:2]
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (w, h))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV cannot write MP4 to {path}")
    for frame in frames:
        writer.write(frame)
    writer.release()
    return len(frames)


def _frame(obs: np.ndarray, state: dict[str, Any], ep: dict[str, Any], title: str, step: int) -> np.ndarray:
    """One BGR video frame: the policy's view (scaled up) above a top-down sketch in the ego's frame."""
    import cv2

    view = np.transpose(np.asarray(obs), (1, 2, 0))[:, :, ::-1]
    view = cv2.resize(view, None, fx=VIEW_SCALE, fy=VIEW_SCALE, interpolation=cv2.INTER_NEAREST)
    h, w = view.shape[:2]
    sketch = np.full((h, w, 3), 235, np.uint8)
    centre = np.array([w / 2, h * 0.6])

    def to_px(forward_m: np.ndarray, left_m: np.ndarray) -> np.ndarray:
        return np.stack([centre[0] - left_m / SKETCH_M_PER_PX, centre[1] - forward_m / SKETCH_M_PER_PX], -1)

    # Lane centre: points (s, 0) of the road frame, where the ego is at lateral q_lat with heading q_rot.
    q_lat, q_rot = float(state.get("q_lat_m", 0.0)), float(state.get("q_rot_rad", 0.0))
    s = np.array([-10.0, 20.0])
    c, sn = np.cos(q_rot), np.sin(q_rot)
    line = to_px(c * s - sn * q_lat, -sn * s - c * q_lat)
    cv2.line(sketch, tuple(int(v) for v in line[0]), tuple(int(v) for v in line[1]), (180, 180, 180), 2)
    _box(sketch, to_px, 0.0, 0.0, 0.0, ep.get("ego_length_m", 4.5), ep.get("ego_width_m", 1.8), (200, 120, 40))
    rel_x, rel_y = state.get("other_rel_x_m"), state.get("other_rel_y_m")
    if rel_x is not None and np.isfinite(rel_x):
        rel_yaw = float(state.get("other_yaw_rad", 0.0)) - float(state.get("ego_yaw_rad", 0.0))
        length, width = ep.get("other_length_m", 4.5), ep.get("other_width_m", 1.8)
        _box(sketch, to_px, float(rel_x), float(rel_y), rel_yaw, length, width, (40, 140, 230))
    text = f"{title}  step {step}  q_lat {q_lat:+.2f} m  clearance {float(state.get('clearance_m', np.nan)):.2f} m"
    cv2.putText(sketch, text, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (20, 20, 20), 1, cv2.LINE_AA)
    return np.ascontiguousarray(np.vstack([view, sketch]))


def _box(img: np.ndarray, to_px: Any, x: float, y: float, yaw: float, length: float, width: float, color) -> None:
    import cv2

    corners = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]]) * [length / 2, width / 2]
    c, s = np.cos(yaw), np.sin(yaw)
    fwd = x + corners[:, 0] * c - corners[:, 1] * s
    left = y + corners[:, 0] * s + corners[:, 1] * c
    cv2.fillPoly(img, [np.round(to_px(fwd, left)).astype(np.int32)], color)


def render_videos(
    results: Sequence[EpisodeResult],
    count: int,
    env_factory: EnvFactory,
    policy_spec: PolicySpec,
    out_dir: Path,
) -> list[Path]:
    """MP4s of the `count` chosen episodes (`video_<label>_<seed>.mp4`) in `out_dir`."""
    if count <= 0 or not results:
        return []
    env = env_factory()
    try:
        policy = policy_spec.load(env)
        paths = []
        for label, seed in choose_episodes(results, count):
            path = out_dir / f"video_{label}_{seed}.mp4"
            render_episode(env, policy, seed, path, f"{label} seed {seed}")
            paths.append(path)
        return paths
    finally:
        env.close()
