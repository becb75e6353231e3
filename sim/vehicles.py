"""The one parametrized vehicle builder: sedan, hatchback, SUV, van and pickup from shape parameters.

A vehicle is five material groups, one `Mesh` each, in this order (`GROUP_NAMES`): the painted body (lower hull,
roof, pillars), the windows (the glass house), the wheels (tyres and hubs), the lights and the trim (the dark
underbody that also lines the wheel arches, bumper valances and the grille). Every group is a
union of closed components with faces counter-clockwise seen from outside, so the rasterizer may cull back faces.

The body carries a per-vertex occlusion factor (`BODY_OCCLUSION_FLOOR` at the ground rising to 1 at the belt line):
the sky lights a car's upper panels while its lower sides see the road and the car's own shadow, so real cars read
dark at the bottom and bright higher up. It multiplies the paint, so it survives repainting. The windows carry a
factor rising from `GLASS_REFLECTION_FLOOR` at the belt line to 1 at the roof: the renderer has no environment map,
so the glass's albedo stands in for what it reflects (see `PART_RANGES`).

Vehicle frame: x forward, y left, z up; the origin is the centre of the footprint on the ground (z = 0).

Two levels of detail: "full" (rounded hull, pillars, hubs, valances, grille; about 2 k triangles, to look
at) and "light" (chamfered hull, no pillars, hubs or small trim, the underbody kept; a few hundred triangles, for the
policy's 160 x 64 view where a car covers a few hundred pixels).

Paint (`sample_paint`) follows the paper's five material parameters (§III-A: diffuse colour, specular colour,
specular highlight, metalness, roughness), drawn from physically plausible ranges:

- diffuse colour: a colour family drawn with the frequencies of the global car colour popularity report (Axalta
  2022: white 35 %, black 19 %, grey 18 %, silver 10 %, blue 7 %, red 6 %, beige/brown 2 %, green 2 %, yellow/
  orange 1 %), each family a linear-RGB albedo range measured for car paints (albedo 0.02–0.04 for black,
  0.6–0.85 for white; a chromatic paint keeps its dominant channel within 0.2–0.6). Albedo never exceeds 0.9:
  no real paint reflects more.
- specular colour: the clear coat is a dielectric of refractive index n = 1.5–1.65, whose normal-incidence
  reflectance F0 = ((n - 1) / (n + 1))^2 is 0.04–0.06, achromatic (Real-Time Rendering, 4th ed., Table 9.2).
- specular highlight (Blinn–Phong exponent): 64–256 (log-uniform): the tight highlight of a polished clear coat
  (automotive paints measure 85–95 gloss units at 20°).
- metalness: solid paints 0; metallic-flake paints (half of the silver/grey/blue/red/green draws, all silver)
  0.3–0.7: the flakes tint part of the reflection with the base colour, as the Disney/UE4 "metallic" blend does
  for a flake-filled base coat (Burley 2012, "Physically-Based Shading at Disney").
- roughness: 0.05–0.3, a clear coat (Burley 2012 uses clearcoat gloss near 1, i.e. low roughness); weathered
  cars at the top of the range.

The other parts' materials are drawn per car too (`sample_part_materials`, `PART_RANGES`), the same five
parameters: glass (a smooth dielectric whose specular colour is raised to 0.15–0.3 for the glancing views of a
windscreen; its albedo 0.12–0.25 is not the tinted glass's own 0.02–0.08 but what a window seen from a car's height
shows: Schlick's Fresnel reflectance of glass is 0.06–0.2 at the 55–70 degree incidence of a raked windscreen or rear
window, times a sky brighter than the frame's mean, which the scene's ambient light stands for), tyre rubber (rough,
dull), black trim plastic (albedo 0.04–0.09, semi-matte), light lenses (smooth polycarbonate) and the wheel's hub
(painted steel or alloy).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from drivesim.sim.mesh import Material, Mesh

BODY_TYPES: tuple[str, ...] = ("sedan", "hatchback", "suv", "van", "pickup")
GROUP_NAMES: tuple[str, ...] = ("body", "windows", "wheels", "lights", "trim")
DETAILS: tuple[str, ...] = ("full", "light")

ROOF_THICKNESS_M = 0.05
LENS_PROUD_M = 0.012
TRIM_PROUD_M = 0.008  # valances and grille stand this far out of the hull's ends
BODY_OCCLUSION_FLOOR = 0.3
"""The body's per-vertex light factor at the ground (1 at the belt line and above; linear in between)."""
GLASS_REFLECTION_FLOOR = 0.3
"""The windows' per-vertex factor at the belt line (1 at the roof; linear in between): what a window shows is mostly
the sky it reflects at its top and the darker street and cabin lower down."""


