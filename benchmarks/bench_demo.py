"""The demo run's wall time per stage (issue 10): `drivesim run --preset demo` in a fresh workspace, as `make demo`.

    .venv/bin/python benchmarks/bench_demo.py                        # runs the chain (~30 min on 2 cores)
    .venv/bin/python benchmarks/bench_demo.py --stdout demo.log      # the printed output of an earlier `make demo`

Each stage's time is the one `drivesim run` prints ("<stage>: done in X s"); the total is the sum. Writes
benchmarks/results/demo.md.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from datetime import UTC, datetime
from pathlib import Path

from _lib.report import write_markdown

from drivesim.bench.machine import machine_line

RESULTS = Path(__file__).resolve().parent / "results" / "demo.md"
STAGE_LINE = re.compile(r"^(?P<stage>[a-z-]+): (?:done in (?P<s>[0-9.]+) s|(?P<skipped>fresh, skipped))")
BUDGET_MIN = 30.0


def stage_times(output: str) -> list[tuple[str, float | None]]:
    """(stage, seconds or None when skipped) from the output of `drivesim run`."""
    times = []
    for line in output.splitlines():
        m = STAGE_LINE.match(line.strip())
        if m:
            times.append((m["stage"], None if m["skipped"] else float(m["s"])))
    return times


def run_demo(workspace: Path) -> str:
    """Run `drivesim run --preset demo` in `workspace`; its printed output."""
    cmd = [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(workspace), "run", "--preset", "demo"]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        sys.exit(f"drivesim run failed (exit {done.returncode}):\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    return done.stdout


def main() -> None:
    """Measure (or read) the demo run and write its markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stdout", type=Path, default=None, help="printed output of an earlier demo run")
    args = parser.parse_args()
    if args.stdout is not None:
        output, source = args.stdout.read_text(errors="replace"), f"the output of `make demo` ({args.stdout.name})"
        # The run happened when the log was last written; the load now says nothing about it.
        when = datetime.fromtimestamp(args.stdout.stat().st_mtime, UTC)
        machine = machine_line().rsplit(", load average", 1)[0]
        load = None
    else:
        with tempfile.TemporaryDirectory(prefix="bench-demo-") as tmp:
            output, source = run_demo(Path(tmp)), "`python benchmarks/bench_demo.py`"
        when, machine = datetime.now(UTC), machine_line()
        load = [round(x, 2) for x in os.getloadavg()]
    times = stage_times(output)
    if not times:
        sys.exit("no stage lines ('<stage>: done in X s') in the output: was it `drivesim run`?")
    total_s = sum(s for _, s in times if s is not None)
    lines = [
        "# The demo run: `make demo` = `drivesim run --preset demo`, wall time per stage",
        "",
        f"Machine: {machine}. Finished: {when:%Y-%m-%d %H:%M} UTC. Source: {source}, in a fresh "
        "clone and a fresh workspace (the first `make demo` also spends about 2 min creating the venv: not counted).",
        "",
        "| stage | wall time |",
        "|---|---:|",
    ]
    lines += [f"| {stage} | {'skipped (fresh)' if s is None else f'{s:.1f} s'} |" for stage, s in times]
    verdict = "within" if total_s <= BUDGET_MIN * 60 else "over"
    lines += [
        f"| **total** | **{total_s / 60:.1f} min** |",
        "",
        f"Budget (issue 10): {BUDGET_MIN:.0f} min; this run is {verdict} it. The train stage (warm start included) "
        "stops at the preset's `total_steps` or its 15-min training time limit, whichever comes first.",
        "",
    ]
    raw = {
        "measured": {"date_utc": f"{when:%Y-%m-%d %H:%M}", "machine": machine, "load_average_1_5_15_min": load}
        | ({} if load else {"load_note": "not recorded: read from an earlier run's printed output"}),
        "source": source,
        "stages": [{"stage": stage, "wall_s": s} for stage, s in times],
        "total_s": total_s,
        "budget_min": BUDGET_MIN,
    }
    write_markdown(RESULTS, lines, raw)


if __name__ == "__main__":
    main()
