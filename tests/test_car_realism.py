"""The realism test's mechanics: the hand-marked boxes, the crops, the inserted car's place and the C2ST itself."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivesim.bench import car_realism as cr

ROOT = Path(__file__).resolve().parents[1]
BOXES = ROOT / "benchmarks" / "data" / "real_car_boxes.json"
REAL = ROOT.parent / "shared" / "data" / "real"
FRAME_SIZES = {"0001": (1242, 375), "06": (1226, 370), "00": (1241, 376), "07": (1226, 370)}  # (w, h) px
FRAME_COUNTS = {"0001": 108, "06": 51, "00": 200, "07": 160}


def test_boxes_file_has_cars_on_several_drives_inside_their_frames():
    boxes = cr.load_boxes(BOXES)
    assert len(boxes) >= 60
    assert len({b.drive for b in boxes}) >= 3
    for b in boxes:
        w, h = FRAME_SIZES[b.drive]
        x0, y0, x1, y1 = b.box
        assert 0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h, b
        assert y1 - y0 >= 10, f"{b}: too small to judge"
        assert 0 <= b.frame < FRAME_COUNTS[b.drive], b
    assert {b.motion for b in boxes} == {"parked", "moving"}
    assert {b.view for b in boxes} == set(cr.VIEW_YAW_RAD)  # cars seen from behind, in front and broadside


def test_boxes_file_with_a_bad_entry_is_refused(tmp_path):
    bad = tmp_path / "boxes.json"
    bad.write_text(json.dumps({"boxes": [{"drive": "0001", "frame": 0, "box": [10, 10, 5, 20], "motion": "parked"}]}))
    with pytest.raises(ValueError, match="box 0 is empty"):
        cr.load_boxes(bad)
    entry = {"drive": "0001", "frame": 0, "box": [10, 10, 50, 40], "motion": "parked", "view": "top"}
    bad.write_text(json.dumps({"boxes": [entry]}))
    with pytest.raises(ValueError, match="box 0 has view 'top'"):
        cr.load_boxes(bad)


def test_the_car_turns_to_the_view_and_its_near_end_stays_on_the_box_row():
    K = np.array([[721.5, 0.0, 609.6], [0.0, 721.5, 172.9], [0.0, 0.0, 1.0]])
    box = (500, 180, 600, 240)
    length_m, width_m = 4.5, 1.8
    near_m = cr.ground_distance_m(K, box[3], box[3] - box[1])
    for view, forward_cam, depth_m in (
        ("rear", (0, 0, 1), length_m), ("front", (0, 0, -1), length_m), ("left", (-1, 0, 0), width_m),
        ("right", (1, 0, 0), width_m),
    ):  # fmt: skip
        T = cr.camera_pose_of_car(K, box, length_m, width_m, cr.VIEW_YAW_RAD[view])
        np.testing.assert_allclose(T[:3, 0], forward_cam, atol=1e-12, err_msg=view)  # the car's nose points there
        np.testing.assert_allclose(T[:3, 2], (0, -1, 0), atol=1e-12)  # still upright
        assert T[2, 3] - 0.5 * depth_m == pytest.approx(near_m), view  # the footprint's near edge on the box row


def test_crop_is_the_box_widened_and_resized_to_one_gray_size():
    image = np.zeros((100, 200, 3), dtype=np.uint8)
    image[40:60, 50:90] = 200  # a bright 40 x 20 box
    patch = cr.crop(image, (50, 40, 90, 60), margin=0.0)
    assert patch.shape == (cr.CROP_SIZE_PX[1], cr.CROP_SIZE_PX[0]) and patch.dtype == np.uint8
    assert patch.min() == 200
    widened = cr.crop(image, (50, 40, 90, 60), margin=0.25)  # the 25 % margins are dark
    assert widened[0].max() == 0 and widened[:, 0].max() == 0 and widened[20, 32] == 200
    halved = cr.crop(image, (50, 40, 90, 60), margin=0.0, width_px=100)  # the box follows the reduced image
    assert halved.shape == patch.shape and halved.min() == 200
    with pytest.raises(ValueError, match="outside"):
        cr.crop(image, (300, 10, 350, 40))


def test_c2st_is_near_chance_on_one_distribution_and_near_certain_on_two():
    rng = np.random.default_rng(1)
    same = rng.normal(size=(120, 40))
    labels = np.r_[np.zeros(60), np.ones(60)]
    chance, low, high = cr.accuracy_interval(cr.c2st(same, labels))
    assert 0.35 <= chance <= 0.65 and low < 0.5 < high
    apart = same + labels[:, None] * 1.5
    assert cr.accuracy_interval(cr.c2st(apart, labels))[0] >= 0.97


def test_c2st_on_hog_tells_bright_boxes_from_striped_ones():
    rng = np.random.default_rng(2)
    h, w = cr.CROP_SIZE_PX[1], cr.CROP_SIZE_PX[0]
    plain = [np.clip(rng.normal(120, 10, (h, w)), 0, 255).astype(np.uint8) for _ in range(20)]
    striped = []
    for _ in range(20):
        image = np.clip(rng.normal(120, 10, (h, w)), 0, 255).astype(np.uint8)
        image[:, ::6] = 30
        striped.append(image)
    features = cr.hog_features(np.stack(plain + striped))
    assert cr.accuracy_interval(cr.c2st(features, np.r_[np.zeros(20), np.ones(20)]))[0] >= 0.95


@pytest.mark.skipif(not (REAL / "kitti_raw").is_dir(), reason="the real drives are not beside the checkout")
def test_inserted_car_lands_on_the_real_box_at_every_level():
    box = (311, 178, 399, 227)  # the first parked car of KITTI raw 0001, frame 0
    frame = cr.load_frame(REAL, "0001", 0)
    K = cr.drive_intrinsics(REAL, "0001")
    model = cr.library_car(0)
    aspect = {}
    for level, view in [(level, "rear") for level in cr.LEVELS] + [("camera", "front"), ("camera", "left")]:
        image, (x0, y0, x1, y1) = cr.insert_car(frame, K, box, model, level, view)
        aspect[view] = (x1 - x0) / (y1 - y0)
        assert image.shape == frame.shape
        assert abs(y1 - box[3]) <= 6, (level, y1)  # stands on the box's bottom row
        assert abs(0.5 * (x0 + x1) - 0.5 * (box[0] + box[2])) <= 0.25 * (box[2] - box[0]), level
        assert 0.5 <= (y1 - y0) / (box[3] - box[1]) <= 1.5, level
        changed = np.any(image != frame, axis=-1)
        assert changed[y0:y1, x0:x1].mean() > 0.5 and not changed[:100].any(), level
        gray = cv2.cvtColor(image[y0:y1, x0:x1], cv2.COLOR_RGB2GRAY)
        assert np.array_equal(image[y0:y1, x0:x1, 0], gray), level  # a gray camera's car is gray
    assert aspect["left"] > 1.5 * aspect["rear"]  # broadside, the car's length shows
    assert aspect["front"] == pytest.approx(aspect["rear"], rel=0.3)


def test_reduced_view_scales_the_frame_its_intrinsics_and_the_box_together():
    frame = np.zeros((375, 1242, 3), dtype=np.uint8)
    frame[180:230, 300:400] = 200
    K = np.array([[721.5, 0.0, 609.6], [0.0, 721.5, 172.9], [0.0, 0.0, 1.0]])
    small, K_small, box = cr.reduced_view(frame, K, (300, 180, 400, 230), 320)
    assert small.shape == (97, 320, 3)
    assert box == (77, 46, 103, 59)
    point = np.array([2.0, 1.0, 20.0])  # a camera-frame point lands where the reduced image shows it
    u, v = (K @ point)[:2] / point[2]
    u_small, v_small = (K_small @ point)[:2] / point[2]
    # Pixel centres at integer coordinates: a pixel's centre u maps to (u + 0.5) * scale - 0.5.
    assert u_small == pytest.approx((u + 0.5) * 320 / 1242 - 0.5)
    assert v_small == pytest.approx((v + 0.5) * 97 / 375 - 0.5)
    x0, y0, x1, y1 = box
    assert small[y0 + 2 : y1 - 2, x0 + 2 : x1 - 2].min() == 200, "the box still holds the bright patch"
