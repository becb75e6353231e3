"""Learning, shown by numbers (issue 9): train under a wall-clock budget, then evaluate on held-back seeds.

Scenarios (each: `drivesim train` through `run_training` with the task's preset and a time limit, then N episodes
of the deterministic policy in eval mode, where any overlap is a collision; a random policy beside it):
    lane-demo       lane on the demo world, 15 min            target: >= 90 % of episodes without intervention
    overtake-demo   overtake on the demo world, 60 min, warm start from the expert   target: >= 70 % passes
    lane-kitti      lane on a world built from the real KITTI drive, 15 min          target: >= 80 %
    cutin-demo      cutin on the demo world, 30 min with the warm start, from the expert  target: >= 80 %

    .venv/bin/python experiments/learning/bench_learning.py --only lane-demo --minutes 3    # a short check
    .venv/bin/python experiments/learning/bench_learning.py --kitti-world WS/world          # everything (~1.5 h)

Writes experiments/learning/results/learning.md and the curves as experiments/learning/results/learning_<scenario>.png.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivesim.bench.machine import machine_line
from drivesim.chain.towns import training_towns
from drivesim.pipeline.config import load_config
from drivesim.pipeline.workspace import Workspace
from drivesim.policy.run_folder import load_policy
from drivesim.sim.envs.registry import task_spec
from drivesim.stages.train.config import TrainConfig
from drivesim.stages.train.envs import EnvSource
from drivesim.stages.train.stage import run_training

RESULTS = Path(__file__).parent / "results"
HELD_BACK_SEED = 2_000_000
KITTI_DRIVE = (
    Path(__file__).resolve().parents[3]
    / "shared"
    / "data"
    / "real"
    / "kitti_raw"
    / "2011_09_26"
    / "2011_09_26_drive_0001_sync"
)


@dataclass
class Scenario:
    name: str
    task: str
    minutes: float
    target: float
    warm_start: bool
    world_kind: str


SCENARIOS = {
    "lane-demo": Scenario("lane-demo", "lane", 15, 0.90, False, "demo"),
    "overtake-demo": Scenario("overtake-demo", "overtake", 60, 0.70, True, "demo"),
    "lane-kitti": Scenario("lane-kitti", "lane", 15, 0.80, False, "kitti"),
    "cutin-demo": Scenario("cutin-demo", "cutin", 30, 0.80, True, "demo"),
}


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson interval of a rate."""
    if n == 0:
        return math.nan, math.nan
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def evaluate(task: str, world: Path, episodes: int, policy=None, env_config: dict | None = None) -> dict:  # noqa: ANN001
    """Success rate and termination causes over held-back seeds; a random policy when `policy` is None."""
    env = EnvSource(task=task, worlds=[world], config=task_spec(task).config_with(env_config)).make_env("eval")
    rng = np.random.default_rng(0)
    successes, causes, lengths = 0, {}, []
    for i in range(episodes):
        obs, _ = env.reset(seed=HELD_BACK_SEED + i)
        state = None if policy is None else policy.initial_state(1)
        start = np.array([True])
        length = 0
        while True:
            length += 1
            if policy is None:
                action = rng.uniform(-1, 1, (1,)).astype(np.float32)
            else:
                actions, state = policy.predict(obs[None], state, start)
                action = actions[0]
            start = np.array([False])
            obs, _, terminated, truncated, info = env.step(action)
            if terminated or truncated:
                break
        lengths.append(length)
        successes += bool(info.get("success", False))
        for cause, flag in (info.get("termination") or {}).items():
            causes[cause] = causes.get(cause, 0) + bool(flag)
    env.close()
    return {"episodes": episodes, "successes": successes, "causes": causes, "mean_length": float(np.mean(lengths))}


def build_kitti_world(scratch: Path) -> Path | None:
    """A world from the real KITTI drive in ../shared/data/real (ingest, preprocess, build-world), or None."""
    drive = KITTI_DRIVE
    if not drive.is_dir():
        return None
    ws = scratch / "kitti-world"
    if not (ws / "world" / "manifest.json").is_file():
        for args in (["ingest", str(drive)], ["preprocess"], ["build-world"]):
            subprocess.run([sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args], check=True)
    return ws / "world"


