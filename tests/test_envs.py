"""The drivesim gymnasium envs on a small hand-made world: API, determinism, rewards, terminations, the expert,
the batched vector env and one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from sim_worlds import SMALL_VIEW, write_test_world
from stable_baselines3.common.vec_env import DummyVecEnv, VecEnv

import drivesim.sim.envs  # noqa: F401  (registers the envs)
from drivesim.sim.dynamics import BicycleState
from drivesim.sim.envs.augment import Augmentation, ViewJitter
from drivesim.sim.envs.parallel import ProcessBatchedVecEnv
from drivesim.sim.envs.vector import BatchedVecEnv

TASKS = {name: spec.env_id for name, spec in drivesim.sim.envs.TASKS.items()}


@pytest.fixture(scope="session")
def world_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_test_world(tmp_path_factory.mktemp("sim-world") / "world")


STILL = {
    "gamma": (1.0, 1.0), "brightness": (0.0, 0.0), "contrast": (1.0, 1.0), "saturation": (1.0, 1.0),
    "pitch_jitter_deg": 0.0, "blur_sigma_px": (0.0, 0.0), "noise_std": (0.0, 0.0),
}  # fmt: skip
"""Training augmentation that leaves the view as rendered (lane's own pitch, blur and noise off too)."""


def _make(world_dir: Path, task: str, mode: str = "train", **overrides: object) -> gymnasium.Env:
    return gymnasium.make(TASKS[task], world=str(world_dir), meshes=None, mode=mode, config={**SMALL_VIEW, **overrides})


@pytest.mark.parametrize("task", list(TASKS))
def test_check_env(world_dir: Path, task: str) -> None:
    env = _make(world_dir, task)
    check_env(env.unwrapped)  # gymnasium's own checker on the env as it is (determinism of infos included)
    obs, info = env.reset(seed=3)
    assert obs.shape == (3, 16, 40) and obs.dtype == np.uint8
    assert set(info["episode"]) >= {"seed", "world", "start_frame", "ego_speed_mps"}
    has_other = env.unwrapped.has_other
    assert ("other_speed_mps" in info["episode"]) == has_other
    assert all(v == v for v in info["state"].values()), "no NaN in info['state']: absent quantities are left out"


def test_same_seed_same_observation_bytes(world_dir: Path) -> None:
    a, b = _make(world_dir, "overtake"), _make(world_dir, "overtake")
    obs_a, info_a = a.reset(seed=11)
    obs_b, info_b = b.reset(seed=11)
    assert obs_a.tobytes() == obs_b.tobytes() and info_a["episode"] == info_b["episode"]
    for _ in range(3):
        obs_a, *_ = a.step(np.array([0.3], np.float32))
        obs_b, *_ = b.step(np.array([0.3], np.float32))
    assert obs_a.tobytes() == obs_b.tobytes()
    other, _ = a.reset(seed=12)
    assert other.tobytes() != obs_b.tobytes()


def test_render_threads_change_no_observation(world_dir: Path) -> None:
    """`envs.config.render_threads` reaches the env's view synthesizer, and an overtake episode seen through it is
    the same, byte for byte, as on one thread."""
    one, two = _make(world_dir, "overtake"), _make(world_dir, "overtake", render_threads=2)
    obs_one, _ = one.reset(seed=5)
    obs_two, _ = two.reset(seed=5)
    assert two.unwrapped.sim.renderer.config.render_threads == 2
    for step in range(20):
        action = np.array([0.4 * np.sin(step / 3.0)], np.float32)
        assert obs_one.tobytes() == obs_two.tobytes(), step
        obs_one, *_ = one.step(action)
        obs_two, *_ = two.step(action)


def test_harmonizer_key_reaches_the_view(world_dir: Path) -> None:
    """`envs.config.harmonizer: learned` puts the learned harmonizer in the env's view; the episode is the same one
    (same cars, same steps), drawn with the car's colours changed only where a car is seen."""
    from drivesim.sim.harmonize import LearnedHarmonizer

    plain, learned = _make(world_dir, "overtake"), _make(world_dir, "overtake", harmonizer="learned")
    obs_plain, info_plain = plain.reset(seed=5)
    obs_learned, info_learned = learned.reset(seed=5)
    assert isinstance(learned.unwrapped.sim.renderer.harmonizer, LearnedHarmonizer)
    assert info_plain["episode"] == info_learned["episode"]
    differing = 0
    for step in range(30):
        action = np.array([0.4 * np.sin(step / 3.0)], np.float32)
        obs_plain, *_ = plain.step(action)
        obs_learned, _, _, _, info = learned.step(action)
        differing += int(obs_plain.tobytes() != obs_learned.tobytes())
    assert differing > 0


def test_reward_terms_sum_to_the_reward(world_dir: Path) -> None:
    env = _make(world_dir, "overtake").unwrapped
    env.reset_state(5)
    seen = set()
    for step in range(60):
        reward, terminated, truncated, info = env.advance(np.array([np.sin(step / 5.0)], np.float32))
        assert set(info["rewards"]) == {"lane", "pass", "collision", "comfort"}
        assert sum(info["rewards"].values()) == pytest.approx(reward, abs=1e-9)
        seen |= {k for k, v in info["rewards"].items() if v != 0.0}
        if terminated or truncated:
            break
    assert {"lane", "comfort"} <= seen


def _place_ego(env: gymnasium.Env, arc_m: float, lateral_m: float, yaw_offset_rad: float = 0.0) -> None:
    x, y, yaw = env.sim.reference.pose(arc_m, lateral_m)
    ego = env.sim.agents[0]
    ego.state = BicycleState(x, y, yaw + yaw_offset_rad, 0.0, ego.state.speed_mps)
    ego.frame_index = int(np.argmin(np.abs(env.sim.reference.arc_m - arc_m)))


@pytest.mark.parametrize(
    ("flag", "where"),
    [("off_lane", "lateral"), ("over_rotation", "yaw"), ("collision", "ram"), ("end_of_data", "end")],
)
def test_each_termination_flag(world_dir: Path, flag: str, where: str) -> None:
    env = _make(world_dir, "overtake", mode="eval").unwrapped
    env.reset_state(1)
    ego, other = env.sim.agents
    if where == "lateral":
        _place_ego(env, ego.arc_m, 3.0)
    elif where == "yaw":
        _place_ego(env, ego.arc_m, 0.0, 0.7)
    elif where == "ram":
        _place_ego(env, other.arc_m - 1.0, other.lateral_m)
    else:
        _place_ego(env, env.sim.reference.end_m - 3.0, 0.0)
    _, terminated, truncated, info = env.advance(np.zeros(1, np.float32))
    assert terminated and not truncated and info["termination"][flag]
    assert not info["success"]
    assert [k for k, v in info["termination"].items() if v] == [flag]


def test_training_overtake_goes_on_after_the_pass(world_dir: Path) -> None:
    """In training the episode outlives the pass, so R_pass is paid per step ahead; evaluation ends at the pass."""
    for seed in range(10):
        trained = _make(world_dir, "overtake", mode="train", episode_steps=300).unwrapped
        evaluated = _make(world_dir, "overtake", mode="eval", episode_steps=300).unwrapped
        trained.reset_state(seed)
        evaluated.reset_state(seed)
        eval_steps = 0
        while True:
            _, terminated, truncated, eval_info = evaluated.advance(evaluated.expert_action())
            eval_steps += 1
            if terminated or truncated:
                break
        if not eval_info["success"]:
            continue
        pass_rewards, steps = 0.0, 0
        while True:
            _, terminated, truncated, info = trained.advance(trained.expert_action())
            pass_rewards += info["rewards"]["pass"]
            steps += 1
            if terminated or truncated:
                break
        assert steps > eval_steps + 10  # it went on well past the step where evaluation ended it
        assert pass_rewards > 10.0  # and paid R_pass for the steps ahead
        assert info["success"] == (not any(info["termination"][k] for k in ("off_lane", "over_rotation", "collision")))
        return
    pytest.fail("the expert passed in none of 10 episodes")


def test_time_limit_truncates(world_dir: Path) -> None:
    env = _make(world_dir, "lane", episode_steps=4)
    env.reset(seed=0)
    results = [env.step(np.zeros(1, np.float32)) for _ in range(4)]
    assert [r[3] for r in results] == [False, False, False, True]
    assert results[-1][4]["termination"]["time_limit"] and results[-1][4]["success"]


def test_expert_passes_the_front_car(world_dir: Path) -> None:
    """The privileged expert overtakes without intervention in most episodes (state only: no rendering needed)."""
    env = _make(world_dir, "overtake", mode="eval").unwrapped
    successes = 0
    for seed in range(30):
        env.reset_state(seed)
        while True:
            _, terminated, truncated, info = env.advance(env.expert_action())
            if terminated or truncated:
                break
        successes += info["success"]
        if info["success"]:
            assert info["state"]["pass_margin_m"] > env.config.pass_distance_m
    assert successes >= 24


def _assert_same_steps(a: VecEnv, b: VecEnv, actions: np.ndarray, steps: int = 5) -> None:
    """Both vector envs step to the same observations, rewards, dones, states and terminal observations."""
    for _ in range(steps):  # 5 steps cross a 4-step time limit: automatic reset with terminal_observation
        obs_a, rew_a, done_a, info_a = a.step(actions)
        obs_b, rew_b, done_b, info_b = b.step(actions)
        assert np.array_equal(obs_a, obs_b) and np.allclose(rew_a, rew_b) and np.array_equal(done_a, done_b)
        for ia, ib in zip(info_a, info_b, strict=True):
            assert ia["state"] == pytest.approx(ib["state"], nan_ok=True)
            assert ("terminal_observation" in ia) == ("terminal_observation" in ib)
            if "terminal_observation" in ib:
                assert np.array_equal(ia["terminal_observation"], ib["terminal_observation"])


def test_batched_vec_env_equals_single_envs(world_dir: Path) -> None:
    config = {**SMALL_VIEW, "episode_steps": 4}
    batched = BatchedVecEnv("overtake", 2, str(world_dir), None, "train", config, seed=7)
    single = DummyVecEnv([lambda: _make(world_dir, "overtake", episode_steps=4) for _ in range(2)])
    single.seed(7)
    assert np.array_equal(batched.reset(), single.reset())
    actions = np.array([[0.2], [-0.4]], np.float32)
    _assert_same_steps(batched, single, actions)
    assert batched.expert_actions().shape == (2, 1)


def test_process_batched_vec_env_equals_one_batched_env(world_dir: Path) -> None:
    """Episodes split over two worker processes give what one BatchedVecEnv of them all gives (episode i: seed
    7 + i)."""
    config = {**SMALL_VIEW, "episode_steps": 4}
    one = BatchedVecEnv("overtake", 3, str(world_dir), None, "train", config, seed=7)
    split = ProcessBatchedVecEnv("overtake", 3, str(world_dir), None, "train", config, seed=7, workers=2)
    try:
        assert split.num_envs == 3 and split.observation_space == one.observation_space
        assert np.array_equal(split.reset(), one.reset())
        actions = np.array([[0.2], [-0.4], [0.0]], np.float32)
        _assert_same_steps(split, one, actions)
        assert np.array_equal(split.expert_actions(), one.expert_actions())
        assert split.get_attr("task") == ["overtake"] * 3
    finally:
        split.close()
    with pytest.raises(ValueError, match="too short"):
        ProcessBatchedVecEnv("overtake", 2, str(write_test_world(world_dir.parent / "short", length_m=40.0)), workers=2)


def test_bad_worlds_and_meshes_are_one_line(world_dir: Path, tmp_path: Path) -> None:
    short = write_test_world(tmp_path / "short", length_m=40.0)
    with pytest.raises(ValueError, match=r"world.json: path of 40 m is too short"):
        _make(short, "overtake")
    with pytest.raises(FileNotFoundError, match="no such meshes folder"):
        gymnasium.make(TASKS["overtake"], world=str(world_dir), meshes=str(tmp_path / "nope"), config=SMALL_VIEW)
    old = write_test_world(tmp_path / "old", length_m=100.0)
    (old / "world.json").write_text(json.dumps({**json.loads((old / "world.json").read_text()), "format": 0}))
    with pytest.raises(ValueError, match="world format 0"):
        _make(old, "lane")
    with pytest.raises(FileNotFoundError, match="frames.npy: missing"):
        _make(tmp_path / "nothing", "lane")


def test_a_front_car_past_the_sure_road_is_refused(world_dir: Path) -> None:
    # 150 m ahead on a drive with 60 m sure: every episode would end at its first step with end_of_data
    for task in ("overtake", "follow"):
        with pytest.raises(ValueError, match=r"front_distance_m up to 150 m .* past the 60 m of road"):
            _make(world_dir, task, front_distance_m=(140.0, 150.0))
    env = _make(world_dir, "overtake", front_distance_m=(50.0, 60.0))  # within it: episodes run
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.zeros(1, np.float32))
    assert not info["termination"]["end_of_data"]
    _make(world_dir, "lane", front_distance_m=(140.0, 150.0))  # no front car: the key is not read


