"""The simulator and the learner on an accelerator (issue 21, item 4), against the same machine's CPU in one run.

Part 1, frames/s of the batched view path (`ViewSynthesizer(..., device="cuda")`: every recorded frame on the GPU, all
views warped, hole-filled, shadowed, rasterized, composited and harmonized as one batch) at the policy's view (the
world's default region resized to 160 x 64), for several batch sizes; each view an agent up to 1 m beside its recorded
frame, turned up to 0.1 rad, with one other car 8-25 m ahead of it, a model of the env's vehicle library in a paint of
its own as every episode draws it (the share of views where the car was drawn is counted from the views' car masks),
and the same views without a car. Timed per `render` call, views returned to
the host as numpy arrays (what an env hands the policy). The CPU row is the per-view path that the envs use on CPU,
one torch thread, on the same machine.

Part 2, env steps/s of the bare PPO loop (`build_model(...).learn()`) for overtake with the train preset's 8192-step
buffer and 4 epochs; the preset's imitation passes, VecNormalize, evaluations and checkpoints are not attached
(`bench_train_speed.py` times `drivesim train` with them): the views rendered on the GPU
(`envs.config.render_device`) and PPO on the GPU (`device`), for several numbers of batched envs, and the preset's
CPU layout (8 envs, 2 learner threads) on the same machine.

    python benchmarks/bench_gpu.py --world WORLD            # on a machine with a CUDA device
    python benchmarks/bench_gpu.py --world WORLD --device cpu --quick   # the mechanics, anywhere

Writes the markdown table to benchmarks/results/gpu.md (or --out) and its raw figures to gpu.json.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np
import torch
from _lib.report import write_markdown

from drivesim.bench.sim_steps import make_env
from drivesim.sim.view import CarPlacement, ViewSynthesizer

HERE = Path(__file__).resolve().parent


def random_views(world: Any, count: int, seed: int) -> tuple[np.ndarray, ...]:
    """`count` agents near the recorded path: (frame, x, y, yaw) and each one's car position (x, y, yaw) 8-25 m ahead
    of it and up to 1.5 m to either side."""
    rng = np.random.default_rng(seed)
    px, py, pyaw = (np.asarray(world.path[k], dtype=np.float64) for k in ("x_m", "y_m", "yaw_rad"))
    frame = rng.integers(0, world.frame_count, count)
    lateral_m, yaw_rad = rng.uniform(-1.0, 1.0, count), rng.uniform(-0.1, 0.1, count)
    heading = pyaw[frame]
    x = px[frame] - np.sin(heading) * lateral_m
    y = py[frame] + np.cos(heading) * lateral_m
    ahead_m, side_m = rng.uniform(8.0, 25.0, count), rng.uniform(-1.5, 1.5, count)
    car_x = px[frame] + np.cos(heading) * ahead_m - np.sin(heading) * side_m
    car_y = py[frame] + np.sin(heading) * ahead_m + np.cos(heading) * side_m
    return frame, x, y, heading + yaw_rad, car_x, car_y, heading


def time_renders(views: ViewSynthesizer, batch: tuple, cars: list, min_s: float) -> dict[str, Any]:
    """Median s per `render` call of the batch (after two warm-up calls), its parts and the car-drawn share."""
    frame, x, y, yaw = batch[:4]
    for _ in range(2):
        out = views.render(frame, x, y, yaw, cars)
    times, parts = [], {}
    start = time.perf_counter()
    while len(times) < 3 or (time.perf_counter() - start < min_s and len(times) < 50):
        t0 = time.perf_counter()
        out = views.render(frame, x, y, yaw, cars)
        times.append(time.perf_counter() - t0)
        for key, ms in out.timings_ms.items():
            parts.setdefault(key, []).append(ms)
    drawn = out.car_mask.reshape(len(frame), -1).any(axis=1)
    return {
        "s_per_call": float(np.median(times)),
        "calls": len(times),
        "car_drawn_share": float(drawn.mean()),
        "parts_ms": {k: float(np.median(v)) for k, v in parts.items()},
    }


def render_rows(world_dir: str, device: str, batches: list[int], cpu_batch: int, min_s: float) -> list[dict]:
    """Part 1's rows: the batched path on `device` for each batch size, with and without the car, and the CPU's
    per-view path."""
    env = make_env("overtake", world_dir, None, "eval", None)
    env.reset(seed=0)
    sim, vehicles = env.unwrapped.sim, env.unwrapped.vehicles
    world, config = sim.renderer.world, sim.renderer.config
    rows = []
    for name, views, sizes in (
        (f"batched path on {device}", ViewSynthesizer(world, config, device=device, batched=True), batches),
        ("per-view path on the CPU, 1 thread", ViewSynthesizer(world, config), [cpu_batch]),
    ):
        torch.set_num_threads(1)
        for count in sizes:
            batch = random_views(world, count, seed=count)
            rng = np.random.default_rng(count)  # each view's car a library model in a paint of its own, as episodes
            with_car = [
                [CarPlacement(vehicles.sample(rng), cx, cy, cyaw)] for cx, cy, cyaw in zip(*batch[4:], strict=True)
            ]
            for car, cars in (("one car", with_car), ("no car", [[] for _ in range(count)])):
                timed = time_renders(views, batch, cars, min_s)
                row = {"path": name, "views": count, "cars": car, **timed}
                row["frames_per_s"] = count / timed["s_per_call"]
                rows.append(row)
                print(json.dumps(row), flush=True)
    return rows


def train_rows(world_dir: str, device: str, counts: list[int], updates: int) -> list[dict]:
    """Part 2's rows: learn() for `updates` updates of the preset's buffer on `device` for each env count, and the
    preset's CPU layout."""
    from drivesim.pipeline.config import load_config
    from drivesim.stages.train.config import TrainConfig
    from drivesim.stages.train.envs import EnvSource
    from drivesim.stages.train.recurrent import TimedVecEnv
    from drivesim.stages.train.run import build_model

    layouts = [(device, count, 1) for count in counts] + [("cpu", 8, 2)]
    rows = []
    for where, count, threads in layouts:
        overrides = [f"device={where}", f"envs.config.render_device={where}", f"envs.count={count}"]
        overrides += ["envs.vec_env=batched", "envs.processes=1", f"learner_threads={threads}"]
        cfg = load_config(TrainConfig, preset="train/overtake", overrides=overrides)
        source = EnvSource(task="overtake", worlds=[Path(world_dir)], config=cfg.envs.config)
        torch.set_num_threads(threads)
        timed_env = TimedVecEnv(source.make_vec(cfg.envs.count, "batched", seed=0))
        try:
            model = build_model(cfg, timed_env)
            steps = updates * cfg.ppo.buffer_steps
            start = time.perf_counter()
            model.learn(steps)
            elapsed = time.perf_counter() - start
        except Exception as e:  # a benchmark on a lent machine goes on to its other rows and says what broke
            traceback.print_exc()
            rows.append({"device": where, "envs": count, "learner_threads": threads, "error": repr(e)[:300]})
            continue
        finally:
            timed_env.close()
        row = {
            "device": where, "envs": count, "learner_threads": threads, "steps": int(model.num_timesteps),
            "s": elapsed, "steps_per_s": model.num_timesteps / elapsed, "rollout_s": model.time_s["rollout"],
            "simulator_s": timed_env.step_time_s, "optimization_s": model.time_s["optimization"],
        }  # fmt: skip
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def device_name(device: str) -> str:
    """The accelerator's name, or the CPU's."""
    if torch.device(device).type == "cuda":
        props = torch.cuda.get_device_properties(torch.device(device))
        return f"{props.name}, {props.total_memory / 2**30:.0f} GiB, {props.multi_processor_count} SMs"
    return platform.processor() or platform.machine()


