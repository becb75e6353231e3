"""Does mirroring the scene on inserted cars' paint and glass make them harder to tell from real cars? (issue 44)

The C2ST of `benchmarks/bench_car_realism.py` (the car drawn at a world's 320 px, as the simulator draws it), with a
reflection added to every drawn car pixel after shading, from the rasterizer's own normals:

    rgb += strength * fresnel * surroundings,   fresnel = f0 + (1 - f0) (1 - n.v)^5 (Schlick)

along the reflected ray r = 2 (n.v) n - v, where `surroundings` is, per mode:
- sky: the frame's top-third mean where r points up (fading across the horizon), its whole mean below;
- frame: the frame itself, blurred, sampled where r meets it (r mirrored to the front where it points back).
The same for every material (glass and paint alike): a probe of whether reflections move the test, not a renderer.

    .venv/bin/python experiments/car_look/reflection_probe.py --mode frame --f0 0.05 --blur 2
    writes one line of experiments/car_look/results/reflection_probe.jsonl per run
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))
import bench_car_realism as bench  # noqa: E402

from drivesim.bench import car_realism as cr  # noqa: E402
from drivesim.sim import raster  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "reflection_probe.jsonl"
LEVELS = ("lighting", "harmonization", "camera")


def _surroundings(mode: str, frame: np.ndarray, blurred: np.ndarray, K: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(P, 3) colour in [0, 1] seen along reflected rays r (P, 3) in the camera frame (y down)."""
    if mode == "sky":
        top = frame[: frame.shape[0] // 3].reshape(-1, 3).mean(axis=0) / 255.0
        mean = frame.reshape(-1, 3).mean(axis=0) / 255.0
        up = np.clip(0.5 - 2.0 * r[:, 1], 0.0, 1.0)[:, None]
        return mean + up * (top - mean)
    forward = r.copy()
    forward[:, 2] = np.abs(forward[:, 2]) + 1e-3
    u = K[0, 0] * forward[:, 0] / forward[:, 2] + K[0, 2]
    v = K[1, 1] * forward[:, 1] / forward[:, 2] + K[1, 2]
    h, w = blurred.shape[:2]
    return blurred[np.clip(v, 0, h - 1).astype(int), np.clip(u, 0, w - 1).astype(int)] / 255.0


def install(mode: str, strength: float, f0: float, blur: float) -> None:
    """Wrap the rasterizer's render and the C2ST's insert_car so that lit cars get the probe's reflection."""
    plain_render, plain_insert = raster.Rasterizer.render, cr.insert_car
    scene: dict = {}

    def render(self, meshes, T, K, lighting=None, background_rgb=None):
        out = plain_render(self, meshes, T, K, lighting, background_rgb)
        lit = lighting is not None and float(np.asarray(lighting)[0, 6:9].sum()) > 0  # not the unlit levels
        if mode == "none" or not lit:
            return out
        mask = np.isfinite(out.depth_m[0].numpy())
        ys, xs = np.nonzero(mask)
        K_roi = np.asarray(K)
        rays = np.stack([(xs - K_roi[0, 2]) / K_roi[0, 0], (ys - K_roi[1, 2]) / K_roi[1, 1], np.ones(len(xs))], 1)
        to_viewer = -rays / np.linalg.norm(rays, axis=1, keepdims=True)
        normal = out.normal_cam[0].numpy()[ys, xs]
        n_dot_v = np.clip((normal * to_viewer).sum(axis=1), 0.0, 1.0)
        reflected = 2.0 * n_dot_v[:, None] * normal - to_viewer
        fresnel = f0 + (1.0 - f0) * (1.0 - n_dot_v) ** 5
        seen = _surroundings(mode, scene["frame"], scene["blurred"], scene["K"], reflected)
        rgb = out.rgb[0].numpy()
        rgb[ys, xs] = np.clip(rgb[ys, xs] + strength * fresnel[:, None] * seen, 0.0, 1.0)
        return out

    def insert_car(frame, K, box, model, level, view="rear", harmonizer=None):
        scene.update(frame=frame, K=K, blurred=cv2.GaussianBlur(frame, (0, 0), blur * frame.shape[1] / 320))
        return plain_insert(frame, K, box, model, level, view, harmonizer)

    raster.Rasterizer.render = render
    cr.insert_car = insert_car


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", choices=("none", "sky", "frame"), default="frame")
    parser.add_argument("--strength", type=float, default=1.0, help="scale of the reflection")
    parser.add_argument("--f0", type=float, default=0.05, help="reflectance at normal incidence")
    parser.add_argument("--blur", type=float, default=2.0, help="blur of the frame (px of a 320-px-wide frame)")
    args = parser.parse_args()
    install(args.mode, args.strength, args.f0, args.blur)
    start = time.time()
    boxes = cr.load_boxes(bench.BOXES)
    real, inserted = bench.crops_of(boxes, bench.REAL, 0, bench.WORLD_WIDTH_PX, True)
    results = bench.measure(real, inserted, np.array([b.drive for b in boxes]), 0)
    row = {**vars(args), "boxes": len(boxes), "seconds": round(time.time() - start),
           "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime())}  # fmt: skip
    row.update({level: [round(float(x), 3) for x in results[level]["all"]] for level in LEVELS})
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    with RESULTS.open("a") as f:
        f.write(json.dumps(row) + "\n")
    print(json.dumps(row))


if __name__ == "__main__":
    main()
