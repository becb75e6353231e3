"""Training mechanics on the cost-free env (seconds): the fused recurrent pass is exact, save -> load gives identical
actions, damaged runs are refused with one line, a killed run resumes, the warm start clones the expert.
Learning itself is shown by experiments/learning/bench_learning.py, not here."""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from cli_helpers import interruptible
from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import DummyVecEnv

from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import ConfigError
from drivesim.pipeline.workspace import Workspace
from drivesim.policy.run_folder import RunError, latest_run, load_policy
from drivesim.sim.envs.registry import TASK_NAMES
from drivesim.stages.train.best import BestPolicy
from drivesim.stages.train.config import TrainConfig
from drivesim.stages.train.cost_free_env import CostFreeDrivingEnv
from drivesim.stages.train.envs import EnvSource
from drivesim.stages.train.recurrent import ChunkedRecurrentPPO
from drivesim.stages.train.run import build_model
from drivesim.stages.train.sb3_policy import DrivingLstmPolicy
from drivesim.stages.train.stage import run_training
from drivesim.stages.train.warm_start import warm_start

SMALL = [
    "envs.source=cost_free",
    "envs.count=2",
    "ppo.buffer_steps=256",
    "ppo.minibatch_steps=128",
    "ppo.epochs=2",
    "eval.every_steps=256",
    "eval.episodes=2",
    "envs.config.episode_steps=40",
    "policy.sequence_length_steps=16",
    "envs.vec_env=dummy",
]


def small_config(total_steps: int = 512, extra: list[str] | None = None) -> TrainConfig:
    return load_config(
        TrainConfig, preset="train/lane", overrides=[*SMALL, f"total_steps={total_steps}", *(extra or [])]
    )


def small_ppo(venv: Any, conv_layers: list[tuple[int, int, int]], input_pool: int) -> ChunkedRecurrentPPO:
    """A small ChunkedRecurrentPPO: 64-step rollouts per env, one epoch, 16-step chunks."""
    return ChunkedRecurrentPPO(
        DrivingLstmPolicy,
        venv,
        n_steps=64,
        batch_size=64,
        n_epochs=1,
        sequence_length=16,
        seed=0,
        device="cpu",
        policy_kwargs={"conv_layers": conv_layers, "input_pool": input_pool},
    )


def cost_free_model(episode_steps: int = 23) -> ChunkedRecurrentPPO:
    venv = DummyVecEnv([lambda: CostFreeDrivingEnv(episode_steps=episode_steps) for _ in range(2)])
    venv.seed(0)
    return small_ppo(venv, [(8, 5, 2), (16, 3, 2)], 2)


def test_fused_recurrent_pass_is_exact() -> None:
    """Chunks with episode starts inside: log-probs and values equal sb3-contrib's per-step loop and the rollout's."""
    torch.manual_seed(0)
    model = cost_free_model(episode_steps=23)  # episodes end inside the 16-step chunks
    model.set_logger(Logger(None, []))  # no SB3 log folder in /tmp
    model._setup_learn(128, None)
    model.collect_rollouts(model.env, model._init_callback(None), model.rollout_buffer, model.n_steps)
    starts_inside = 0
    for batch in model.rollout_buffer.get(64):
        starts = batch.episode_starts.view(-1, 16)
        starts_inside += int(starts[:, 1:].sum())
        policy = model.policy
        with torch.no_grad():
            values, log_prob, _ = policy.evaluate_actions(
                batch.observations.float(), batch.actions, batch.lstm_states, batch.episode_starts
            )
            features = policy.extract_features(batch.observations.float())
            latent, _ = RecurrentActorCriticPolicy._process_sequence(
                features, batch.lstm_states.pi, batch.episode_starts, policy.lstm_actor
            )
            ref_log_prob = policy._get_action_dist_from_latent(latent).log_prob(batch.actions)
        assert torch.allclose(log_prob, ref_log_prob, atol=1e-5)
        assert torch.allclose(values.flatten(), policy.value_net(latent).flatten(), atol=1e-5)
        # ... and equal to what the rollout computed step by step (the stored chunk states are right)
        assert torch.allclose(log_prob, batch.old_log_prob, atol=1e-4)
        assert torch.allclose(values.flatten(), batch.old_values, atol=1e-4)
    assert starts_inside >= 2
    # The update's path: observations preprocessed once for all epochs give the same log-probs and values.
    buffer = model.rollout_buffer
    buffer.preprocessed = model.policy.preprocess_observations(buffer.observations)
    model.policy.observations_preprocessed = True
    for batch in buffer.get(64):
        with torch.no_grad():
            values, log_prob, _ = model.policy.evaluate_actions(
                batch.observations, batch.actions, batch.lstm_states, batch.episode_starts
            )
        assert torch.allclose(log_prob, batch.old_log_prob, atol=1e-4)
        assert torch.allclose(values.flatten(), batch.old_values, atol=1e-4)


