"""A task is one class: `gymnasium.make(id, world=W)` is the env `drivesim train <task>` trains, the train presets
hold budgets only, `drivesim config train --task T` lists T's env keys, and no code outside the task modules and the
registry asks which task it runs."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import yaml
from sim_worlds import write_test_world

import drivesim.sim.envs  # noqa: F401  (registers the envs)
from drivesim.pipeline.config import load_config, preset_path
from drivesim.sim.envs.config import TASK_ONLY_KEYS, EnvConfig
from drivesim.sim.envs.registry import TASK_NAMES, TASKS, task_spec
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.train.config import EnvsConfig, TrainConfig
from drivesim.stages.train.envs import EnvSource

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def world_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # Long enough for cut-in's 190 m of road ahead of a start.
    return write_test_world(tmp_path_factory.mktemp("tasks") / "world", length_m=400.0, curve_from_m=250.0)


def _trained_config(task: str, *sets: str) -> EnvConfig:
    """`envs.config` as `drivesim train <task> [--set ...]` resolves it (cli/train.py)."""
    return load_config(TrainConfig, preset=f"train/{task}", overrides=[f"task={task}", *sets]).envs.config


def _observations(env: gymnasium.Env, seed: int, count: int = 100) -> np.ndarray:
    """The first `count` observations from reset(seed) with the expert driving (the next seed after an end)."""
    obs, _ = env.reset(seed=seed)
    frames = [obs]
    while len(frames) < count:
        obs, _, terminated, truncated, _ = env.step(env.unwrapped.expert_action())
        frames.append(obs)
        if terminated or truncated:
            seed += 1
            frames.append(env.reset(seed=seed)[0])
    return np.stack(frames[:count])


@pytest.mark.parametrize("task", TASK_NAMES)
def test_gymnasium_make_is_the_env_drivesim_train_builds(world_dir: Path, task: str) -> None:
    """The same config and the same first 100 training observations on a seed, augmentation included."""
    source = EnvSource(task=task, worlds=[world_dir], config=_trained_config(task))  # as the train stage makes it
    trained = source.make_env("train")
    made = gymnasium.make(TASKS[task].env_id, world=str(world_dir))
    assert made.unwrapped.config == trained.unwrapped.config == type(made.unwrapped).default_config()
    np.testing.assert_array_equal(_observations(made, seed=7), _observations(trained, seed=7))


def test_each_task_has_its_own_settings() -> None:
    """The settings the train presets used to carry are the tasks' own: cut-in's other car is faster than the ego
    (else it never passes), overtake penalizes the dilated overlap 5x the base's, lane trains with camera jitter."""
    cutin, overtake, lane = (task_spec(t).config_with() for t in ("cutin", "overtake", "lane"))
    assert cutin.other_speed_mps[0] > cutin.ego_speed_mps[1] and cutin.episode_steps == 150
    assert overtake.weight_collision == 50.0 == 5 * EnvConfig().weight_collision and overtake.grey_probability == 0.3
    assert lane.pitch_jitter_deg == 3.0 and lane.noise_std == (0.0, 0.03)
    assert task_spec("follow").config_with() == EnvConfig()


def test_task_only_keys_are_grouped_by_the_task_that_reads_them() -> None:
    """Every key of TASK_ONLY_KEYS is some task's, each task lists only such keys, lane none of them."""
    classes = [task_spec(t).env_class() for t in TASK_NAMES]
    assert all(set(c.task_keys) <= set(TASK_ONLY_KEYS) for c in classes)
    assert set(TASK_ONLY_KEYS) == {key for c in classes for key in c.task_keys}
    assert task_spec("lane").env_class().task_keys == ()
    assert set(task_spec("lane").env_class().config_keys()) == set(EnvConfig.model_fields) - set(TASK_ONLY_KEYS)


@pytest.mark.parametrize("task", TASK_NAMES)
def test_train_presets_hold_budgets_only(task: str) -> None:
    data = yaml.safe_load(preset_path(f"train/{task}").read_text())
    assert "config" not in (data.get("envs") or {}), f"configs/train/{task}.yaml sets env keys: the task owns them"


