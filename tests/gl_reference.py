"""Reference renderer on OpenGL (moderngl, EGL, Mesa llvmpipe) and procedural test meshes.

Used by tests/test_raster.py and tests/test_warp.py to check drivesim.sim.raster against an established renderer, and
by benchmarks/bench_render.py as the side-by-side timing reference. The GLSL shader implements the same Blinn–Phong /
PBR-lite formula as drivesim.sim.shading (see its module docstring); everything else (projection, clipping, depth
test, interpolation, texture filtering) is OpenGL's.

Projection from K: pixel (row r, column c) has its centre at image coordinates (u, v) = (c, r) and at GL window
coordinates (c + 0.5, r + 0.5); image row r is stored as GL row r (no flip: NDC y grows with v, which only mirrors
the triangle winding, and culling is off). Depth is written as camera z into a float target, not read back from the
non-linear depth buffer.
"""

from __future__ import annotations

import numpy as np

from drivesim.sim.mesh import Material, Mesh
from drivesim.sim.shading import Lighting

_VERTEX_SHADER = """
#version 330
uniform mat3 R_cam_world;
uniform vec3 t_cam_world;
uniform vec4 intrinsics;   // fx, fy, cx, cy (px)
uniform vec2 size_px;      // width, height
uniform vec2 clip_m;       // near, far
in vec3 in_pos;
in vec3 in_normal;
in vec3 in_color;
in vec2 in_uv;
out vec3 v_pos;
out vec3 v_normal;
out vec3 v_color;
out vec2 v_uv;
void main() {
    vec3 p = R_cam_world * in_pos + t_cam_world;
    v_pos = p;
    v_normal = R_cam_world * in_normal;
    v_color = in_color;
    v_uv = in_uv;
    float n = clip_m.x;
    float f = clip_m.y;
    gl_Position = vec4(
        2.0 * intrinsics.x / size_px.x * p.x + ((2.0 * intrinsics.z + 1.0) / size_px.x - 1.0) * p.z,
        2.0 * intrinsics.y / size_px.y * p.y + ((2.0 * intrinsics.w + 1.0) / size_px.y - 1.0) * p.z,
        (f + n) / (f - n) * p.z - 2.0 * f * n / (f - n),
        p.z);
}
"""

_FRAGMENT_SHADER = """
#version 330
uniform vec3 specular_rgb;
uniform float shininess;
uniform float metalness;
uniform float roughness;
uniform bool unlit;
uniform bool textured;
uniform sampler2D tex;
uniform vec3 ambient_rgb;
uniform vec3 light_dir_cam;
uniform vec3 light_rgb;
uniform float object_id;
in vec3 v_pos;
in vec3 v_normal;
in vec3 v_color;
in vec2 v_uv;
layout(location = 0) out vec4 out_rgb;
layout(location = 1) out vec4 out_aux;
void main() {
    vec3 base = v_color;
    if (textured) base *= texture(tex, v_uv).rgb;
    vec3 V = normalize(-v_pos);
    vec3 N = normalize(v_normal);
    if (dot(N, V) < 0.0) N = -N;
    vec3 L = -normalize(light_dir_cam);
    vec3 H = normalize(L + V);
    float ndl = max(dot(N, L), 0.0);
    float ndh = max(dot(N, H), 0.0);
    vec3 f0 = (1.0 - metalness) * specular_rgb + metalness * base;
    float expo = 1.0 + shininess * (1.0 - roughness) * (1.0 - roughness);
    vec3 spec = ndl > 0.0 ? f0 * pow(ndh, expo) : vec3(0.0);
    vec3 lit = ambient_rgb * base + light_rgb * ((1.0 - metalness) * base * ndl + spec);
    out_rgb = vec4(clamp(unlit ? base : lit, 0.0, 1.0), 1.0);
    out_aux = vec4(v_pos.z, object_id + 1.0, N.x, N.y);
}
"""


def create_context():
    """A standalone moderngl context on EGL (raises when EGL/Mesa is unavailable)."""
    import moderngl

    return moderngl.create_standalone_context(backend="egl")


