"""`drivesim ingest` as a library call: any supported recording -> a trace folder."""

from __future__ import annotations

from pathlib import Path

from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.kitti import ingest_kitti_odometry, ingest_kitti_raw
from drivesim.stages.ingest.output import IngestResult
from drivesim.stages.ingest.ros import ingest_ros
from drivesim.stages.ingest.sources import detect_format


def ingest_recording(path: Path, cfg: IngestConfig, out_dir: Path) -> IngestResult:
    """Read the recording at `path` (ROS1 bag, rosbag2 folder, MCAP file, KITTI folder) into `out_dir`.

    Raises InputError/ConfigError with one line naming the file and the problem; `out_dir` is then incomplete
    and must be discarded (Workspace.write_artifact does that).
    """
    path = Path(path)
    fmt = detect_format(path)
    if fmt == "kitti_raw":
        return ingest_kitti_raw(path, cfg, out_dir)
    if fmt == "kitti_odometry":
        return ingest_kitti_odometry(path, cfg, out_dir)
    return ingest_ros(path, fmt, cfg, out_dir)