def test_render_episode_writes_the_video_strip_and_plot(world_dir: Path, tmp_path: Path) -> None:
    """`drivesim sim render`'s work: an MP4 with every step, a strip of 80x50 frames and the bird's-eye PNG."""
    import cv2

    from drivesim.sim.envs.render_episode import render_episode

    summary = render_episode("overtake", world_dir, None, tmp_path / "out", seed=2)
    video = cv2.VideoCapture(str(tmp_path / "out" / "episode.mp4"))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == summary["steps"] + 1
    strip = cv2.imread(str(tmp_path / "out" / "strip.png"))
    assert strip.shape[0] == 50 and strip.shape[1] % 80 == 0 and strip.shape[1] >= 80
    assert cv2.imread(str(tmp_path / "out" / "birdseye.png")).shape[0] > 300


def test_augmentation_follows_its_formula() -> None:
    """Gamma, brightness and contrast per channel value, then saturation toward the grey value, rounded."""
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (2, 8, 10, 3), dtype=np.uint8)
    aug = Augmentation(gamma=1.3, brightness=0.05, contrast=1.2, saturation=0.6)
    v = ((image / 255.0) ** 1.3 + 0.05 - 0.5) * 1.2 + 0.5
    toned = np.clip(np.rint(v * 255.0), 0, 255)
    grey = toned @ np.array([0.299, 0.587, 0.114])
    expected = np.clip(np.rint(grey[..., None] + 0.6 * (toned - grey[..., None])), 0, 255)
    out = aug.apply(image)
    assert out.dtype == np.uint8 and out.shape == image.shape
    assert np.abs(out.astype(int) - expected).max() <= 1
    assert Augmentation().apply(image) is image  # the identity draw costs nothing
    grey_only = Augmentation(saturation=0.0).apply(image)
    assert np.abs(grey_only.astype(int) - grey_only[..., :1]).max() <= 1  # no saturation: grey


