"""The world loader the simulator uses: closest-frame association and the paper's relative pose."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from drivesim.sim.geometry import camera_mount, intrinsics_from_hfov, invert, pose_2d
from drivesim.sim.world import WORLD_FORMAT_VERSION, World, relative_pose


def _write_world(root: Path, x: np.ndarray, y: np.ndarray, yaw: np.ndarray) -> Path:
    """A minimal world folder around a given path (frames and depth are blank; only the path matters here)."""
    root.mkdir(parents=True)
    n, h, w = len(x), 4, 6
    np.save(root / "frames.npy", np.zeros((n, h, w, 3), np.uint8))
    np.save(root / "depth_m.npy", np.ones((n, h, w), np.float32))
    T_vc = camera_mount(1.0, 0.0, 1.5)
    K = intrinsics_from_hfov(w, h, 1.5)
    camera = {"width_px": w, "height_px": h, "K": K.tolist(), "T_vehicle_camera": T_vc.tolist()}
    (root / "camera.json").write_text(json.dumps(camera))
    steps = np.hypot(np.diff(x), np.diff(y))
    T_wv = np.stack([pose_2d(x[i], y[i], yaw[i]) for i in range(n)])
    np.savez(
        root / "path.npz",
        frame_index=np.arange(n),
        t_ns=np.arange(n) * 100_000_000,
        x_m=x,
        y_m=y,
        z_m=np.zeros(n),
        yaw_rad=yaw,
        speed_mps=np.full(n, 10.0),
        curvature_1pm=np.zeros(n),
        arc_length_m=np.concatenate([[0.0], np.cumsum(steps)]),
        T_world_vehicle=T_wv,
        T_world_camera=T_wv @ T_vc,
    )
    info = {"format": WORLD_FORMAT_VERSION, "frame_count": n, "road_width_m": 7.0, "lane_width_m": 3.5}
    (root / "world.json").write_text(json.dumps(info))
    return root


@pytest.fixture
def circle_world(tmp_path: Path) -> World:
    """A counter-clockwise circle of radius 20 m, one frame every ~1 m."""
    angle = np.linspace(0.0, 2 * np.pi, 126, endpoint=False)
    x, y = 20.0 * np.cos(angle), 20.0 * np.sin(angle)
    return World.load(_write_world(tmp_path / "world", x, y, angle + np.pi / 2))


def test_relative_pose_matches_the_rigid_transform() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        ref = rng.uniform(-50, 50, 2), rng.uniform(-np.pi, np.pi)
        agent = rng.uniform(-50, 50, 2), rng.uniform(-np.pi, np.pi)
        q_lat, q_long, q_rot = relative_pose(agent[0][0], agent[0][1], agent[1], ref[0][0], ref[0][1], ref[1])
        # the agent's position in the reference vehicle frame, by the 4x4 transforms of sim/geometry
        T_ref_agent = invert(pose_2d(*ref[0], ref[1])) @ pose_2d(*agent[0], agent[1])
        assert q_long == pytest.approx(T_ref_agent[0, 3]) and q_lat == pytest.approx(T_ref_agent[1, 3])
        assert q_rot == pytest.approx(np.arctan2(T_ref_agent[1, 0], T_ref_agent[0, 0]))


def test_agent_left_of_a_frame_gets_positive_lateral_offset(circle_world: World) -> None:
    i = 40
    x, y, yaw = circle_world.pose(i)
    left = np.array([-np.sin(yaw), np.cos(yaw)])
    forward = np.array([np.cos(yaw), np.sin(yaw)])
    position = np.array([x, y]) + 1.2 * left + 0.3 * forward
    index, q_lat, q_long, q_rot = circle_world.closest_frame(position[0], position[1], yaw + 0.1)
    assert index == i
    assert q_lat == pytest.approx(1.2, abs=1e-9)
    assert q_long == pytest.approx(0.3, abs=1e-9)
    assert q_rot == pytest.approx(0.1, abs=1e-9)


def test_closest_frame_ignores_frames_heading_the_other_way(tmp_path: Path) -> None:
    # an out-and-back road: east along y = 0, then west along y = 3 m (the opposite lane)
    xs = np.arange(0.0, 50.0, 1.0)
    x = np.concatenate([xs, xs[::-1]])
    y = np.concatenate([np.zeros_like(xs), np.full_like(xs, 3.0)])
    yaw = np.concatenate([np.zeros_like(xs), np.full_like(xs, np.pi)])
    world = World.load(_write_world(tmp_path / "w", x, y, yaw))
    # an eastbound agent drifted 2 m left (nearer the westbound lane) still belongs to the eastbound pass
    index, q_lat, _, q_rot = world.closest_frame(20.0, 2.0, 0.0)
    assert index == 20 and q_lat == pytest.approx(2.0) and q_rot == pytest.approx(0.0)
    index, q_lat, _, q_rot = world.closest_frame(20.0, 2.0, np.pi)
    assert index == 79 and q_lat == pytest.approx(1.0) and q_rot == pytest.approx(0.0)


def test_near_index_keeps_the_association_on_the_same_pass(tmp_path: Path) -> None:
    # two laps of the same circle: the position alone cannot tell the laps apart
    angle = np.linspace(0.0, 4 * np.pi, 252, endpoint=False)
    x, y = 20.0 * np.cos(angle), 20.0 * np.sin(angle)
    world = World.load(_write_world(tmp_path / "w", x, y, angle + np.pi / 2))
    px, py, pyaw = world.pose(130)
    index, *_ = world.closest_frame(px + 0.05, py, pyaw, near_index=128)
    assert index == 130
    index, *_ = world.closest_frame(px + 0.05, py, pyaw, near_index=2)
    assert index == 4  # the same place on the first lap


def test_batched_lookup_agrees_with_single(circle_world: World) -> None:
    rng = np.random.default_rng(2)
    x = rng.uniform(-22, 22, 30)
    y = rng.uniform(-22, 22, 30)
    yaw = np.arctan2(y, x) + np.pi / 2 + rng.uniform(-0.3, 0.3, 30)
    index, q_lat, q_long, q_rot = circle_world.closest_frames(x, y, yaw)
    for j in range(30):
        single = circle_world.closest_frame(x[j], y[j], yaw[j])
        assert single.index == index[j] and single.q_lat_m == pytest.approx(q_lat[j])
        # the nearest frame is never more than half a frame spacing behind or ahead (along the circle)
        assert abs(single.q_long_m) < 0.6 * (1.0 + abs(single.q_lat_m) / 20.0)


def test_compiled_lookup_picks_the_kd_trees_frames(tmp_path: Path) -> None:
    """The compiled search over every frame and the KD-tree's candidates give the same frames, on a path that passes
    nearly the same places twice (a spiral: an exact tie between two frames may go either way), for agents turned
    any way, with and without the previous association."""
    angle = np.linspace(0.0, 4 * np.pi, 252, endpoint=False)
    radius_m = 20.0 + 0.1 * angle
    world = World.load(
        _write_world(tmp_path / "w", radius_m * np.cos(angle), radius_m * np.sin(angle), angle + np.pi / 2)
    )
    rng = np.random.default_rng(5)
    x, y = rng.uniform(-23, 23, 400), rng.uniform(-23, 23, 400)
    yaw = rng.uniform(-np.pi, np.pi, 400)
    near = rng.integers(0, 252, 400)
    for near_index in (None, near):
        compiled = world.closest_frames(x, y, yaw, near_index=near_index)
        by_tree = world._closest_frames_by_tree(x, y, yaw, near_index, 15.0)
        np.testing.assert_array_equal(compiled[0], by_tree)


def test_world_load_names_the_missing_file(tmp_path: Path) -> None:
    root = _write_world(tmp_path / "w", np.arange(5.0), np.zeros(5), np.zeros(5))
    (root / "depth_m.npy").unlink()
    with pytest.raises(FileNotFoundError, match="depth_m.npy"):
        World.load(root)


def test_world_load_refuses_mismatched_arrays(tmp_path: Path) -> None:
    root = _write_world(tmp_path / "w", np.arange(5.0), np.zeros(5), np.zeros(5))
    np.save(root / "depth_m.npy", np.ones((4, 4, 6), np.float32))
    with pytest.raises(ValueError, match="depth_m.npy"):
        World.load(root)


def test_the_block_search_finds_the_frames_a_scan_of_every_frame_finds(tmp_path: Path) -> None:
    """On a long drive that passes the same places several times, the search that skips far blocks of frames picks
    the frame a scan of every frame picks (8 nearest by distance, then the lower index; the same penalties)."""
    angle = np.linspace(0.0, 12 * np.pi, 3000, endpoint=False)
    radius_m = 30.0 + 0.05 * angle
    x_path, y_path, yaw_path = radius_m * np.cos(angle), radius_m * np.sin(angle), angle + np.pi / 2
    world = World.load(_write_world(tmp_path / "w", x_path, y_path, yaw_path))
    rng = np.random.default_rng(7)
    x, y = rng.uniform(-34, 34, 300), rng.uniform(-34, 34, 300)
    yaw = rng.uniform(-np.pi, np.pi, 300)
    near = rng.integers(0, 3000, 300)
    path = world.path
    found = world.closest_frames(x, y, yaw, near_index=near)[0]
    for b in range(len(x)):
        d = np.hypot(path["x_m"] - x[b], path["y_m"] - y[b])
        nearest = np.lexsort((np.arange(len(d)), d))[:8]
        heading = np.abs((yaw[b] - path["yaw_rad"][nearest] + np.pi) % (2 * np.pi) - np.pi)
        score = d[nearest] + np.where(heading > 0.5 * np.pi, 1e6, 0.0)
        score += np.where(np.abs(path["arc_length_m"][nearest] - path["arc_length_m"][near[b]]) > 15.0, 1e3, 0.0)
        assert found[b] == nearest[int(np.argmin(score))], b
