"""`drivesim ingest` on the command line: success, freshness, one-line errors with exit 2, Ctrl-C."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cli_helpers import REAL_DATA, interruptible, run_main_captured
from recordings import (
    START_NS,
    Msg,
    drive_messages,
    navsat_values,
    textured_image,
    write_recording,
)

REAL = REAL_DATA
HUSKY = REAL / "husky_gps_imu_odom.bag"


def _run(monkeypatch, capsys, ws: Path, *args: str) -> tuple[int, str, str]:
    """Run `drivesim --workspace ws ARGS` in-process; (exit code, stdout, stderr)."""
    return run_main_captured(ws, *args, monkeypatch=monkeypatch, capsys=capsys)


def _assert_refused(code: int, err: str, ws: Path, *fragments: str) -> None:
    assert code == 2
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1, err
    for fragment in fragments:
        assert fragment in lines[0]
    assert not (ws / "trace").exists()
    assert not any(p.name.startswith(".tmp-") for p in ws.glob("*")) if ws.exists() else True


def test_ingest_writes_the_trace_then_is_fresh(tmp_path: Path, monkeypatch, capsys) -> None:
    rec = write_recording(tmp_path / "drive.mcap", "mcap", drive_messages(n_frames=5))
    ws = tmp_path / "ws"
    code, out, _ = _run(monkeypatch, capsys, ws, "ingest", str(rec))
    assert code == 0, out
    assert "5 frames 64x40" in out and "camera: /camera/image_raw" in out
    manifest = json.loads((ws / "trace" / "manifest.json").read_text())
    summary = manifest["summary"]
    assert summary["frame_count"] == 5 and summary["width_px"] == 64 and summary["height_px"] == 40
    assert summary["duration_s"] == pytest.approx(0.4)
    assert summary["sensors"]["gps"] == {"topic": "/gps/fix", "type": "sensor_msgs/msg/NavSatFix", "message_count": 5}
    assert "frames.imgs" in manifest["outputs"]

    code, out, _ = _run(monkeypatch, capsys, ws, "ingest", str(rec))
    assert code == 0 and "nothing to do" in out
    # a different working width is a different artifact: it is redone
    code, out, _ = _run(monkeypatch, capsys, ws, "ingest", str(rec), "--set", "image.width_px=32")
    assert code == 0 and "5 frames 32x20" in out


def test_topic_option(tmp_path: Path, monkeypatch, capsys) -> None:
    rec = write_recording(tmp_path / "drive.mcap", "mcap", drive_messages(n_frames=3))
    ws = tmp_path / "ws"
    code, out, _ = _run(monkeypatch, capsys, ws, "ingest", str(rec), "--topic", "camera=/camera/image_raw")
    assert code == 0 and "chosen with --topic camera" in out
    manifest = json.loads((ws / "trace" / "manifest.json").read_text())
    assert manifest["config"]["topics"]["camera"] == "/camera/image_raw"
    code, _, err = _run(monkeypatch, capsys, tmp_path / "ws2", "ingest", str(rec), "--topic", "radar=/x")
    _assert_refused(code, err, tmp_path / "ws2", "unknown role 'radar'", "roles: camera, camera_info")


def test_no_pose_source_is_exit_2_without_trace(tmp_path: Path, monkeypatch, capsys) -> None:
    rec = write_recording(tmp_path / "cam.mcap", "mcap", drive_messages(n_frames=3, with_gps=False))
    ws = tmp_path / "ws"
    code, _, err = _run(monkeypatch, capsys, ws, "ingest", str(rec))
    _assert_refused(code, err, ws, str(rec), "no pose source")


def test_no_camera_is_exit_2_without_trace(tmp_path: Path, monkeypatch, capsys) -> None:
    msgs = [
        Msg("/fix", "sensor_msgs/msg/NavSatFix", START_NS + i, navsat_values(START_NS + i, 49.0, 8.4)) for i in range(3)
    ]
    rec = write_recording(tmp_path / "gps.bag", "ros1", msgs)
    ws = tmp_path / "ws"
    code, _, err = _run(monkeypatch, capsys, ws, "ingest", str(rec))
    _assert_refused(code, err, ws, str(rec), "no camera topic", "found: /fix NavSatFix")


def test_failed_reingest_keeps_the_previous_trace(tmp_path: Path, monkeypatch, capsys) -> None:
    good = write_recording(tmp_path / "good.mcap", "mcap", drive_messages(n_frames=4))
    bad = write_recording(tmp_path / "bad.mcap", "mcap", drive_messages(n_frames=4, stamps_ns=[0, 2, 1, 3]))
    ws = tmp_path / "ws"
    assert _run(monkeypatch, capsys, ws, "ingest", str(good))[0] == 0
    before = (ws / "trace" / "manifest.json").read_text()
    code, _, err = _run(monkeypatch, capsys, ws, "ingest", str(bad))
    assert code == 2 and "stamps not strictly increasing" in err
    assert (ws / "trace" / "manifest.json").read_text() == before


def test_missing_path_is_exit_2(tmp_path: Path, monkeypatch, capsys) -> None:
    ws = tmp_path / "ws"
    code, _, err = _run(monkeypatch, capsys, ws, "ingest", str(tmp_path / "nope.bag"))
    _assert_refused(code, err, ws, "nope.bag: no such file or folder")


def test_husky_bag_is_refused_by_the_cli(tmp_path: Path, monkeypatch, capsys) -> None:
    if not HUSKY.is_file():
        pytest.skip(f"real data not available at {HUSKY}")
    ws = tmp_path / "ws"
    code, _, err = _run(monkeypatch, capsys, ws, "ingest", str(HUSKY))
    _assert_refused(code, err, ws, str(HUSKY), "no camera topic", "/fix NavSatFix")


@pytest.mark.slow
def test_ctrl_c_leaves_no_artifact_and_the_next_run_succeeds(tmp_path: Path) -> None:
    w, h = 640, 400
    pool = [textured_image(w, h, i) for i in range(8)]
    msgs = drive_messages(n_frames=250, width=w, height=h, image_fn=lambda i: pool[i % 8], with_imu=False)
    rec = write_recording(tmp_path / "big.mcap", "mcap", msgs, mcap_compression="none")
    ws = tmp_path / "ws"
    cmd = [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), "ingest", str(rec)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=interruptible)
    # wait until frames are being written into the temporary artifact, then interrupt
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        tmp = [p for p in ws.glob(".tmp-trace-*") if (p / "frames.imgs").is_file()] if ws.is_dir() else []
        if tmp and (tmp[0] / "frames.imgs").stat().st_size > 5_000_000:
            break
        time.sleep(0.05)
    else:
        proc.kill()
        pytest.fail("ingest never started writing frames")
    os.kill(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "interrupted" in err
    assert not (ws / "trace").exists()
    assert not list(ws.glob(".tmp-*"))

    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert json.loads((ws / "trace" / "manifest.json").read_text())["summary"]["frame_count"] == 250
