"""The lateral probe (issue 19): views labelled as the picture shows them, scores that tell a read offset from a flat
one, and a fit that learns the offset on a small world."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch
from sim_worlds import SMALL_VIEW, write_test_world

import drivesim.sim.envs  # noqa: F401  (registers the envs)
from drivesim.stages.train.config import PolicyConfig

# The probe is research code in experiments/ (not installed), imported from its folder.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments" / "lateral_probe"))
from lateral_probe import blank_view_part, fit_probe, fit_readout, render_views, score_probe  # noqa: E402

# Photometric augmentation off, so that a mirrored view can be compared with the plain one pixel for pixel.
# The lane task trains with a jittered, blurred and noisy camera by default: off here, so pictures compare exactly.
NO_PHOTOMETRY = {
    "gamma": (1.0, 1.0),
    "brightness": (0.0, 0.0),
    "contrast": (1.0, 1.0),
    "saturation": (1.0, 1.0),
    "pitch_jitter_deg": 0.0,
    "blur_sigma_px": (0.0, 0.0),
    "noise_std": (0.0, 0.0),
}


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory) -> str:
    """The small test world with two white lane lines painted on its ground, 1.75 m to either side of the path."""
    root = write_test_world(tmp_path_factory.mktemp("probe-world") / "world")
    camera = json.loads((root / "camera.json").read_text())
    K, frames, depth_m = np.array(camera["K"]), np.load(root / "frames.npy"), np.load(root / "depth_m.npy")
    u = np.arange(frames.shape[2])[None, None, :] + 0.5
    right_m = (u - K[0, 2]) * depth_m / K[0, 0]  # a ground point's distance to the right of the camera
    ground = depth_m < 29.0
    line = ground & (np.abs(np.abs(right_m) - 1.75) < 0.15)
    frames[line] = 250
    np.save(root / "frames.npy", frames)
    return str(root)


def _lane_env(world: str, mode: str, **config: object) -> gymnasium.Env:
    full = {**SMALL_VIEW, "min_path_length_m": 30.0, **NO_PHOTOMETRY, **config}
    return gymnasium.make("drivesim/Lane-v0", world=world, meshes=None, mode=mode, config=full).unwrapped


def test_a_placed_ego_sees_and_reports_its_offset_mirrored_with_the_picture(world: str) -> None:
    plain, mirrored = _lane_env(world, "eval"), _lane_env(world, "train", mirror_probability=1.0)
    plain.reset_state(3)
    mirrored.reset_state(3)
    seen = plain.place_ego(60.0, 1.2, 0.1)
    seen_mirrored = mirrored.place_ego(60.0, 1.2, 0.1)
    np.testing.assert_allclose(plain.lane_position(), [1.2, 0.1], atol=0.05)
    np.testing.assert_allclose(mirrored.lane_position(), [-1.2, -0.1], atol=0.05)
    np.testing.assert_array_equal(seen_mirrored, seen[:, :, ::-1])
    # the view moves with the ego: another offset is another picture
    assert np.abs(plain.place_ego(60.0, -1.2, 0.1).astype(int) - seen).mean() > 5


def test_the_scores_tell_a_read_offset_from_a_flat_one() -> None:
    rng = np.random.default_rng(0)
    labels = np.stack([rng.uniform(-2.5, 2.5, 400), rng.uniform(-0.2, 0.2, 400)], axis=1).astype(np.float32)
    images = np.zeros((400, 3, 4, 4), np.uint8)
    read = score_probe(lambda x: torch.from_numpy(labels * np.array([1.0, 10.0], np.float32)), images, labels, 2.5)
    flat = score_probe(lambda x: torch.full((len(x), 2), 0.4), images, labels, 2.5)
    assert read["offset_mae_m"] < 1e-6 and read["offset_slope"] == pytest.approx(1.0) and read["side_right"] == 1.0
    assert read["yaw_corr"] == pytest.approx(1.0) and read["offset_per_heading_m_per_rad"] == pytest.approx(
        0.0, abs=1e-6
    )
    # an offset read as the heading: 3 m of read offset per radian of heading, and none of the true offset
    confused = score_probe(
        lambda x: torch.from_numpy(labels[:, ::-1] * np.array([3.0, 0.0], np.float32)), images, labels, 2.5
    )
    assert (
        confused["offset_per_heading_m_per_rad"] == pytest.approx(3.0, rel=1e-4)
        and abs(confused["offset_slope"]) < 0.05
    )
    assert abs(flat["offset_slope"]) < 1e-6 and flat["offset_corr"] == 0.0 and flat["offset_mae_m"] > 1.0
    assert flat["binned_m"] == pytest.approx([0.4] * 10)
    assert 0.3 < flat["side_right"] < 0.7  # one side right, the other wrong


def test_the_probe_learns_the_offset_on_its_own_world(world: str) -> None:
    config = {**SMALL_VIEW, **NO_PHOTOMETRY}
    images, labels = render_views(world, config, "train", 800, seed=1, offset_m=2.5, yaw_rad=0.2)
    assert images.shape == (800, 3, 16, 40) and np.abs(labels[:, 0]).max() <= 2.6
    net = fit_probe(
        images, labels, epochs=15, seed=0, policy=PolicyConfig(conv_layers=[(8, 5, 2), (16, 3, 2)], input_pool=1)
    )
    test_images, test_labels = render_views(world, config, "eval", 300, seed=9, offset_m=2.5, yaw_rad=0.2)
    scores = score_probe(net, test_images, test_labels, 2.5)
    assert scores["offset_mae_m"] < 0.6  # a constant guess scores 1.25 m
    assert scores["offset_slope"] > 0.7 and scores["side_right"] > 0.9
    # a trained encoder, frozen, read by a fitted linear readout (how a policy's own encoder is probed)
    encoder = net[0]
    weights = [p.clone() for p in encoder.parameters()]
    readout = fit_readout(encoder, images, labels)
    assert all(torch.equal(a, b) for a, b in zip(weights, encoder.parameters(), strict=True))
    read = score_probe(readout, test_images, test_labels, 2.5)
    assert read["offset_mae_m"] < 0.6 and read["offset_slope"] > 0.7


def test_a_blanked_half_is_black_and_the_other_half_untouched(world: str) -> None:
    env = _lane_env(world, "eval")
    env.reset_state(3)
    views = np.stack([env.place_ego(60.0, offset_m, 0.0) for offset_m in (-1.0, 1.0)])
    half = views.shape[2] // 2
    road_only, beyond_only = blank_view_part(views, "top"), blank_view_part(views, "bottom")
    assert not road_only[:, :, :half].any() and not beyond_only[:, :, half:].any()
    np.testing.assert_array_equal(road_only[:, :, half:], views[:, :, half:])
    np.testing.assert_array_equal(beyond_only[:, :, :half], views[:, :, :half])
    assert views[:, :, :half].any() and views[:, :, half:].any()  # both halves had something to blank
    assert blank_view_part(views, None) is views
    with pytest.raises(ValueError, match="top, bottom"):
        blank_view_part(views, "left")
