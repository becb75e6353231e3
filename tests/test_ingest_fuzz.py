"""Fuzzing ingest (issue 22): damaged recordings give a checked trace or one line, never a traceback or wrong data.

A seeded mutator makes ~100 damaged recordings from small clean ones: recordings the test writes (MCAP with and
without compression, ROS1, rosbag2 sqlite3 and mcap storage, CompressedImage jpeg, a KITTI-layout stereo folder) and
the shared real ones cut to a few frames (`../shared/data/real/`, skipped with the reason when absent). Mutations:
truncation, byte flips in the first 512 bytes (headers) and after them (payloads), an empty or garbage image, NaN in
CameraInfo / tf / GPS / IMU / twist / poses / calibration, non-rigid poses, wrong sizes. Each case is ingested
in-process (a few through the real CLI in a subprocess) and must end in one of:
- ok: the trace passes an oracle independent of trace.py (finite intrinsics, rigid extrinsics and poses, finite
  series, strictly increasing stamps; and where the format can tell damage from data — MCAP and rosbag2-mcap chunk
  CRCs, PNG chunk CRCs, every field-level mutation — frames, stamps, calibration and series equal to the clean
  recording's, less the messages it skipped);
- refused: an InputError/ConfigError whose line has no newline (CLI: exit 2, one stderr line, no trace, no temp
  folder).
Anything else (another exception, an alarm after HANG_S, wrong data) fails the test, naming the case.

`python tests/test_ingest_fuzz.py` prints the counts tried / clean / traceback / silently wrong / hang (with
PYTHONPATH pointing at another checkout's parent, the counts of that code: the "before" figures of the report).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from kitti_fakes import kitti_stereo_folder
from recordings import (
    START_NS,
    Msg,
    drive_messages,
    image_values,
    odometry_values,
    patch_image,
    recording_path,
    textured_image,
    write_recording,
)

from drivesim.pipeline.errors import DrivesimError
from drivesim.sim.image_stack import ImageStack
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.run import ingest_recording

SEED = 22
HANG_S = 30
N_FRAMES = 5
REAL_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
KITTI_CFG = {"image": {"width_px": 160}}


# ------------------------------------------------------------------ recordings the test makes


def _cut_kitti_odometry(src: Path, dst: Path, n: int = 4) -> Path:
    """The first n frames of a KITTI odometry folder (images, poses, calib) copied to dst."""
    dst.mkdir(parents=True)
    shutil.copy(src / "calib.txt", dst / "calib.txt")
    lines = (src / "poses.txt").read_text().splitlines()[:n]
    (dst / "poses.txt").write_text("\n".join(lines) + "\n")
    for side in ("image_l", "image_r"):
        if (src / side).is_dir():
            (dst / side).mkdir()
            for f in sorted((src / side).iterdir())[:n]:
                shutil.copy(f, dst / side / f.name)
    return dst


def _cut_kitti_raw(date: Path, dst_date: Path, n: int = 4) -> Path:
    """The first n frames of the shared KITTI raw drive (image_00, oxts, timestamps, the date's calib files)."""
    drive = next(date.glob("*_sync"))
    dst_date.mkdir(parents=True)
    for f in date.glob("calib_*.txt"):
        shutil.copy(f, dst_date / f.name)
    out = dst_date / drive.name
    for sub in ("image_00", "oxts"):
        if not (drive / sub).is_dir():
            continue
        (out / sub / "data").mkdir(parents=True)
        for f in sorted((drive / sub / "data").iterdir())[:n]:
            shutil.copy(f, out / sub / "data" / f.name)
        stamps = drive / sub / "timestamps.txt"
        if stamps.is_file():
            (out / sub / "timestamps.txt").write_text("\n".join(stamps.read_text().splitlines()[:n]) + "\n")
    return out


# ------------------------------------------------------------------ mutations

ROS_CONTAINERS = ("mcap", "mcap_zstd", "ros1", "rosbag2_sqlite3", "rosbag2_mcap", "jpeg")
# Byte damage these containers can detect (MCAP chunk CRCs): the oracle then also wants the clean recording's data.
# Not rosbag2_mcap here: rosbags' writer leaves its chunk CRCs 0 ("none"); ROS1 and sqlite3 have no checksums.
CHECKSUMMED = {"mcap", "mcap_zstd", "jpeg"}


def _write_ros(folder: Path, container: str, msgs: list[Msg]) -> Path:
    fmt = {"mcap_zstd": "mcap", "jpeg": "mcap"}.get(container, container)
    compression = "zstd" if container == "mcap_zstd" else "none"
    return write_recording(recording_path(folder, fmt), fmt, msgs, mcap_compression=compression)


def _base_messages(container: str) -> list[Msg]:
    if container == "jpeg":
        return drive_messages(n_frames=N_FRAMES, compressed="jpeg", image_fn=lambda i: textured_image(64, 40, i))
    return drive_messages(n_frames=N_FRAMES)


def _data_file(rec: Path) -> Path:
    return rec if rec.is_file() else next(p for p in rec.iterdir() if p.suffix in (".db3", ".mcap"))


def _flip(path: Path, rng: np.random.Generator, lo: int, hi: int, count: int) -> None:
    data = bytearray(path.read_bytes())
    hi = min(hi, len(data))
    if hi <= lo:
        return
    for pos in rng.integers(lo, hi, size=count):
        data[pos] ^= int(rng.integers(1, 256))
    path.write_bytes(bytes(data))


def _truncate(path: Path, rng: np.random.Generator) -> None:
    size = path.stat().st_size
    with open(path, "r+b") as f:
        f.truncate(int(size * rng.uniform(0.05, 0.98)))


def _camera_msgs(msgs: list[Msg]) -> list[Msg]:
    return [m for m in msgs if m.topic.startswith("/camera/image_raw")]


def _set(msgs: list[Msg], topic: str, index: int, edit: Callable[[dict], None]) -> list[Msg]:
    [m for m in msgs if m.topic == topic][index].values.update(_edited(msgs, topic, index, edit))
    return msgs


def _edited(msgs: list[Msg], topic: str, index: int, edit: Callable[[dict], None]) -> dict:
    values = dict([m for m in msgs if m.topic == topic][index].values)
    edit(values)
    return values


def _nan_tf(translation: bool) -> Callable[[list[Msg]], list[Msg]]:
    def mutate(msgs: list[Msg]) -> list[Msg]:
        tf = next(m for m in msgs if m.topic == "/tf_static")
        part = tf.values["transforms"][1]["transform"]
        if translation:
            part["translation"] = {**part["translation"], "z": float("nan")}
        else:
            part["rotation"] = {**part["rotation"], "w": float("nan")}
        return msgs

    return mutate


def _with_odometry(nan_at: int | None) -> Callable[[list[Msg]], list[Msg]]:
    def mutate(msgs: list[Msg]) -> list[Msg]:
        msgs = [m for m in msgs if m.topic != "/gps/fix"]
        for i in range(8):
            t = START_NS + i * 50_000_000 + 7
            x = float("nan") if i == nan_at else 0.4 * i
            msgs.append(Msg("/odom", "nav_msgs/msg/Odometry", t, odometry_values(t, x, 8.0)))
        return sorted(msgs, key=lambda m: m.t_ns)

    return mutate


def _raw_camera(edit: Callable[[dict], None], index: int = 2) -> Callable[[list[Msg]], list[Msg]]:
    return lambda msgs: _set(msgs, "/camera/image_raw", index, edit)


def _info(edit: Callable[[dict], None]) -> Callable[[list[Msg]], list[Msg]]:
    def mutate(msgs: list[Msg]) -> list[Msg]:
        for i in range(len([m for m in msgs if m.topic == "/camera/camera_info"])):
            _set(msgs, "/camera/camera_info", i, edit)
        return msgs

    return mutate


def _nan_field(topic: str, index: int | None, edit: Callable[[dict], None]) -> Callable[[list[Msg]], list[Msg]]:
    def mutate(msgs: list[Msg]) -> list[Msg]:
        count = len([m for m in msgs if m.topic == topic])
        for i in range(count) if index is None else [index % count]:
            _set(msgs, topic, i, edit)
        return msgs

    return mutate


def _k_with(i: int, value: float) -> Callable[[dict], None]:
    def edit(v: dict) -> None:
        k = np.array(v["k"], dtype=float)
        k[i] = value
        v["k"] = k

    return edit


NAN = float("nan")
# name -> (containers it applies to, mutation of the message list)
FIELD_MUTATIONS: dict[str, tuple[tuple[str, ...], Callable[[list[Msg]], list[Msg]]]] = {
    "empty_jpeg": (("jpeg",), lambda m: _set(m, "/camera/image_raw/compressed", 2, lambda v: v.update(data=b""))),
    "garbage_jpeg": (
        ("jpeg",),
        lambda m: _set(m, "/camera/image_raw/compressed", 1, lambda v: v.update(data=os.urandom(300))),
    ),
    "all_empty_jpeg": (("jpeg",), _nan_field("/camera/image_raw/compressed", None, lambda v: v.update(data=b""))),
    "short_raw": (("mcap", "ros1"), _raw_camera(lambda v: v.update(data=v["data"][:100]))),
    "small_step": (("mcap",), _raw_camera(lambda v: v.update(step=10))),
    "raw_size_change": (("ros1",), _raw_camera(lambda v: v.update(image_values(0, patch_image(32, 20))))),
    "bad_encoding": (("mcap",), _raw_camera(lambda v: v.update(encoding="rgb9"), index=0)),
    "nan_K": (("mcap", "ros1", "rosbag2_sqlite3"), _info(_k_with(0, NAN))),
    "inf_K_cx": (("mcap",), _info(_k_with(2, float("inf")))),
    "zero_K": (("ros1",), _info(lambda v: v.update(k=np.zeros(9), p=np.zeros(12)))),
    "nan_D": (("mcap",), _info(lambda v: v.update(d=[NAN, 0.0, 0.0, 0.0, 0.0]))),
    "nan_P": (("ros1",), _info(lambda v: v.update(p=np.full(12, NAN)))),
    "info_size_mismatch": (("mcap",), _info(lambda v: v.update(width=65))),
    "nan_tf_translation": (("mcap", "ros1"), _nan_tf(translation=True)),
    "nan_tf_rotation": (("mcap", "ros1"), _nan_tf(translation=False)),
    "nan_gps_one": (("mcap", "rosbag2_sqlite3"), _nan_field("/gps/fix", 2, lambda v: v.update(latitude=NAN))),
    "nan_gps_all": (("ros1",), _nan_field("/gps/fix", None, lambda v: v.update(longitude=NAN))),
    "inf_gps_cov": (("mcap",), _nan_field("/gps/fix", 1, lambda v: v.update(position_covariance=np.full(9, np.inf)))),
    "nan_imu": (
        ("mcap", "ros1"),
        _nan_field("/imu/data", 7, lambda v: v.update(angular_velocity={"x": NAN, "y": 0.0, "z": 0.1})),
    ),
    "nan_twist": (
        ("mcap",),
        _nan_field("/vehicle/twist", 3, lambda v: v["twist"].update(linear={"x": NAN, "y": 0.0, "z": 0.0})),
    ),
    "nan_odometry": (("ros1", "mcap"), _with_odometry(nan_at=3)),
    "zero_stamp_camera": (
        ("mcap",),
        _raw_camera(lambda v: v.update(header={**v["header"], "stamp": {"sec": 0, "nanosec": 0}})),
    ),
}


def _replace_number(path: Path, line: int, column: int, text: str) -> None:
    lines = path.read_text().splitlines()
    key, sep, rest = lines[line].partition(":") if ":" in lines[line] else ("", "", lines[line])
    values = rest.split()
    values[column] = text
    lines[line] = f"{key}{sep} {' '.join(values)}" if sep else " ".join(values)
    path.write_text("\n".join(lines) + "\n")


def _scale_pose(path: Path, line: int) -> None:
    rows = np.loadtxt(path, ndmin=2)
    rows[line, [0, 5, 10]] *= 1.5
    np.savetxt(path, rows, fmt="%.6e")


def _write_times(folder: Path, seconds: Callable[[int], np.ndarray]) -> None:
    n = len(list((folder / "image_l").iterdir()))
    np.savetxt(folder / "times.txt", seconds(n))


def _png(folder: Path, side: str, rng: np.random.Generator) -> Path:
    images = folder / side / "data" if side == "image_00" else folder / side
    files = sorted(images.iterdir())
    return files[int(rng.integers(0, len(files)))]


KITTI_MUTATIONS: dict[str, Callable[[Path, np.random.Generator], None]] = {
    "png_truncated": lambda f, r: _truncate(_png(f, "image_l", r), r),
    "png_flip": lambda f, r: _flip(p := _png(f, "image_l", r), r, 60, p.stat().st_size, 4),
    "png_empty": lambda f, r: _png(f, "image_l", r).write_bytes(b""),
    "right_png_flip": lambda f, r: _flip(p := _png(f, "image_r", r), r, 60, p.stat().st_size, 4),
    "right_png_missing": lambda f, r: _png(f, "image_r", r).unlink(),
    "right_png_other_size": lambda f, r: cv2.imwrite(str(_png(f, "image_r", r)), np.zeros((10, 20), np.uint8)),
    "calib_nan_fx": lambda f, r: _replace_number(f / "calib.txt", 0, 0, "nan"),
    "calib_garbage": lambda f, r: _replace_number(f / "calib.txt", 0, 2, "x1.5"),
    "calib_right_off_axis": lambda f, r: _replace_number(f / "calib.txt", 1, 7, "-40.0"),
    "calib_right_other_fx": lambda f, r: _replace_number(f / "calib.txt", 1, 0, "81.0"),
    "poses_nan": lambda f, r: _replace_number(f / "poses.txt", 1, 3, "nan"),
    "poses_line_missing": lambda f, r: (f / "poses.txt").write_text(
        "\n".join((f / "poses.txt").read_text().splitlines()[:-1]) + "\n"
    ),
    "poses_not_rigid": lambda f, r: _scale_pose(f / "poses.txt", 2),
    "times_nan": lambda f, r: _write_times(f, lambda n: np.where(np.arange(n) == 2, np.nan, 0.1 * np.arange(n))),
    "times_decreasing": lambda f, r: _write_times(f, lambda n: 0.1 * np.arange(n)[::-1]),
    "times_huge": lambda f, r: _write_times(f, lambda n: 1e300 * np.arange(1, n + 1)),
}

KITTI_RAW_MUTATIONS: dict[str, Callable[[Path, np.random.Generator], None]] = {
    "oxts_nan": lambda d, r: _replace_number(sorted((d / "oxts" / "data").iterdir())[1], 0, 0, "nan"),
    "oxts_short": lambda d, r: sorted((d / "oxts" / "data").iterdir())[2].write_text("1.0 2.0\n"),
    "png_flip": lambda d, r: _flip(p := _png(d, "image_00", r), r, 60, p.stat().st_size, 4),
    "calib_nan": lambda d, r: (d.parent / "calib_cam_to_cam.txt").write_text(
        (d.parent / "calib_cam_to_cam.txt").read_text().replace("P_rect_00: 7", "P_rect_00: nan 7", 1)
    ),
}


# ------------------------------------------------------------------ cases


@dataclass
class Case:
    """One damaged recording: how to make it, which clean recording it came from, whether the data must match."""

    name: str
    base: str
    make: Callable[[Path], Path]
    strict: bool
    cfg: dict


def _ros_byte_case(container: str, kind: str, seed: int) -> Case:
    def make(folder: Path) -> Path:
        rng = np.random.default_rng([SEED, seed])
        rec = _write_ros(folder, container, _base_messages(container))
        data = _data_file(rec)
        if kind == "truncate":
            _truncate(data, rng)
        elif kind == "flip_header":
            _flip(data, rng, 0, 512, int(rng.integers(1, 5)))
        else:
            _flip(data, rng, 512, data.stat().st_size, int(rng.integers(1, 9)))
        return rec

    return Case(f"{container}/{kind}/{seed}", container, make, container in CHECKSUMMED, {})


def _ros_field_case(name: str, container: str) -> Case:
    mutate = FIELD_MUTATIONS[name][1]
    return Case(
        f"{container}/{name}",
        container,
        lambda f: _write_ros(f, container, mutate(_base_messages(container))),
        strict=True,
        cfg={},
    )


def _kitti_case(name: str, base: str, seed: int) -> Case:
    def make(folder: Path) -> Path:
        rec = _make_base(base, folder)
        table = KITTI_RAW_MUTATIONS if base == "kitti_raw_real" else KITTI_MUTATIONS
        table[name](rec, np.random.default_rng([SEED, seed]))
        return rec

    return Case(f"{base}/{name}", base, make, strict=True, cfg=KITTI_CFG)


def _make_base(base: str, folder: Path) -> Path:
    """The clean recording `base` in `folder`."""
    if base in ROS_CONTAINERS:
        return _write_ros(folder, base, _base_messages(base))
    if base == "kitti_stereo":
        return kitti_stereo_folder(folder / "seq")
    if base == "kitti_odometry_real":
        return _cut_kitti_odometry(REAL_DATA / "kitti_odometry_straight", folder / "seq")
    if base == "kitti_stereo_real":
        return _cut_kitti_odometry(REAL_DATA / "kitti_odometry_stereo", folder / "seq")
    if base == "kitti_raw_real":
        return _cut_kitti_raw(REAL_DATA / "kitti_raw" / "2011_09_26", folder / "2011_09_26")
    raise ValueError(base)


REAL_BASES = {
    "kitti_odometry_real": REAL_DATA / "kitti_odometry_straight",
    "kitti_stereo_real": REAL_DATA / "kitti_odometry_stereo",
    "kitti_raw_real": REAL_DATA / "kitti_raw" / "2011_09_26",
}


def all_cases() -> list[Case]:
    """The seeded case list (about 100)."""
    cases = [
        _ros_byte_case(c, kind, s)
        for c in ROS_CONTAINERS
        for kind in ("truncate", "flip_header", "flip_payload")
        for s in range(3)
    ]
    for name, (containers, _) in FIELD_MUTATIONS.items():
        cases += [_ros_field_case(name, c) for c in containers]
    stereo_only = (
        "right_png_flip",
        "right_png_missing",
        "right_png_other_size",
        "calib_right_off_axis",
        "calib_right_other_fx",
    )
    cases += [_kitti_case(name, "kitti_stereo", i) for i, name in enumerate(KITTI_MUTATIONS)]
    cases += [
        _kitti_case(name, "kitti_odometry_real", i)
        for i, name in enumerate(KITTI_MUTATIONS)
        if name not in stereo_only and not name.startswith("times")
    ][:5]
    cases += [_kitti_case(name, "kitti_stereo_real", 50 + i) for i, name in enumerate(stereo_only[:3])]
    cases += [_kitti_case(name, "kitti_raw_real", 90 + i) for i, name in enumerate(KITTI_RAW_MUTATIONS)]
    return cases


# ------------------------------------------------------------------ the oracle


def _rigid(T: np.ndarray) -> bool:
    R = T[:3, :3]
    return bool(
        np.all(np.isfinite(T))
        and np.allclose(R @ R.T, np.eye(3), atol=1e-4)
        and np.linalg.det(R) > 0
        and np.allclose(T[3], [0, 0, 0, 1])
    )


@dataclass
class Trace:
    """What the oracle compares: calibration, stamps, frames, series (name -> arrays)."""

    calibration: dict
    times: np.ndarray
    frames: np.ndarray
    right: np.ndarray | None
    series: dict[str, dict[str, np.ndarray]]


def load_trace(out: Path) -> Trace:
    calibration = json.loads((out / "calibration.json").read_text())
    series = {}
    for f in out.glob("*.npz"):
        with np.load(f) as data:
            series[f.stem] = {k: data[k] for k in data.files}
    right = np.asarray(ImageStack(out / "frames_right.imgs")) if (out / "frames_right.imgs").is_file() else None
    frames = np.asarray(ImageStack(out / "frames.imgs"))
    return Trace(calibration, np.load(out / "frame_times_ns.npy"), frames, right, series)


def wrong(out: Path, clean: Trace | None, strict: bool) -> str:
    """Why the trace in `out` is wrong ("" when it is right); independent of stages/ingest/trace.py."""
    try:
        t = load_trace(out)
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as e:
        return f"unloadable trace ({e})"
    K = np.asarray(t.calibration["K"], dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        return f"K {K.tolist()}"
    if not _rigid(np.asarray(t.calibration["T_vehicle_camera"], dtype=float)):
        return "T_vehicle_camera not rigid"
    h = t.calibration["camera_height_m"]
    if h is not None and not np.isfinite(h):
        return "camera height not finite"
    if len(t.frames) < 1 or len(t.times) != len(t.frames) or np.any(np.diff(t.times) <= 0):
        return f"{len(t.frames)} frames, {len(t.times)} stamps"
    if t.right is not None and t.right.shape != t.frames.shape:
        return "right frames differ in shape"
    for name, arrays in t.series.items():
        for col, arr in arrays.items():
            if arr.dtype.kind == "f" and (name, col) != ("imu", "orientation_xyzw") and not np.all(np.isfinite(arr)):
                return f"{name}.{col} not finite"
    if "poses" in t.series and not all(_rigid(T) for T in t.series["poses"]["T_world_camera"]):
        return "poses not rigid"
    return _differs(t, clean) if strict and clean is not None else ""


def _differs(t: Trace, clean: Trace) -> str:
    """Where the trace differs from the clean recording's (messages left out are allowed)."""
    for key in ("K", "T_vehicle_camera", "baseline_m"):
        if key in clean.calibration and not np.allclose(t.calibration.get(key, np.nan), clean.calibration[key]):
            return f"{key} differs from the clean recording's"
    index = {int(s): i for i, s in enumerate(clean.times)}
    if any(int(s) not in index for s in t.times):
        return "stamps the clean recording does not have"
    for i, s in enumerate(t.times):
        if t.frames.shape[1:] != clean.frames.shape[1:] or not np.array_equal(t.frames[i], clean.frames[index[int(s)]]):
            return f"frame at {int(s)} differs from the clean recording's"
        if t.right is not None and (clean.right is None or not np.array_equal(t.right[i], clean.right[index[int(s)]])):
            return "right frame differs"
    for name, arrays in t.series.items():
        base = clean.series.get(name)
        if base is None:  # a series the mutation added (odometry): checked for finite values above
            continue
        rows = {int(s): j for j, s in enumerate(base["t_ns"])}
        for j, s in enumerate(arrays["t_ns"]):
            if int(s) not in rows:
                return f"{name} sample at {int(s)} the clean recording does not have"
            for col, arr in arrays.items():
                if not np.allclose(arr[j], base[col][rows[int(s)]], equal_nan=True):
                    return f"{name}.{col} at {int(s)} differs"
    return ""


# ------------------------------------------------------------------ running cases


class HangError(Exception):
    """The case ran past HANG_S."""


@contextlib.contextmanager
def alarm(seconds: float) -> Iterator[None]:
    def on_alarm(signum, frame):  # noqa: ARG001
        raise HangError()

    previous = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def run_case(case: Case, folder: Path, clean: Trace | None) -> tuple[str, str]:
    """(outcome, detail): outcome is ok / refused / traceback / silently wrong / hang."""
    folder.mkdir(parents=True)
    rec = case.make(folder)
    out = folder / "trace"
    out.mkdir()
    try:
        with alarm(HANG_S):
            ingest_recording(rec, IngestConfig.model_validate(case.cfg), out)
    except HangError:
        return "hang", ""
    except DrivesimError as e:
        line = e.one_line()
        return ("refused", line) if "\n" not in line else ("traceback", repr(line))
    except Exception as e:  # noqa: BLE001 (what the fuzz test counts)
        return "traceback", f"{type(e).__name__}: {e}"[:300]
    problem = wrong(out, clean, case.strict)
    return ("silently wrong", problem) if problem else ("ok", "")


def clean_trace(base: str, folder: Path) -> Trace:
    folder.mkdir(parents=True)
    rec = _make_base(base, folder)
    out = folder / "trace"
    out.mkdir()
    ingest_recording(rec, IngestConfig.model_validate(KITTI_CFG if base.startswith("kitti") else {}), out)
    return load_trace(out)


def run_all(root: Path, cases: list[Case]) -> list[tuple[Case, str, str]]:
    cleans: dict[str, Trace | None] = {}
    results = []
    for i, case in enumerate(cases):
        if case.base not in cleans:
            try:
                cleans[case.base] = clean_trace(case.base, root / f"clean-{case.base}")
            except Exception:  # noqa: BLE001 (old code in probe mode may refuse a clean recording)
                cleans[case.base] = None
        results.append((case, *run_case(case, root / f"case-{i:03d}", cleans[case.base])))
    return results


def _available(cases: list[Case]) -> tuple[list[Case], list[str]]:
    missing = sorted({c.base for c in cases if c.base in REAL_BASES and not REAL_BASES[c.base].exists()})
    return [c for c in cases if c.base not in missing], missing


# ------------------------------------------------------------------ the tests


def test_fuzzed_recordings_are_ingested_right_or_refused_in_one_line(tmp_path: Path, capsys) -> None:
    cases, missing = _available(all_cases())
    results = run_all(tmp_path, cases)
    counts = Counter(outcome for _, outcome, _ in results)
    with capsys.disabled():
        skipped = f"; real recordings absent, their cases skipped: {', '.join(missing)}" if missing else ""
        print(f"\ningest fuzz: {len(results)} cases, {dict(counts)}{skipped}")
    bad = [f"{case.name}: {outcome}: {detail}" for case, outcome, detail in results if outcome not in ("ok", "refused")]
    assert not bad, "\n".join(bad)
    assert len(results) >= 80 if not missing else len(results) >= 60
    assert counts["ok"] >= 10 and counts["refused"] >= 10  # both outcomes are exercised


def test_fuzz_mutations_that_must_be_refused_or_skipped(tmp_path: Path) -> None:
    """Field-level damage whose answer is known: refused with the reason, or ingested without the damaged sample."""
    refused = {
        "nan_K": "non-finite",
        "nan_tf_rotation": "T_vehicle_camera",
        "nan_tf_translation": "T_vehicle_camera",
        "all_empty_jpeg": "is empty",
        "nan_gps_all": "no usable pose source",
    }
    for name, reason in refused.items():
        container = FIELD_MUTATIONS[name][0][0]
        outcome, line = run_case(_ros_field_case(name, container), tmp_path / name, None)
        assert outcome == "refused" and reason in line, (name, outcome, line)
    skipped = {"empty_jpeg": "camera", "small_step": "camera", "short_raw": "camera", "nan_gps_one": "gps"}
    for name, role in skipped.items():
        folder = tmp_path / f"skip-{name}"
        folder.mkdir()
        container = FIELD_MUTATIONS[name][0][0]
        rec = _write_ros(folder, container, FIELD_MUTATIONS[name][1](_base_messages(container)))
        (folder / "trace").mkdir()
        result = ingest_recording(rec, IngestConfig(), folder / "trace")
        frames = N_FRAMES - 1 if role == "camera" else N_FRAMES
        assert result.summary["frame_count"] == frames and result.summary["skipped"] == {role: 1}, name
        assert any(f"skipped 1 unreadable or non-finite {role}" in note for note in result.notes), result.notes


CLI_CASES = ("jpeg/empty_jpeg", "mcap/nan_K", "mcap/truncate/0", "kitti_stereo/poses_not_rigid", "mcap/nan_gps_one")


def _cli(ws: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), "ingest", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )


def _check_cli(result: subprocess.CompletedProcess[str], ws: Path, clean: Trace | None, strict: bool) -> str:
    """ "" when the CLI run is right: exit 0 with a right trace, or exit 2 with one line and nothing left behind."""
    leftovers = [p.name for p in ws.glob(".tmp-*")] if ws.is_dir() else []
    if leftovers:
        return f"left {leftovers}"
    if result.returncode == 0:
        return wrong(ws / "trace", clean, strict)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    if result.returncode != 2 or len(lines) != 1 or "Traceback" in result.stderr or (ws / "trace").exists():
        return f"exit {result.returncode}: {result.stderr[-500:]}"
    return ""


def test_fuzzed_recordings_through_the_cli(tmp_path: Path) -> None:
    cases = {c.name: c for c in all_cases()}
    for name in CLI_CASES:
        case = cases[name]
        clean = clean_trace(case.base, tmp_path / f"clean-{name.replace('/', '-')}")
        (tmp_path / name.replace("/", "-")).mkdir()
        rec = case.make(tmp_path / name.replace("/", "-"))
        sets = [arg for key, value in case.cfg.get("image", {}).items() for arg in ("--set", f"image.{key}={value}")]
        ws = tmp_path / f"ws-{name.replace('/', '-')}"
        problem = _check_cli(_cli(ws, str(rec), *sets), ws, clean, case.strict)
        assert not problem, f"{name}: {problem}"
    # a non-rigid configured extrinsics is refused before anything is read
    rec = write_recording(tmp_path / "good.mcap", "mcap", drive_messages(n_frames=2))
    ws = tmp_path / "ws-T"
    result = _cli(ws, str(rec), "--set", "extrinsics.T_vehicle_camera=[[2,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]")
    assert not _check_cli(result, ws, None, False) and result.returncode == 2
    assert "T_vehicle_camera" in result.stderr and "rigid" in result.stderr


def _probe() -> None:
    """Print the counts of every case with the drivesim on sys.path (the report's before/after figures)."""
    cases, missing = _available(all_cases())
    with tempfile.TemporaryDirectory() as root:
        results = run_all(Path(root), cases)
    counts = Counter(outcome for _, outcome, _ in results)
    print(f"tried {len(results)}: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    if missing:
        print(f"(real recordings absent: {missing})")
    for case, outcome, detail in results:
        if outcome not in ("ok", "refused") or "-v" in sys.argv:
            print(f"  {case.name}: {outcome}: {detail}")


if __name__ == "__main__":
    _probe()
