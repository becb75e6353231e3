"""Camera-to-vehicle transform from a static tf tree (`/tf_static`)."""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from drivesim.sim.geometry import invert, se3


def transform_from_msg(translation: Any, rotation: Any) -> np.ndarray:
    """4x4 from a geometry_msgs Transform's translation (Vector3) and rotation (Quaternion).

    A zero quaternion (an unset field) is the identity; a non-finite one gives NaN, for the caller to refuse.
    """
    quat = np.array([rotation.x, rotation.y, rotation.z, rotation.w], dtype=float)
    t = np.array([translation.x, translation.y, translation.z], dtype=float)
    if not np.all(np.isfinite(quat)):
        return se3(np.full((3, 3), np.nan), t)
    if np.linalg.norm(quat) < 1e-9:
        quat = np.array([0.0, 0.0, 0.0, 1.0])
    return se3(Rotation.from_quat(quat).as_matrix(), t)


def pose_from_msg(position: Any, orientation: Any) -> np.ndarray:
    """4x4 from a geometry_msgs Pose's position (Point) and orientation (Quaternion)."""
    return transform_from_msg(position, orientation)


def _strip(frame: str) -> str:
    return frame.lstrip("/")


class StaticTfTree:
    """The static transforms of a recording: T_parent_child edges, looked up in either direction."""

    def __init__(self) -> None:
        self._edges: dict[str, dict[str, np.ndarray]] = {}

    def add_message(self, msg: Any) -> None:
        """Add every transform of a TFMessage."""
        for tf in msg.transforms:
            parent, child = _strip(tf.header.frame_id), _strip(tf.child_frame_id)
            T = transform_from_msg(tf.transform.translation, tf.transform.rotation)
            self._edges.setdefault(parent, {})[child] = T
            self._edges.setdefault(child, {})[parent] = invert(T)

    @property
    def frames(self) -> set[str]:
        """Every frame name in the tree."""
        return set(self._edges)

    def lookup(self, target: str, source: str) -> np.ndarray | None:
        """T_target_source (maps points in `source` to `target`), or None when the frames are not connected."""
        target, source = _strip(target), _strip(source)
        if target == source:
            return np.eye(4)
        if target not in self._edges or source not in self._edges:
            return None
        # Breadth-first search from target; T accumulates T_target_frame.
        seen = {target: np.eye(4)}
        queue = deque([target])
        while queue:
            frame = queue.popleft()
            for neighbour, T_frame_neighbour in self._edges[frame].items():
                if neighbour in seen:
                    continue
                seen[neighbour] = seen[frame] @ T_frame_neighbour
                if neighbour == source:
                    return seen[neighbour]
                queue.append(neighbour)
        return None
