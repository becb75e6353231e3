"""How a training run's policy moves over its budget: its periodic checkpoints evaluated on the same seeds.

    .venv/bin/python experiments/real_gap/checkpoint_curve.py WS/runs/RUN --episodes 1000 --every 3

Each chosen `checkpoints/step-*.pt` (and the warm start and the final policy) goes through `drivesim eval` in the
run's workspace (seeds 0..episodes-1, no baselines); prints one markdown row per checkpoint: env steps, training
minutes at the checkpoint (from progress.csv), intervention with its interval, success. If the last third of the
budget still moves the figure, a longer budget would too.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import subprocess
import sys
from pathlib import Path


def _minutes_at(run: Path, steps: int) -> float:
    """Training wall minutes when progress.csv first reached `steps` env steps."""
    with open(run / "progress.csv") as f:
        for row in csv.DictReader(f):
            if int(row["steps"]) >= steps:
                return float(row["wall_s"]) / 60.0
    return float("nan")


def _existing(workspace: Path, policy: Path, episodes: int) -> Path | None:
    """An evaluation of `policy` on seeds 0..episodes-1 with the run's own settings already in the workspace (a
    Table I row's, bench_table1.py's `table1-*`), if any: its metrics.json."""
    for metrics in sorted(workspace.glob("eval/table1-*/metrics.json")):
        m = json.loads(metrics.read_text())
        if Path(m.get("policy_path", "")) == policy and m["episodes"] == episodes and m["seed"] == 0:
            return metrics
    return None


def _evaluate(workspace: Path, policy: Path, name: str, episodes: int, drivesim: list[str]) -> dict:
    """`drivesim eval` of `policy` (or an evaluation of it already there); its metrics.json."""
    metrics = _existing(workspace, policy, episodes) or workspace / "eval" / name / "metrics.json"
    if not metrics.exists():
        cmd = [*drivesim, "--workspace", str(workspace), "eval", "--policy", str(policy), "--episodes", str(episodes)]
        cmd += ["--name", name, "--record", "none", "--set", "baseline_episodes=0", "--force"]
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return json.loads(metrics.read_text())


def main() -> None:
    """Evaluate the run's checkpoints and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a training run folder (runs/<task>-<time>) inside its workspace")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--every", type=int, default=3, help="every Nth step checkpoint (the last one always)")
    parser.add_argument("--last", type=int, default=0, help="instead of --every: the last N step checkpoints")
    parser.add_argument("--drivesim", default=os.environ.get("DRIVESIM", f"{sys.executable} -m drivesim.cli.main"))
    args = parser.parse_args()
    run = args.run.absolute()
    workspace = run.parent.parent
    steps_ckpts = sorted(run.glob("checkpoints/step-*.pt"))
    chosen = steps_ckpts[-args.last :] if args.last else steps_ckpts[args.every - 1 :: args.every]
    if steps_ckpts and steps_ckpts[-1] not in chosen:
        chosen.append(steps_ckpts[-1])
    rows = [(0, run / "checkpoints" / "warm_start.pt", "warm start")]
    rows += [(int(re.search(r"step-(\d+)", p.name).group(1)), p, p.stem) for p in chosen]
    with open(run / "progress.csv") as f:
        last = list(csv.DictReader(f))[-1]
    rows.append((int(last["steps"]), run, "final policy"))
    print(f"{run.name}, {args.episodes} episodes per row (seeds 0-{args.episodes - 1})\n")
    print("| checkpoint | env steps | training min | intervention [95 % CI] | success |")
    print("|---|---:|---:|---:|---:|")
    for steps, policy, label in rows:
        name = f"curve-{run.name}-{label.replace(' ', '-')}"
        m = _evaluate(workspace, policy, name, args.episodes, args.drivesim.split())["aggregate"]
        i = m["intervention"]
        minutes = _minutes_at(run, steps) if steps else 0.0
        print(
            f"| {label} | {steps} | {minutes:.1f} | {i['value']:.3f} [{i['ci_low']:.3f}, {i['ci_high']:.3f}] | "
            f"{m['success']['value']:.3f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
