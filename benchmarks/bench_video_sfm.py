"""Plain video in (issue 23): the shared KITTI raw drive's grey frames made into an MP4, ingested with only the
video and either `--camera-height-m 1.65` or a GPX track made from the OXTS fixes; the SfM camera path checked
against the OXTS camera path. Two more camera-height rows show how far the estimated focal length (and so the scale)
depends on the input: the same frames as an image folder (lossless PNGs), and the KITTI odometry snippet (another
drive, sequence 06) as an MP4. A last row gives the MP4 the OXTS fixes as GoPro GPMF telemetry inside it and no flag.
Writes benchmarks/results/video_sfm.md.

    python benchmarks/bench_video_sfm.py
    python benchmarks/bench_video_sfm.py --only height     # just the camera-height run
    python benchmarks/bench_video_sfm.py --timing   # with nothing else running: SfM time alone on the machine;
                                                    # replaces only the "SfM time on a quiet machine" paragraph
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from _lib.report import table_records, update_json, write_markdown
from scipy.spatial.transform import Rotation

from drivesim.bench.machine import machine_line
from drivesim.sim.geometry import se3
from drivesim.stages.ingest.kitti import IMU_HEIGHT_M, kitti_raw_extrinsics, parse_timestamps, read_oxts
from drivesim.stages.ingest.scale import fit_similarity
from drivesim.stages.preprocess.poses import enu_transformer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from gopro_mp4 import add_gopro_gps, gpmf_payload  # noqa: E402  (the tests' GoPro MP4 writer)

DRIVE = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "kitti_raw" / "2011_09_26"
    / "2011_09_26_drive_0001_sync"
)  # fmt: skip
ODOMETRY = DRIVE.parents[2] / "kitti_odometry_straight"
RESULTS = Path(__file__).resolve().parent / "results" / "video_sfm.md"
NOTES = (
    "Notes. The camera ran at 9.69 Hz (107 intervals in 11.04 s of image_00 timestamps) but the MP4 says 10 fps, so "
    "the video's clock runs 3.1 % fast against the GPX's: GPS positions matched at video times fall short of the "
    "frames', which shrinks the GPX row's scale (a real video's container clock is the same kind of risk). The "
    "camera-height rows' scale has no clock in it: it follows the focal length SfM estimates (the image heights of "
    "road points, and so the camera's height over the fitted road, scale with 1 / focal length; with the focal "
    "given, third row, the road plane gives the path within 1 %). How the focal length is estimated (changed "
    "2026-11-27, `stages/ingest/sfm.py`): the model is mapped with a 90 degree guess held fixed, then one global "
    "bundle adjustment frees the focal length. On this drive (8 degrees of yaw in 11 s) the reprojection error is "
    "nearly flat in it: on one mapping (20-frame window), with the focal held at 76, 80, 82, 84, 88 and 92 degrees, "
    "the sum of squared residuals (86,171 observations) was 36,053 / 36,040 / 36,040 / 36,044 / 36,072 / 36,131 "
    "px^2, 0.06 % between 81 and 87 degrees, so a few outlying matches decided the least-squares optimum: with the "
    "previous settings (least squares, each frame matched with the next 10) this MP4 gave 84.6-84.7 degrees (path "
    "-5.0 to -5.1 %), the same frames read from their PNGs 87.8 (-10.9 %), the odometry MP4 82.0 (-0.2 %). A "
    "20-frame window alone (least squares) gave 81.3-81.4 degrees on the MP4 (-0.1 to -0.7 %, three runs; windows "
    "15, 30, 40: 82.3, 80.9, 81.4) but 87.5 on the PNGs (-10.5 %) and 83.0 on the odometry drive (-2.1 %). A Cauchy "
    "loss (scale 0.5 px; the inliers' residuals: median 0.2 px, 99th percentile 2.4 px) in that one adjustment, "
    "with the 20-frame window (now the defaults), gives 83.5-83.9 degrees on all three inputs (this table; the MP4 "
    "83.6 and 83.5 in two earlier runs, paths -4.6 and -4.1 %): the estimate no longer depends on the encoding, and "
    "on both KITTI drives it is 2.1-2.4 degrees wider than the truth, so the camera-height paths come out 3.7-4.6 % "
    "short, inside the 5 % target but by less than 1 point. With the Cauchy loss and a 10-frame window the MP4 gave "
    "85.4 degrees (-7.3 %); the true principal point held fixed instead of the image centre moved the Cauchy "
    "estimate by 0.5 degree (83.1 / 83.5). On the tests' rendered drive (true 90 degrees; a noise texture that "
    "aliases in the distance) least squares gives 82-85 degrees and the Cauchy loss 79.3-79.8: not a benchmark of "
    "focal accuracy, the test checks that the scale follows the focal length printed."
)
FPS = 10.0
TIMING_HEAD = "SfM time on a quiet machine"


def make_video(out: Path) -> int:
    """The drive's image_00 frames (grey, 1242x375) as an MP4 at 10 fps (OpenCV's mp4v encoder); frame count."""
    files = sorted((DRIVE / "image_00" / "data").glob("*.png"))
    first = cv2.imread(str(files[0]))
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (first.shape[1], first.shape[0]))
    for f in files:
        writer.write(cv2.imread(str(f)))
    writer.release()
    return len(files)


def make_odometry_video(out: Path) -> np.ndarray:
    """The KITTI odometry snippet's left frames (grey, 1226x370) as an MP4 at 10 fps; their true camera centres (m)."""
    files = sorted((ODOMETRY / "image_l").glob("*.png"))
    first = cv2.imread(str(files[0]))
    writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"mp4v"), FPS, (first.shape[1], first.shape[0]))
    for f in files:
        writer.write(cv2.imread(str(f)))
    writer.release()
    return np.loadtxt(ODOMETRY / "poses.txt").reshape(-1, 3, 4)[:, :, 3]