def world_line(world_dir: str) -> str:
    """Frames, image size and path length of a world folder (its world.json and camera.json)."""
    info = json.loads((Path(world_dir) / "world.json").read_text())
    camera = json.loads((Path(world_dir) / "camera.json").read_text())
    size = f"{camera['width_px']} x {camera['height_px']} px"
    return f"{info['frame_count']} frames, {size}, {info['path_length_m']:.0f} m"


def markdown(render: list[dict], train: list[dict], args: argparse.Namespace) -> str:
    """The result file."""
    import os

    load = os.getloadavg()
    lines = [
        "# The simulator and the learner on an accelerator (issue 21)",
        "",
        f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} on {platform.node()}: "
        f"{device_name(args.device)}; {os.cpu_count()} CPU cores, torch {torch.__version__}; load average after: "
        f"{load[0]:.2f}. World `{args.world}` ({world_line(args.world)}), the policy's view 160 x 64. "
        "`python benchmarks/bench_gpu.py --world WORLD` redoes it (module docstring: what each row times).",
        "",
        "## Views per second",
        "",
        "| path | views per call | other car | car drawn in | frames/s | ms per call | warp + fill | raster |"
        " composite + shadow | lighting + placement | harmonize |",
        "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in render:
        p = r["parts_ms"]
        lines.append(
            f"| {r['path']} | {r['views']} | {r['cars']} | {100 * r['car_drawn_share']:.0f} % | "
            f"{r['frames_per_s']:,.0f} | {1e3 * r['s_per_call']:.1f} | {p.get('warp', 0):.1f} | "
            f"{p.get('raster', 0):.1f} | {p.get('composite', 0):.1f} | {p.get('lighting', 0):.1f} | "
            f"{p.get('harmonize', 0):.1f} |"
        )
    if train:
        lines += [
            "",
            "## learn() for overtake (train preset, no warm start)",
            "",
            "| views and PPO on | batched envs | learner threads | env steps | env steps/s | rollout [s] | of which "
            "simulator [s] | optimization [s] |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in train:
            if "error" in r:
                lines.append(f"| {r['device']} | {r['envs']} | {r['learner_threads']} | failed: {r['error']} |||||")
                continue
            lines.append(
                f"| {r['device']} | {r['envs']} | {r['learner_threads']} | {r['steps']} | {r['steps_per_s']:,.0f} | "
                f"{r['rollout_s']:.1f} | {r['simulator_s']:.1f} | {r['optimization_s']:.1f} |"
            )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", required=True, help="a built world folder (overtake needs a path of 68 m or more)")
    parser.add_argument("--device", default="cuda", help="torch device of the batched path and the GPU learner")
    parser.add_argument("--batches", type=int, nargs="+", default=[256, 1024, 4096, 16384])
    parser.add_argument("--envs", type=int, nargs="+", default=[64, 256], help="batched envs of the device learner")
    parser.add_argument("--updates", type=int, default=2, help="PPO updates (of 8192 steps) per learn() row")
    parser.add_argument("--quick", action="store_true", help="small batches, one update, no CPU learner: mechanics")
    parser.add_argument("--skip-train", action="store_true")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "gpu.md")
    args = parser.parse_args()
    if args.quick:
        args.batches, args.envs, args.updates = [8, 32], [8], 1
    render = render_rows(args.world, args.device, args.batches, cpu_batch=64 if not args.quick else 8, min_s=2.0)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(markdown(render, [], args))  # kept if the training rows break
    train = [] if args.skip_train else train_rows(args.world, args.device, args.envs, args.updates)
    write_markdown(args.out, [markdown(render, train, args)], {"render": render, "train": train})


if __name__ == "__main__":
    main()
