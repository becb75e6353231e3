"""The paper cuts a new user hit, each as the user types it: the command in a subprocess, its output read from a pipe
(as in a log file), never a terminal."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TESTS_DIR = Path(__file__).parent


def _no_window(environ: os._Environ[str]) -> dict[str, str]:
    """The environment without a terminal size (COLUMNS, LINES), as in a cron job or a CI log."""
    return {k: v for k, v in environ.items() if k not in ("COLUMNS", "LINES")}


def drivesim(
    ws: Path, *args: str, env: dict[str, str] | None = None, timeout_s: float = 120
) -> subprocess.CompletedProcess[str]:
    """`drivesim --workspace ws ARGS...` in a subprocess, stdout and stderr read from pipes (not a terminal)."""
    return subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env={**_no_window(os.environ), "PYTHONPATH": str(TESTS_DIR), "OMP_NUM_THREADS": "1", **(env or {})},
    )


def make_dry_run(target: str, venv: Path) -> list[str]:
    """The commands `make TARGET` would run with the venv at `venv` (absent, so its set-up is due)."""
    # Run as a top-level make even under `make test`: no inherited MAKEFLAGS/MAKELEVEL, no directory lines.
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}
    done = subprocess.run(
        ["make", "-n", "--no-print-directory", target, f"VENV={venv}"],
        cwd=REPO, capture_output=True, text=True, timeout=30, check=True, env=env,
    )  # fmt: skip
    return [line for line in done.stdout.splitlines() if line.strip()]


# ---------------------------------------------------------------- 1. a set-up-only command


def test_make_install_sets_up_and_runs_nothing_else(tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    setup = [f"VENV={venv} bash scripts/setup.sh", f"touch {venv}/.drivesim-installed"]
    assert make_dry_run("install", venv) == setup
    # demo and test still set up first, then do their work.
    assert make_dry_run("demo", venv)[:2] == setup and "run --preset demo" in make_dry_run("demo", venv)[2]
    assert make_dry_run("test", venv) == [*setup, f"{venv}/bin/python -m pytest -q"]


# ---------------------------------------------------------------- 2. `drivesim run` takes ingest's flags


def _image_folder(folder: Path, count: int) -> Path:
    import cv2
    import numpy as np

    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(count):
        cv2.imwrite(str(folder / f"{i:04d}.png"), rng.integers(0, 255, (48, 64, 3), dtype=np.uint8))
    return folder


def test_run_reads_an_image_folder_with_fps_and_the_trimming_flags(tmp_path: Path) -> None:
    """12 images at --fps 10 cut at --end-s 0.5 are 6 frames: too few for SfM, refused in one line that shows both
    flags reached the ingest (without --fps the folder would be refused for lacking a frame rate)."""
    images = _image_folder(tmp_path / "images", 12)
    done = drivesim(tmp_path / "ws", "run", str(images), "--fps", "10", "--end-s", "0.5")
    assert done.returncode == 2, done.stderr
    assert "too short: 6 frame(s)" in done.stderr and "--fps" not in done.stderr, done.stderr
    assert not (tmp_path / "ws" / "trace").exists()


def test_run_help_lists_every_ingest_flag(tmp_path: Path) -> None:
    run_help = drivesim(tmp_path / "ws", "run", "--help", env={"COLUMNS": "200"}).stdout
    ingest_help = drivesim(tmp_path / "ws", "ingest", "--help", env={"COLUMNS": "200"}).stdout
    ingest_flags = set(re.findall(r"(--[a-z][a-z0-9-]+)", ingest_help)) - {"--help", "--set", "--config", "--force"}
    assert ingest_flags and ingest_flags <= set(re.findall(r"(--[a-z][a-z0-9-]+)", run_help))


def test_a_folder_that_is_no_recording_lists_every_kind_drivesim_reads(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    done = drivesim(tmp_path / "ws", "ingest", str(tmp_path / "empty"))
    assert done.returncode == 2
    line = done.stderr.strip()
    assert "\n" not in line
    for kind in (
        "ROS1 .bag",
        ".mcap",
        "rosbag2 folder",
        "KITTI raw",
        "KITTI odometry",
        ".mp4",
        "images only (with --fps)",
    ):
        assert kind in line, (kind, line)


# ---------------------------------------------------------------- 3. eval with no trained policy


def test_eval_without_a_trained_run_refuses_instead_of_evaluating_the_expert(tmp_path: Path) -> None:
    from eval_fakes import fake_env_args, fake_world

    ws = tmp_path / "ws"
    world = fake_world(tmp_path / "my-drive" / "world")
    fake_env = fake_env_args(world)
    done = drivesim(ws, "eval", "--episodes", "3", "--workers", "1", *fake_env)
    assert done.returncode == 2, done.stdout + done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "drivesim train overtake" in lines[0] and "--policy" in lines[0], done.stderr
    assert "expert" in lines[0] and not (ws / "eval").exists() and done.stdout == ""
    # Named, the expert is evaluated.
    done = drivesim(ws, "eval", "--episodes", "3", "--workers", "1", "--policy", "expert", *fake_env)
    assert done.returncode == 0, done.stdout + done.stderr
    assert (ws / "eval" / "overtake-expert" / "metrics.json").is_file()


# ---------------------------------------------------------------- 5. labels, empty lines, messages


def test_episodes_0_says_episodes_must_be_at_least_1(tmp_path: Path) -> None:
    done = drivesim(tmp_path / "ws", "eval", "--episodes", "0", "--policy", "expert")
    assert done.returncode == 2
    assert done.stderr.strip() == "error: --episodes 0: episodes must be >= 1", done.stderr


def test_an_empty_workspace_names_every_step_to_a_world(tmp_path: Path) -> None:
    for args in (["train", "overtake"], ["eval", "--policy", "expert"]):
        done = drivesim(tmp_path / "ws", *args)
        assert done.returncode == 2, done.stdout + done.stderr
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and "no world artifact" in lines[0], done.stderr
        for step in (
            "drivesim run RECORDING",
            "drivesim ingest RECORDING",
            "drivesim preprocess",
            "drivesim build-world",
        ):
            assert step in lines[0], (step, lines[0])


# ---------------------------------------------------------------- 4 and 5. piped tables, world labels, status


def _ingested_workspace(ws: Path, recording_name: str) -> Path:
    """A user's workspace after `drivesim ingest <recording_name>.mcap` (run in-process: the commands under test
    are the later ones), with a (fake) world beside its trace."""
    from eval_fakes import fake_world
    from recordings import drive_messages, write_recording

    from drivesim.pipeline.config import load_config
    from drivesim.pipeline.workspace import Workspace
    from drivesim.stages.ingest.config import IngestConfig
    from drivesim.stages.ingest.stage import run_ingest

    ws.parent.mkdir(parents=True, exist_ok=True)
    rec = write_recording(ws.parent / f"{recording_name}.mcap", "mcap", drive_messages(n_frames=5))
    run_ingest(Workspace(ws), rec, load_config(IngestConfig, preset="ingest"))
    fake_world(ws / "world")
    return ws


def test_piped_eval_table_is_whole_and_labels_worlds_by_their_recording(tmp_path: Path) -> None:
    from eval_fakes import FAKE

    a = _ingested_workspace(tmp_path / "a" / "my-work", "drive_0005")
    b = _ingested_workspace(tmp_path / "b" / "my-work", "drive_0009")
    args = ["--world", str(a / "world"), "--world", str(b / "world"), "--episodes", "2", "--workers", "1"]
    args += ["--policy", "expert", "--set", f"env_id={FAKE['env_id']}", "--trust-entry-point"]
    done = drivesim(tmp_path / "ws", "eval", *args, "--set", f"env_entry_point={FAKE['env_entry_point']}")
    assert done.returncode == 0, done.stdout + done.stderr
    assert "…" not in done.stdout, done.stdout
    header = next(line for line in done.stdout.splitlines() if "world" in line and "episodes" in line and "┃" in line)
    for heading in ("intervention", "collision", "off lane", "min clearance (m, all episodes)"):
        assert heading in header, (heading, header)
    rows = [line.split("│")[1].strip() for line in done.stdout.splitlines() if line.startswith("│")]
    assert rows[:2] == ["drive_0005", "drive_0009"], rows
    assert "my-work" not in done.stdout, done.stdout
    assert {p.name for p in (tmp_path / "ws" / "eval" / "overtake-expert" / "worlds").iterdir()} == {
        "drive_0005",
        "drive_0009",
    }


def test_every_command_prints_through_the_one_console_that_knows_it_is_piped() -> None:
    """Every table of every command (status, config, eval, bench, synth, the run's result) goes through
    `cli.common.console`, the one that keeps full width when piped: no command makes a Console of its own."""
    others = [p.name for p in sorted((REPO / "cli").glob("*.py")) if "Console(" in p.read_text()]
    assert others == ["common.py"], others


def test_piped_status_prints_no_empty_field(tmp_path: Path) -> None:
    ws = _ingested_workspace(tmp_path / "my-work", "drive")
    done = drivesim(ws, "status")
    assert done.returncode == 0, done.stderr
    trace_row = next(line for line in done.stdout.splitlines() if line.lstrip("│ ").startswith("ingest"))
    assert "frame_count=5" in trace_row and "tf_static (1) │" in trace_row, done.stdout  # the whole summary, one line
    # The ingest skipped no message: no "skipped:" with nothing after it (checked across folded lines too).
    assert "skipped" not in re.sub(r"[\s│]", "", done.stdout), done.stdout


# ---------------------------------------------------------------- 6. no pointer to a tool that is not installed


def test_the_report_points_to_a_topic_lister_that_is_installed_and_works(tmp_path: Path) -> None:
    import html
    import shlex

    from eval_fakes import FAKE, fake_world

    world = fake_world(tmp_path / "world")
    args = ["--world", str(world), "--episodes", "4", "--workers", "1", "--policy", "expert", "--record", "all"]
    args += ["--set", f"env_id={FAKE['env_id']}", "--set", f"env_entry_point={FAKE['env_entry_point']}"]
    done = drivesim(tmp_path / "ws", "eval", *args, "--trust-entry-point")
    assert done.returncode == 0, done.stdout + done.stderr
    folder = tmp_path / "ws" / "eval" / "overtake-expert"
    report = (folder / "report.html").read_text()
    assert "mcap info" not in report and "mcap cat" not in report
    for doc in (REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))):
        assert not re.search(r"`mcap (info|cat|list|doctor)", doc.read_text()), doc  # the mcap CLI is not installed
    # The command the report gives, as a user pastes it (with the venv's python), lists the episode's topics.
    snippet = html.unescape(re.search(r"<code>(python -c .*?)</code>", report).group(1))
    recording = sorted((folder / "recordings").glob("*.mcap"))[0]
    argv = shlex.split(snippet.replace("FILE.mcap", shlex.quote(str(recording))))
    listed = subprocess.run([sys.executable, *argv[1:]], capture_output=True, text=True, timeout=60, check=True)
    assert {"/camera/image", "/ego/step", "/log"} <= set(listed.stdout.split()), listed.stdout


# ---------------------------------------------------------------- 7. time figures that hold


VAGUE_TIME = re.compile(r"\b(about|around|roughly|~)\s*[0-9.]+\s*(s|sec|seconds|min|minutes|h|hours)\b", re.IGNORECASE)
MINUTES = re.compile(r"\b[0-9.]+\s*(min|minutes)\b")


def _help_and_config_files() -> list[Path]:
    return [
        REPO / "Makefile",
        *sorted((REPO / "scripts").glob("*.sh")),
        *sorted((REPO / "cli").glob("*.py")),
        *sorted((REPO / "configs").rglob("*.yaml")),
    ]


def test_time_figures_in_help_and_config_are_measurements_with_their_machine() -> None:
    """No "about N min" promise; a duration in minutes is a limit the config enforces ("at most") or a measured
    figure that says on which machine and whether it was quiet or shared."""
    for path in _help_and_config_files():
        text = path.read_text()
        vague = VAGUE_TIME.search(text)
        assert vague is None, f"{path.relative_to(REPO)}: {vague.group(0)!r}"
        for figure in MINUTES.finditer(text):
            if "at most" in text[max(0, figure.start() - 12) : figure.start()]:
                continue
            said = text[figure.start() : figure.start() + 200]
            assert ("quiet" in said or "shared" in said) and "core" in said, f"{path.relative_to(REPO)}: {said[:80]!r}"


def test_run_help_gives_the_demo_time_its_benchmark_measured(tmp_path: Path) -> None:
    run_help = re.sub(r"[\s│]+", " ", drivesim(tmp_path / "ws", "run", "--help").stdout)
    measured_min = json.loads((REPO / "benchmarks" / "results" / "demo.json").read_text())["total_s"] / 60
    assert f"demo ({measured_min:.1f} min on a quiet 2-core VM)" in run_help, run_help  # the figure of demo.json