@dataclass(frozen=True)
class VehicleShape:
    """Shape parameters of one vehicle (metres; fractions of the length).

    :param body_type: one of `BODY_TYPES`.
    :param length_m: bumper to bumper. :param width_m: body width without mirrors. :param height_m: ground to roof.
    :param hood_fraction: front bumper to the base of the windscreen, fraction of the length.
    :param cabin_fraction: base of the windscreen to the base of the rear window (or the tailgate), fraction.
    :param trunk_fraction: rear of the cabin to the rear bumper (trunk, hatch overhang or pickup bed), fraction;
        the three fractions sum to 1.
    :param wheel_radius_m: tyre radius.
    :param wheelbase_fraction: axle to axle, fraction of the length.
    :param belt_fraction: height of the belt line (bottom of the side windows), fraction of the height.
    :param windscreen_rake: horizontal run of the windscreen per metre of rise.
    :param rear_rake: horizontal run of the rear window per metre of rise (0 = vertical tailgate).
    """

    body_type: str
    length_m: float
    width_m: float
    height_m: float
    hood_fraction: float
    cabin_fraction: float
    trunk_fraction: float
    wheel_radius_m: float
    wheelbase_fraction: float = 0.6
    belt_fraction: float = 0.62
    windscreen_rake: float = 1.4
    rear_rake: float = 1.0

    def __post_init__(self) -> None:
        if self.body_type not in BODY_TYPES:
            raise ValueError(f"body_type {self.body_type!r} is not one of {', '.join(BODY_TYPES)}")
        if not (self.length_m > 0 and self.width_m > 0 and self.height_m > 0 and self.wheel_radius_m > 0):
            raise ValueError("vehicle length, width, height and wheel radius must be positive")
        fractions = (self.hood_fraction, self.cabin_fraction, self.trunk_fraction)
        if min(fractions) < 0 or abs(sum(fractions) - 1.0) > 1e-6:
            raise ValueError(f"hood + cabin + trunk fractions must be >= 0 and sum to 1, got {fractions}")


# Per body type: (mean, half-range) of length, width, height (m), hood, cabin, trunk fractions, wheel radius (m),
# wheelbase fraction, belt fraction, windscreen rake, rear rake. Dimensions span typical current models of each
# class (e.g. sedan: Toyota Camry / VW Passat / BMW 3; hatchback: VW Golf / Toyota Yaris; SUV: Toyota RAV4 /
# VW Tiguan; van: Ford Transit Custom / VW Transporter; pickup: Ford F-150 / Toyota Hilux).
_SHAPE_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "sedan": dict(
        length_m=(4.75, 0.3),
        width_m=(1.82, 0.06),
        height_m=(1.45, 0.05),
        hood=(0.27, 0.03),
        cabin=(0.47, 0.03),
        trunk=(0.26, 0.03),
        wheel_radius_m=(0.325, 0.02),
        wheelbase=(0.59, 0.02),
        belt=(0.62, 0.03),
        windscreen_rake=(1.5, 0.2),
        rear_rake=(1.4, 0.3),
    ),
    "hatchback": dict(
        length_m=(4.1, 0.3),
        width_m=(1.77, 0.06),
        height_m=(1.48, 0.05),
        hood=(0.25, 0.03),
        cabin=(0.64, 0.03),
        trunk=(0.11, 0.03),
        wheel_radius_m=(0.31, 0.02),
        wheelbase=(0.63, 0.02),
        belt=(0.6, 0.03),
        windscreen_rake=(1.4, 0.2),
        rear_rake=(0.45, 0.15),
    ),
    "suv": dict(
        length_m=(4.6, 0.3),
        width_m=(1.88, 0.06),
        height_m=(1.70, 0.07),
        hood=(0.25, 0.03),
        cabin=(0.66, 0.03),
        trunk=(0.09, 0.03),
        wheel_radius_m=(0.36, 0.02),
        wheelbase=(0.6, 0.02),
        belt=(0.6, 0.03),
        windscreen_rake=(1.0, 0.15),
        rear_rake=(0.3, 0.1),
    ),
    "van": dict(
        length_m=(5.0, 0.3),
        width_m=(1.97, 0.05),
        height_m=(1.97, 0.1),
        hood=(0.15, 0.02),
        cabin=(0.82, 0.02),
        trunk=(0.03, 0.01),
        wheel_radius_m=(0.34, 0.02),
        wheelbase=(0.6, 0.02),
        belt=(0.52, 0.03),
        windscreen_rake=(0.9, 0.1),
        rear_rake=(0.06, 0.04),
    ),
    "pickup": dict(
        length_m=(5.4, 0.35),
        width_m=(1.95, 0.07),
        height_m=(1.82, 0.08),
        hood=(0.28, 0.02),
        cabin=(0.30, 0.03),
        trunk=(0.42, 0.03),
        wheel_radius_m=(0.39, 0.02),
        wheelbase=(0.62, 0.02),
        belt=(0.6, 0.03),
        windscreen_rake=(1.0, 0.15),
        rear_rake=(0.15, 0.05),
    ),
}
# Traffic mix of body types (roughly a European/US street: mostly sedans, hatchbacks and SUVs).
_BODY_TYPE_WEIGHTS = np.array([0.3, 0.25, 0.3, 0.08, 0.07])


