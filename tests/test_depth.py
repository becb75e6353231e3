"""Per-frame depth (plane, mvs, lidar) on scenes of known geometry, ray cast here with numpy.

The scene: a flat textured ground (z = 0 in the world), optional textured axis-aligned boxes (building walls along
the road, a car-sized box ahead), a textureless sky at infinity; a camera 1.6 m high, pitched down 3 degrees, on a
vehicle driving +x at 1 m per frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from pydantic import ValidationError

from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import ConfigError, InputError
from drivesim.sim.geometry import camera_mount, intrinsics_from_hfov, pose_2d
from drivesim.stages.preprocess.config import DepthConfig
from drivesim.stages.preprocess.depth import estimate_depth
from drivesim.stages.preprocess.depth_lidar import densify, project_points
from drivesim.stages.preprocess.depth_plane import pixel_rays

WIDTH_PX, HEIGHT_PX = 320, 200
CAMERA_HEIGHT_M = 1.6
T_VEHICLE_CAMERA = camera_mount(1.5, 0.0, CAMERA_HEIGHT_M, pitch_down_rad=np.deg2rad(3.0))
K = intrinsics_from_hfov(WIDTH_PX, HEIGHT_PX, np.deg2rad(80.0))


def _noise_texture(seed: int, size: int = 256) -> np.ndarray:
    """Multi-scale smooth noise in [0, 1], tileable (wrap), (size, size)."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    tex = np.zeros((size, size))
    for sigma, weight in ((1.0, 0.35), (3.0, 0.35), (8.0, 0.3)):
        layer = ndimage.gaussian_filter(rng.standard_normal((size, size)), sigma, mode="wrap")
        tex += weight * layer / layer.std()
    return np.clip(0.5 + 0.15 * tex, 0.0, 1.0)


