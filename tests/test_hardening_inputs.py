"""Hardening of the chain's inputs: a full disk under memmapped writes, bad pose timing, damaged worlds and config
files, damaged frames and videos, files that are not regular files, names that would forge a line, and native
libraries' chatter. Each case ends in one clear line (exit 2, or 1 for a full disk) and no half-written artifact.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_helpers import run_main
from test_preprocess_stage_fakes import install_fake_poses, make_trace

from drivesim.pipeline.workspace import Workspace
from drivesim.sim.image_stack import ImageStack, ImageStackWriter
from drivesim.stages.preprocess import stage as preprocess_stage
from drivesim.stages.preprocess.config import PreprocessConfig


def _error_lines(err: str) -> list[str]:
    """The error lines of stderr (asserting there is no traceback among the rest)."""
    assert "Traceback" not in err, err
    return [line for line in err.splitlines() if line.startswith("error:")]


# ---------------------------------------------------------------- a full disk under memmapped writes


def _disk_full(monkeypatch: pytest.MonkeyPatch) -> None:
    """The kernel refuses to allocate: what posix_fallocate says on a full disk."""

    def full(fd: int, offset: int, length: int) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full)


def _disk_full_on_write(monkeypatch: pytest.MonkeyPatch) -> None:
    """A plain file write fails for lack of space: what the image stacks (written with file writes) meet."""

    def full(self: ImageStackWriter, frame: np.ndarray) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(ImageStackWriter, "write", full)


@pytest.mark.parametrize("stage", ["preprocess", "build-world"])
def test_full_disk_under_a_memmap_is_one_line_and_keeps_nothing(tmp_path, monkeypatch, capsys, stage) -> None:
    """Preprocess's depth memmap reserves its space first, and build-world's image stacks are written with plain
    file writes: a full disk is the one-line disk-full error (exit 1), not a SIGBUS, and no temporary folder or
    artifact is left."""
    ws = Workspace(tmp_path / "ws")
    make_trace(ws)
    install_fake_poses(monkeypatch)
    if stage == "build-world":
        preprocess_stage.run_preprocess(ws, PreprocessConfig.model_validate({"depth": {"method": "plane"}}))
    _disk_full(monkeypatch) if stage == "preprocess" else _disk_full_on_write(monkeypatch)
    args = [stage, "--set", "depth.method=plane"] if stage == "preprocess" else [stage]
    code, err = run_main(ws.root, *args, monkeypatch=monkeypatch, capsys=capsys)
    lines = _error_lines(err)
    assert code == 1 and len(lines) == 1 and "disk full" in lines[0] and str(ws.root) in lines[0], err
    artifact = "preprocessed" if stage == "preprocess" else "world"
    assert not list(ws.root.glob(".tmp-*")) and not ws.artifact_dir(artifact).exists()


_PREPROCESS_WITH_FAKE_POSES = """
import sys
import pytest
from test_preprocess_stage_fakes import install_fake_poses
install_fake_poses(pytest.MonkeyPatch())
sys.argv = ["drivesim", "--workspace", sys.argv[1], "preprocess", "--set", "depth.method=plane"]
from drivesim.cli.main import main
main()
"""


def test_preprocess_on_a_really_full_disk_says_so_instead_of_dying_of_sigbus(tmp_path) -> None:
    """On a real 400 KB tmpfs (where the machine lets the test mount one) the trace fits and the depth memmap does
    not: before, the kernel killed preprocess with SIGBUS (exit 135, no message, .tmp-* left); now it is one line."""
    import subprocess

    small = tmp_path / "small"
    small.mkdir()
    if sys.platform != "linux" or os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a small tmpfs needs root on Linux")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=400k", "tmpfs", str(small)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        ws = Workspace(small / "ws")
        make_trace(ws)
        script = tmp_path / "preprocess.py"
        script.write_text(_PREPROCESS_WITH_FAKE_POSES)
        paths = [str(Path(__file__).parent), *filter(None, [os.environ.get("PYTHONPATH")])]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}
        done = subprocess.run([sys.executable, str(script), str(ws.root)], capture_output=True, text=True, env=env)
        errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
        assert done.returncode == 1 and len(errors) == 1 and "disk full" in errors[0], (done.returncode, done.stderr)
        assert not list(ws.root.glob(".tmp-*")) and not ws.artifact_dir("preprocessed").exists()
    finally:
        subprocess.run(["umount", str(small)], check=False)


def test_reserved_memmap_falls_back_to_zeros_where_the_file_system_cannot_allocate(tmp_path, monkeypatch) -> None:
    """Where posix_fallocate is unsupported the space is still claimed, by writing zeros through the file."""
    from drivesim.pipeline.npy_files import open_reserved_memmap

    def unsupported(fd: int, offset: int, length: int) -> None:
        raise OSError(errno.EOPNOTSUPP, "Operation not supported")

    monkeypatch.setattr(os, "posix_fallocate", unsupported)
    out = open_reserved_memmap(tmp_path / "a.npy", np.float32, (3, 64, 64))
    out[1] = 2.5
    out.flush()
    del out
    back = np.load(tmp_path / "a.npy")
    assert back.shape == (3, 64, 64) and back[1].min() == 2.5 and back[0].max() == 0.0
    assert os.stat(tmp_path / "a.npy").st_blocks * 512 >= back.nbytes  # allocated, not sparse


# ---------------------------------------------------------------- a world is checked when it is loaded


@pytest.fixture(scope="module")
def built_world(tmp_path_factory) -> Path:
    """A small world built by the real build-world stage from the fake trace and poses."""
    from drivesim.pipeline.config import load_config
    from drivesim.stages.world.config import WorldConfig
    from drivesim.stages.world.stage import run_build_world

    with pytest.MonkeyPatch.context() as mp:
        ws = Workspace(tmp_path_factory.mktemp("world") / "ws")
        make_trace(ws)
        install_fake_poses(mp)
        preprocess_stage.run_preprocess(ws, PreprocessConfig.model_validate({"depth": {"method": "plane"}}))
        return run_build_world(ws, load_config(WorldConfig, preset="world", overrides=["sim_width_px=48"])).path


def _edit_json(name: str, edit) -> callable:
    def apply(world: Path) -> None:
        path = world / name
        path.write_text(json.dumps(edit(json.loads(path.read_text())), allow_nan=True))

    return apply


def _set_camera(key: str, value) -> callable:
    return _edit_json("camera.json", lambda c: {**c, key: value})


def _depth(fill) -> callable:
    def apply(world: Path) -> None:
        depth = np.asarray(ImageStack(world / "depth_m.imgs"))
        fill(depth)
        writer = ImageStackWriter(world / "depth_m.imgs", depth.shape[1:], depth.dtype, "png")
        writer.write_rows(depth)
        writer.close()

    return apply


def _nested(name: str, depth: int = 5000) -> callable:
    def apply(world: Path) -> None:
        (world / name).write_text("[" * depth + "]" * depth)

    return apply


def _overflow_focal(world: Path) -> None:
    """1e999 is valid JSON that Python reads as infinity (not through the NaN/Infinity constants)."""
    camera = json.loads((world / "camera.json").read_text())
    camera["K"][0][0] = "FOCAL"
    (world / "camera.json").write_text(json.dumps(camera).replace('"FOCAL"', "1e999"))


def _path_nan(world: Path) -> None:
    with np.load(world / "path.npz") as data:
        arrays = {k: data[k].copy() for k in data.files}
    arrays["yaw_rad"][3] = np.nan
    np.savez(world / "path.npz", **arrays)


DAMAGED_WORLDS = {
    "nan focal length": (
        _set_camera("K", [[float("nan"), 0, 24], [0, 24, 15], [0, 0, 1]]),
        "camera.json: not valid JSON (NaN",
    ),
    "infinite focal length": (_overflow_focal, "camera.json: K is not a finite 3x3 matrix"),
    "K all zero": (_set_camera("K", [[0, 0, 0], [0, 0, 0], [0, 0, 0]]), "camera.json: K has no positive focal"),
    "K a string": (_set_camera("K", "eye"), "camera.json: K is not"),
    "T not rigid": (_set_camera("T_vehicle_camera", np.diag([2.0, 1, 1, 1]).tolist()), "not a rigid transform"),
    "width a float": (_set_camera("width_px", 48.5), "width_px is 48.5"),
    "all-NaN depth": (_depth(lambda d: d.fill(np.nan)), "depth_m.imgs: frame 0 has NaN depth"),
    "negative depth": (_depth(lambda d: d.__setitem__((5, 3, 3), -4.0)), "frame 5 has negative depth"),
    "world.json a list": (_edit_json("world.json", lambda w: [w]), "world.json: holds a JSON list, not an object"),
    "world.json without a key": (
        _edit_json("world.json", lambda w: {k: v for k, v in w.items() if k != "lane_width_m"}),
        "world.json: lacks lane_width_m",
    ),
    "road width NaN": (_edit_json("world.json", lambda w: {**w, "road_width_m": float("nan")}), "not valid JSON (NaN"),
    "deeply nested world.json": (_nested("world.json"), "world.json: nested more than 32 levels deep"),
    "deeply nested camera.json": (_nested("camera.json"), "camera.json: nested more than"),
    "path NaN": (_path_nan, "path.npz: yaw_rad holds non-finite"),
    "frames.imgs garbage": (lambda w: (w / "frames.imgs").write_bytes(b"\x00" * 100), "frames.imgs: not a readable"),
}


@pytest.mark.parametrize("case", list(DAMAGED_WORLDS))
def test_damaged_world_is_refused_on_load_naming_the_file(built_world, tmp_path, case) -> None:
    """Every damaged world file is a WorldError (a ValueError, which the stages print as one line) naming the file
    and what is wrong: never a NaN that trains silently, a LinAlgError, KeyError or RecursionError."""
    from drivesim.sim.world import World
    from drivesim.sim.world_checks import WorldError

    World.load(built_world)  # the undamaged world loads
    world = tmp_path / "world"
    shutil.copytree(built_world, world)
    damage, expect = DAMAGED_WORLDS[case]
    damage(world)
    with pytest.raises(WorldError) as refused:
        World.load(world)
    assert expect in str(refused.value) and "\n" not in str(refused.value)


def test_deeply_nested_manifest_is_a_damaged_artifact_not_a_recursion_error(tmp_path, monkeypatch, capsys) -> None:
    ws = Workspace(tmp_path / "ws")
    make_trace(ws)
    (ws.artifact_dir("trace") / "manifest.json").write_text("[" * 5000 + "]" * 5000)
    assert ws.read_manifest("trace") is None and ws.manifest_unreadable("trace")
    code, err = run_main(ws.root, "preprocess", monkeypatch=monkeypatch, capsys=capsys)
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1 and "manifest.json is unreadable" in lines[0], err


@pytest.mark.parametrize(
    "text", ["a: " + "[" * 3000 + "]" * 3000, "a:\n" + "".join("  " * i + f"k{i}:\n" for i in range(1, 200))]
)
def test_deeply_nested_config_is_one_line(tmp_path, monkeypatch, capsys, text) -> None:
    path = tmp_path / "deep.yaml"
    path.write_text(text)
    code, err = run_main(
        tmp_path / "ws", "config", "eval", "--config", str(path), monkeypatch=monkeypatch, capsys=capsys
    )
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1 and "nested more than 32 levels deep" in lines[0], err
    assert len(err.splitlines()) == 1


def test_json_reader_refuses_nan_and_depth_but_reads_strings_with_brackets() -> None:
    from drivesim.pipeline.json_files import JsonFileError, loads_checked

    assert loads_checked('{"a": "[[[[{{{{", "b": [[1]]}') == {"a": "[[[[{{{{", "b": [[1]]}
    with pytest.raises(JsonFileError, match="NaN"):
        loads_checked('{"a": NaN}')
    with pytest.raises(JsonFileError, match="nested more than"):
        loads_checked("[" * 33 + "]" * 33)


# ---------------------------------------------------------------- paths that are not regular files or folders


def _ingest_cli(ws: Path, recording: str, monkeypatch, capsys) -> tuple[int, str]:
    return run_main(ws, "ingest", recording, monkeypatch=monkeypatch, capsys=capsys)


@pytest.fixture
def no_hang():
    """Fail (instead of hanging the suite) when the code under test blocks for more than 30 s."""

    def hung(signum, frame):
        raise AssertionError("blocked for 30 s")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(30)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


@pytest.mark.parametrize(
    "kind",
    ["fifo recording", "fifo in a recording folder", "fifo config", "/dev/zero recording", "/dev/null workspace"],
)
def test_non_regular_files_are_refused_with_one_line(tmp_path, monkeypatch, capsys, no_hang, kind) -> None:
    """A FIFO would block the first read forever, /dev/zero is a device, /dev/null is not a folder: each is one
    line (exit 2) naming it, nothing is created, and nothing waits (the test would hang)."""
    fifo = tmp_path / "drive.mcap"
    os.mkfifo(fifo)
    ws = tmp_path / "ws"
    if kind == "fifo recording":
        code, err = _ingest_cli(ws, str(fifo), monkeypatch, capsys)
        expect = "is a FIFO (named pipe), not a regular file or folder"
    elif kind == "fifo in a recording folder":
        folder = tmp_path / "frames"
        folder.mkdir()
        os.mkfifo(folder / "0001.png")
        code, err = _ingest_cli(ws, str(folder), monkeypatch, capsys)
        expect = "0001.png: is a FIFO (named pipe), not a regular file or folder"
    elif kind == "fifo config":
        code, err = run_main(ws, "train", "lane", "--config", str(fifo), monkeypatch=monkeypatch, capsys=capsys)
        expect = "is a FIFO (named pipe), not a regular file; --config takes a YAML file"
    elif kind == "/dev/zero recording":
        code, err = _ingest_cli(ws, "/dev/zero", monkeypatch, capsys)
        expect = "/dev/zero: is a device"
    else:
        ws = Path("/dev/null")
        code, err = _ingest_cli(ws, str(tmp_path), monkeypatch, capsys)
        expect = "/dev/null: is not a folder; --workspace takes a folder"
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1 and expect in lines[0], err
    assert not (tmp_path / "ws").exists()


def test_a_newline_in_a_file_name_cannot_forge_a_second_error_line(tmp_path, monkeypatch, capsys) -> None:
    name = tmp_path / "drive\nerror: all is well \x1b[32m.mcap"
    name.write_bytes(b"not a recording")
    code, err = _ingest_cli(tmp_path / "ws", str(name), monkeypatch, capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "drive\\nerror: all is well \\x1b[32m.mcap" in err and "\x1b" not in err


# ---------------------------------------------------------------- pose streams whose stamps cannot time the drive

ARC_RADIUS_M, ODOM_SPEED_MPS, ODOM_PERIOD_NS = 50.0, 10.0, 50_000_000


def _odometry_values(t_ns: int, i: int) -> dict:
    """nav_msgs/Odometry on a left arc of ARC_RADIUS_M, sample i at ODOM_SPEED_MPS."""
    from recordings import header

    yaw = ODOM_SPEED_MPS * i * ODOM_PERIOD_NS * 1e-9 / ARC_RADIUS_M
    position = {"x": ARC_RADIUS_M * np.sin(yaw), "y": ARC_RADIUS_M * (1 - np.cos(yaw))}
    orientation = {"z": float(np.sin(yaw / 2)), "w": float(np.cos(yaw / 2))}
    return {
        "header": header(t_ns, "odom"),
        "child_frame_id": "base_link",
        "pose": {"pose": {"position": position, "orientation": orientation}},
        "twist": {"twist": {"linear": {"x": ODOM_SPEED_MPS}}},
    }


def _odometry_drive(folder: Path, stamp_of) -> tuple[Path, Path]:
    """An MCAP of 52 camera frames and 104 odometry messages in log order whose header stamps are
    `stamp_of(i, log_time_ns)`; ingested into folder/trace. Returns (recording, trace folder)."""
    from recordings import START_NS, Msg, drive_messages, write_recording

    from drivesim.stages.ingest.config import IngestConfig
    from drivesim.stages.ingest.run import ingest_recording

    msgs = drive_messages(n_frames=52, with_gps=False, with_twist=False, with_imu=False)
    for i in range(104):
        t = START_NS + i * ODOM_PERIOD_NS + 7
        msgs.append(Msg("/odom", "nav_msgs/msg/Odometry", t, _odometry_values(stamp_of(i, t), i)))
    recording = write_recording(folder / "drive.mcap", "mcap", sorted(msgs, key=lambda m: m.t_ns))
    trace = folder / "trace"
    trace.mkdir()
    ingest_recording(recording, IngestConfig(), trace)
    return recording, trace


def _odometry_poses(trace: Path):
    from drivesim.stages.preprocess import poses, series
    from drivesim.stages.preprocess.config import PoseConfig

    return poses.estimate_poses(series.load_series(trace), np.load(trace / "frame_times_ns.npy"), PoseConfig())


def test_odometry_with_a_few_swapped_stamps_is_sorted_and_measures_the_drive(tmp_path) -> None:
    """One swapped pair in 104 (two publishers interleaving): sorted, and the world is the drive's length."""
    start = 1_700_000_000_000_000_007

    def swap_one(i: int, t: int) -> int:
        return t + ODOM_PERIOD_NS if i == 40 else t - ODOM_PERIOD_NS if i == 41 else t

    _, trace = _odometry_drive(tmp_path, swap_one)
    fused = _odometry_poses(trace)
    drive_m = ODOM_SPEED_MPS * (np.load(trace / "frame_times_ns.npy")[-1] - start + 7) * 1e-9
    assert fused.arc_length_m[-1] == pytest.approx(drive_m, abs=0.2)
    assert np.allclose(fused.curvature_1pm, 1 / ARC_RADIUS_M, atol=2e-3)


