"""The simulatable world (`<workspace>/world/`, written by `drivesim build-world`) and its loader.

The world is what the simulator reads at run time: the recorded frames and their depth at the simulation resolution,
the camera model, and the reference path (the recorded trajectory is the lane centre, DESIGN §3). Frames follow
`sim/geometry.py`: world = local ENU, vehicle x forward / y left / z up, camera optical x right / y down / z forward.

Files (N = frame count, h x w = simulation resolution). Frames and depth are image stacks (`sim/image_stack.py`:
one compressed image per frame, decoded one frame at a time by `world.frames[i]` / `world.depth_m[i]`); worlds
written by earlier versions as frames.npy / depth_m.npy (opened with mmap_mode="r") load as well:
    frames.imgs     uint8   (N, h, w, 3)  RGB frames resized with cv2.INTER_AREA, JPEG (quality 97, 4:4:4) or PNG
    depth_m.imgs    float16 (N, h, w)     metric depth along the optical axis, lossless (the float16 bits in a
                                          16-bit PNG); min-pooled (or nearest) from the preprocessed depth so thin
                                          near objects survive; sky / no estimate = world.json far_depth_m.
                                          float16 keeps 11 significant bits (a relative error under 0.05 %, 5 mm
                                          at 10 m); worlds written with float32 depth (.npy) load as well
    camera.json     {"width_px": w, "height_px": h, "K": 3x3 at (w, h), "T_vehicle_camera": 4x4,
                     "camera_height_m": float | null, "source_width_px", "source_height_px"}
    path.npz        per frame, float64 unless noted:
                    frame_index int64 (N,)   index of the frame in the trace
                    t_ns int64 (N,); x_m, y_m, z_m, yaw_rad, speed_mps, curvature_1pm (+ = left turn),
                    arc_length_m (N,); T_world_vehicle (N,4,4); T_world_camera (N,4,4)
    world.json      {"format": 1, "frame_count": N, "road_width_m", "lane_width_m", "path_length_m",
                     "curvature_min_1pm", "curvature_max_1pm", "pose_source", "origin_lat_deg",
                     "origin_lon_deg", "origin_alt_m", "depth_method", "far_depth_m"}
    pointcloud.ply  fused coloured point cloud of the drive (for people; the simulator does not read it)
    birdseye.png    the path from above coloured by curvature (for people)

The KD-tree over the frame positions is not stored: `World.load` builds a `scipy.spatial.cKDTree` over (x, y), which
takes milliseconds even for an hour of driving and keeps the artifact free of pickles.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from drivesim.sim import association_kernel, world_checks
from drivesim.sim.geometry import wrap_angle
from drivesim.sim.image_stack import ImageStack, open_frames, stack_path, stored_file

WORLD_FORMAT_VERSION = 1
# The dtype build-world stores depth in, and every dtype the loader accepts (the simulator reads depth as float32).
WORLD_DEPTH_DTYPE = np.float16
DEPTH_DTYPES = (np.dtype(np.float16), np.dtype(np.float32))

PATH_ARRAYS_FLOAT = (
    "x_m",
    "y_m",
    "z_m",
    "yaw_rad",
    "speed_mps",
    "curvature_1pm",
    "arc_length_m",
)
# Every array of path.npz (and of the preprocessed poses.npz, which has the same per-frame arrays).
PATH_ARRAYS = ("frame_index", "t_ns", *PATH_ARRAYS_FLOAT, "T_world_vehicle", "T_world_camera")

# How many nearest frames to consider before filtering by heading and arc length: a handful is enough because
# frames are spaced along one path; more only matters where the path passes the same place twice.
_CANDIDATES = 8


class Association(NamedTuple):
    """The recorded frame closest to an agent, and the agent's pose relative to it (paper §III-B).

    :param index: index of the frame in the world (0..N-1).
    :param q_lat_m: lateral offset of the agent from the frame's pose, + = to the left of the recorded heading.
    :param q_long_m: longitudinal offset, + = ahead of the recorded frame.
    :param q_rot_rad: heading of the agent minus the recorded heading, wrapped to [-pi, pi).
    """

    index: int
    q_lat_m: float
    q_long_m: float
    q_rot_rad: float


def _stored_file(root: Path, stem: str) -> Path:
    """The file of the per-frame array `stem`: its image stack, or the .npy of a world built by an earlier version."""
    path = stored_file(root, stem)
    if path is None:
        raise FileNotFoundError(
            f"{stack_path(root, stem)} or {stem}.npy: missing; is {root} a world built by `drivesim build-world`?"
        )
    return path


def _load_frames(path: Path) -> np.ndarray | ImageStack:
    """The per-frame array in `path` (an image stack, or a memory-mapped .npy); a damaged file is a WorldError
    naming it."""
    try:
        return open_frames(path)
    except (OSError, ValueError, EOFError) as e:
        raise world_checks.WorldError(f"{path}: not a readable frame array ({e}); rebuild the world") from e


def _load_path(path: Path) -> dict[str, np.ndarray]:
    """The arrays of path.npz; a damaged file is a WorldError naming it."""
    try:
        with np.load(path) as data:
            return {k: np.asarray(data[k]) for k in data.files}
    except (OSError, ValueError, EOFError, KeyError) as e:
        raise world_checks.WorldError(f"{path}: not a readable .npz archive ({e}); rebuild the world") from e


def _file_of(array: np.ndarray | ImageStack, root: Path, stem: str) -> Path:
    """The file a world's per-frame array was read from (for messages)."""
    if isinstance(array, ImageStack):
        return array.path
    return stored_file(root, stem) or stack_path(root, stem)


