"""Hardening of runs and artifacts: concurrent runs, resumed chains, stale and changed artifacts, SIGHUP.

Two trainings started in the same second each get their own run folder; a second writer of an artifact stops with one
line while the first holds the artifact's lock (two evaluations into one --name); `drivesim run` after an interrupted
training continues that run; a stale world (another recording ingested since) and a world file changed after the build
are refused by their readers with the commands that refresh them, and `status` says so; SIGHUP is handled as SIGTERM.
Fast fakes only: artifacts written with the workspace's own writer, the fake driving envs of the eval tests, the
cost-free training env.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from datetime import datetime
from pathlib import Path

import numpy as np
import psutil
import pytest
from cli_helpers import run_main
from eval_fakes import FAKE, fake_world, register_fake_envs
from test_hardening import _assert_all_end, _env, _eval_command, _wait_for_episodes
from test_train import small_config

from drivesim.chain.registry import CHAIN
from drivesim.pipeline.errors import ArtifactBusyError, StaleArtifactError
from drivesim.pipeline.status import status_report
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.train import run as train_run

TESTS_DIR = Path(__file__).parent
FAKE_SETS = [a for key, value in FAKE.items() for a in ("--set", f"{key}={value}")]


def _error_lines(err: str) -> list[str]:
    return [line for line in err.strip().splitlines() if line.strip() and not line.startswith("eval")]


# ---------------------------------------------------------------- a tiny chain of artifacts


def _recording(tmp_path: Path, name: str, content: bytes) -> Path:
    path = tmp_path / name
    path.write_bytes(content)
    return path


def _write(ws: Workspace, name: str, stage: str, command: str, inputs: dict, payload: bytes) -> None:
    with ws.write_artifact(name, stage, {}, inputs, command=command) as build:
        (build.dir / "frames.bin").write_bytes(payload)


def _write_world(ws: Workspace) -> Path:
    inputs = {"preprocessed": ws.artifact_input("preprocessed")}
    with ws.write_artifact("world", "build-world", {}, inputs, command="drivesim build-world") as build:
        fake_world(build.dir)
        np.save(build.dir / "frames.npy", np.arange(4 * 8 * 8 * 3, dtype=np.uint8).reshape(4, 8, 8, 3))
    return ws.artifact_dir("world")


def _chain_workspace(tmp_path: Path) -> Workspace:
    """trace <- recording, preprocessed <- trace, world <- preprocessed: manifests as the stages write them."""
    ws = Workspace(tmp_path / "ws")
    first = _recording(tmp_path, "drive1.bag", b"the first drive")
    _write(ws, "trace", "ingest", "drivesim ingest PATH", {"recording": ws.external_input(first)}, b"trace of drive 1")
    _write(ws, "preprocessed", "preprocess", "drivesim preprocess", {"trace": ws.artifact_input("trace")}, b"poses 1")
    _write_world(ws)
    return ws


def _rows(ws: Workspace) -> dict[str, dict]:
    return {row["stage"]: row for row in status_report(ws, CHAIN)["stages"]}


# ---------------------------------------------------------------- 3: a stale world is refused


def test_a_stale_world_is_refused_with_the_commands_that_refresh_it(tmp_path, monkeypatch, capsys) -> None:
    """A second recording ingested into a built workspace: status says the world is stale and how to refresh it;
    eval and train refuse it in one line (exit 2) naming `drivesim preprocess`, then `drivesim build-world`; an
    explicit `eval --world PATH` is the user's choice and runs."""
    register_fake_envs()
    ws = _chain_workspace(tmp_path)
    eval_args = ["eval", *FAKE_SETS, "--policy", "expert", "--episodes", "2", "--workers", "1"]
    code, err = run_main(ws.root, *eval_args, "--name", "before", monkeypatch=monkeypatch, capsys=capsys)
    assert code == 0, err
    assert _rows(ws)["build-world"]["state"] == "fresh"

    second = _recording(tmp_path, "drive2.bag", b"the second drive, longer")
    _write(ws, "trace", "ingest", "drivesim ingest PATH", {"recording": ws.external_input(second)}, b"trace 2")

    world = _rows(ws)["build-world"]
    assert world["state"] == "stale", world
    assert world["reasons"][-1] == "refresh: `drivesim preprocess`, then `drivesim build-world`", world
    refresh = "refresh it with `drivesim preprocess`, then `drivesim build-world`"
    for args in ([*eval_args, "--name", "after"], ["train", "lane", "--total-steps", "256"]):
        code, err = run_main(ws.root, *args, monkeypatch=monkeypatch, capsys=capsys)
        lines = _error_lines(err)
        assert code == 2 and len(lines) == 1, err
        assert "the world artifact is stale (input preprocessed is stale (input trace changed))" in lines[0], err
        assert refresh in lines[0] and "Traceback" not in err
    assert not (ws.root / "eval" / "after").exists() and not list((ws.root / "runs").glob("lane-*"))
    with pytest.raises(StaleArtifactError, match="stale"):
        ws.require("world", "drivesim build-world")

    explicit = [*eval_args, "--world", str(ws.artifact_dir("world")), "--name", "explicit"]
    code, err = run_main(ws.root, *explicit, monkeypatch=monkeypatch, capsys=capsys)
    assert code == 0, err
    assert (ws.root / "eval" / "explicit" / "manifest.json").is_file()


