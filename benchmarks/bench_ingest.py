"""Ingest throughput and peak memory against the bare read+decode limit; writes benchmarks/results/ingest.md.

Cases (ROS2 .mcap recordings generated in a temporary folder, uncompressed chunks as `ros2 bag record` writes by
default, with CameraInfo, NavSatFix 10 Hz, Imu 50 Hz, TwistStamped 20 Hz and /tf_static beside the camera):
  - raw:  960x600 sensor_msgs/Image bgr8
  - jpeg: 960x600 sensor_msgs/CompressedImage jpeg (quality 90, textured frames)
Each measurement runs in its own subprocess, which reports its wall time and its peak RSS (ru_maxrss):
  - bare:   read the camera messages with mcap + mcap_ros2 and np.frombuffer / cv2.imdecode them, nothing else
  - ingest: drivesim's ingest stage (all topics, decode, resize to 640 px, write the trace) into a temp folder
The memory claim (flat in the recording's length) is checked by ingesting a quarter-length recording too.

Usage: python benchmarks/bench_ingest.py [--quick] [--frames N]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path

import cv2
import numpy as np
from _lib.paths import use_folder
from _lib.report import write_markdown

from drivesim.bench.machine import machine_line

use_folder("tests")
from recordings import (  # noqa: E402  (the recording writers shared with the tests)
    START_NS,
    T_FOOTPRINT_LINK,
    T_LINK_CAMERA,
    Msg,
    camera_info_values,
    header,
    imu_values,
    navsat_values,
    textured_image,
    tf_static_values,
    twist_values,
    write_recording,
)

REPO = Path(__file__).resolve().parents[1]

WIDTH, HEIGHT = 960, 600
K = np.array([[600.0, 0.0, 479.5], [0.0, 600.0, 299.5], [0.0, 0.0, 1.0]])
CAMERA_TOPICS = {"raw": "/camera/image_raw", "jpeg": "/camera/image_raw/compressed"}
POOL = 24  # distinct frames cycled through (generating 2000 textures would dominate the run)


def _messages(kind: str, n_frames: int) -> Iterator[Msg]:
    """The recording's messages in log-time order, generated lazily (a raw recording is GBs)."""
    pool = [textured_image(WIDTH, HEIGHT, i, seed=i) for i in range(POOL)]
    if kind == "raw":
        payloads = [cv2.cvtColor(img, cv2.COLOR_RGB2BGR).tobytes() for img in pool]
    else:
        payloads = [
            cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
            for img in pool
        ]
    edges = [("base_footprint", "base_link", T_FOOTPRINT_LINK), ("base_link", "camera_optical", T_LINK_CAMERA)]
    yield Msg("/tf_static", "tf2_msgs/msg/TFMessage", START_NS, tf_static_values(START_NS, edges))
    dt = 100_000_000
    for i in range(n_frames):
        t = START_NS + i * dt + 1
        hdr = header(t, "camera_optical")
        if kind == "raw":
            values = {"header": hdr, "height": HEIGHT, "width": WIDTH, "encoding": "bgr8", "step": WIDTH * 3}
            yield Msg(CAMERA_TOPICS[kind], "sensor_msgs/msg/Image", t, {**values, "data": payloads[i % POOL]})
        else:
            values = {"header": hdr, "format": "jpeg", "data": payloads[i % POOL]}
            yield Msg(CAMERA_TOPICS[kind], "sensor_msgs/msg/CompressedImage", t, values)
        yield Msg("/camera/camera_info", "sensor_msgs/msg/CameraInfo", t, camera_info_values(t, WIDTH, HEIGHT, K))
        yield Msg("/gps/fix", "sensor_msgs/msg/NavSatFix", t + 1, navsat_values(t + 1, 49.0 + 1e-6 * i, 8.4))
        for k in range(5):
            tk = t + 2 + k * dt // 5
            yield Msg("/imu/data", "sensor_msgs/msg/Imu", tk, imu_values(tk))
        for k in range(2):
            tk = t + 3 + k * dt // 2
            yield Msg("/vehicle/twist", "geometry_msgs/msg/TwistStamped", tk, twist_values(tk, 10.0))


