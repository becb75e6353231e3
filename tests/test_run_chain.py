"""`drivesim run`: the whole chain on a recording with a tiny preset, then again with every stage fresh; bad input."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml
from cli_helpers import drivesim_with_fakes

from drivesim.chain.run import load_run_preset
from drivesim.pipeline.errors import ConfigError

# A tiny chain: an 8-s synthetic drive, a few hundred training steps on the cost-free env (the simulator's envs
# are tested by their owners), eval on the fake overtake env of the eval tests, export with its checks.
TINY = {
    "synth": {"drive": {"duration_s": 6.0}, "camera": {"width_px": 320, "height_px": 200}},
    "train": {
        "task": "overtake",
        "total_steps": 256,
        "envs": {"source": "cost_free", "count": 2, "vec_env": "dummy", "config": {"episode_steps": 40}},
        "ppo": {"buffer_steps": 128, "minibatch_steps": 64, "epochs": 1},
        "eval": {"every_steps": 100000, "episodes": 1},
    },
    "eval": {
        "task": "overtake",
        "episodes": 4,
        "env_id": "drivesim-test/FakeOvertake-v0",
        "env_entry_point": "eval_fakes:FakeDrivingEnv",
    },
    "export": {"latency_steps": 50},
}


def drivesim(ws: Path, *args: str) -> subprocess.CompletedProcess:
    return drivesim_with_fakes(ws, *args)


@pytest.mark.slow
def test_run_walks_the_chain_then_skips_it(tmp_path: Path) -> None:
    from drivesim.chain.registry import CHAIN

    names = [spec.name for spec in CHAIN]
    if "export" not in names:
        pytest.skip("export is not in the chain registry yet")
    tiny = tmp_path / "tiny.yaml"
    tiny.write_text(yaml.safe_dump(TINY))
    ws = tmp_path / "ws"
    args = ["run", "--preset", "demo", "--config", str(tiny), "--set", "preprocess.depth.method=plane"]
    # Training gets what the stages before it left of the hour; a re-run still finds the run fresh.
    args += ["--set", "chain.budget_s=3600", "--set", "train.time_limit_s=3600"]
    done = drivesim(ws, *args, "--trust-entry-point")
    assert done.returncode == 0, done.stderr[-2000:]
    out = done.stdout
    for stage in ["synth", *names]:
        assert f"{stage}: done" in out, out
    assert (ws / "recordings" / "demo.mcap").is_file()
    onnx = ws / "export" / "policy.onnx"
    assert f"policy: {onnx}" in out
    report_lines = [line for line in out.splitlines() if line.startswith("report: ")]
    assert len(report_lines) == 1
    report = Path(report_lines[0][len("report: ") :])
    assert report.is_file() and report.parent.parent == ws / "eval"
    assert "chain finished in " in out and " env steps)" in out  # with the training's time and steps
    run_dir = next((ws / "runs").iterdir())
    time_limit_s = json.loads((run_dir / "manifest.json").read_text())["summary"]["time_limit_s"]
    assert 3000 < time_limit_s <= 3600 - 420  # the hour less what eval and export keep, less the stages before
    check = json.loads((ws / "export" / "check.json").read_text())
    assert check["max_abs_diff"] <= 1e-4 and Path(check["run"]).parent == ws / "runs"

    again = drivesim(ws, *args, "--trust-entry-point")
    assert again.returncode == 0, again.stderr[-2000:]
    for stage in ["synth", *names]:
        assert f"{stage}: fresh, skipped" in again.stdout, again.stdout
    assert f"policy: {onnx}" in again.stdout
    assert len(list((ws / "runs").iterdir())) == 1  # no second training run


def test_run_presets_load_and_bad_ones_are_one_line(tmp_path: Path) -> None:
    demo = load_run_preset("demo")
    assert demo["synth"]["drive"]["duration_s"] == 60.0
    assert demo["preprocess"]["depth"]["method"] == "mvs"
    assert demo["train"]["time_limit_s"] <= 900
    merged = load_run_preset("demo", overrides=["train.total_steps=512"])
    assert merged["train"]["total_steps"] == 512 and merged["train"]["task"] == "overtake"
    with pytest.raises(ConfigError, match="no run preset 'nope'; presets: demo, full"):
        load_run_preset("nope")
    with pytest.raises(ConfigError, match="STAGE.KEY=VALUE"):
        load_run_preset("demo", overrides=["total_steps=5"])

    ws = tmp_path / "ws"
    done = drivesim(ws, "run", str(tmp_path / "missing.bag"))
    assert done.returncode == 2 and "no such recording" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    bad = tmp_path / "bad.yaml"
    bad.write_text("trian:\n  total_steps: 5\n")
    done = drivesim(ws, "run", str(bad), "--config", str(bad))
    assert done.returncode == 2 and "unknown stage(s) trian" in done.stderr
    bad.write_text("train:\n  total_stepz: 5\n")
    done = drivesim(ws, "run", str(bad), "--config", str(bad))
    assert done.returncode == 2 and "train.total_stepz" in done.stderr
    assert not (ws / "trace").exists()
    shutil.rmtree(ws, ignore_errors=True)