def test_a_mirrored_episode_flips_the_image_and_the_steering(world_dir: Path) -> None:
    """mirror_probability 1: the policy sees the plain episode's image flipped left to right, its steering +a moves
    the ego as -a does in the plain episode, the expert's label and the lane position are negated; evaluation is
    never mirrored."""
    still = STILL
    plain, mirrored = _make(world_dir, "lane", **still), _make(world_dir, "lane", **still, mirror_probability=1.0)
    obs_plain, _ = plain.reset(seed=5)
    obs_mirrored, _ = mirrored.reset(seed=5)
    assert np.abs(obs_plain.astype(int) - obs_plain[:, :, ::-1]).max() > 0  # the view is not symmetric
    np.testing.assert_array_equal(obs_mirrored, obs_plain[:, :, ::-1])
    np.testing.assert_allclose(mirrored.unwrapped.expert_action(), -plain.unwrapped.expert_action())
    for _ in range(4):
        obs_plain, *_, info_plain = plain.step(np.array([-0.5], np.float32))
        obs_mirrored, *_, info_mirrored = mirrored.step(np.array([0.5], np.float32))
    assert info_plain["state"]["q_lat_m"] < -0.05  # steered right of the centre line
    assert info_mirrored["state"]["q_lat_m"] == info_plain["state"]["q_lat_m"]
    np.testing.assert_array_equal(obs_mirrored, obs_plain[:, :, ::-1])
    # the lane position (lane_aux's target) is the state's, mirrored with the picture
    state = info_plain["state"]
    np.testing.assert_allclose(plain.unwrapped.lane_position(), [state["q_lat_m"], state["q_rot_rad"]], rtol=1e-6)
    np.testing.assert_allclose(mirrored.unwrapped.lane_position(), -plain.unwrapped.lane_position())
    evaluation = _make(world_dir, "lane", "eval", **still, mirror_probability=1.0)
    np.testing.assert_array_equal(evaluation.reset(seed=5)[0], plain.reset(seed=5)[0])


