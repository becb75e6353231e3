"""The compiled rectangle measures an env step uses (sim/footprint_kernel.py) against shapely's polygons."""

from __future__ import annotations

import numpy as np
import pytest
from shapely import Polygon, distance, intersection

from drivesim.sim.footprint import (
    COLLISION_DILATION_LENGTH_M,
    COLLISION_DILATION_WIDTH_M,
    collision_overlap,
    footprint,
    pose_clearance_m,
)
from drivesim.sim.footprint_kernel import rectangle


def _random_pairs(count: int, seed: int) -> list[tuple[tuple, tuple, tuple, tuple]]:
    """Pairs of vehicles near each other: apart, touching corners, overlapping, one inside the other."""
    rng = np.random.default_rng(seed)
    pairs = []
    for _ in range(count):
        ego_pose = (float(rng.uniform(-5, 5)), float(rng.uniform(-5, 5)), float(rng.uniform(-np.pi, np.pi)))
        offset = rng.normal(0.0, 3.0, 2)
        other_pose = (ego_pose[0] + offset[0], ego_pose[1] + offset[1], float(rng.uniform(-np.pi, np.pi)))
        ego_size = (float(rng.uniform(3.5, 5.0)), float(rng.uniform(1.6, 2.0)))
        other_size = (float(rng.uniform(0.5, 6.0)), float(rng.uniform(0.5, 2.5)))
        pairs.append((ego_pose, ego_size, other_pose, other_size))
    return pairs


def test_rectangle_corners_are_footprints_corners() -> None:
    corners = rectangle(1.0, -2.0, 0.7, 4.5, 1.8)
    expected = np.asarray(footprint(1.0, -2.0, 0.7, 4.5, 1.8).exterior.coords)[:4]
    np.testing.assert_allclose(corners, expected, atol=1e-12)


def test_clearance_and_overlaps_match_shapely_on_random_pairs() -> None:
    overlapping = apart = 0
    for ego_pose, ego_size, other_pose, other_size in _random_pairs(2000, seed=3):
        ego, other = footprint(*ego_pose, *ego_size), footprint(*other_pose, *other_size)
        expected_clearance = distance(ego, other)
        assert pose_clearance_m(ego_pose, ego_size, other_pose, other_size) == pytest.approx(
            expected_clearance, abs=1e-9
        )
        dilated = footprint(
            *ego_pose, ego_size[0] + COLLISION_DILATION_LENGTH_M, ego_size[1] + COLLISION_DILATION_WIDTH_M
        )
        area = ego_size[0] * ego_size[1]
        assert collision_overlap(ego_pose, ego_size, other_pose, other_size, dilate=False) == pytest.approx(
            intersection(ego, other).area / area, abs=1e-9
        )
        assert collision_overlap(ego_pose, ego_size, other_pose, other_size, dilate=True) == pytest.approx(
            intersection(dilated, other).area / area, abs=1e-9
        )
        overlapping += expected_clearance == 0.0
        apart += expected_clearance > 0.5
    assert overlapping > 200 and apart > 200  # both branches exercised


def test_a_rectangle_inside_another_shares_its_whole_area() -> None:
    ego_pose, ego_size = (0.0, 0.0, 0.3), (4.5, 1.8)
    inner = ((0.2, 0.1, 0.3), (1.0, 0.5))
    assert collision_overlap(ego_pose, ego_size, *inner, dilate=False) == pytest.approx(0.5 / 8.1)
    assert pose_clearance_m(ego_pose, ego_size, *inner) == 0.0


def test_touching_edges_have_zero_clearance_and_no_area() -> None:
    ego_pose, size = (0.0, 0.0, 0.0), (4.0, 2.0)
    beside = (0.0, 2.0, 0.0)  # shares the ego's left edge
    assert pose_clearance_m(ego_pose, size, beside, size) == 0.0
    assert collision_overlap(ego_pose, size, beside, size, dilate=False) == pytest.approx(0.0, abs=1e-12)
    assert Polygon(footprint(*ego_pose, *size)).touches(footprint(*beside, *size))