def sample_vehicle_shape(rng: np.random.Generator, body_type: str | None = None) -> VehicleShape:
    """A random vehicle shape of `body_type` (or of a type drawn from a street's traffic mix)."""
    if body_type is None:
        body_type = str(rng.choice(BODY_TYPES, p=_BODY_TYPE_WEIGHTS / _BODY_TYPE_WEIGHTS.sum()))
    if body_type not in _SHAPE_RANGES:
        raise ValueError(f"body_type {body_type!r} is not one of {', '.join(BODY_TYPES)}")
    r = {k: float(m + h * rng.uniform(-1.0, 1.0)) for k, (m, h) in _SHAPE_RANGES[body_type].items()}
    total = r["hood"] + r["cabin"] + r["trunk"]
    return VehicleShape(
        body_type=body_type,
        length_m=r["length_m"],
        width_m=r["width_m"],
        height_m=r["height_m"],
        hood_fraction=r["hood"] / total,
        cabin_fraction=r["cabin"] / total,
        trunk_fraction=1.0 - r["hood"] / total - r["cabin"] / total,
        wheel_radius_m=r["wheel_radius_m"],
        wheelbase_fraction=r["wheelbase"],
        belt_fraction=r["belt"],
        windscreen_rake=r["windscreen_rake"],
        rear_rake=r["rear_rake"],
    )


# Colour families: (popularity weight, linear-RGB albedo low, high, chance of a metallic-flake paint).
_PAINT_FAMILIES: tuple[tuple[float, tuple[float, float, float], tuple[float, float, float], float], ...] = (
    (0.35, (0.60, 0.60, 0.60), (0.85, 0.85, 0.85), 0.1),  # white
    (0.19, (0.02, 0.02, 0.02), (0.04, 0.04, 0.045), 0.3),  # black
    (0.18, (0.10, 0.10, 0.11), (0.25, 0.25, 0.27), 0.5),  # grey
    (0.10, (0.35, 0.36, 0.38), (0.55, 0.56, 0.58), 1.0),  # silver
    (0.07, (0.01, 0.04, 0.15), (0.05, 0.12, 0.45), 0.5),  # blue
    (0.06, (0.25, 0.01, 0.01), (0.55, 0.04, 0.04), 0.5),  # red
    (0.02, (0.20, 0.14, 0.08), (0.45, 0.35, 0.22), 0.5),  # beige / brown
    (0.02, (0.02, 0.08, 0.03), (0.08, 0.25, 0.10), 0.5),  # green
    (0.01, (0.50, 0.25, 0.01), (0.80, 0.55, 0.03), 0.0),  # yellow / orange
)
PAINT_RANGES: dict[str, tuple[float, float]] = {
    "albedo": (0.01, 0.9),
    "specular_f0": (0.04, 0.06),
    "shininess": (64.0, 256.0),
    "metalness": (0.0, 0.7),
    "roughness": (0.05, 0.3),
}


def sample_paint(rng: np.random.Generator) -> Material:
    """A car paint from physically plausible ranges of the paper's five material parameters (see module doc)."""
    weights = np.array([f[0] for f in _PAINT_FAMILIES])
    family = _PAINT_FAMILIES[int(rng.choice(len(weights), p=weights / weights.sum()))]
    _, low, high, metallic_chance = family
    t = rng.uniform(0.0, 1.0)  # one brightness draw for all channels keeps the hue of the family
    jitter = rng.uniform(-0.03, 0.03, 3) * np.asarray(high)
    diffuse = np.clip(np.asarray(low) + t * (np.asarray(high) - np.asarray(low)) + jitter, *PAINT_RANGES["albedo"])
    f0 = rng.uniform(*PAINT_RANGES["specular_f0"])
    metalness = float(rng.uniform(0.3, 0.7)) if rng.uniform() < metallic_chance else 0.0
    return Material(
        diffuse_rgb=tuple(float(c) for c in diffuse),
        specular_rgb=(float(f0),) * 3,
        shininess=float(np.exp(rng.uniform(*np.log(PAINT_RANGES["shininess"])))),
        metalness=metalness,
        roughness=float(rng.uniform(*PAINT_RANGES["roughness"])),
    )


