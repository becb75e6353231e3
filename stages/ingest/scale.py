"""Metric scale and a level world for SfM poses: the road plane fitted in the SfM cloud below the camera (its distance
to the camera against `--camera-height-m`), or a GPS track (a similarity fitted to its ENU positions).

Frames: SfM (arbitrary scale, any orientation); world = z up along the road's normal, origin on the road below the
first kept camera, x along that camera's heading (or local ENU about the first GPS fix when a track is given).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage.transform import SimilarityTransform

from drivesim.pipeline.errors import InputError
from drivesim.sim.geometry import invert, se3

# A road point seen from camera i: at least ~4.5 degrees below its optical axis, within one height sideways (its lane:
# two heights let kerbs and pavements in, 1.3 % lower on KITTI) and
# twenty heights (~33 m at 1.65 m) ahead, where SIFT still finds asphalt texture and the road is locally flat.
_BELOW_AXIS = 0.08
_SIDEWAYS = 1.0
_AHEAD = 20.0


@dataclass
class RoadFit:
    """The road plane under the cameras, in SfM units.

    :param frame_rows: rows (into the SfM result) of the frames where a plane was fitted.
    :param heights_sfm: camera height above the plane at those frames (SfM units).
    :param normal_camera: the road's up normal in the camera frame (median over the fits), unit (3,).
    :param normal_sfm: the road's up normal in the SfM frame (median over the fits), unit (3,).
    """

    frame_rows: np.ndarray
    heights_sfm: np.ndarray
    normal_camera: np.ndarray
    normal_sfm: np.ndarray

    @property
    def height_sfm(self) -> float:
        """Median camera height above the road (SfM units)."""
        return float(np.median(self.heights_sfm))


def _ransac_plane(
    points: np.ndarray, up: np.ndarray, tol: float, rng: np.random.Generator, max_tilt_deg: float = 15.0
) -> tuple[np.ndarray, float, np.ndarray] | None:
    """Plane n.x = d through most points with n within `max_tilt_deg` of `up` (n oriented like up).

    Hand-written rather than Open3D's segment_plane: the tilt limit keeps walls and car sides out of the road.
    """
    best: tuple[int, np.ndarray, float] | None = None
    cos_max = np.cos(np.radians(max_tilt_deg))
    for _ in range(200):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n = n / norm * np.sign(n @ up or 1.0)
        if n @ up < cos_max:
            continue
        count = int(np.sum(np.abs(points @ n - n @ a) < tol))
        if best is None or count > best[0]:
            best = (count, n, float(n @ a))
    if best is None or best[0] < 12:
        return None
    inliers = np.abs(points @ best[1] - best[2]) < tol
    centre = points[inliers].mean(axis=0)
    n = np.linalg.svd(points[inliers] - centre)[2][-1]  # least-squares refit on the inliers
    n = n * np.sign(n @ up)
    return n, float(n @ centre), inliers


def fit_road(T_sfm_camera: np.ndarray, points_sfm: np.ndarray, window: int = 5, step: int = 2) -> RoadFit | None:
    """Fit the road plane below every `step`-th camera to the cloud points seen near it; None when no fit holds."""
    C = T_sfm_camera[:, :3, 3]
    R = T_sfm_camera[:, :3, :3]
    rng = np.random.default_rng(0)
    rows, heights, normals_sfm, normals_cam = [], [], [], []
    for i in range(0, len(T_sfm_camera), step):
        lo, hi = max(0, i - window), min(len(T_sfm_camera), i + window + 1)
        candidates = []
        for j in range(lo, hi):
            p = (points_sfm - C[j]) @ R[j]  # points in camera j's frame
            below = (p[:, 2] > 0) & (p[:, 1] > _BELOW_AXIS * p[:, 2])
            below &= (np.abs(p[:, 0]) < _SIDEWAYS * p[:, 1]) & (p[:, 2] < _AHEAD * p[:, 1])
            candidates.append(np.flatnonzero(below))
        idx = np.unique(np.concatenate(candidates))
        if len(idx) < 30:
            continue
        up = -R[i][:, 1]  # image up: the road's normal for a camera mounted near level
        local = (points_sfm[idx] - C[i]) @ R[i]
        tol = 0.03 * float(np.median(local[:, 1]))
        fit = _ransac_plane(points_sfm[idx], up, tol, rng)
        if fit is None:
            continue
        n, d, _ = fit
        rows.append(i)
        heights.append(float(n @ C[i] - d))
        normals_sfm.append(n)
        normals_cam.append(R[i].T @ n)
    if len(rows) < max(2, len(range(0, len(T_sfm_camera), step)) // 4):
        return None
    unit = lambda v: v / np.linalg.norm(v)  # noqa: E731
    return RoadFit(
        frame_rows=np.asarray(rows),
        heights_sfm=np.asarray(heights),
        normal_camera=unit(np.median(normals_cam, axis=0)),
        normal_sfm=unit(np.median(normals_sfm, axis=0)),
    )


def vehicle_mount(normal_camera: np.ndarray, height_m: float) -> np.ndarray:
    """T_vehicle_camera of a camera `height_m` above the road whose up normal, in the camera frame, is
    `normal_camera`: vehicle z along the normal, x the optical axis projected on the road."""
    z = normal_camera / np.linalg.norm(normal_camera)
    x = np.array([0.0, 0.0, 1.0]) - z[2] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_camera_vehicle = np.column_stack([x, y, z])
    return se3(R_camera_vehicle.T, np.array([0.0, 0.0, height_m]))


def level_world(T_sfm_camera0: np.ndarray, normal_sfm: np.ndarray, height_sfm: float) -> np.ndarray:
    """T_world_sfm (rigid, SfM units): z along the road normal, origin on the road below camera 0, x its heading."""
    z = normal_sfm / np.linalg.norm(normal_sfm)
    forward = T_sfm_camera0[:3, 2]
    x = forward - (forward @ z) * z
    x /= np.linalg.norm(x)
    R_sfm_world = np.column_stack([x, np.cross(z, x), z])
    origin = T_sfm_camera0[:3, 3] - height_sfm * z
    return invert(se3(R_sfm_world, origin))


def scale_poses(T_world_camera: np.ndarray, scale: float) -> np.ndarray:
    """The same poses with positions multiplied by `scale` (SfM units -> metres)."""
    out = T_world_camera.copy()
    out[:, :3, 3] *= scale
    return out


def fit_similarity(src: np.ndarray, dst: np.ndarray) -> SimilarityTransform | None:
    """The least-squares similarity src -> dst (Umeyama, scikit-image; 2D or 3D points), None when degenerate."""
    if hasattr(SimilarityTransform, "from_estimate"):  # scikit-image >= 0.26
        fitted = SimilarityTransform.from_estimate(src, dst)
        return fitted if fitted else None
    similarity = SimilarityTransform(dimensionality=src.shape[1])
    return similarity if similarity.estimate(src, dst) else None


def gps_alignment(level_xyz: np.ndarray, enu_xyz: np.ndarray, min_path_m: float = 10.0) -> np.ndarray:
    """T_enu_level as a 4x4 similarity (scale, yaw about z, translation) that best maps the levelled SfM camera
    positions onto the GPS ENU positions at the same times (least squares in the horizontal plane, Umeyama's
    method via scikit-image; the height offset is the mean difference).

    :raises InputError: the GPS path is too short to give a scale.
    """
    path_m = float(np.sum(np.linalg.norm(np.diff(enu_xyz[:, :2], axis=0), axis=1)))
    if len(enu_xyz) < 3 or path_m < min_path_m:
        raise InputError(
            f"the GPS track moves only {path_m:.1f} m while the video is registered (at least {min_path_m:g} m "
            "needed for a scale); give --camera-height-m instead"
        )
    similarity = fit_similarity(level_xyz[:, :2], enu_xyz[:, :2])
    if similarity is None:
        raise InputError("the GPS track cannot be aligned with the SfM path (degenerate); give --camera-height-m")
    scale = float(similarity.scale)
    T = np.eye(4)
    T[:2, :2] = similarity.params[:2, :2]
    T[2, 2] = scale
    T[:2, 3] = similarity.params[:2, 2]
    T[2, 3] = float(np.mean(enu_xyz[:, 2] - scale * level_xyz[:, 2]))
    return T
