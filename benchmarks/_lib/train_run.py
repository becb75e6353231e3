"""`drivesim train` as a user types it, timed: the rate its own progress.csv reports."""

from __future__ import annotations

import csv
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

PROGRESS_KEYS = ("steps", "wall_s", "steps_per_s_run", "time_rollout_s", "time_optimization_s", "time_imitation_s",
                 "time_simulator_s", "eval_success_rate", "eval_return_mean")  # fmt: skip


def train_stage_row(world: Path, task: str, steps: int, eval_every: int, eval_episodes: int) -> dict[str, Any]:
    """`drivesim train` in a fresh workspace for `steps` env steps; its last progress.csv row and its wall time."""
    with tempfile.TemporaryDirectory(prefix="bench-train-speed-") as tmp:
        command = [
            sys.executable, "-m", "drivesim.cli.main", "--workspace", tmp, "train", task, "--world", str(world),
            "--total-steps", str(steps), "--set", "towns=[]", "--set", f"eval.every_steps={eval_every}",
            "--set", f"eval.episodes={eval_episodes}",
        ]  # fmt: skip
        began = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True, check=False)
        wall_s = time.perf_counter() - began
        if done.returncode != 0:
            sys.exit(f"drivesim train failed (exit {done.returncode}):\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
        progress = next(Path(tmp, "runs").glob("*/progress.csv"))
        rows = list(csv.DictReader(progress.open()))
    last = {k: float(v) for k, v in rows[-1].items() if k in PROGRESS_KEYS and v}
    print(
        f"drivesim train: {last['steps']:.0f} steps, {last['steps_per_s_run']} env steps/s, {wall_s:.0f} s", flush=True
    )
    command_line = "drivesim " + " ".join(command[3:]).replace(tmp, "WS")
    return {"command": command_line, "updates": len(rows), "command_wall_s": wall_s, "last_progress_row": last}