# ---------------------------------------------------------------- 7: a changed artifact is found


def test_a_world_file_changed_after_the_build_is_found_by_status_readers_and_the_build(
    tmp_path, monkeypatch, capsys
) -> None:
    """world/frames.npy overwritten with other bytes of the same size: status says stale naming the file and the
    command; eval (the workspace's world, or the folder by path) refuses in one line; build-world's freshness check
    no longer says "nothing to do". A `touch` (same bytes, new time) stays fresh: the hash decides, once."""
    register_fake_envs()
    ws = _chain_workspace(tmp_path)
    frames = ws.artifact_dir("world") / "frames.npy"
    key = ws.read_manifest("world")["key"]
    assert ws.is_fresh("world", key)

    os.utime(frames, ns=(frames.stat().st_atime_ns, frames.stat().st_mtime_ns + 10**9))  # a touch: same bytes
    assert _rows(ws)["build-world"]["state"] == "fresh" and ws.is_fresh("world", key)
    recorded = ws.read_manifest("world")["outputs"]["frames.npy"]["mtime_ns"]
    assert recorded == frames.stat().st_mtime_ns  # hashed once, then known unchanged by its time again

    data = np.load(frames)
    data[0, 0, 0, 0] ^= 0xFF  # one byte changed, same size
    np.save(frames, data)
    world = _rows(ws)["build-world"]
    assert world["state"] == "stale", world
    assert "file frames.npy changed since it was written" in world["reasons"]
    assert world["reasons"][-1] == "refresh: `drivesim build-world`"
    assert not ws.is_fresh("world", key)  # build-world rebuilds it instead of "fresh, nothing to do"

    eval_args = ["eval", *FAKE_SETS, "--policy", "expert", "--episodes", "2", "--workers", "1"]
    for extra in ([], ["--world", str(ws.artifact_dir("world"))]):
        code, err = run_main(ws.root, *eval_args, *extra, monkeypatch=monkeypatch, capsys=capsys)
        lines = _error_lines(err)
        assert code == 2 and len(lines) == 1, err
        assert "frames.npy changed" in lines[0] and "`drivesim build-world`" in lines[0], err
    assert not (ws.root / "eval").exists() or not list((ws.root / "eval").glob("*/manifest.json"))


# ---------------------------------------------------------------- 1: run folders and the artifact lock


