"""Ensemble runs (`drivesim train --ensemble N`, `--ensemble-of`): the members are runs of their own, the ensemble's
steering is the mean of their clipped steering, it exports to ONNX, and runs that see different observations are
refused with one line. Tiny cost-free trainings; whether ensembles transfer better is a benchmark
(experiments/transfer), not a test."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from test_train import _drivesim, small_config

from drivesim.pipeline.workspace import Workspace
from drivesim.policy.run_folder import load_policy
from drivesim.stages.train.stage import run_training


@pytest.fixture(scope="module")
def ensemble_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    ws = Workspace(tmp_path_factory.mktemp("ws"))
    result = run_training(ws, small_config(256, ["ensemble=2", "seed=3"]))
    return result.path


def _members(run: Path) -> list[Path]:
    return [Path(p) for p in json.loads((run / "config.json").read_text())["ensemble_of"]]


def test_an_ensemble_is_its_members_runs_and_a_run_of_them(ensemble_run: Path) -> None:
    """--ensemble 2 trains two runs with seeds seed and seed + 1, then the ensemble run, whose manifest names them as
    inputs and whose summary adds up their training."""
    members = _members(ensemble_run)
    assert len(members) == 2 and ensemble_run not in members
    seeds = [json.loads((m / "config.json").read_text())["train"]["seed"] for m in members]
    assert seeds == [3, 4]
    for name in ("policy.json", "policy.pt", "config.json", "normalization.json", "manifest.json"):
        assert (ensemble_run / name).is_file(), name
    info = json.loads((ensemble_run / "policy.json").read_text())
    assert info["ensemble"] == {"members": 2, "runs": [m.name for m in members]}
    manifest = json.loads((ensemble_run / "manifest.json").read_text())
    assert {k: Path(v["path"]) for k, v in manifest["inputs"].items()} == {"member_00": members[0],
                                                                           "member_01": members[1]}  # fmt: skip
    steps = [json.loads((m / "manifest.json").read_text())["summary"]["steps"] for m in members]
    assert manifest["summary"]["steps"] == sum(steps) and manifest["config"]["ensemble"] == 2


def test_the_ensemble_steers_the_mean_of_its_members(ensemble_run: Path) -> None:
    """Step by step, with an episode restarting in the middle, the ensemble's action is the mean of its members'
    clipped actions, and its export module acts the same."""
    ensemble = load_policy(ensemble_run)
    members = [load_policy(m) for m in _members(ensemble_run)]
    export = ensemble.export_module()
    rng = np.random.default_rng(0)
    state = ensemble.initial_state(2)
    member_states = [m.initial_state(2) for m in members]
    h, c = (torch.from_numpy(s) for s in ensemble.initial_state(2))
    differ = False
    for t in range(10):
        obs = rng.integers(0, 255, (2, *ensemble.observation_shape), dtype=np.uint8)
        start = np.array([t == 0, t in (0, 5)], dtype=bool)
        action, state = ensemble.predict(obs, state, start)
        outputs = [m.predict(obs, s, start) for m, s in zip(members, member_states, strict=True)]
        member_states = [s for _, s in outputs]
        np.testing.assert_allclose(action, np.mean([a for a, _ in outputs], axis=0), atol=1e-6)
        with torch.no_grad():
            exported, h, c = export(torch.from_numpy(obs), h, c, torch.from_numpy(start.astype(np.float32)))
        np.testing.assert_allclose(exported.numpy(), action, atol=1e-5)
        differ |= not np.allclose(outputs[0][0], outputs[1][0], atol=1e-4)
    assert differ, "the members act alike: the mean would not be tested"
    assert state[0].shape == (1, 2, 2 * members[0].hidden_size)


def test_an_ensemble_exports_to_onnx(ensemble_run: Path) -> None:
    """`drivesim export onnx` of an ensemble run: the graph holds every member and matches torch (the stage's own
    onnxruntime check over a rollout with a reset)."""
    ws = ensemble_run.parents[1]
    result = subprocess.run(_drivesim(ws, "export", "onnx", "--run", str(ensemble_run)),
                            capture_output=True, text=True, timeout=300)  # fmt: skip
    assert result.returncode == 0, result.stderr
    check = json.loads((ws / "export" / "check.json").read_text())
    assert check["max_abs_diff"] < 1e-4 and check["rollout"]["action_range"] > 0


def test_runs_that_see_differently_are_refused_with_one_line(ensemble_run: Path, tmp_path: Path) -> None:
    """--ensemble-of with one run, or with runs of another network, is one line and exit code 2, and no run is
    written; two of the members again make a second ensemble."""
    members = _members(ensemble_run)
    other = run_training(Workspace(tmp_path / "other"), small_config(256, ["policy.features_dim=64"])).path
    ws = tmp_path / "ws"
    for runs, message in (([members[0]], "at least 2 runs"), ([members[0], other], "network architecture differs")):
        args = [a for run in runs for a in ("--ensemble-of", str(run))]
        result = subprocess.run(_drivesim(ws, "train", *args), capture_output=True, text=True, timeout=120)
        assert result.returncode == 2, result.stderr
        assert message in result.stderr and "Traceback" not in result.stderr
        assert not (ws / "runs").exists() or not [p for p in (ws / "runs").iterdir() if not p.name.startswith(".")]
    args = [a for run in members for a in ("--ensemble-of", str(run))]
    result = subprocess.run(_drivesim(ws, "train", *args), capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "ensemble of 2 runs" in result.stdout