class ThreadRecordingEnv(CostFreeDrivingEnv):
    """The cost-free env that notes the learner's torch thread count at every step."""

    seen_threads: list[int] = []

    def step(self, action: np.ndarray) -> Any:
        ThreadRecordingEnv.seen_threads.append(torch.get_num_threads())
        return super().step(action)


def test_rollouts_run_with_their_own_thread_count() -> None:
    """rollout_threads: the rollout runs with 1 torch thread, the optimization with the process's 2 again."""
    cfg = small_config(256, ["rollout_threads=1", "learner_threads=2"])
    venv = DummyVecEnv([lambda: ThreadRecordingEnv(episode_steps=40) for _ in range(2)])
    model = build_model(cfg, venv)
    model.set_logger(Logger(None, []))
    threads_in_updates: list[int] = []
    model.update_hooks.append(lambda: threads_in_updates.append(torch.get_num_threads()))
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    ThreadRecordingEnv.seen_threads = []
    try:
        model.learn(256)
        assert set(ThreadRecordingEnv.seen_threads) == {1}
        assert threads_in_updates and set(threads_in_updates) == {2}
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def _threads_after_making(env_fn: Any) -> int:
    env_fn()
    return torch.get_num_threads()


def test_an_env_made_in_the_learners_process_leaves_it_its_threads() -> None:
    """The learner's torch threads (learner_threads) survive the envs it makes in its own process (the batched
    envs, the probe, the evaluations); an env made in a worker process takes worker_threads there."""
    source = EnvSource("overtake", cost_free=True, config=TrainConfig().envs.config, worker_threads=1)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        source.make_env("eval")
        source.make_vec(2, "dummy", seed=0).close()
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    with multiprocessing.get_context("forkserver").Pool(1) as pool:
        assert pool.apply(_threads_after_making, (source.env_fn("train"),)) == 1


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    ws = Workspace(tmp_path_factory.mktemp("ws"))
    result = run_training(ws, small_config(512))
    assert result.summary.steps >= 512
    return result.path


def test_run_folder_and_round_trip(finished_run: Path) -> None:
    """A finished run holds its files; the loaded policy acts exactly like the trained one (and its export)."""
    for name in (
        "config.json",
        "policy.json",
        "policy.pt",
        "normalization.json",
        "progress.csv",
        "curves.png",
        "manifest.json",
        "checkpoints/last.pt",
        "checkpoints/best.pt",
    ):
        assert (finished_run / name).is_file(), name
    assert list((finished_run / "tb").iterdir())
    header = (finished_run / "progress.csv").read_text().splitlines()[0].split(",")
    for column in (
        "steps_per_s",
        "reward_lane",
        "reward_comfort",
        "term_off_lane",
        "term_time_limit",
        "eval_success_rate",
        "time_simulator_s",
        "time_optimization_s",
    ):
        assert column in header, column
    assert latest_run(finished_run.parents[1], task="lane") == finished_run
    assert latest_run(finished_run.parents[1], task="overtake") is None

    loaded = load_policy(finished_run)
    assert loaded.task == "lane" and loaded.observation_shape == (3, 64, 160)
    cfg = small_config(512)
    venv = DummyVecEnv([lambda: CostFreeDrivingEnv(episode_steps=40) for _ in range(3)])
    model = build_model(cfg, venv)
    # The run's policy is its last update's weights (eval.keep_best off, the default), as in checkpoints/last.pt.
    summary = json.loads((finished_run / "manifest.json").read_text())["summary"]
    checkpoint = torch.load(finished_run / "checkpoints" / "last.pt", weights_only=True)
    assert checkpoint["num_timesteps"] == summary["policy_steps"] == summary["steps"]
    model.policy.load_driving_net_state(checkpoint["policy"])
    export = loaded.export_module()
    rng = np.random.default_rng(1)
    state_sb3, state_ours = None, loaded.initial_state(3)
    h, c = (torch.from_numpy(s) for s in loaded.initial_state(3))
    acted = []
    for t in range(12):
        obs = rng.integers(0, 255, (3, 3, 64, 160), dtype=np.uint8)
        start = np.array([t == 0, t == 0 or t == 6, t == 0], dtype=bool)
        a_sb3, state_sb3 = model.policy.predict(obs, state_sb3, start, deterministic=True)
        a_ours, state_ours = loaded.predict(obs, state_ours, start)
        with torch.no_grad():
            a_export, h, c = export(torch.from_numpy(obs), h, c, torch.from_numpy(start.astype(np.float32)))
        np.testing.assert_allclose(a_ours, np.clip(a_sb3, -1, 1), atol=1e-5)
        np.testing.assert_allclose(a_export.numpy(), a_ours, atol=1e-5)
        acted.append(a_ours)
    assert a_ours.dtype == np.float32 and a_ours.shape == (3, 1)
    assert np.ptp(np.concatenate(acted)) > 1e-4  # the actions depend on the input (not a constant)