def test_runs_started_in_the_same_second_get_folders_of_their_own(tmp_path, monkeypatch) -> None:
    """new_run_dir creates the folder (os.mkdir fails on a taken name): two calls in one second, or eight threads at
    once, never return the same folder."""

    class FrozenClock(datetime):
        @classmethod
        def now(cls, tz=None):  # noqa: ANN206
            return datetime(2026, 1, 2, 3, 4, 5, tzinfo=tz)

    monkeypatch.setattr(train_run, "datetime", FrozenClock)
    first = train_run.new_run_dir(tmp_path, "lane")
    second = train_run.new_run_dir(tmp_path, "lane")
    assert first.name == "lane-20260102-030405" and second.name == "lane-20260102-030405-2"
    assert first.is_dir() and second.is_dir()

    found: list[Path] = []
    barrier = threading.Barrier(8)

    def start() -> None:
        barrier.wait()
        found.append(train_run.new_run_dir(tmp_path, "overtake"))

    threads = [threading.Thread(target=start) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(set(found)) == 8 and all(p.is_dir() for p in found)


_HOLD_LOCK = """
import sys, time
from drivesim.pipeline.workspace import Workspace
with Workspace(sys.argv[1]).lock(sys.argv[2]):
    print("held", flush=True)
    time.sleep(120)
"""


def _hold_lock(ws: Path, name: str) -> subprocess.Popen:
    proc = subprocess.Popen(
        [sys.executable, "-c", _HOLD_LOCK, str(ws), name], stdout=subprocess.PIPE, text=True, env=_env()
    )
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_writer_of_an_artifact_stops_with_one_line_until_the_first_ends(tmp_path, monkeypatch, capsys) -> None:
    """Another process holds the world's lock: build-world's stage (run_stage) stops with ArtifactBusyError naming
    the holder's pid, exit 2, nothing written; once the holder is killed (SIGKILL: no cleanup) the lock is free."""
    ws = _chain_workspace(tmp_path)
    holder = _hold_lock(ws.root, "world")
    try:
        with pytest.raises(ArtifactBusyError, match=f"pid {holder.pid}"), ws.lock("world"):
            pass
        code, err = run_main(ws.root, "build-world", "--force", monkeypatch=monkeypatch, capsys=capsys)
        lines = _error_lines(err)
        assert code == 2 and len(lines) == 1 and "is writing the world artifact" in lines[0], err
        assert not list(ws.root.glob(".tmp-*"))
    finally:
        holder.kill()
        holder.wait()
    with ws.lock("world"), ws.lock("world"):  # free again; re-entrant within a process
        pass


def test_two_evaluations_into_one_name_never_touch_each_others_work(tmp_path) -> None:
    """A second `eval --name N` with other settings while the first runs: one line, exit 2, nothing of the first's
    work folder removed (it used to empty it); the first goes on writing episodes after."""
    world = fake_world(tmp_path / "world")
    ws = tmp_path / "ws"
    common = ["--name", "shared", "--trust-entry-point", "--policy", "expert", "--workers", "1"]
    episodes = ws / "eval" / ".partial-shared" / "episodes"
    first = subprocess.Popen(
        _eval_command(ws, world, "--episodes", "40", *common),  # about 70 s: still running when the second ends
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )
    try:
        _wait_for_episodes(episodes, 1, first)
        kept = {p.name for p in episodes.glob("*.json")}
        second = subprocess.run(
            _eval_command(ws, world, "--episodes", "2", "--seed", "50", *common),
            capture_output=True,
            text=True,
            env=_env(),
            timeout=120,
        )
        lines = _error_lines(second.stderr)
        assert second.returncode == 2 and len(lines) == 1, second.stderr
        assert "is writing the eval/shared artifact" in lines[0] and f"pid {first.pid}" in lines[0], lines[0]
        assert first.poll() is None, "the first evaluation ended before the second was refused"
        assert kept <= {p.name for p in episodes.glob("*.json")}, "the second evaluation removed episodes"
        _wait_for_episodes(episodes, len(kept) + 1, first)  # the first goes on in its work folder
    finally:
        first.send_signal(signal.SIGTERM)
        first.communicate(timeout=60)
    assert first.returncode == 143
    assert not (ws / "eval" / "shared").exists() and kept <= {p.name for p in episodes.glob("*.json")}


# ---------------------------------------------------------------- 12: SIGHUP as SIGTERM


def test_sighup_during_eval_is_handled_as_sigterm(tmp_path) -> None:
    """SIGHUP (the terminal closed): exit 129, one line saying what was kept and that the same command resumes, no
    temporary folder, no worker left, the episodes done kept."""
    world = fake_world(tmp_path / "world")
    ws = tmp_path / "ws"
    command = _eval_command(ws, world, "--episodes", "6", "--workers", "2", "--trust-entry-point", "--policy", "expert")
    episodes = ws / "eval" / ".partial-overtake-expert" / "episodes"
    # A terminal that closes sends SIGHUP to a process that has it at its default: reset it in the child, so that a
    # test session started under nohup (SIGHUP ignored, inherited) tests the same thing.
    proc = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        preexec_fn=lambda: signal.signal(signal.SIGHUP, signal.SIG_DFL),
    )
    _wait_for_episodes(episodes, 1, proc)
    workers = psutil.Process(proc.pid).children(recursive=True)
    proc.send_signal(signal.SIGHUP)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 129, err
    lines = _error_lines(err)
    assert len(lines) == 1 and lines[0].startswith("terminated (SIGHUP)") and "resumes" in lines[0], err
    assert "Traceback" not in err and "error" not in err
    assert not list(ws.glob(".tmp-*")) and not list((ws / "eval").glob(".tmp-*"))
    _assert_all_end(workers)
    assert 1 <= len(list(episodes.glob("*.json"))) < 6