@pytest.mark.parametrize(
    ("case", "expect"),
    [
        ("shuffled", "the odometry stamps go back in time at"),
        ("stuck clock", "odometry samples share their stamp with another of different values"),
    ],
)
def test_odometry_whose_stamps_cannot_time_it_is_refused_at_ingest(tmp_path, case, expect) -> None:
    """Shuffled stamps (a 66 m zig-zag for a 51 m drive before) and a clock that ticks every other message (wrong
    speeds and curvature) are refused with one line naming the recording, not sorted into a wrong world."""
    from drivesim.pipeline.errors import InputError

    rng = np.random.default_rng(1)
    shuffle = np.arange(104)
    for j in range(0, 100, 4):
        shuffle[j : j + 4] = rng.permutation(shuffle[j : j + 4])

    def shuffled(i: int, t: int) -> int:
        return t + int(shuffle[i] - i) * ODOM_PERIOD_NS

    def stuck(i: int, t: int) -> int:
        return t - (i % 2) * ODOM_PERIOD_NS

    with pytest.raises(InputError) as refused:
        _odometry_drive(tmp_path, shuffled if case == "shuffled" else stuck)
    line = refused.value.one_line()
    assert expect in line and line.startswith(str(tmp_path / "drive.mcap")) and "\n" not in line


