"""Benchmark of an evaluation's start-up for many episodes: the time `run_episodes` takes before its first episode
ends (finding the seeds left to run, building the env and the policy, the first episode), and the seeds-left scan
alone, for 10,000 episodes with none or half of them already on disk (a resumed evaluation).

    .venv/bin/python benchmarks/bench_eval_startup.py                      # this checkout, about 20 s
    .venv/bin/python benchmarks/bench_eval_startup.py --before 9267520     # and the rollout of that commit

The env is the tests' fake overtake env (tests/eval_fakes.py: no renderer, about 25 ms per episode on one loaded
core) driven by the expert in this process (one worker), so the figures are the evaluation's own bookkeeping, not the
simulator's. torch is imported before the clock starts (every worker imports it once whatever the episode count).
`--before REF` also times the rollout module of git commit REF (its `run_episodes`, same env and seeds) at 500 and
1000 episodes, and extrapolates its quadratic start-up to 10,000. The 1000-episode wall time is the start-up plus 1000
times the time per episode measured over `--episodes-timed` episodes, for both.
Writes benchmarks/results/eval_startup.json and eval_startup.md.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from types import ModuleType
from typing import Any

from _lib.paths import REPO, use_folder
from _lib.report import write_markdown

from drivesim.bench.machine import machine_line
from drivesim.stages.evaluate import rollout

use_folder("tests")
from eval_fakes import FAKE, fake_world, pass_record, register_fake_envs  # noqa: E402

RESULTS = REPO / "benchmarks" / "results"
EPISODES = 10_000


class _StartupDoneError(Exception):
    """Raised by the progress callback when the first episode is done: the start-up is over."""


def _stop(done: Any) -> None:
    raise _StartupDoneError


def time_to_first_episode(module: ModuleType, world: Path, folder: Path, episodes: int) -> float:
    """Seconds from calling `module.run_episodes` for `episodes` seeds until its first episode is written."""
    factory = module.EnvFactory(FAKE["env_id"], {"world": str(world), "mode": "eval"})
    began = time.perf_counter()
    try:
        module.run_episodes(factory, module.PolicySpec("expert"), "overtake", list(range(episodes)), folder, 1, _stop)
    except _StartupDoneError:
        return time.perf_counter() - began
    raise RuntimeError("no episode ran")


def seconds_per_episode(module: ModuleType, world: Path, folder: Path, episodes: int) -> float:
    """Seconds per episode of `run_episodes` over `episodes` seeds, its start-up (timed separately) left out."""
    first: list[float] = []
    factory = module.EnvFactory(FAKE["env_id"], {"world": str(world), "mode": "eval"})
    began = time.perf_counter()
    module.run_episodes(
        factory,
        module.PolicySpec("expert"),
        "overtake",
        list(range(episodes)),
        folder,
        1,
        lambda done: first.append(time.perf_counter()) if not first else None,
    )
    return (time.perf_counter() - first[0]) / max(episodes - 1, 1) if first else (time.perf_counter() - began)


def half_done(folder: Path, episodes: int) -> Path:
    """`folder` with the episode files of every other seed of `episodes` (a resumed evaluation)."""
    record = pass_record(1.5)
    for seed in range(0, episodes, 2):
        rollout.write_episode(folder, replace(record, seed=seed))
    return folder


def module_at(ref: str) -> ModuleType:
    """stages/evaluate/rollout.py as it was at git commit `ref`, imported under another name."""
    text = subprocess.run(
        ["git", "-C", str(REPO), "show", f"{ref}:stages/evaluate/rollout.py"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    path = Path(tempfile.mkdtemp()) / "rollout_before.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("rollout_before", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["rollout_before"] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def measure_now(world: Path, tmp: Path, timed: int) -> dict[str, float]:
    """This checkout's figures."""
    empty = tmp / "empty"
    began = time.perf_counter()
    rollout.seeds_to_run(empty, list(range(EPISODES)))
    scan_empty = time.perf_counter() - began
    resumed = half_done(tmp / "half", EPISODES)
    began = time.perf_counter()
    left = rollout.seeds_to_run(resumed, list(range(EPISODES)))
    scan_half = time.perf_counter() - began
    assert len(left) == EPISODES // 2
    startup_1000 = time_to_first_episode(rollout, world, tmp / "s1000", 1000)
    per_episode = seconds_per_episode(rollout, world, tmp / "rate", timed)
    return {
        "scan_s_10000_empty": scan_empty,
        "scan_s_10000_half_on_disk": scan_half,
        "first_episode_s_1000": startup_1000,
        "first_episode_s_10000": time_to_first_episode(rollout, world, tmp / "s10000", EPISODES),
        "first_episode_s_10000_half_on_disk": time_to_first_episode(rollout, world, resumed, EPISODES),
        "s_per_episode": per_episode,
        "wall_s_1000_estimate": startup_1000 + 1000 * per_episode,
    }