def oxts_camera_track() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(times ns, OXTS rows, camera-0 centres in local ENU (N, 3) m) of every frame."""
    T_vehicle_camera, _, _ = kitti_raw_extrinsics(DRIVE.parent, 0)
    times, oxts = read_oxts(DRIVE, 100_000_000, use_timestamps=True)
    e, n, u = enu_transformer(oxts[0, 0], oxts[0, 1], oxts[0, 2]).transform(oxts[:, 1], oxts[:, 0], oxts[:, 2])
    T_enu_imu = np.tile(np.eye(4), (len(oxts), 1, 1))
    T_enu_imu[:, :3, :3] = Rotation.from_euler("ZYX", oxts[:, [5, 4, 3]]).as_matrix()
    T_enu_imu[:, :3, 3] = np.column_stack([e, n, u])
    T_imu_camera = se3(np.eye(3), np.array([0.0, 0.0, -IMU_HEIGHT_M])) @ T_vehicle_camera
    return times, oxts, (T_enu_imu @ T_imu_camera)[:, :3, 3]


def gopro_payloads(times_ns: np.ndarray, oxts: np.ndarray) -> list[bytes]:
    """The OXTS fixes as GoPro GPMF samples: one per second from the first fix, each starting at its first fix."""
    second = (times_ns - times_ns[0]) // 1_000_000_000
    payloads = []
    for s in np.unique(second):
        rows = np.flatnonzero(second == s)
        utc = dt.datetime.fromtimestamp(times_ns[rows[0]] / 1e9, dt.UTC)
        fixes = np.column_stack([oxts[rows, 0], oxts[rows, 1], oxts[rows, 2], np.zeros((len(rows), 2))])
        payloads.append(gpmf_payload(utc, fixes))
    return payloads


def write_gpx(path: Path, times_ns: np.ndarray, oxts: np.ndarray) -> None:
    """One GPX track point per OXTS packet (lat, lon, alt, time as UTC)."""
    points = []
    for t, row in zip(times_ns, oxts, strict=True):
        when = dt.datetime.fromtimestamp(t / 1e9, dt.UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
        ele = f"<ele>{row[2]:.3f}</ele><time>{when}</time>"
        points.append(f'<trkpt lat="{row[0]:.9f}" lon="{row[1]:.9f}">{ele}</trkpt>')
    path.write_text(
        '<?xml version="1.0"?><gpx version="1.1" creator="bench_video_sfm" xmlns="http://www.topografix.com/GPX/1/1">'
        f"<trk><trkseg>{''.join(points)}</trkseg></trk></gpx>\n"
    )


def ingest(video: Path, ws: Path, extra: list[str]) -> tuple[float, float, str]:
    """`drivesim ingest` in a child process: (wall s, CPU s (user + system), its output)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), "ingest", str(video), *extra],
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    if proc.returncode != 0:
        raise SystemExit(f"drivesim ingest failed:\n{proc.stdout}\n{proc.stderr}")
    return wall, cpu, proc.stdout