def test_repeated_identical_messages_are_kept_once(tmp_path) -> None:
    """The same odometry message recorded twice (same stamp, same values) is not an error: it is kept once."""
    from drivesim.stages.ingest.stamps import ordered_series

    t = np.array([0, 10, 10, 20], dtype=np.int64)
    x = np.array([0.0, 1.0, 1.0, 2.0])
    out = ordered_series({"t_ns": t, "x": x}, "odometry")
    assert out["t_ns"].tolist() == [0, 10, 20] and out["x"].tolist() == [0.0, 1.0, 2.0]


def test_gps_fixes_stamped_in_whole_seconds_keep_the_first_of_each_stamp() -> None:
    """A receiver that stamps 5 Hz fixes in whole seconds: the fusion gets one fix per stamp, nothing is refused."""
    from drivesim.stages.ingest.stamps import ordered_series

    t = np.repeat(np.arange(4, dtype=np.int64) * 10**9, 5)
    lat = 49.0 + np.arange(20) * 1e-5
    out = ordered_series({"t_ns": t, "lat_deg": lat}, "gps")
    assert out["t_ns"].tolist() == [0, 10**9, 2 * 10**9, 3 * 10**9] and out["lat_deg"].tolist() == lat[::5].tolist()


def test_pose_stream_that_never_overlaps_the_camera_is_refused(tmp_path) -> None:
    """Odometry stamped 1000 s after the camera: refused (it was a 0.0 m world), naming both time spans."""
    from drivesim.pipeline.errors import InputError

    _, trace = _odometry_drive(tmp_path, lambda i, t: t + 1000 * 10**9)
    with pytest.raises(InputError, match=r"cover 0 of the 52 camera frames .*poses 1000\.0 s to 1005\.2 s"):
        _odometry_poses(trace)