def run_scenario(
    scenario: Scenario, world: Path, minutes: float, episodes: int, scratch: Path, extra: list[str] | None = None
) -> dict:
    ws = Workspace(scratch / scenario.name)
    overrides = [f"time_limit_s={minutes * 60:.0f}", "total_steps=100000000", *(extra or [])]
    if scenario.warm_start:
        overrides.append("warm_start.method=expert")
    cfg = load_config(TrainConfig, preset=f"train/{scenario.task}", overrides=overrides)
    start = time.perf_counter()
    result = run_training(ws, cfg, worlds=[world], towns=training_towns(ws, cfg, [world]))
    train_s = time.perf_counter() - start
    policy = load_policy(result.path)
    trained = evaluate(scenario.task, world, episodes, policy, policy.env_config)
    random = evaluate(scenario.task, world, episodes, None, policy.env_config)
    curves = RESULTS / f"learning_{scenario.name}.png"
    shutil.copyfile(result.path / "curves.png", curves)
    return {
        "summary": result.summary,
        "train_s": train_s,
        "trained": trained,
        "random": random,
        "curves": curves,
        "run": result.path,
    }


def _rate(r: dict) -> str:
    lo, hi = wilson(r["successes"], r["episodes"])
    return f"{r['successes'] / r['episodes']:.0%} ({lo:.0%}–{hi:.0%})"


def scenario_row(scenario: Scenario, world: Path, r: dict, load_1min: float, episodes: int) -> dict:
    """One scenario's figures as plain JSON (kept per scenario, so scenarios can be run one at a time)."""
    s, trained = r["summary"], r["trained"]
    return {
        "scenario": scenario.name,
        "warm_start": scenario.warm_start,
        "world": str(world),
        "target": scenario.target,
        "trained_min": s.wall_s / 60,
        "steps": s.steps,
        "steps_per_s": s.steps_per_s,
        "policy_steps": s.policy_steps,
        "policy_eval_success_rate": s.policy_eval_success_rate,
        "trained": trained,
        "random": r["random"],
        "curves": r["curves"].name,
        "run": str(r["run"]),
        "load_1min": load_1min,
        "episodes": episodes,
        "measured_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine_line(),
    }


def _policy_steps(r: dict) -> str:
    steps = r.get("policy_steps")
    if not steps:
        return f"{r['steps']} (last)"
    chosen = r.get("policy_eval_success_rate")
    return f"{steps}" + ("" if chosen is None else f" ({chosen:.0%})")


def write_results() -> None:
    """experiments/learning/results/learning.md from every scenario JSON beside it."""
    rows = [json.loads(p.read_text()) for p in sorted(RESULTS.glob("learning_*.json"))]
    rows.sort(key=lambda r: list(SCENARIOS).index(r["scenario"]) if r["scenario"] in SCENARIOS else 99)
    lines = [
        "# Learning: success on held-back seeds after a wall-clock training budget",
        "",
        f"Evaluation episodes per policy: seeds {HELD_BACK_SEED}+, eval mode (any overlap is a collision); success = "
        "lane/follow/cutin: the time limit without intervention, overtake: passed and back in the lane without "
        "intervention. 95 % Wilson intervals in brackets. "
        "`python experiments/learning/bench_learning.py --only NAME` redoes one scenario.",
        "",
        "| scenario | measured | world | trained | env steps | env steps/s | policy of step | success (trained) | "
        "success, `drivesim eval` | success (random) | target | how the trained policy's episodes ended (besides the "
        "time limit) | curves |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---|",
    ]
    for r in rows:
        trained = r["trained"]
        causes = ", ".join(f"{k} {v}" for k, v in sorted(trained["causes"].items()) if v and k != "time_limit")
        full = r.get("full_eval")
        # The larger evaluation, when there is one, decides: it is the more precise figure.
        rate = full["success"] if full else trained["successes"] / trained["episodes"]
        met = "met" if rate >= r["target"] else "not met"
        full_cell = (
            f"{full['success']:.1%} ({full['ci_low']:.1%}–{full['ci_high']:.1%}) of {full['episodes']}" if full else "—"
        )
        lines.append(
            f"| {r['scenario']}{' (warm start)' if r['warm_start'] else ''}"
            f"{''.join(f', `{o}`' for o in r.get('overrides', []))} | {r['measured_utc']}, {_cpu(r)}, load "
            f"{r['load_1min']:.1f} | `{r['world']}` | {r['trained_min']:.1f} min | {r['steps']} | "
            f"{r['steps_per_s']:.0f} | {_policy_steps(r)} | {_rate(trained)} | {full_cell} | {_rate(r['random'])} | "
            f"≥ {r['target']:.0%} ({met}) | {causes or 'none'} | {r['curves']} |"
        )
    if rows:
        lines += [
            "",
            "Policy of step: the env steps of the weights evaluated: the run's best periodic evaluation on its own "
            "held-back seeds (1000000+, `eval.keep_best`), with that evaluation's success in brackets; runs from "
            "before keep_best: the last update's. Success, `drivesim eval`: the same weights over more episodes "
            "(`drivesim eval --episodes 1000`, seeds 0+, 95 % Wilson interval), attached with `--attach-eval`; where "
            "it exists it decides whether the target is met.",
            "",
            "Machines (the CPU of each run is in its row; speeds of runs on different CPUs do not compare): "
            + "; ".join(sorted({r["machine"].split(", load average")[0] for r in rows}))
            + ".",
        ]
    (RESULTS / "learning.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {RESULTS / 'learning.md'}")


