"""Hardening (issue 22): no orphan, no traceback, nothing lost, nothing silently wrong.

Signals with real processes (an evaluation with two workers killed by SIGTERM, then by SIGKILL, then resumed), a full
disk (a small tmpfs where the machine lets us mount one, else a simulated ENOSPC), bad input and bad settings through
the CLI's one error boundary, a damaged manifest, a re-run that must not replace a result made with other settings,
and a finished training run trained further.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import psutil
import pytest
import torch
from cli_helpers import run_main
from eval_fakes import FAKE, fake_world, register_fake_envs
from test_eval_stage import _make_run
from test_train import small_config

from drivesim.chain.registry import CHAIN
from drivesim.chain.run import RUNNERS
from drivesim.chain.walk import Walk
from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import ArtifactConflictError, DrivesimError, MissingArtifactError
from drivesim.pipeline.status import status_report
from drivesim.pipeline.workspace import Workspace
from drivesim.policy.run_folder import RunError, load_policy
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.evaluate.stage import SPEC as EVAL_SPEC
from drivesim.stages.evaluate.stage import run_eval
from drivesim.stages.train.config import TrainConfig
from drivesim.stages.train.resume import plan_resume, reopen
from drivesim.stages.train.stage import run_training

TESTS_DIR = Path(__file__).parent
SLOW = {"env_id": "drivesim-test/SlowOvertake-v0", "env_entry_point": "hardening_fakes:SlowFakeDrivingEnv"}


# ---------------------------------------------------------------- signals, with real processes


def _eval_command(ws: Path, world: Path, *extra: str) -> list[str]:
    sets = [a for key, value in SLOW.items() for a in ("--set", f"{key}={value}")]
    return [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), "eval", "--world", str(world)] + [
        "--policy",
        "expert",
        *sets,
        "--trust-entry-point",
        *extra,
    ]


def _env() -> dict[str, str]:
    return {"PYTHONPATH": str(TESTS_DIR), "OMP_NUM_THREADS": "1", "PATH": os.environ.get("PATH", "/usr/bin:/bin")}


def _wait_for_episodes(folder: Path, count: int, proc: subprocess.Popen, timeout_s: float = 90) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if len(list(folder.glob("*.json"))) >= count:
            return
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.1)
    raise AssertionError(f"fewer than {count} episodes in {folder} after {timeout_s} s")


def _alive(processes: list[psutil.Process]) -> list[psutil.Process]:
    alive = []
    for p in processes:
        try:
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                alive.append(p)
        except psutil.NoSuchProcess:
            pass
    return alive


def _assert_all_end(processes: list[psutil.Process], timeout_s: float = 10) -> None:
    deadline = time.monotonic() + timeout_s
    while _alive(processes) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _alive(processes), f"still alive after their parent: {_alive(processes)}"


def _listing(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*")}


def test_killed_evaluation_leaves_no_worker_and_resumes(tmp_path: Path) -> None:
    """SIGTERM: one line, exit 143, no temporary folder, no worker left. SIGKILL: the workers die with the parent and
    write nothing after. The same command then finishes the evaluation with every episode."""
    world = fake_world(tmp_path / "world")
    ws = tmp_path / "ws"
    command = _eval_command(ws, world, "--episodes", "8", "--workers", "2")
    episodes = ws / "eval" / ".partial-overtake-expert" / "episodes"

    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    _wait_for_episodes(episodes, 1, proc)
    workers = psutil.Process(proc.pid).children(recursive=True)
    assert len(workers) >= 2
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("eval")]  # progress: "eval"
    assert len(lines) == 1 and lines[0].startswith("terminated (SIGTERM)") and "resumes" in lines[0], err
    assert "Traceback" not in err and "error" not in err
    assert not list(ws.glob(".tmp-*")), "a temporary folder was left"
    _assert_all_end(workers)
    kept = len(list(episodes.glob("*.json")))
    assert 1 <= kept < 8

    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    _wait_for_episodes(episodes, kept + 1, proc)
    workers = psutil.Process(proc.pid).children(recursive=True)
    proc.kill()
    proc.communicate()
    _assert_all_end(workers, timeout_s=5)
    before = _listing(episodes.parent)
    time.sleep(3.0)  # longer than an episode: a live worker would have written one
    assert _listing(episodes.parent) == before, "something was written after the evaluation was killed"

    result = subprocess.run(command, capture_output=True, text=True, env=_env(), timeout=180)
    assert result.returncode == 0, result.stderr
    assert "resumed:" in result.stdout
    final = ws / "eval" / "overtake-expert"
    assert sorted(int(p.stem) for p in (final / "episodes").glob("*.json")) == list(range(8))
    assert not episodes.parent.exists() and not list(ws.glob(".tmp-*"))
    assert json.loads((final / "manifest.json").read_text())["summary"]["episodes"] == 8


def test_terminated_training_stops_its_worker_processes_and_says_how_to_resume(tmp_path: Path) -> None:
    """SIGTERM to `drivesim train` with subprocess envs: exit 143, one line naming --resume (not an error), the env
    worker processes gone, no temporary folder; the header names the run folder before training starts."""
    from test_train import SMALL

    ws = tmp_path / "ws"
    sets = [a for s in [*SMALL, "envs.vec_env=subproc", "eval.every_steps=0"] for a in ("--set", s)]
    command = [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), "train", "lane", *sets]
    out_path, err_path = tmp_path / "out.txt", tmp_path / "err.txt"
    with open(out_path, "w") as out, open(err_path, "w") as err:
        proc = subprocess.Popen([*command, "--total-steps", "100000"], stdout=out, stderr=err, env=_env())
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and not list(ws.glob("runs/lane-*/progress.csv")):
            assert proc.poll() is None, err_path.read_text()
            time.sleep(0.2)
        workers = psutil.Process(proc.pid).children(recursive=True)
        assert len(workers) >= 2
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    run_dir = next(ws.glob("runs/lane-*"))
    assert proc.returncode == 143
    lines = [line for line in err_path.read_text().splitlines() if line.strip() and " s elapsed" not in line]
    assert len(lines) == 1 and lines[0].startswith("terminated (SIGTERM)") and f"--resume {run_dir}" in lines[0]
    assert out_path.read_text().splitlines()[0].startswith(f"training lane to 100000 env steps in {run_dir}")
    _assert_all_end(workers)
    assert not list(ws.glob(".tmp-*")) and (run_dir / "checkpoints" / "last.pt").is_file()


def test_subprocess_envs_close_after_a_step_interrupted_between_two_replies() -> None:
    """Ctrl-C can land after one worker's reply to a step was read and before the next: close() then stops the
    workers within seconds instead of waiting forever for the reply already read."""
    from drivesim.stages.train.envs import EnvSource

    source = EnvSource("lane", cost_free=True, config=TrainConfig().envs.config, worker_threads=1)
    venv = source.make_vec(2, "subproc", seed=0)
    workers = [psutil.Process(p.pid) for p in venv.processes]
    venv.reset()
    venv.step_async(np.zeros((2, *venv.action_space.shape), dtype=np.float32))
    venv.remotes[0].recv()  # the first reply read, as step_wait does before an interrupt
    start = time.monotonic()
    venv.close()
    assert time.monotonic() - start < 15 and venv.closed
    _assert_all_end(workers)


# ---------------------------------------------------------------- the CLI's error boundary, in this process


BAD_SETTINGS = [
    *[
        (["train", "lane", "--set", setting], key)
        for setting, key in [
            ("learner_threads=0", "learner_threads"),
            ("policy.input_pool=0", "policy.input_pool"),
            ("ppo.epochs=0", "ppo.epochs"),
            ("policy.conv_layers=[[16,5,2],[0,3,2]]", "policy.conv_layers"),
            ("policy.features_dim=2000000", "parameters"),
            ("eval.episodes=-5", "eval.episodes"),
            ("time_limit_s=-1", "time_limit_s"),
            ("ppo.gamma=2", "ppo.gamma"),
            ("ppo.buffer_steps=-256", "ppo.buffer_steps"),
            ("ppo.learning_rate=.nan", "finite"),
        ]
    ],
    (["train", "lane", "--total-steps", "0"], "total_steps"),
    (["train", "lane", "--total-steps", "-5"], "total_steps"),
    (["eval", "--workers", "0"], "workers"),
    (["eval", "--episodes", "-5"], "episodes"),
    (["export", "onnx", "--set", "opset=0"], "opset"),
    (["export", "onnx", "--set", "check_steps=-1"], "check_steps"),
]


@pytest.mark.parametrize(("args", "key"), BAD_SETTINGS, ids=[" ".join(a[1:]) for a, _ in BAD_SETTINGS])
def test_bad_settings_are_one_line_and_exit_2(tmp_path, monkeypatch, capsys, args, key) -> None:
    code, err = run_main(tmp_path / "ws", *args, monkeypatch=monkeypatch, capsys=capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error:") and key in lines[0], err
    assert not (tmp_path / "ws").exists()  # nothing created, not even the workspace


def test_bad_config_files_are_one_line(tmp_path, monkeypatch, capsys) -> None:
    duplicate = tmp_path / "dup.yaml"
    duplicate.write_text("episodes: 10\nseed: 1\nepisodes: 20\n")
    binary = tmp_path / "weights.yaml"
    binary.write_bytes(bytes(range(256)))
    for path, expect in ((duplicate, "duplicate key 'episodes'"), (binary, "binary"), (tmp_path, "is a folder")):
        code, err = run_main(
            tmp_path / "ws", "config", "eval", "--config", str(path), monkeypatch=monkeypatch, capsys=capsys
        )
        assert code == 2 and len(err.strip().splitlines()) == 1 and expect in err, err
    run_preset = tmp_path / "run.yaml"
    run_preset.write_text("train:\n  total_steps: 4096\neval:\n  episodes: 5\ntrain:\n  seed: 1\n")
    code, err = run_main(tmp_path / "ws", "run", "--config", str(run_preset), monkeypatch=monkeypatch, capsys=capsys)
    assert code == 2 and "duplicate" in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("error", "expect"),
    [
        (OSError(errno.ENOSPC, "No space left on device"), "disk full"),
        (PermissionError(errno.EACCES, "Permission denied", "/data/ws/world/frames.npy"), "permission denied: "),
    ],
)
def test_os_errors_are_one_clear_line(tmp_path, monkeypatch, capsys, error, expect) -> None:
    import drivesim.cli.status as status_cli

    def fail(*args, **kwargs):
        raise error

    monkeypatch.setattr(status_cli, "status_report", fail)
    code, err = run_main(tmp_path / "ws", "status", monkeypatch=monkeypatch, capsys=capsys)
    lines = err.strip().splitlines()
    assert code == 1 and len(lines) == 1 and expect in lines[0], err
    where = str(tmp_path / "ws") if error.errno == errno.ENOSPC else "/data/ws/world/frames.npy"
    assert where in lines[0]


def _mount_tmpfs(folder: Path, size: str) -> bool:
    """Mount a size-limited tmpfs on `folder` where the machine allows it (root, Linux); False elsewhere."""
    folder.mkdir(parents=True, exist_ok=True)
    if sys.platform != "linux" or os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], capture_output=True)
    return done.returncode == 0


def test_full_disk_names_the_folder_and_keeps_nothing(tmp_path, monkeypatch, capsys) -> None:
    """An evaluation on a 256 KB disk (a real tmpfs where possible, else a simulated ENOSPC): one line naming the
    workspace and the space left, no artifact, no temporary folder."""
    register_fake_envs()
    world = fake_world(tmp_path / "world")
    small = tmp_path / "small"
    mounted = _mount_tmpfs(small, "256k")
    try:
        if not mounted:
            from drivesim.stages.evaluate import rollout

            def full(folder, record):
                raise OSError(errno.ENOSPC, "No space left on device")

            monkeypatch.setattr(rollout, "write_episode", full)
        ws = small / "ws"
        sets = [a for key, value in FAKE.items() for a in ("--set", f"{key}={value}")]
        args = ["eval", "--world", str(world), *sets, "--trust-entry-point", "--episodes", "60", "--workers", "1"]
        args += ["--policy", "expert"]
        code, err = run_main(ws, *args, monkeypatch=monkeypatch, capsys=capsys)
        lines = [line for line in err.strip().splitlines() if not line.startswith("eval")]
        assert code == 1 and len(lines) == 1, err
        assert "disk full" in lines[0] and str(ws) in lines[0] and "are free there now" in lines[0], err
        assert not list(ws.glob(".tmp-*")) and not (ws / "eval" / "overtake-expert").exists()
    finally:
        if mounted:
            subprocess.run(["umount", str(small)], check=False)


# ---------------------------------------------------------------- damaged files


@pytest.mark.parametrize("text", ["{not json", '{"artifact_hash": 5}', "[]", '{"artifact_hash": "x", "outputs": 3}'])
def test_damaged_manifest_is_stale_and_the_next_stage_says_rebuild(tmp_path, text, monkeypatch, capsys) -> None:
    ws = Workspace(tmp_path / "ws")
    (ws.root / "world").mkdir(parents=True)
    (ws.root / "world" / "manifest.json").write_text(text)
    row = next(r for r in status_report(ws, CHAIN)["stages"] if r["artifact"] == "world")
    assert row["state"] == "stale" and "manifest unreadable" in row["reasons"][0]
    with pytest.raises(MissingArtifactError, match="unreadable.*rebuild it with `drivesim build-world`"):
        ws.require("world", "drivesim build-world")
    code, err = run_main(ws.root, "status", monkeypatch=monkeypatch, capsys=capsys)
    assert code == 0 and not err
    code, err = run_main(ws.root, "train", "lane", monkeypatch=monkeypatch, capsys=capsys)
    assert code == 2 and "rebuild it" in err and len(err.strip().splitlines()) == 1


def test_run_folder_describing_a_huge_network_is_refused_before_allocating(tmp_path) -> None:
    run = _make_run(tmp_path / "runs" / "overtake-1", "overtake")
    info = json.loads((run / "policy.json").read_text())
    info["architecture"]["features_dim"] = 20_000_000  # ~85 GB of float32 after the convolutions
    (run / "policy.json").write_text(json.dumps(info))
    with pytest.raises(RunError, match="parameters"):
        load_policy(run)


def test_resume_of_a_refused_checkpoint_is_one_line(tmp_path, monkeypatch, capsys) -> None:
    marker = tmp_path / "pwned"

    class Evil:
        def __reduce__(self):  # noqa: ANN204
            return (os.system, (f"touch {marker}",))

    run = tmp_path / "ws" / "runs" / "lane-1"
    (run / "checkpoints").mkdir(parents=True)
    cfg = small_config(512)
    (run / "config.json").write_text(json.dumps({"train": cfg.model_dump(mode="json"), "worlds": []}))
    torch.save({"num_timesteps": 256, "policy": Evil()}, run / "checkpoints" / "last.pt")
    code, err = run_main(tmp_path / "ws", "train", "--resume", str(run), monkeypatch=monkeypatch, capsys=capsys)
    assert code == 2 and "cannot read the checkpoint" in err and len(err.strip().splitlines()) == 1, err
    assert not marker.exists() and (run / "checkpoints" / "last.pt").is_file()


# ---------------------------------------------------------------- re-runs never destroy a result


def test_rerun_never_replaces_an_evaluation_made_with_other_settings(tmp_path) -> None:
    """`drivesim eval --episodes N` in a chain's workspace, then `drivesim run` again: the chain's evaluation goes
    beside it; `drivesim eval` with other settings refuses naming --force; --force replaces."""
    register_fake_envs()
    world = fake_world(tmp_path / "world")
    run = _make_run(tmp_path / "ws" / "runs" / "overtake-1", "overtake")
    ws = Workspace(tmp_path / "ws")
    users = run_eval(ws, EvalConfig(episodes=6, world=str(world), workers=1, policy=str(run), **FAKE))
    before = (users.path / "metrics.json").read_bytes()

    chain_cfg = EvalConfig(episodes=3, world=str(world), workers=1, **FAKE)
    walk = Walk(ws=ws, recording=tmp_path, hints={}, run_dir=run)
    chained = RUNNERS["eval"](walk, EVAL_SPEC, chain_cfg)
    assert chained.path != users.path and chained.path.name.startswith(users.path.name + "-")
    assert chained.summary.episodes == 3
    assert (users.path / "metrics.json").read_bytes() == before
    assert RUNNERS["eval"](walk, EVAL_SPEC, chain_cfg).skipped  # the next `drivesim run` finds its own, fresh
    walk.force = True  # `drivesim run --force` redoes the chain's evaluation, still beside the user's
    assert RUNNERS["eval"](walk, EVAL_SPEC, chain_cfg).path == chained.path
    assert (users.path / "metrics.json").read_bytes() == before

    other = EvalConfig(episodes=3, world=str(world), workers=1, policy=str(run), **FAKE)
    with pytest.raises(ArtifactConflictError, match=r"episodes: 6, here 3.*--force"):
        run_eval(ws, other)
    assert (users.path / "metrics.json").read_bytes() == before
    assert run_eval(ws, other, force=True).summary.episodes == 3


# ---------------------------------------------------------------- a finished run trained further


def test_finished_run_is_trained_further_with_more_steps(tmp_path) -> None:
    ws = Workspace(tmp_path / "ws")
    first = run_training(ws, small_config(256))
    with pytest.raises(DrivesimError, match="finished at 256 env steps; give --total-steps"):
        plan_resume(ws, first.path, None, None, [], [])
    elsewhere = Workspace(tmp_path / "elsewhere")  # `--resume RUN` from another folder: the run's own workspace
    plan = plan_resume(elsewhere, first.path, None, None, ["total_steps=512"], [])
    assert plan.workspace.root == ws.root and not elsewhere.root.exists()
    assert plan.finished_steps == 256 and plan.cfg.total_steps == 512
    assert plan.cfg.model_dump(exclude={"total_steps"}) == first_config(first.path)
    reopen(plan)
    again = run_training(plan.workspace, plan.cfg, worlds=plan.worlds or None, resume=plan.run_dir)
    assert again.path == first.path and again.summary.steps == 512
    old = json.loads((first.path / "manifest-256-steps.json").read_text())
    assert old["summary"]["steps"] == 256
    steps = [int(line.split(",")[0]) for line in (first.path / "progress.csv").read_text().splitlines()[1:]]
    assert steps == [256, 512]  # the old figures kept, the new ones after them
    assert load_policy(first.path).task == "lane"


def first_config(run_dir: Path) -> dict:
    saved = TrainConfig.model_validate(json.loads((run_dir / "config.json").read_text())["train"])
    return saved.model_dump(exclude={"total_steps"})


# ---------------------------------------------------------------- the stage layer


def test_every_stage_names_how_to_make_what_it_needs() -> None:
    """Each StageSpec carries its own "run X first" hint for each artifact it requires: the upstream stage's command."""
    commands = {spec.artifact: spec.command for spec in CHAIN}
    commands["preprocessed"] = commands.get("preprocessed", "drivesim preprocess")
    for spec in CHAIN:
        for upstream in spec.requires:
            assert spec.upstream_hints.get(upstream) == commands[upstream], (spec.name, upstream)