# The default materials of the other groups (a car built without sampled parts): tinted glass (dielectric, F0 ~0.04
# raised for the glancing views of a windscreen; smooth), tyre rubber (dark, rough), light lenses (polycarbonate,
# smooth; colour per vertex) and trim plastic (semi-matte; colour per vertex).
GLASS = Material(diffuse_rgb=(0.035, 0.045, 0.055), specular_rgb=(0.25, 0.25, 0.25), shininess=256.0, roughness=0.05)
RUBBER = Material(diffuse_rgb=(1.0, 1.0, 1.0), specular_rgb=(0.04, 0.04, 0.04), shininess=8.0, roughness=0.8)
LENS = Material(diffuse_rgb=(1.0, 1.0, 1.0), specular_rgb=(0.3, 0.3, 0.3), shininess=200.0, roughness=0.1)
TRIM = Material(diffuse_rgb=(1.0, 1.0, 1.0), specular_rgb=(0.04, 0.04, 0.04), shininess=24.0, roughness=0.6)
_TYRE_RGB = (0.045, 0.045, 0.05)
_HUB_RGB = (0.45, 0.46, 0.48)
_HEADLIGHT_RGB = (0.85, 0.85, 0.80)
_TAILLIGHT_RGB = (0.55, 0.02, 0.02)
_UNDERBODY_RGB = (0.03, 0.03, 0.03)  # the underside and arch liners: dark and in the car's own shadow


@dataclass(frozen=True)
class PartMaterials:
    """The materials of a car's parts other than its paint, and the colours its parts carry per vertex.

    :param glass: the windows. :param rubber: the tyres and hubs (their colours per vertex).
    :param lens: the lights (colours per vertex). :param trim: underbody, valances and grille (per vertex).
    :param trim_rgb: albedo of the black plastic trim. :param hub_rgb: albedo of the wheel's hub.
    """

    glass: Material = field(default_factory=lambda: GLASS)
    rubber: Material = field(default_factory=lambda: RUBBER)
    lens: Material = field(default_factory=lambda: LENS)
    trim: Material = field(default_factory=lambda: TRIM)
    trim_rgb: tuple[float, float, float] = (0.06, 0.06, 0.06)
    hub_rgb: tuple[float, float, float] = _HUB_RGB


PART_RANGES: dict[str, tuple[float, float]] = {
    "glass_albedo": (0.12, 0.25),
    "glass_specular": (0.15, 0.3),
    "glass_shininess": (128.0, 512.0),
    "glass_roughness": (0.02, 0.1),
    "rubber_roughness": (0.7, 0.9),
    "rubber_shininess": (4.0, 16.0),
    "trim_albedo": (0.04, 0.09),
    "trim_roughness": (0.4, 0.8),
    "trim_shininess": (12.0, 48.0),
    "lens_specular": (0.2, 0.4),
    "lens_roughness": (0.05, 0.15),
    "hub_albedo": (0.05, 0.6),
}


def sample_part_materials(rng: np.random.Generator) -> PartMaterials:
    """Per-car materials of the glass, tyres, lenses, trim and hubs from `PART_RANGES` (see module doc)."""
    R = PART_RANGES
    glass = float(rng.uniform(*R["glass_albedo"]))
    tint = rng.uniform([0.85, 0.95, 1.0], [1.0, 1.1, 1.25])  # most glass is tinted green-blue, a little
    glass_spec = float(rng.uniform(*R["glass_specular"]))
    trim = float(rng.uniform(*R["trim_albedo"]))
    lens_spec = float(rng.uniform(*R["lens_specular"]))
    # alloy hubs (bright, most cars) or black-painted steel ones
    hub = float(rng.uniform(0.3, R["hub_albedo"][1]) if rng.uniform() < 0.7 else rng.uniform(R["hub_albedo"][0], 0.1))
    return PartMaterials(
        glass=Material(
            diffuse_rgb=tuple(float(c) for c in np.clip(glass * tint, 0.0, R["glass_albedo"][1])),
            specular_rgb=(glass_spec,) * 3,
            shininess=float(np.exp(rng.uniform(*np.log(R["glass_shininess"])))),
            roughness=float(rng.uniform(*R["glass_roughness"])),
        ),
        rubber=Material(
            diffuse_rgb=(1.0, 1.0, 1.0),
            specular_rgb=(0.04, 0.04, 0.04),
            shininess=float(rng.uniform(*R["rubber_shininess"])),
            roughness=float(rng.uniform(*R["rubber_roughness"])),
        ),
        lens=Material(
            diffuse_rgb=(1.0, 1.0, 1.0),
            specular_rgb=(lens_spec,) * 3,
            shininess=200.0,
            roughness=float(rng.uniform(*R["lens_roughness"])),
        ),
        trim=Material(
            diffuse_rgb=(1.0, 1.0, 1.0),
            specular_rgb=(0.04, 0.04, 0.04),
            shininess=float(rng.uniform(*R["trim_shininess"])),
            roughness=float(rng.uniform(*R["trim_roughness"])),
        ),
        trim_rgb=(trim, trim, trim),
        hub_rgb=(hub, hub, 1.02 * hub),
    )


