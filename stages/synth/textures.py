"""Procedural textures (uint8 RGB) for the synthetic world: asphalt with lane markings, paving, grass, facades.

Noise is made periodic (filtered in the Fourier domain) so that textures repeat along the road without seams.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

ROAD_PX_PER_M = 32.0
SIDEWALK_PX_PER_M = 48.0
GRASS_PX_PER_M = 24.0
FACADE_PX_PER_M = 16.0

DASH_PERIOD_M = 9.0
DASH_LENGTH_M = 3.0
LINE_WIDTH_M = 0.15


def periodic_noise(rng: np.random.Generator, height_px: int, width_px: int, scale_px: float) -> np.ndarray:
    """Seamlessly tiling noise of zero mean and unit std with features about `scale_px` pixels across."""
    white = rng.normal(size=(height_px, width_px))
    fy = np.fft.fftfreq(height_px)[:, None]
    fx = np.fft.fftfreq(width_px)[None, :]
    gain = np.exp(-2.0 * (np.pi * scale_px) ** 2 * (fx * fx + fy * fy))
    out = np.real(np.fft.ifft2(np.fft.fft2(white) * gain))
    return (out - out.mean()) / (out.std() + 1e-12)


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.round(rgb), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class RoadLayout:
    """Lateral layout of the asphalt (metres, left positive, centreline at 0).

    :param lane_width_m: width of each lane; edge lines at +-lane_width_m.
    :param half_width_m: half the asphalt width (lanes + parking strip), where the curbs are.
    :param edge_lines: whether the edge lines are painted (the dashed centre line always is).
    """

    lane_width_m: float
    half_width_m: float
    edge_lines: bool = True


def asphalt_texture(rng: np.random.Generator, layout: RoadLayout) -> np.ndarray:
    """One dash period of road (rows = along the road, v down = forward; columns = across, u = 0 at the left curb):
    asphalt with grain, wear, white edge lines (unless `layout.edge_lines` is off) and a dashed centre line."""
    h = int(round(DASH_PERIOD_M * ROAD_PX_PER_M))
    w = int(round(2 * layout.half_width_m * ROAD_PX_PER_M))
    grain = periodic_noise(rng, h, w, 0.5)
    blotch = periodic_noise(rng, h, w, 18.0)
    lateral_m = layout.half_width_m - (np.arange(w) + 0.5) / ROAD_PX_PER_M  # left positive
    # wheel tracks are a little darker and smoother; parking strips a little lighter
    track = np.zeros(w)
    for centre in (-0.5, 0.5):
        for wheel in (-0.8, 0.8):
            track += np.exp(-0.5 * ((lateral_m - centre * layout.lane_width_m - wheel) / 0.35) ** 2)
    parking = (np.abs(lateral_m) > layout.lane_width_m + LINE_WIDTH_M).astype(float)
    base = 74.0 + 6.0 * blotch - 7.0 * track[None, :] + 5.0 * parking[None, :] + 11.0 * grain * (1 - 0.4 * track)
    rgb = np.stack([base, base + 1.0, base + 4.0], axis=-1)
    paint = np.zeros((h, w))
    if layout.edge_lines:
        edge = np.abs(np.abs(lateral_m) - layout.lane_width_m) < LINE_WIDTH_M / 2
        paint[:, edge] = 1.0
    centre = np.abs(lateral_m) < LINE_WIDTH_M / 2
    along_m = (np.arange(h) + 0.5) / ROAD_PX_PER_M
    dash = along_m < DASH_LENGTH_M
    paint[np.ix_(dash, centre)] = 1.0
    paint = cv2.GaussianBlur(paint, (0, 0), 0.6)
    wear = np.clip(0.85 + 0.25 * periodic_noise(rng, h, w, 3.0), 0.0, 1.0)
    paint *= wear
    white = np.array([228.0, 228.0, 222.0])
    rgb = rgb * (1 - paint[..., None]) + white * paint[..., None]
    return _to_uint8(rgb)


def paving_texture(rng: np.random.Generator, width_m: float, length_m: float) -> np.ndarray:
    """Sidewalk paving: light grey square slabs (30 cm) with dark joints and stains."""
    h = int(round(length_m * SIDEWALK_PX_PER_M))
    w = int(round(width_m * SIDEWALK_PX_PER_M))
    slab_m = 0.3
    yy, xx = np.mgrid[0:h, 0:w] / SIDEWALK_PX_PER_M
    joint = (np.minimum(yy % slab_m, slab_m - yy % slab_m) < 0.012) | (
        np.minimum(xx % slab_m, slab_m - xx % slab_m) < 0.012
    )
    slab_id = (np.floor(yy / slab_m) * 131 + np.floor(xx / slab_m) * 17).astype(int)
    slab_tone = rng.normal(0.0, 5.0, slab_id.max() + 1)[slab_id]
    base = 158.0 + slab_tone + 8.0 * periodic_noise(rng, h, w, 1.0) + 7.0 * periodic_noise(rng, h, w, 25.0)
    base = np.where(joint, base - 45.0, base)
    rgb = np.stack([base + 2.0, base, base - 4.0], axis=-1)
    return _to_uint8(rgb)


def grass_texture(rng: np.random.Generator, size_m: float) -> np.ndarray:
    """A tile of lawn: green blades (fine noise) with patches of dry grass and soil."""
    n = int(round(size_m * GRASS_PX_PER_M))
    fine = periodic_noise(rng, n, n, 0.6)
    mid = periodic_noise(rng, n, n, 6.0)
    patch = periodic_noise(rng, n, n, 30.0)
    dry = np.clip(0.5 + 0.6 * patch, 0.0, 1.0)[..., None]
    green = np.array([72.0, 112.0, 48.0])
    straw = np.array([130.0, 128.0, 78.0])
    rgb = green * (1 - dry) + straw * dry
    rgb = rgb * (1.0 + 0.18 * fine[..., None] + 0.10 * mid[..., None])
    return _to_uint8(rgb)


FACADE_COLOURS = np.array(
    [
        [214, 202, 178],  # sandstone
        [232, 228, 218],  # white render
        [170, 92, 70],  # brick
        [150, 150, 148],  # concrete
        [226, 196, 140],  # ochre
        [176, 190, 200],  # pale blue
        [200, 170, 150],  # pink-beige
        [120, 110, 100],  # dark stone
    ],
    dtype=float,
)


def facade_texture(rng: np.random.Generator, width_m: float, height_m: float) -> np.ndarray:
    """A building facade `width_m` x `height_m`: rendered wall with rows of windows (one per floor), a ground floor
    with shop windows or a door, and a darker plinth."""
    w = max(8, int(round(width_m * FACADE_PX_PER_M)))
    h = max(8, int(round(height_m * FACADE_PX_PER_M)))
    colour = FACADE_COLOURS[rng.integers(len(FACADE_COLOURS))] * rng.uniform(0.9, 1.05)
    wall = colour[None, None, :] * (1.0 + 0.025 * periodic_noise(rng, h, w, 1.5)[..., None])
    rgb = wall.copy()
    floor_m = rng.uniform(2.9, 3.5)
    bay_m = rng.uniform(2.4, 3.8)
    win_w_m = bay_m * rng.uniform(0.38, 0.6)
    win_h_m = floor_m * rng.uniform(0.42, 0.6)
    glass = np.array([62.0, 74.0, 88.0]) * rng.uniform(0.8, 1.2)
    frame = np.array([235.0, 235.0, 230.0]) if rng.random() < 0.6 else colour * 0.6
    n_bays = max(1, int(width_m // bay_m))
    margin_m = (width_m - n_bays * bay_m) / 2
    n_floors = max(1, int(height_m // floor_m))
    shop = rng.random() < 0.5
    for floor in range(n_floors):
        bottom_m = floor * floor_m
        for bay in range(n_bays):
            x0_m = margin_m + bay * bay_m + (bay_m - win_w_m) / 2
            ww_m, wh_m, sill_m = win_w_m, win_h_m, floor_m * 0.3
            if floor == 0 and shop:
                x0_m, ww_m, wh_m, sill_m = margin_m + bay * bay_m + 0.2, bay_m - 0.4, floor_m * 0.7, 0.3
            top_m = bottom_m + sill_m + wh_m
            r0 = int(round((height_m - top_m) * FACADE_PX_PER_M))
            r1 = int(round((height_m - bottom_m - sill_m) * FACADE_PX_PER_M))
            c0 = int(round(x0_m * FACADE_PX_PER_M))
            c1 = int(round((x0_m + ww_m) * FACADE_PX_PER_M))
            if r1 - r0 < 3 or c1 - c0 < 3 or r0 < 0:
                continue
            rgb[r0:r1, c0:c1] = frame
            pane = glass * rng.uniform(0.75, 1.3)
            # sky reflected in the upper part of the pane
            grad = np.linspace(1.35, 0.9, r1 - r0 - 2)[:, None, None]
            rgb[r0 + 1 : r1 - 1, c0 + 1 : c1 - 1] = pane * grad
    plinth = int(round(0.4 * FACADE_PX_PER_M))
    rgb[h - plinth :] = rgb[h - plinth :] * 0.7
    # a soft darkening towards the bottom (dirt, ambient occlusion)
    rgb *= np.linspace(1.0, 0.88, h)[:, None, None]
    return _to_uint8(rgb)


def facade_size_px(width_m: float, height_m: float) -> tuple[int, int]:
    """(height, width) in pixels of `facade_texture(rng, width_m, height_m)`."""
    return max(8, int(round(height_m * FACADE_PX_PER_M))), max(8, int(round(width_m * FACADE_PX_PER_M)))


def atlas_layout(
    sizes: list[tuple[int, int]], atlas_width_px: int = 1024
) -> tuple[list[tuple[int, int]], int, list[tuple[float, ...]]]:
    """Where images of (height, width) `sizes` go in an atlas (shelf packing): each one's (x, y) corner in pixels,
    the atlas height, and each one's uv rectangle (u0, v0, u1, v1) in [0, 1] with half-pixel insets so that sampling
    never bleeds into a neighbour."""
    order = sorted(range(len(sizes)), key=lambda i: -sizes[i][0])
    places: dict[int, tuple[int, int]] = {}
    x = y = shelf_h = 0
    for i in order:
        h, w = sizes[i]
        if w > atlas_width_px:
            raise ValueError(f"image {w} px wide does not fit an atlas {atlas_width_px} px wide")
        if x + w > atlas_width_px:
            x, y, shelf_h = 0, y + shelf_h, 0
        places[i] = (x, y)
        x += w
        shelf_h = max(shelf_h, h)
    atlas_h = y + shelf_h
    corners = [places[i] for i in range(len(sizes))]
    rects = [
        ((px + 0.5) / atlas_width_px, (py + 0.5) / atlas_h, (px + w - 0.5) / atlas_width_px, (py + h - 0.5) / atlas_h)
        for (px, py), (h, w) in zip(corners, sizes, strict=True)
    ]
    return corners, atlas_h, rects


def pack_atlas(images: list[np.ndarray], atlas_width_px: int = 1024) -> tuple[np.ndarray, list[tuple[float, ...]]]:
    """Pack images into one atlas (shelf packing); returns the atlas and, per image, its uv rectangle
    (u0, v0, u1, v1) in [0, 1] with half-pixel insets so that sampling never bleeds into a neighbour."""
    corners, atlas_h, rects = atlas_layout([img.shape[:2] for img in images], atlas_width_px)
    atlas = np.zeros((atlas_h, atlas_width_px, 3), np.uint8)
    for (px, py), img in zip(corners, images, strict=True):
        h, w = img.shape[:2]
        atlas[py : py + h, px : px + w] = img
    return atlas, rects