def make_recording(folder: Path, kind: str, n_frames: int) -> Path:
    """Write the `kind` recording of `n_frames` camera frames as an uncompressed .mcap."""
    path = folder / f"{kind}_{n_frames}.mcap"
    write_recording(path, "mcap", _messages(kind, n_frames), mcap_compression="none")
    return path


# ---------------------------------------------------------------- child processes


def _child_bare(recording: Path, kind: str) -> dict:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    factory = DecoderFactory()
    frames = 0
    cpu0 = _cpu_s()
    t0 = time.perf_counter()
    with open(recording, "rb") as f:
        reader = make_reader(f)
        # Every message is read and decoded, as ingest must; only the camera's are turned into images.
        decoders: dict[int, object] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            decode = decoders.get(channel.id)
            if decode is None:
                decode = decoders[channel.id] = factory.decoder_for(channel.message_encoding, schema)
            msg = decode(message.data)
            if channel.topic != CAMERA_TOPICS[kind]:
                continue
            if kind == "raw":
                img = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width, 3)
            else:
                img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
            frames += int(img.shape[0] > 0)
    return {"frames": frames, "wall_s": time.perf_counter() - t0, "cpu_s": _cpu_s() - cpu0}


def _child_ingest(recording: Path, interpolation: str) -> dict:
    from drivesim.pipeline.hashing import sha256_file
    from drivesim.stages.ingest.config import IngestConfig
    from drivesim.stages.ingest.run import ingest_recording

    out = Path(tempfile.mkdtemp(prefix="bench-trace-", dir=recording.parent))
    try:
        cfg = IngestConfig.model_validate({"image": {"interpolation": interpolation}})
        cpu0 = _cpu_s()
        t0 = time.perf_counter()
        result = ingest_recording(recording, cfg, out)
        wall_s = time.perf_counter() - t0
        cpu_s = _cpu_s() - cpu0
        t1 = time.perf_counter()
        for file in out.iterdir():  # what Workspace.write_artifact adds: the manifest's output hashes
            sha256_file(file)
        hash_s = time.perf_counter() - t1
    finally:
        shutil.rmtree(out, ignore_errors=True)
    return {"frames": result.summary["frame_count"], "wall_s": wall_s, "cpu_s": cpu_s, "hash_s": hash_s}


