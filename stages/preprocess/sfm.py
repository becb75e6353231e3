"""Camera-only poses: the SfM pipeline of `stages/ingest/sfm.py` (pycolmap, known intrinsics) on a recording's frames,
scaled to metres from a speed series or a user-given path length.

The reconstruction's world is re-anchored at the first vehicle pose (x forward, z up when the drive starts level).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import cv2
import numpy as np

from drivesim.pipeline.errors import InputError
from drivesim.sim.geometry import invert, scale_intrinsics

SCALE_HINT = (
    "SfM recovers the path only up to scale: set poses.sfm_scale_m (the camera's path length in metres) "
    "or record a speed series"
)


def _write_images(frames: np.ndarray, folder: Path, max_width_px: int) -> tuple[list[str], tuple[int, int]]:
    """Frames as PNGs at most `max_width_px` wide; returns (names, (width, height) px of the PNGs)."""
    h, w = frames.shape[1:3]
    factor = min(1.0, max_width_px / w)
    size = (max(1, round(w * factor)), max(1, round(h * factor)))
    names = []
    for i, frame in enumerate(frames):
        image = np.asarray(frame)
        if factor < 1.0:
            image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        name = f"{i:06d}.png"
        cv2.imwrite(str(folder / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        names.append(name)
    return names, size


def reconstruct(frames: np.ndarray, K: np.ndarray, max_width_px: int = 640, overlap: int = 10) -> dict[int, np.ndarray]:
    """Camera poses T_sfm_camera (4x4, arbitrary scale and frame) of the frames the SfM pipeline registers in its
    largest piece (`stages/ingest/sfm.py`: known intrinsics, each frame matched with the next `overlap`, no loop
    closure), by frame index.

    :raises InputError: fewer than 2 frames, or no reconstruction could be made.
    """
    from drivesim.stages.ingest.sfm import SfmOptions
    from drivesim.stages.ingest.sfm import reconstruct as reconstruct_images

    if len(frames) < 2:
        raise InputError("SfM needs at least 2 frames")
    with tempfile.TemporaryDirectory(prefix="drivesim-sfm-") as tmp:
        tmp_dir = Path(tmp)
        image_dir = tmp_dir / "images"
        image_dir.mkdir()
        names, size = _write_images(frames, image_dir, max_width_px)
        factor = size[0] / frames.shape[2]
        Ks = scale_intrinsics(np.asarray(K, dtype=float), factor, factor)
        opts = SfmOptions(window=overlap, loop_keyframes=0)
        result = reconstruct_images(image_dir, names, Ks, size, opts, tmp_dir, min_frames=2)
    return {int(i): T for i, T in zip(result.image_index, result.T_sfm_camera, strict=True)}


def metric_scale(
    t_ns: np.ndarray, positions: np.ndarray, speed: tuple[np.ndarray, np.ndarray] | None, scale_m: float | None
) -> float:
    """Metres per SfM unit: the user's path length or the speed integrated over the registered span, over the SfM
    path length.

    :raises InputError: neither is given, or the camera did not move.
    """
    sfm_length = float(np.sum(np.linalg.norm(np.diff(positions, axis=0), axis=1)))
    if sfm_length <= 0:
        raise InputError("SfM: the camera does not move between the registered frames; cannot scale the path")
    if scale_m is not None:
        return scale_m / sfm_length
    if speed is None or len(speed[0]) == 0:
        raise InputError(SCALE_HINT)
    ts = (np.asarray(speed[0], dtype=np.int64) - t_ns[0]) * 1e-9
    tf = (np.asarray(t_ns, dtype=np.int64) - t_ns[0]) * 1e-9
    grid = np.linspace(tf[0], tf[-1], max(2, 20 * len(tf)))
    metric_length = float(np.trapezoid(np.abs(np.interp(grid, ts, np.asarray(speed[1], dtype=float))), grid))
    if metric_length <= 0:
        raise InputError("SfM: the speed series says the vehicle stands still; cannot scale the path")
    return metric_length / sfm_length


def sfm_track(
    frames: np.ndarray,
    K: np.ndarray,
    frame_times_ns: np.ndarray,
    speed: tuple[np.ndarray, np.ndarray] | None,
    scale_m: float | None,
    T_vehicle_camera: np.ndarray,
    max_width_px: int = 640,
) -> tuple[np.ndarray, np.ndarray]:
    """The vehicle's metric track from the images alone: (t_ns (M,), T_world_vehicle (M, 4, 4)) of the registered
    frames, world = the first registered vehicle pose (the pose source "sfm" turns it into per-frame poses).

    :param speed: (t_ns, speed_mps) to scale the path, or None.
    :param scale_m: the camera's path length over the sequence (m), used instead of the speed when given.
    :raises InputError: no scale source, or the reconstruction failed or registered under half of the frames.
    """
    if scale_m is None and (speed is None or len(speed[0]) == 0):
        raise InputError(SCALE_HINT)  # before spending minutes on the reconstruction
    frame_times_ns = np.asarray(frame_times_ns, dtype=np.int64)
    poses = reconstruct(frames, K, max_width_px=max_width_px)
    if len(poses) < max(2, len(frames) // 2):
        raise InputError(f"SfM registered only {len(poses)} of {len(frames)} frames; the poses would be guesses")
    idx = np.array(sorted(poses))
    T_sfm_camera = np.stack([poses[i] for i in idx])
    t_ns = frame_times_ns[idx]
    scale = metric_scale(t_ns, T_sfm_camera[:, :3, 3], speed, scale_m)
    T_sfm_camera[:, :3, 3] *= scale
    T_camera_vehicle = invert(np.asarray(T_vehicle_camera, dtype=float))
    T_sfm_vehicle = T_sfm_camera @ T_camera_vehicle
    T_world_vehicle = invert(T_sfm_vehicle[0]) @ T_sfm_vehicle
    return t_ns, T_world_vehicle
