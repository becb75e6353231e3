"""`drivesim export onnx` and `OnnxPolicy`: one graph that reproduces the torch policy, with metadata; bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from drivesim.pipeline.errors import DrivesimError
from drivesim.pipeline.workspace import Workspace
from drivesim.policy.onnx_runtime import OnnxPolicy
from drivesim.policy.run_folder import load_policy

SHAPE = (3, 64, 160)


def make_run(folder: Path, task: str = "overtake", hidden: int = 16) -> Path:
    """A finished run folder as `drivesim train` writes it (small network, random but non-trivial weights)."""
    import torch

    from drivesim.pipeline.hashing import sha256_file
    from drivesim.policy.run_folder import build_net
    from drivesim.stages.train.run_files import write_json, write_policy_files

    arch = {"conv_layers": [[8, 5, 4], [16, 3, 2]], "features_dim": 32, "lstm_hidden_size": hidden, "lstm_layers": 1}
    torch.manual_seed(0)
    net = build_net({"observation_shape": list(SHAPE), "architecture": arch})
    with torch.no_grad():  # a steering head large enough that actions vary over the rollout
        net.action_head.weight.mul_(20.0)
    folder.mkdir(parents=True)
    write_policy_files(folder, task, SHAPE, arch, net.state_dict(), 0.15)
    env_config = {"roi_px": [40, 60, 240, 96], "episode_steps": 300}  # as training resolves it (run config)
    config = {"train": {"task": task}, "env_config": env_config, "worlds": [], "meshes": None}
    write_json(folder / "config.json", config)
    outputs = {"policy.pt": {"sha256": sha256_file(folder / "policy.pt")}}
    write_json(folder / "manifest.json", {"outputs": outputs, "config_hash": "abc123", "created_utc": "2026-01-01"})
    return folder


def drivesim(ws: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "-w", str(ws), *args], capture_output=True, text=True, timeout=300
    )


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    ws = tmp_path_factory.mktemp("ws")
    run = make_run(ws / "runs" / "overtake-20260101-000000")
    done = drivesim(ws, "export", "onnx", "--set", "latency_steps=50")  # default run: the newest one
    assert done.returncode == 0, done.stderr
    assert "policy.onnx" in done.stdout
    return ws, run


def test_export_writes_a_checked_graph_with_metadata(exported: tuple[Path, Path]) -> None:
    ws, run = exported
    onnx_path = ws / "export" / "policy.onnx"
    check = json.loads((ws / "export" / "check.json").read_text())
    assert check["run"] == str(run)
    assert check["rollout"]["steps"] == 200 and check["rollout"]["reset_step"] == 100
    assert check["max_abs_diff"] <= 1e-4 and check["rollout"]["max_rel_diff_state"] <= 1e-4
    assert check["rollout"]["action_range"] > 0.05  # the compared actions really vary
    assert 0 < check["latency"]["median_ms"] < 1000 / 30
    assert check["size_bytes"] == onnx_path.stat().st_size

    policy = OnnxPolicy(onnx_path)
    assert policy.observation_shape == SHAPE and policy.task == "overtake"
    assert (policy.lstm_layers, policy.hidden_size) == (1, 16)
    assert policy.config_hash == "abc123"
    assert policy.metadata["roi_px"] == [40, 60, 240, 96]
    assert policy.metadata["action_scale"]["max_curvature_1pm"] == pytest.approx(0.15)
    assert policy.env_config["episode_steps"] == 300


def test_onnx_policy_matches_loaded_policy_with_resets(exported: tuple[Path, Path]) -> None:
    ws, run = exported
    torch_policy, onnx_policy = load_policy(run), OnnxPolicy(ws / "export" / "policy.onnx")
    rng = np.random.default_rng(3)
    state_t, state_o = torch_policy.initial_state(3), onnx_policy.initial_state(3)
    actions = []
    for t in range(30):
        obs = rng.integers(0, 256, size=(3, *SHAPE), dtype=np.uint8)
        starts = np.array([t == 0, t == 12, t in (0, 20)], dtype=bool)
        a_t, state_t = torch_policy.predict(obs, state_t, starts)
        a_o, state_o = onnx_policy.predict(obs, state_o, starts)
        assert a_o.shape == (3, 1) and a_o.dtype == np.float32
        np.testing.assert_allclose(a_o, a_t, atol=1e-5)
        np.testing.assert_allclose(state_o[0], state_t[0], atol=1e-5)
        actions.append(a_o)
    assert np.ptp(np.stack(actions)) > 0.05
    with pytest.raises(ValueError, match="uint8"):
        onnx_policy.predict(np.zeros((1, 3, 32, 32), np.uint8), None, np.ones(1))


def test_second_export_is_fresh(exported: tuple[Path, Path]) -> None:
    ws, _ = exported
    done = drivesim(ws, "export", "onnx", "--set", "latency_steps=50")
    assert done.returncode == 0 and "fresh" in done.stdout


def test_onnx_with_wrong_inputs_is_one_line(tmp_path: Path) -> None:
    import torch

    class Other(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return x * 2

    path = tmp_path / "other.onnx"
    torch.onnx.export(Other(), (torch.zeros(1, 4),), str(path), input_names=["x"], dynamo=False)
    with pytest.raises(DrivesimError, match="not a drivesim policy graph") as info:
        OnnxPolicy(path)
    assert "\n" not in info.value.one_line()
    (tmp_path / "junk.onnx").write_bytes(b"not onnx")
    with pytest.raises(DrivesimError, match="not a readable ONNX model"):
        OnnxPolicy(tmp_path / "junk.onnx")


def test_bad_input_is_one_line_and_writes_nothing(tmp_path: Path) -> None:
    ws = tmp_path / "ws"
    done = drivesim(ws, "export", "onnx")
    assert done.returncode == 2 and "drivesim train" in done.stderr and len(done.stderr.strip().splitlines()) == 1
    make_run(ws / "runs" / "lane-20260101-000000", task="lane")
    # A tolerance nothing can meet: the check fails and no export/ folder is left behind.
    done = drivesim(ws, "export", "onnx", "--set", "tolerance=1e-15")
    assert done.returncode == 2 and "differs from torch" in done.stderr
    assert len(done.stderr.strip().splitlines()) == 1
    assert not (ws / "export").exists()
    assert Workspace(ws).read_manifest("export") is None


@pytest.mark.slow
def test_onnx_policy_evaluates_like_the_trained_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run of a few hundred PPO steps, exported: `eval --policy model.onnx` gives the torch run's metrics."""
    from drivesim.pipeline.config import load_config
    from drivesim.stages.evaluate.config import EvalConfig
    from drivesim.stages.evaluate.stage import run_eval
    from drivesim.stages.export.config import ExportConfig
    from drivesim.stages.export.stage import run_export
    from drivesim.stages.train.config import TrainConfig
    from drivesim.stages.train.stage import run_training

    monkeypatch.syspath_prepend(str(Path(__file__).parent))  # eval_fakes, for the eval workers too
    monkeypatch.setenv("PYTHONPATH", str(Path(__file__).parent))
    ws = Workspace(tmp_path / "ws")
    small = [
        "envs.source=cost_free",
        "envs.count=2",
        "envs.vec_env=dummy",
        "envs.config.episode_steps=40",
        "ppo.buffer_steps=128",
        "ppo.minibatch_steps=64",
        "ppo.epochs=2",
        "eval.every_steps=100000",
        "eval.episodes=1",
        "total_steps=384",
    ]
    run = run_training(ws, load_config(TrainConfig, preset="train/overtake", overrides=small)).path
    exported = run_export(ws, ExportConfig(run=str(run), latency_steps=50))
    onnx_path = exported.path / "policy.onnx"
    fake = {"env_id": "drivesim-test/FakeOvertake-v0", "env_entry_point": "eval_fakes:FakeDrivingEnv"}
    world = tmp_path / "world"  # the fake env's road: one recorded frame per metre, a gentle bend
    world.mkdir()
    x_m = np.arange(200.0)
    np.savez(world / "path.npz", x_m=x_m, y_m=0.002 * x_m**2, arc_length_m=x_m)
    metrics = {}
    for policy in (str(run), str(onnx_path)):
        cfg = EvalConfig(task="overtake", policy=policy, episodes=6, world=str(world), workers=1, **fake)
        result = run_eval(ws, cfg, trust_entry_point=True)
        metrics[policy] = json.loads((result.path / "metrics.json").read_text())
    torch_metrics, onnx_metrics = metrics[str(run)], metrics[str(onnx_path)]
    assert torch_metrics["aggregate"].keys() == onnx_metrics["aggregate"].keys()
    compared = []
    for key, value in torch_metrics["aggregate"].items():
        theirs = onnx_metrics["aggregate"][key]
        if isinstance(value, dict) and isinstance(value.get("value"), float):
            assert theirs["value"] == pytest.approx(value["value"], abs=1e-4, nan_ok=True), key
            compared.append(key)
    assert {"intervention", "min_clearance_m", "max_deviation_m", "max_yaw_rad"} <= set(compared)


