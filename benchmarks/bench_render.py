"""Rendering speed: the torch rasterizer and forward warp (drivesim.sim.raster / drivesim.sim.warp) against OpenGL.

Measures ms per frame (median and p90 over --runs runs after warm-up) and writes the markdown table to
benchmarks/results/render.md:
- rasterizer at 200x320 (H x W) with 1, 3 and 8 vehicle meshes of ~5k triangles (the agent-insertion pass), and at
  600x960 for a big world scene (the synth stage's world when available, and a ~150k-triangle stand-in), each beside
  moderngl on EGL (Mesa llvmpipe, its default thread count), timed including the read-back of colour and depth;
- forward warp into a full 200x320 frame and into a 64x160 region of interest, from 200x320 and 600x960 sources.
Torch runs on one thread (torch.set_num_threads(1)) unless --threads says otherwise.

    python benchmarks/bench_render.py            # full run, a few minutes
    python benchmarks/bench_render.py --quick    # smoke run
"""

from __future__ import annotations

import argparse
import datetime as dt
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from _lib.paths import use_folder
from _lib.report import table_records, write_markdown

from drivesim.bench.machine import machine_line
from drivesim.sim import geometry as g
from drivesim.sim import warp as warp_module
from drivesim.sim.mesh import Material, Mesh
from drivesim.sim.raster import Rasterizer, pack_meshes
from drivesim.sim.warp import forward_warp

use_folder("tests")
from gl_reference import GLRenderer, car_meshes, create_context  # noqa: E402  (the moderngl reference of the tests)

HERE = Path(__file__).resolve().parent

CAR_POSES = [(8, 0.8, 0.6), (14, -3, 0.1), (20, 3.5, -0.2), (11, -6, 1.2), (25, 0, 0), (30, -3.5, 0), (17, 6, 0.4),
             (35, 3, 0.1)]  # fmt: skip
T_VEHICLE_CAMERA = g.camera_mount(0.0, 0.0, 1.5, pitch_down_rad=0.05)


def timed_ms(fn: Callable[[], object], runs: int, warmup: int = 5) -> tuple[float, float, float]:
    """Median and 90th percentile wall time of fn() in ms, and the median CPU time of this process in ms (all its
    threads; robust to other load on the machine, unlike wall time)."""
    for _ in range(warmup):
        fn()
    times, cpu = [], []
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    ms = np.array(times) * 1e3
    return float(np.median(ms)), float(np.percentile(ms, 90)), float(np.median(cpu) * 1e3)


def vehicle_scene(n_cars: int) -> list[Mesh]:
    """n cars of ~5k triangles each on an otherwise empty road (what the agent pass rasterizes)."""
    return [m.transformed(g.pose_2d(*CAR_POSES[i])) for i in range(n_cars) for m in car_meshes(object_id=i)]


def stand_in_world(seed: int = 0) -> list[Mesh]:
    """A ~150k-triangle procedural street: subdivided ground, rows of box buildings with subdivided facades, cars."""
    rng = np.random.default_rng(seed)
    meshes = []
    n = 120  # ground grid 240 m x 240 m of n x n quads
    xs = np.linspace(-40, 200, n + 1)
    ys = np.linspace(-120, 120, n + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    v = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], 1).astype(np.float32)
    idx = np.arange(gx.size).reshape(gx.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    tint = rng.uniform(0.8, 1.0, (len(v), 3)).astype(np.float32)
    meshes.append(Mesh(v, f, vertex_rgb=tint, material=Material(diffuse_rgb=(0.35, 0.35, 0.37)), object_id=0))
    for side in (-1, 1):
        for k in range(14):
            x0, depth_m, height_m = -20 + 15 * k, rng.uniform(8, 14), rng.uniform(8, 25)
            y0 = side * (10 + rng.uniform(0, 3))
            meshes.append(_box_building(x0, y0, side, 12.0, depth_m, height_m, rng, object_id=10 + k))
    for i in range(8):
        meshes += [m.transformed(g.pose_2d(10 + 12 * i, -3.5 * (i % 2), 0.0)) for m in car_meshes(object_id=50 + i)]
    return meshes


def _box_building(
    x0: float, y0: float, side: int, length_m: float, depth_m: float, height_m: float, rng, object_id: int
) -> Mesh:
    """An axis-aligned box with each face subdivided into a 16 x 16 grid (facade detail)."""
    lo = np.array([x0, y0 if side > 0 else y0 - depth_m, 0.0])
    hi = lo + [length_m, depth_m, height_m]
    t = np.linspace(0, 1, 17)
    gu, gv = np.meshgrid(t, t, indexing="xy")
    verts, faces, count = [], [], 0
    for axis in range(3):
        for end in (0, 1):
            p = np.zeros((gu.size, 3))
            a1, a2 = (axis + 1) % 3, (axis + 2) % 3
            p[:, axis] = end
            p[:, a1], p[:, a2] = gu.ravel(), gv.ravel()
            verts.append(lo + p * (hi - lo))
            ix = np.arange(gu.size).reshape(gu.shape) + count
            a, b, c, d = ix[:-1, :-1].ravel(), ix[:-1, 1:].ravel(), ix[1:, 1:].ravel(), ix[1:, :-1].ravel()
            faces.append(np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))
            count += gu.size
    colour = tuple(rng.uniform(0.4, 0.8, 3))
    return Mesh(np.concatenate(verts).astype(np.float32), np.concatenate(faces), material=Material(diffuse_rgb=colour),
                object_id=object_id)  # fmt: skip