def test_damaged_runs_are_refused_with_one_line(finished_run: Path, tmp_path: Path) -> None:
    import shutil

    copy = tmp_path / "lane-copy"
    shutil.copytree(finished_run, copy)
    weights = copy / "policy.pt"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    with pytest.raises(RunError, match="changed or truncated"):
        load_policy(copy)
    (copy / "manifest.json").unlink()
    with pytest.raises(RunError, match="unfinished.*--resume"):
        load_policy(copy)
    with pytest.raises(RunError, match="no such run folder"):
        load_policy(tmp_path / "nope")


def test_pickled_code_is_never_executed(tmp_path: Path) -> None:
    """A weights file holding a pickle that would run code is refused by weights_only loading."""
    from drivesim.policy.net import DrivingNet
    from drivesim.policy.run_folder import load_weights

    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):  # noqa: ANN204
            return (os.system, (f"touch {marker}",))

    bad = tmp_path / "policy.pt"
    torch.save({"encoder.linear.0.weight": Evil()}, bad)
    with pytest.raises(RunError, match="not a readable"):
        load_weights(DrivingNet((3, 64, 160), [(8, 5, 2)], input_pool=2), bad)
    assert not marker.exists()


def _drivesim(ws: Path, *args: str) -> list[str]:
    return [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args]


def _checkpointed_steps(path: Path) -> int:
    """Env steps of a run's last checkpoint (0 while there is none: it is replaced atomically)."""
    return int(torch.load(path, weights_only=True)["num_timesteps"]) if path.is_file() else 0