def test_a_users_keys_go_over_the_tasks_settings() -> None:
    """--set, a preset or a typed EnvConfig: the keys given win, the task's settings fill the rest."""
    by_set = _trained_config("cutin", "envs.config.episode_steps=99")
    assert by_set.episode_steps == 99 and by_set.other_speed_mps == (10.0, 12.0)
    typed = TrainConfig(task="cutin", envs=EnvsConfig(count=2, config=EnvConfig(weight_lane=2.0)))
    assert typed.envs.count == 2 and typed.envs.config.weight_lane == 2.0
    assert typed.envs.config.other_speed_mps == (10.0, 12.0)
    typed.total_steps = 5  # an assignment is validated again: the env config stays typed, with its keys
    assert isinstance(typed.envs.config, EnvConfig) and typed.envs.config.weight_lane == 2.0
    assert TrainConfig(task="lane").envs.config == task_spec("lane").config_with()
    # a saved run's config (every key) stays exactly as it was saved
    saved = TrainConfig(task="cutin").model_dump(mode="json")
    saved["envs"]["config"]["other_speed_mps"] = [1.0, 2.0]
    assert TrainConfig.model_validate(saved).envs.config.other_speed_mps == (1.0, 2.0)


def test_a_dict_config_goes_over_the_tasks_settings_and_an_env_config_is_taken_whole(world_dir: Path) -> None:
    env_id = TASKS["cutin"].env_id
    over = gymnasium.make(env_id, world=str(world_dir), config={"episode_steps": 99}).unwrapped.config
    assert over.episode_steps == 99 and over.other_speed_mps == (10.0, 12.0)
    whole = EnvConfig(min_path_length_m=190.0, front_distance_m=(5.0, 15.0))
    assert gymnasium.make(env_id, world=str(world_dir), config=whole).unwrapped.config is whole


def _config_show(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "config", "train", *args],
        capture_output=True, text=True, timeout=120, env={"COLUMNS": "250", "PATH": ""},
    )  # fmt: skip


def test_config_train_task_lists_that_tasks_keys_and_values() -> None:
    lane = _config_show("--task", "lane")
    assert lane.returncode == 0, lane.stderr
    assert re.search(r"envs\.config\.pitch_jitter_deg\s*│\s*float\s*│\s*3\.0", lane.stdout)
    assert re.search(r"│ task\s*│[^│]*│\s*lane", lane.stdout)
    for key in TASK_ONLY_KEYS:  # lane has no other car and no task-only key
        assert f"envs.config.{key} " not in lane.stdout
    overtake = yaml.safe_load(_config_show("--task", "overtake", "--yaml").stdout)["envs"]["config"]
    assert overtake["weight_collision"] == 50.0 and overtake["pass_distance_m"] == 6.0
    assert "follow_speed_mps" not in overtake
    assert set(overtake) == set(task_spec("overtake").env_class().config_keys())
    follow = yaml.safe_load(_config_show("--task", "follow", "--yaml").stdout)["envs"]["config"]
    assert "follow_speed_mps" in follow and "pass_distance_m" not in follow and "other_speed_mps" not in follow
    bad = _config_show("--task", "merge")
    assert bad.returncode == 2 and "choose one of lane, follow, overtake, cutin" in bad.stderr + bad.stdout


def test_the_table_ii_scenarios_are_overtakes() -> None:
    overrides = EvalConfig(task="overtake", scenario=["static", "pass-left"]).env_overrides()
    assert overrides == {"other_speed_mps": (0.0, 0.0), "front_side": "right"}
    with pytest.raises(ValueError, match="not one of the lane task's scenarios: it has none"):
        EvalConfig(task="lane", scenario=["static"])
    with pytest.raises(ValueError, match="static and dynamic exclude each other"):
        EvalConfig(task="overtake", scenario=["static", "dynamic"])


def test_the_report_shows_the_scenario_table_for_the_task_that_has_the_scenarios(tmp_path: Path) -> None:
    """The same passing episodes: overtake's report splits them by its Table II scenarios; cut-in's, whose other car
    comes from behind, has no such table; neither reports a tracking error (follow's measurement)."""
    from dataclasses import replace

    from eval_fakes import pass_record

    from drivesim.stages.evaluate.metrics import evaluate_episode
    from drivesim.stages.evaluate.report import write_outputs

    results = []
    for seed in range(3):  # a front car at 5 m/s, 1.5 m right of the lane centre
        result = evaluate_episode(pass_record(2.6, seed=seed))
        results.append(replace(result, metrics=replace(result.metrics, other_speed_mps=5.0, other_lateral_m=-1.5)))
    overtake = write_outputs(tmp_path / "overtake", results, None, "overtake", {})
    cutin = write_outputs(tmp_path / "cutin", results, None, "cutin", {})
    assert [row["episodes"] for row in overtake["scenarios"]] == [0, 3, 3, 0]  # moving car, passed on the left
    assert cutin["scenarios"] == [] and "scenario" not in (tmp_path / "cutin" / "report.html").read_text()
    assert overtake["aggregate"]["mean_tracking_error_m"]["n"] == 0