# ---------------------------------------------------------------------------------------------- closed primitives
class _Parts:
    """Closed components accumulated into one mesh (each component oriented outward on its own)."""

    def __init__(self) -> None:
        self.vertices: list[np.ndarray] = []
        self.faces: list[np.ndarray] = []
        self.rgb: list[np.ndarray] = []
        self.count = 0

    def add(
        self, vertices: np.ndarray, faces: np.ndarray, rgb: tuple[float, float, float] | np.ndarray = (1.0, 1.0, 1.0)
    ) -> None:
        """Add one closed component; `rgb` is its colour, or (V, 3) colours per vertex."""
        faces = _outward(vertices, faces)
        self.vertices.append(vertices)
        self.faces.append(faces + self.count)
        self.rgb.append(np.broadcast_to(np.asarray(rgb, dtype=np.float32), (len(vertices), 3)))
        self.count += len(vertices)

    def build(self, material: Material, object_id: int, coloured: bool = False) -> Mesh:
        return Mesh(
            vertices_m=np.concatenate(self.vertices).astype(np.float32),
            faces=np.concatenate(self.faces).astype(np.int64),
            vertex_rgb=np.concatenate(self.rgb) if coloured else None,
            material=material,
            object_id=object_id,
        )


def _outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces flipped if needed so that the closed component has positive volume (normals point out)."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
    return faces if volume > 0 else faces[:, ::-1].copy()


