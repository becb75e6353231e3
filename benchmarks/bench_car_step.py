"""A car-drawn overtake step, before and after a change of the simulator, in one run (issue 21).

Each round runs one subprocess per code version, alternating (so both see the same machine state); a version is a
folder holding a `drivesim` package tree (e.g. a copy of the repository's code folders made before the change,
`--before /tmp/before`, with /tmp/before/drivesim/{sim,bench,...}) put first on PYTHONPATH, or this checkout.
Each subprocess times overtake evaluation episodes (expert actions, one thread) until `--steps` steps drew the other car
in the ego's view (`bench/sim_steps.py`) and reports the median ms of those steps and their mean ms per part.

    .venv/bin/python benchmarks/bench_car_step.py --world /tmp/ws-demo/world --before /tmp/before

Writes benchmarks/results/car_step.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from _lib.report import write_markdown

from drivesim.bench.machine import machine_line

_CHILD = """
import json, sys
from drivesim.bench.sim_steps import make_env, time_env_steps
import drivesim.sim.raster as raster
world, steps, config = sys.argv[1], int(sys.argv[2]), json.loads(sys.argv[3])
env = make_env("overtake", world, None, "eval", config or None)
times = time_env_steps(env, steps, seed=0, car_drawn_steps=steps, max_steps=40 * steps)
print(json.dumps({"summary": times.summary(), "parts": times.mean_part_ms(True), "raster_file": raster.__file__}))
"""


def measure(code: Path | None, world: str, steps: int, config: dict | None) -> dict:
    """One subprocess's figures with the `drivesim` package of folder `code` (None: this checkout)."""
    env = dict(os.environ)
    if code is not None:
        env["PYTHONPATH"] = f"{code}{os.pathsep}{env.get('PYTHONPATH', '')}"
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, world, str(steps), json.dumps(config or {})],
        env=env, check=True, capture_output=True, text=True,
    )  # fmt: skip
    return json.loads(out.stdout.strip().splitlines()[-1])


def full_camera(world: str) -> dict:
    """Env config for a 320 x 200 observation of the centre of the world's image (as bench_vista_ratio.py)."""
    camera = json.loads((Path(world) / "camera.json").read_text())
    width, height = int(camera["width_px"]), int(camera["height_px"])
    w, h = min(320, width), min(200, height)
    return {"roi_px": ((width - w) // 2, (height - h) // 2, w, h), "observation_width_px": 320,
            "observation_height_px": 200}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", required=True)
    parser.add_argument("--before", type=Path, required=True, help="folder holding the earlier drivesim package")
    parser.add_argument("--steps", type=int, default=200, help="car-drawn steps per measurement")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--full-camera", action="store_true", help="also at a 320 x 200 observation")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "car_step.md")
    args = parser.parse_args()
    if not (args.before / "drivesim" / "sim").is_dir():
        sys.exit(f"--before {args.before}: no drivesim/sim folder in it; copy the code folders there first")
    load_before = os.getloadavg()[0]
    views = {"default view": None, **({"320x200": full_camera(args.world)} if args.full_camera else {})}
    runs: dict[tuple[str, str], list[dict]] = {}
    for _ in range(args.rounds):
        for view, config in views.items():
            for version, code in (("before", args.before.resolve()), ("after", None)):
                runs.setdefault((view, version), []).append(measure(code, args.world, args.steps, config))
    lines = [
        "# A car-drawn overtake step, before and after (issue 21)",
        "",
        f"- machine: {machine_line()} (load average {load_before:.1f} at the start, {os.getloadavg()[0]:.1f} at the "
        "end; other sessions' jobs outside the CPU slots may run beside it)",
        f"- date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC; world `{args.world}`",
        f"- each cell: median ms over {args.steps} overtake evaluation steps in which the other car was drawn, one "
        f"process, one thread; {args.rounds} rounds, before and after alternating; the cell is the lower round",
        "- command: `.venv/bin/python benchmarks/bench_car_step.py " + " ".join(sys.argv[1:]) + "`",
        "",
        "| view | version | median ms, car drawn (rounds) | steps/s | car-drawn share | mean ms per part (car drawn) |",
        "|---|---|---:|---:|---:|---|",
    ]
    for (view, version), results in runs.items():
        medians = [r["summary"]["median_ms_car_drawn"] for r in results]
        best = results[int(np.argmin(medians))]
        parts = ", ".join(f"{k} {v:.2f}" for k, v in best["parts"].items() if k != "total")
        share = np.mean([r["summary"]["car_drawn_share"] for r in results])
        lines.append(
            f"| {view} | {version} | {min(medians):.2f} ({', '.join(f'{m:.2f}' for m in medians)}) | "
            f"{1e3 / min(medians):.0f} | {100 * share:.0f} % | {parts} |"
        )
    raw = {
        "command_arguments": sys.argv[1:],
        "world": str(args.world),
        "load_average_start_end": [load_before, os.getloadavg()[0]],
        "runs": [{"view": view, "version": version, "rounds": results} for (view, version), results in runs.items()],
    }
    write_markdown(args.out, [*lines, ""], raw)


if __name__ == "__main__":
    main()