def relative_pose(
    x_m: np.ndarray | float,
    y_m: np.ndarray | float,
    yaw_rad: np.ndarray | float,
    ref_x_m: np.ndarray | float,
    ref_y_m: np.ndarray | float,
    ref_yaw_rad: np.ndarray | float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q_lat, q_long, q_rot) of poses (x, y, yaw) relative to reference poses, in the reference's vehicle frame.

    The paper writes this as a rotation of [x_t - x_s, y_t - y_s, theta_t - theta_s] by the reference heading in
    VISTA's frame (lateral x, longitudinal y); in our ENU frame with yaw measured from +x the same projection is the
    rotation by -theta_s: q_long = cos(theta_s) dx + sin(theta_s) dy, q_lat = -sin(theta_s) dx + cos(theta_s) dy.
    """
    dx = np.asarray(x_m, dtype=float) - ref_x_m
    dy = np.asarray(y_m, dtype=float) - ref_y_m
    c, s = np.cos(ref_yaw_rad), np.sin(ref_yaw_rad)
    q_long = c * dx + s * dy
    q_lat = -s * dx + c * dy
    q_rot = wrap_angle(np.asarray(yaw_rad, dtype=float) - ref_yaw_rad)
    return q_lat, q_long, np.asarray(q_rot)


@dataclass
class World:
    """A loaded world: memory-mapped frames and depth, camera model, reference path and a KD-tree over frame poses.

    :param root: the world folder.
    :param frames: (N, h, w, 3) uint8 RGB frames; `frames[i]` decodes frame i (a memmap for .npy worlds).
    :param depth_m: (N, h, w) float16 (or float32) depth in metres; `depth_m[i]` as frames.
    :param K: 3x3 intrinsics at the simulation resolution.
    :param T_vehicle_camera: 4x4 camera optical frame -> vehicle frame.
    :param width_px: simulation image width.
    :param height_px: simulation image height.
    :param camera_height_m: optical centre above the ground, or None when unknown.
    :param path: per-frame reference path arrays (see the module docstring), plain numpy arrays.
    :param road_width_m: width of the drivable road.
    :param lane_width_m: width of the ego lane centred on the recorded path.
    :param info: the whole of world.json.
    """

    root: Path
    frames: np.ndarray | ImageStack
    depth_m: np.ndarray | ImageStack
    K: np.ndarray
    T_vehicle_camera: np.ndarray
    width_px: int
    height_px: int
    camera_height_m: float | None
    path: dict[str, np.ndarray]
    road_width_m: float
    lane_width_m: float
    info: dict
    _tree: cKDTree | None = None
    _blocks: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @classmethod
    def load(cls, root: Path | str) -> World:
        """Open and check a world folder written by `drivesim build-world`.

        :raises FileNotFoundError: a file is missing. WorldError (a ValueError): a file is damaged or does not follow
            the schema above (JSON nesting, non-finite or missing values, a singular K, NaN or negative depth); the
            text names the file.
        """
        root = Path(root)
        frames_file, depth_file = _stored_file(root, "frames"), _stored_file(root, "depth_m")
        for name in ("camera.json", "path.npz", "world.json"):
            if not (root / name).is_file():
                raise FileNotFoundError(f"{root / name}: missing; is {root} a world built by `drivesim build-world`?")
        info = world_checks.read_json_object(root / "world.json", ("format", "road_width_m", "lane_width_m"))
        if info.get("format") != WORLD_FORMAT_VERSION:
            raise world_checks.WorldError(
                f"{root / 'world.json'}: world format {info.get('format')!r}, expected {WORLD_FORMAT_VERSION}"
            )
        camera_json = root / "camera.json"
        camera = world_checks.read_json_object(camera_json, ("K", "T_vehicle_camera", "width_px", "height_px"))
        world = cls(
            root=root,
            frames=_load_frames(frames_file),
            depth_m=_load_frames(depth_file),
            K=world_checks.intrinsics(camera_json, camera["K"]),
            T_vehicle_camera=world_checks.rigid_transform(camera_json, "T_vehicle_camera", camera["T_vehicle_camera"]),
            width_px=world_checks.image_size(camera_json, "width_px", camera["width_px"]),
            height_px=world_checks.image_size(camera_json, "height_px", camera["height_px"]),
            camera_height_m=world_checks.finite_number(
                camera_json, "camera_height_m", camera.get("camera_height_m"), positive=True, optional=True
            ),
            path=_load_path(root / "path.npz"),
            road_width_m=world_checks.finite_number(root / "world.json", "road_width_m", info["road_width_m"], True),
            lane_width_m=world_checks.finite_number(root / "world.json", "lane_width_m", info["lane_width_m"], True),
            info=info,
        )
        world._check()
        world._tree = cKDTree(np.column_stack([world.path["x_m"], world.path["y_m"]]))
        return world

    def _check(self) -> None:
        n = self.frame_count
        if n < 2:
            raise world_checks.WorldError(f"{self.root}: a world needs at least 2 frames, this one has {n}")
        if self.frames.shape != (n, self.height_px, self.width_px, 3) or self.frames.dtype != np.uint8:
            raise world_checks.WorldError(
                f"{_file_of(self.frames, self.root, 'frames')}: {self.frames.dtype} {self.frames.shape} does not match"
            )
        if self.depth_m.shape != (n, self.height_px, self.width_px) or self.depth_m.dtype not in DEPTH_DTYPES:
            where = _file_of(self.depth_m, self.root, "depth_m")
            raise world_checks.WorldError(f"{where}: {self.depth_m.dtype} {self.depth_m.shape} does not match")
        for key in PATH_ARRAYS:
            if key not in self.path or len(self.path[key]) != n:
                raise world_checks.WorldError(
                    f"{self.root / 'path.npz'}: array {key!r} is missing or not of length {n}"
                )
        world_checks.check_path_values(self.root / "path.npz", self.path, PATH_ARRAYS_FLOAT)
        world_checks.check_depth(_file_of(self.depth_m, self.root, "depth_m"), self.depth_m)

    @property
    def frame_count(self) -> int:
        """Number of frames N."""
        return int(self.path["x_m"].shape[0])

    @property
    def path_length_m(self) -> float:
        """Length of the reference path."""
        return float(self.path["arc_length_m"][-1] - self.path["arc_length_m"][0])

    def closest_frames(
        self,
        x_m: np.ndarray,
        y_m: np.ndarray,
        yaw_rad: np.ndarray,
        near_index: np.ndarray | None = None,
        max_arc_gap_m: float = 15.0,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Batched `closest_frame`: arrays of shape (B,) in, (index, q_lat_m, q_long_m, q_rot_rad) arrays out."""
        x = np.atleast_1d(np.asarray(x_m, dtype=float))
        y = np.atleast_1d(np.asarray(y_m, dtype=float))
        yaw = np.atleast_1d(np.asarray(yaw_rad, dtype=float))
        if self.frame_count <= association_kernel.BRUTE_FORCE_MAX_FRAMES:
            near = np.full(len(x), -1, dtype=np.int64) if near_index is None else near_index
            best = association_kernel.closest_frames(
                x, y, yaw, np.broadcast_to(np.asarray(near, dtype=np.int64), x.shape), self.path["x_m"],
                self.path["y_m"], self.path["yaw_rad"], self.path["arc_length_m"], _CANDIDATES, float(max_arc_gap_m),
                self._path_blocks(),
            )  # fmt: skip
        else:
            best = self._closest_frames_by_tree(x, y, yaw, near_index, max_arc_gap_m)
        q_lat, q_long, q_rot = relative_pose(
            x, y, yaw, self.path["x_m"][best], self.path["y_m"][best], self.path["yaw_rad"][best]
        )
        return best.astype(np.int64), q_lat, q_long, q_rot

    def _path_blocks(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The path's blocks of frames as bounding circles (`association_kernel.path_blocks`), made once."""
        if self._blocks is None:
            self._blocks = association_kernel.path_blocks(self.path["x_m"], self.path["y_m"])
        return self._blocks

    def _closest_frames_by_tree(
        self, x: np.ndarray, y: np.ndarray, yaw: np.ndarray, near_index: np.ndarray | None, max_arc_gap_m: float
    ) -> np.ndarray:
        """closest_frames's frame indices from the KD-tree's nearest candidates (drives of many frames)."""
        k = min(_CANDIDATES, self.frame_count)
        dist, cand = self._tree.query(np.column_stack([x, y]), k=k)
        dist = dist.reshape(len(x), k)
        cand = cand.reshape(len(x), k)
        # Candidates facing the other way (the road back on a loop) or far along the path from the previous
        # association (another pass of the same place) are only taken when nothing else is near.
        penalty = np.zeros_like(dist)
        heading_gap = np.abs(wrap_angle(yaw[:, None] - self.path["yaw_rad"][cand]))
        penalty += np.where(heading_gap > 0.5 * np.pi, 1e6, 0.0)
        if near_index is not None:
            arc = self.path["arc_length_m"]
            near = np.broadcast_to(np.asarray(near_index, dtype=int), x.shape)
            gap = np.abs(arc[cand] - arc[near][:, None])
            penalty += np.where(gap > max_arc_gap_m, 1e3, 0.0)
        return cand[np.arange(len(x)), np.argmin(dist + penalty, axis=1)]

    def closest_frame(
        self, x_m: float, y_m: float, yaw_rad: float, near_index: int | None = None, max_arc_gap_m: float = 15.0
    ) -> Association:
        """The recorded frame to synthesise an agent's view from, and the agent's (q_lat, q_long, q_rot) relative to it.

        The frame is the nearest in position among those heading the same way as the agent (within 90°);
        with `near_index` (the previous association) frames more than `max_arc_gap_m` of arc length away are
        avoided, so a path that passes the same place twice does not make the agent jump between passes. Only the
        8 nearest frames are candidates: found by a compiled loop over every frame (`association_kernel`), or by the
        KD-tree for drives of more than 20,000 frames.
        Unpack as `index, q_lat_m, q_long_m, q_rot_rad = world.closest_frame(x, y, yaw)`.
        """
        idx, q_lat, q_long, q_rot = self.closest_frames(
            np.array([x_m]),
            np.array([y_m]),
            np.array([yaw_rad]),
            None if near_index is None else [near_index],
            max_arc_gap_m,
        )
        return Association(int(idx[0]), float(q_lat[0]), float(q_long[0]), float(q_rot[0]))

    def pose(self, index: int) -> tuple[float, float, float]:
        """(x_m, y_m, yaw_rad) of recorded frame `index`."""
        return float(self.path["x_m"][index]), float(self.path["y_m"][index]), float(self.path["yaw_rad"][index])