def synth_world():
    """(meshes, T_camera_world, K, lighting) of the synth stage's world, or None when it is not importable."""
    try:
        from drivesim.stages.synth.world import SynthWorld
    except ImportError:
        return None
    world = SynthWorld.from_seed(0)
    p = world.path.at(60.0)
    T_world_camera = g.pose_2d(float(p["x_m"]), float(p["y_m"]), float(p["yaw_rad"])) @ T_VEHICLE_CAMERA
    return world.meshes, g.invert(T_world_camera), world.lighting(T_world_camera)


def bench_raster(rows: list[str], runs: int, quick: bool, ctx) -> None:
    H, W = 200, 320
    K = g.intrinsics_from_hfov(W, H, np.deg2rad(70.0))
    T = g.invert(T_VEHICLE_CAMERA)
    scenes = [(f"{n} vehicle{'s' if n > 1 else ''}", vehicle_scene(n), T, None, H, W, K) for n in (1, 3, 8)]
    scenes.append(("8 vehicles, torch culling back faces (OpenGL: both sides)", vehicle_scene(8), T, None, H, W, K))
    if not quick:
        Hb, Wb = 600, 960
        Kb = g.intrinsics_from_hfov(Wb, Hb, np.deg2rad(70.0))
        world = synth_world()
        if world is not None:
            meshes, T_cw, light = world
            scenes.append(("synth world (stages/synth)", meshes, T_cw, light, Hb, Wb, Kb))
        T_si = g.invert(g.pose_2d(0.0, -1.75, 0.0) @ T_VEHICLE_CAMERA)
        scenes.append(("procedural stand-in world", stand_in_world(), T_si, None, Hb, Wb, Kb))
    for name, meshes, T_cw, light, h, w, K in scenes:
        tris = sum(m.triangle_count for m in meshes)
        args = (meshes, T_cw, K, light)
        rast = Rasterizer(w, h, cull_back_faces="culling" in name)
        ours = timed_ms(lambda rast=rast, args=args: rast.render(*args), runs)
        gl = ("n/a", "n/a", "n/a")
        if ctx is not None:
            ref = GLRenderer(ctx, w, h)
            gl = tuple(f"{x:.1f}" for x in timed_ms(lambda ref=ref, args=args: ref.render(*args), runs))
            ref.release()
        rows.append(
            f"| raster | {name} | {tris:,} | {h}x{w} | {ours[0]:.1f} | {ours[1]:.1f} | {ours[2]:.1f} "
            f"| {gl[0]} | {gl[1]} | {gl[2]} |"
        )
        print(rows[-1], flush=True)
    bench_agents(rows, runs, ctx, H, W, K, T)


def bench_agents(rows: list[str], runs: int, ctx, H: int, W: int, K: np.ndarray, T: np.ndarray, B: int = 8) -> None:
    """The agent pass of B environments in one call: each camera sees one vehicle at its own pose (a car packed once,
    placed with PackedScene.transformed every step), against B OpenGL renders of one vehicle."""
    car = pack_meshes(car_meshes())
    rng = np.random.default_rng(0)
    poses = [g.pose_2d(rng.uniform(6, 15), rng.uniform(-2, 2), rng.uniform(-0.3, 0.3)) for _ in range(B)]
    rast = Rasterizer(W, H)
    Ts = np.stack([T] * B)

    def ours():
        return rast.render([[car.transformed(P, object_id=1)] for P in poses], Ts, K)

    med, p90, cpu = timed_ms(ours, runs)
    gl = ("n/a", "n/a", "n/a")
    if ctx is not None:
        ref = GLRenderer(ctx, W, H)
        placed = [[m.transformed(P) for m in car_meshes()] for P in poses]  # static buffers: GL's best case

        def theirs():
            return [ref.render(meshes, T, K) for meshes in placed]

        gl = tuple(f"{x:.1f}" for x in timed_ms(theirs, runs))
        ref.release()
    name = f"{B} cameras x 1 vehicle (batched, poses updated per call)"
    rows.append(
        f"| raster | {name} | {B} x {car.triangle_count:,} | {B}x{H}x{W} | {med:.1f} | {p90:.1f} | {cpu:.1f} "
        f"| {gl[0]} | {gl[1]} | {gl[2]} |"
    )
    print(rows[-1], flush=True)