def test_progress_prints_lines_off_a_terminal(monkeypatch, capsys) -> None:
    from drivesim.pipeline.progress import progress_bar

    monkeypatch.setenv("DRIVESIM_PROGRESS_S", "0.05")
    with progress_bar("work", total=4) as (progress, task):
        for _ in range(4):
            time.sleep(0.06)
            progress.advance(task)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("work: ")]
    assert len(lines) >= 3 and lines[-1].startswith("work: 4/4 (100 %)"), lines


def test_progress_lines_take_the_callers_time_left(monkeypatch, capsys) -> None:
    """A bar whose caller knows better (training stops at its time limit) says the caller's time left, not the one
    the steps so far would give."""
    from drivesim.pipeline.progress import progress_bar

    monkeypatch.setenv("DRIVESIM_PROGRESS_S", "0.05")
    with progress_bar("train", total=1000) as (progress, task):
        progress.update(task, completed=10, left_s=42.0)
        time.sleep(0.12)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.startswith("train: 10/1000")]
    assert lines and all(line.endswith("about 42 s left") for line in lines), lines


def test_config_loader_refuses_duplicate_keys_in_presets_and_files(tmp_path) -> None:
    path = tmp_path / "train.yaml"
    path.write_text("ppo:\n  epochs: 3\n  epochs: 4\n")
    with pytest.raises(DrivesimError, match="duplicate key 'epochs'"):
        load_config(TrainConfig, config_file=path)