class GLRenderer:
    """Renders world-frame Meshes with OpenGL; the same call shape as drivesim's Rasterizer for one camera.

    Vertex buffers are built once per mesh list (kept while the same list object is passed), like a real engine with
    static geometry; per frame only uniforms change.
    """

    def __init__(self, ctx, width_px: int, height_px: int, near_m: float = 0.05, far_m: float = 2000.0):
        self.ctx = ctx
        self.width_px, self.height_px = width_px, height_px
        self.near_m, self.far_m = near_m, far_m
        self.program = ctx.program(vertex_shader=_VERTEX_SHADER, fragment_shader=_FRAGMENT_SHADER)
        size = (width_px, height_px)
        self._color = ctx.texture(size, 4, dtype="f4")
        self._aux = ctx.texture(size, 4, dtype="f4")
        self._depth = ctx.depth_renderbuffer(size)
        self.fbo = ctx.framebuffer(color_attachments=[self._color, self._aux], depth_attachment=self._depth)
        self._cache_key: list[Mesh] | None = None
        self._draws: list = []

    def _build(self, meshes: list[Mesh]) -> None:
        for vao, _, tex, _ in self._draws:
            vao.release()
            if tex is not None:
                tex.release()
        self._draws = []
        for mesh in meshes:
            f = np.asarray(mesh.faces, dtype=np.int64)
            v = np.asarray(mesh.vertices_m, np.float32)[f].reshape(-1, 3)
            if mesh.normals is not None:
                n = np.asarray(mesh.normals, np.float32)[f].reshape(-1, 3)
            else:
                tri = np.asarray(mesh.vertices_m, np.float64)[f]
                fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
                fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-20)
                n = np.repeat(fn, 3, axis=0).astype(np.float32)
            diffuse = np.asarray(mesh.material.diffuse_rgb, np.float32)
            c = (
                np.ones((len(v), 3), np.float32) if mesh.vertex_rgb is None else mesh.vertex_rgb[f].reshape(-1, 3)
            ) * diffuse
            textured = mesh.uv is not None and mesh.texture_rgb is not None
            uv = np.asarray(mesh.uv, np.float32)[f].reshape(-1, 2) if textured else np.zeros((len(v), 2), np.float32)
            data = np.concatenate([v, n, c.astype(np.float32), uv], axis=1).astype(np.float32)
            vbo = self.ctx.buffer(data.tobytes())
            vao = self.ctx.vertex_array(
                self.program, [(vbo, "3f 3f 3f 2f", "in_pos", "in_normal", "in_color", "in_uv")]
            )
            tex = None
            if textured:
                img = np.ascontiguousarray(mesh.texture_rgb, dtype=np.uint8)
                tex = self.ctx.texture((img.shape[1], img.shape[0]), 3, img.tobytes(), alignment=1)
                tex.repeat_x = False
                tex.repeat_y = False
                import moderngl

                tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
            self._draws.append((vao, mesh.material, tex, mesh.object_id))
        self._cache_key = meshes

    def render(
        self,
        meshes: list[Mesh],
        T_camera_world: np.ndarray,
        K: np.ndarray,
        lighting: Lighting | None = None,
        background_rgb: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> dict[str, np.ndarray]:
        """rgb (H, W, 3) float32, depth_m (H, W) (+inf where nothing), object_id (H, W) int32 (-1 where nothing)."""
        if self._cache_key is not meshes:
            self._build(meshes)
        lighting = lighting or Lighting()
        p = self.program
        p["R_cam_world"].write(np.asarray(T_camera_world[:3, :3], np.float32).T.tobytes())
        p["t_cam_world"].value = tuple(float(x) for x in T_camera_world[:3, 3])
        p["intrinsics"].value = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        p["size_px"].value = (float(self.width_px), float(self.height_px))
        p["clip_m"].value = (self.near_m, self.far_m)
        p["ambient_rgb"].value = tuple(float(x) for x in lighting.ambient_rgb)
        ldir = np.asarray(lighting.light_dir_cam, np.float64)
        p["light_dir_cam"].value = tuple(float(x) for x in ldir / np.linalg.norm(ldir))
        p["light_rgb"].value = tuple(float(x) for x in lighting.light_rgb)
        self.fbo.use()
        self.fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self.ctx.enable(self.ctx.DEPTH_TEST)
        self.ctx.disable(self.ctx.CULL_FACE)
        for vao, material, tex, object_id in self._draws:
            p["specular_rgb"].value = tuple(float(x) for x in material.specular_rgb)
            p["shininess"].value = float(material.shininess)
            p["metalness"].value = float(material.metalness)
            p["roughness"].value = float(material.roughness)
            p["unlit"].value = bool(material.unlit)
            p["object_id"].value = float(object_id)
            p["textured"].value = tex is not None
            if tex is not None:
                tex.use(0)
                p["tex"].value = 0
            vao.render()
        H, W = self.height_px, self.width_px
        rgb = np.frombuffer(self.fbo.read(components=4, dtype="f4", attachment=0), np.float32).reshape(H, W, 4)
        aux = np.frombuffer(self.fbo.read(components=4, dtype="f4", attachment=1), np.float32).reshape(H, W, 4)
        covered = aux[..., 1] > 0.5
        out_rgb = np.where(covered[..., None], rgb[..., :3], np.asarray(background_rgb, np.float32))
        depth = np.where(covered, aux[..., 0], np.inf).astype(np.float32)
        object_id = np.where(covered, np.round(aux[..., 1]) - 1, -1).astype(np.int32)
        return {"rgb": out_rgb, "depth_m": depth, "object_id": object_id}

    def release(self) -> None:
        """Free GL objects."""
        self._build([])
        self.fbo.release()
        self._color.release()
        self._aux.release()
        self._depth.release()
        self.program.release()


# ---------------------------------------------------------------------------------------------- procedural meshes


def _superellipsoid_patch(
    half_extent_m: np.ndarray, centre_m: np.ndarray, n_per_side: int, exponent: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A rounded box: a cube surface grid (6 faces, n x n quads each) pushed onto |x/a|^p + |y/b|^p + |z/c|^p = 1,
    with analytic normals. Returns vertices, faces (outward counter-clockwise), normals."""
    verts, faces, normals = [], [], []
    t = np.linspace(-1.0, 1.0, n_per_side + 1)
    gu, gv = np.meshgrid(t, t, indexing="xy")
    count = 0
    for axis in range(3):
        for sign in (-1.0, 1.0):
            p = np.zeros((gu.size, 3))
            a1, a2 = (axis + 1) % 3, (axis + 2) % 3
            p[:, axis] = sign
            p[:, a1] = gu.ravel()
            p[:, a2] = gv.ravel()
            r = (np.abs(p) ** exponent).sum(1) ** (1.0 / exponent)
            q = p / r[:, None]  # on the unit superellipsoid
            n = np.sign(q) * np.abs(q) ** (exponent - 1) / half_extent_m
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            verts.append(q * half_extent_m + centre_m)
            normals.append(n)
            idx = np.arange(gu.size).reshape(gu.shape) + count
            a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
            c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
            quad = np.stack([np.stack([a, b, c], 1), np.stack([a, c, d], 1)], 1).reshape(-1, 3)
            faces.append(quad if sign > 0 else quad[:, ::-1])
            count += gu.size
    return np.concatenate(verts), np.concatenate(faces), np.concatenate(normals)


def _cylinder_y(
    radius_m: float, width_m: float, centre_m: np.ndarray, segments: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A closed cylinder with its axis along y (a wheel), smooth side normals and flat caps."""
    ang = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(ang) * radius_m, np.zeros_like(ang), np.sin(ang) * radius_m], 1)
    side_n = np.stack([np.cos(ang), np.zeros_like(ang), np.sin(ang)], 1)
    verts, normals, faces = [], [], []
    for y in (-0.5 * width_m, 0.5 * width_m):
        verts.append(ring + [0, y, 0])
        normals.append(side_n)
    i = np.arange(segments)
    j = (i + 1) % segments
    faces.append(np.stack([i, segments + j, j], 1))  # counter-clockwise seen from outside
    faces.append(np.stack([i, segments + i, segments + j], 1))
    base = 2 * segments
    for k, y in enumerate((-0.5 * width_m, 0.5 * width_m)):
        off = base + k * (segments + 1)
        verts.append(np.vstack([ring + [0, y, 0], [[0, y, 0]]]))
        normals.append(np.tile([0.0, np.sign(y), 0.0], (segments + 1, 1)))
        cap = np.stack([off + i, off + j, np.full(segments, off + segments)], 1)
        faces.append(cap if k == 0 else cap[:, ::-1])
    return np.concatenate(verts) + centre_m, np.concatenate(faces), np.concatenate(normals)