# ---------------------------------------------------------------- damaged frames, cut videos, blank cameras, odd sizes


def _damaged_jpeg(data: np.ndarray | bytes) -> np.ndarray:
    """The JPEG cut in the middle of its scan and closed with an end marker: it still decodes, the lower half grey,
    and libjpeg says "Corrupt JPEG data: premature end of data segment"."""
    data = bytes(data)
    return np.frombuffer(data[: len(data) // 2] + b"\xff\xd9", np.uint8)


def _jpeg_drive(folder: Path, damaged: int, image_fn=None) -> Path:
    """An MCAP of 20 JPEG camera frames (GPS, IMU, twist) whose first `damaged` frames are damaged."""
    from recordings import drive_messages, textured_image, write_recording

    image_fn = image_fn or (lambda i: textured_image(160, 100, i))
    msgs = drive_messages(n_frames=20, width=160, height=100, compressed="jpeg", image_fn=image_fn)
    for m in [m for m in msgs if m.topic.endswith("compressed")][:damaged]:
        m.values["data"] = _damaged_jpeg(m.values["data"])
    return write_recording(folder / "drive.mcap", "mcap", msgs)


def _ingest(recording: Path, out: Path):
    from drivesim.stages.ingest.config import IngestConfig
    from drivesim.stages.ingest.run import ingest_recording

    out.mkdir()
    return ingest_recording(recording, IngestConfig(), out)


def test_a_few_damaged_jpeg_frames_are_left_out_and_reported(tmp_path) -> None:
    """Two of 20 frames that decode with "Corrupt JPEG data": left out (not kept with invented pixels), counted in
    the summary and said in a note."""
    result = _ingest(_jpeg_drive(tmp_path, damaged=2), tmp_path / "trace")
    assert result.summary["frame_count"] == 18 and result.summary["skipped"] == {"camera": 2}
    assert any("left out 2 damaged camera frame(s) of 20" in note for note in result.notes)


def test_many_damaged_jpeg_frames_refuse_the_recording(tmp_path) -> None:
    """Seven of 20 damaged (35 %, past the 10 % a drive may lose): refused with one line, not ingested with grey
    blocks."""
    from drivesim.pipeline.errors import InputError

    with pytest.raises(InputError, match=r"7 of 20 frames are damaged \(the image decoder reported corrupt data"):
        _ingest(_jpeg_drive(tmp_path, damaged=7), tmp_path / "trace")


@pytest.mark.parametrize("colour", [0, 255])
def test_a_camera_without_a_picture_is_refused(tmp_path, colour) -> None:
    """An all-black (or all-white) camera through the whole drive is refused at ingest."""
    from drivesim.pipeline.errors import InputError

    flat = lambda i: np.full((100, 160, 3), colour, np.uint8)  # noqa: E731
    with pytest.raises(InputError, match=r"shows no picture: 20 of 20 frames looked at are one flat colour"):
        _ingest(_jpeg_drive(tmp_path, damaged=0, image_fn=flat), tmp_path / "trace")


def test_a_dark_but_real_picture_is_not_called_blank(tmp_path) -> None:
    from recordings import textured_image

    dark = lambda i: (textured_image(160, 100, i) // 12).astype(np.uint8)  # noqa: E731
    result = _ingest(_jpeg_drive(tmp_path, damaged=0, image_fn=dark), tmp_path / "trace")
    assert result.summary["frame_count"] == 20


@pytest.mark.parametrize(("width", "height"), [(4000, 8), (8, 3000), (12, 8)])
def test_absurd_image_sizes_are_refused_with_one_line(tmp_path, monkeypatch, capsys, width, height) -> None:
    """A 4000x8 strip, an 8x3000 column or a 12x8 thumbnail is no driving camera: one line, exit 2, no trace (a
    100000x1 image gave a 640x1 trace, then "error: OSError (OSError)")."""
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i in range(5):
        cv2.imwrite(str(folder / f"{i:03d}.png"), rng.integers(0, 255, (height, width, 3), dtype=np.uint8))
    code, err = run_main(
        tmp_path / "ws",
        "ingest",
        str(folder),
        "--fps",
        "10",
        "--camera-height-m",
        "1.5",
        monkeypatch=monkeypatch,
        capsys=capsys,
    )
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1 and f"pictures of {width}x{height} px" in lines[0], err
    assert not (tmp_path / "ws" / "trace").exists()


def _mjpeg_avi(path: Path, frames: int) -> Path:
    from recordings import textured_image

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (160, 96))
    for i in range(frames):
        writer.write(textured_image(160, 96, i))
    writer.release()
    return path


def test_a_video_cut_short_is_refused_and_ffmpeg_stays_quiet(tmp_path) -> None:
    """An AVI announcing 60 frames cut in half (30 decode): one line naming both counts and the --end-s that takes
    the part that decodes, and nothing else on stderr: FFmpeg's own "overread" goes to the workspace's log."""
    import subprocess

    whole = _mjpeg_avi(tmp_path / "whole.avi", 60).read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(whole[: len(whole) // 2])
    ws = tmp_path / "ws"
    command = [sys.executable, "-m", "drivesim.cli.main", "-w", str(ws), "ingest", str(cut), "--camera-height-m", "1.5"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1, done.stderr
    assert "the video announces 60 frames but only 30 decode" in lines[0] and "--end-s 2.9" in lines[0]
    log = ws / "logs" / "ingest-decoders.log"
    assert "overread" in log.read_text() and not (ws / "trace").exists()


def test_damaged_world_through_eval_is_one_line_and_exit_2(built_world, tmp_path, monkeypatch, capsys) -> None:
    """K = 0 gave a LinAlgError traceback: now `drivesim eval` says which file is wrong, exit 2, no report."""
    world = tmp_path / "world"
    shutil.copytree(built_world, world)
    _set_camera("K", [[0, 0, 0], [0, 0, 0], [0, 0, 0]])(world)
    (world / "manifest.json").unlink()  # a world made by hand or by another tool: no hashes to catch the edit
    args = ["eval", "--world", str(world), "--policy", "expert", "--task", "lane", "--episodes", "1"]
    code, err = run_main(tmp_path / "ws", *args, monkeypatch=monkeypatch, capsys=capsys)
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1 and "camera.json: K has no positive focal lengths" in lines[0], err
    assert not (tmp_path / "ws" / "eval" / "lane-expert").exists()


def test_an_os_error_with_only_a_text_prints_the_text(tmp_path, monkeypatch, capsys) -> None:
    import drivesim.cli.status as status_cli

    def fail(*args, **kwargs):
        raise OSError("cannot map world/frames.npy")

    monkeypatch.setattr(status_cli, "status_report", fail)
    code, err = run_main(tmp_path / "ws", "status", monkeypatch=monkeypatch, capsys=capsys)
    assert code == 1 and _error_lines(err) == ["error: cannot map world/frames.npy (OSError)"], err


def test_decoder_messages_stay_out_of_the_terminal(tmp_path) -> None:
    """`drivesim ingest` of a drive with two damaged JPEGs: libjpeg's "Corrupt JPEG data" lines go to the
    workspace's log, the terminal gets drivesim's own lines only."""
    import subprocess

    recording = _jpeg_drive(tmp_path, damaged=2)
    ws = tmp_path / "ws"
    command = [sys.executable, "-m", "drivesim.cli.main", "-w", str(ws), "ingest", str(recording)]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "Corrupt JPEG" not in done.stderr + done.stdout
    assert "Corrupt JPEG data" in (ws / "logs" / "ingest-decoders.log").read_text()
    assert "left out 2 damaged camera frame(s)" in done.stdout


def test_a_damaged_jpeg_in_an_image_folder_is_refused_naming_it(tmp_path, monkeypatch, capsys) -> None:
    """An image folder's frames are SfM's input, so one that decodes with "Corrupt JPEG data" refuses the folder
    (as an unreadable one does), naming the file, instead of feeding grey blocks to SfM."""
    from recordings import textured_image

    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(12):
        ok, jpeg = cv2.imencode(".jpg", textured_image(160, 100, i))
        (folder / f"{i:03d}.jpg").write_bytes(bytes(_damaged_jpeg(jpeg) if i == 4 else jpeg))
    args = ["ingest", str(folder), "--fps", "10", "--camera-height-m", "1.5"]
    code, err = run_main(tmp_path / "ws", *args, monkeypatch=monkeypatch, capsys=capsys)
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1, err
    assert "004.jpg: unreadable image file: the image decoder reported damaged data" in lines[0]