# A task's name compared as a string: ==/!= either side, `in` a collection of strings, a match case.
_NAMES = "|".join(TASK_NAMES)
_COMPARED = re.compile(
    rf"""(==|!=)\s*["']({_NAMES})["']|["']({_NAMES})["']\s*(==|!=|in\b|not\s+in\b)"""
    rf"""|\bin\s*[(\[{{]\s*(["'][^"']*["']\s*,\s*)*["']({_NAMES})["']|\bcase\s+["']({_NAMES})["']"""
)
_PRODUCT = ("cli", "pipeline", "stages", "sim", "policy", "chain", "bench")


def test_no_code_outside_the_task_modules_and_the_registry_asks_which_task_it_runs() -> None:
    assert _COMPARED.search('tracking = task == "follow"') and _COMPARED.search('if task in ("lane", "follow"):')
    assert not _COMPARED.search('for name, half in (("lane", 1.0), ("limit", 2.0)):')  # a reward term, iterated
    owners = {ROOT / "sim" / "envs" / f"{name}.py" for name in TASK_NAMES} | {ROOT / "sim" / "envs" / "registry.py"}
    found = []
    for folder in _PRODUCT:
        for path in sorted((ROOT / folder).rglob("*.py")):
            if path in owners:
                continue
            for number, line in enumerate(path.read_text().splitlines(), 1):
                if _COMPARED.search(line):
                    found.append(f"{path.relative_to(ROOT)}:{number}: {line.strip()}")
    assert not found, "task names compared outside the tasks (give the task class a hook):\n" + "\n".join(found)


def test_a_run_preset_naming_a_task_starts_from_that_tasks_train_preset() -> None:
    """`drivesim run --preset lane` trains lane from `train/lane` (its budgets and LaneEnv's settings), not from the
    chain's default `train/overtake` preset."""
    import yaml

    from drivesim.chain.walk import stage_config, task_preset
    from drivesim.pipeline.config import preset_path
    from drivesim.stages.train.config import TrainConfig

    assert task_preset("train/overtake", {"task": "lane"}) == "train/lane"
    assert task_preset("train/overtake", {}) == "train/overtake"
    run_train = yaml.safe_load(preset_path("run/lane").read_text())["train"]
    cfg = stage_config(TrainConfig, "train/overtake", run_train, "train")
    assert cfg.task == "lane" and cfg.towns == []
    assert cfg.envs.config.pitch_jitter_deg == 3.0  # LaneEnv.default_config()'s, not restated by the run preset
    assert "pitch_jitter_deg" not in run_train["envs"]["config"]


def test_eval_hands_the_env_a_typed_config_with_the_users_keys(world_dir: Path) -> None:
    """`drivesim eval --set env.max_lateral_m=2.0`: the env gets an `EnvConfig` (the task's settings with the user's
    key on top), not a dict re-validated in the env; a user's own env (`env_entry_point`) keeps plain keys."""
    from drivesim.stages.evaluate.stage import _factory

    cfg = load_config(EvalConfig, preset="eval", overrides=["task=overtake", "env.max_lateral_m=2.0"])
    factory = _factory(cfg, world_dir, None, trusted=False)
    config = factory.kwargs["config"]
    assert isinstance(config, EnvConfig) and config.max_lateral_m == 2.0
    assert config.weight_collision == task_spec("overtake").config_with().weight_collision  # the task's own value
    env = factory()
    try:
        assert env.unwrapped.config == config
    finally:
        env.close()
    own = load_config(
        EvalConfig, overrides=["env_id=mine/X-v0", "env_entry_point=drivesim.sim.envs.lane:LaneEnv", "env.dt_s=0.2"]
    )
    assert _factory(own, world_dir, None, trusted=True).kwargs["config"] == {"dt_s": 0.2}