def test_view_jitter_shifts_blurs_and_adds_noise() -> None:
    """A pitch shifts the image by whole rows (edge rows repeated), a blur keeps the mean and lowers the spread, the
    noise has the asked standard deviation and is new at every call; nothing asked, nothing done."""
    rng = np.random.default_rng(1)
    image = rng.integers(40, 216, (16, 24, 3), dtype=np.uint8)
    shifted = ViewJitter(shift_rows=2.0).apply(image)
    np.testing.assert_array_equal(shifted[2:], image[:-2])
    np.testing.assert_array_equal(shifted[:2], image[:1].repeat(2, axis=0))
    blurred = ViewJitter(blur_sigma_px=1.5).apply(image).astype(float)
    assert abs(blurred.mean() - image.mean()) < 2.0 and blurred.std() < 0.6 * image.std()
    noisy = ViewJitter(noise_std=0.05, noise_rng=np.random.default_rng(0))
    first, second = noisy.apply(image).astype(float), noisy.apply(image).astype(float)
    assert 0.045 * 255 < np.std(first - image) < 0.055 * 255
    assert np.abs(first - second).max() > 0  # sensor noise changes from step to step
    assert ViewJitter().apply(image) is image


def test_cutout_erases_its_rectangles_to_one_colour_each_and_moves_them_every_step() -> None:
    """cutout_count (2, 2): each call changes two rectangles of the asked size range (no more of the image), each to
    one colour, in new places at the next call; a range of (0, 0) leaves the image as it is."""
    image = np.full((40, 60, 3), 128, np.uint8)
    jitter = ViewJitter(cutout_count=(2, 2), cutout_size=(0.2, 0.3), noise_rng=np.random.default_rng(0))
    first, second = jitter.apply(image), jitter.apply(image)
    for out in (first, second):
        changed = np.any(out != image, axis=2)
        assert 0 < changed.mean() <= 2 * 0.3 * 0.3 + 1e-9  # at most two rectangles of at most 30 % x 30 %
        assert len(np.unique(out[changed], axis=0)) <= 2  # one colour per rectangle
    assert np.any(first != second)  # redrawn at every step
    np.testing.assert_array_equal(image, 128)  # the input is left alone
    assert ViewJitter(cutout_count=(0, 0)).apply(image) is image


