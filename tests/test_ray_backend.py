"""`--backend ray` of eval and train on a real Ray cluster on the loopback address: the same seeds give the same
episode files and metrics as the local backend, a worker node killed mid-evaluation loses no episode and runs none
twice, the Ray VecEnv steps exactly like SB3's DummyVecEnv, `drivesim train --backend ray` saves a run, and without
Ray `--backend ray` is one line saying how to install it.

Run alone: `.venv/bin/pytest -q tests/test_ray_backend.py` (about a minute and a half on 2 cores).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import pytest
from eval_fakes import register_fake_envs
from ray_fakes import SLOW_ENTRY_POINT, SLOW_ENV_ID, register_slow_env
from ray_loopback import LOOPBACK, TESTS_DIR, loopback_cluster
from sim_worlds import SMALL_VIEW, write_test_world

from drivesim.pipeline.workspace import Workspace
from drivesim.sim.envs.registry import task_spec
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.evaluate.metrics import aggregate, evaluate_episode
from drivesim.stages.evaluate.rollout import EnvFactory, PolicySpec, read_episode, run_episodes
from drivesim.stages.evaluate.stage import run_eval
from drivesim.stages.train.envs import EnvSource

FAKE = {"env_id": "drivesim-test/FakeOvertake-v0", "env_entry_point": "eval_fakes:FakeDrivingEnv"}


@pytest.fixture(scope="module")
def cluster() -> Any:
    """A Ray cluster of one head node (1 CPU) on 127.0.0.1 for this module; tests add a worker node to it."""
    with loopback_cluster() as ray_cluster:
        yield ray_cluster


def _fake_world(folder: Path, frames: int = 200) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    x = np.arange(float(frames))
    np.savez(folder / "path.npz", x_m=x, y_m=0.002 * x**2, arc_length_m=x)
    return folder


def _drivesim(ws: Path, *args: str, env: dict[str, str] | None = None, timeout_s: float = 240):
    """`drivesim --workspace ws ARGS` in a subprocess with this process's environment (the cluster's included)."""
    return subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env={**os.environ, "OMP_NUM_THREADS": "1", **(env or {})},
    )


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob("*.json"))}


def _headline(folder: Path) -> dict[str, float | None]:
    """Intervention rate, mean min clearance, max deviation and max yaw of the episode files in `folder`."""
    metrics = [evaluate_episode(read_episode(p)).metrics for p in sorted(folder.glob("*.json"))]
    agg = aggregate(metrics)
    return {k: agg[k].value for k in ("intervention", "success", "min_clearance_m", "max_deviation_m", "max_yaw_rad")}


@pytest.mark.parametrize("command", ["eval", "train"])
def test_without_ray_backend_ray_is_one_line_saying_how_to_install(tmp_path: Path, command: str) -> None:
    hidden = tmp_path / "no-ray"
    (hidden / "ray").mkdir(parents=True)
    (hidden / "ray" / "__init__.py").write_text("raise ImportError(\"No module named 'ray'\")\n")
    world = _fake_world(tmp_path / "world")
    args = {
        "eval": ["eval", "--backend", "ray", "--world", str(world), "--policy", "expert"]
        + ["--set", f"env_id={FAKE['env_id']}"],
        "train": ["train", "lane", "--backend", "ray", "--set", "envs.source=cost_free"],
    }[command]
    result = _drivesim(tmp_path / "ws", *args, env={"PYTHONPATH": f"{hidden}{os.pathsep}{TESTS_DIR}"})
    assert result.returncode == 2, result.stdout + result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "pip install 'drivesim[ray]'" in lines[0], result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "ws" / "eval").exists() and not (tmp_path / "ws" / "runs").exists()


def test_eval_on_ray_gives_the_local_files_and_metrics(cluster: Any, tmp_path: Path) -> None:
    world = _fake_world(tmp_path / "world")
    args = ["--world", str(world), "--episodes", "12", "--seed", "100", "--workers", "2", "--policy", "expert"]
    args += ["--set", f"env_id={FAKE['env_id']}", "--set", f"env_entry_point={FAKE['env_entry_point']}"]
    args.append("--trust-entry-point")
    on_ray = _drivesim(tmp_path / "ws", "eval", *args, "--backend", "ray", "--address", cluster.address)
    assert on_ray.returncode == 0, on_ray.stdout + on_ray.stderr
    assert "ray: 2 actors on 1 node(s)" in on_ray.stdout and "with 2 Ray actors" in on_ray.stdout
    ray_dir = tmp_path / "ws" / "eval" / "overtake-expert"

    register_fake_envs()
    cfg = EvalConfig(episodes=12, seed=100, world=str(world), workers=1, **FAKE)
    local = run_eval(Workspace(tmp_path / "ws-local"), cfg)
    files = _files(ray_dir / "episodes")
    assert sorted(files) == sorted(f"{s}.json" for s in range(100, 112))
    assert files == _files(local.path / "episodes")
    by_ray = json.loads((ray_dir / "metrics.json").read_text())
    by_local = json.loads((local.path / "metrics.json").read_text())
    assert by_ray["backend"] == "ray" and by_local["backend"] == "local"
    assert by_ray["aggregate"] == by_local["aggregate"] and by_ray["breakdowns"] == by_local["breakdowns"]
    assert 0 < by_ray["aggregate"]["max_deviation_m"]["value"] < 2.5  # the expert moves over to pass
    # The backend is not part of what an evaluation is: the local backend finds the Ray evaluation fresh.
    assert run_eval(Workspace(tmp_path / "ws"), cfg).skipped


def _assert_same(a: Any, b: Any, where: str = "") -> None:
    """Equal observations, rewards and infos (arrays bit for bit, NaN equal to NaN)."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _assert_same(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray | float | np.floating):
        assert np.array_equal(a, b, equal_nan=True), where
    else:
        assert a == b, where


