"""The rasterizer's CPU kernels (numba), for `raster.Rasterizer` on CPU: the per-triangle set-up, the depth test of
every (triangle, pixel) of the triangles' bounding boxes, and the per-pixel shading, each one compiled loop.

Why kernels of our own: the torch path expands triangles into (triangle, pixel) pairs and 8 x 8 tiles, scatters
packed keys and shades through channel-major gathers, a chain of whole-array operations whose fixed costs dominate
for the few hundred small triangles of a car in the policy's region of interest. The loops evaluate the same
formulas in the same float32 arithmetic (w_i = c_i + a_i x + b_i y from the bbox corner, inside when all w_i >= 0,
depth = |det| / sum w, at or beyond the near plane), keep per pixel the nearest depth, then the smallest candidate,
as the torch path's packed key does, and shade with `shading.py`'s formula.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

OCCLUDER_MIN_GAP = 0.12
"""How much nearer than an inserted car (fraction of the car's depth) the warped world must be to cover it. The world's
depth near a car is mostly the road it stands on, whose estimated depth (pooled to the view's pixels) comes out up to
about a tenth nearer than the car's lowest rows: without this gap that road is drawn through the car's body."""

_CAR_VISIBLE_FRACTION = np.float32(1.0 - OCCLUDER_MIN_GAP)


@njit(cache=True, nogil=True, inline="always")
def car_in_front(car_depth_m: float, world_depth_m: float) -> bool:
    """Whether an inserted car at car_depth_m (finite) shows over the world at world_depth_m: unless the world is
    nearer by more than OCCLUDER_MIN_GAP of the car's depth (+inf, sky or a hole, never covers it)."""
    return car_depth_m * _CAR_VISIBLE_FRACTION <= world_depth_m


@njit(cache=True, nogil=True)
def depth_test(
    table: np.ndarray,
    bbox: np.ndarray,
    camera: np.ndarray,
    width_px: int,
    height_px: int,
    near_m: float,
    depth: np.ndarray,
    winner: np.ndarray,
) -> None:
    """Fill the z-buffer (depth (B*H*W,) float32, +inf initially; winner (B*H*W,) int64, -1 initially) with every
    triangle's covered pixels.

    table (13, n) float32: bbox width, then (a, b, c) of the three edge functions at the bbox corner, |det|, the
    corner x, y; bbox (n, 4) int64 inclusive x0, y0, x1, y1; camera (n,) int64 the camera of each candidate.
    """
    cameras = 0
    for i in range(camera.shape[0]):
        cameras = max(cameras, camera[i] + 1)
    layout = np.zeros((cameras, 4), np.int64)  # each camera's whole image: offset b * H * W, corner (0, 0), row W
    for b in range(cameras):
        layout[b, 0], layout[b, 3] = b * height_px * width_px, width_px
    depth_test_regions(table, bbox, camera, layout, near_m, depth, winner)


@njit(cache=True, nogil=True)
def depth_test_regions(
    table: np.ndarray,
    bbox: np.ndarray,
    camera: np.ndarray,
    layout: np.ndarray,
    near_m: float,
    depth: np.ndarray,
    winner: np.ndarray,
    only_camera: int = -1,
    first_row: int = 0,
    end_row: int = 1 << 62,
) -> None:
    """`depth_test` into z-buffers that hold only a region of each camera's image: camera b's pixel (x, y) is entry
    layout[b, 0] + (y - layout[b, 2]) * layout[b, 3] + (x - layout[b, 1]) (offset, region corner x, y, row width);
    every candidate's bbox must lie inside its camera's region. With `only_camera` >= 0, only that camera's
    candidates, and only rows first_row .. end_row - 1: bands of rows tested apart fill the z-buffer exactly as one
    pass does (the nearer depth wins, of equal ones the lower candidate: the order does not matter)."""
    near = np.float32(near_m)
    for t in range(table.shape[1]):
        cam = camera[t]
        if only_camera >= 0 and cam != only_camera:
            continue
        a0, b0, c0 = table[1, t], table[2, t], table[3, t]
        a1, b1, c1 = table[4, t], table[5, t], table[6, t]
        a2, b2, c2 = table[7, t], table[8, t], table[9, t]
        abs_det = table[10, t]
        x0, y0, x1, y1 = bbox[t, 0], bbox[t, 1], bbox[t, 2], bbox[t, 3]
        row_px = layout[cam, 3]
        base = layout[cam, 0] - layout[cam, 2] * row_px - layout[cam, 1]
        for y in range(max(y0, first_row), min(y1 + 1, end_row)):
            yo = np.float32(y - y0)
            for x in range(x0, x1 + 1):
                xo = np.float32(x - x0)
                w0 = c0 + a0 * xo + b0 * yo
                w1 = c1 + a1 * xo + b1 * yo
                w2 = c2 + a2 * xo + b2 * yo
                if w0 < 0 or w1 < 0 or w2 < 0:
                    continue
                ssum = w0 + w1 + w2
                if not (ssum > 0 and ssum * near <= abs_det):
                    continue
                z = abs_det / ssum
                p = base + y * row_px + x
                if z < depth[p] or (z == depth[p] and t < winner[p]):
                    depth[p] = z
                    winner[p] = t


@njit(cache=True, nogil=True)
def setup(
    vc: np.ndarray,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    width_px: int,
    height_px: int,
    near_m: float,
    cull_back_faces: bool,
    table: np.ndarray,
    bbox: np.ndarray,
    index: np.ndarray,
) -> int:
    """`Rasterizer._setup` as one loop: from camera-frame vertices vc (9, N) float32 (row 3 * xyz + corner), fill the
    first n columns of table (13, N), rows of bbox (N, 4) and entries of index (N,) with the kept candidates; returns n.

    Same float32 formulas as the torch path: bbox of the projected corners (of the polygon clipped at z = near for a
    triangle crossing it), edge coefficients re-based at the bbox corner, degenerate and (optionally) back faces
    dropped.
    """
    f32 = np.float32
    near = f32(near_m)
    fx32, fy32, cx32, cy32 = f32(fx), f32(fy), f32(cx), f32(cy)
    limit = f32(width_px + height_px)
    n = 0
    px = np.empty(6, np.float32)
    py = np.empty(6, np.float32)
    pz = np.empty(6, np.float32)
    for t in range(vc.shape[1]):
        x0, x1, x2 = vc[0, t], vc[1, t], vc[2, t]
        y0, y1, y2 = vc[3, t], vc[4, t], vc[5, t]
        z0, z1, z2 = vc[6, t], vc[7, t], vc[8, t]
        n_front = int(z0 >= near) + int(z1 >= near) + int(z2 >= near)
        if n_front == 0:
            continue
        count = _bbox_points(vc, t, n_front, near, px, py, pz)
        u_lo = v_lo = np.inf
        u_hi = v_hi = -np.inf
        for i in range(count):
            z = max(pz[i], near)
            u = px[i] / z * fx32 + cx32
            v = py[i] / z * fy32 + cy32
            u_lo, u_hi = min(u_lo, u), max(u_hi, u)
            v_lo, v_hi = min(v_lo, v), max(v_hi, v)
        lo_x = max(np.ceil(min(max(f32(u_lo), f32(-1.0)), limit)), f32(0.0))
        lo_y = max(np.ceil(min(max(f32(v_lo), f32(-1.0)), limit)), f32(0.0))
        hi_x = min(np.floor(min(max(f32(u_hi), f32(-1.0)), limit)), f32(width_px - 1))
        hi_y = min(np.floor(min(max(f32(v_hi), f32(-1.0)), limit)), f32(height_px - 1))
        if hi_x < lo_x or hi_y < lo_y:
            continue
        cx0, cy0, cz0 = y1 * z2 - z1 * y2, z1 * x2 - x1 * z2, x1 * y2 - y1 * x2  # P1 x P2
        cx1, cy1, cz1 = y2 * z0 - z2 * y0, z2 * x0 - x2 * z0, x2 * y0 - y2 * x0  # P2 x P0
        cx2, cy2, cz2 = y0 * z1 - z0 * y1, z0 * x1 - x0 * z1, x0 * y1 - y0 * x1  # P0 x P1
        det = x0 * cx0 + y0 * cy0 + z0 * cz0
        abs_det = abs(det)
        scale = (abs(x0) + abs(y0) + abs(z0) + abs(x1) + abs(y1) + abs(z1) + abs(x2) + abs(y2) + abs(z2)) / f32(3.0)
        if not abs_det > f32(1e-9) * scale * scale * scale:  # seen edge-on or degenerate: covers nothing
            continue
        if cull_back_faces and not det < 0:  # det < 0: the front (counter-clockwise) side faces the camera
            continue
        sign = f32(1.0) if det > 0 else f32(-1.0)
        table[0, n] = hi_x - lo_x + 1
        edges = ((cx0, cy0, cz0), (cx1, cy1, cz1), (cx2, cy2, cz2))
        for i in range(3):
            ex, ey, ez = edges[i]
            a = ex * (sign / fx32)
            b = ey * (sign / fy32)
            table[1 + 3 * i, n] = a
            table[2 + 3 * i, n] = b
            table[3 + 3 * i, n] = ez * sign + a * (lo_x - cx32) + b * (lo_y - cy32)
        table[10, n] = abs_det
        table[11, n] = lo_x
        table[12, n] = lo_y
        bbox[n, 0], bbox[n, 1], bbox[n, 2], bbox[n, 3] = int(lo_x), int(lo_y), int(hi_x), int(hi_y)
        index[n] = t
        n += 1
    return n


@njit(cache=True, nogil=True, inline="always")
def _bbox_points(
    vc: np.ndarray, t: int, n_front: int, near: float, px: np.ndarray, py: np.ndarray, pz: np.ndarray
) -> int:
    """Fill px, py, pz with the points triangle t's bbox is made of; returns their count: its corners, or for a
    triangle crossing the near plane the corners in front of it and the edges' crossings of it."""
    f32 = np.float32
    x0, x1, x2 = vc[0, t], vc[1, t], vc[2, t]
    y0, y1, y2 = vc[3, t], vc[4, t], vc[5, t]
    z0, z1, z2 = vc[6, t], vc[7, t], vc[8, t]
    px[0], px[1], px[2] = x0, x1, x2
    py[0], py[1], py[2] = y0, y1, y2
    pz[0], pz[1], pz[2] = z0, z1, z2
    if n_front == 3:
        return 3
    count = 0
    for i in range(3):
        if pz[i] >= near:
            px[count], py[count], pz[count] = px[i], py[i], pz[i]
            count += 1
    xs = (x0, x1, x2)
    ys = (y0, y1, y2)
    zs = (z0, z1, z2)
    for i in range(3):
        j = (i + 1) % 3
        zi, zj = zs[i], zs[j]
        if (zi - near) * (zj - near) < 0:
            s = min(max((near - zi) / (zj - zi), f32(0.0)), f32(1.0))
            px[count] = xs[i] + s * (xs[j] - xs[i])
            py[count] = ys[i] + s * (ys[j] - ys[i])
            pz[count] = zi + s * (zj - zi)
            count += 1
    return count


@njit(cache=True, nogil=True)
def normalized(x: float, y: float, z: float) -> tuple[float, float, float]:
    """(x, y, z) scaled to unit length (float32 arithmetic; a zero vector stays near zero)."""
    inv = np.float32(1.0) / np.sqrt(max(x * x + y * y + z * z, np.float32(1e-30)))
    return x * inv, y * inv, z * inv


@njit(cache=True, nogil=True)
def shade(
    depth: np.ndarray,
    winner: np.ndarray,
    table: np.ndarray,
    source: np.ndarray,
    attributes: np.ndarray,
    material: np.ndarray,
    object_ids: np.ndarray,
    R_cam_world: np.ndarray,
    K_inv: np.ndarray,
    lights: np.ndarray,
    background_rgb: np.ndarray,
    width_px: int,
    height_px: int,
    rgb_out: np.ndarray,
    depth_out: np.ndarray,
    id_out: np.ndarray,
    normal_out: np.ndarray,
    regions: np.ndarray,
) -> None:
    """`Rasterizer._resolve` for untextured scenes as one loop: per covered pixel of the z-buffer (depth, winner), the
    winner's perspective-correct barycentrics, its interpolated normal and colour, and the shading of `shading.py`.

    source (n,) the scene triangle of each candidate; attributes (24, T), material (7, T), object_ids (T,) the packed
    scene's tables; R_cam_world (B, 3, 3); K_inv (3, 3); lights (B, 9) ambient, unit direction, light colour.
    Every pixel of the outputs (B*H*W, ...) is written: where nothing is drawn, background_rgb (3,), depth +inf,
    id -1 and a zero normal. Only the pixels of camera b's `regions[b]` (x0, y0, x1, y1 inclusive: the kept
    triangles' bounding boxes) can be drawn: the rest is written as background in plain loops, without the per-pixel
    branch (a car covers a few percent of a view).
    """
    plane = width_px * height_px
    for p in range(winner.shape[0]):
        depth_out[p] = np.inf
        id_out[p] = -1
    for p in range(winner.shape[0]):
        for c in range(3):
            rgb_out[p, c] = background_rgb[c]
            normal_out[p, c] = 0.0
    for cam in range(regions.shape[0]):
        for y in range(regions[cam, 1], regions[cam, 3] + 1):
            for x in range(regions[cam, 0], regions[cam, 2] + 1):
                p = cam * plane + y * width_px + x
                t = winner[p]
                if t >= 0:
                    r, g, b, n0, n1, n2 = _shade_pixel(
                        x, y, cam, t, table, source, attributes, material, R_cam_world, K_inv, lights
                    )
                    rgb_out[p, 0], rgb_out[p, 1], rgb_out[p, 2] = r, g, b
                    normal_out[p, 0], normal_out[p, 1], normal_out[p, 2] = n0, n1, n2
                    depth_out[p] = depth[p]
                    id_out[p] = object_ids[source[t]]


@njit(cache=True, nogil=True, inline="always")
def pixel_barycentrics(table: np.ndarray, t: int, x: int, y: int) -> tuple[float, float, float]:
    """Perspective-correct barycentric weights of pixel (x, y) in set-up candidate t (`setup`'s column table)."""
    f32 = np.float32
    xo = f32(x) - table[11, t]
    yo = f32(y) - table[12, t]
    w0 = table[3, t] + table[1, t] * xo + table[2, t] * yo
    w1 = table[6, t] + table[4, t] * xo + table[5, t] * yo
    w2 = table[9, t] + table[7, t] * xo + table[8, t] * yo
    inv_sum = f32(1.0) / (w0 + w1 + w2)
    return w0 * inv_sum, w1 * inv_sum, w2 * inv_sum


@njit(cache=True, nogil=True, inline="always")
def _shade_pixel(
    x: int,
    y: int,
    cam: int,
    t: int,
    table: np.ndarray,
    source: np.ndarray,
    attributes: np.ndarray,
    material: np.ndarray,
    R_cam_world: np.ndarray,
    K_inv: np.ndarray,
    lights: np.ndarray,
) -> tuple[float, float, float, float, float, float]:
    """`shade` of one covered pixel (x, y of camera cam) whose z-buffer winner is candidate t: its colour in [0, 1]
    and its camera-frame unit normal (r, g, b, nx, ny, nz)."""
    f32 = np.float32
    b0, b1, b2 = pixel_barycentrics(table, t, x, y)
    s = source[t]
    nw0 = attributes[0, s] * b0 + attributes[8, s] * b1 + attributes[16, s] * b2
    nw1 = attributes[1, s] * b0 + attributes[9, s] * b1 + attributes[17, s] * b2
    nw2 = attributes[2, s] * b0 + attributes[10, s] * b1 + attributes[18, s] * b2
    R = R_cam_world[cam]
    n0, n1, n2 = normalized(
        R[0, 0] * nw0 + R[0, 1] * nw1 + R[0, 2] * nw2,
        R[1, 0] * nw0 + R[1, 1] * nw1 + R[1, 2] * nw2,
        R[2, 0] * nw0 + R[2, 1] * nw1 + R[2, 2] * nw2,
    )
    fx, fy = f32(x), f32(y)
    v0, v1, v2 = normalized(
        -(K_inv[0, 0] * fx + K_inv[0, 1] * fy + K_inv[0, 2]),
        -(K_inv[1, 0] * fx + K_inv[1, 1] * fy + K_inv[1, 2]),
        -(K_inv[2, 0] * fx + K_inv[2, 1] * fy + K_inv[2, 2]),
    )
    if n0 * v0 + n1 * v1 + n2 * v2 < 0:  # two-sided: the normal turned towards the viewer
        n0, n1, n2 = -n0, -n1, -n2
    l0, l1, l2 = -lights[cam, 3], -lights[cam, 4], -lights[cam, 5]
    h0, h1, h2 = normalized(v0 + l0, v1 + l1, v2 + l2)
    n_dot_l = max(n0 * l0 + n1 * l1 + n2 * l2, f32(0.0))
    n_dot_h = max(n0 * h0 + n1 * h1 + n2 * h2, f32(0.0))
    metalness, roughness, unlit = material[4, s], material[5, s], material[6, s]
    exponent = f32(1.0) + material[3, s] * (f32(1.0) - roughness) ** 2
    highlight = n_dot_h**exponent if n_dot_l > 0 else f32(0.0)
    diffuse_weight = f32(1.0) - metalness
    w, m = diffuse_weight, metalness
    r = _lit_channel(0, s, cam, b0, b1, b2, attributes, material, lights, w, m, unlit, highlight, n_dot_l)
    g = _lit_channel(1, s, cam, b0, b1, b2, attributes, material, lights, w, m, unlit, highlight, n_dot_l)
    b = _lit_channel(2, s, cam, b0, b1, b2, attributes, material, lights, w, m, unlit, highlight, n_dot_l)
    return r, g, b, n0, n1, n2


@njit(cache=True, nogil=True, inline="always")
def _lit_channel(
    c: int,
    s: int,
    cam: int,
    b0: float,
    b1: float,
    b2: float,
    attributes: np.ndarray,
    material: np.ndarray,
    lights: np.ndarray,
    diffuse_weight: float,
    metalness: float,
    unlit: float,
    highlight: float,
    n_dot_l: float,
) -> float:
    """Colour channel c in [0, 1] of a pixel of scene triangle s at barycentrics (b0, b1, b2) (`shading.py`'s
    formula)."""
    f32 = np.float32
    base = attributes[3 + c, s] * b0 + attributes[11 + c, s] * b1 + attributes[19 + c, s] * b2
    f0 = diffuse_weight * material[c, s] + metalness * base
    light = f0 * highlight + diffuse_weight * base * n_dot_l
    lit = lights[cam, c] * base + lights[cam, 6 + c] * light
    return min(max(lit + unlit * (base - lit), f32(0.0)), f32(1.0))


@njit(cache=True, nogil=True)
def render_untextured(
    vc: np.ndarray,
    intrinsics: np.ndarray,
    width_px: int,
    height_px: int,
    near_m: float,
    cull_back_faces: bool,
    owner: np.ndarray,
    triangles_per_camera: int,
    attributes: np.ndarray,
    material: np.ndarray,
    object_ids: np.ndarray,
    R_cam_world: np.ndarray,
    K_inv: np.ndarray,
    lights: np.ndarray,
    background_rgb: np.ndarray,
    rgb_out: np.ndarray,
    depth_out: np.ndarray,
    id_out: np.ndarray,
    normal_out: np.ndarray,
) -> int:
    """`setup`, `depth_test` and `shade` in one compiled call (the same formulas, the same result): for a car of a
    few hundred triangles in the policy's view the Python-side costs of three calls (argument checks, five
    intermediate arrays) were about as large as the work. Returns the number of triangles kept by the set-up.

    vc (9, N) camera-frame vertices (as `setup`); intrinsics (4,) fx, fy, cx, cy; candidate n's camera and scene
    triangle: owner[n] and n when owner has N entries (per-camera scenes), else n // triangles_per_camera and
    n % triangles_per_camera (one scene seen by every camera). The rest as `shade`.
    """
    kept, bbox, camera, source = _kept_candidates(
        vc, intrinsics, width_px, height_px, near_m, cull_back_faces, owner, triangles_per_camera
    )
    size = depth_out.shape[0]
    depth = np.full(size, np.inf, np.float32)
    winner = np.full(size, -1, np.int64)
    depth_test(kept, bbox, camera, width_px, height_px, near_m, depth, winner)
    regions = _regions(bbox, camera, R_cam_world.shape[0], width_px, height_px)
    shade(
        depth, winner, kept, source, attributes, material, object_ids, R_cam_world, K_inv, lights, background_rgb,
        width_px, height_px, rgb_out, depth_out, id_out, normal_out, regions,
    )  # fmt: skip
    return kept.shape[1]


@njit(cache=True, nogil=True)
def _kept_candidates(
    vc: np.ndarray,
    intrinsics: np.ndarray,
    width_px: int,
    height_px: int,
    near_m: float,
    cull_back_faces: bool,
    owner: np.ndarray,
    triangles_per_camera: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`setup` of the candidates vc (9, N), and the kept ones' column table (13, n), bboxes (n, 4), cameras (n,) and
    scene triangles (n,) (owner and triangles_per_camera as `render_untextured`)."""
    N = vc.shape[1]
    table = np.empty((13, N), np.float32)
    bbox = np.empty((N, 4), np.int64)
    index = np.empty(N, np.int64)
    n = setup(
        vc, intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3], width_px, height_px, near_m, cull_back_faces,
        table, bbox, index,
    )  # fmt: skip
    kept = np.empty((13, n), np.float32)
    camera = np.empty(n, np.int64)
    source = np.empty(n, np.int64)
    per_scene = owner.shape[0] == N
    for i in range(n):
        for r in range(13):
            kept[r, i] = table[r, i]
        t = index[i]
        if per_scene:
            camera[i], source[i] = owner[t], t
        else:
            camera[i] = t // triangles_per_camera
            source[i] = t - camera[i] * triangles_per_camera
    return kept, bbox[:n], camera, source


@njit(cache=True, nogil=True)
def _regions(bbox: np.ndarray, camera: np.ndarray, cameras: int, width_px: int, height_px: int) -> np.ndarray:
    """Per camera, the union of its candidates' bounding boxes (cameras, 4) inclusive x0, y0, x1, y1 (empty: x1 < x0):
    only there can a pixel be drawn."""
    regions = np.empty((cameras, 4), np.int64)
    regions[:, 0], regions[:, 1], regions[:, 2], regions[:, 3] = width_px, height_px, -1, -1
    for i in range(bbox.shape[0]):
        b = camera[i]
        regions[b, 0], regions[b, 1] = min(regions[b, 0], bbox[i, 0]), min(regions[b, 1], bbox[i, 1])
        regions[b, 2], regions[b, 3] = max(regions[b, 2], bbox[i, 2]), max(regions[b, 3], bbox[i, 3])
    return regions


@njit(cache=True, nogil=True)
def draw_untextured_into(*inputs: np.ndarray) -> int:
    """`render_untextured` then `composite_uint8` in one call, with the same pixels, for views that need only the
    composite. The inputs, in order (as `_prepare_draw`'s after `bands`): vc, intrinsics, near_m, cull_back_faces,
    owner, triangles_per_camera (as `render_untextured`), attributes, material, R_cam_world, K_inv, lights (as
    `shade`), view_of_camera (B,), rgb (V, h, w, 3) uint8, depth (V, h, w), front (V, h, w) bool and gray: camera b
    draws into view rgb[view_of_camera[b]] over its depth, and front (False initially) receives where its scene is
    nearer. The z-buffer covers only each camera's region (`_regions`) and only its nearer pixels are shaded: no
    full-image float image, depth, id or normal is written (a car covers a few percent of a view; those writes were
    most of a car's raster). Returns the number of triangles kept by the set-up."""
    rows, target, scene, kept_count = _prepare_draw(1, *inputs)
    for i in range(rows.shape[0]):
        _draw_rows(rows[i], target, scene, inputs[2])
    return kept_count


@njit(cache=True, nogil=True, parallel=True)
def draw_untextured_into_bands(bands: int, *inputs: np.ndarray) -> int:
    """`draw_untextured_into` with each region's rows cut into `bands` bands depth-tested and shaded at the same time
    in numba's threads (the same pixels: each band owns its rows of the z-buffer, each pixel is shaded on its own).
    A separate entry point, called only with more than one thread: compiling a parallel loop starts numba's threading
    layer, whose OpenMP pool shares the process with torch's and changed a training run's floats (not a pixel) where
    the view path ran on one thread."""
    rows, target, scene, kept_count = _prepare_draw(bands, *inputs)
    for i in prange(rows.shape[0]):
        _draw_rows(rows[i], target, scene, inputs[2])
    return kept_count


@njit(cache=True, nogil=True)
def _prepare_draw(
    bands: int,
    vc: np.ndarray,
    intrinsics: np.ndarray,
    near_m: float,
    cull_back_faces: bool,
    owner: np.ndarray,
    triangles_per_camera: int,
    attributes: np.ndarray,
    material: np.ndarray,
    R_cam_world: np.ndarray,
    K_inv: np.ndarray,
    lights: np.ndarray,
    view_of_camera: np.ndarray,
    rgb: np.ndarray,
    depth: np.ndarray,
    front: np.ndarray,
    gray: bool,
) -> tuple:
    """The set-up of `draw_untextured_into`: the row bands to depth-test and shade (`_row_bands`), `_draw_rows`'
    target and scene tuples (the region-sized z-buffer, still empty) and the number of triangles kept."""
    height_px, width_px = depth.shape[1], depth.shape[2]
    kept, bbox, camera, source = _kept_candidates(
        vc, intrinsics, width_px, height_px, near_m, cull_back_faces, owner, triangles_per_camera
    )
    cameras = R_cam_world.shape[0]
    regions = _regions(bbox, camera, cameras, width_px, height_px)
    layout = np.zeros((cameras, 4), np.int64)  # offset, corner x, y, row width of each camera's z-buffer region
    size = 0
    for b in range(cameras):
        layout[b, 0], layout[b, 1], layout[b, 2] = size, regions[b, 0], regions[b, 1]
        layout[b, 3] = max(regions[b, 2] - regions[b, 0] + 1, 0)
        size += layout[b, 3] * max(regions[b, 3] - regions[b, 1] + 1, 0)
    z = np.full(size, np.inf, np.float32)
    winner = np.full(size, -1, np.int64)
    rows = _row_bands(regions, max(bands, 1))
    scene = (kept, source, attributes, material, R_cam_world, K_inv, lights, bbox, camera)
    target = (regions, layout, z, winner, view_of_camera, rgb, depth, front, gray)
    return rows, target, scene, kept.shape[1]


@njit(cache=True, nogil=True)
def _draw_rows(band: np.ndarray, target: tuple, scene: tuple, near_m: float) -> None:
    """The depth test of band (camera, first row, last row + 1) of a camera's region (its own rows of the z-buffer:
    bands drawn at the same time write apart), then its shading and composite (`_shade_rows`)."""
    layout, z, winner = target[1], target[2], target[3]
    kept, bbox, camera = scene[0], scene[7], scene[8]
    depth_test_regions(kept, bbox, camera, layout, near_m, z, winner, band[0], band[1], band[2])
    _shade_rows(band, target, scene)


@njit(cache=True, nogil=True)
def _row_bands(regions: np.ndarray, bands: int) -> np.ndarray:
    """(n, 3) camera, first row, last row + 1 of each camera's region cut into up to `bands` bands of rows."""
    rows = np.empty((regions.shape[0] * bands, 3), np.int64)
    n = 0
    for cam in range(regions.shape[0]):
        y0, y1 = regions[cam, 1], regions[cam, 3] + 1
        count = min(bands, max(y1 - y0, 0))
        for k in range(count):
            rows[n, 0], rows[n, 1], rows[n, 2] = cam, y0 + (y1 - y0) * k // count, y0 + (y1 - y0) * (k + 1) // count
            n += 1
    return rows[:n]


@njit(cache=True, nogil=True)
def _shade_rows(band: np.ndarray, target: tuple, scene: tuple) -> None:
    """Shade and composite the pixels of band (camera, first row, last row + 1) whose z-buffer entry is in front of
    the view's depth (`car_in_front`). `target`: (regions, layout, z, winner, view_of_camera, rgb, depth, front,
    gray) as in `draw_untextured_into` (layout as `depth_test_regions`); `scene`: `_shade_pixel`'s tables (kept, source,
    attributes, material, R_cam_world, K_inv, lights)."""
    regions, layout, z, winner, view_of_camera, rgb, depth, front, gray = target
    kept, source, attributes, material, R_cam_world, K_inv, lights = scene[:7]
    cam = band[0]
    v = view_of_camera[cam]
    for y in range(band[1], band[2]):
        for x in range(regions[cam, 0], regions[cam, 2] + 1):
            p = layout[cam, 0] + (y - layout[cam, 2]) * layout[cam, 3] + (x - layout[cam, 1])
            t = winner[p]
            if t < 0 or not car_in_front(z[p], depth[v, y, x]):
                continue
            r, g, b, _, _, _ = _shade_pixel(
                x, y, cam, t, kept, source, attributes, material, R_cam_world, K_inv, lights
            )
            _composite_pixel(rgb[v, y, x], r, g, b, gray)
            front[v, y, x] = True


@njit(cache=True, nogil=True)
def composite_uint8(
    rgb: np.ndarray, depth: np.ndarray, car_rgb: np.ndarray, car_depth: np.ndarray, front: np.ndarray, gray: bool
) -> None:
    """`raster.composite` for one uint8 view, in place: where the drawn car (car_rgb (h, w, 3) float [0, 1],
    car_depth (h, w), +inf where none) is in front of the view's depth (h, w) (`car_in_front`), its colour replaces
    the view's (rgb (h, w, 3) uint8); front (h, w) bool receives where. With `gray` (a gray camera's world) the car's
    pixels take their luma in all three channels, with OpenCV's RGB2GRAY arithmetic to the grey level (15-bit fixed
    point; checked against cv2.cvtColor on every 8-bit colour in tests/test_raster.py)."""
    h, w = depth.shape
    for y in range(h):
        for x in range(w):
            nearer = car_depth[y, x] < np.inf and car_in_front(car_depth[y, x], depth[y, x])
            front[y, x] = nearer
            if not nearer:
                continue
            _composite_pixel(rgb[y, x], car_rgb[y, x, 0], car_rgb[y, x, 1], car_rgb[y, x, 2], gray)


@njit(cache=True, nogil=True, inline="always")
def _composite_pixel(pixel: np.ndarray, r: float, g: float, b: float, gray: bool) -> None:
    """Write the car's colour (r, g, b in [0, 1]) to the uint8 pixel (3,), rounded; its luma in all three channels
    with `gray`."""
    r8 = np.uint8(r * np.float32(255.0) + np.float32(0.5))
    g8 = np.uint8(g * np.float32(255.0) + np.float32(0.5))
    b8 = np.uint8(b * np.float32(255.0) + np.float32(0.5))
    if gray:
        r8 = g8 = b8 = luma_uint8(r8, g8, b8)
    pixel[0], pixel[1], pixel[2] = r8, g8, b8


@njit(cache=True, nogil=True, inline="always")
def luma_uint8(r: np.uint8, g: np.uint8, b: np.uint8) -> np.uint8:
    """OpenCV's RGB2GRAY of one 8-bit colour: (9798 R + 19235 G + 3735 B + 2^14) >> 15."""
    return np.uint8((np.int32(r) * 9798 + np.int32(g) * 19235 + np.int32(b) * 3735 + 16384) >> 15)


@njit(cache=True, nogil=True)
def contact_shadow_uint8(
    rgb: np.ndarray,
    depth_m: np.ndarray,
    K: np.ndarray,
    T_camera_car: np.ndarray,
    length_m: float,
    width_m: float,
    strength: float,
    fade_m: float,
    depth_tolerance_m: float,
) -> None:
    """`shading.contact_shadow_` in one compiled loop (its numpy form took about 0.08 ms per car): the same ground
    plane, box, fade and depth test, in float64."""
    R, t = T_camera_car[:3, :3], T_camera_car[:3, 3]
    half_l, half_w = 0.5 * length_m + fade_m, 0.5 * width_m + fade_m
    h, w = depth_m.shape
    u_lo, u_hi, v_lo, v_hi = np.inf, -np.inf, np.inf, -np.inf
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            p = R[:, 0] * (sx * half_l) + R[:, 1] * (sy * half_w) + t
            if p[2] <= 0.1:
                return
            u = (K[0, 0] * p[0] + K[0, 1] * p[1] + K[0, 2] * p[2]) / p[2]
            v = (K[1, 0] * p[0] + K[1, 1] * p[1] + K[1, 2] * p[2]) / p[2]
            u_lo, u_hi, v_lo, v_hi = min(u_lo, u), max(u_hi, u), min(v_lo, v), max(v_hi, v)
    x0, y0 = max(int(np.floor(u_lo)), 0), max(int(np.floor(v_lo)), 0)
    x1, y1 = min(int(np.ceil(u_hi)) + 1, w), min(int(np.ceil(v_hi)) + 1, h)
    n0, n1, n2 = R[0, 2], R[1, 2], R[2, 2]  # the car's up axis in the camera
    n_dot_t = n0 * t[0] + n1 * t[1] + n2 * t[2]
    for y in range(y0, y1):
        for x in range(x0, x1):
            rx, ry = (x - K[0, 2]) / K[0, 0], (y - K[1, 2]) / K[1, 1]
            denominator = rx * n0 + ry * n1 + n2
            z = n_dot_t / denominator if abs(denominator) > 1e-9 else -1.0
            if z <= 0 or depth_m[y, x] < z - depth_tolerance_m:
                continue
            px, py, pz = rx * z - t[0], ry * z - t[1], z - t[2]
            local_x = px * R[0, 0] + py * R[1, 0] + pz * R[2, 0]
            local_y = px * R[0, 1] + py * R[1, 1] + pz * R[2, 1]
            outside = np.hypot(max(abs(local_x) - 0.5 * length_m, 0.0), max(abs(local_y) - 0.5 * width_m, 0.0))
            fade = min(max(1.0 - outside / fade_m, 0.0), 1.0)
            weight = strength * fade * fade * (3.0 - 2.0 * fade)
            for c in range(3):
                rgb[y, x, c] = np.uint8(rgb[y, x, c] * (1.0 - weight) + 0.5)
