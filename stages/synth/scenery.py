"""Where things stand beside the road: buildings, trees and parked cars, placed from a seed.

The layout is plain data (positions and sizes in world ENU metres); `world.py` turns it into meshes and `preview.py`
draws it on the map. Objects keep clear of the road and sidewalks and of each other (checked on a 1 m grid).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from drivesim.stages.synth.config import RoadConfig, SceneryConfig
from drivesim.stages.synth.road import RoadPath

BLOCK_LENGTH_M = 60.0
PARKING_BAY_M = 6.0
OCCUPANCY_CELL_M = 1.0


@dataclass(frozen=True)
class Building:
    """A box building: centre on the ground, heading of its x axis (along the road), size, facade seed, and the side of
    the road it stands on (+1 left, -1 right)."""

    x_m: float
    y_m: float
    yaw_rad: float
    length_m: float
    depth_m: float
    height_m: float
    facade_seed: int
    road_side: float


@dataclass(frozen=True)
class Tree:
    """A tree: trunk base position, trunk height and crown radius."""

    x_m: float
    y_m: float
    trunk_height_m: float
    crown_radius_m: float
    shade: float


@dataclass(frozen=True)
class ParkedCar:
    """A parked car: centre on the ground, heading, body colour (RGB in [0, 1])."""

    x_m: float
    y_m: float
    yaw_rad: float
    length_m: float
    width_m: float
    rgb: tuple[float, float, float]


@dataclass
class Layout:
    """Everything placed beside the road."""

    buildings: list[Building] = field(default_factory=list)
    trees: list[Tree] = field(default_factory=list)
    cars: list[ParkedCar] = field(default_factory=list)


def road_half_width_m(road: RoadConfig) -> float:
    """Half the asphalt width: one lane plus its parking strip."""
    return road.lane_width_m + road.parking_width_m


CURB_TOP_WIDTH_M = 0.2


def sidewalk_outer_m(road: RoadConfig) -> float:
    """Lateral distance from the centreline to the outer edge of the sidewalks."""
    return road_half_width_m(road) + CURB_TOP_WIDTH_M + road.sidewalk_width_m


CAR_COLOURS = [
    (0.85, 0.85, 0.86),
    (0.08, 0.08, 0.09),
    (0.45, 0.47, 0.50),
    (0.62, 0.64, 0.67),
    (0.55, 0.06, 0.06),
    (0.08, 0.18, 0.45),
    (0.12, 0.28, 0.18),
    (0.80, 0.72, 0.55),
]


class _Occupancy:
    """Footprints already taken, on a 1 m grid, plus a distance check against the road centreline."""

    def __init__(self, road: RoadPath, clearance_m: float) -> None:
        self.tree = cKDTree(np.column_stack([road.x_m, road.y_m]))
        self.clearance_m = clearance_m
        self.cells: set[tuple[int, int]] = set()

    @staticmethod
    def _rect_points(cx: float, cy: float, yaw: float, length: float, width: float) -> np.ndarray:
        u = np.arange(-length / 2, length / 2 + 1e-9, OCCUPANCY_CELL_M / 2)
        v = np.arange(-width / 2, width / 2 + 1e-9, OCCUPANCY_CELL_M / 2)
        uu, vv = np.meshgrid(np.append(u, length / 2), np.append(v, width / 2))
        c, s = np.cos(yaw), np.sin(yaw)
        return np.column_stack([cx + c * uu.ravel() - s * vv.ravel(), cy + s * uu.ravel() + c * vv.ravel()])

    def try_take(self, cx: float, cy: float, yaw: float, length: float, width: float, clearance_m: float) -> bool:
        """Reserve the rectangle if it is at least `clearance_m` from the road centreline and free."""
        pts = self._rect_points(cx, cy, yaw, length, width)
        dist, _ = self.tree.query(pts)
        if np.min(dist) < clearance_m:
            return False
        cells = {(int(a), int(b)) for a, b in np.floor(pts / OCCUPANCY_CELL_M)}
        if cells & self.cells:
            return False
        self.cells |= cells
        return True


def place_scenery(road: RoadPath, road_cfg: RoadConfig, cfg: SceneryConfig, rng: np.random.Generator) -> Layout:
    """Buildings in built-up blocks, trees in open blocks, on the sidewalks and in the background, parked cars."""
    layout = Layout()
    outer = sidewalk_outer_m(road_cfg)
    occ = _Occupancy(road, outer)
    for side in (1.0, -1.0):
        s_block = 0.0
        while s_block < road.length_m:
            built = rng.random() < cfg.building_probability
            s_end = min(s_block + BLOCK_LENGTH_M, road.length_m)
            if built:
                _place_buildings(road, side, s_block, s_end, outer, cfg, occ, rng, layout)
                _place_trees(road, side, s_block, s_end, outer - 0.9, outer - 0.7, 11.0, occ, rng, layout, 0.7)
            else:
                _place_trees(
                    road, side, s_block, s_end, outer + 1.5, outer + 14.0, cfg.tree_spacing_m, occ, rng, layout
                )
            s_block = s_end
    _place_background_trees(road, outer, cfg, occ, rng, layout)
    _place_cars(road, road_cfg, cfg, rng, layout)
    return layout


def _place_buildings(
    road: RoadPath,
    side: float,
    s0: float,
    s1: float,
    outer: float,
    cfg: SceneryConfig,
    occ: _Occupancy,
    rng: np.random.Generator,
    layout: Layout,
) -> None:
    cursor = s0 + rng.uniform(0.0, 4.0)
    while cursor < s1:
        length = rng.uniform(8.0, 22.0)
        depth = rng.uniform(8.0, 15.0)
        height = rng.uniform(*cfg.building_height_m)
        station = cursor + length / 2
        if station > road.length_m:
            break
        p = road.at(station)
        setback = rng.uniform(*cfg.building_setback_m)
        lateral = side * (outer + setback + depth / 2)
        yaw = float(p["yaw_rad"])
        cx = float(p["x_m"]) - np.sin(yaw) * lateral
        cy = float(p["y_m"]) + np.cos(yaw) * lateral
        if occ.try_take(cx, cy, yaw, length, depth, outer + 0.5):
            layout.buildings.append(Building(cx, cy, yaw, length, depth, height, int(rng.integers(1 << 31)), side))
        cursor += length + rng.uniform(0.3, 4.0)


def _place_trees(
    road: RoadPath,
    side: float,
    s0: float,
    s1: float,
    lat_min: float,
    lat_max: float,
    spacing: float,
    occ: _Occupancy,
    rng: np.random.Generator,
    layout: Layout,
    probability: float = 1.0,
) -> None:
    station = s0 + rng.uniform(0.0, spacing)
    while station < s1:
        if rng.random() < probability:
            p = road.at(station)
            lateral = side * rng.uniform(lat_min, lat_max)
            yaw = float(p["yaw_rad"])
            x = float(p["x_m"]) - np.sin(yaw) * lateral
            y = float(p["y_m"]) + np.cos(yaw) * lateral
            if occ.try_take(x, y, 0.0, 1.0, 1.0, lat_min - 0.6):
                layout.trees.append(_random_tree(x, y, rng))
        station += spacing * rng.uniform(0.6, 1.4)


def _random_tree(x: float, y: float, rng: np.random.Generator) -> Tree:
    return Tree(x, y, rng.uniform(1.8, 3.2), rng.uniform(1.6, 3.2), rng.uniform(0.75, 1.15))


def _place_background_trees(
    road: RoadPath, outer: float, cfg: SceneryConfig, occ: _Occupancy, rng: np.random.Generator, layout: Layout
) -> None:
    """Scattered trees 25-100 m from the road so that the horizon is not bare."""
    area_m2 = 2 * 75.0 * road.length_m
    n = int(area_m2 / 700.0)
    s = rng.uniform(0.0, road.length_m, n)
    lateral = rng.choice([-1.0, 1.0], n) * rng.uniform(outer + 18.0, outer + 95.0, n)
    p = road.at(s)
    xs = p["x_m"] - np.sin(p["yaw_rad"]) * lateral
    ys = p["y_m"] + np.cos(p["yaw_rad"]) * lateral
    for x, y in zip(xs, ys, strict=True):
        if occ.try_take(float(x), float(y), 0.0, 1.0, 1.0, outer + 15.0):
            layout.trees.append(_random_tree(float(x), float(y), rng))


def _place_cars(
    road: RoadPath, road_cfg: RoadConfig, cfg: SceneryConfig, rng: np.random.Generator, layout: Layout
) -> None:
    """Cars in the parking strips, parked with the traffic (right-hand traffic: facing +s on the right)."""
    if road_cfg.parking_width_m < 1.6:
        return
    lateral_abs = road_cfg.lane_width_m + road_cfg.parking_width_m / 2 + 0.05
    for side in (1.0, -1.0):
        for station in np.arange(PARKING_BAY_M / 2, road.length_m - PARKING_BAY_M / 2, PARKING_BAY_M):
            if rng.random() >= cfg.parked_car_probability:
                continue
            s = station + rng.uniform(-0.6, 0.6)
            p = road.at(s)
            yaw = float(p["yaw_rad"])
            lateral = side * (lateral_abs + rng.uniform(-0.15, 0.15))
            x = float(p["x_m"]) - np.sin(yaw) * lateral
            y = float(p["y_m"]) + np.cos(yaw) * lateral
            heading = yaw if side < 0 else yaw + np.pi
            colour = CAR_COLOURS[int(rng.integers(len(CAR_COLOURS)))]
            layout.cars.append(ParkedCar(x, y, heading, rng.uniform(4.0, 4.8), rng.uniform(1.72, 1.86), colour))
