"""Why the overtake policy falls short of the expert on real (grey) drives when it matches it on procedural towns:
measurements, no retuning.

For each world (real drives and the demo town, the town also shown in grey) it measures
  a. the inserted car in the policy's view over expert episodes: its pixels and its luminance contrast against a ring
     of road around it;
  b. the view's quality at the lateral offsets a pass needs: the share of pixels filled from neighbouring frames or
     inpainted, at offsets -1.5 .. +1.5 m (+ = left) of the recorded path;
  c. the left/right asymmetry: the expert's side, deviation and success on each side, and the camera's lateral position
     and yaw in the extrinsics;
  d. how well a trained policy (a run folder and its warm start) imitates the expert on the expert's own states:
     the mean absolute action error, per world.

Run from the repository root:  .venv/bin/python experiments/real_gap/bench_real_gap.py --help
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "_lib"))
from study import add_result_arguments, save_result  # noqa: E402

STUDY = "real_gap"
RESULTS = Path(__file__).resolve().parent / "results"
OFFSETS_M = (-1.5, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5)
RING_PX = 3  # width of the road ring around the car that its contrast is measured against
LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def make_env(world: str, meshes: str, config: dict[str, Any]) -> Any:
    """The overtake env (eval mode: no augmentation) on `world` with the given env config."""
    import gymnasium

    import drivesim.sim.envs  # noqa: F401  (registers the envs)

    return gymnasium.make("drivesim/Overtake-v0", world=world, meshes=meshes, mode="eval", config=config).unwrapped


def render_with_mask(env: Any) -> tuple[np.ndarray, np.ndarray]:
    """The ego's view (h, w, 3) uint8 and where the inserted car is visible in it (h, w) bool."""
    frame, x, y, yaw, cars = env.view_request()
    batch = env.sim.renderer.render(np.array([frame]), np.array([x]), np.array([y]), np.array([yaw]), [cars])
    return batch.rgb[0], batch.car_mask[0]


