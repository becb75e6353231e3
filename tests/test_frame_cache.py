"""The view's prepared frames stored beside the world (sim/frame_cache.py): the same views to the bit as frames
prepared in memory, built once per world and view settings, never read when stale, never left half-written."""

from __future__ import annotations

import threading
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from sim_worlds import write_test_world
from test_view import box_model

from drivesim.sim import frame_cache
from drivesim.sim import view as view_module
from drivesim.sim.view import CarPlacement, ViewConfig, ViewSynthesizer
from drivesim.sim.world import World

# The test world's 80 x 50 image: a region of interest and policy image for which the source is halved (as the
# default view halves a 320 x 200 world) and widened by 10 px on each side from frames -1, -2, -3, +1.
SMALL = {"roi_px": (0, 10, 80, 40), "out_width_px": 40, "out_height_px": 20}


@pytest.fixture(autouse=True)
def _long_worlds(monkeypatch: pytest.MonkeyPatch) -> None:
    """The test worlds count as long: more frames than the view's memory cache holds, so the prepared frames are
    stored beside them."""
    monkeypatch.setattr(view_module, "_FRAME_CACHE_SIZE", 4)


def _world(tmp_path: Path, depth_dtype: type = np.float16) -> World:
    root = write_test_world(tmp_path / "world", length_m=60.0)
    depth = np.load(root / "depth_m.npy")
    np.save(root / "depth_m.npy", depth.astype(depth_dtype))
    return World.load(root)


def _render_drive(vs: ViewSynthesizer, frames: range) -> tuple[np.ndarray, np.ndarray]:
    """Views from every frame in `frames`, off the recorded path (left, turned) so that the margins show, a car
    ahead; (rgb, car mask) of all of them."""
    world, model = vs.world, box_model()
    rgbs, masks = [], []
    for k, frame in enumerate(frames):
        x, y, yaw = world.pose(frame)
        lateral, turn = 0.8 * np.sin(k), 0.25 * np.cos(0.7 * k)
        ax, ay = x - np.sin(yaw) * lateral, y + np.cos(yaw) * lateral
        car = CarPlacement(model, x + 9.0 * np.cos(yaw), y + 9.0 * np.sin(yaw), yaw)
        out = vs.render(np.array([frame]), np.array([ax]), np.array([ay]), np.array([yaw + turn]), [[car]])
        rgbs.append(out.rgb[0])
        masks.append(out.car_mask[0])
    return np.stack(rgbs), np.stack(masks)


def _without_cache(monkeypatch: pytest.MonkeyPatch, world: World, config: ViewConfig) -> ViewSynthesizer:
    with monkeypatch.context() as patch:
        patch.setattr(view_module, "open_prepared_frames", lambda *args, **kwargs: None)
        return ViewSynthesizer(world, config)