def peak_child_rss_gb() -> float:
    """Largest resident memory of any child process so far (GB)."""
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024**2


def similarity_rmse(estimate: np.ndarray, truth: np.ndarray) -> float:
    """RMS distance (m) between the truth and the estimate after the best similarity (scale, rotation, shift)."""
    aligned = fit_similarity(estimate, truth)(estimate)
    return float(np.sqrt(np.mean(np.sum((aligned - truth) ** 2, axis=1))))


def path_length(points: np.ndarray) -> float:
    """Sum of the steps between consecutive points (m)."""
    return float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)))


def evaluate(ws: Path, truth_m: np.ndarray, n_frames: int, start_ns: int) -> dict[str, float]:
    """The trace's SfM camera path against the OXTS camera path at the same frames."""
    with np.load(ws / "trace" / "poses.npz") as poses:
        t_ns, T_world_camera = poses["t_ns"], poses["T_world_camera"]
    frame = np.round((t_ns - start_ns) * 1e-9 * FPS).astype(int)
    est, ref = T_world_camera[:, :3, 3], truth_m[frame]
    rmse = similarity_rmse(est, ref)
    return {
        "registered": len(frame),
        "frames": n_frames,
        "length_m": path_length(est),
        "truth_length_m": path_length(ref),
        "rmse_m": rmse,
        "rigid_end_m": float(np.linalg.norm((est[-1] - est[0]) - (ref[-1] - ref[0]))),
    }


def _sfm_seconds(output: str) -> float:
    """features + matching + mapping seconds from ingest's "SfM registered ..." note."""
    return sum(float(v) for v in re.findall(r"(?:features|matching|mapping)_s (\d+(?:\.\d+)?) s", output))


def _row(name: str, m: dict[str, float], wall_s: float, cpu_s: float, sfm_s: float, output: str) -> str:
    focal = re.search(r"fx ([\d.]+) px at (\d+) px wide \(horizontal FOV ([\d.]+) deg\)", output)
    fov = f"{float(focal.group(3)):.1f}" if focal else "?"
    length_err = m["length_m"] / m["truth_length_m"] - 1
    return (
        f"| {name} | {m['registered']}/{m['frames']} ({m['registered'] / m['frames']:.0%}) | {m['length_m']:.1f} | "
        f"{m['truth_length_m']:.1f} | {length_err:+.1%} | {m['rmse_m']:.3f} ({m['rmse_m'] / m['truth_length_m']:.2%}) "
        f"| {fov} | {sfm_s:.0f} ({sfm_s / m['frames']:.2f}) | {wall_s:.0f} | {cpu_s:.0f} "
        f"({cpu_s / 2 / m['frames']:.2f}) |"
    )