def test_killed_run_resumes_with_nothing_lost(tmp_path: Path) -> None:
    """SIGKILL mid-run leaves an unfinished, resumable run; --resume finishes it from the last update."""
    ws = tmp_path / "ws"
    sets = [a for s in SMALL for a in ("--set", s)]
    proc = subprocess.Popen(
        _drivesim(ws, "train", "lane", "--total-steps", "100000", *sets), stdout=subprocess.PIPE, stderr=subprocess.PIPE
    )
    try:
        deadline = time.time() + 90
        progress = None
        while time.time() < deadline:
            runs = list((ws / "runs").glob("lane-*")) if (ws / "runs").is_dir() else []
            if runs and (runs[0] / "progress.csv").is_file():
                progress = runs[0] / "progress.csv"
                last = runs[0] / "checkpoints" / "last.pt"
                # two updates logged and checkpointed (the checkpoint is written after its progress row)
                if len(progress.read_text().splitlines()) >= 3 and _checkpointed_steps(last) >= 512:
                    break
            time.sleep(0.2)
        assert progress is not None, "the run wrote no progress in 90 s"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    run_dir = progress.parent
    assert not (run_dir / "manifest.json").exists()
    with pytest.raises(RunError, match="unfinished"):
        load_policy(run_dir)
    done = torch.load(run_dir / "checkpoints" / "last.pt", weights_only=True)["num_timesteps"]
    assert done >= 512
    result = subprocess.run(
        _drivesim(ws, "train", "--resume", str(run_dir), "--total-steps", str(done + 512)),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    assert f"resuming {run_dir.name} at {done} env steps" in result.stderr
    steps = [int(line.split(",")[0]) for line in (run_dir / "progress.csv").read_text().splitlines()[1:]]
    assert steps == sorted(steps) and steps[0] == 256 and steps[-1] >= done + 512
    assert len(set(steps)) == len(steps)  # nothing logged twice, nothing lost
    assert load_policy(run_dir).task == "lane"
    again = subprocess.run(_drivesim(ws, "train", "--resume", str(run_dir)), capture_output=True, text=True)
    assert again.returncode == 2 and "finished" in again.stderr and "Traceback" not in again.stderr


def test_a_run_that_used_its_time_limit_resumes_only_with_more_time(tmp_path: Path) -> None:
    """The time limit counts a run's time across resumes: a plain --resume would stop at once, so it is refused in
    one line that says what to give; with a larger time_limit_s the run trains on."""
    ws = tmp_path / "ws"
    sets = [a for s in [*SMALL, "time_limit_s=2"] for a in ("--set", s)]
    first = subprocess.run(
        _drivesim(ws, "train", "lane", "--total-steps", "100000", *sets), capture_output=True, text=True, timeout=120
    )
    assert first.returncode == 0, first.stderr
    (run_dir,) = (ws / "runs").glob("lane-*")
    done = int((run_dir / "progress.csv").read_text().splitlines()[-1].split(",")[0])
    assert done < 100000
    refused = subprocess.run(_drivesim(ws, "train", "--resume", str(run_dir)), capture_output=True, text=True)
    assert refused.returncode == 2 and "Traceback" not in refused.stderr
    assert "time limit" in refused.stderr and "--set time_limit_s=" in refused.stderr
    assert (run_dir / "manifest.json").is_file()  # left as it was
    more = ["--set", "time_limit_s=600", "--total-steps", str(done + 512)]
    resumed = subprocess.run(_drivesim(ws, "train", "--resume", str(run_dir), *more), capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    assert int((run_dir / "progress.csv").read_text().splitlines()[-1].split(",")[0]) >= done + 512


@pytest.mark.parametrize("clone_chunk_steps", [None, 32])
def test_warm_start_clones_the_expert(clone_chunk_steps: int | None) -> None:
    """After DAgger the deterministic policy steers like the expert on states it drives into itself, with the cloning
    over the policy's 16-step chunks or over chunks of its own length."""
    torch.manual_seed(0)
    chunk_override = [] if clone_chunk_steps is None else [f"warm_start.sequence_length_steps={clone_chunk_steps}"]
    cfg = small_config(
        256,
        [
            *chunk_override,
            "warm_start.method=expert",
            "warm_start.iterations=3",
            "warm_start.epochs=6",
            "warm_start.steps_per_iteration=512",
            "warm_start.value_fit_steps=256",
            "warm_start.value_fit_epochs=2",
        ],
    )
    venv = DummyVecEnv([lambda: CostFreeDrivingEnv(episode_steps=60) for _ in range(2)])
    venv.seed(3)
    model = build_model(cfg, venv)

    def disagreement() -> float:
        env = CostFreeDrivingEnv(episode_steps=60)
        errors = []
        for seed in range(4):
            obs, _ = env.reset(seed=100 + seed)
            state, start = None, np.array([True])
            for _ in range(40):
                action, state = model.policy.predict(obs[None], state, start, deterministic=True)
                errors.append(abs(float(np.clip(action[0, 0], -1, 1)) - float(env.expert_action()[0])))
                obs, _, terminated, truncated, _ = env.step(action[0])
                start = np.array([False])
                if terminated or truncated:
                    break
        return float(np.mean(errors))

    before = disagreement()
    kept: list[Any] = []
    figures = warm_start(model, venv, cfg.warm_start, seed=0, report=lambda _: None, keep=kept.append)
    after = disagreement()
    assert after < 0.5 * before, (before, after)
    assert np.isfinite(figures["warm_start_value_loss"])
    assert kept[0].obs.shape[1] == (clone_chunk_steps or 16)  # steps per cloned chunk
    assert model.sequence_length == 16  # PPO's chunks are left as they were


def test_clone_chunks_of_another_length_refused_with_a_kept_history() -> None:
    """The imitation history holds PPO's chunks, so warm-start chunks of another length cannot join it."""
    with pytest.raises(ConfigError, match=r"warm_start.sequence_length_steps \(32\) must equal"):
        small_config(256, ["warm_start.sequence_length_steps=32", "imitation.epochs=1", "imitation.history_steps=64"])


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["train", "bogus"], "choose one of " + ", ".join(TASK_NAMES)),
        (["train", "lane", "--world", "/nonexistent"], "not a world folder"),
        (["train", "lane"], "`drivesim ingest RECORDING`, `drivesim preprocess` and `drivesim build-world`"),
        (["train", "--resume", "nope"], "no such run folder"),
        (
            ["train", "cutin", "--set", "envs.config.weight_colision=1"],
            "unknown config key 'envs.config.weight_colision'",
        ),
        (["train", "cutin", "--set", "envs.config.dt_s=-1"], "config key 'envs.config.dt_s'"),
        (
            ["eval", "--task", "cutin", "--set", "env.weight_colision=1"],
            "valid keys here: augment, blur_sigma_px, brightness",
        ),
    ],
)
def test_bad_input_is_one_line(tmp_path: Path, args: list[str], message: str) -> None:
    result = subprocess.run(_drivesim(tmp_path / "ws", *args), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert message in result.stderr and "Traceback" not in result.stderr
    assert not (tmp_path / "ws" / "runs").exists() or not list((tmp_path / "ws" / "runs").iterdir())


def test_ctrl_c_keeps_a_resumable_run(tmp_path: Path) -> None:
    """Ctrl-C: exit code 130, one line naming the --resume command, the run left unfinished but resumable."""
    ws = tmp_path / "ws"
    sets = [a for s in SMALL for a in ("--set", s)]
    proc = subprocess.Popen(
        _drivesim(ws, "train", "lane", "--total-steps", "100000", *sets),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=interruptible,
    )
    deadline = time.time() + 60
    while time.time() < deadline and not list(ws.glob("runs/lane-*/progress.csv")):
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    # One line about the interrupt (not an error), after the progress lines a log gets every few seconds.
    lines = [line for line in err.strip().splitlines() if " s elapsed" not in line]
    assert "--resume" in err and "Traceback" not in err and "error" not in err and len(lines) == 1
    run_dir = next(ws.glob("runs/lane-*"))
    assert (run_dir / "checkpoints" / "last.pt").is_file() and not (run_dir / "manifest.json").exists()


def test_best_policy_keeps_the_best_evaluation(tmp_path: Path) -> None:
    """The kept weights are those of the highest success rate (ties: higher return), and survive a resume."""
    best = BestPolicy(tmp_path / "best.pt")
    assert not best.offer({"ep_return_mean": 3.0}, 100, lambda: {"policy": {"w": torch.zeros(1)}})  # no evaluation
    assert best.offer(
        {"eval_success_rate": 0.5, "eval_return_mean": 10.0}, 200, lambda: {"policy": {"w": torch.ones(1)}}
    )
    assert not best.offer(
        {"eval_success_rate": 0.4, "eval_return_mean": 90.0}, 300, lambda: {"policy": {"w": torch.zeros(1)}}
    )
    assert not best.offer(
        {"eval_success_rate": 0.5, "eval_return_mean": 9.0}, 400, lambda: {"policy": {"w": torch.zeros(1)}}
    )
    assert best.offer(
        {"eval_success_rate": 0.5, "eval_return_mean": 11.0}, 500, lambda: {"policy": {"w": torch.full((1,), 2.0)}}
    )
    resumed = BestPolicy.load(tmp_path / "best.pt")
    assert (resumed.success_rate, resumed.return_mean, resumed.steps) == (0.5, 11.0, 500)
    assert float(resumed.weights()["policy"]["w"]) == 2.0
    assert not resumed.offer({"eval_success_rate": 0.3, "eval_return_mean": 50.0}, 600, lambda: {"policy": {}})


def test_a_checkpoint_of_the_run_is_a_policy(finished_run: Path) -> None:
    """`<run>/checkpoints/<name>.pt` loads as the run's policy with that checkpoint's weights (the baselines of the
    learning benchmarks: the warm start alone, the best evaluation), and a missing checkpoint is one line."""
    final = load_policy(finished_run)
    last = load_policy(finished_run / "checkpoints" / "last.pt")
    assert last.run_dir == finished_run and last.task == "lane"
    for name, tensor in final.net.state_dict().items():
        assert torch.equal(tensor, last.net.state_dict()[name]), name  # the run's policy is its last update's
    best = load_policy(finished_run / "checkpoints" / "best.pt")
    saved = torch.load(finished_run / "checkpoints" / "best.pt", weights_only=True)["policy"]
    for name, tensor in saved.items():
        assert torch.equal(tensor, best.net.state_dict()[name]), name
    with pytest.raises(RunError, match="no such checkpoint"):
        load_policy(finished_run / "checkpoints" / "warm_start.pt")  # this run had no warm start


def test_training_counts_episodes_with_any_contact() -> None:
    """An episode whose footprints overlapped at any step is counted as a contact (what evaluation calls a
    collision) even when training's threshold let it go on."""
    from drivesim.stages.train.callbacks import EpisodeTracker, summarize_episodes

    tracker = EpisodeTracker(2)
    touch = {"state": {"overlap_frac": 0.02}, "termination": {"collision": False}}
    clear = {"state": {"overlap_frac": 0.0}, "termination": {"collision": False}}
    tracker.step(np.zeros(2), np.array([False, False]), [touch, clear])
    tracker.step(np.zeros(2), np.array([True, True]), [clear, clear])
    tracker.step(np.zeros(2), np.array([True, False]), [clear, clear])  # env 0's next episode: no contact
    figures = summarize_episodes(tracker.take())
    assert figures["episodes"] == 3 and figures["ep_contact_rate"] == pytest.approx(1 / 3)
