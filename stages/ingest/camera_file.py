"""A camera calibration file for a video: OpenCV's YAML (`cv2.FileStorage`: camera_matrix, distortion_coefficients,
image_width/height) or ROS CameraInfo YAML (camera_calibration's ost.yaml: camera_matrix.data,
distortion_model, distortion_coefficients.data, image_width, image_height)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from drivesim.pipeline.config import load_yaml_text
from drivesim.pipeline.errors import InputError
from drivesim.pipeline.input_paths import refuse_special_file
from drivesim.sim.geometry import intrinsics_from_hfov, scale_intrinsics
from drivesim.stages.ingest.images import CameraModel


def _matrix(value: object, size: int) -> np.ndarray | None:
    data = value.get("data") if isinstance(value, dict) else value
    try:
        array = np.asarray(data, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        return None
    return array if array.size >= size else None


def _opencv_yaml(path: Path) -> dict:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        out = {}
        for key in ("camera_matrix", "K", "distortion_coefficients", "D", "image_width", "image_height"):
            node = storage.getNode(key)
            if node.empty():
                continue
            out[key] = node.mat() if node.isMap() else node.real()
        return out
    finally:
        storage.release()


def read_camera_file(path: Path, video_size: tuple[int, int]) -> CameraModel:
    """The camera of a calibration file, scaled to the video's size when it was calibrated at another one with
    the same aspect ratio.

    :raises InputError: unreadable file, no 3x3 camera matrix, or a different aspect ratio.
    """
    refuse_special_file(path, "a calibration YAML file")
    try:
        text = path.read_text()
        opencv = text.lstrip().startswith("%YAML") or "!!opencv-matrix" in text  # cv2.FileStorage's own YAML
        values = _opencv_yaml(path) if opencv else load_yaml_text(text)  # nesting limited, duplicate keys refused
    except (OSError, UnicodeDecodeError, yaml.YAMLError, cv2.error) as e:
        raise InputError(f"unreadable camera calibration file ({type(e).__name__})", path) from e
    if not isinstance(values, dict):
        raise InputError("camera calibration file is not a YAML mapping", path)
    K = _matrix(values.get("camera_matrix", values.get("K")), 9)
    if K is None:
        raise InputError("camera calibration file has no 3x3 camera_matrix", path)
    K = K[:9].reshape(3, 3)
    D = _matrix(values.get("distortion_coefficients", values.get("D")), 1)
    D = np.zeros(5) if D is None else D
    model = str(values.get("distortion_model", "plumb_bob"))
    if model not in ("plumb_bob", "rational_polynomial", "equidistant"):
        raise InputError(f"distortion model {model!r} is not supported (plumb_bob, rational_polynomial, equidistant)")
    width = int(values.get("image_width") or video_size[0])
    height = int(values.get("image_height") or video_size[1])
    if (width, height) != video_size:
        if abs(width / height - video_size[0] / video_size[1]) > 0.01:
            raise InputError(
                f"calibrated at {width}x{height}, the video is {video_size[0]}x{video_size[1]} (another aspect ratio)",
                path,
            )
        K = scale_intrinsics(K, video_size[0] / width, video_size[1] / height)
    model = model if np.any(np.abs(D) > 0) else "none"
    return CameraModel(K, D, model, K.copy(), np.eye(3), video_size[0], video_size[1])


def camera_from_hfov(hfov_deg: float, video_size: tuple[int, int]) -> CameraModel:
    """A distortion-free camera with the given horizontal field of view, principal point at the centre."""
    K = intrinsics_from_hfov(video_size[0], video_size[1], np.radians(hfov_deg))
    return CameraModel(K, np.zeros(5), "none", K.copy(), np.eye(3), video_size[0], video_size[1])