def _cpu(row: dict) -> str:
    """The CPU model of a row's machine line ("2-core CPU (AMD EPYC), no GPU, ..." -> "AMD EPYC")."""
    machine = row["machine"]
    start = machine.find("(") + 1
    end = machine.find("),", start)  # the model itself may hold brackets: "Intel(R) Xeon(R) Processor"
    return machine[start:end] if start and end > 0 else machine


def attach_eval(result_json: Path, metrics_json: Path) -> None:
    """Record a `drivesim eval` of the row's run (its metrics.json) as the row's `full_eval`."""
    row = json.loads(result_json.read_text())
    metrics = json.loads(metrics_json.read_text())
    if Path(metrics["policy_path"]).resolve() != Path(row["run"]).resolve():
        raise SystemExit(f"{metrics_json} evaluates {metrics['policy_path']}, not this row's run {row['run']}")
    success = metrics["aggregate"]["success"]
    row["full_eval"] = {
        "episodes": metrics["episodes"],
        "success": success["value"],
        "ci_low": success["ci_low"],
        "ci_high": success["ci_high"],
        "causes": metrics["intervention_causes"],
        "metrics": str(metrics_json),
    }
    result_json.write_text(json.dumps(row, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", action="append", choices=sorted(SCENARIOS), help="run only these scenarios")
    parser.add_argument("--minutes", type=float, default=None, help="override every scenario's training budget")
    parser.add_argument("--episodes", type=int, default=50, help="evaluation episodes per policy")
    parser.add_argument(
        "--set", action="append", default=None, help="a train config override on top of the preset (repeatable)"
    )
    parser.add_argument("--demo-world", type=Path, default=Path("/tmp/ws-demo/world"))
    parser.add_argument(
        "--kitti-world",
        type=Path,
        default=None,
        help="a world built from ../shared/data/real (default: built into --scratch)",
    )
    parser.add_argument(
        "--scratch",
        type=Path,
        default=Path("/tmp/drivesim-bench-learning"),
        help="workspace root for the runs (outside the repository)",
    )
    parser.add_argument(
        "--attach-eval",
        nargs=2,
        metavar=("RESULT_JSON", "METRICS_JSON"),
        help="attach a `drivesim eval` metrics.json of a run's policy to its result row "
        "(experiments/learning/results/learning_*.json), rewrite learning.md and stop",
    )
    args = parser.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.attach_eval:
        attach_eval(Path(args.attach_eval[0]), Path(args.attach_eval[1]))
        write_results()
        return
    for name in args.only or list(SCENARIOS):
        scenario = SCENARIOS[name]
        world = args.demo_world if scenario.world_kind == "demo" else args.kitti_world
        if scenario.world_kind == "kitti" and world is None:
            world = build_kitti_world(args.scratch)
        if world is None or not (world / "manifest.json").is_file():
            print(f"skipping {name}: no world at {world} (build one and pass --kitti-world / --demo-world)")
            continue
        load_1min = os.getloadavg()[0]
        minutes = args.minutes if args.minutes is not None else scenario.minutes
        result = run_scenario(scenario, world, minutes, args.episodes, args.scratch, args.set)
        print(f"{name}: trained {_rate(result['trained'])}, random {_rate(result['random'])}")
        row = scenario_row(scenario, world, result, load_1min, args.episodes)
        row["overrides"] = args.set or []
        (RESULTS / f"learning_{name}.json").write_text(json.dumps(row, indent=1))
        write_results()


if __name__ == "__main__":
    main()
