"""Lighting and the Blinn–Phong / PBR-lite shading model used by the rasterizer (paper §III-A, DESIGN §4 step 4).

All vectors are in the camera optical frame (x right, y down, z forward); colours are linear RGB in [0, 1].

Per pixel, with base = diffuse_rgb x vertex_rgb x texture, n the unit normal turned towards the viewer (two-sided),
l = -light_dir_cam (towards the light), v towards the viewer and h = normalize(l + v):

    exponent = 1 + shininess * (1 - roughness)^2        # rough surfaces spread (and dim) the highlight
    f0       = (1 - metalness) * specular_rgb + metalness * base
    rgb      = ambient_rgb * base + light_rgb * ((1 - metalness) * base * max(n.l, 0) + f0 * max(n.h, 0)^exponent)

with the specular term only where n.l > 0, clamped to [0, 1]. Unlit materials give `base` as is.
The GLSL reference renderer in tests/gl_reference.py implements the same formula.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch


@dataclass
class Lighting:
    """Ambient plus one directional light.

    :param ambient_rgb: (3,) ambient light colour, linear [0, 1] (DESIGN: the scene's mean colour).
    :param light_dir_cam: (3,) unit vector the light travels along, in the camera optical frame. The default
        (0, 0, 1) is a directional light from the ego viewpoint at infinity.
    :param light_rgb: (3,) directional light colour, linear [0, 1].
    """

    ambient_rgb: np.ndarray = field(default_factory=lambda: np.array([0.35, 0.35, 0.35]))
    light_dir_cam: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    light_rgb: np.ndarray = field(default_factory=lambda: np.array([0.7, 0.7, 0.7]))


def specular_exponent(shininess: torch.Tensor, roughness: torch.Tensor) -> torch.Tensor:
    """Blinn–Phong exponent after roughness damping: 1 + shininess * (1 - roughness)^2."""
    return 1.0 + shininess * (1.0 - roughness) ** 2


def dot3(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Column-wise dot product of channel-major (3, P) vectors (either may be (3, 1)), shape (P,).

    Written out per component: torch's reductions over a length-3 axis cost far more than three fused multiply-adds.
    """
    return torch.addcmul(torch.addcmul(a[0] * b[0], a[1], b[1]), a[2], b[2])


def normalize3(a: torch.Tensor) -> torch.Tensor:
    """Unit-length columns of a channel-major (3, P) tensor (zero columns stay zero)."""
    return a * torch.rsqrt(dot3(a, a).clamp_min(1e-30))


def shade_blinn_phong(
    base_rgb: torch.Tensor,
    normal_cam: torch.Tensor,
    to_viewer_cam: torch.Tensor,
    specular_rgb: torch.Tensor,
    shininess: torch.Tensor,
    metalness: torch.Tensor,
    roughness: torch.Tensor,
    unlit: torch.Tensor,
    ambient_rgb: torch.Tensor,
    light_dir_cam: torch.Tensor,
    light_rgb: torch.Tensor,
) -> torch.Tensor:
    """Shaded colour of P surface points, channel-major (3, P) (module docstring has the formula).

    :param base_rgb: (3, P) albedo. :param normal_cam: (3, P) unit normals, already facing the viewer.
    :param to_viewer_cam: (3, P) unit vectors from the point towards the camera.
    :param specular_rgb: (3, P). :param shininess, metalness, roughness: (P,). :param unlit: (P,) 1 = unlit, 0 = lit.
    :param ambient_rgb, light_dir_cam, light_rgb: (3, 1) for one camera, or (3, P) per pixel.
    """
    to_light = -light_dir_cam
    half = normalize3(to_viewer_cam + to_light)
    n_dot_l = dot3(normal_cam, to_light).clamp_min_(0.0)
    n_dot_h = dot3(normal_cam, half).clamp_min_(0.0)
    diffuse_weight = 1.0 - metalness
    f0 = torch.addcmul(diffuse_weight * specular_rgb, metalness, base_rgb)
    highlight = n_dot_h.pow_(specular_exponent(shininess, roughness)).mul_(n_dot_l > 0)
    light = torch.addcmul(f0 * highlight, diffuse_weight * base_rgb, n_dot_l)
    lit = torch.addcmul(ambient_rgb * base_rgb, light_rgb, light)
    return torch.lerp(lit, base_rgb, unlit).clamp_(0.0, 1.0)


SHADOW_FADE_M = 0.5
"""How far outside a car's footprint its contact shadow fades out (m)."""
_SHADOW_DEPTH_TOLERANCE_M = 0.5  # a recorded surface nearer than the shadowed ground by more than this is not shadowed


def contact_shadow_(
    rgb: np.ndarray,
    depth_m: np.ndarray,
    K: np.ndarray,
    T_camera_car: np.ndarray,
    length_m: float,
    width_m: float,
    strength: float,
) -> None:
    """Darken, in place, the ground of a uint8 view (h, w, 3) under a car: a soft contact shadow (ambient occlusion
    of the ground by the car's body), `strength` of the colour removed under the footprint, fading smoothly to none
    `SHADOW_FADE_M` outside it.

    The ground is the car's own ground plane (z = 0 of the car's frame, x forward, y left, origin at the centre of the
    footprint). Each pixel of the footprint's projected box is intersected with that plane; pixels whose warped depth
    `depth_m` (h, w) is nearer than the plane by more than half a metre (something in front of the shadow) are left
    alone. Nothing is drawn when a corner of the widened footprint is behind the camera.
    """
    from drivesim.sim import raster_kernel  # numba compiles (or loads its cache) on first import

    raster_kernel.contact_shadow_uint8(
        rgb, depth_m, np.asarray(K, dtype=np.float64), np.asarray(T_camera_car, dtype=np.float64), float(length_m),
        float(width_m), float(strength), SHADOW_FADE_M, _SHADOW_DEPTH_TOLERANCE_M,
    )  # fmt: skip


def contact_shadows_batched(
    rgb: torch.Tensor,
    depth_m: torch.Tensor,
    K: np.ndarray,
    view_index: torch.Tensor,
    T_camera_car: torch.Tensor,
    size_m: torch.Tensor,
    strength: float,
) -> torch.Tensor:
    """`contact_shadow_` for S cars in B uint8 views (B, h, w, 3) at once on their device (the GPU path): car s, with
    pose T_camera_car[s] (S, 4, 4) and (length, width) size_m[s] (S, 2), darkens view view_index[s] (S,). Returns
    the shadowed views; the same arithmetic as `contact_shadow_`, over every pixel instead of the footprint's box, and
    rounded once per view instead of once per car."""
    B, h, w = depth_m.shape
    dev = depth_m.device
    R, t = T_camera_car[:, :3, :3].to(torch.float32), T_camera_car[:, :3, 3].to(torch.float32)
    half = size_m.to(torch.float32) * 0.5
    signs = torch.tensor([[sx, sy] for sx in (-1.0, 1.0) for sy in (-1.0, 1.0)], device=dev)
    corners_z = (signs[None] * (half[:, None] + SHADOW_FADE_M)) @ R[:, 2, :2].unsqueeze(-1)  # (S, 4, 1)
    in_front = (corners_z[..., 0] + t[:, None, 2] > 0.1).all(dim=1)  # as contact_shadow_: all corners ahead
    v, u = torch.meshgrid(torch.arange(h, device=dev), torch.arange(w, device=dev), indexing="ij")
    K_t = torch.as_tensor(np.asarray(K, dtype=np.float64), device=dev).to(torch.float32)
    rays = torch.stack([(u - K_t[0, 2]) / K_t[0, 0], (v - K_t[1, 2]) / K_t[1, 1], torch.ones((h, w), device=dev)], -1)
    normal = R[:, :, 2]  # the car's up axis in the camera frame
    denominator = torch.einsum("hwc,sc->shw", rays, normal)
    safe = torch.where(denominator.abs() > 1e-9, denominator, torch.ones_like(denominator))
    z = torch.where(denominator.abs() > 1e-9, (normal * t).sum(-1)[:, None, None] / safe, -torch.ones_like(safe))
    # The ground point in the car's frame, axis by axis: (ray z - t) . R[:, k].
    local = [
        z * torch.einsum("hwc,sc->shw", rays, R[:, :, k]) - (t * R[:, :, k]).sum(-1)[:, None, None] for k in (0, 1)
    ]
    outside = torch.hypot((local[0].abs() - half[:, 0, None, None]).clamp(min=0.0),
                          (local[1].abs() - half[:, 1, None, None]).clamp(min=0.0))  # fmt: skip
    fade = (1.0 - outside / SHADOW_FADE_M).clamp(0.0, 1.0)
    weight = strength * fade * fade * (3.0 - 2.0 * fade)
    occluded = depth_m.index_select(0, view_index) < z - _SHADOW_DEPTH_TOLERANCE_M
    weight = torch.where((z <= 0) | occluded | ~in_front[:, None, None], torch.zeros_like(weight), weight)
    # The product of (1 - weight) over a view's cars, as a sum of logs (1 - weight >= 1 - strength > 0 or exactly 1).
    factor = torch.zeros((B, h, w), device=dev).index_add_(0, view_index, torch.log1p(-weight)).exp_()
    return (rgb.to(torch.float32) * factor[..., None] + 0.5).to(torch.uint8)
