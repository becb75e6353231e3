"""The camera's look on inserted cars: blended edges, the frame's blur and noise measured and given to the car."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from drivesim.sim.camera_look import (
    EDGE_SIGMA_PX,
    CameraLook,
    apply_camera_look_,
    frame_blur_sigma,
    frame_noise_sigma,
    look_of_frames,
)
from drivesim.sim.view import CarPlacement, ViewConfig, ViewSynthesizer
from tests.test_view import box_model, make_world, render_one


def _blocks(seed: int = 0, size: tuple[int, int] = (240, 320)) -> np.ndarray:
    """A sharp uint8 test frame: flat rectangles of random grey levels (step edges, no noise)."""
    rng = np.random.default_rng(seed)
    image = np.full(size, 120.0, dtype=np.float32)
    for _ in range(60):
        y, x = rng.integers(0, size[0] - 10), rng.integers(0, size[1] - 10)
        image[y : y + rng.integers(8, 60), x : x + rng.integers(8, 80)] = rng.uniform(0, 255)
    return image


def _car_on_black(size: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """A white 20 x 12 px 'car' on a black uint8 view, and its mask."""
    rgb = np.zeros((size, size, 3), dtype=np.uint8)
    mask = np.zeros((size, size), dtype=bool)
    mask[10:22, 10:30] = True
    rgb[mask] = 255
    return rgb, mask


@pytest.mark.parametrize("sigma", [1.0, 2.0])
def test_blur_estimate_finds_the_blur_of_a_blurred_frame(sigma):
    blurred = cv2.GaussianBlur(_blocks(), (0, 0), sigma)
    assert frame_blur_sigma(np.rint(blurred).astype(np.uint8)) == pytest.approx(sigma, abs=0.3)
    assert frame_blur_sigma(np.rint(_blocks()).astype(np.uint8)) < 0.5, "a point-sampled frame is sharp"


@pytest.mark.parametrize("sigma", [2.0, 5.0])
def test_noise_estimate_finds_the_noise_added_to_a_frame_with_edges(sigma):
    rng = np.random.default_rng(1)
    noisy = np.clip(_blocks() + rng.normal(0.0, sigma, (240, 320)), 0, 255).astype(np.uint8)
    assert frame_noise_sigma(noisy) == pytest.approx(sigma, rel=0.2)
    assert frame_noise_sigma(np.rint(_blocks()).astype(np.uint8)) < 0.5


def test_edge_pixels_become_blends_and_far_pixels_stay():
    rgb, mask = _car_on_black()
    apply_camera_look_(rgb, mask, CameraLook(blur_sigma_px=EDGE_SIGMA_PX, noise_sigma=0.0))
    gray = rgb[..., 0].astype(int)
    edge_inside = mask & ~cv2.erode(mask.view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))  # side neighbours (a corner's diagonal gets little)
    edge_outside = cv2.dilate(mask.view(np.uint8), cross).astype(bool) & ~mask
    assert ((gray[edge_inside] > 20) & (gray[edge_inside] < 235)).all(), "the car's rim is a blend"
    assert ((gray[edge_outside] > 20) & (gray[edge_outside] < 235)).all(), "the background's rim is a blend"
    assert (gray[14:18, 14:26] == 255).all(), "the car's middle keeps its colour"
    far = ~cv2.dilate(mask.view(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert (gray[far] == 0).all(), "pixels two away from the car are not touched"


def test_grain_has_the_asked_spread_on_the_car_only_and_keeps_gray_gray():
    rgb = np.full((80, 80, 3), 100, dtype=np.uint8)
    mask = np.zeros((80, 80), dtype=bool)
    mask[10:70, 10:70] = True
    apply_camera_look_(rgb, mask, CameraLook(blur_sigma_px=0.0, noise_sigma=4.0))
    car = rgb[mask].astype(float)
    assert car[:, 0].std() == pytest.approx(4.0, rel=0.15)
    assert abs(car[:, 0].mean() - 100.0) < 0.5
    assert (rgb[..., 0] == rgb[..., 1]).all() and (rgb[..., 1] == rgb[..., 2]).all(), "a gray car stays gray"
    assert (rgb[~mask] == 100).all()
    again = np.full((80, 80, 3), 100, dtype=np.uint8)
    apply_camera_look_(again, mask, CameraLook(blur_sigma_px=0.0, noise_sigma=4.0))
    assert np.array_equal(again, rgb), "the same inputs give the same view"


def test_look_of_a_drive_is_the_median_of_its_frames():
    rng = np.random.default_rng(2)
    frames = np.stack(
        [np.repeat(np.clip(_blocks(i) + rng.normal(0, 3.0, (240, 320)), 0, 255)[..., None], 3, -1) for i in range(5)]
    ).astype(np.uint8)
    look = look_of_frames(frames, scale=0.5)
    assert look.noise_sigma == pytest.approx(3.0, rel=0.2)
    halved = look_of_frames(frames, factor=2)
    assert halved.noise_sigma == pytest.approx(1.5, rel=0.25), "a 2 x 2 block mean halves the noise"


def test_view_with_camera_look_blends_the_cars_edges_and_without_keeps_them_hard(tmp_path):
    world = make_world(tmp_path)
    cars = [CarPlacement(box_model(rgb=(0.9, 0.9, 0.9)), 10.0, 0.0, 0.0)]
    hard = render_one(ViewSynthesizer(world, ViewConfig(camera_look=False, harmonization=False)), cars)
    soft_vs = ViewSynthesizer(world, ViewConfig(camera_look=True, harmonization=False))
    soft = render_one(soft_vs, cars)
    assert soft_vs.camera_look.noise_sigma > 1.0, "the test world's frames carry noise"
    mask = hard.car_mask[0]
    assert np.array_equal(soft.car_mask[0], mask)
    rim = cv2.dilate(mask.view(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & ~mask
    changed = np.abs(soft.rgb[0].astype(int) - hard.rgb[0].astype(int)).max(axis=-1)
    assert (changed[rim] > 0).mean() > 0.9, "the background's rim takes some of the car"
    far = ~cv2.dilate(mask.view(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    assert (changed[far] == 0).all()
    inner = cv2.erode(mask.view(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    assert soft.rgb[0][inner][:, 0].astype(float).std() > hard.rgb[0][inner][:, 0].astype(float).std() + 0.5


def test_grain_on_a_car_larger_than_the_noise_tile_has_the_asked_spread():
    rgb = np.full((300, 400, 3), 100, dtype=np.uint8)
    mask = np.zeros((300, 400), dtype=bool)
    mask[5:290, 7:395] = True
    apply_camera_look_(rgb, mask, CameraLook(blur_sigma_px=0.0, noise_sigma=3.0))
    assert rgb[mask][:, 0].astype(float).std() == pytest.approx(3.0, rel=0.1)
    assert abs(rgb[mask][:, 0].astype(float).mean() - 100.0) < 0.3
