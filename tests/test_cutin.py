"""drivesim/CutIn-v0: the other car passes from the adjacent lane and cuts in ahead; the expert holds its lane."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from sim_worlds import SMALL_VIEW, write_test_world

import drivesim.sim.envs  # noqa: F401  (registers the envs)


@pytest.fixture(scope="module")
def cutin_env(tmp_path_factory: pytest.TempPathFactory) -> gymnasium.Env:
    world = write_test_world(tmp_path_factory.mktemp("cutin") / "world", length_m=400.0, curve_from_m=250.0)
    return gymnasium.make("drivesim/CutIn-v0", world=str(world), meshes=None, mode="eval", config=SMALL_VIEW)


def _drive_with_expert(env: gymnasium.Env, seed: int) -> tuple[list[dict], dict]:
    """Per step: the other car's lead over the ego along the road and its lateral offset; the last info."""
    _, info = env.reset(seed=seed)
    sim = env.unwrapped.sim
    steps = []
    while True:
        _, _, terminated, truncated, info = env.step(env.unwrapped.expert_action())
        ego, other = sim.agents
        steps.append({"lead_m": other.arc_m - ego.arc_m, "other_lateral_m": other.lateral_m, "state": info["state"]})
        if terminated or truncated:
            return steps, info


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_other_car_passes_and_cuts_in_ahead_and_the_expert_holds_its_lane(cutin_env, seed: int) -> None:
    steps, info = _drive_with_expert(cutin_env, seed)
    first = steps[0]
    assert first["lead_m"] < 0.0, "the other car starts behind the ego"
    assert 3.0 <= abs(first["other_lateral_m"]) <= 4.0, "in the adjacent lane"
    # The moment its footprint starts to overlap the ego's lane width, it is ahead by at least a car length.
    entering = next(s for s in steps if abs(s["other_lateral_m"]) < 1.9)
    assert entering["lead_m"] >= 4.5
    assert abs(steps[-1]["other_lateral_m"]) < 0.3 and steps[-1]["lead_m"] > 5.0, "it ends in the ego's lane, ahead"
    assert info["success"] and not info["termination"]["collision"]
    assert info["termination"]["time_limit"] or info["termination"]["end_of_data"]
    assert max(abs(s["state"]["q_lat_m"]) for s in steps) < 0.5, "the expert stays in its lane"


def test_cutin_rewards_are_lane_comfort_and_the_dilated_gap(cutin_env) -> None:
    _, info = cutin_env.reset(seed=5)
    _, reward, _, _, info = cutin_env.step(np.zeros(1, np.float32))
    assert set(info["rewards"]) == {"lane", "collision", "comfort"}  # no pass term: overtake's own
    assert reward == pytest.approx(sum(info["rewards"].values()))


def test_the_registry_is_the_one_list_of_tasks() -> None:
    from drivesim.sim.envs.registry import TASKS, task_spec
    from drivesim.stages.evaluate.config import EvalConfig

    assert "cutin" in TASKS and task_spec("cutin").env_id == "drivesim/CutIn-v0"
    assert EvalConfig(task="cutin").task == "cutin"
    with pytest.raises(ValueError, match="choose one of lane, follow, overtake, cutin"):
        task_spec("merge")


def test_the_expert_is_evaluated_in_the_task_s_own_env(tmp_path) -> None:
    """`drivesim eval --task cutin` (the expert brings no env config): the task's faster other car, and the
    user's keys on top."""
    from drivesim.stages.evaluate.config import EvalConfig

    keys = EvalConfig.model_validate({"task": "cutin", "env": {"episode_steps": 99}}).start_env_config()
    world = write_test_world(tmp_path / "world", length_m=400.0, curve_from_m=250.0)
    env = gymnasium.make("drivesim/CutIn-v0", world=str(world), mode="eval", config={**SMALL_VIEW, **keys})
    assert env.unwrapped.config.other_speed_mps == (10.0, 12.0) and env.unwrapped.config.episode_steps == 99


@pytest.mark.parametrize(("side", "sign"), [("left", 1.0), ("right", -1.0)])
def test_front_side_places_the_other_car(tmp_path, side: str, sign: float) -> None:
    world = write_test_world(tmp_path / "world")
    env = gymnasium.make("drivesim/Overtake-v0", world=str(world), config={**SMALL_VIEW, "front_side": side})
    for seed in range(4):
        _, info = env.reset(seed=seed)
        assert np.sign(info["episode"]["other_lateral_m"]) == sign