def _loft(sections: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A closed tube through (S, K, 3) convex cross-sections (same vertex order in each), capped at both ends."""
    S, K, _ = sections.shape
    verts = np.concatenate([sections.reshape(-1, 3), sections[0].mean(0)[None], sections[-1].mean(0)[None]])
    s, k = np.meshgrid(np.arange(S - 1), np.arange(K), indexing="ij")
    a = (s * K + k).ravel()
    b = (s * K + (k + 1) % K).ravel()
    c, d = a + K, b + K
    sides = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    ring = np.arange(K)
    cap0 = np.stack([np.full(K, S * K), (ring + 1) % K, ring], 1)
    cap1 = np.stack([np.full(K, S * K + 1), (S - 1) * K + ring, (S - 1) * K + (ring + 1) % K], 1)
    return verts, np.concatenate([sides, cap0, cap1])


def _hexahedron(bottom: np.ndarray, top: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A closed six-faced solid from a bottom and a top quad (4 x 3 each, corresponding corners)."""
    return _loft(np.stack([bottom, top]))


def _cylinder_y(centre: np.ndarray, radius_m: float, width_m: float, sides: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed cylinder with its axis along y (a wheel)."""
    angle = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)
    ring = np.stack([radius_m * np.cos(angle), np.zeros(sides), radius_m * np.sin(angle)], 1)
    sections = np.stack([ring + centre - [0, width_m / 2, 0], ring + centre + [0, width_m / 2, 0]])
    return _loft(sections)


def _rounded_section(
    half_width_m: float, top_half_width_m: float, z_bottom_m: float, z_top_m: float, radius_m: float, arc: int
) -> np.ndarray:
    """A convex cross-section in (y, z) with rounded corners (`arc` points per corner): (4 * arc, 2)."""
    r = min(radius_m, 0.45 * (z_top_m - z_bottom_m), 0.45 * top_half_width_m)
    centres = (
        (half_width_m - r, z_bottom_m + r, -90.0),
        (top_half_width_m - r, z_top_m - r, 0.0),
        (-top_half_width_m + r, z_top_m - r, 90.0),
        (-half_width_m + r, z_bottom_m + r, 180.0),
    )
    points = []
    for cy, cz, start in centres:
        angles = np.radians(start + np.linspace(0.0, 90.0, arc)) if arc > 1 else np.radians([start + 45.0])
        points.append(np.stack([cy + r * np.cos(angles), cz + r * np.sin(angles)], 1))
    return np.concatenate(points)


# ---------------------------------------------------------------------------------------------- the builder
@dataclass(frozen=True)
class _Layout:
    """Derived key heights and positions of a shape (vehicle frame)."""

    front_x: float
    rear_x: float
    cabin_front_x: float
    cabin_rear_x: float
    glass_top_front_x: float
    glass_top_rear_x: float
    belt_z: float
    roof_z: float
    sill_z: float
    axles_x: tuple[float, float]
    track_half_m: float
    tyre_width_m: float


def _layout(shape: VehicleShape) -> _Layout:
    L, H, r = shape.length_m, shape.height_m, shape.wheel_radius_m
    front, rear = L / 2, -L / 2
    cabin_front = front - shape.hood_fraction * L
    cabin_rear = rear + shape.trunk_fraction * L
    belt = shape.belt_fraction * H
    roof = H - ROOF_THICKNESS_M
    rise = roof - belt
    top_front = cabin_front - shape.windscreen_rake * rise
    top_rear = cabin_rear + shape.rear_rake * rise
    min_roof = 0.25 * (cabin_front - cabin_rear)  # keep a roof however raked the glass
    if top_front - top_rear < min_roof:
        mid = (cabin_front * shape.rear_rake + cabin_rear * shape.windscreen_rake) / max(
            shape.rear_rake + shape.windscreen_rake, 1e-6
        )
        top_front, top_rear = mid + min_roof / 2, mid - min_roof / 2
    wheelbase = shape.wheelbase_fraction * L
    # axles centred a little behind the middle: front overhangs are usually shorter... of the same order; centre them
    tyre_width = float(np.clip(0.12 * shape.width_m, 0.18, 0.3))
    return _Layout(
        front_x=front,
        rear_x=rear,
        cabin_front_x=cabin_front,
        cabin_rear_x=cabin_rear,
        glass_top_front_x=top_front,
        glass_top_rear_x=top_rear,
        belt_z=belt,
        roof_z=roof,
        sill_z=max(0.16, 0.55 * r),
        axles_x=(wheelbase / 2, -wheelbase / 2),
        track_half_m=shape.width_m / 2 - tyre_width / 2 - 0.015,
        tyre_width_m=tyre_width,
    )


def _hull(shape: VehicleShape, lay: _Layout, detail: str) -> tuple[np.ndarray, np.ndarray]:
    """The painted lower hull: a loft along x with wheel arches cut up from the sill."""
    r = shape.wheel_radius_m
    half_w = shape.width_m / 2
    arch_z = 1.12 * r
    nose = min(0.18, 0.05 * shape.length_m)
    # key stations: ends, nose/tail rounding, where the profile bends, and the arch edges
    front_x, rear_x = lay.front_x - LENS_PROUD_M, lay.rear_x + LENS_PROUD_M  # the lenses reach the bumper ends
    xs = [rear_x, rear_x + nose, front_x - nose, front_x, lay.cabin_front_x, lay.cabin_rear_x]
    for ax in lay.axles_x:
        xs += [ax - 1.2 * r, ax - 1.0 * r, ax - 0.6 * r, ax + 0.6 * r, ax + 1.0 * r, ax + 1.2 * r]
    if detail == "full":
        xs += list(np.linspace(rear_x, front_x, 24))
        xs += [rear_x + nose / 3, front_x - nose / 3]
    xs = np.unique(np.round(np.clip(xs, rear_x, front_x), 4))

    hood_front_z = lay.belt_z - min(0.12, 0.3 * (lay.belt_z - lay.sill_z))
    trunk_z = lay.belt_z if shape.body_type != "sedan" else lay.belt_z - 0.02
    top_x = [rear_x, rear_x + nose, lay.cabin_rear_x, lay.cabin_front_x, front_x - nose, front_x]
    top_z = [trunk_z - 0.6 * nose, trunk_z, lay.belt_z, lay.belt_z, hood_front_z, hood_front_z - 0.6 * nose]
    order = np.argsort(top_x)
    z_top = np.interp(xs, np.asarray(top_x)[order], np.asarray(top_z)[order])
    end_x = [rear_x, rear_x + nose, front_x - nose, front_x]
    bumper_z = lay.sill_z + 0.08
    z_bottom = np.interp(xs, end_x, [bumper_z, lay.sill_z, lay.sill_z, bumper_z])
    half = np.interp(xs, end_x, [0.9 * half_w, half_w, half_w, 0.9 * half_w])
    for ax in lay.axles_x:  # arches: full height within 0.6 r of the axle, sloping back to the sill by 1.2 r
        d = np.abs(xs - ax)
        z_bottom = np.maximum(z_bottom, np.interp(d, [0.6 * r, 1.2 * r], [arch_z, lay.sill_z]))

    arc = 4 if detail == "full" else 2
    corner_r = 0.1 if detail == "full" else 0.07
    sections = []
    for x, zb, zt, w in zip(xs, z_bottom, z_top, half, strict=True):
        yz = _rounded_section(w, 0.95 * w, zb, zt, corner_r, arc)
        sections.append(np.column_stack([np.full(len(yz), x), yz]))
    return _loft(np.asarray(sections))


def _glass_house(shape: VehicleShape, lay: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """The windows: a frustum from the belt line (sunk 3 cm into the hull) to under the roof."""
    wb, wt = 0.45 * shape.width_m, 0.39 * shape.width_m
    zb, zt = lay.belt_z - 0.03, lay.roof_z + 0.01
    bottom = np.array([[lay.cabin_front_x, -wb, zb], [lay.cabin_front_x, wb, zb], [lay.cabin_rear_x, wb, zb],
                       [lay.cabin_rear_x, -wb, zb]])  # fmt: skip
    top = np.array([[lay.glass_top_front_x, -wt, zt], [lay.glass_top_front_x, wt, zt],
                    [lay.glass_top_rear_x, wt, zt], [lay.glass_top_rear_x, -wt, zt]])  # fmt: skip
    return _hexahedron(bottom, top)


def _roof(shape: VehicleShape, lay: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """The painted roof panel on top of the glass house."""
    w = 0.39 * shape.width_m + 0.012
    x0, x1 = lay.glass_top_rear_x - 0.012, lay.glass_top_front_x + 0.012
    zb, zt = lay.roof_z, shape.height_m
    inset = 0.03  # rounded roof edge
    bottom = np.array([[x1, -w, zb], [x1, w, zb], [x0, w, zb], [x0, -w, zb]])
    top = np.array([[x1 - inset, -w + inset, zt], [x1 - inset, w - inset, zt], [x0 + inset, w - inset, zt],
                    [x0 + inset, -w + inset, zt]])  # fmt: skip
    return _hexahedron(bottom, top)


def _pillars(shape: VehicleShape, lay: _Layout) -> list[tuple[np.ndarray, np.ndarray]]:
    """A-, B- (not on a pickup's short cab) and C-pillars: thin slanted posts just outside the glass."""
    wb, wt = 0.45 * shape.width_m, 0.39 * shape.width_m
    zb, zt = lay.belt_z - 0.01, lay.roof_z + 0.005
    posts = [
        (lay.cabin_front_x, lay.glass_top_front_x, -1.0),  # A: its width runs backwards from the glass edge
        (lay.cabin_rear_x, lay.glass_top_rear_x, 1.0),  # C
    ]
    if shape.body_type != "pickup":
        mid_b = lay.cabin_rear_x + 0.55 * (lay.cabin_front_x - lay.cabin_rear_x)
        mid_t = lay.glass_top_rear_x + 0.55 * (lay.glass_top_front_x - lay.glass_top_rear_x)
        posts.append((mid_b + 0.05, mid_t + 0.05, -1.0))  # B
    out = []
    thickness = 0.018
    for xb, xt, direction in posts:
        width = 0.1 if direction < 0 and xb != lay.cabin_front_x else 0.08
        for side in (1.0, -1.0):
            bottom = np.array(
                [[xb, side * (wb + thickness), zb], [xb + direction * width, side * (wb + thickness), zb],
                 [xb + direction * width, side * (wb - 0.02), zb], [xb, side * (wb - 0.02), zb]]
            )  # fmt: skip
            top = np.array(
                [[xt, side * (wt + thickness), zt], [xt + direction * width, side * (wt + thickness), zt],
                 [xt + direction * width, side * (wt - 0.02), zt], [xt, side * (wt - 0.02), zt]]
            )  # fmt: skip
            out.append(_hexahedron(bottom, top))
    return out


def _lights(shape: VehicleShape, lay: _Layout) -> list[tuple[np.ndarray, np.ndarray, tuple[float, float, float]]]:
    """Head- and tail-light lenses: flat boxes standing `LENS_PROUD_M` proud of the hull's ends."""
    half_w = shape.width_m / 2
    nose = min(0.18, 0.05 * shape.length_m)
    hood_front_z = lay.belt_z - min(0.12, 0.3 * (lay.belt_z - lay.sill_z))
    out = []
    for end_x, top_z, rgb, sign in (
        (lay.front_x, hood_front_z - 0.6 * nose, _HEADLIGHT_RGB, 1.0),
        (lay.rear_x, lay.belt_z - 0.6 * nose, _TAILLIGHT_RGB, -1.0),
    ):
        z1 = top_z - 0.04
        z0 = z1 - 0.12
        x_out, x_in = end_x, end_x - sign * 0.1
        for side in (1.0, -1.0):
            y0, y1 = side * 0.5 * half_w, side * 0.84 * half_w
            bottom = np.array([[x_out, y0, z0], [x_out, y1, z0], [x_in, y1, z0], [x_in, y0, z0]])
            top = bottom + [0, 0, z1 - z0]
            out.append((*_hexahedron(bottom, top), rgb))
    return out


def _underbody(shape: VehicleShape, lay: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """The dark underside: a slab inside the hull from 8 cm above the ground to just over the arches' tops, between
    the bumpers. Where the hull is cut away (the wheel arches, under the sills and bumpers) it is what the camera
    sees: black arch liners behind the tyres and a dark band under the car."""
    r = shape.wheel_radius_m
    y = shape.width_m / 2 - 0.04  # behind the tyres' outer faces, inside the hull's sides
    x0, x1 = lay.rear_x + 0.15, lay.front_x - 0.15
    z0, z1 = 0.08, 1.12 * r + 0.01
    bottom = np.array([[x1, -y, z0], [x1, y, z0], [x0, y, z0], [x0, -y, z0]])
    return _hexahedron(bottom, bottom + [0.0, 0.0, z1 - z0])


def _end_box(end_x: float, depth_m: float, half_width_m: float, z0: float, z1: float, y_centre: float = 0.0):
    """A flat box whose outer face is at `end_x` (sign of `depth_m` points inward), spanning y_centre +- half
    width and z0..z1: a valance or a grille on a car's end."""
    x_in = end_x - depth_m
    y0, y1 = y_centre - half_width_m, y_centre + half_width_m
    bottom = np.array([[end_x, y0, z0], [end_x, y1, z0], [x_in, y1, z0], [x_in, y0, z0]])
    return _hexahedron(bottom, bottom + [0.0, 0.0, z1 - z0])


def _trim(shape: VehicleShape, lay: _Layout, parts: PartMaterials) -> list[tuple[np.ndarray, np.ndarray, tuple]]:
    """Bumper valances (dark plastic, the lower 14 cm of each end) and the grille between the headlights, standing
    `TRIM_PROUD_M` out of the hull's ends."""
    half_w = shape.width_m / 2
    nose = min(0.18, 0.05 * shape.length_m)
    bumper_z = lay.sill_z + 0.08
    hood_front_z = lay.belt_z - min(0.12, 0.3 * (lay.belt_z - lay.sill_z))
    head_top = hood_front_z - 0.6 * nose - 0.04
    out = []
    for sign, end in ((1.0, lay.front_x), (-1.0, lay.rear_x)):
        trim_x = end - sign * (LENS_PROUD_M - TRIM_PROUD_M)
        out.append((*_end_box(trim_x, sign * 0.1, 0.86 * half_w, bumper_z - 0.02, bumper_z + 0.12), parts.trim_rgb))
    grille_x = lay.front_x - (LENS_PROUD_M - TRIM_PROUD_M)
    out.append((*_end_box(grille_x, 0.1, 0.48 * half_w, head_top - 0.12, head_top), parts.trim_rgb))
    return out


def _height_ramp(vertices: np.ndarray, z0: float, z1: float, floor: float) -> np.ndarray:
    """(V, 3) per-vertex factors rising linearly from `floor` at height z0 to 1 at z1 (held outside)."""
    t = np.clip((vertices[:, 2] - z0) / max(z1 - z0, 1e-6), 0.0, 1.0)
    return np.repeat((floor + (1.0 - floor) * t)[:, None], 3, axis=1).astype(np.float32)


def build_vehicle_meshes(
    shape: VehicleShape, paint: Material, detail: str = "full", object_id: int = 0, parts: PartMaterials | None = None
) -> list[Mesh]:
    """The meshes of one vehicle: [body, windows, wheels, lights, trim] (`GROUP_NAMES`), closed, in the vehicle
    frame (x forward, z up, origin at the centre of the footprint on the ground), each with `object_id`.

    :param shape: the shape parameters.
    :param paint: the body's material (e.g. from `sample_paint`).
    :param detail: "full" (to look at) or "light" (a few hundred triangles).
    :param object_id: id written to the rasterizer's object mask.
    :param parts: the other parts' materials (e.g. from `sample_part_materials`); None: the defaults.
    """
    if detail not in DETAILS:
        raise ValueError(f"detail {detail!r} is not one of {', '.join(DETAILS)}")
    parts = parts or PartMaterials()
    lay = _layout(shape)
    body, glass, wheels, lights, trim = _Parts(), _Parts(), _Parts(), _Parts(), _Parts()
    hull = _hull(shape, lay, detail)
    body.add(*hull, rgb=_height_ramp(hull[0], 0.0, lay.belt_z, BODY_OCCLUSION_FLOOR))
    body.add(*_roof(shape, lay))
    if detail == "full":
        for part in _pillars(shape, lay):
            body.add(*part)
    house = _glass_house(shape, lay)
    glass.add(*house, rgb=_height_ramp(house[0], lay.belt_z, lay.roof_z, GLASS_REFLECTION_FLOOR))
    r = shape.wheel_radius_m
    sides = 20 if detail == "full" else 8
    for ax in lay.axles_x:
        for side in (1.0, -1.0):
            centre = np.array([ax, side * lay.track_half_m, r])
            wheels.add(*_cylinder_y(centre, r, lay.tyre_width_m, sides), rgb=_TYRE_RGB)
            if detail == "full":  # hub cap standing 5 mm out of the tyre's outer face
                hub_centre = centre + [0.0, side * (lay.tyre_width_m / 2 + 0.005 - 0.02), 0.0]
                wheels.add(*_cylinder_y(hub_centre, 0.62 * r, 0.04, 12), rgb=parts.hub_rgb)
    for v, f, rgb in _lights(shape, lay):
        lights.add(v, f, rgb=rgb)
    trim.add(*_underbody(shape, lay), rgb=_UNDERBODY_RGB)
    if detail == "full":
        for v, f, rgb in _trim(shape, lay, parts):
            trim.add(v, f, rgb=rgb)
    return [
        body.build(paint, object_id, coloured=True),
        glass.build(parts.glass, object_id, coloured=True),
        wheels.build(parts.rubber, object_id, coloured=True),
        lights.build(parts.lens, object_id, coloured=True),
        trim.build(parts.trim, object_id, coloured=True),
    ]


def repaint(meshes: list[Mesh], paint: Material) -> list[Mesh]:
    """The same vehicle meshes with the body (the first group) in a new paint; other groups shared."""
    return [replace(meshes[0], material=paint), *meshes[1:]]