def test_ray_vec_env_steps_like_dummy_vec_env(cluster: Any, tmp_path: Path) -> None:
    """Same seeds, same actions: the same observations, rewards, dones and infos, across automatic resets."""
    world = write_test_world(tmp_path / "world")
    source = EnvSource(
        task="overtake", worlds=[world], config=task_spec("overtake").config_with({**SMALL_VIEW, "episode_steps": 6})
    )
    dummy = source.make_vec(2, "dummy", seed=7)
    on_ray = source.make_vec(2, "ray", seed=7, address=cluster.address)
    try:
        assert on_ray.num_envs == 2 and on_ray.observation_space == dummy.observation_space
        assert np.array_equal(on_ray.reset(), dummy.reset())
        _assert_same(on_ray.reset_infos, dummy.reset_infos)
        actions = np.random.default_rng(0).uniform(-1, 1, (14, 2, 1)).astype(np.float32)
        resets = 0
        for step_actions in actions:  # crosses the 6-step limit twice: resets with terminal_observation
            obs_r, rew_r, done_r, info_r = on_ray.step(step_actions)
            obs_d, rew_d, done_d, info_d = dummy.step(step_actions)
            assert np.array_equal(obs_r, obs_d) and np.array_equal(rew_r, rew_d) and np.array_equal(done_r, done_d)
            assert obs_r.dtype == np.uint8 and rew_r.dtype == rew_d.dtype
            _assert_same(info_r, info_d)
            resets += int(done_r.sum())
        assert resets >= 4 and np.ptp(obs_r) > 0
        assert np.array_equal(on_ray.env_method("expert_action"), dummy.env_method("expert_action"))
        on_ray.set_attr("marker_m", 1.5, indices=[1])
        assert on_ray.get_attr("marker_m", indices=1) == [1.5] and not on_ray.has_attr("no_such_attribute")
        wrapper = gymnasium.wrappers.TimeLimit  # drivesim's envs end their episodes themselves, unwrapped
        assert on_ray.env_is_wrapped(wrapper) == dummy.env_is_wrapped(wrapper) == [False, False]
    finally:
        on_ray.close()
        dummy.close()


