"""The `drivesim` command as a user types it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

STAGES = [
    "ingest",
    "preprocess",
    "build-world",
    "meshes",
    "synth",
    "train",
    "eval",
    "export",
    "run",
    "status",
    "config",
]


def _drivesim(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", *args], cwd=cwd, capture_output=True, text=True, timeout=120
    )


def test_help_lists_every_stage(tmp_path: Path) -> None:
    result = _drivesim("--help", cwd=tmp_path)
    assert result.returncode == 0
    for stage in STAGES:
        assert f" {stage} " in result.stdout, stage


def test_stage_without_its_input_says_what_to_run_and_exits_2(tmp_path: Path) -> None:
    result = _drivesim("train", "overtake", cwd=tmp_path)
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "no world artifact" in lines[0] and "drivesim build-world" in lines[0]


def test_status_json_on_empty_workspace(tmp_path: Path) -> None:
    result = _drivesim("--workspace", str(tmp_path / "ws"), "status", "--json", cwd=tmp_path)
    assert result.returncode == 0
    report = json.loads(result.stdout)
    assert report["format"] == 1
    assert [row["stage"] for row in report["stages"]][:3] == ["ingest", "preprocess", "build-world"]
    assert {row["state"] for row in report["stages"]} == {"missing"}


def test_config_shows_resolved_values_and_units(tmp_path: Path) -> None:
    result = _drivesim("config", "preprocess", "--yaml", "--set", "depth.method=mvs", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    import yaml

    resolved = yaml.safe_load(result.stdout)
    assert resolved["depth"]["method"] == "mvs"
    (tmp_path / "mine.yaml").write_text(result.stdout)
    table = _drivesim("config", "ingest", "--config", str(tmp_path / "mine.yaml"), cwd=tmp_path)
    assert table.returncode == 2 and "unknown config key" in table.stderr  # a preprocess file is not an ingest one
    table = _drivesim("config", "ingest", cwd=tmp_path)
    assert "image.width_px" in table.stdout and "640" in table.stdout


def test_unknown_override_key_is_one_line_naming_valid_keys(tmp_path: Path) -> None:
    result = _drivesim("config", "ingest", "--set", "image.widht=3", cwd=tmp_path)
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "image.widht" in lines[0] and "width_px" in lines[0]


def test_a_device_this_machine_lacks_is_one_line(tmp_path: Path) -> None:
    """`device` and `envs.config.render_device` take a torch device this machine has; a GPU asked for on a machine
    without one, or a device drivesim does not run on, is refused in one line that says what to give."""
    import torch

    result = _drivesim("config", "train", "--set", "device=cpu", "--set", "envs.config.render_device=cpu", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    asks = [("envs.config.render_device=tpu", "cpu or cuda"), ("device=gpu0", "not a torch device")]
    if not torch.cuda.is_available():
        asks.append(("device=cuda", "no CUDA device"))
    for setting, reason in asks:
        result = _drivesim("config", "train", "--set", setting, cwd=tmp_path)
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        assert result.returncode == 2 and len(lines) == 1 and reason in lines[0], (setting, result.stderr)