def timing() -> None:
    """The camera-height ingest once, with no other heavy job on the machine: its SfM and
    ingest times and memory replace the timing paragraph of the results file, the rest of the file is kept."""
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="bench-video-") as tmp:
        video = Path(tmp) / "kitti_0001.mp4"
        n_frames = make_video(video)
        wall_s, cpu_s, output = ingest(video, Path(tmp) / "ws", ["--camera-height-m", "1.65", "--gps", "none"])
    sfm_s = _sfm_seconds(output)
    parts = dict(re.findall(r"(features|matching|mapping)_s (\d+(?:\.\d+)?) s", output))
    line = (
        f"{TIMING_HEAD} ({dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M} UTC, `python "
        f"benchmarks/bench_video_sfm.py --timing` with nothing else running: load average {load_before:.1f} before and "
        f"{os.getloadavg()[0]:.1f} after): video + `--camera-height-m 1.65`, 640 px wide, 2 threads: SfM "
        f"{sfm_s:.0f} s for {n_frames} frames, {sfm_s / n_frames:.2f} s per frame (features {parts.get('features')} "
        f"s, matching {parts.get('matching')} s, mapping {parts.get('mapping')} s); the whole ingest {wall_s:.0f} s "
        f"wall, {cpu_s:.0f} s CPU; peak memory {peak_child_rss_gb():.2f} GB. Target: <= 1 s per frame, <= 4 GB."
    )
    kept = [p for p in RESULTS.read_text().split("\n\n") if not p.startswith(TIMING_HEAD)] if RESULTS.is_file() else []
    RESULTS.write_text("\n\n".join([*[p.strip("\n") for p in kept if p.strip()], line]) + "\n")
    print(line)
    raw = {"load_average_before_after": [load_before, os.getloadavg()[0]], "frames": n_frames, "sfm_s": sfm_s}
    raw |= {"sfm_parts_s": parts, "ingest_wall_s": wall_s, "ingest_cpu_s": cpu_s, "peak_rss_gb": peak_child_rss_gb()}
    update_json(RESULTS.with_suffix(".json"), "timing", raw)


TABLE_HEADER = (
    "| input | frames registered | path (m) | true path (m) | length error | RMSE after similarity (m, % of path) | "
    "HFOV (deg; true 81.4 on KITTI raw) | SfM wall s (per frame) | ingest wall s | ingest CPU s (per frame / 2) |"
)
ROW_KINDS = {
    "height": "video + `--camera-height-m 1.65`",
    "gpx": "video + GPX of the OXTS fixes",
    "focal": "video + `--camera-height-m 1.65 --hfov-deg 81.4` (focal given)",
    "png": "the same frames as PNGs (image folder, `--fps 10`) + `--camera-height-m 1.65`",
    "odometry": "KITTI odometry 06, 51 frames (MP4; true HFOV 81.8) + `--camera-height-m 1.65`",
    "gopro": "video with the OXTS fixes inside it as GoPro GPMF telemetry (no flags)",
}


def _inputs(tmp: Path) -> dict[str, tuple[Path, list[str], int, np.ndarray]]:
    """Each row's (input, extra ingest arguments, start time ns for matching the truth, true camera centres)."""
    stamps = parse_timestamps(DRIVE / "image_00" / "timestamps.txt")
    start_utc = dt.datetime.fromtimestamp(stamps[0] / 1e9, dt.UTC).isoformat()
    oxts_times, oxts, truth_m = oxts_camera_track()
    video = tmp / "kitti_0001.mp4"
    make_video(video)
    write_gpx(video.with_suffix(".gpx"), oxts_times, oxts)
    odometry_truth_m = make_odometry_video(tmp / "kitti_odometry_06.mp4")
    gopro = tmp / "GX010001.MP4"
    gopro.write_bytes(video.read_bytes())
    add_gopro_gps(gopro, gopro_payloads(oxts_times, oxts))
    height = ["--camera-height-m", "1.65", "--gps", "none"]
    gpx = ["--video-start-utc", start_utc, "--gps", str(video.with_suffix(".gpx"))]
    return {
        "height": (video, height, 0, truth_m),
        "gpx": (video, gpx, int(stamps[0]), truth_m),
        "focal": (video, [*height, "--hfov-deg", "81.4"], 0, truth_m),
        "png": (DRIVE / "image_00" / "data", [*height, "--fps", str(FPS)], 0, truth_m),
        "odometry": (tmp / "kitti_odometry_06.mp4", height, 0, odometry_truth_m),
        "gopro": (gopro, [], int(oxts_times[0]), truth_m),
    }