@pytest.mark.slow
def test_train_with_ray_backend_saves_a_run(cluster: Any, tmp_path: Path) -> None:
    small = [
        "envs.source=cost_free",
        "envs.count=3",
        "envs.config.episode_steps=40",
        "ppo.buffer_steps=96",
        "ppo.minibatch_steps=48",
        "ppo.epochs=1",
        "policy.sequence_length_steps=16",
        "eval.every_steps=0",
    ]
    args = ["train", "lane", "--backend", "ray", "--address", cluster.address, "--total-steps", "300"]
    result = _drivesim(tmp_path / "ws", *args, *[a for s in small for a in ("--set", s)])
    assert result.returncode == 0, result.stdout + result.stderr
    runs = list((tmp_path / "ws" / "runs").glob("lane-*"))
    assert len(runs) == 1
    run = runs[0]
    for name in ("manifest.json", "policy.pt", "policy.json", "progress.csv", "checkpoints/last.pt"):
        assert (run / name).is_file(), name
    config = json.loads((run / "config.json").read_text())["train"]
    assert config["envs"]["backend"] == "ray" and config["envs"]["count"] == 3
    rows = (run / "progress.csv").read_text().splitlines()
    header = rows[0].split(",")
    steps = [float(r.split(",")[header.index("steps")]) for r in rows[1:]]
    assert steps[-1] >= 300 and len(steps) >= 3  # 96 steps per update over 3 actor envs


@pytest.mark.slow
def test_killed_worker_node_loses_no_episode_and_runs_none_twice(cluster: Any, tmp_path: Path) -> None:
    """Two nodes on the loopback, one actor each; the worker node is killed once both have returned episodes."""
    import ray

    register_slow_env()
    world = _fake_world(tmp_path / "world")
    factory = EnvFactory(SLOW_ENV_ID, {"world": str(world), "mode": "eval"}, SLOW_ENTRY_POINT, trusted=True)
    seeds = list(range(16))
    worker = cluster.add_node(num_cpus=1, node_ip_address=LOOPBACK)
    cluster.wait_for_nodes()
    from drivesim.stages.evaluate.ray_backend import run_episodes_ray

    done: list[Any] = []
    killed: list[int] = []

    def kill_worker_node_once_both_ran(episode: Any) -> None:
        done.append(episode)
        if not killed and len({d.node for d in done}) == 2:
            cluster.remove_node(worker, allow_graceful=False)
            killed.append(len(done))

    folder = tmp_path / "ray" / "episodes"
    outcome = run_episodes_ray(
        factory, PolicySpec("expert"), "overtake", seeds, folder, cluster.address, None, kill_worker_node_once_both_ran
    )
    assert not ray.is_initialized()  # the evaluation's connection is closed; the cluster is the fixture's
    assert killed and killed[0] < len(seeds), "the worker node was not killed mid-evaluation"
    assert outcome.actors == 2 and outcome.nodes == 2 and outcome.episodes_run == 16
    assert outcome.resubmitted >= 1  # the killed actor's episode in flight ran again on the head node
    assert sorted(d.seed for d in done) == seeds  # every episode reported once, none twice
    assert sorted(p.name for p in folder.iterdir()) == sorted(f"{s}.json" for s in seeds)  # no leftovers
    clean = tmp_path / "clean" / "episodes"  # the same episodes without the delay: FakeDrivingEnv, one process
    register_fake_envs()
    fast = EnvFactory(FAKE["env_id"], {"world": str(world), "mode": "eval"}, FAKE["env_entry_point"], trusted=True)
    run_episodes(fast, PolicySpec("expert"), "overtake", seeds, clean, workers=1)
    assert _files(folder) == _files(clean)
    assert _headline(folder) == _headline(clean)
    assert 0 <= _headline(folder)["intervention"] < 1
