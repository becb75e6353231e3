"""Rigid transforms and camera frames shared by the whole engine.

Conventions (DESIGN §4): vehicle x forward, y left, z up (REP-103); camera optical x right, y down, z forward;
world = local ENU (x east, y north, z up). A transform `T_a_b` is a 4x4 matrix mapping points in frame b to frame a
(p_a = T_a_b @ p_b). Angles in radians, distances in metres.
"""

from __future__ import annotations

import numpy as np

# Rotation taking optical-frame vectors to a vehicle-aligned frame (x fwd, y left, z up): optical z (forward)
# -> vehicle x, optical x (right) -> vehicle -y, optical y (down) -> vehicle -z.
R_VEHICLE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def rot_z(yaw_rad: float) -> np.ndarray:
    """3x3 rotation about +z (counter-clockwise seen from above)."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(pitch_rad: float) -> np.ndarray:
    """3x3 rotation about +y."""
    c, s = np.cos(pitch_rad), np.sin(pitch_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(roll_rad: float) -> np.ndarray:
    """3x3 rotation about +x."""
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def se3(rotation: np.ndarray, translation_m: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transform from a 3x3 rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = rotation
    T[:3, 3] = translation_m
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (or a stack of them, shape (..., 4, 4))."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def pose_2d(x_m: float, y_m: float, yaw_rad: float, z_m: float = 0.0) -> np.ndarray:
    """T_world_vehicle for a vehicle at (x, y, z) heading `yaw_rad` (flat ground)."""
    return se3(rot_z(yaw_rad), np.array([x_m, y_m, z_m]))


def camera_mount(
    x_m: float, y_m: float, height_m: float, yaw_rad: float = 0.0, pitch_down_rad: float = 0.0, roll_rad: float = 0.0
) -> np.ndarray:
    """T_vehicle_camera for a camera at (x, y, height) looking forward, pitched down by `pitch_down_rad`."""
    R = rot_z(yaw_rad) @ rot_y(pitch_down_rad) @ rot_x(roll_rad) @ R_VEHICLE_OPTICAL
    return se3(R, np.array([x_m, y_m, height_m]))


def intrinsics(fx_px: float, fy_px: float, cx_px: float, cy_px: float) -> np.ndarray:
    """3x3 pinhole intrinsic matrix."""
    return np.array([[fx_px, 0.0, cx_px], [0.0, fy_px, cy_px], [0.0, 0.0, 1.0]])


def intrinsics_from_hfov(width_px: int, height_px: int, hfov_rad: float) -> np.ndarray:
    """Square-pixel intrinsics with the principal point at the image centre and the given horizontal field of view."""
    f = 0.5 * width_px / np.tan(0.5 * hfov_rad)
    return intrinsics(f, f, 0.5 * width_px, 0.5 * height_px)


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics of the same camera after resizing the image by (sx, sy) (pixel-centre convention)."""
    K2 = K.copy().astype(float)
    K2[0, 0] *= sx
    K2[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K2[1, 1] *= sy
    K2[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K2


def yaw_of(T: np.ndarray) -> np.ndarray:
    """Heading (rad) of the x axis of a transform (or stack) projected on the ground plane."""
    return np.arctan2(T[..., 1, 0], T[..., 0, 0])


def wrap_angle(angle_rad: np.ndarray | float) -> np.ndarray | float:
    """Angle wrapped to [-pi, pi)."""
    return (np.asarray(angle_rad) + np.pi) % (2 * np.pi) - np.pi
