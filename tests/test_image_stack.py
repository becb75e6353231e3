"""Image stacks (sim/image_stack.py): the compressed per-frame storage of trace frames, preprocessed depth and the
world's frames and depth. Lossless codecs give back the same arrays, JPEG at quality 97 stays close, reads are per
frame, damage is one clear error, and worlds and traces written as .npy by earlier versions still load."""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import numpy as np
import pytest
from sim_worlds import write_test_world

from drivesim.sim.image_stack import ImageStack, ImageStackError, ImageStackWriter, read_meta
from drivesim.sim.world import World


def _scene_frames(n: int, h: int = 48, w: int = 64) -> np.ndarray:
    """Smooth colour gradients with a moving edge, like road scenes (JPEG's error stays small on them)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    frames = np.empty((n, h, w, 3), np.uint8)
    for i in range(n):
        frames[i, ..., 0] = np.clip(40 + 3 * x + 5 * i, 0, 255)
        frames[i, ..., 1] = np.clip(90 + 2 * y, 0, 255)
        frames[i, ..., 2] = np.where(x > 20 + i, 200, 60)
    return frames


def _write(path: Path, frames: np.ndarray, codec: str) -> ImageStack:
    writer = ImageStackWriter(path, frames.shape[1:], frames.dtype, codec)
    for frame in frames:
        writer.write(frame)
    writer.close()
    return ImageStack(path)


def _psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return 10.0 * np.log10(255.0**2 / mse)


def test_png_frames_and_float16_depth_come_back_bit_for_bit(tmp_path: Path) -> None:
    frames = _scene_frames(5)
    stack = _write(tmp_path / "frames.imgs", frames, "png")
    assert stack.shape == frames.shape and stack.dtype == np.uint8
    np.testing.assert_array_equal(np.asarray(stack), frames)
    depth = np.linspace(0.5, 80.0, 5 * 48 * 64).reshape(5, 48, 64).astype(np.float16)
    depth[0, 0, :3] = [np.inf, np.nan, 65504.0]  # sky, no estimate, float16's largest: their bits survive
    loaded = _write(tmp_path / "depth.imgs", depth, "png")
    for i in range(5):
        np.testing.assert_array_equal(loaded[i].view(np.uint16), depth[i].view(np.uint16))
    assert loaded[2].dtype == np.float16 and loaded[2].shape == (48, 64)


def test_jpeg_frames_stay_close_and_are_several_times_smaller(tmp_path: Path) -> None:
    frames = _scene_frames(4, 96, 128)
    stack = _write(tmp_path / "frames.imgs", frames, "jpeg")
    assert read_meta(stack.path)[0]["quality"] == 97
    assert min(_psnr_db(stack[i], frames[i]) for i in range(4)) > 38.0
    assert stack.path.stat().st_size < frames.nbytes / 4


def test_indexing_is_per_frame_and_slices_stay_lazy(tmp_path: Path) -> None:
    frames = _scene_frames(10)
    stack = _write(tmp_path / "frames.imgs", frames, "png")
    view = stack[2:9:3]  # frames 2, 5, 8, not decoded yet
    assert isinstance(view, ImageStack) and view.shape == (3, 48, 64, 3) and len(view) == 3
    np.testing.assert_array_equal(view[1], frames[5])
    np.testing.assert_array_equal(view[-1], frames[8])
    np.testing.assert_array_equal(stack[np.array([7, 1])], frames[[7, 1]])
    np.testing.assert_array_equal(stack[4, ::2, 1:3], frames[4, ::2, 1:3])  # (frame, rows, cols) as a memmap
    np.testing.assert_array_equal(stack[[1, 6], 5:, :7], frames[[1, 6], 5:, :7])
    np.testing.assert_array_equal(stack[3:5, :, :, 0], frames[3:5, :, :, 0])
    np.testing.assert_array_equal(np.stack(list(view)), frames[2:9:3])
    with pytest.raises(IndexError):
        stack[10]
    again = pickle.loads(pickle.dumps(view))  # to worker processes: reopened by path
    np.testing.assert_array_equal(again[2], frames[8])


def test_an_unfinished_or_truncated_stack_is_refused(tmp_path: Path) -> None:
    frames = _scene_frames(3)
    writer = ImageStackWriter(tmp_path / "cut.imgs", frames.shape[1:], np.uint8, "jpeg")
    writer.write(frames[0])
    writer.abort()  # a write that stopped half-way: no index
    with pytest.raises(ImageStackError, match="not a finished image stack"):
        ImageStack(tmp_path / "cut.imgs")
    path = _write(tmp_path / "frames.imgs", frames, "jpeg").path
    data = path.read_bytes()
    path.write_bytes(data[:20] + data[-200:])
    with pytest.raises(ImageStackError, match="cut.imgs|frames.imgs"):
        ImageStack(path)[1]
    with pytest.raises(ValueError, match="jpeg stores RGB"):
        ImageStackWriter(tmp_path / "d.imgs", (4, 4), np.uint8, "jpeg")


def _world_with_stacks(tmp_path: Path) -> tuple[Path, np.ndarray, np.ndarray]:
    """A small world in the .npy layout of earlier versions, and a copy with its frames and depth as image stacks."""
    old = write_test_world(tmp_path / "old", length_m=20.0)
    frames = np.load(old / "frames.npy")
    depth = np.load(old / "depth_m.npy")
    new = tmp_path / "new"
    new.mkdir()
    for name in ("camera.json", "path.npz", "world.json"):
        (new / name).write_bytes((old / name).read_bytes())
    _write(new / "frames.imgs", frames, "png")
    _write(new / "depth_m.imgs", depth.astype(np.float16), "png")
    return old, frames, depth


def test_a_world_loads_from_image_stacks_and_from_the_older_npy_files(tmp_path: Path) -> None:
    old, frames, depth = _world_with_stacks(tmp_path)
    before, after = World.load(old), World.load(tmp_path / "new")
    assert after.frames.shape == before.frames.shape and after.depth_m.shape == before.depth_m.shape
    i = len(frames) // 2
    np.testing.assert_array_equal(after.depth_m[i], depth[i].astype(np.float16))  # lossless
    np.testing.assert_array_equal(after.frames[i], frames[i])
    np.testing.assert_array_equal(after.frames[i], before.frames[i])
    assert after.frames[i].dtype == np.uint8 and after.frames[i].flags.c_contiguous


def test_a_damaged_world_stack_is_one_line_naming_it(tmp_path: Path) -> None:
    _world_with_stacks(tmp_path)
    root = tmp_path / "new"
    (root / "depth_m.imgs").write_bytes(b"not a stack")
    with pytest.raises(ValueError, match=r"depth_m.imgs: not a readable frame array .*rebuild the world"):
        World.load(root)
    meta = json.loads(json.dumps(read_meta(root / "frames.imgs")[0]))
    assert meta["codec"] == "png" and meta["dtype"] == "uint8"


def test_threads_reading_one_stack_get_the_frames_a_single_reader_gets(tmp_path: Path) -> None:
    from concurrent.futures import ThreadPoolExecutor

    frames = _scene_frames(16)
    stack = _write(tmp_path / "frames.imgs", frames, "png")
    order = np.random.default_rng(0).integers(0, 16, 200)
    with ThreadPoolExecutor(4) as pool:
        got = list(pool.map(lambda i: stack[int(i)], order))
    for i, frame in zip(order, got, strict=True):
        np.testing.assert_array_equal(frame, frames[i])