@dataclass
class Scene:
    """Ground plane plus axis-aligned boxes (min corner, max corner) in the world frame."""

    boxes: list[tuple[np.ndarray, np.ndarray]]
    texel_m: float = 0.06

    def __post_init__(self) -> None:
        self.texture = _noise_texture(7)

    def _shade(self, a: np.ndarray, b: np.ndarray, tint: np.ndarray) -> np.ndarray:
        from scipy import ndimage

        coords = np.stack([a.ravel() / self.texel_m, b.ravel() / self.texel_m])
        grey = ndimage.map_coordinates(self.texture, coords, order=1, mode="grid-wrap").reshape(a.shape)
        return grey[..., None] * tint

    def render(self, T_world_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rgb uint8 (H, W, 3), optical depth float32 (H, W), inf for sky) seen from a camera pose."""
        rays = pixel_rays(K, WIDTH_PX, HEIGHT_PX) @ T_world_camera[:3, :3].T  # unit optical z: t = depth
        origin = T_world_camera[:3, 3]
        depth = np.full(rays.shape[:2], np.inf)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_ground = np.where(rays[..., 2] < 0, -origin[2] / rays[..., 2], np.inf)
        depth = np.minimum(depth, t_ground)
        hit_box = np.full(rays.shape[:2], -1)
        hit_axis = np.zeros(rays.shape[:2], dtype=int)
        for b, (lo, hi) in enumerate(self.boxes):
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (lo - origin) / rays
                t2 = (hi - origin) / rays
            t_min = np.nan_to_num(np.minimum(t1, t2), nan=-np.inf)
            t_max = np.nan_to_num(np.maximum(t1, t2), nan=np.inf)
            t_near = t_min.max(axis=-1)
            t_far = t_max.min(axis=-1)
            hit = (t_near <= t_far) & (t_near > 0) & (t_near < depth)
            depth = np.where(hit, t_near, depth)
            hit_box = np.where(hit, b, hit_box)
            hit_axis = np.where(hit, t_min.argmax(axis=-1), hit_axis)
        point = origin + rays * np.where(np.isfinite(depth), depth, 0.0)[..., None]
        rgb = np.empty(rays.shape, np.float64)
        rgb[:] = np.array([0.55, 0.7, 0.9]) - 0.2 * np.linspace(0, 1, HEIGHT_PX)[:, None, None]  # smooth sky
        ground = (hit_box < 0) & np.isfinite(depth)
        rgb[ground] = self._shade(point[ground, 0], point[ground, 1], np.array([0.9, 0.9, 0.85]))
        for axis, (ia, ib) in enumerate(((1, 2), (0, 2), (0, 1))):
            sel = (hit_box >= 0) & (hit_axis == axis)
            tint = np.array([1.0, 0.75, 0.6]) if axis == 1 else np.array([0.7, 0.8, 1.0])
            rgb[sel] = self._shade(point[sel, ia] + 3.1 * axis, point[sel, ib], tint)
        return (np.clip(rgb, 0, 1) * 255).astype(np.uint8), depth.astype(np.float32)


def _street() -> Scene:
    box = np.array
    return Scene(
        boxes=[
            (box([-10.0, 7.0, 0.0]), box([80.0, 12.0, 9.0])),  # building row on the left
            (box([5.0, -14.0, 0.0]), box([60.0, -6.0, 7.0])),  # building row on the right
            (box([20.0, -3.0, 0.0]), box([24.5, -1.2, 1.5])),  # a car-sized box ahead on the right
            (box([45.0, -2.0, 0.0]), box([47.0, 4.0, 6.0])),  # a wall across the road far ahead
        ]
    )


def _drive(scene: Scene, n_frames: int, step_m: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    poses = np.stack([pose_2d(i * step_m, 0.0, 0.0) @ T_VEHICLE_CAMERA for i in range(n_frames)])
    renders = [scene.render(T) for T in poses]
    return np.stack([r[0] for r in renders]), np.stack([r[1] for r in renders]), poses


def _abs_rel(depth_m: np.ndarray, gt_m: np.ndarray, max_depth_m: float = 80.0) -> float:
    valid = np.isfinite(gt_m) & (gt_m < max_depth_m)
    return float(np.mean(np.abs(depth_m[valid] - gt_m[valid]) / gt_m[valid]))


@pytest.fixture(scope="module")
def street_drive() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return _drive(_street(), 7)


def test_plane_depth_is_exact_on_flat_ground() -> None:
    frames, gt, poses = _drive(Scene(boxes=[]), 3)
    out = np.zeros(gt.shape, np.float32)
    summary = estimate_depth(frames, K, poses, T_VEHICLE_CAMERA, CAMERA_HEIGHT_M, DepthConfig(method="plane"), out)
    ground = np.isfinite(gt) & (gt < 80.0)
    assert ground.mean() > 0.4
    np.testing.assert_allclose(out[ground], gt[ground], rtol=1e-4)
    assert np.all(out[~np.isfinite(gt)] == 80.0)  # above the horizon: the far value
    assert summary["frames"] == 3 and summary["method"] == "plane"


def test_plane_depth_follows_camera_height_override() -> None:
    frames, gt, poses = _drive(Scene(boxes=[]), 1)
    out = np.zeros(gt.shape, np.float32)
    estimate_depth(frames, K, poses, T_VEHICLE_CAMERA, 2 * CAMERA_HEIGHT_M, DepthConfig(max_depth_m=500.0), out)
    near = np.isfinite(gt) & (gt < 40.0)
    np.testing.assert_allclose(out[near], 2 * gt[near], rtol=1e-4)


def test_mvs_beats_plane_on_a_street_with_walls(street_drive: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    frames, gt, poses = street_drive
    plane = np.zeros(gt.shape, np.float32)
    mvs = np.zeros(gt.shape, np.float32)
    estimate_depth(frames, K, poses, T_VEHICLE_CAMERA, CAMERA_HEIGHT_M, DepthConfig(method="plane"), plane)
    summary = estimate_depth(frames, K, poses, T_VEHICLE_CAMERA, CAMERA_HEIGHT_M, DepthConfig(method="mvs"), mvs)
    middle = slice(2, 5)  # frames with neighbours on both sides
    abs_rel_plane = _abs_rel(plane[middle], gt[middle])
    abs_rel_mvs = _abs_rel(mvs[middle], gt[middle])
    print(f"AbsRel plane {abs_rel_plane:.3f} mvs {abs_rel_mvs:.3f} {summary}")
    assert abs_rel_plane > 0.3  # the walls are far from the ground plane's guess
    assert abs_rel_mvs < 0.5 * abs_rel_plane
    walls = np.isfinite(gt[middle]) & (np.abs(plane[middle] - gt[middle]) > 0.3 * gt[middle])
    err_walls = np.abs(mvs[middle][walls] - gt[middle][walls]) / gt[middle][walls]
    assert np.median(err_walls) < 0.1
    assert summary["stereo_fraction"] > 0.2
    assert np.all(np.isfinite(mvs)) and mvs.min() > 0 and mvs.max() <= 80.0


def test_mvs_streams_every_frame_into_a_memmap(tmp_path, street_drive) -> None:
    frames, gt, poses = street_drive
    out = np.lib.format.open_memmap(tmp_path / "depth.npy", mode="w+", dtype=np.float32, shape=gt.shape)
    out[:] = np.nan
    done = []
    cfg = DepthConfig(method="mvs", mvs={"neighbour_offsets": [-1, 1], "num_hypotheses": 16})
    estimate_depth(frames, K, poses, T_VEHICLE_CAMERA, CAMERA_HEIGHT_M, cfg, out, progress=done.append)
    out.flush()
    written = np.load(tmp_path / "depth.npy", mmap_mode="r")
    assert sum(done) == len(frames)
    assert np.all(np.isfinite(written)) and np.all(written > 0)


def test_mvs_single_frame_falls_back_to_plane(street_drive) -> None:
    frames, gt, poses = street_drive
    plane = np.zeros(gt[:1].shape, np.float32)
    mvs = np.zeros(gt[:1].shape, np.float32)
    estimate_depth(frames[:1], K, poses[:1], T_VEHICLE_CAMERA, CAMERA_HEIGHT_M, DepthConfig(method="plane"), plane)
    estimate_depth(frames[:1], K, poses[:1], T_VEHICLE_CAMERA, CAMERA_HEIGHT_M, DepthConfig(method="mvs"), mvs)
    np.testing.assert_array_equal(plane, mvs)


def test_lidar_projection_and_fill_recover_scene_depth(street_drive) -> None:
    frames, gt, poses = street_drive
    # A synthetic point cloud: every 3rd pixel's true 3D point, expressed in the vehicle frame.
    rays = pixel_rays(K, WIDTH_PX, HEIGHT_PX)
    points = []
    for i in range(2):
        keep = np.zeros(gt[i].shape, bool)
        keep[::3, ::3] = np.isfinite(gt[i][::3, ::3])
        cam = rays[keep] * gt[i][keep][:, None]
        points.append(cam @ T_VEHICLE_CAMERA[:3, :3].T + T_VEHICLE_CAMERA[:3, 3])
    sparse = project_points(points[0], K, T_VEHICLE_CAMERA, WIDTH_PX, HEIGHT_PX)
    assert np.isfinite(sparse).sum() == np.count_nonzero(np.isfinite(gt[0][::3, ::3]))
    dense = densify(sparse, 4)
    out = np.zeros(gt[:2].shape, np.float32)
    cfg = DepthConfig(method="lidar")
    summary = estimate_depth(
        frames[:2], K, poses[:2], T_VEHICLE_CAMERA, CAMERA_HEIGHT_M, cfg, out, points_vehicle=points
    )
    valid = np.isfinite(gt[0]) & (gt[0] < 80.0)
    assert np.isfinite(dense[valid]).mean() > 0.99
    assert _abs_rel(out[0], gt[0]) < 0.03
    assert summary["lidar_coverage_fraction"] > 0.5


def test_lidar_without_points_is_a_clear_input_error(street_drive) -> None:
    frames, gt, poses = street_drive
    out = np.zeros(gt.shape, np.float32)
    with pytest.raises(InputError, match="no point cloud"):
        estimate_depth(frames, K, poses, T_VEHICLE_CAMERA, CAMERA_HEIGHT_M, DepthConfig(method="lidar"), out)


def test_config_validation() -> None:
    cfg = load_config(DepthConfig, overrides=["method=mvs", "mvs.num_hypotheses=32", "max_depth_m=60"])
    assert cfg.method == "mvs" and cfg.mvs.num_hypotheses == 32 and cfg.max_depth_m == 60
    with pytest.raises(ConfigError, match="unknown config key 'mvs.hypotheses'"):
        load_config(DepthConfig, overrides=["mvs.hypotheses=32"])
    with pytest.raises(ConfigError, match="method"):
        load_config(DepthConfig, overrides=["method=sonar"])
    for bad in ({"mvs": {"patch_size_px": 4}}, {"mvs": {"neighbour_offsets": [0, 1]}}, {"max_depth_m": 1.0}):
        with pytest.raises(ValidationError):
            DepthConfig.model_validate(bad)


def test_bad_shapes_are_input_errors() -> None:
    frames = np.zeros((2, 10, 12, 3), np.uint8)
    with pytest.raises(InputError, match="out must be"):
        estimate_depth(
            frames,
            K,
            np.stack([np.eye(4)] * 2),
            T_VEHICLE_CAMERA,
            1.6,
            DepthConfig(method="plane"),
            np.zeros((2, 10, 12)),
        )
    with pytest.raises(InputError, match="T_world_camera"):
        estimate_depth(
            frames,
            K,
            np.eye(4)[None],
            T_VEHICLE_CAMERA,
            1.6,
            DepthConfig(method="plane"),
            np.zeros((2, 10, 12), np.float32),
        )


def test_sky_mask_takes_only_blue_textureless_regions_touching_the_top() -> None:
    from drivesim.stages.preprocess.depth_mvs import sky_mask

    h, w = 20, 30
    colour = np.zeros((h, w, 3), np.float32)
    colour[:] = [0.5, 0.7, 0.95]  # sky blue everywhere ...
    colour[:, 20:] = [0.8, 0.7, 0.6]  # ... but a plain beige facade on the right reaching the top
    std = np.full((h, w), 0.001, np.float32)
    std[8, :] = 0.2  # a textured line (a roof edge) cutting the left part at row 8
    below_horizon = np.zeros((h, w), bool)
    below_horizon[15:] = True
    sky = sky_mask(std, colour, below_horizon, max_std=0.012)
    assert sky[:8, :20].all()  # blue, textureless, connected to the top
    assert not sky[:, 20:].any()  # not sky-coloured
    assert not sky[9:, :].any()  # cut off from the top by texture, or below the horizon


def test_nearest_in_column_picks_the_closest_known_row() -> None:
    from drivesim.stages.preprocess.depth_mvs import _nearest_in_column

    values = np.array([[1.0, 5.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [3.0, 0.0]])
    known = np.array([[True, True], [False, False], [False, False], [False, False], [True, False]])
    near = _nearest_in_column(values, known)
    np.testing.assert_array_equal(near[:, 0], [1.0, 1.0, 1.0, 3.0, 3.0])
    np.testing.assert_array_equal(near[:, 1], [5.0] * 5)
    above = _nearest_in_column(values, known & (np.arange(5)[:, None] > 0), above_only=True)
    assert np.isnan(above[3, 0]) and above[4, 0] == 3.0 and np.isnan(above[:, 1]).all()


def test_mvs_on_a_stationary_vehicle_keeps_the_plane(street_drive) -> None:
    frames, gt, poses = street_drive
    still = np.repeat(frames[3:4], 4, axis=0)
    still_poses = np.repeat(poses[3:4], 4, axis=0)
    plane = np.zeros(still.shape[:3], np.float32)
    mvs = np.zeros(still.shape[:3], np.float32)
    estimate_depth(still, K, still_poses, T_VEHICLE_CAMERA, CAMERA_HEIGHT_M, DepthConfig(method="plane"), plane)
    summary = estimate_depth(still, K, still_poses, T_VEHICLE_CAMERA, CAMERA_HEIGHT_M, DepthConfig(method="mvs"), mvs)
    assert summary["stereo_fraction"] == 0.0  # no baseline, no parallax: nothing to triangulate
    below = plane < 80.0
    assert np.mean(np.isclose(mvs[below], plane[below], rtol=0.05)) > 0.95
    assert np.all(np.isfinite(mvs)) and mvs.max() <= 80.0
