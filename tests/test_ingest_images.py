"""Camera pixels through ingest: every raw encoding, compressed jpeg/png, undistortion (plumb_bob, equidistant)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from recordings import (
    Msg,
    drive_messages,
    image_values,
    patch_image,
    textured_image,
    write_recording,
)

from drivesim.pipeline.errors import InputError
from drivesim.sim.image_stack import ImageStack
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.images import CameraModel, EncodingError, FrameProcessor, area_remap_tables, decode_raw
from drivesim.stages.ingest.run import ingest_recording
from drivesim.stages.ingest.trace import validate_trace

COLOUR = (200, 40, 90)
# Frames stored losslessly (PNG): the tests that compare pixels exactly check the decoding, not JPEG's rounding.
LOSSLESS = IngestConfig.model_validate({"image": {"codec": "png"}})
W, H = 64, 40


def _ingest(tmp_path: Path, msgs: list[Msg], cfg: IngestConfig | None = None, fmt: str = "mcap"):
    rec = write_recording(tmp_path / ("rec.mcap" if fmt == "mcap" else "rec.bag"), fmt, msgs)
    out = tmp_path / "trace"
    out.mkdir()
    result = ingest_recording(rec, cfg or IngestConfig(), out)
    return result, validate_trace(out)


def _patch_centre(frames: np.ndarray) -> np.ndarray:
    """Mean colour of the inner half of the colour patch over all frames."""
    return frames[:, H // 2 - 4 : H // 2 + 4, W // 2 - 8 : W // 2 + 8].reshape(-1, 3).mean(axis=0)


@pytest.mark.parametrize(
    ("encoding", "tolerance"),
    [
        ("rgb8", 0),
        ("bgr8", 0),
        ("rgba8", 0),
        ("bgra8", 0),
        ("yuv422", 6),
        ("yuv422_yuy2", 6),
        ("bayer_rggb8", 3),
        ("bayer_bggr8", 3),
        ("bayer_gbrg8", 3),
        ("bayer_grbg8", 3),
    ],
)
def test_colour_encodings_keep_the_patch_colour(tmp_path: Path, encoding: str, tolerance: int) -> None:
    _, info = _ingest(tmp_path, drive_messages(n_frames=3, encoding=encoding), LOSSLESS)
    frames = np.asarray(info.frames())
    assert frames.shape == (3, H, W, 3)
    np.testing.assert_allclose(_patch_centre(frames), COLOUR, atol=tolerance + 0.5)
    if tolerance == 0:  # lossless encodings give back the exact image, gradient included
        np.testing.assert_array_equal(frames[1], patch_image(W, H, COLOUR, frame=1))


@pytest.mark.parametrize("encoding", ["mono8", "mono16"])
def test_mono_encodings_give_grey_rgb(tmp_path: Path, encoding: str) -> None:
    _, info = _ingest(tmp_path, drive_messages(n_frames=2, encoding=encoding))
    frames = np.asarray(info.frames())
    grey = cv2.cvtColor(np.uint8([[COLOUR]]), cv2.COLOR_RGB2GRAY)[0, 0]
    centre = _patch_centre(frames)
    np.testing.assert_allclose(centre, [grey] * 3, atol=1.0)


@pytest.mark.parametrize(
    ("fmt", "tolerance", "container"), [("png", 0, "mcap"), ("jpeg", 8, "mcap"), ("jpeg", 8, "ros1")]
)
def test_compressed_images(tmp_path: Path, fmt: str, tolerance: int, container: str) -> None:
    result, info = _ingest(tmp_path, drive_messages(n_frames=4, compressed=fmt), LOSSLESS, fmt=container)
    assert result.summary["sensors"]["camera"]["type"] == "sensor_msgs/msg/CompressedImage"
    frames = np.asarray(info.frames())
    assert frames.shape == (4, H, W, 3)
    np.testing.assert_allclose(_patch_centre(frames), COLOUR, atol=tolerance + 0.5)


def test_jpeg_decoded_at_reduced_size_keeps_colour_and_intrinsics(tmp_path: Path) -> None:
    w, h = 256, 160
    K = np.array([[200.0, 0, 127.5], [0, 200.0, 79.5], [0, 0, 1]])
    msgs = drive_messages(
        n_frames=3, width=w, height=h, K=K, compressed="jpeg", image_fn=lambda i: patch_image(w, h, COLOUR, i)
    )
    cfg = IngestConfig.model_validate({"image": {"width_px": 64}})
    _, info = _ingest(tmp_path, msgs, cfg)
    assert (info.width_px, info.height_px) == (64, 40)
    np.testing.assert_allclose(_patch_centre(np.asarray(info.frames())), COLOUR, atol=8)
    # K follows the 4x downscale with the pixel-centre convention: cx = (127.5 + 0.5) / 4 - 0.5
    np.testing.assert_allclose(info.K[0], [50.0, 0.0, 31.5])


def test_row_padding_is_skipped() -> None:
    rgb = patch_image(6, 4, COLOUR)
    padded = np.zeros((4, 6 * 3 + 5), np.uint8)
    padded[:, :18] = rgb.reshape(4, 18)
    out = decode_raw(padded.tobytes(), "rgb8", 4, 6, step=23)
    np.testing.assert_array_equal(out, rgb)


def test_unknown_encoding_is_one_clear_error(tmp_path: Path) -> None:
    msgs = drive_messages(n_frames=2)
    for m in msgs:
        if m.topic == "/camera/image_raw":
            m.values["encoding"] = "rgb16f"
    with pytest.raises(InputError, match=r"unsupported image encoding 'rgb16f'"):
        _ingest(tmp_path, msgs)
    with pytest.raises(EncodingError):
        decode_raw(b"\0" * 12, "nv21", 2, 2)


# ---------------------------------------------------------------- undistortion


def _distorted_points(points_cam: np.ndarray, K: np.ndarray, D: np.ndarray, model: str) -> np.ndarray:
    """Pixel positions of 3D camera-frame points in the distorted image."""
    rvec = tvec = np.zeros(3)
    if model == "equidistant":
        pts, _ = cv2.fisheye.projectPoints(points_cam.reshape(-1, 1, 3), rvec, tvec, K, D)
    else:
        pts, _ = cv2.projectPoints(points_cam, rvec, tvec, K, D)
    return pts.reshape(-1, 2)


def _render_points(w: int, h: int, pixels: np.ndarray) -> np.ndarray:
    """Black image with a small white anti-aliased dot at each pixel position."""
    img = np.zeros((h, w, 3), np.uint8)
    shift = 4
    for u, v in pixels:
        centre = (round(u * (1 << shift)), round(v * (1 << shift)))
        cv2.circle(img, centre, 2 << shift, (255, 255, 255), -1, cv2.LINE_AA, shift)
    return img


def _centroid(frame: np.ndarray, u: float, v: float) -> tuple[float, float]:
    """Intensity centroid of the dot drawn near (u, v)."""
    y0, x0 = int(round(v)) - 3, int(round(u)) - 3
    win = frame[y0 : y0 + 7, x0 : x0 + 7]
    assert win.sum() > 1000, f"no dot near ({u:.1f}, {v:.1f})"
    ys, xs = np.mgrid[y0 : y0 + 7, x0 : x0 + 7]
    return (win * xs).sum() / win.sum(), (win * ys).sum() / win.sum()


@pytest.mark.parametrize(
    ("model", "D"),
    [
        ("plumb_bob", np.array([-0.35, 0.12, 0.001, -0.001, 0.0])),
        ("equidistant", np.array([0.08, -0.02, 0.01, -0.002])),
    ],
)
def test_undistortion_maps_points_to_their_pinhole_projection(tmp_path: Path, model: str, D: np.ndarray) -> None:
    w, h = 320, 200
    K = np.array([[170.0, 0, 159.5], [0, 170.0, 99.5], [0, 0, 1]])
    # A 3D straight line across the view, and a few isolated points near the corners (strongest distortion).
    line = np.stack([np.linspace(-1.4, 1.4, 24), np.full(24, 0.75), np.full(24, 2.0)], axis=1)
    corners = np.array([[-0.7, -0.4, 1.0], [0.7, 0.4, 1.0], [0.6, -0.38, 1.0]])
    img = _render_points(w, h, _distorted_points(np.vstack([line, corners]), K, D, model))
    msgs = drive_messages(
        n_frames=2, width=w, height=h, K=K, D=D.tolist(), distortion_model=model, image_fn=lambda i: img
    )
    cfg = IngestConfig.model_validate({"image": {"width_px": w}})
    _, info = _ingest(tmp_path, msgs, cfg)
    assert info.calibration["distortion_model"] == model
    frame = np.asarray(info.frames()[0])[..., 0].astype(float)

    # Every dot lands at its pinhole projection K X: the corner dots, and the line's dots, which are straight again.
    for X in np.vstack([corners, line[2:-2]]):
        u, v = (info.K @ X)[:2] / X[2]
        cu, cv_ = _centroid(frame, u, v)
        assert abs(cu - u) < 0.35 and abs(cv_ - v) < 0.35, f"dot at ({cu:.2f}, {cv_:.2f}), expected ({u:.2f}, {v:.2f})"
    # Without undistortion the same dots would bow by several pixels: the check above can fail.
    raw_v = _distorted_points(line, K, D, model)[:, 1]
    assert raw_v.max() - raw_v.min() > 3


def test_camera_message_for_image_values_roundtrip() -> None:
    values = image_values(5, patch_image(8, 6, COLOUR), "bgr8")
    out = decode_raw(values["data"], "bgr8", 6, 8, values["step"])
    np.testing.assert_array_equal(out, patch_image(8, 6, COLOUR))


@pytest.mark.parametrize(("src", "out"), [((960, 600), (640, 400)), ((800, 500), (640, 400))])
def test_area_by_remap_matches_inter_area(src: tuple[int, int], out: tuple[int, int]) -> None:
    assert area_remap_tables(src, out) is not None
    img = textured_image(*src, frame=3)
    K = np.array([[300.0, 0, src[0] / 2 - 0.5], [0, 300.0, src[1] / 2 - 0.5], [0, 0, 1]])
    camera = CameraModel(K=K, D=np.zeros(5), model="none", P=K, R=np.eye(3), width_px=src[0], height_px=src[1])
    ours = FrameProcessor(camera, out, "area").process(img).astype(int)
    reference = cv2.resize(img, out, interpolation=cv2.INTER_AREA).astype(int)
    assert np.abs(ours - reference).max() <= 5 and np.abs(ours - reference).mean() < 0.5
    # and it is an average, not a point sample: linear interpolation differs much more on this texture
    linear = cv2.resize(img, out, interpolation=cv2.INTER_LINEAR).astype(int)
    assert np.abs(linear - reference).mean() > 3 * np.abs(ours - reference).mean()


def test_area_remap_only_where_it_is_exact() -> None:
    assert area_remap_tables((1242, 375), (640, 193)) is None  # footprints of 1.94 px span three pixels
    assert area_remap_tables((1280, 800), (640, 400)) is None  # integer factor: cv2.INTER_AREA's fast path


def test_keep_original_stores_undistorted_frames_at_the_recorded_size(tmp_path: Path) -> None:
    w, h = 128, 80
    K = np.array([[90.0, 0, 63.5], [0, 90.0, 39.5], [0, 0, 1]])
    D = [-0.3, 0.1, 0.0, 0.0, 0.0]
    msgs = drive_messages(n_frames=3, width=w, height=h, K=K, D=D, image_fn=lambda i: patch_image(w, h, frame=i))
    cfg = IngestConfig.model_validate({"image": {"width_px": 64, "keep_original": True, "codec": "png"}})
    _, info = _ingest(tmp_path, msgs, cfg)
    originals = ImageStack(info.path / "frames_original.imgs")
    assert originals.shape == (3, h, w, 3) and info.frames().shape == (3, 40, 64, 3)
    np.testing.assert_allclose(info.calibration["K_source"], K)
    # the originals are undistorted: equal to cv2.undistort of the recorded image
    expected = cv2.undistort(patch_image(w, h, frame=1), K, np.array(D))
    assert np.abs(originals[1].astype(int) - expected.astype(int)).mean() < 1.0
    # and the working frames are the originals downscaled
    np.testing.assert_allclose(
        info.frames()[1], cv2.resize(originals[1], (64, 40), interpolation=cv2.INTER_AREA), atol=1
    )