# ---------------------------------------------------------------- 2: `drivesim run` continues an interrupted training


def _interrupted_run(ws: Workspace, steps_done: int, total_steps: int) -> Path:
    """An unfinished run at `steps_done` of `total_steps` env steps: a finished short run whose manifest is gone and
    whose saved config asks for more steps (what Ctrl-C during a longer run leaves)."""
    import json

    done = train_run_training(ws, small_config(steps_done))
    run_dir = done.path
    (run_dir / "manifest.json").unlink()
    saved = json.loads((run_dir / "config.json").read_text())
    saved["train"]["total_steps"] = total_steps
    (run_dir / "config.json").write_text(json.dumps(saved))
    return run_dir


def train_run_training(ws: Workspace, cfg):  # noqa: ANN001, ANN201
    from drivesim.stages.train.stage import run_training

    return run_training(ws, cfg)


def test_the_chain_continues_an_interrupted_training_of_the_same_config(tmp_path) -> None:
    """`drivesim run` after Ctrl-C in training: the unfinished run of the same config is continued from its last
    checkpoint (no second run beside it); while another command trains it, one line instead of a twin run; a
    different config starts a run of its own and leaves it alone."""
    from drivesim.chain.run import RUNNERS
    from drivesim.chain.walk import Walk
    from drivesim.stages.train.stage import SPEC

    ws = Workspace(tmp_path / "ws")
    run_dir = _interrupted_run(ws, 256, 512)
    walk = Walk(ws=ws, recording=tmp_path, hints={})
    result = RUNNERS["train"](walk, SPEC, small_config(512))
    assert result.path == run_dir and not result.skipped
    assert [p.name for p in (ws.root / "runs").iterdir()] == [run_dir.name]
    steps = [int(line.split(",")[0]) for line in (run_dir / "progress.csv").read_text().splitlines()[1:]]
    assert steps == [256, 512]  # continued from the checkpoint at 256, not from step 0
    assert ws.read_manifest(f"runs/{run_dir.name}")["summary"]["steps"] == 512

    other = _interrupted_run(ws, 256, 768)
    holder = _hold_lock(ws.root, f"runs/{other.name}")  # another command is training it now: one line, no twin run
    try:
        with pytest.raises(ArtifactBusyError, match=f"pid {holder.pid}.*runs/{other.name}"):
            RUNNERS["train"](walk, SPEC, small_config(768))
    finally:
        holder.kill()
        holder.wait()
    seeded = RUNNERS["train"](walk, SPEC, small_config(256, ["seed=7"]))
    assert seeded.path not in (run_dir, other) and seeded.summary.steps == 256
    assert not (other / "manifest.json").exists()  # another config's run is not taken over
    assert len(list((ws.root / "runs").iterdir())) == 3
