"""The trace validator that later stages call: a good trace passes, each kind of damage is one clear error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from recordings import drive_messages, write_recording

from drivesim.pipeline.errors import InputError
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.run import ingest_recording
from drivesim.stages.ingest.trace import validate_trace


@pytest.fixture
def trace(tmp_path: Path) -> Path:
    rec = write_recording(tmp_path / "rec.mcap", "mcap", drive_messages(n_frames=4, with_ground_truth=True))
    out = tmp_path / "trace"
    out.mkdir()
    ingest_recording(rec, IngestConfig(ground_truth_depth=True), out)
    return out


def test_ground_truth_depth_is_kept_only_when_asked_for(tmp_path: Path) -> None:
    """A synthetic recording's depth truth (4 bytes per pixel and frame) is opt-in; its poses are always kept."""
    rec = write_recording(tmp_path / "rec.mcap", "mcap", drive_messages(n_frames=4, with_ground_truth=True))
    out = tmp_path / "default"
    out.mkdir()
    ingest_recording(rec, IngestConfig(), out)
    info = validate_trace(out)
    assert not info.has_gt_depth and not (out / "gt_depth.npy").exists()
    assert "ground_truth" in info.series


def test_a_fresh_trace_is_valid(trace: Path) -> None:
    info = validate_trace(trace)
    assert info.frame_count == 4 and info.has_gt_depth
    assert set(info.series) == {"gps", "imu", "speed", "ground_truth"}
    assert info.load_series("odometry") is None


def test_missing_frames(trace: Path) -> None:
    (trace / "frames.imgs").unlink()
    with pytest.raises(InputError, match=r"frames.imgs: invalid trace: missing file"):
        validate_trace(trace)


def test_truncated_frames(trace: Path) -> None:
    with open(trace / "frames.imgs", "r+b") as f:
        f.truncate(f.seek(0, 2) - 100)
    with pytest.raises(InputError, match=r"frames.imgs: invalid trace: unreadable image stack .*truncated"):
        validate_trace(trace)


def test_truncated_frames_of_an_older_npy_trace(trace: Path) -> None:
    """A trace written as frames.npy by an earlier version still validates; a truncated one is refused."""
    frames = np.asarray(validate_trace(trace).frames())
    (trace / "frames.imgs").unlink()
    np.save(trace / "frames.npy", frames)
    assert validate_trace(trace).frame_count == 4
    np.testing.assert_array_equal(validate_trace(trace).frames()[3], frames[3])
    with open(trace / "frames.npy", "r+b") as f:
        f.truncate(f.seek(0, 2) - 100)
    with pytest.raises(InputError, match=r"shorter than its header says"):
        validate_trace(trace)


def test_times_must_increase(trace: Path) -> None:
    times = np.load(trace / "frame_times_ns.npy")
    times[2] = times[1]
    np.save(trace / "frame_times_ns.npy", times)
    with pytest.raises(InputError, match=r"frame times are not strictly increasing"):
        validate_trace(trace)


def test_calibration_keys_and_shapes(trace: Path) -> None:
    calib = json.loads((trace / "calibration.json").read_text())
    calib["T_vehicle_camera"] = np.diag([2.0, 1, 1, 1]).tolist()
    (trace / "calibration.json").write_text(json.dumps(calib))
    with pytest.raises(InputError, match=r"T_vehicle_camera must be a 4x4 rigid transform"):
        validate_trace(trace)
    del calib["K"]
    (trace / "calibration.json").write_text(json.dumps(calib))
    with pytest.raises(InputError, match=r"missing keys \['K'\]"):
        validate_trace(trace)


def test_series_columns(trace: Path) -> None:
    with np.load(trace / "gps.npz") as data:
        arrays = {k: data[k] for k in data.files if k != "status"}
    np.savez(trace / "gps.npz", **arrays)
    with pytest.raises(InputError, match=r"gps.npz: invalid trace: no status array"):
        validate_trace(trace)