def car_meshes(
    object_id: int = 0, body_rgb: tuple[float, float, float] = (0.7, 0.1, 0.1), body_quads: int = 18
) -> list[Mesh]:
    """Test fixture, not a vehicle model: a car-sized object of about 5k triangles in the vehicle frame (x forward,
    y left, z up, ground at z = 0) made of superellipsoid patches with smooth per-vertex normals, so the rasterizer
    is checked against OpenGL on curved shading, textures-free materials and a high triangle count; three materials
    (glossy paint, glass-like cabin, rubber). The simulator's vehicles come from `sim.vehicles.build_vehicle_meshes`
    (flat-shaded, closed; compared against OpenGL in tests/test_vehicles.py)."""
    body = _superellipsoid_patch(np.array([2.2, 0.9, 0.45]), np.array([0.0, 0.0, 0.8]), body_quads, 6.0)
    cabin = _superellipsoid_patch(np.array([1.2, 0.8, 0.35]), np.array([-0.3, 0.0, 1.4]), body_quads // 2, 4.0)
    wheels = [_cylinder_y(0.35, 0.25, np.array([x, y, 0.35]), 32) for x in (-1.4, 1.4) for y in (-0.85, 0.85)]
    wv = np.concatenate([w[0] for w in wheels])
    wf = np.concatenate([w[1] + k * len(wheels[0][0]) for k, w in enumerate(wheels)])
    wn = np.concatenate([w[2] for w in wheels])
    paint = Material(diffuse_rgb=body_rgb, specular_rgb=(0.5, 0.5, 0.5), shininess=64.0, metalness=0.3, roughness=0.3)
    glass = Material(diffuse_rgb=(0.15, 0.2, 0.25), specular_rgb=(0.8, 0.8, 0.8), shininess=128.0, roughness=0.1)
    rubber = Material(diffuse_rgb=(0.05, 0.05, 0.05), specular_rgb=(0.02, 0.02, 0.02), shininess=8.0, roughness=0.9)

    def mesh(part: tuple[np.ndarray, np.ndarray, np.ndarray], material: Material) -> Mesh:
        v, f, n = part
        return Mesh(v.astype(np.float32), f.astype(np.int64), normals=n.astype(np.float32), material=material,
                    object_id=object_id)  # fmt: skip

    return [mesh(body, paint), mesh(cabin, glass), mesh((wv, wf, wn), rubber)]


def checker_texture(size_px: int = 64, squares: int = 8) -> np.ndarray:
    """(size, size, 3) uint8 coloured checkerboard with a gradient, so that uv mistakes show."""
    y, x = np.mgrid[0:size_px, 0:size_px]
    check = ((x * squares // size_px + y * squares // size_px) % 2).astype(np.float32)
    rgb = np.stack([0.2 + 0.7 * check, 0.2 + 0.6 * x / size_px, 0.2 + 0.6 * y / size_px], -1)
    return (rgb * 255).astype(np.uint8)


def textured_quad(
    width_m: float = 2.0, height_m: float = 1.5, object_id: int = 0, texture: np.ndarray | None = None
) -> Mesh:
    """A vertical textured quad in the x-z plane facing -y, centred at the origin (u right, v down)."""
    w, h = 0.5 * width_m, 0.5 * height_m
    v = np.array([[-w, 0, h], [w, 0, h], [w, 0, -h], [-w, 0, -h]], np.float32)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
    tex = checker_texture() if texture is None else texture
    return Mesh(v, f, uv=uv, texture_rgb=tex, material=Material(diffuse_rgb=(1.0, 1.0, 1.0)), object_id=object_id)


def ground_plane(
    size_m: float = 400.0, object_id: int = 100, rgb: tuple[float, float, float] = (0.3, 0.3, 0.3)
) -> Mesh:
    """Two huge triangles at z = 0 (they pass behind any camera above them: a near-plane clipping test)."""
    s = size_m
    v = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], np.float32)
    f = np.array([[0, 1, 2], [0, 2, 3]], np.int64)
    n = np.tile(np.array([0, 0, 1], np.float32), (4, 1))
    return Mesh(v, f, normals=n, material=Material(diffuse_rgb=rgb, roughness=0.9), object_id=object_id)