def measure_before(module: ModuleType, world: Path, tmp: Path, timed: int) -> dict[str, float]:
    """The figures of an earlier rollout module (its start-up extrapolated quadratically to 10,000 episodes)."""
    startup = {n: time_to_first_episode(module, world, tmp / f"b{n}", n) for n in (500, 1000)}
    per_episode = seconds_per_episode(module, world, tmp / "brate", timed)
    return {
        "first_episode_s_500": startup[500],
        "first_episode_s_1000": startup[1000],
        "first_episode_s_10000_extrapolated": startup[1000] * (EPISODES / 1000) ** 2,
        "s_per_episode": per_episode,
        "wall_s_1000_estimate": startup[1000] + 1000 * per_episode,
    }


def report(data: dict[str, Any]) -> list[str]:
    """The markdown table."""
    now, before = data["now"], data.get("before")
    lines = [
        "# eval start-up for many episodes",
        "",
        f"{data['machine']}; {data['date_utc']}; `{data['command']}`",
        "",
        "Time from calling `run_episodes` (one worker, the tests' fake env, the expert) until its first episode is "
        "written, and the seeds-left scan alone; the 1000-episode wall time is that start-up plus 1000 episodes at "
        f"the time per episode measured over {data['episodes_timed']} episodes. Target: 10,000 episodes start in "
        "<= 5 s.",
        "",
        "| figure | before | now |",
        "|---|---:|---:|",
    ]

    def cell(section: dict[str, float] | None, key: str) -> str:
        return "-" if not section or key not in section else f"{section[key]:.3f}"

    rows = [
        ("start-up, 500 episodes [s]", "first_episode_s_500", None),
        ("start-up, 1000 episodes [s]", "first_episode_s_1000", "first_episode_s_1000"),
        ("start-up, 10,000 episodes [s]", "first_episode_s_10000_extrapolated", "first_episode_s_10000"),
        ("start-up, 10,000 episodes, half on disk [s]", None, "first_episode_s_10000_half_on_disk"),
        ("seeds-left scan alone, 10,000 episodes [s]", None, "scan_s_10000_empty"),
        ("seeds-left scan alone, 10,000, half on disk [s]", None, "scan_s_10000_half_on_disk"),
        ("time per episode [s]", "s_per_episode", "s_per_episode"),
        ("1000-episode wall time (estimate) [s]", "wall_s_1000_estimate", "wall_s_1000_estimate"),
    ]
    for label, before_key, now_key in rows:
        extrapolated = " (extrapolated, quadratic)" if before_key and "extrapolated" in before_key and before else ""
        b = cell(before, before_key) if before_key else "-"
        lines.append(f"| {label} | {b}{extrapolated} | {cell(now, now_key) if now_key else '-'} |")
    if before:
        lines += ["", f"before: the rollout of commit {data['before_ref']} (finished seeds re-scanned for every seed)."]
    return lines + [""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", help="git commit whose stages/evaluate/rollout.py to time as well")
    parser.add_argument("--episodes-timed", type=int, default=100, help="episodes the time per episode is taken over")
    args = parser.parse_args()
    import torch  # noqa: F401  (imported once before any clock: every worker imports it whatever the episodes)

    register_fake_envs()
    with tempfile.TemporaryDirectory() as name:
        tmp = Path(name)
        world = fake_world(tmp / "world")
        time_to_first_episode(rollout, world, tmp / "warm", 1)  # the env's first build, outside any figure
        data: dict[str, Any] = {
            "machine": machine_line(),
            "date_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "command": "benchmarks/bench_eval_startup.py" + (f" --before {args.before}" if args.before else ""),
            "episodes_timed": args.episodes_timed,
            "now": measure_now(world, tmp, args.episodes_timed),
        }
        if args.before:
            data["before_ref"] = args.before
            data["before"] = measure_before(module_at(args.before), world, tmp, args.episodes_timed)
    write_markdown(RESULTS / "eval_startup.md", report(data), data)


if __name__ == "__main__":
    main()
