"""`sensor_msgs/PointCloud2` scans into the trace: points in the vehicle frame, appended to one .npy as they arrive.

lidar_points.npy holds every scan's points (x, y, z in metres in the vehicle frame, intensity or NaN), concatenated;
lidar_scans.npz says which rows belong to which scan. The total point count is unknown until the end, so the .npy
header is written with room to spare and rewritten with the real row count when the file is closed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from drivesim.stages.ingest.output import GrowableArray, npy_header

# sensor_msgs/PointField datatypes
_POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_HEADER_BYTES = 128  # magic + version + length + a dict with a 12-digit row count fits, padded to 64-byte alignment


class PointCloudError(ValueError):
    """A PointCloud2 message that cannot be read as x, y, z points."""


def cloud_points(msg: Any) -> np.ndarray:
    """(M, 4) float32 x, y, z, intensity (NaN when absent) of a PointCloud2 in its own frame, invalid points dropped."""
    fields = {f.name: f for f in msg.fields}
    missing = [n for n in "xyz" if n not in fields]
    if missing:
        raise PointCloudError(f"PointCloud2 without field(s) {', '.join(missing)}")
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for name in ("x", "y", "z", "intensity"):
        if name not in fields:
            continue
        f = fields[name]
        if f.datatype not in _POINTFIELD_DTYPES:
            raise PointCloudError(f"PointCloud2 field {name} has unknown datatype {f.datatype}")
        names.append(name)
        formats.append(order + _POINTFIELD_DTYPES[f.datatype])
        offsets.append(int(f.offset))
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": int(msg.point_step)})
    n_points = int(msg.width) * int(msg.height)
    data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, np.ndarray) else msg.data, dtype=np.uint8)
    row_step = int(msg.row_step) or int(msg.width) * int(msg.point_step)
    if int(msg.height) > 1 and row_step != int(msg.width) * int(msg.point_step):
        rows = data[: int(msg.height) * row_step].reshape(int(msg.height), row_step)
        data = np.ascontiguousarray(rows[:, : int(msg.width) * int(msg.point_step)]).ravel()
    if data.size < n_points * int(msg.point_step):
        raise PointCloudError(f"PointCloud2 data has {data.size} bytes for {n_points} points of {msg.point_step}")
    points = data[: n_points * int(msg.point_step)].view(dtype)
    out = np.empty((n_points, 4), np.float32)
    for i, name in enumerate(("x", "y", "z", "intensity")):
        out[:, i] = points[name] if name in names else np.nan
    return out[np.all(np.isfinite(out[:, :3]), axis=1)]


class LidarWriter:
    """Appends scans to lidar_points.npy and records their stamps and row ranges for lidar_scans.npz.

    :param out_dir: the trace folder.
    :param T_vehicle_lidar: 4x4 lidar frame -> vehicle frame, or None when the cloud is already in the vehicle frame.
    """

    def __init__(self, out_dir: Path, T_vehicle_lidar: np.ndarray | None) -> None:
        self.points_path = out_dir / "lidar_points.npy"
        self.scans_path = out_dir / "lidar_scans.npz"
        self.T = T_vehicle_lidar
        self.rows = 0
        self.t_ns = GrowableArray((), np.int64)
        self.start = GrowableArray((), np.int64)
        self.count = GrowableArray((), np.int64)
        self._file = open(self.points_path, "wb")  # noqa: SIM115 (closed by close())
        self._file.write(b"\0" * _HEADER_BYTES)

    def add(self, t_ns: int, points: np.ndarray) -> None:
        """Append one scan (points (M, 4) in the lidar frame)."""
        if self.T is not None and len(points):
            xyz = points[:, :3].astype(np.float64) @ self.T[:3, :3].T + self.T[:3, 3]
            points = np.column_stack([xyz.astype(np.float32), points[:, 3:4]])
        self._file.write(np.ascontiguousarray(points, dtype="<f4").tobytes())
        self.t_ns.append(t_ns)
        self.start.append(self.rows)
        self.count.append(len(points))
        self.rows += len(points)

    def close(self) -> int:
        """Write the final .npy header and lidar_scans.npz; the number of scans."""
        self._file.seek(0)
        self._file.write(npy_header((self.rows, 4), np.dtype("<f4"), _HEADER_BYTES))
        self._file.close()
        np.savez(self.scans_path, t_ns=self.t_ns.array(), start=self.start.array(), count=self.count.array())
        return len(self.t_ns)

    def abort(self) -> None:
        """Close the file without finishing it (the whole trace is discarded)."""
        self._file.close()
