"""The lateral-view stereo benchmark on a synthetic rectified pair whose answer is known: a textured wall."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivesim.bench.stereo import (
    IDENTITY,
    REFERENCE,
    read_stereo_folder,
    run_stereo_bench,
    view_metrics,
    warp_to_right,
)
from drivesim.pipeline.errors import InputError
from drivesim.stages.preprocess.config import StereoConfig
from drivesim.stages.preprocess.depth_stereo import stereo_frame_depth

FX_PX = 200.0
BASELINE_M = 0.5
W, H = 256, 96
K = np.array([[FX_PX, 0.0, (W - 1) / 2], [0.0, FX_PX, (H - 1) / 2], [0.0, 0.0, 1.0]])


def _texture(seed: int = 0) -> np.ndarray:
    noise = np.random.default_rng(seed).uniform(0, 255, (600, 2000)).astype(np.float32)
    return cv2.GaussianBlur(noise, (0, 0), 1.2)


def render_wall(texture: np.ndarray, depth_m: float, camera_x_m: float) -> np.ndarray:
    """RGB view of a fronto-parallel textured wall `depth_m` ahead, from a camera `camera_x_m` to the right."""
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    x_m = (u - K[0, 2]) * depth_m / FX_PX + camera_x_m
    y_m = (v - K[1, 2]) * depth_m / FX_PX
    map_x, map_y = (x_m * 100.0 + 1000.0).astype(np.float32), (y_m * 100.0 + 300.0).astype(np.float32)
    grey = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR)
    return np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=-1)


def _warp(left: np.ndarray, depth_m: float) -> tuple[np.ndarray, np.ndarray]:
    image, valid = warp_to_right(left, np.full((H, W), depth_m, np.float32), K, BASELINE_M)
    return image, valid


def test_a_warp_with_the_true_depth_reproduces_the_right_view() -> None:
    texture = _texture()
    left, right = render_wall(texture, 5.0, 0.0), render_wall(texture, 5.0, BASELINE_M)
    disparity_px = FX_PX * BASELINE_M / 5.0  # 20 px: whole pixels, no resampling
    image, valid = _warp(left, 5.0)
    true = view_metrics(image, right, valid)
    image, valid = _warp(left, 10.0)
    wrong = view_metrics(image, right, valid)
    identity = view_metrics(left, right, np.ones((H, W), bool))
    assert true["psnr_db"] > 35.0  # only resampling remains
    assert true["psnr_db"] > max(wrong["psnr_db"], identity["psnr_db"]) + 10.0
    # The right camera sees disparity_px columns on its right edge that the left one does not.
    assert true["filled_fraction"] == pytest.approx(1.0 - disparity_px / W, abs=0.02)
    assert true["psnr_all_db"] < true["psnr_db"] - 5.0  # the black holes count in the whole-image figure


def test_sgbm_finds_the_walls_depth_from_the_pair() -> None:
    texture = _texture(1)
    left, right = render_wall(texture, 8.0, 0.0), render_wall(texture, 8.0, BASELINE_M)
    plane = np.full((H, W), 80.0, np.float32)
    depth, matched = stereo_frame_depth(left, right, FX_PX, BASELINE_M, plane, 80.0, StereoConfig())
    assert matched > 0.7
    assert np.median(np.abs(depth[:, 40:] - 8.0)) < 0.2  # left border: no match, filled from the right


def write_wall_folder(folder: Path, n: int = 9) -> Path:
    """A KITTI-layout stereo drive towards the wall: 10 m away at frame 0, 0.5 m nearer each frame."""
    texture = _texture(2)
    for side in ("image_l", "image_r"):
        (folder / side).mkdir(parents=True)
    poses = []
    for i in range(n):
        depth_m = 10.0 - 0.5 * i
        cv2.imwrite(str(folder / "image_l" / f"{i:06d}.png"), render_wall(texture, depth_m, 0.0))
        cv2.imwrite(str(folder / "image_r" / f"{i:06d}.png"), render_wall(texture, depth_m, BASELINE_M))
        poses.append([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0.5 * i])
    P0 = np.hstack([K, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -FX_PX * BASELINE_M
    (folder / "calib.txt").write_text("".join(f"P{k}: {' '.join(f'{v:.6e}' for v in P.ravel())}\n"
                                              for k, P in enumerate((P0, P1))))  # fmt: skip
    np.savetxt(folder / "poses.txt", np.array(poses, float))
    return folder


def test_the_bench_ranks_the_true_pair_above_the_plane_and_the_identity(tmp_path: Path) -> None:
    write_wall_folder(tmp_path / "pair")
    drive = read_stereo_folder(tmp_path / "pair", width_px=W)
    assert drive.baseline_m == pytest.approx(BASELINE_M)
    result = run_stereo_bench(tmp_path / "pair", methods=("plane",), width_px=W, eval_width_px=W // 2,
                              figure_path=tmp_path / "worst.png")  # fmt: skip
    assert result.frames == [3, 4, 5]  # the frames with every mvs neighbour (offsets -3..3)
    reference, plane, identity = (result.row(n) for n in (REFERENCE, "plane", IDENTITY))
    assert reference.psnr_db > 30.0
    for wrong in (plane, identity):  # the plane puts the wall at the far depth, the identity at infinity
        assert reference.psnr_db > wrong.psnr_db + 4.0
        assert reference.ssim > wrong.ssim + 0.3
    assert (tmp_path / "worst.png").is_file()


def test_a_folder_without_right_images_is_refused(tmp_path: Path) -> None:
    write_wall_folder(tmp_path / "pair", n=2)
    for f in (tmp_path / "pair" / "image_r").iterdir():
        f.unlink()
    (tmp_path / "pair" / "image_r").rmdir()
    with pytest.raises(InputError, match="no right images"):
        read_stereo_folder(tmp_path / "pair")


def test_a_built_worlds_depth_is_a_row(tmp_path: Path) -> None:
    from sim_worlds import write_test_world

    write_wall_folder(tmp_path / "pair")
    world = write_test_world(tmp_path / "world", length_m=20.0)
    n = len(np.load(world / "path.npz")["frame_index"])
    true_depth_m = np.array([10.0 - 0.5 * min(i, 8) for i in range(n)], np.float32)[:, None, None]
    np.save(world / "depth_m.npy", np.broadcast_to(true_depth_m, (n, H // 2, W // 2)).copy())
    np.save(world / "frames.npy", np.zeros((n, H // 2, W // 2, 3), np.uint8))
    camera = json.loads((world / "camera.json").read_text())
    camera.update(width_px=W // 2, height_px=H // 2)
    (world / "camera.json").write_text(json.dumps(camera))
    result = run_stereo_bench(tmp_path / "pair", methods=("plane",), worlds=(world,), width_px=W, eval_width_px=W // 2)
    row = result.row(
        f"built world {tmp_path.name} (test)"
    )  # the world's true depth warps as well as the pair's own depth
    assert row.psnr_db > result.row("plane").psnr_db + 4.0
    assert row.psnr_db > result.row(REFERENCE).psnr_db - 1.0
