"""The memory head: the cloning passes fit an LSTM head to where the other car is, so the LSTM keeps a car it no
longer sees; its targets follow the picture (mirrored with a mirrored episode) and it is never part of the driving
net."""

from __future__ import annotations

from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch
from sim_worlds import SMALL_VIEW, write_test_world
from stable_baselines3.common.vec_env import DummyVecEnv
from test_train import small_ppo

import drivesim.sim.envs  # noqa: F401  (registers the envs)
from drivesim.sim.envs.base import MEMORY_CLIP, MEMORY_SCALE_M
from drivesim.stages.train.config import WarmStartConfig
from drivesim.stages.train.cost_free_env import CostFreeDrivingEnv
from drivesim.stages.train.imitation import ExpertLabels, ImitationRegularizer
from drivesim.stages.train.sb3_policy import DrivingLstmPolicy
from drivesim.stages.train.warm_start import warm_start

SHAPE = (3, 16, 40)
SHOWN_STEPS = 3


class GlimpseEnv(CostFreeDrivingEnv):
    """A car on one side, drawn at random at each reset, is in the picture for the first SHOWN_STEPS steps only
    (a bright left or right half), and the memory target is its side (+1 left, -1 right) all episode long."""

    side = 1.0

    def reset(self, *, seed=None, options=None):
        obs, info = super().reset(seed=seed, options=options)
        self.side = float(self.np_random.choice([-1.0, 1.0]))
        return self._obs(), info

    def _obs(self) -> np.ndarray:
        obs = np.full(SHAPE, 60, np.uint8)
        if self.steps < SHOWN_STEPS:
            half = SHAPE[2] // 2
            obs[:, :, :half] = 250 if self.side > 0 else 60
            obs[:, :, half:] = 60 if self.side > 0 else 250
        return obs

    def memory_target(self) -> np.ndarray:
        return np.array([0.0, self.side], np.float32)


def _model(memory_outputs: int):
    venv = DummyVecEnv([lambda: GlimpseEnv(observation_shape=SHAPE, episode_steps=40, drift=0.0) for _ in range(4)])
    venv.seed(0)
    model = small_ppo(venv, [(8, 3, 2), (16, 3, 1)], 1)
    if memory_outputs:
        kwargs = {"conv_layers": [(8, 3, 2), (16, 3, 1)], "input_pool": 1, "memory_outputs": memory_outputs}
        model.policy = DrivingLstmPolicy(venv.observation_space, venv.action_space, lambda _: 3e-4, **kwargs)
    return model, venv


def _remembered_side_error(model, venv, steps: int = 20) -> float:
    """Mean squared error of the memory head's side, SHOWN_STEPS+ steps after the car was last in the picture."""
    policy = model.policy
    obs = venv.reset()
    layers, hidden = policy.lstm_actor.num_layers, policy.lstm_actor.hidden_size
    state = (torch.zeros(layers, 4, hidden), torch.zeros(layers, 4, hidden))
    start = torch.ones(4)
    errors = []
    for t in range(steps):
        with torch.no_grad():
            features = policy.extract_features(torch.from_numpy(obs).float())
            latent, state = policy._process_sequence(features, state, start, policy.lstm_actor)
            predicted = policy.memory_net(latent)[:, 1].numpy()
        target = np.array([env.side for env in venv.envs])
        if t >= 2 * SHOWN_STEPS:
            errors.append(np.mean((predicted - target) ** 2))
        obs, _, _, _ = venv.step(np.zeros((4, 1), np.float32))
        start = torch.zeros(4)
    return float(np.mean(errors))


def test_the_memory_head_learns_to_keep_a_car_that_left_the_picture():
    torch.manual_seed(0)
    model, venv = _model(memory_outputs=2)
    before = _remembered_side_error(model, venv)
    cfg = WarmStartConfig(method="expert", iterations=3, steps_per_iteration=512, epochs=20, value_fit_steps=64)
    warm_start(model, venv, cfg, seed=0, report=lambda _: None, memory_weight=1.0)
    after = _remembered_side_error(model, venv)
    # guessing 0 for a side of +-1 costs 1; the head remembers the side 3-17 steps after the car was last seen
    assert after < 0.3 < before, (before, after)


def test_memory_labels_ride_with_the_expert_action_and_the_regularizer_fits_them():
    torch.manual_seed(0)
    model, venv = _model(memory_outputs=2)
    labelled = ExpertLabels(venv, steps=64, memory=True)
    model.set_env(labelled)
    regularizer = ImitationRegularizer(model, labelled, epochs=4, learning_rate=3e-3, seed=0, memory_weight=1.0)
    model.update_hooks.append(regularizer)
    head_before = model.policy.memory_net.weight.detach().clone()
    model.learn(64 * 4 * 2)
    assert not torch.equal(head_before, model.policy.memory_net.weight)  # the regularizer fitted the head (PPO cannot)
    recorded = np.stack(list(labelled.labels))
    assert recorded.shape == (64, 4, 3)
    assert set(np.unique(recorded[:, :, 2])) <= {-1.0, 1.0}  # the side, beside the expert's steering
    assert np.all(np.abs(recorded[:, :, 0]) <= 1.0)  # the expert's steering first
    changes = (np.diff(recorded[:, :, 2], axis=0) != 0).sum(axis=0)
    assert np.all(changes <= 2)  # a car's side changes only at an episode's start (every 40 steps)
    assert np.isfinite(model.logger.name_to_value["train/imitation_loss"])


def test_the_memory_head_is_not_part_of_the_driving_net():
    model, _ = _model(memory_outputs=2)
    state = model.policy.driving_net_state()
    assert not any(name.startswith("memory") for name in state)
    assert model.policy.to_driving_net() is not None
    plain, _ = _model(memory_outputs=0)
    assert plain.policy.memory_net is None
    assert set(state) == set(plain.policy.driving_net_state())


@pytest.fixture(scope="module")
def bend_world(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_test_world(tmp_path_factory.mktemp("bend") / "world", length_m=220.0, curve_from_m=0.0)


@pytest.mark.parametrize("mirrored", [False, True])
def test_the_env_gives_the_other_car_in_the_egos_frame_as_the_picture_shows_it(mirrored, bend_world):
    env = gymnasium.make("drivesim/Overtake-v0", world=str(bend_world), mode="eval", config=SMALL_VIEW).unwrapped
    env.reset(seed=3)
    env._mirrored = mirrored
    for _ in range(2):
        ego, other = env.sim.agents[0].state, env.sim.agents[1].state
        dx, dy = other.x_m - ego.x_m, other.y_m - ego.y_m
        c, s = np.cos(ego.yaw_rad), np.sin(ego.yaw_rad)
        forward, left = c * dx + s * dy, -s * dx + c * dy
        left = -left if mirrored else left
        expected = np.clip([forward / MEMORY_SCALE_M[0], left / MEMORY_SCALE_M[1]], -MEMORY_CLIP, MEMORY_CLIP)
        np.testing.assert_allclose(env.memory_target(), expected, atol=1e-5)
        assert env.memory_target()[0] > 0  # the front car is ahead
        env.step(np.array([0.3], np.float32))
    lane = gymnasium.make("drivesim/Lane-v0", world=str(bend_world), mode="eval", config=SMALL_VIEW).unwrapped
    lane.reset(seed=0)
    np.testing.assert_array_equal(lane.memory_target(), np.zeros(2, np.float32))  # no other car