def _count_preparations(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    prepared: list[int] = []
    original = ViewSynthesizer._frame_arrays

    def counted(self: ViewSynthesizer, index: int) -> tuple[np.ndarray, ...]:
        prepared.append(index)
        return original(self, index)

    monkeypatch.setattr(ViewSynthesizer, "_frame_arrays", counted)
    return prepared


@pytest.mark.parametrize("depth_dtype", [np.float16, np.float32])
def test_views_from_the_cache_are_the_views_prepared_in_memory_to_the_bit(tmp_path, monkeypatch, depth_dtype):
    """Every view of a drive (off the path, turned, a car ahead) is the same, pixel for pixel and in its car mask,
    whether the frames come from the cache file or are prepared in memory; with a memory cache of 4 frames every
    frame is read from the file again and again, and no frame is prepared after the build."""
    world = _world(tmp_path, depth_dtype)
    config = ViewConfig(**SMALL)
    expected_rgb, expected_mask = _render_drive(_without_cache(monkeypatch, world, config), range(world.frame_count))
    monkeypatch.setattr(view_module, "_FRAME_CACHE_SIZE", 4)
    cached = ViewSynthesizer(world, config)
    assert cached._prepared is not None and cached.source_factor == 2 and cached.margin_px == 10
    prepared = _count_preparations(monkeypatch)
    for frames in (range(world.frame_count), range(world.frame_count)):  # the second pass reads evicted frames again
        rgb, mask = _render_drive(cached, frames)
        assert np.array_equal(rgb, expected_rgb)
        assert np.array_equal(mask, expected_mask)
    assert mask.any() and (rgb != expected_rgb[::-1]).any(), "the views must show the car and differ by frame"
    assert prepared == []


def test_the_cache_is_built_once_per_world_and_settings_and_stores_each_frame_compressed(tmp_path, monkeypatch):
    """A second synthesizer, or two made at the same time, prepare no frame again; the file holds two LZ4 blocks per
    frame (the widened rgb and its float16 depth) where the offsets say, smaller than the frames' raw bytes."""
    world = _world(tmp_path)
    prepared = _count_preparations(monkeypatch)
    made: list[ViewSynthesizer] = []
    threads = [threading.Thread(target=lambda: made.append(ViewSynthesizer(world, ViewConfig(**SMALL)))) for _ in "ab"]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(prepared) == list(range(world.frame_count))  # one build, by one of the two
    ViewSynthesizer(world, ViewConfig(**SMALL))
    assert len(prepared) == world.frame_count
    cache = made[0]._prepared
    layout = cache.layout
    assert (layout.height_px, layout.width_px, layout.margin_px) == (25, 40, 10)
    assert (layout.rgb_bytes, layout.depth_bytes) == (25 * 60 * 3, 25 * 60 * 2)

    folders = [p for p in (world.root / frame_cache.CACHE_DIR_NAME).iterdir() if p.is_dir()]
    assert len(folders) == 1
    stored = (folders[0] / "frames.bin").stat().st_size
    assert stored == cache.offsets[-1] and np.all(np.diff(cache.offsets) > 0)
    assert stored < 0.8 * world.frame_count * (layout.rgb_bytes + layout.depth_bytes)


def test_a_truncated_cache_file_is_refused(tmp_path):
    """A frames.bin shorter than its offsets say (a disk that filled, a copy cut short) is not read."""
    world = _world(tmp_path)
    folder = ViewSynthesizer(world, ViewConfig(**SMALL))._prepared.folder
    with open(folder / "frames.bin", "r+b") as f:
        f.truncate(int(np.load(folder / "offsets.npy")[-1]) - 1)
    with pytest.raises(OSError, match="its offsets say"):
        frame_cache.PreparedFrames(folder)


def test_a_changed_setting_or_world_is_never_served_a_stale_cache(tmp_path, monkeypatch):
    """Another margin gets its own cache; a world whose frames were rewritten gets a new one too, and its views are
    those of the new frames."""
    world = _world(tmp_path)
    first = ViewSynthesizer(world, ViewConfig(**SMALL))
    other = ViewSynthesizer(world, ViewConfig(**SMALL, source_margin=0.5))
    assert other._prepared.folder != first._prepared.folder and other.margin_px == 20
    frames = np.load(world.root / "frames.npy")
    np.save(world.root / "frames.npy", frames // 2)
    rewritten = World.load(world.root)
    fresh = ViewSynthesizer(rewritten, ViewConfig(**SMALL))
    assert fresh._prepared.folder not in (first._prepared.folder, other._prepared.folder)
    expected, _ = _render_drive(_without_cache(monkeypatch, rewritten, ViewConfig(**SMALL)), range(0, 40, 7))
    got, _ = _render_drive(fresh, range(0, 40, 7))
    assert np.array_equal(got, expected)
    old, _ = _render_drive(first, range(0, 40, 7))  # the first cache's views: the frames before they were rewritten
    assert old.mean() - got.mean() > 40


def test_a_build_that_fails_leaves_nothing_and_the_next_one_completes(tmp_path, monkeypatch):
    """A frame that cannot be prepared stops the build with its own error and leaves no cache, complete or not; the
    next synthesizer builds it whole."""
    world = _world(tmp_path)
    original = ViewSynthesizer._frame_arrays

    def broken(self: ViewSynthesizer, index: int) -> tuple[np.ndarray, ...]:
        if index == 17:
            raise RuntimeError("frame 17 is damaged")
        return original(self, index)

    with monkeypatch.context() as patch:
        patch.setattr(ViewSynthesizer, "_frame_arrays", broken)
        with pytest.raises(RuntimeError, match="frame 17"):
            ViewSynthesizer(world, ViewConfig(**SMALL))
    cache_dir = world.root / frame_cache.CACHE_DIR_NAME
    assert [p for p in cache_dir.iterdir() if p.is_dir()] == []
    vs = ViewSynthesizer(world, ViewConfig(**SMALL))
    assert vs._prepared.frame_count == world.frame_count
    assert vs._prepared.read(17)[0].shape == (25, 60, 3)


def test_a_folder_that_cannot_hold_the_cache_prepares_in_memory(tmp_path):
    """Where the cache folder cannot be made (here a file has its name) or for an in-memory world, frames are prepared
    in memory and the views are made all the same."""
    world = _world(tmp_path)
    (world.root / frame_cache.CACHE_DIR_NAME).write_text("not a folder")
    vs = ViewSynthesizer(world, ViewConfig(**SMALL))
    assert vs._prepared is None
    rgb, _ = _render_drive(vs, range(0, 40, 13))
    assert rgb.max() > 0


def test_a_long_drive_keeps_only_the_frames_in_use_in_memory(tmp_path, monkeypatch):
    """With a memory cache of 4 frames, driving through all 61 frames leaves at most the records of those 4 frames
    (and the neighbours a view's fill may hold) alive in the process, not the whole file: counted by tracemalloc,
    which sees numpy's buffers, at the line that reads a record."""
    world = _world(tmp_path)
    monkeypatch.setattr(view_module, "_FRAME_CACHE_SIZE", 4)
    vs = ViewSynthesizer(world, ViewConfig(**SMALL))
    layout = vs._prepared.layout
    frame_bytes = layout.rgb_bytes + layout.depth_bytes
    assert world.frame_count == 61
    tracemalloc.start()
    try:
        _render_drive(vs, range(world.frame_count))
        snapshot = tracemalloc.take_snapshot().filter_traces([tracemalloc.Filter(True, frame_cache.__file__)])
    finally:
        tracemalloc.stop()
    held_bytes = sum(stat.size for stat in snapshot.statistics("filename"))
    assert frame_bytes <= held_bytes <= 6 * frame_bytes


def test_a_world_the_memory_cache_holds_whole_spends_no_disk(tmp_path, monkeypatch):
    """A drive short enough for the memory cache (up to 2048 frames) is prepared in memory: no view_cache folder."""
    world = _world(tmp_path)
    monkeypatch.setattr(view_module, "_FRAME_CACHE_SIZE", world.frame_count)
    rgb, _ = _render_drive(ViewSynthesizer(world, ViewConfig(**SMALL)), range(0, world.frame_count, 5))
    assert rgb.std() > 0
    assert not (world.root / "view_cache").exists()


@pytest.mark.parametrize("height_px, width_px, margin_px", [(4, 6, 1), (3, 5, 0)])
def test_a_decoded_frame_is_its_encoded_arrays_writable_whether_its_depth_starts_aligned_or_not(
    height_px, width_px, margin_px
):
    layout = frame_cache.FrameLayout(height_px, width_px, margin_px)
    assert (layout.rgb_bytes % 8 == 0) == (height_px == 4)  # the first layout decodes in place, the second copies
    rng = np.random.default_rng(0)
    shape = (height_px, layout.wide_width_px)
    rgb = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
    depth_m = rng.uniform(0.5, 80.0, shape).astype(np.float32)
    out_rgb, out_depth = layout.decode(layout.encode(rgb, depth_m))
    np.testing.assert_array_equal(out_rgb, rgb)
    np.testing.assert_array_equal(out_depth, depth_m.astype(np.float16))
    assert out_rgb.flags.writeable and out_depth.flags.writeable and out_depth.flags.aligned
