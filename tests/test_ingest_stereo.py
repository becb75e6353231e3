"""A KITTI odometry stereo folder through ingest (issue 20): the left camera is the trace's camera, the right one's
frames and the stereo baseline are kept for `depth.method: stereo`."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from cli_helpers import REAL_DATA
from kitti_fakes import FX_PX, kitti_stereo_folder

from drivesim.pipeline.errors import InputError
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.run import ingest_recording
from drivesim.stages.ingest.trace import validate_trace

STEREO = REAL_DATA / "kitti_odometry_stereo"


def _ingest(folder: Path, tmp_path: Path, cfg: IngestConfig | None = None):
    out = tmp_path / f"trace-{folder.name}"
    out.mkdir()
    result = ingest_recording(folder, cfg or IngestConfig(), out)
    return result, validate_trace(out)


def _grey_rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), cv2.COLOR_GRAY2RGB)


def test_stereo_folder_keeps_both_cameras_and_the_baseline(tmp_path: Path) -> None:
    folder = kitti_stereo_folder(tmp_path / "seq", n=5, baseline_m=0.54)
    lossless = IngestConfig.model_validate({"image": {"codec": "png"}})  # frames compared pixel for pixel below
    result, info = _ingest(folder, tmp_path, lossless)
    assert info.sources["format"] == "kitti_odometry_stereo" and info.sources["camera_topic"] == "image_l"
    assert info.frame_count == 5 and (info.width_px, info.height_px) == (96, 32)
    # 10 Hz without times.txt; poses.txt of the left camera, 1 m forward per frame
    np.testing.assert_array_equal(info.frame_times_ns(), np.arange(5) * 100_000_000)
    np.testing.assert_allclose(info.load_series("poses")["T_world_camera"][:, 2, 3], np.arange(5.0))
    np.testing.assert_allclose(info.K, [[FX_PX, 0, 47.5], [0, FX_PX, 15.5], [0, 0, 1]])
    # the right camera: same size and intrinsics, frame i taken with left frame i, 0.54 m to the right
    assert info.baseline_m == pytest.approx(0.54)
    assert info.calibration["right_camera"] == "image_r"
    right = info.right_frames()
    assert right.shape == info.frames().shape
    for i in (0, 4):
        np.testing.assert_array_equal(info.frames()[i], _grey_rgb(folder / "image_l" / f"{i:06d}.png"))
        np.testing.assert_array_equal(right[i], _grey_rgb(folder / "image_r" / f"{i:06d}.png"))
    assert result.summary["sensors"]["camera_right"] == {"topic": "image_r", "type": "png", "message_count": 5}
    assert any("baseline 0.540 m" in note for note in result.notes)


def test_stereo_at_a_working_width_and_with_kitti_names_and_times(tmp_path: Path) -> None:
    folder = kitti_stereo_folder(tmp_path / "seq", n=4, width=128, height=40, names=("image_0", "image_1"))
    np.savetxt(folder / "times.txt", [0.0, 0.11, 0.2, 0.31])
    _, info = _ingest(folder, tmp_path, IngestConfig.model_validate({"image": {"width_px": 64}}))
    assert (info.width_px, info.height_px) == (64, 20) and info.right_frames().shape == (4, 20, 64, 3)
    assert info.K[0, 0] == pytest.approx(FX_PX / 2) and info.baseline_m == pytest.approx(0.5)
    np.testing.assert_array_equal(info.frame_times_ns(), [0, 110_000_000, 200_000_000, 310_000_000])


def test_a_mono_odometry_folder_has_no_right_camera(tmp_path: Path) -> None:
    folder = kitti_stereo_folder(tmp_path / "seq", n=3)
    shutil.rmtree(folder / "image_r")
    _, info = _ingest(folder, tmp_path)
    assert info.sources["format"] == "kitti_odometry" and info.baseline_m is None and info.right_frames() is None
    assert not (info.path / "frames_right.imgs").exists() and "baseline_m" not in info.calibration


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        ("one_right_image_missing", "4 right images for 5 left images"),
        ("right_other_intrinsics", "not a rectified stereo pair: the two cameras' P have different intrinsics"),
        ("right_on_the_left", "not a rectified stereo pair: the right camera sits at [-0.5"),
    ],
)
def test_a_broken_pair_is_refused_in_one_line(tmp_path: Path, damage: str, message: str) -> None:
    folder = kitti_stereo_folder(tmp_path / "seq", n=5)
    calib = (folder / "calib.txt").read_text().splitlines()
    if damage == "one_right_image_missing":
        (folder / "image_r" / "000003.png").unlink()
    elif damage == "right_other_intrinsics":
        calib[1] = calib[1].replace("8.000000000000e+01", "8.100000000000e+01", 1)
    else:
        calib[1] = calib[1].replace("-4.000000000000e+01", "4.000000000000e+01")
    (folder / "calib.txt").write_text("\n".join(calib) + "\n")
    with pytest.raises(InputError) as err:
        _ingest(folder, tmp_path)
    assert message in err.value.one_line() and "\n" not in err.value.one_line()


def test_the_shared_kitti_stereo_snippet(tmp_path: Path) -> None:
    if not STEREO.is_dir():
        pytest.skip(f"real data not available at {STEREO}")
    folder = tmp_path / "seq"
    folder.mkdir()
    shutil.copy(STEREO / "calib.txt", folder / "calib.txt")
    (folder / "poses.txt").write_text("\n".join((STEREO / "poses.txt").read_text().splitlines()[:3]) + "\n")
    for side in ("image_l", "image_r"):
        (folder / side).mkdir()
        for f in sorted((STEREO / side).iterdir())[:3]:
            shutil.copy(f, folder / side / f.name)
    _, info = _ingest(folder, tmp_path, IngestConfig.model_validate({"image": {"width_px": 320}}))
    assert info.baseline_m == pytest.approx(0.537, abs=0.001)  # -P1[0,3] / P1[0,0] = 379.8145 / 707.0912
    right = np.asarray(info.right_frames())
    assert right.shape == (3, 97, 320, 3) and right.std() > 20  # a real picture, not blank
    # the right camera sees the scene shifted left: its image is not the left one
    assert np.abs(right.astype(int) - np.asarray(info.frames()).astype(int)).mean() > 5