def test_a_training_episode_with_cutout_sees_erased_rectangles_and_evaluation_never(world_dir: Path) -> None:
    """cutout_count (1, 1): each training observation differs from the plain episode's (the same start state, the
    same photometric draw) in one rectangle, a new one at each step; an evaluation episode is the plain one."""
    still = STILL
    cut = {"cutout_count": (1, 1), "cutout_size": (0.3, 0.3)}
    plain, erased = _make(world_dir, "lane", **still), _make(world_dir, "lane", **still, **cut)
    obs_plain, info_plain = plain.reset(seed=3)
    obs_erased, info_erased = erased.reset(seed=3)
    assert info_erased["episode"] == info_plain["episode"]
    masks = []
    for _ in range(2):
        changed = np.any(obs_erased != obs_plain, axis=0)
        rows, cols = np.nonzero(changed)
        assert changed.any() and changed.mean() <= 0.3 * 0.3 + 0.02  # one rectangle of 30 % x 30 % (rounded)
        assert (rows.max() - rows.min() + 1) * (cols.max() - cols.min() + 1) <= changed.size * 0.1
        masks.append(changed)
        action = np.array([0.0], np.float32)
        obs_plain, obs_erased = plain.step(action)[0], erased.step(action)[0]
    assert not np.array_equal(masks[0], masks[1])  # redrawn at every step
    evaluation = _make(world_dir, "lane", "eval", **still, **cut)
    np.testing.assert_array_equal(
        evaluation.reset(seed=5)[0], _make(world_dir, "lane", "eval", **still).reset(seed=5)[0]
    )


