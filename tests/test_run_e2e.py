"""`drivesim run REC` end to end on a small synthetic recording with the real simulator and real PPO on overtake:
the recording preset (no --preset), tiny budgets by --set; the run ends with the Table I rows, the worlds it trained
on and the report, and the run kept its warm start."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

# Tiny budgets on top of the recording preset: a few hundred PPO steps after a one-round warm start, 2 envs, short
# episodes, a handful of evaluation episodes and baselines.
TINY = [
    "preprocess.depth.method=plane",
    "train.total_steps=256",
    "train.time_limit_s=300",
    "train.envs.count=2",
    "train.envs.config.episode_steps=40",
    "train.ppo.buffer_steps=128",
    "train.ppo.minibatch_steps=64",
    "train.ppo.epochs=1",
    "train.warm_start.iterations=1",
    "train.warm_start.steps_per_iteration=128",
    "train.imitation.epochs=0",
    "train.eval.every_steps=0",
    "eval.episodes=4",
    "eval.baseline_episodes=3",
    "eval.workers=1",
    "eval.record=none",
    "export.latency_steps=20",
]
NUMBER = r"\d+\.\d{3}"


def _drivesim(ws: Path, *args: str, timeout_s: float = 600) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env=env,
    )


@pytest.mark.slow
def test_drivesim_run_trains_overtake_in_the_real_simulator_and_ends_with_the_result(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    recording = tmp_path / "drive.mcap"
    synth = [f"--set={key}" for key in ("camera.width_px=320", "camera.height_px=200")]
    made = _drivesim(ws, "synth", "--seed", "3", "--duration-s", "10", "--output", str(recording), *synth)
    assert made.returncode == 0, made.stderr[-2000:]
    began = time.perf_counter()
    done = _drivesim(ws, "run", str(recording), *(a for key in TINY for a in ("--set", key)))
    wall_s = time.perf_counter() - began
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    out = done.stdout

    (run_dir,) = (ws / "runs").iterdir()
    config = json.loads((run_dir / "config.json").read_text())
    assert config["train"]["task"] == "overtake" and config["train"]["envs"]["source"] == "simulator"
    assert config["train"]["time_limit_s"] == 300  # the recording preset's key, overridden by --set
    assert (run_dir / "checkpoints" / "warm_start.pt").is_file()

    rows = {line.split("│")[1].strip(): [c.strip() for c in line.split("│")[2:-1]] for line in out.splitlines()
            if line.count("│") > 5}  # fmt: skip
    policy = f"{run_dir.name} (all episodes)"
    for name in (policy, f"{run_dir.name} (same seeds)", "expert", "warm start", "paper, garage", "paper, outdoor"):
        assert name in rows, out
    assert rows[policy][0] == "4" and rows["expert"][0] == rows["warm start"][0] == "3"
    for name in (policy, "expert", "warm start"):
        intervention, *rates = rows[name][1:6]
        assert re.fullmatch(rf"{NUMBER} \[{NUMBER}, {NUMBER}\]", intervention), rows[name]
        assert all(0.0 <= float(v) <= 1.0 for v in [intervention.split()[0], *rates]), rows[name]
        clearance, deviation, yaw = (float(v) if v != "n/a" else None for v in rows[name][6:9])
        assert clearance is not None and 0.0 <= clearance < 50.0
        assert deviation is not None and 0.0 <= deviation <= 2.5 and yaw is not None and 0.0 <= yaw <= 0.5
    assert "trained on: drive" in out  # the workspace's world, named after the recording
    report_lines = [line for line in out.splitlines() if line.startswith("report: ")]
    assert len(report_lines) == 1
    report = Path(report_lines[0][len("report: ") :])
    assert report.is_file() and report.parent.parent == ws / "eval"
    assert "Beside the expert and the warm start" in report.read_text()
    print(f"drivesim run on the tiny recording: {wall_s:.1f} s")
