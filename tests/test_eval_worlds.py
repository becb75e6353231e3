"""`drivesim eval --world A --world B`: the same seeds in each world, a row per world with the pooled figures, the
worlds a run trained on labelled train (the others unseen) with the gap between them; one world's output unchanged."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from eval_fakes import FAKE, fake_world, lane_departure_record, pass_record, register_fake_envs

from drivesim.pipeline.errors import ConfigError, InputError
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.evaluate.metrics import evaluate_episode
from drivesim.stages.evaluate.stage import run_eval
from drivesim.stages.evaluate.worlds import world_labels, world_tables

TESTS_DIR = Path(__file__).parent


@pytest.fixture(autouse=True)
def _fake_envs_registered() -> None:
    """The fake env is registered in this process, as drivesim's tests of the fake env do, so that this file passes
    alone and not only after another file registered it."""
    register_fake_envs()


def _make_run(
    folder: Path, trained_on: list[Path], env_config: dict | None = None, observation_shape: tuple = (3, 64, 160)
) -> Path:
    """A finished overtake run folder (small network, random weights) whose config.json names its training worlds."""
    import torch

    from drivesim.pipeline.hashing import sha256_file
    from drivesim.policy.run_folder import build_net
    from drivesim.stages.train.run_files import write_json, write_policy_files

    arch = {"conv_layers": [[4, 5, 4], [8, 3, 2]], "features_dim": 16, "lstm_hidden_size": 8, "lstm_layers": 1}
    torch.manual_seed(0)
    net = build_net({"observation_shape": list(observation_shape), "architecture": arch})
    folder.mkdir(parents=True)
    write_policy_files(folder, "overtake", observation_shape, arch, net.state_dict(), 0.15)
    worlds = [str(w) for w in trained_on]
    config = {"train": {"task": "overtake"}, "env_config": env_config or {}, "worlds": worlds}
    write_json(folder / "config.json", config)
    write_json(folder / "manifest.json", {"outputs": {"policy.pt": {"sha256": sha256_file(folder / "policy.pt")}}})
    return folder


def test_labels_name_the_town_and_stay_unique() -> None:
    worlds = [Path("/w/towns/seed3/world"), Path("/w/towns/seed3/world"), Path("/data/kitti 0005"), Path("/x/world")]
    assert world_labels(worlds) == ["seed3", "seed3-2", "kitti_0005", "x"]


def test_per_world_rows_pool_and_gap_count_every_episode() -> None:
    """World a: 4 clean passes; world b: 2 collisions and 2 lane departures. a is a training world, b unseen."""
    passes = [evaluate_episode(pass_record(3.0, seed=s)) for s in range(4)]
    crashes = [evaluate_episode(pass_record(0.5, seed=s)) for s in range(2)]
    departures = [evaluate_episode(lane_departure_record(seed=s)) for s in (2, 3)]
    assert all(r.metrics.success for r in passes) and all(r.metrics.collision for r in crashes)
    tables = world_tables(["a", "b"], [Path("/a"), Path("/b")], ["train", "unseen"], [passes, crashes + departures])
    a, b = tables["per_world"]
    assert (a["world"], a["group"], a["episodes"], b["group"], b["episodes"]) == ("a", "train", 4, "unseen", 4)
    assert a["success"]["value"] == 1.0 and b["success"]["value"] == 0.0
    assert b["intervention"]["value"] == 1.0 and b["collision"]["value"] == 0.5 and b["off_lane"]["value"] == 0.5
    # Minimum clearance over all episodes: the collisions count 0, the departures keep their (far) clearance.
    far = np.mean([r.metrics.min_clearance_m for r in departures])
    assert b["min_clearance_m"]["value"] == pytest.approx((0 + 0 + 2 * far) / 4, abs=1e-4)
    assert b["min_clearance_no_collision_m"]["value"] == pytest.approx(far, abs=1e-4)
    assert tables["pooled"]["episodes"] == 8 and tables["pooled"]["success"]["value"] == 0.5
    assert tables["groups"]["train"]["success"]["value"] == 1.0
    assert tables["gap"]["success"] == -1.0 and tables["gap"]["collision"] == 0.5
    # The policy's training worlds unknown (the expert): no groups, no gap, the pooled row still there.
    plain = world_tables(["a", "b"], [Path("/a"), Path("/b")], [None, None], [passes, crashes])
    assert plain["groups"] == {} and plain["gap"] == {} and plain["pooled"]["episodes"] == 6


def test_one_world_keeps_its_identity_and_a_repeat_is_refused(tmp_path: Path) -> None:
    one = EvalConfig(world=str(tmp_path)).model_dump(mode="json")
    assert one["world"] == str(tmp_path) and EvalConfig(world=[str(tmp_path)]).model_dump(mode="json") == one
    world = fake_world(tmp_path / "w")
    with pytest.raises(ConfigError, match="twice"):
        run_eval(Workspace(tmp_path / "ws"), EvalConfig(world=[str(world), str(world)], episodes=1, **FAKE))


def test_two_worlds_same_seeds_rows_labelled_by_the_run(tmp_path: Path) -> None:
    seen = fake_world(tmp_path / "towns" / "seed1" / "world")
    unseen = fake_world(tmp_path / "towns" / "seed2" / "world")
    run = _make_run(tmp_path / "ws" / "runs" / "overtake-test", trained_on=[seen])
    cfg = EvalConfig(world=[str(seen), str(unseen)], episodes=3, seed=5, workers=1, policy=str(run), **FAKE)
    result = run_eval(Workspace(tmp_path / "ws"), cfg)
    data = json.loads((result.path / "metrics.json").read_text())
    rows = {row["world"]: row for row in data["per_world"]}
    assert {k: (r["group"], r["episodes"]) for k, r in rows.items()} == {"seed1": ("train", 3), "seed2": ("unseen", 3)}
    assert data["episodes"] == 6 and result.summary.episodes == 6 and data["pooled"]["episodes"] == 6
    for label in rows:
        names = sorted(p.name for p in (result.path / "worlds" / label / "episodes").glob("*.json"))
        assert names == ["5.json", "6.json", "7.json"]
        world_metrics = json.loads((result.path / "worlds" / label / "metrics.json").read_text())
        assert world_metrics["aggregate"]["success"] == rows[label]["success"]
    # The fake env does not depend on the world: the same seeds give the same episodes, so no gap.
    assert data["gap"]["success"] == 0.0 and data["groups"]["train"]["episodes"] == 3
    csv_head = (result.path / "episodes.csv").read_text().splitlines()[:2]
    assert csv_head[0].startswith("world,seed,") and csv_head[1].startswith("seed1,5,")
    report = (result.path / "report.html").read_text()
    assert (
        "<h2>Worlds</h2>" in report and "gap: unseen − train" in report and 'href="worlds/seed2/report.html"' in report
    )
    assert (result.path / "worlds" / "seed2" / "track.png").is_file() and not (result.path / "track.png").exists()


def test_one_world_writes_no_world_table(tmp_path: Path) -> None:
    world = fake_world(tmp_path / "w")
    result = run_eval(Workspace(tmp_path / "ws"), EvalConfig(world=str(world), episodes=2, workers=1, **FAKE))
    data = json.loads((result.path / "metrics.json").read_text())
    assert "per_world" not in data and data["world"] == str(world)
    assert (result.path / "episodes" / "0.json").is_file() and not (result.path / "worlds").exists()
    assert "<h2>Worlds</h2>" not in (result.path / "report.html").read_text()


def test_cli_prints_a_row_per_world_and_the_pooled_row(tmp_path: Path) -> None:
    a, b = fake_world(tmp_path / "a"), fake_world(tmp_path / "b")
    env = {**os.environ, "PYTHONPATH": str(TESTS_DIR), "OMP_NUM_THREADS": "1", "COLUMNS": "200"}
    args = ["--world", str(a), "--world", str(b), "--episodes", "2", "--workers", "1", "--policy", "expert"]
    args += ["--set", f"env_id={FAKE['env_id']}", "--set", f"env_entry_point={FAKE['env_entry_point']}"]
    args.append("--trust-entry-point")
    done = subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(tmp_path / "ws"), "eval", *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    out = done.stdout
    assert "2 episodes in each of 2 worlds" in out and "4 episodes of expert" in out
    table = [line for line in out.splitlines() if line.strip().startswith(("│ a ", "│ b ", "│ all worlds"))]
    assert len(table) == 3, out
    assert "trained on" not in out  # the expert: no training worlds to label


def test_a_short_drive_the_run_trained_on_is_evaluated_with_the_runs_own_config(tmp_path: Path) -> None:
    # 50 m of drive: too short for the default 60 + 8 m an episode needs, but the run trained with 40 m; its own env
    # config is read before the world is opened, so the world is admitted (it was refused before any episode)
    from sim_worlds import SMALL_VIEW, write_test_world

    short = write_test_world(tmp_path / "short" / "world", length_m=50.0)
    env_config = {**SMALL_VIEW, "min_path_length_m": 40.0, "front_distance_m": [6.0, 15.0]}
    run = _make_run(tmp_path / "ws" / "runs" / "overtake-short", [short], env_config, observation_shape=(3, 16, 40))
    cfg = EvalConfig(world=[str(short)], episodes=2, workers=1, policy=str(run), record="none")
    result = run_eval(Workspace(tmp_path / "ws"), cfg)
    assert result.summary.episodes == 2
    ran_with = json.loads((result.path / "metrics.json").read_text())["env"]  # what ran, not the eval's defaults
    assert ran_with["min_path_length_m"] == 40.0
    assert ran_with["observation_height_px"] == SMALL_VIEW["observation_height_px"]
    plain = _make_run(tmp_path / "ws" / "runs" / "overtake-plain", [short], dict(SMALL_VIEW), (3, 16, 40))
    with pytest.raises(InputError, match="path of 50 m is too short"):  # without it: one line, as before
        run_eval(Workspace(tmp_path / "ws"), EvalConfig(world=[str(short)], episodes=2, workers=1, policy=str(plain)))