@pytest.mark.slow
def test_a_real_runs_onnx_records_its_view_and_evaluates_like_the_run(tmp_path: Path) -> None:
    """A short run in the simulator (default ROI): the export's metadata carries the ROI and observation shape
    training used, and `drivesim eval` of the ONNX gives the run folder's metrics on 50 seeds."""
    from sim_worlds import write_test_world

    from drivesim.pipeline.config import load_config
    from drivesim.stages.evaluate.config import EvalConfig
    from drivesim.stages.evaluate.stage import run_eval
    from drivesim.stages.export.config import ExportConfig
    from drivesim.stages.export.stage import run_export
    from drivesim.stages.train.config import TrainConfig
    from drivesim.stages.train.stage import run_training

    world = write_test_world(tmp_path / "world")  # 80 x 50 pixels
    (world / "manifest.json").write_text(json.dumps({"outputs": {}, "config_hash": "test-world"}))
    ws = Workspace(tmp_path / "ws")
    small = [
        "envs.count=2",
        "envs.config.observation_width_px=40",
        "envs.config.observation_height_px=16",
        "envs.config.episode_steps=30",
        "policy.input_pool=1",
        "policy.conv_layers=[[8,3,2],[16,3,1]]",
        "ppo.buffer_steps=128",
        "ppo.minibatch_steps=64",
        "ppo.epochs=1",
        "eval.every_steps=0",
        "total_steps=128",
    ]
    cfg = load_config(TrainConfig, preset="train/lane", overrides=small)
    run = run_training(ws, cfg, worlds=[world]).path
    run_config = json.loads((run / "config.json").read_text())
    # The default ROI of an 80 x 50 image for a 40 x 16 observation: full width, the bottom 32 rows.
    assert run_config["env_config"]["roi_px"] == [0, 18, 80, 32]
    assert run_config["observation_shape"] == [3, 16, 40]

    onnx_path = run_export(ws, ExportConfig(run=str(run), latency_steps=20)).path / "policy.onnx"
    policy = OnnxPolicy(onnx_path)
    assert policy.metadata["roi_px"] == [0, 18, 80, 32]
    assert list(policy.observation_shape) == policy.metadata["observation_shape"] == [3, 16, 40]

    metrics = {}
    for name, chosen in (("run", str(run)), ("onnx", str(onnx_path))):
        eval_cfg = EvalConfig(task="lane", policy=chosen, episodes=50, world=str(world), workers=1, name=name)
        metrics[name] = json.loads((run_eval(ws, eval_cfg).path / "metrics.json").read_text())["aggregate"]
    compared = 0
    for key, value in metrics["run"].items():
        if isinstance(value, dict) and isinstance(value.get("value"), float):
            assert metrics["onnx"][key]["value"] == pytest.approx(value["value"], abs=1e-3, nan_ok=True), key
            compared += 1
    assert compared >= 5
