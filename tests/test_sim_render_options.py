"""`drivesim sim render` options: frames at the recording's size by default (--size to change it), a trained policy
driving (--policy RUN or FILE.onnx) while the video shows the whole image, and bad values as one line."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from sim_worlds import HEIGHT_PX, WIDTH_PX, write_test_world

TESTS_DIR = Path(__file__).parent


def _world(tmp_path: Path, source_size: tuple[int, int] | None) -> Path:
    """An 80 m test world whose camera.json names the recording's size `source_size` (None: it names none)."""
    world = write_test_world(tmp_path / "world", length_m=80.0)
    camera_path = world / "camera.json"
    camera = json.loads(camera_path.read_text())
    camera.pop("source_width_px", None), camera.pop("source_height_px", None)
    if source_size is not None:
        camera["source_width_px"], camera["source_height_px"] = source_size
    camera_path.write_text(json.dumps(camera))
    return world


def _frames(path: Path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            return frames
        frames.append(frame)


def _cli(tmp_path: Path, *args: str):
    from typer.testing import CliRunner

    from drivesim.cli.main import app

    return CliRunner().invoke(app, ["--workspace", str(tmp_path / "ws"), "sim", "render", *args])


def _make_run(folder: Path, task: str) -> Path:
    """A finished run folder as `drivesim train` writes it: a small network with random weights."""
    import torch

    from drivesim.pipeline.hashing import sha256_file
    from drivesim.policy.run_folder import build_net
    from drivesim.stages.train.run_files import write_json, write_policy_files

    arch = {"conv_layers": [[4, 5, 4], [8, 3, 2]], "features_dim": 16, "lstm_hidden_size": 8, "lstm_layers": 1}
    torch.manual_seed(0)
    net = build_net({"observation_shape": [3, 64, 160], "architecture": arch})
    folder.mkdir(parents=True)
    write_policy_files(folder, task, (3, 64, 160), arch, net.state_dict(), 0.15)
    write_json(folder / "config.json", {"train": {"task": task}, "env_config": {}, "worlds": [], "meshes": None})
    write_json(folder / "manifest.json", {"outputs": {"policy.pt": {"sha256": sha256_file(folder / "policy.pt")}}})
    return folder


@pytest.mark.parametrize(
    ("source_size", "size", "expected"),
    [
        ((160, 100), None, (160, 100)),
        (None, None, (WIDTH_PX, HEIGHT_PX)),
        ((160, 100), "96x60", (96, 60)),
        ((161, 99), None, (161, 99)),
    ],
)
def test_frames_are_at_the_recordings_size_unless_asked(tmp_path, source_size, size, expected):
    world = _world(tmp_path, source_size)
    out = tmp_path / "out"
    done = _cli(tmp_path, "--world", str(world), "--out", str(out), "--seed", "2", *(["--size", size] if size else []))
    assert done.exit_code == 0, done.output
    frames = _frames(out / "episode.mp4")
    summary = json.loads((out / "summary.json").read_text())
    assert len(frames) == summary["steps"] + 1 > 5
    # an odd size is padded by one copied row or column in the MP4 (its codec takes even sizes), never cut
    assert {f.shape for f in frames} == {(expected[1] + expected[1] % 2, expected[0] + expected[0] % 2, 3)}
    assert tuple(summary["size_px"]) == expected
    assert cv2.imread(str(out / "strip.png")).shape[0] == expected[1]
    assert f"at {expected[0]}x{expected[1]}" in done.output


def test_at_the_worlds_size_the_frames_are_the_full_view_of_the_env(tmp_path):
    """--size equal to the world's: the frames are the env's own full-image observations, pixel for pixel (compared
    on the lossless strip)."""
    from drivesim.sim.envs.registry import task_spec
    from drivesim.sim.envs.render_episode import _drive, _write_strip, render_episode
    from drivesim.sim.world import World

    world = _world(tmp_path, (160, 100))
    w = World.load(world)
    config = {"roi_px": (0, 0, w.width_px, w.height_px)}
    config |= {"observation_width_px": w.width_px, "observation_height_px": w.height_px}
    env = task_spec("overtake").env_class()(world=w, meshes=None, mode="eval", config=config)
    frames, states, _ = _drive(env, 2, None, None, None)
    _write_strip(frames, states, tmp_path / "expected.png")
    summary = render_episode("overtake", world, None, tmp_path / "out", 2, size_px=(WIDTH_PX, HEIGHT_PX))
    assert summary["steps"] + 1 == len(frames)
    np.testing.assert_array_equal(
        cv2.imread(str(tmp_path / "out" / "strip.png")), cv2.imread(str(tmp_path / "expected.png"))
    )


def test_a_policy_drives_on_its_own_observation_while_the_video_shows_the_whole_image(tmp_path):
    from drivesim.sim.envs.render_episode import render_episode

    class SteersLeft:
        """Steers left at half the limit and keeps what it was shown."""

        def __init__(self) -> None:
            self.seen: list[tuple[int, ...]] = []

        def initial_state(self, n: int) -> None:
            return None

        def predict(self, obs, state, episode_start, deterministic=True):
            self.seen.append(obs.shape)
            return np.full((len(obs), 1), 0.5, np.float32), state

    world = _world(tmp_path, (160, 100))
    policy = SteersLeft()
    by_policy = render_episode("overtake", world, None, tmp_path / "policy", 2, policy=policy)
    by_expert = render_episode("overtake", world, None, tmp_path / "expert", 2)
    assert set(policy.seen) == {(1, 3, 64, 160)}  # the task's own observation, not the video's frames
    assert len(policy.seen) == by_policy["steps"]
    assert {f.shape for f in _frames(tmp_path / "policy" / "episode.mp4")} == {(100, 160, 3)}
    assert by_policy["outcome"] != by_expert["outcome"] or by_policy["steps"] != by_expert["steps"]


def test_a_trained_run_drives_from_the_cli(tmp_path):
    world = _world(tmp_path, (160, 100))
    run = _make_run(tmp_path / "runs" / "overtake-1", "overtake")
    out = tmp_path / "out"
    done = _cli(tmp_path, "--world", str(world), "--out", str(out), "--seed", "2", "--policy", str(run))
    assert done.exit_code == 0, done.output
    assert len(_frames(out / "episode.mp4")) == json.loads((out / "summary.json").read_text())["steps"] + 1


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--size", "640"], "--size '640': give WIDTHxHEIGHT"),
        (["--size", "8x8"], "each 16 to 8192"),
        (["--policy", "RUN"], "no such run folder"),
        (["--policy", "RUN_OTHER_TASK"], "trained on follow, not overtake"),
    ],
)
def test_bad_options_are_one_line_and_write_nothing(tmp_path, args, message):
    world = _world(tmp_path, (160, 100))
    args = [str(tmp_path / "missing-run") if a == "RUN" else a for a in args]
    if "RUN_OTHER_TASK" in args:
        args[args.index("RUN_OTHER_TASK")] = str(_make_run(tmp_path / "runs" / "follow-1", "follow"))
    out = tmp_path / "out"
    done = subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(tmp_path / "ws"), "sim", "render"]
        + ["--world", str(world), "--out", str(out), *args],
        capture_output=True,
        text=True,
        timeout=120,
        env={"PYTHONPATH": str(TESTS_DIR), "OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"},
    )
    assert done.returncode == 2, done.stderr
    assert message in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert "Traceback" not in done.stderr and not out.exists()
