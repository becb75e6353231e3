"""`drivesim run a.mcap --recordings-file list.txt` on two tiny synthetic recordings with the real stages, simulator
and PPO: each recording made into a world of its own (the first in the workspace, the second in drives/b/), one run
trained on both, the evaluation's row per recording and pooled row, then the same command with every stage fresh;
`drivesim eval` afterwards evaluates in the same worlds; bad input is one line, exit 2, nothing written."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from cli_helpers import run_main

from drivesim.chain.recordings import read_list_file, recording_name, set_worlds
from drivesim.pipeline.workspace import Workspace

# Lane keeping on 3-s drives (30 frames, about 32 m of road): a short minimum path so that episodes fit, a few dozen
# PPO steps, two evaluation episodes per world.
TINY = {
    "preprocess": {"depth": {"method": "plane"}},
    "build-world": {"sim_width_px": 80},
    "train": {
        "task": "lane",
        "total_steps": 64,
        "towns": [],
        "envs": {"count": 2, "config": {"episode_steps": 20, "min_path_length_m": 10.0, "end_margin_m": 2.0}},
        "ppo": {"buffer_steps": 64, "minibatch_steps": 32, "epochs": 1},
        "warm_start": {"method": "none"},
        "imitation": {"epochs": 0},
        "eval": {"every_steps": 0},
    },
    "eval": {"task": "lane", "episodes": 2, "baseline_episodes": 0, "workers": 1, "record": "none"},
    "export": {"latency_steps": 5},
}


def _synth(path: Path, seed: int) -> Path:
    from drivesim.stages.synth.config import SynthConfig
    from drivesim.stages.synth.synthesize import resolve_config, synthesize

    cfg = SynthConfig.model_validate(
        {
            "seed": seed,
            "drive": {"duration_s": 3.0},
            "camera": {"width_px": 160, "height_px": 100},
            "world": {"scenery": {"view_distance_m": 60}},
        }
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    synthesize(resolve_config(cfg), path)
    return path


def _drivesim(ws: Path, *args: str) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return done


@pytest.fixture(scope="module")
def several(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str, str]:
    """A workspace after `drivesim run a.mcap --recordings-file drives.txt` (b.mcap listed there), then the same
    command again; the workspace and the two outputs."""
    root = tmp_path_factory.mktemp("several")
    _synth(root / "a.mcap", seed=4)
    _synth(root / "more" / "b.mcap", seed=5)
    listing = root / "drives.txt"
    listing.write_text("# the second drive, relative to this file\n\nmore/b.mcap\n")
    tiny = root / "tiny.yaml"
    tiny.write_text(yaml.safe_dump(TINY))
    ws = root / "ws"
    args = ["run", str(root / "a.mcap"), "--recordings-file", str(listing), "--config", str(tiny)]
    first = _drivesim(ws, *args).stdout
    again = _drivesim(ws, *args).stdout
    return ws, first, again


@pytest.mark.slow
def test_each_recording_is_made_into_its_own_world(several) -> None:
    ws, first, _ = several
    for name in ("a", "b"):
        for stage in ("ingest", "preprocess", "build-world"):
            assert f"{name}: {stage}: done" in first, first
    # The first recording's world is the workspace's, as with one recording; the second's is in drives/b/.
    for world in (ws / "world", ws / "drives" / "b" / "world"):
        assert (world / "manifest.json").is_file() and (world / "path.npz").is_file()
    sources = json.loads((ws / "drives" / "b" / "trace" / "sources.json").read_text())
    assert Path(sources["recording"]).name == "b.mcap"
    assert not (ws / "drives" / "a").exists()


@pytest.mark.slow
def test_one_run_trains_on_both_worlds_and_eval_reports_each_and_pooled(several) -> None:
    ws, first, _ = several
    (run_dir,) = (ws / "runs").iterdir()
    config = json.loads((run_dir / "config.json").read_text())
    worlds = [(ws / "world").resolve(), (ws / "drives" / "b" / "world").resolve()]
    assert [Path(w).resolve() for w in config["worlds"]] == worlds
    summary = json.loads((run_dir / "manifest.json").read_text())["summary"]
    assert len(summary["worlds"]) == 2 and summary["steps"] >= 64

    (eval_dir,) = (ws / "eval").iterdir()
    metrics = json.loads((eval_dir / "metrics.json").read_text())
    rows = {row["world"]: row for row in metrics["per_world"]}
    assert list(rows) == ["a", "b"]
    assert all(row["group"] == "train" and row["episodes"] == 2 for row in rows.values())
    assert metrics["pooled"]["episodes"] == 4 and metrics["groups"]["train"]["episodes"] == 4
    for figures in (*rows.values(), metrics["pooled"]):
        assert 0.0 <= figures["success"]["value"] <= 1.0
    assert all((eval_dir / "worlds" / name / "report.html").is_file() for name in ("a", "b"))
    # The end-of-run summary: a row per recording, the pooled row, the report and the policy.
    lines = [line for line in first.splitlines() if line.count("│") > 5]
    named = {line.split("│")[1].strip() for line in lines}
    assert {"a", "b", "all worlds, pooled"} <= named, first
    assert f"report: {eval_dir / 'report.html'}" in first and f"policy: {ws / 'export' / 'policy.onnx'}" in first


@pytest.mark.slow
def test_the_same_command_again_skips_every_stage(several) -> None:
    ws, _, again = several
    for stage in ("a: ingest", "a: build-world", "b: ingest", "b: preprocess", "b: build-world", "train", "eval"):
        assert f"{stage}: fresh, skipped" in again, again
    assert len(list((ws / "runs").iterdir())) == 1 and len(list((ws / "eval").iterdir())) == 1


@pytest.mark.slow
def test_a_later_eval_or_train_defaults_to_every_recordings_world(several, tmp_path: Path, monkeypatch) -> None:
    from typer.testing import CliRunner

    from drivesim.cli.main import app
    from drivesim.stages.evaluate import stage as eval_stage
    from drivesim.stages.train import stage as train_stage

    ws, _, _ = several
    assert set_worlds(Workspace(ws)) == [ws / "world", ws / "drives" / "b" / "world"]
    seen: dict[str, object] = {}

    def fake_run_eval(ws_, cfg, **kwargs):
        seen["world"] = cfg.world
        raise SystemExit(0)

    monkeypatch.setattr(eval_stage, "run_eval", fake_run_eval)
    CliRunner().invoke(app, ["--workspace", str(ws), "eval", "--task", "lane", "--episodes", "2"])
    assert seen["world"] == [str(ws / "world"), str(ws / "drives" / "b" / "world")]
    CliRunner().invoke(app, ["--workspace", str(ws), "eval", "--task", "lane", "--world", str(ws / "world")])
    assert seen["world"] == [str(ws / "world")]  # --world still chooses

    def fake_run_training(ws_, cfg, worlds=None, **kwargs):
        seen["train"] = worlds
        raise SystemExit(0)

    monkeypatch.setattr(train_stage, "run_training", fake_run_training)
    CliRunner().invoke(app, ["--workspace", str(ws), "train", "lane"])
    assert seen["train"] == [ws / "world", ws / "drives" / "b" / "world"]


def _files(root: Path, *names: str, content: bytes = b"") -> list[Path]:
    paths = []
    for i, name in enumerate(names):
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(content or f"recording {i}".encode())
        paths.append(path)
    return paths


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("missing", "no such recording"),
        ("twice", "is given twice; give each recording once"),
        ("copy", "holds the same recording as 'a'; give each recording once"),
        ("same name", "two recordings are named 'a'"),
        ("no list", "cannot read the recordings list"),
        ("empty list", "the recordings list names no recording"),
        ("gps", "--gps FILE is one video's track"),
    ],
)
def test_bad_recordings_are_one_line_and_nothing_is_written(
    tmp_path: Path, monkeypatch, capsys, case: str, message: str
) -> None:
    a, b = _files(tmp_path, "a.mcap", "b.mcap")
    args = {
        "missing": [str(a), str(tmp_path / "missing.bag")],
        "twice": [str(a), str(a)],
        "copy": [str(a), str(shutil.copy(a, tmp_path / "c.mcap"))],
        "same name": [str(a), str(_files(tmp_path, "other/a.mcap", content=b"another drive")[0])],
        "no list": [str(a), "--recordings-file", str(tmp_path / "nothing.txt")],
        "empty list": [str(a), "--recordings-file", str(_files(tmp_path, "list.txt", content=b"# none\n\n")[0])],
        "gps": [str(a), str(b), "--gps", str(_files(tmp_path, "track.gpx")[0])],
    }[case]
    ws = tmp_path / "ws"
    code, err = run_main(ws, "run", *args, monkeypatch=monkeypatch, capsys=capsys)
    assert code == 2, err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not ws.exists()


def test_recording_names_and_list_files(tmp_path: Path) -> None:
    assert recording_name(Path("/data/drive_0005.bag")) == "drive_0005"
    assert recording_name(Path("/data/2011_09_26_drive_0005_sync/")) == "2011_09_26_drive_0005_sync"
    assert recording_name(Path("/data/my drive.mcap")) == "my_drive"
    listing = tmp_path / "lists" / "drives.txt"
    listing.parent.mkdir()
    listing.write_text("  one.bag  \n# skipped\n\n/abs/two.mcap\n")
    assert read_list_file(listing) == [listing.parent / "one.bag", Path("/abs/two.mcap")]


def test_a_run_on_one_recording_forgets_an_earlier_set(tmp_path: Path, monkeypatch) -> None:
    """After `drivesim run a b`, `drivesim run a` alone: a later `drivesim eval` evaluates in a's world only."""
    from drivesim.chain import run as chain_run

    ws = Workspace(tmp_path / "ws")
    (ws.root / "drives").mkdir(parents=True)
    (ws.root / "drives" / "drives.json").write_text(json.dumps({"recordings": []}))
    monkeypatch.setattr(chain_run, "walk_chain", lambda *a, **k: [])
    chain_run.run_chain(ws, tmp_path / "a.mcap", {})
    assert not (ws.root / "drives" / "drives.json").exists() and set_worlds(ws) == []


def test_the_chains_eval_settings_override_only_the_env_keys_they_name() -> None:
    """A run preset's eval section with one env key: the evaluation takes the run's own env config for the others
    (a run trained with a shorter min_path_length_m is evaluated with it)."""
    from drivesim.chain.walk import stage_config
    from drivesim.stages.evaluate.config import EvalConfig

    cfg = stage_config(EvalConfig, "eval", {"episodes": 3, "env": {"max_lateral_m": 2.0}}, "eval")
    assert cfg.episodes == 3 and cfg.env_overrides() == {"max_lateral_m": 2.0}
    assert stage_config(EvalConfig, "eval", {"episodes": 3}, "eval").env_overrides() == {}