def main() -> None:
    """Make the videos and the GPX, ingest each way, write the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=list(ROW_KINDS), help="run one of the ingests")
    parser.add_argument("--timing", action="store_true", help="time the camera-height ingest alone (see above)")
    args = parser.parse_args()
    if not DRIVE.is_dir() or not ODOMETRY.is_dir():
        raise SystemExit(f"KITTI drives not found at {DRIVE} and {ODOMETRY}")
    if args.timing:
        timing()
        return
    load_before = os.getloadavg()[0]
    rows: list[str] = []
    with tempfile.TemporaryDirectory(prefix="bench-video-") as tmp:
        inputs = _inputs(Path(tmp))
        for kind, (source, extra, start_ns, truth_m) in inputs.items():
            if args.only and kind != args.only:
                continue
            ws = Path(tmp) / f"ws-{kind}"
            wall_s, cpu_s, output = ingest(source, ws, extra)
            m = evaluate(ws, truth_m, len(truth_m), start_ns)
            rows.append(_row(ROW_KINDS[kind], m, wall_s, cpu_s, _sfm_seconds(output), output))
            print(rows[-1], flush=True)
    command = "python benchmarks/bench_video_sfm.py" + (f" --only {args.only}" if args.only else "")
    RESULTS.with_suffix(".json").unlink(missing_ok=True)  # the timing paragraph is rewritten with the file
    write_markdown(RESULTS, [_report(rows, command, load_before)])
    raw = {"command": command, "load_average_before": load_before, "peak_child_rss_gb": peak_child_rss_gb()}
    update_json(RESULTS.with_suffix(".json"), "ingests", raw | {"rows": table_records(TABLE_HEADER, rows)})


def _report(rows: list[str], command: str, load_before: float) -> str:
    """The results file: set-up, table, targets and notes."""
    return "\n".join(
        [
            "## Plain video in: SfM poses and metric scale on the KITTI raw drive (issue 23)",
            "",
            f"Machine: {machine_line()} (load average {load_before:.1f} before the runs; the machine is shared). "
            f"Date: {dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M} UTC. Command: `{command}`.",
            "The 108 grey frames of `kitti_raw/2011_09_26_drive_0001_sync/image_00` (1242x375, 10 Hz) written as an "
            "MP4 (OpenCV mp4v, which decodes as 1242x374); `drivesim ingest` sees only the video (no intrinsics: "
            "SfM estimates the focal length), plus either the camera height or a GPX track made from the 108 OXTS "
            "fixes (lat, lon, alt, time); the third row also gives the true horizontal field of view (KITTI P_rect_00: "
            "fx 721.5 px at 1242 px, 81.4 deg) to separate the focal length's error from the scale method's. The "
            "last two rows ask how much the estimated focal length depends on the input: the same frames read from "
            "their PNG files (an image folder), and another KITTI drive (odometry sequence 06, frames 0-50, 1226x370, "
            "fx 707.1 px: 81.8 deg; truth from its poses.txt) made into an MP4 the same way. "
            "SfM at 640 px wide on 2 threads. Truth: the OXTS pose of each frame moved to camera 0 with the "
            "KITTI calibration. Path length: sum of the steps between the registered frames' camera centres. RMSE: "
            "after the best similarity (scale, rotation, shift) of the SfM path onto the true one. SfM s: feature "
            "extraction + matching + mapping wall time, per video frame in brackets; ingest: the whole `drivesim "
            "ingest` (decoding, SfM, trace), wall and CPU time (user + system) with CPU s / frames / 2 in brackets: "
            "the shared machine's load stretches wall times, and on an idle 2-core machine a frame would take "
            "between CPU / 2 (both threads busy) and CPU s per frame. "
            f"Peak memory of the ingest processes: {peak_child_rss_gb():.2f} GB.",
            "",
            TABLE_HEADER,
            "|---|---|---|---|---|---|---|---|---|---|",
            *rows,
            "",
            f"Targets: length within 5 %, RMSE <= 2 % of the path, >= 95 % of frames registered, SfM <= 1 s per "
            f"frame at 640 px on 2 cores, memory <= 4 GB. Load average after the runs: {os.getloadavg()[0]:.1f}.",
            "",
            NOTES,
            "",
        ]
    )


if __name__ == "__main__":
    main()