def _cpu_s() -> float:
    """User + system CPU seconds of this process, all threads (less sensitive to a busy machine than wall time)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM: unlike ru_maxrss it does not inherit the parent's peak)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _run_child(mode: str, recording: Path, kind: str, interpolation: str = "area") -> dict:
    out = subprocess.run(
        [sys.executable, __file__, "--child", mode, "--recording", str(recording), "--kind", kind]
        + ["--interpolation", interpolation],
        capture_output=True,
        text=True,
        check=False,
    )
    if out.returncode != 0:
        raise RuntimeError(f"{mode} on {recording} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


# ---------------------------------------------------------------- main


def main() -> None:
    """Run the benchmark (or, with the hidden worker flags, one measuring subprocess) and write its results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: 200 frames")
    parser.add_argument("--frames", type=int, default=2000, help="camera frames per recording (default 2000)")
    parser.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" / "ingest.md")
    parser.add_argument("--child", choices=["bare", "ingest"], help=argparse.SUPPRESS)
    parser.add_argument("--recording", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--kind", help=argparse.SUPPRESS)
    parser.add_argument("--interpolation", default="area", help=argparse.SUPPRESS)
    args = parser.parse_args()

    if args.child:
        if args.child == "bare":
            result = _child_bare(args.recording, args.kind)
        else:
            result = _child_ingest(args.recording, args.interpolation)
        result["peak_rss_mb"] = _peak_rss_mb()
        print(json.dumps(result))
        return

    rows = _measure_rows(200 if args.quick else args.frames)
    lines = [
        "# Ingest throughput",
        "",
        f"Machine: {machine_line()}; "
        f"date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}; "
        f"command: `python benchmarks/bench_ingest.py{' --quick' if args.quick else ''}`.",
        "",
        f"Recordings: ROS2 .mcap (uncompressed chunks), camera {WIDTH}x{HEIGHT} at 10 Hz plus CameraInfo, NavSatFix,",
        "Imu 50 Hz, TwistStamped 20 Hz, /tf_static. Ingest stores 640x400 RGB frames, resized with cv2.INTER_AREA",
        "(default) or INTER_LINEAR (`--set image.interpolation=linear`). *bare* = read and decode every message with",
        "mcap + mcap_ros2 (as ingest must) and `np.frombuffer` / `cv2.imdecode` (full size) the camera's, nothing",
        "else: no undistortion, resize or writing. Peak RSS = VmHWM of",
        "the measuring subprocess. *hash* = the manifest's sha256 of the outputs that `Workspace.write_artifact`",
        "adds after the stage (not included in ingest frames/s). CPU ms/frame = user + system time of all threads:",
        "ingest decodes and resizes on two worker threads, so on an idle 2-core machine its wall time approaches",
        "half its CPU time; on a busy one (the load average is printed below) frames/s understates it.",
        "",
        "| camera | resize | frames | recording MB | bare frames/s | ingest frames/s | ingest / bare "
        "| bare CPU ms/frame | ingest CPU ms/frame | hash s | bare peak RSS MB | ingest peak RSS MB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    lines += [_table_row(*row) for row in rows]
    lines += [
        "",
        f"Load average (1, 5, 15 min) at the end of the run: {', '.join(f'{x:.1f}' for x in os.getloadavg())}.",
    ]
    keys = ("camera", "resize", "frames", "recording_mb", "bare", "ingest")
    raw = {"quick": args.quick, "rows": [dict(zip(keys, r, strict=True)) for r in rows]}
    write_markdown(args.out, [*lines, ""], raw)


def _measure_rows(n: int) -> list[tuple]:
    """(camera kind, resize, frames, recording MB, bare figures, ingest figures) per recording: raw and JPEG camera
    recordings of n / 4 and n frames, each ingested in a subprocess (the longer one also read bare and resized
    linearly)."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-ingest-") as tmp:
        folder = Path(tmp)
        for kind in ("raw", "jpeg"):
            for frames in (n // 4, n):
                t0 = time.perf_counter()
                rec = make_recording(folder, kind, frames)
                size_mb = rec.stat().st_size / 1e6
                print(
                    f"{kind}: {frames} frames, {size_mb:.0f} MB written in {time.perf_counter() - t0:.1f} s", flush=True
                )
                bare = _run_child("bare", rec, kind) if frames == n else None
                ingest = _run_child("ingest", rec, kind)
                rows.append((kind, "area", frames, size_mb, bare, ingest))
                print(f"  bare {bare}\n  ingest {ingest}", flush=True)
                if frames == n:
                    linear = _run_child("ingest", rec, kind, "linear")
                    rows.append((kind, "linear", frames, size_mb, bare, linear))
                    print(f"  ingest linear {linear}", flush=True)
                rec.unlink()
    return rows


def _table_row(kind: str, interpolation: str, frames: int, size_mb: float, bare: dict | None, ingest: dict) -> str:
    """One markdown row of the ingest table."""
    name = "Image bgr8" if kind == "raw" else "CompressedImage jpeg"
    ingest_fps = ingest["frames"] / ingest["wall_s"]
    ingest_cpu = 1e3 * ingest["cpu_s"] / ingest["frames"]
    if bare is not None:
        bare_fps = bare["frames"] / bare["wall_s"]
        bare_cpu = 1e3 * bare["cpu_s"] / bare["frames"]
        bare_cols = (
            f"{bare_fps:.0f}",
            f"{ingest_fps / bare_fps:.2f}",
            f"{bare_cpu:.1f}",
            f"{bare['peak_rss_mb']:.0f}",
        )
    else:
        bare_cols = ("–", "–", "–", "–")
    return (
        f"| {name} | {interpolation} | {frames} | {size_mb:.0f} | {bare_cols[0]} | {ingest_fps:.0f} | "
        f"{bare_cols[1]} | {bare_cols[2]} | {ingest_cpu:.1f} | {ingest['hash_s']:.1f} | {bare_cols[3]} | "
        f"{ingest['peak_rss_mb']:.0f} |"
    )


if __name__ == "__main__":
    main()
