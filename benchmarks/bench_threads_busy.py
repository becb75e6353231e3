"""`render_threads` 1 and 2 on a busy machine: a car-drawn overtake step and a lane step, ms per step.

Each measurement runs in its own process (numba's threading layer is chosen once per process): overtake evaluation
episodes (expert actions) timed until `--steps` steps drew the other car in the ego's view (`bench/sim_steps.py`),
then `--steps` lane training steps. Four settings: one thread; two threads as the views use them (each call takes a
second thread only while a core is free and where that has run faster, `sim/cpu_threads.py`); and two threads on
every call (`exact_threads`) in numba's workqueue layer, and in its OpenMP layer (the view's threading before that
governor). Each runs twice: on the machine as it is, and with a second process spinning on one core (pinned to it
where affinity can be set).

    .venv/bin/python benchmarks/bench_threads_busy.py --world /tmp/ws-demo/world

Writes benchmarks/results/threads_busy.json and threads_busy.md. About 1-3 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

from drivesim.bench.machine import machine_line

RESULTS = Path(__file__).resolve().parent / "results"

_CHILD = """
import contextlib, json, sys
import numpy as np
from drivesim.bench.sim_steps import make_env, time_env_steps
from drivesim.sim import cpu_threads, view
world, steps, threads, exact = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
granted = []
@contextlib.contextmanager
def counting(requested, site):
    with cpu_threads.governed_threads(requested, site) as n:
        granted.append(n)
        yield n
view.governed_threads = counting
cpu_threads.usable_threads(2)  # the first sample of the CPU counters (env set-up lasts longer than a re-check)
out = {}
with cpu_threads.exact_threads() if exact else contextlib.nullcontext():
    for task, mode, drawn in (("overtake", "eval", steps), ("lane", "train", 0)):
        env = make_env(task, world, None, mode, {"render_threads": threads})
        granted.clear()
        t = time_env_steps(env, steps, seed=0, car_drawn_steps=drawn, max_steps=40 * steps)
        ms = t.ms[t.car_drawn] if drawn else t.ms
        out[task] = {"steps": int(len(ms)), "median_ms": float(np.median(ms)), "p90_ms": float(np.percentile(ms, 90)),
                     "parallel_share": float(np.mean(np.array(granted) > 1)) if granted else 0.0}
print(json.dumps(out))
"""

SETTINGS = (
    ("1 thread", 1, None),
    ("2 threads (governed)", 2, None),
    ("2 threads, every call, workqueue", 2, "workqueue"),
    ("2 threads, every call, OpenMP (before)", 2, "omp"),
)
"""(label, render_threads, numba threading layer of an ungoverned run (every call on all threads) or None): the
settings measured in each condition."""


def measure(world: str, steps: int, threads: int, layer: str | None) -> dict:
    """One process's figures for overtake (car-drawn steps) and lane at `threads`, ungoverned in `layer`."""
    env = dict(os.environ)
    if layer is not None:
        env["NUMBA_THREADING_LAYER"] = layer
    command = [sys.executable, "-c", _CHILD, world, str(steps), str(threads), "0" if layer is None else "1"]
    out = subprocess.run(command, env=env, check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def start_busy() -> tuple[subprocess.Popen, str]:
    """A process spinning on one core (the last this process may use, pinned where affinity can be set)."""
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    pin = f"os.sched_setaffinity(0, {{{cpus[-1]}}})" if cpus else "pass"
    busy = subprocess.Popen([sys.executable, "-c", f"import os\n{pin}\nwhile True:\n    pass"])
    time.sleep(0.5)  # running before the first measurement's CPU sample
    return busy, f"pinned to CPU {cpus[-1]}" if cpus else "not pinned (no affinity here)"


def run(world: str, steps: int) -> dict:
    """Every setting on the machine as it is, then beside a busy process; loads and times recorded."""
    conditions: dict[str, dict] = {}
    for condition in ("as is", "one core busy"):
        busy, pinning = start_busy() if condition == "one core busy" else (None, "")
        try:
            load = os.getloadavg()[0]
            rows = {label: measure(world, steps, n, layer) for label, n, layer in SETTINGS}
        finally:
            if busy is not None:
                busy.kill()
                busy.wait()
        conditions[condition] = {"load_at_start": load, "busy_process": pinning, "settings": rows}
    return conditions


def markdown(result: dict) -> str:
    """The report: machine, date, loads, then one table row per condition and setting."""
    lines = [
        "# `render_threads` on a busy machine: ms per step",
        "",
        f"- date: {result['date']} UTC",
        f"- machine: {result['machine']}",
        f"- world: `{result['world']}`; {result['steps']} car-drawn overtake steps (evaluation episodes, expert "
        f"actions) and {result['steps']} lane steps per setting, each setting in its own process",
        "- settings: 1 thread; 2 threads as the views use them (a second thread only while a core is free and where "
        "it has run faster, "
        "`sim/cpu_threads.py`, numba's workqueue layer); 2 threads on every call in the workqueue layer; 2 threads on "
        "every call in numba's OpenMP layer (the view's threading before that governor)",
        f"- command: `{result['command']}`",
        "",
        "| condition | load at start | setting | overtake car-drawn median ms | p90 ms | lane median ms | p90 ms "
        "| calls with 2 threads (overtake, lane) |",
        "|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    for condition, c in result["conditions"].items():
        name = condition + (f" ({c['busy_process']})" if c["busy_process"] else "")
        for label, r in c["settings"].items():
            o, la = r["overtake"], r["lane"]
            lines.append(
                f"| {name} | {c['load_at_start']:.1f} | {label} | {o['median_ms']:.2f} | {o['p90_ms']:.2f} | "
                f"{la['median_ms']:.2f} | {la['p90_ms']:.2f} | {100 * o['parallel_share']:.0f} %, "
                f"{100 * la['parallel_share']:.0f} % |"
            )
    lines += ["", f"Load average at the end: {result['load_at_end']:.1f}."]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", required=True, help="a world folder (drivesim run's workspace/world)")
    parser.add_argument("--steps", type=int, default=100, help="timed steps per task and setting")
    parser.add_argument("--out-dir", type=Path, default=RESULTS)
    args = parser.parse_args()
    if not (Path(args.world) / "world.json").is_file():
        print(f"--world {args.world}: no world.json there; pass a world folder (a workspace's world/)", file=sys.stderr)
        sys.exit(2)
    if args.steps < 10:
        print(f"--steps {args.steps}: use at least 10 steps", file=sys.stderr)
        sys.exit(2)
    started = datetime.now(UTC)
    command = "python benchmarks/bench_threads_busy.py " + " ".join(sys.argv[1:])
    result = {"date": f"{started:%Y-%m-%d %H:%M}", "machine": machine_line(), "world": args.world,
              "steps": args.steps, "command": command}  # fmt: skip
    result["conditions"] = run(args.world, args.steps)
    result["load_at_end"] = os.getloadavg()[0]
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / "threads_busy.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.out_dir / "threads_busy.md").write_text(markdown(result))
    print(markdown(result))


if __name__ == "__main__":
    main()