def bench_warp(rows: list[str], runs: int) -> None:
    """Warp a rendered RGB-D frame 0.3 m sideways and 1 m forward into a 200x320 camera."""
    H, W = 200, 320
    K_out = g.intrinsics_from_hfov(W, H, np.deg2rad(70.0))
    roi = (80, 100, 160, 64)  # (x0, y0, w, h): a 64x160 policy region of interest
    T_dst_src = g.se3(g.rot_y(0.03), [0.3, 0.0, -1.0])
    world = stand_in_world()
    T_cw = g.invert(g.pose_2d(0.0, -1.75, 0.0) @ T_VEHICLE_CAMERA)
    for sh, sw in ((200, 320), (600, 960)):
        K_src = g.scale_intrinsics(K_out, sw / W, sh / H)
        frame = Rasterizer(sw, sh).render(world, T_cw, K_src)
        rgb = (frame.rgb * 255).to(torch.uint8)
        depth = frame.depth_m
        for label, region in (("full 200x320", None), ("ROI 64x160", roi)):
            for cold in (False, True):

                def run(K_src=K_src, rgb=rgb, depth=depth, region=region, cold=cold):
                    if cold:  # a new source frame: its back-projection is not cached yet
                        warp_module._SOURCE_CACHE.clear()
                    return forward_warp(rgb, depth, K_src, T_dst_src, K_out, W, H, roi=region)

                med, p90, cpu = timed_ms(run, runs)
                case = f"{label} from {sh}x{sw}" + (", new source frame" if cold else ", source cached")
                rows.append(f"| warp | {case} | | {label.split()[-1]} | {med:.2f} | {p90:.2f} | {cpu:.2f} | | | |")
                print(rows[-1], flush=True)


def main() -> None:
    """Run the benchmark and write benchmarks/results/render.md."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: few repetitions, vehicle scenes only")
    parser.add_argument("--runs", type=int, default=None, help="timed runs per case (default 60, quick 5)")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--output", type=Path, default=HERE / "results" / "render.md")
    args = parser.parse_args()
    runs = args.runs or (5 if args.quick else 60)
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    try:
        ctx = create_context()
    except Exception as exc:  # noqa: BLE001 - no EGL: report torch alone
        print(f"moderngl EGL unavailable ({exc}); OpenGL columns left empty")
        ctx = None

    rows: list[str] = []
    bench_raster(rows, runs, args.quick, ctx)
    bench_warp(rows, runs)
    gl_info = ctx.info["GL_RENDERER"] if ctx is not None else "unavailable"
    command = "python benchmarks/bench_render.py" + (" --quick" if args.quick else "")
    header = (
        "| what | scene | triangles | output (HxW) | torch median ms | torch p90 ms | torch CPU ms "
        "| OpenGL median ms | OpenGL p90 ms | OpenGL CPU ms |"
    )
    write_markdown(
        args.output,
        [
            "## Rendering (rasterizer and forward warp)",
            "",
            f"Machine: {machine_line()}. Date: {dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M} UTC. "
            f"Command: `{command}`. torch {torch.__version__}, {args.threads} thread(s); "
            f"OpenGL reference: moderngl on EGL, {gl_info} (default thread count), timed including the read-back of "
            f"colour and depth. ms per frame, median and p90 of wall time over {runs} runs after 5 warm-up runs; "
            "CPU ms: median CPU time of the process (all threads: llvmpipe uses several), which other load on a shared "
            "machine inflates much less than wall time.",
            "",
            header,
            "|---|---|---:|---|---:|---:|---:|---:|---:|---:|",
            *rows,
            "",
            "Warp: T = 0.3 m sideways, 1 m forward, 1.7 degrees of yaw; ROI (x0, y0, w, h) = (80, 100, 160, 64) of the "
            "200x320 destination; crack filling on. 'source cached': the frame's back-projected points and packed "
            "colours come from the per-frame cache (several agents or steps warping the same recorded frame); "
            "'new source frame': computed in the call.",
            "",
        ],
        {
            "command": command,
            "threads": args.threads,
            "runs": runs,
            "opengl": gl_info,
            "torch": torch.__version__,
            "rows": table_records(header, rows),
        },  # fmt: skip
    )


if __name__ == "__main__":
    main()
