"""Procedural towns (`drivesim towns build`, chain/towns.py) on tiny drives: built through the chain, skipped when
fresh, a changed setting redoing only its stage; `drivesim train` adds the towns its config names (building the
missing ones first) to the workspace's world or the --world folders."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from cli_helpers import drivesim_ok

from drivesim.chain import towns as towns_module
from drivesim.chain.towns import TownsConfig, ensure_towns, is_built, town_world
from drivesim.pipeline.errors import DrivesimError
from drivesim.pipeline.stage import StageResult
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.train import stage as train_stage
from drivesim.stages.train.config import TrainConfig

# A town of 1.5 s of drive at 160 x 100 pixels, plane depth: about 10 s to build on the shared 2 cores.
TINY = {
    "duration_s": 1.5,
    "stages": {
        "synth": {"camera": {"width_px": 160, "height_px": 100}, "world": {"scenery": {"view_distance_m": 60}}},
        "preprocess": {"depth": {"method": "plane"}},
        "build-world": {"sim_width_px": 80},
    },
}


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str, str]:
    """A workspace with town 4 built by the CLI, then built again (every stage fresh), then with one setting changed;
    the workspace, the tiny config and the two later outputs."""
    root = tmp_path_factory.mktemp("towns")
    tiny = root / "tiny.yaml"
    tiny.write_text(yaml.safe_dump(TINY))
    ws = root / "ws"
    first = drivesim_ok(ws, "towns", "build", "4", "--config", str(tiny)).stdout
    assert "town seed4: build-world: done" in first, first
    again = drivesim_ok(ws, "towns", "build", "4", "--config", str(tiny)).stdout
    changed = drivesim_ok(
        ws, "towns", "build", "4", "--config", str(tiny), "--set", "stages.build-world.sim_width_px=64"
    ).stdout
    return ws, tiny, again, changed


def test_a_town_is_built_through_the_chain_then_skipped_when_fresh(built) -> None:
    from drivesim.sim.world import World

    ws, _, again, changed = built
    world = World.load(ws / "towns" / "seed4" / "world")
    assert world.frame_count == 15 and world.width_px == 64
    for stage in ("synth", "ingest", "preprocess", "build-world"):
        assert f"town seed4: {stage}: fresh, skipped" in again, again
    # Only build-world's setting changed: the stages before it are fresh, build-world is redone.
    assert "town seed4: preprocess: fresh, skipped" in changed and "town seed4: build-world: done" in changed, changed
    listed = drivesim_ok(ws, "towns", "list").stdout
    assert f"seed4: built: {ws / 'towns' / 'seed4' / 'world'}" in listed.replace("\n", "")


def test_bad_town_settings_are_one_line(tmp_path: Path) -> None:
    import subprocess
    import sys

    for args, text in (
        (["towns", "build", "1", "--set", "stages.export.x=1"], "unknown stage(s) export"),
        (["towns", "build", "--", "-2"], "seeds are 0 or more"),
    ):
        done = subprocess.run(
            [sys.executable, "-m", "drivesim.cli.main", "-w", str(tmp_path / "ws"), *args],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert done.returncode == 2 and text in done.stderr, done.stderr
    assert not (tmp_path / "ws" / "towns" / "seed1").exists()


def _stand_in_world(ws_root: Path) -> Path:
    """A `world` artifact with a manifest (what the train stage checks before training) in workspace `ws_root`."""
    with Workspace(ws_root).write_artifact("world", "build-world", {}, {}) as build:
        (build.dir / "path.npz").write_bytes(b"stand-in")
    return ws_root / "world"


def _workspace_with_world(tmp_path: Path) -> Workspace:
    _stand_in_world(tmp_path / "user")
    return Workspace(tmp_path / "user")


def test_training_worlds_are_the_workspace_world_then_the_towns(tmp_path: Path) -> None:
    ws = _workspace_with_world(tmp_path)
    town = _stand_in_world(ws.root / "towns" / "seed4")
    cfg = TrainConfig(task="overtake", towns=[4])
    spec, external = train_stage.training_inputs(ws, cfg, None, [town])
    assert spec.requires == () and external == {"world_00": ws.root / "world", "world_01": town}
    # --world replaces the workspace's world; a town given twice (a resumed run's worlds) counts once.
    spec, external = train_stage.training_inputs(ws, cfg, [town, ws.root / "world"], [town])
    assert list(external.values()) == [town, ws.root / "world"]
    # A world the user gives twice stays twice (twice the episodes), not folded into one.
    spec, external = train_stage.training_inputs(ws, cfg, [ws.root / "world", ws.root / "world"], [town])
    assert list(external.values()) == [ws.root / "world", ws.root / "world", town]
    # No towns, no --world: the workspace's world as the artifact input, as before.
    spec, external = train_stage.training_inputs(ws, TrainConfig(task="overtake"), None, [])
    assert spec.requires == ("world",) and external == {}
    with pytest.raises(DrivesimError, match="not a world folder"):
        train_stage.training_inputs(ws, cfg, None, [tmp_path / "nothing"])
    with pytest.raises(ValueError, match="town seeds are 0 or more"):
        TrainConfig(towns=[-1])


def test_train_builds_the_missing_towns_first_and_uses_the_built_as_they_are(tmp_path, monkeypatch) -> None:
    """Town 4 exists (made with whatever settings): used as it is; town 7 is missing: built first. The run gets the
    workspace's world, then towns 4 and 7 (stand-ins for the build and for run_stage's training)."""
    ws = _workspace_with_world(tmp_path)
    _stand_in_world(ws.root / "towns" / "seed4")
    asked: list[list[int]] = []

    def fake_build(ws_: Workspace, seeds, cfg=None, force=False, on_stage=None) -> list[Path]:
        asked.append(list(seeds))
        for seed in seeds:  # a stand-in for a 30-s build
            _stand_in_world(ws_.root / "towns" / f"seed{seed}")
        return [town_world(ws_, s) for s in seeds]

    seen: dict[str, object] = {}

    def fake_run_stage(ws_, spec, cfg, **kwargs) -> StageResult:
        seen.update(spec=spec, external=kwargs["external"])
        return StageResult(stage="train", path=ws_.root / "runs" / "x", skipped=False, summary=None)

    monkeypatch.setattr(towns_module, "build_towns", fake_build)
    monkeypatch.setattr(train_stage, "run_stage", fake_run_stage)
    cfg = TrainConfig(task="overtake", towns=[4, 7])
    train_stage.run_training(ws, cfg, towns=towns_module.training_towns(ws, cfg))
    assert asked == [[7]] and is_built(ws, 7)
    assert list(seen["external"].values()) == [ws.root / "world", town_world(ws, 4), town_world(ws, 7)]
    # Both towns there now: nothing is built again.
    assert ensure_towns(ws, [4, 7]) == [town_world(ws, 4), town_world(ws, 7)] and asked == [[7]]


def test_a_missing_workspace_world_is_one_line_before_any_town_is_built(tmp_path, monkeypatch) -> None:
    monkeypatch.setattr(towns_module, "build_towns", lambda *a, **k: pytest.fail("a town was built"))
    with pytest.raises(DrivesimError, match="no world artifact"):
        towns_module.training_towns(Workspace(tmp_path / "empty"), TrainConfig(task="overtake", towns=[1]))


def test_the_train_stage_refuses_a_config_with_towns_but_no_town_worlds(tmp_path) -> None:
    with pytest.raises(DrivesimError, match="towns 1, 2, but their worlds were not given"):
        train_stage.run_training(Workspace(tmp_path / "empty"), TrainConfig(task="overtake", towns=[1, 2]))


def test_town_overrides_put_the_seed_and_drive_length_under_the_config() -> None:
    cfg = TownsConfig.model_validate(TINY)
    overrides = towns_module.town_overrides(cfg, 9)
    assert overrides["synth"]["seed"] == 9 and overrides["synth"]["drive"] == {"duration_s": 1.5}
    assert overrides["synth"]["camera"] == {"width_px": 160, "height_px": 100}
    assert overrides["preprocess"] == {"depth": {"method": "plane"}}


def test_per_town_overrides_apply_to_their_town_only() -> None:
    trees = {"synth": {"world": {"scenery": {"tree_spacing_m": 4.0}}}}
    cfg = TownsConfig.model_validate({**TINY, "per_town": {8: trees}})
    eight, nine = towns_module.town_overrides(cfg, 8), towns_module.town_overrides(cfg, 9)
    assert eight["synth"]["world"]["scenery"] == {"view_distance_m": 60, "tree_spacing_m": 4.0}  # merged with stages
    assert nine["synth"]["world"]["scenery"] == {"view_distance_m": 60}
    assert eight["synth"]["camera"] == nine["synth"]["camera"] == {"width_px": 160, "height_px": 100}
    assert eight["synth"]["seed"] == 8 and eight["preprocess"] == {"depth": {"method": "plane"}}
    with pytest.raises(ValueError, match="unknown stage"):
        TownsConfig.model_validate({"per_town": {8: {"export": {}}}})


def test_the_preset_makes_towns_8_and_9_tree_lined() -> None:
    from drivesim.pipeline.config import load_config

    cfg = load_config(TownsConfig, preset="towns")
    for seed in (8, 9):
        scenery = towns_module.town_overrides(cfg, seed)["synth"]["world"]["scenery"]
        assert scenery["building_probability"] < 0.5 and scenery["tree_spacing_m"] < 14.0
    assert "world" not in towns_module.town_overrides(cfg, 1)["synth"]