def car_contrast(rgb: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """The car's pixel count, and its luminance and colour contrast against a RING_PX ring around it (0..255)."""
    import cv2

    kernel = np.ones((2 * RING_PX + 1, 2 * RING_PX + 1), np.uint8)
    ring = cv2.dilate(mask.astype(np.uint8), kernel).astype(bool) & ~mask
    img = rgb.astype(np.float32)
    luma = img @ LUMA
    car_mean, ring_mean = img[mask].mean(axis=0), img[ring].mean(axis=0)
    return {
        "pixels": float(mask.sum()),
        "luma_contrast": float(abs(luma[mask].mean() - luma[ring].mean())),
        "luma_abs_diff": float(np.abs(luma[mask] - luma[ring].mean()).mean()),
        "colour_contrast": float(np.abs(car_mean - ring_mean).mean()),
        "car_luma": float(luma[mask].mean()),
        "ring_luma": float(luma[ring].mean()),
    }


def grey(rgb: np.ndarray) -> np.ndarray:
    """`rgb` (h, w, 3) uint8 shown in grey (its luminance in the three channels)."""
    luma = np.clip(np.rint(rgb.astype(np.float32) @ LUMA), 0, 255).astype(np.uint8)
    return np.repeat(luma[..., None], 3, axis=2)


def expert_episode(env: Any, seed: int, policies: dict[str, Any], as_grey: bool) -> dict[str, Any]:
    """One episode driven by the expert: the car's visibility per step, the episode's side, deviation and outcome,
    and each policy's action error on the expert's states (its LSTM fed the same views)."""
    env.reset_state(seed)
    rgb, mask = render_with_mask(env)
    states = {name: None for name in policies}
    errors: dict[str, list[float]] = {name: [] for name in policies}
    visible, steps, max_dev, info, start = [], 0, 0.0, {}, True
    side = 1.0 if env.expert_target_offset() > 0.0 else -1.0  # + = the ego passes on the left
    while True:
        view = grey(rgb) if as_grey else rgb
        obs = env.observation_from(view)
        expert = float(env.expert_action()[0])
        for name, policy in policies.items():
            action, states[name] = policy.predict(obs[None], states[name], np.array([start]))
            errors[name].append(abs(float(action[0, 0]) - expert))
        start = False
        if mask.any():
            visible.append({"ahead_m": float(env._m.get("other_rel_x_m", math.nan)), **car_contrast(view, mask)})
        _, terminated, truncated, info = env.advance(np.array([expert], dtype=np.float32))
        steps += 1
        max_dev = max(max_dev, abs(env._m["q_lat_m"]))
        if terminated or truncated:
            break
        rgb, mask = render_with_mask(env)
    return {
        "seed": seed,
        "side": "left" if side > 0 else "right",
        "success": bool(info.get("success", False)),
        "max_deviation_m": max_dev,
        "steps": steps,
        "steps_car_visible": len(visible),
        "visible": visible,
        "action_error": {name: float(np.mean(e)) for name, e in errors.items()},
        "other_lateral_m": float(env._episode["other_lateral_m"]),
        "end": next((k for k, v in info.get("termination", {}).items() if v), "success"),
    }


def sharpness(obs: np.ndarray) -> float:
    """Mean absolute luminance gradient of a (3, h, w) uint8 observation: a smeared (stretched) view has less."""
    luma = np.tensordot(LUMA, obs.astype(np.float32), axes=1)
    return float(np.abs(np.diff(luma, axis=1)).mean() + np.abs(np.diff(luma, axis=0)).mean())


def fill_counts(renderer: Any) -> np.ndarray:
    """The renderer's cumulative (total, own frame, neighbour, inpainted) pixel counts."""
    f = renderer.fill_stats
    return np.array([f.total_px, f.frame_px, f.neighbour_px, f.inpainted_px], dtype=float)


def view_quality(env: Any, places: int, seed: int) -> dict[str, dict[str, float]]:
    """At each of OFFSETS_M, averaged over `places` random places of the path: the share of the policy's view filled
    from neighbouring frames and inpainted (the warp's counts: the inserted car does not change them), and the view's
    sharpness relative to the same places on the recorded path."""
    rng = np.random.default_rng(seed)
    env.reset_state(seed)
    renderer, ref = env.sim.renderer, env.sim.reference
    arcs = rng.uniform(ref.start_m + 3.0, ref.end_m - 3.0, places)
    sharp0 = np.array([sharpness(env.place_ego(float(arc), 0.0)) for arc in arcs])
    out = {}
    for offset in OFFSETS_M:
        totals, sharp = np.zeros(4), []
        for arc in arcs:
            before = fill_counts(renderer)
            sharp.append(sharpness(env.place_ego(float(arc), offset)))
            totals += fill_counts(renderer) - before
        n = max(totals[0], 1.0)
        out[f"{offset:+.1f}"] = {
            "frame": totals[1] / n,
            "neighbour": totals[2] / n,
            "inpainted": totals[3] / n,
            "sharpness_ratio": float(np.mean(np.array(sharp) / np.maximum(sharp0, 1e-6))),
        }
    return out


def camera_extrinsics(world: str) -> dict[str, float]:
    """The camera's position (x forward, y left, z up, m) and yaw (rad, + = left) on the vehicle, and the lane width."""
    camera = json.loads((Path(world) / "camera.json").read_text())
    T = np.asarray(camera["T_vehicle_camera"], dtype=float)
    forward = T[:3, 2]
    meta = json.loads((Path(world) / "world.json").read_text())
    return {
        "x_m": float(T[0, 3]),
        "y_m": float(T[1, 3]),
        "z_m": float(T[2, 3]),
        "yaw_rad": float(math.atan2(forward[1], forward[0])),
        "pitch_rad": float(math.asin(max(-1.0, min(1.0, -forward[2])))),
        "image_px": [camera["width_px"], camera["height_px"]],
        "lane_width_m": meta.get("lane_width_m"),
        "road_width_m": meta.get("road_width_m"),
        "frames": meta.get("frame_count"),
    }


def depth_sides(world: str, shift_m: float = 1.5) -> dict[str, dict[str, float]]:
    """Road-side geometry from the recorded depth, below the principal point (the road and what stands beside it):
    per image half (left / right of the principal point), the median depth, the share of pixels nearer than 10 m and
    the mean parallax (px of the camera image) that a `shift_m` sideways move gives, f·shift/Z; the larger it is, the
    more a view synthesized that far aside on that side stretches and uncovers."""
    camera = json.loads((Path(world) / "camera.json").read_text())
    K = np.asarray(camera["K"], dtype=float)
    from drivesim.sim.image_stack import open_frames, stored_file

    depth = open_frames(stored_file(Path(world), "depth_m"))  # an image stack, or the .npy of an older world
    frames = np.linspace(0, depth.shape[0] - 1, min(depth.shape[0], 40)).astype(int)
    cy, cx = int(round(K[1, 2])), int(round(K[0, 2]))
    out = {}
    for side, cols in (("left", slice(0, cx)), ("right", slice(cx, None))):
        z = np.asarray(depth[frames, cy:, cols], dtype=np.float32)
        z = z[np.isfinite(z) & (z > 0.1)]
        out[side] = {
            "median_depth_m": float(np.median(z)),
            "share_nearer_10m": float(np.mean(z < 10.0)),
            "parallax_px": float(np.mean(K[0, 0] * shift_m / z)),
        }
    return out


def summarize_world(episodes: list[dict[str, Any]]) -> dict[str, Any]:
    """Per-world figures from its expert episodes: the car's visibility, the sides, the action errors."""
    visible = [v for e in episodes for v in e["visible"]]
    near = [v for v in visible if v["ahead_m"] <= 8.0]

    def med(rows: list[dict], key: str) -> float:
        return float(np.median([r[key] for r in rows])) if rows else math.nan

    sides = {}
    for side in ("left", "right"):
        eps = [e for e in episodes if e["side"] == side]
        sides[side] = {
            "episodes": len(eps),
            "success": float(np.mean([e["success"] for e in eps])) if eps else math.nan,
            "max_deviation_m": float(np.mean([e["max_deviation_m"] for e in eps])) if eps else math.nan,
            "ends": {k: sum(e["end"] == k for e in eps) for k in sorted({e["end"] for e in eps})},
            "share_steps_car_visible": sum(e["steps_car_visible"] for e in eps) / max(sum(e["steps"] for e in eps), 1),
            "car_pixels_median": med([v for e in eps for v in e["visible"]], "pixels"),
            "luma_contrast_median": med([v for e in eps for v in e["visible"]], "luma_contrast"),
        }
    names = episodes[0]["action_error"].keys() if episodes else []
    return {
        "episodes": len(episodes),
        "share_steps_car_visible": sum(e["steps_car_visible"] for e in episodes)
        / max(sum(e["steps"] for e in episodes), 1),
        "car_pixels_median": med(visible, "pixels"),
        "car_pixels_median_within_8m": med(near, "pixels"),
        "luma_contrast_median": med(visible, "luma_contrast"),
        "luma_contrast_p25": float(np.percentile([v["luma_contrast"] for v in visible], 25)) if visible else math.nan,
        "share_luma_contrast_below_10": float(np.mean([v["luma_contrast"] < 10 for v in visible]))
        if visible
        else math.nan,
        "colour_contrast_median": med(visible, "colour_contrast"),
        "car_luma_median": med(visible, "car_luma"),
        "ring_luma_median": med(visible, "ring_luma"),
        "expert_success": float(np.mean([e["success"] for e in episodes])),
        "sides": sides,
        "action_error": {n: float(np.mean([e["action_error"][n] for e in episodes])) for n in names},
        "action_error_by_side": {
            n: {
                s: float(np.mean([e["action_error"][n] for e in episodes if e["side"] == s] or [math.nan]))
                for s in ("left", "right")
            }
            for n in names
        },
    }


def load_policies(run: str | None) -> dict[str, Any]:
    """The run's final policy and its warm start (none without a run)."""
    if not run:
        return {}
    from drivesim.policy.run_folder import load_policy

    out = {"final": load_policy(run)}
    warm = Path(run) / "checkpoints" / "warm_start.pt"
    if warm.is_file():
        out["warm_start"] = load_policy(warm)
    return out


def measure_world(
    label: str, world: str, as_grey: bool, args: argparse.Namespace, config: dict, policies: dict
) -> dict:
    """All of a world's measurements (a, b, c, d)."""
    start = time.perf_counter()
    env = make_env(world, args.meshes, config)
    episodes = [expert_episode(env, seed, policies, as_grey) for seed in range(args.episodes)]
    row = {"label": label, "world": world, "grey": as_grey, **summarize_world(episodes)}
    row["view_quality"] = view_quality(env, args.places, 1000) if not as_grey else None
    row["camera"] = camera_extrinsics(world)
    row["depth_sides"] = depth_sides(world)
    row["seconds"] = time.perf_counter() - start
    print(
        f"{label}: {row['seconds']:.0f} s, car px {row['car_pixels_median']:.0f}, luma contrast "
        f"{row['luma_contrast_median']:.1f}, action error {row['action_error']}",
        flush=True,
    )
    return row


def sample_views(world: str, meshes: str, config: dict, as_grey: bool, seed: int) -> np.ndarray:
    """The policy's view (h, w, 3) at the first step where the car is within 10 m ahead in an expert episode."""
    env = make_env(world, meshes, config)
    env.reset_state(seed)
    rgb, mask = render_with_mask(env)
    for _ in range(200):
        if mask.any() and env._m["other_rel_x_m"] < 10.0:
            break
        _, terminated, truncated, _ = env.advance(env.expert_action())
        if terminated or truncated:
            break
        rgb, mask = render_with_mask(env)
    return grey(rgb) if as_grey else rgb


def plot(rows: list[dict], views: list[tuple[str, np.ndarray]], path: Path) -> None:
    """One picture: each world's view with the car, and the inpainted share against the lateral offset."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(12, 6))
    for i, (label, view) in enumerate(views):
        ax = fig.add_subplot(2, len(views), i + 1)
        ax.imshow(view)
        ax.set_title(label, fontsize=9)
        ax.axis("off")
    ax = fig.add_subplot(2, 1, 2)
    for row in rows:
        if row["view_quality"]:
            q = row["view_quality"]
            ax.plot(
                OFFSETS_M,
                [100 * (q[f"{o:+.1f}"]["inpainted"] + q[f"{o:+.1f}"]["neighbour"]) for o in OFFSETS_M],
                marker="o",
                label=row["label"],
            )
    ax.set_xlabel("ego lateral offset from the recorded path, m (+ = left)")
    ax.set_ylabel("% of the policy's view not from its own frame")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _f(value: Any, digits: int = 1) -> str:
    return "–" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def _perception_lines(r: dict[str, Any]) -> list[str]:
    """The car's visibility and the sides' outcomes, and the view quality by offset, of one result."""
    lines: list[str] = []
    lines += [
        "| world | car visible, % steps | car px (median / ≤8 m ahead) | luma contrast median (p25) | "
        "% steps contrast < 10 | colour contrast | car / ring luma | expert success | "
        "pass left: n, success, max dev m | pass right: n, success, max dev m |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for w in r["worlds"]:
        s = w["sides"]
        lines.append(
            f"| {w['label']} | {_f(100 * w['share_steps_car_visible'], 0)} | {_f(w['car_pixels_median'], 0)} / "
            f"{_f(w['car_pixels_median_within_8m'], 0)} | {_f(w['luma_contrast_median'])} "
            f"({_f(w['luma_contrast_p25'])}) | {_f(100 * w['share_luma_contrast_below_10'], 0)} | "
            f"{_f(w['colour_contrast_median'])} | {_f(w['car_luma_median'], 0)} / {_f(w['ring_luma_median'], 0)} | "
            f"{_f(w['expert_success'], 2)} | {s['left']['episodes']}, {_f(s['left']['success'], 2)}, "
            f"{_f(s['left']['max_deviation_m'], 2)} | {s['right']['episodes']}, {_f(s['right']['success'], 2)}, "
            f"{_f(s['right']['max_deviation_m'], 2)} |"
        )
    lines += _offset_table(
        r["worlds"],
        "View quality: % of the policy's view filled from neighbouring frames + inpainted, by ego offset "
        "from the recorded path (m, + = left)",
        lambda q: f"{_f(100 * q['neighbour'])} + {_f(100 * q['inpainted'])}",
    )
    lines += _offset_table(
        r["worlds"],
        "Sharpness at the offset / on the recorded path (mean luminance gradient of the policy's view, same places;"
        " below 1: smeared)",
        lambda q: _f(q["sharpness_ratio"], 2),
    )
    return lines


def _geometry_lines(r: dict[str, Any]) -> list[str]:
    """How the expert's episodes ended, the camera, the road-side depth and the imitation error, of one result."""
    lines: list[str] = []
    lines += [
        "",
        "By the side the expert passed on: how its episodes ended; % steps with the car in view, its median px"
        " and luma contrast",
        "",
    ]
    for w in r["worlds"]:
        parts = []
        for side in ("left", "right"):
            s = w["sides"][side]
            seen = (
                f"; car in view {_f(100 * s['share_steps_car_visible'], 0)} % of steps, {_f(s['car_pixels_median'], 0)}"
                f" px, contrast {_f(s['luma_contrast_median'])}"
                if "share_steps_car_visible" in s
                else ""
            )
            parts.append(f"{side} {s['ends']}{seen}")
        lines.append(f"- {w['label']}: " + "; ".join(parts))
    lines += [
        "",
        "Camera on the vehicle (y + = left) and the world's lane width",
        "",
        "| world | x m | y m | z m | yaw rad | pitch rad | image px | lane width m |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for w in r["worlds"]:
        if not w["grey"] or "town" not in w["label"]:
            c = w["camera"]
            lines.append(
                f"| {w['label']} | {c['x_m']:.2f} | {c['y_m']:+.2f} | {c['z_m']:.2f} | {c['yaw_rad']:+.4f} "
                f"| {c['pitch_rad']:+.4f} | {c['image_px']} | {c['lane_width_m']} |"
            )
    lines += [
        "",
        "Recorded depth below the principal point, left / right half of the camera image (a 1.5 m shift's "
        "parallax f·1.5/Z in camera px)",
        "",
        "| world | median depth m (L / R) | % nearer than 10 m (L / R) | parallax px (L / R) |",
        "|---|---|---|---|",
    ]
    for w in r["worlds"]:
        if not w["grey"] and "depth_sides" in w:
            d = w["depth_sides"]
            lines.append(
                f"| {w['label']} | {d['left']['median_depth_m']:.1f} / {d['right']['median_depth_m']:.1f} | "
                f"{100 * d['left']['share_nearer_10m']:.0f} / {100 * d['right']['share_nearer_10m']:.0f} | "
                f"{d['left']['parallax_px']:.1f} / {d['right']['parallax_px']:.1f} |"
            )
    if r["policy_run"]:
        names = list(r["worlds"][0]["action_error"])
        lines += [
            "",
            f"Imitation: mean |policy action - expert action| on the expert's states (policy: "
            f"{r['policy_run']}; actions in [-1, 1])",
            "",
            "| world | " + " | ".join(f"{n} (all / left / right)" for n in names) + " |",
            "|---|" + "---|" * len(names),
        ]
        for w in r["worlds"]:
            cells = [
                f"{_f(w['action_error'][n], 3)} / {_f(w['action_error_by_side'][n]['left'], 3)} / "
                f"{_f(w['action_error_by_side'][n]['right'], 3)}"
                for n in names
            ]
            lines.append(f"| {w['label']} | " + " | ".join(cells) + " |")
    if r.get("notes"):
        lines += ["", r["notes"]]
    return lines


def write_markdown() -> None:
    """Remake results/real_gap.md from every results/real_gap_*.json."""
    lines = ["# Real drives vs the town: the car's visibility, view quality, sides, imitation", ""]
    for path in sorted(RESULTS.glob(f"{STUDY}_*.json")):
        r = json.loads(path.read_text())
        lines += [f"## {r['name']} ({r['date']}, {r['machine']}, load {r['load']})", "", r["command"], ""]
        lines += [*_perception_lines(r), *_geometry_lines(r), ""]
    (RESULTS / f"{STUDY}.md").write_text("\n".join(lines))


def parse_world(text: str) -> tuple[str, str, bool]:
    """LABEL=PATH[:grey] -> (label, path, shown in grey)."""
    label, sep, rest = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"--world {text!r}: give LABEL=PATH or LABEL=PATH:grey")
    as_grey = rest.endswith(":grey")
    path = rest[: -len(":grey")] if as_grey else rest
    if not (Path(path) / "camera.json").is_file():
        raise argparse.ArgumentTypeError(f"--world {text!r}: {path} has no camera.json; give a built world folder")
    return label, path, as_grey


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_result_arguments(parser, STUDY)
    parser.add_argument(
        "--world",
        type=parse_world,
        action="append",
        required=True,
        help="LABEL=PATH of a built world; PATH:grey shows it in grey (repeatable)",
    )
    parser.add_argument("--meshes", required=True, help="the car meshes folder (the same for every world)")
    parser.add_argument(
        "--run",
        default=None,
        help="a trained overtake run folder: its env config, and its final "
        "policy and warm start for the imitation error (d); without it the task's default config",
    )
    parser.add_argument("--episodes", type=int, default=20, help="expert episodes per world (seeds 0..N-1)")
    parser.add_argument("--places", type=int, default=20, help="places on the path for the view quality (b)")
    args = parser.parse_args()
    if args.episodes < 1 or args.places < 1:
        parser.exit(2, "bench_real_gap: --episodes and --places must be >= 1\n")
    if not Path(args.meshes).is_dir():
        parser.exit(2, f"bench_real_gap: --meshes {args.meshes}: no such folder; give a built meshes folder\n")
    config: dict[str, Any] = {}
    if args.run:
        config = json.loads((Path(args.run) / "config.json").read_text())["train"]["envs"]["config"]
    policies = load_policies(args.run)
    rows = [measure_world(label, path, g, args, config, policies) for label, path, g in args.world]
    views = [(label, sample_views(path, args.meshes, config, g, 3)) for label, path, g in args.world]
    RESULTS.mkdir(exist_ok=True)
    plot(rows, views, RESULTS / f"{STUDY}_{args.name}.png")
    result = {
        "name": args.name,
        "notes": args.notes,
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.node()} {os.cpu_count()} cores",
        "load": " ".join(f"{v:.2f}" for v in os.getloadavg()),
        "command": "`" + " ".join(sys.argv) + "`",
        "policy_run": args.run,
        "worlds": rows,
    }
    save_result(RESULTS, STUDY, result, write_markdown)


def _offset_table(worlds: list[dict], title: str, cell: Callable[[dict], str]) -> list[str]:
    """A markdown table of one view-quality figure per world (rows) and ego offset (columns), under `title`."""
    lines = ["", title, "", "| world | " + " | ".join(f"{o:+.1f}" for o in OFFSETS_M) + " |"]
    lines.append("|---|" + "---|" * len(OFFSETS_M))
    for w in worlds:
        if w["view_quality"]:
            cells = [cell(w["view_quality"][f"{o:+.1f}"]) for o in OFFSETS_M]
            lines.append(f"| {w['label']} | " + " | ".join(cells) + " |")
    return lines


if __name__ == "__main__":
    main()
