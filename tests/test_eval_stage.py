"""drivesim eval on a fake env with drivesim's info keys: fixed seeds give the same files with 1 or 2 workers, an
interrupted evaluation resumes and loses nothing, bad input is one line with no report, the report renders with its
images in a real headless browser, and the videos hold the episode."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from eval_fakes import FAKE, fake_env_args, fake_world, register_fake_envs

from drivesim.pipeline.workspace import Workspace
from drivesim.stages.evaluate import rollout
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.evaluate.rollout import EnvFactory, PolicySpec, run_episodes
from drivesim.stages.evaluate.stage import run_eval

TESTS_DIR = Path(__file__).parent


def _factory(world: Path) -> EnvFactory:
    register_fake_envs()
    return EnvFactory(
        FAKE["env_id"], {"world": str(world), "mode": "eval"}, entry_point=FAKE["env_entry_point"], trusted=True
    )


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.glob("*.json"))}


def _make_run(folder: Path, task: str) -> Path:
    """A finished run folder as `drivesim train` writes it (small network, random weights)."""
    import torch

    from drivesim.pipeline.hashing import sha256_file
    from drivesim.policy.run_folder import build_net
    from drivesim.stages.train.run_files import write_json, write_policy_files

    arch = {"conv_layers": [[4, 5, 4], [8, 3, 2]], "features_dim": 16, "lstm_hidden_size": 8, "lstm_layers": 1}
    info = {"observation_shape": [3, 64, 160], "architecture": arch}
    torch.manual_seed(0)
    net = build_net(info)
    folder.mkdir(parents=True)
    write_policy_files(folder, task, (3, 64, 160), arch, net.state_dict(), 0.15)
    write_json(folder / "config.json", {"train": {"task": task}, "env_config": {}, "worlds": [], "meshes": None})
    outputs = {"policy.pt": {"sha256": sha256_file(folder / "policy.pt")}}
    write_json(folder / "manifest.json", {"outputs": outputs, "config_hash": "test"})
    return folder


def test_same_seeds_give_the_same_files_with_one_or_two_workers(tmp_path):
    factory = _factory(fake_world(tmp_path / "world"))
    seeds = list(range(10, 22))
    one, two = tmp_path / "one", tmp_path / "two"
    assert run_episodes(factory, PolicySpec("expert"), "overtake", seeds, one, workers=1) == 12
    assert run_episodes(factory, PolicySpec("expert"), "overtake", seeds, two, workers=2) == 12
    files = _files(one)
    assert sorted(files) == sorted(f"{s}.json" for s in seeds)
    assert files == _files(two)
    first = json.loads(files["10.json"])
    assert first["seed"] == 10 and first["steps"] == len(first["trajectory"]["t_s"]) - 1 > 5
    # A second call finds everything on disk and runs nothing.
    assert run_episodes(factory, PolicySpec("expert"), "overtake", seeds, one, workers=2) == 0


def test_a_trained_policy_gives_the_same_files_with_one_or_two_workers(tmp_path):
    factory = _factory(fake_world(tmp_path / "world"))
    spec = PolicySpec("run", str(_make_run(tmp_path / "runs" / "overtake-1", "overtake")))
    seeds = list(range(4))
    run_episodes(factory, spec, "overtake", seeds, tmp_path / "one", workers=1)
    run_episodes(factory, spec, "overtake", seeds, tmp_path / "two", workers=2)
    one, two = _files(tmp_path / "one"), _files(tmp_path / "two")
    assert one == two and len(one) == 4
    actions = np.array(json.loads(one["0.json"])["trajectory"]["action"][1:])
    assert np.all(np.abs(actions) <= 1) and np.ptp(actions) > 0  # the network steers, not a constant


def test_interrupted_evaluation_resumes_and_loses_nothing(tmp_path, monkeypatch):
    world = fake_world(tmp_path / "world")
    cfg = EvalConfig(episodes=12, world=str(world), workers=1, **FAKE)
    calls = {"n": 0}
    original = rollout.RunningRate.add

    def interrupt_after_five(self, done):
        calls["n"] += 1
        if calls["n"] == 6:
            raise KeyboardInterrupt
        return original(self, done)

    ws = Workspace(tmp_path / "ws")
    register_fake_envs()
    monkeypatch.setattr(rollout.RunningRate, "add", interrupt_after_five)
    with pytest.raises(KeyboardInterrupt):
        run_eval(ws, cfg)
    monkeypatch.setattr(rollout.RunningRate, "add", original)
    assert not (ws.root / "eval" / "overtake-expert").exists()  # no half-written report
    partial = ws.root / "eval" / ".partial-overtake-expert" / "episodes"
    assert len(list(partial.glob("*.json"))) == 6  # the sixth finished on disk before the interrupt

    resumed = run_eval(ws, cfg)
    assert resumed.summary.episodes_resumed == 6 and resumed.summary.episodes == 12
    assert not partial.parent.exists()
    fresh = run_eval(Workspace(tmp_path / "ws2"), cfg)
    assert _files(resumed.path / "episodes") == _files(fresh.path / "episodes")
    a = json.loads((resumed.path / "metrics.json").read_text())["aggregate"]
    b = json.loads((fresh.path / "metrics.json").read_text())["aggregate"]
    assert a == b
    # Same config and inputs: fresh, nothing redone; the worker count is not part of the identity.
    assert run_eval(ws, cfg.model_copy(update={"workers": 2})).skipped


def _run_cli(ws: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {"PYTHONPATH": str(TESTS_DIR), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    return subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), "eval", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )


@pytest.mark.parametrize("case", ["missing_run", "unfinished_run", "other_task_run", "short_world", "not_a_world"])
def test_bad_input_is_one_line_and_no_report(tmp_path, case):
    world = fake_world(tmp_path / "world")
    args = fake_env_args(world) + ["--episodes", "3", "--workers", "1"]
    expect = {
        "missing_run": "no such run folder",
        "unfinished_run": "unfinished",
        "other_task_run": "trained on follow, not overtake",
        "short_world": "needs at least 100",
        "not_a_world": "not a world folder",
    }[case]
    if case == "missing_run":
        args += ["--policy", str(tmp_path / "runs" / "nope")]
    elif case == "unfinished_run":
        run = tmp_path / "runs" / "overtake-unfinished"
        run.mkdir(parents=True)
        (run / "config.json").write_text("{}")
        args += ["--policy", str(run)]
    elif case == "other_task_run":
        args += ["--policy", str(_make_run(tmp_path / "runs" / "follow-1", "follow"))]
    elif case == "short_world":
        short = fake_world(tmp_path / "world-too-short", frames=10)
        args = fake_env_args(short) + ["--episodes", "3", "--workers", "1", "--policy", "expert"]
    else:
        empty = tmp_path / "empty"
        empty.mkdir()
        args = fake_env_args(empty) + ["--episodes", "3", "--workers", "1", "--policy", "expert"]
    result = _run_cli(tmp_path / "ws", *args)
    assert result.returncode == 2, result.stdout + result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and expect in lines[0], result.stderr
    if case == "short_world":  # the env's error names the world in front too: the line names it once
        assert lines[0].count(str(short)) == 1, lines[0]
    assert "Traceback" not in result.stderr
    eval_dir = tmp_path / "ws" / "eval"
    assert not eval_dir.exists() or not any(p.name == "report.html" for p in eval_dir.rglob("*"))


def test_onnx_with_wrong_inputs_is_one_line(tmp_path):
    import onnx
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])],
        "wrong",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 4])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 4])],
    )
    path = tmp_path / "wrong.onnx"
    onnx.save(helper.make_model(graph), path)
    result = _run_cli(tmp_path / "ws", *fake_env_args(fake_world(tmp_path / "world")), "--policy", str(path))
    assert result.returncode == 2, result.stdout + result.stderr
    assert len([line for line in result.stderr.splitlines() if line.strip()]) == 1
    assert not (tmp_path / "ws" / "eval" / "overtake-wrong").exists()


@pytest.mark.slow
def test_report_renders_with_its_images_in_headless_chromium(tmp_path):
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        pytest.skip("chromium is not installed (scripts/setup.sh installs it: apt-get install chromium)")
    world = fake_world(tmp_path / "world")
    args = [*fake_env_args(world), "--episodes", "30", "--workers", "2", "--video", "2", "--policy", "expert"]
    result = _run_cli(tmp_path / "ws", *args)
    assert result.returncode == 0, result.stdout + result.stderr
    folder = tmp_path / "ws" / "eval" / "overtake-expert"
    report = (folder / "report.html").read_text()
    assert "0.129" in report and "0.167" in report  # Table I beside ours
    assert 'src="http' not in report and 'href="http' not in report  # self-contained

    # The page reports, after load, how many of its images decoded with a width.
    probe = tmp_path / "probe.html"
    script = (
        "<script>window.addEventListener('load',()=>{const imgs=[...document.images];"
        "const ok=imgs.filter(i=>i.complete&&i.naturalWidth>0).length;"
        "document.body.setAttribute('data-images',ok+'/'+imgs.length);});</script>"
    )
    probe.write_text(report.replace("</body>", script + "</body>"))
    dom = subprocess.run(
        [
            chromium,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            f"--user-data-dir={tmp_path / 'chromium-profile'}",
            "--virtual-time-budget=5000",
            "--dump-dom",
            probe.as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert dom.returncode == 0, dom.stderr[-2000:]
    assert 'data-images="4/4"' in dom.stdout, dom.stdout[:500]

    # metrics.json and episodes.csv agree, and the videos hold the episodes they show.
    import csv

    import cv2

    metrics = json.loads((folder / "metrics.json").read_text())
    with open(folder / "episodes.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == metrics["episodes"] == 30
    rate = np.mean([r["intervention"] == "True" for r in rows])
    assert metrics["aggregate"]["intervention"]["value"] == pytest.approx(rate, abs=1e-5)
    videos = sorted(folder.glob("video_*.mp4"))
    assert len(videos) == 2
    for video in videos:
        seed = int(video.stem.rsplit("_", 1)[1])
        steps = json.loads((folder / "episodes" / f"{seed}.json").read_text())["steps"]
        capture = cv2.VideoCapture(str(video))
        assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == steps + 1
        ok, frame = capture.read()
        assert ok and frame.std() > 5


def test_follow_reports_tracking_error_by_track_position(tmp_path):
    register_fake_envs()
    world = fake_world(tmp_path / "world")
    cfg = EvalConfig(
        task="follow",
        episodes=4,
        world=str(world),
        workers=1,
        env_id="drivesim-test/FakeFollow-v0",
        env_entry_point="eval_fakes:FakeDrivingEnv",
    )
    result = run_eval(Workspace(tmp_path / "ws"), cfg)
    assert result.path.name == "follow-expert"
    metrics = json.loads((result.path / "metrics.json").read_text())
    tracking = metrics["aggregate"]["mean_tracking_error_m"]
    # The fake front car keeps its 1-2 m lateral offset while the expert holds the lane centre.
    assert tracking["n"] == 4 and 0.9 < tracking["value"] < 2.1
    assert (result.path / "tracking.png").stat().st_size > 10_000


def test_resume_into_fewer_episodes_keeps_only_those(tmp_path, monkeypatch):
    register_fake_envs()
    world = fake_world(tmp_path / "world")
    ws = Workspace(tmp_path / "ws")
    original = rollout.RunningRate.add

    def interrupt_at_five(self, done):
        if self.count == 4:
            raise KeyboardInterrupt
        return original(self, done)

    monkeypatch.setattr(rollout.RunningRate, "add", interrupt_at_five)
    with pytest.raises(KeyboardInterrupt):
        run_eval(ws, EvalConfig(episodes=8, world=str(world), workers=1, **FAKE))
    monkeypatch.setattr(rollout.RunningRate, "add", original)
    # The episode count is not part of what an episode is: 3 of the 5 on disk are reused, the others left out.
    result = run_eval(ws, EvalConfig(episodes=3, world=str(world), workers=1, **FAKE))
    assert result.summary.episodes_resumed == 3 and result.summary.episodes_per_min is None
    assert sorted(p.name for p in (result.path / "episodes").glob("*.json")) == ["0.json", "1.json", "2.json"]
    # Another env config is another evaluation: the work folder starts afresh. (force: the finished 3-episode
    # evaluation of the same name was made with other settings, which only --force replaces.)
    with pytest.raises(KeyboardInterrupt):
        monkeypatch.setattr(rollout.RunningRate, "add", interrupt_at_five)
        run_eval(ws, EvalConfig(episodes=8, world=str(world), workers=1, **FAKE), force=True)
    monkeypatch.setattr(rollout.RunningRate, "add", original)
    other_env = {"weight_comfort": 0.5}
    other = run_eval(ws, EvalConfig(episodes=3, world=str(world), workers=1, env=other_env, **FAKE), force=True)
    assert other.summary.episodes_resumed == 0 and any("discarded" in note for note in other.notes)


def test_onnx_policy_gives_the_torch_policy_metrics(tmp_path):
    from drivesim.policy.run_folder import load_policy
    from drivesim.stages.export.onnx_export import export_onnx

    register_fake_envs()
    world = fake_world(tmp_path / "world")
    run = _make_run(tmp_path / "runs" / "overtake-1", "overtake")
    loaded = load_policy(run)
    onnx_path = tmp_path / "policy.onnx"
    meta = {"task": "overtake", "observation_shape": [3, 64, 160], "lstm_layers": 1, "hidden_size": 8, "env_config": {}}
    export_onnx(loaded.export_module(), (3, 64, 160), meta, onnx_path)
    ws = Workspace(tmp_path / "ws")
    by_torch = run_eval(ws, EvalConfig(episodes=4, world=str(world), workers=1, policy=str(run), **FAKE))
    by_onnx = run_eval(ws, EvalConfig(episodes=4, world=str(world), workers=1, policy=str(onnx_path), **FAKE))
    assert by_onnx.path.name == "overtake-policy" and by_torch.path.name == "overtake-1"
    a = json.loads((by_torch.path / "metrics.json").read_text())["aggregate"]
    b = json.loads((by_onnx.path / "metrics.json").read_text())["aggregate"]
    for key in ("intervention", "success", "max_deviation_m", "max_yaw_rad", "min_clearance_no_collision_m"):
        assert b[key]["value"] == pytest.approx(a[key]["value"], abs=1e-4), key
    # An ONNX policy of another task is refused like a run folder.
    result = _run_cli(tmp_path / "ws2", *fake_env_args(world), "--task", "follow", "--policy", str(onnx_path))
    assert result.returncode == 2 and "trained on overtake, not follow" in result.stderr


def test_random_policy_is_a_baseline_that_repeats_its_episodes(tmp_path):
    """`--policy random` steers at random, drawn from each episode's seed: the same files with one or two workers,
    actions spread over [-1, 1], and other seeds other actions."""
    factory = _factory(fake_world(tmp_path / "world"))
    seeds = list(range(6))
    run_episodes(factory, PolicySpec.parse("random"), "overtake", seeds, tmp_path / "one", workers=1)
    run_episodes(factory, PolicySpec.parse("random"), "overtake", seeds, tmp_path / "two", workers=2)
    one, two = _files(tmp_path / "one"), _files(tmp_path / "two")
    assert one == two and len(one) == 6
    first = np.array(json.loads(one["0.json"])["trajectory"]["action"][1:])
    second = np.array(json.loads(one["1.json"])["trajectory"]["action"][1:])
    assert np.all(np.abs(first) <= 1) and np.ptp(first) > 0.5
    assert not np.array_equal(first[: len(second)], second[: len(first)])
    assert PolicySpec.parse("random").label == "random"


def test_straight_policy_never_steers(tmp_path):
    """`--policy straight` (the baseline of a policy that never steers) acts 0 at every step and names itself."""
    factory = _factory(fake_world(tmp_path / "world"))
    run_episodes(factory, PolicySpec.parse("straight"), "overtake", [0, 1], tmp_path / "out", workers=1)
    for text in _files(tmp_path / "out").values():
        actions = np.array(json.loads(text)["trajectory"]["action"][1:])
        assert len(actions) >= 3 and np.all(actions == 0.0)
    assert PolicySpec.parse("straight").label == "straight"