def test_cutout_sizes_outside_zero_to_one_are_refused() -> None:
    """cutout_size is a fraction of the image's sides: 0 or above 1 is refused with the key named."""
    from drivesim.sim.envs.config import EnvConfig

    for bad in ((0.0, 0.5), (0.2, 1.5)):
        with pytest.raises(ValueError, match="cutout_size"):
            EnvConfig(cutout_size=bad)


def test_a_pitched_episode_sees_its_view_shifted_and_evaluation_never(world_dir: Path) -> None:
    """pitch_jitter_deg: the training observation is the plain episode's shifted by the drawn pitch's rows (the same
    start state: the draw comes last), within the asked angle at the image's focal length; evaluation is unchanged."""
    still = STILL
    plain, pitched = _make(world_dir, "lane", **still), _make(world_dir, "lane", **{**still, "pitch_jitter_deg": 4.0})
    shifts = []
    for seed in range(6):
        obs_plain, info_plain = plain.reset(seed=seed)
        obs_pitched, info_pitched = pitched.reset(seed=seed)
        assert info_pitched["episode"] == info_plain["episode"]
        jitter = pitched.unwrapped._jitter
        expected = ViewJitter(shift_rows=jitter.shift_rows).apply(obs_plain.transpose(1, 2, 0)).transpose(2, 0, 1)
        np.testing.assert_array_equal(obs_pitched, expected)
        shifts.append(jitter.shift_rows)
    env = pitched.unwrapped
    focal_rows_px = float(env.worlds[0].K[1, 1]) * env.config.observation_height_px / env.roi_px_of(0)[3]
    assert max(abs(s) for s in shifts) <= focal_rows_px * np.tan(np.radians(4.0)) + 1e-9
    assert min(abs(s) for s in shifts) < max(abs(s) for s in shifts)  # drawn per episode
    evaluation = _make(world_dir, "lane", "eval", **{**still, "pitch_jitter_deg": 4.0})
    np.testing.assert_array_equal(evaluation.reset(seed=5)[0], plain.reset(seed=5)[0])


def test_grey_episodes_come_at_their_rate_and_leave_other_draws_alone() -> None:
    """grey_probability p makes about p of the training episodes grey; p = 0 draws exactly as before."""
    ranges = ((0.8, 1.25), (-0.1, 0.1), (0.8, 1.2), (0.7, 1.3))
    rng_a, rng_b = np.random.default_rng(3), np.random.default_rng(3)
    assert Augmentation.sample(rng_a, *ranges) == Augmentation.sample(rng_b, *ranges, grey_probability=0.0)
    rng = np.random.default_rng(0)
    draws = [Augmentation.sample(rng, *ranges, grey_probability=0.3) for _ in range(2000)]
    grey = np.mean([d.saturation == 0.0 for d in draws])
    assert 0.26 < grey < 0.34
    assert all(0.7 <= d.saturation <= 1.3 for d in draws if d.saturation != 0.0)
