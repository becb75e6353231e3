"""Benchmark of `drivesim eval --record failures` (issue 24): how much recording the failed episodes as Foxglove MCAP
adds to an evaluation's wall time, against the same evaluation with `--record none`.

    .venv/bin/python benchmarks/bench_record.py                      # the tests' small world, 2 policies
    .venv/bin/python benchmarks/bench_record.py --world small --world WS/world --episodes 100,20

Each row evaluates the same seeds twice per repeat in fresh workspaces, once without recording and once recording
the failures (the default), alternating which goes first, after one warm-up evaluation (numba compiles the renderer's
kernels once); the figure is the median over the repeats of the difference over the time without recording, end to
end (`run_eval`: episodes, figures, report). With one worker the whole evaluation runs in this process, so its CPU
time is measured beside the wall time: on a machine shared with other jobs the CPU time is the steadier figure.
Two policies bound the cost: the privileged expert (few failures: the cost of keeping each step in memory) and a
network with random weights, whose every episode fails (the cost of writing `FAILURES_CAP` recordings). Without
--world it writes the small hand-made world of the tests (tests/sim_worlds.py: 80 x 50 pixels, a 40 x 16
observation), where a step renders fastest, so writing a recording weighs the most beside it; a demo world (`make
demo`) is the realistic case.
Writes benchmarks/results/record.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from _lib.report import write_markdown

from drivesim.bench.machine import machine_line
from drivesim.pipeline.workspace import Workspace
from drivesim.sim.envs.config import EnvConfig
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.evaluate.record import FAILURES_CAP
from drivesim.stages.evaluate.stage import run_eval

RESULTS = Path(__file__).resolve().parent / "results" / "record.md"
TESTS = Path(__file__).resolve().parents[1] / "tests"


def random_policy(folder: Path, observation: tuple[int, int, int]) -> Path:
    """A run folder as `drivesim train` writes it, with a small network of random weights (it fails every episode)."""
    import torch

    from drivesim.pipeline.hashing import sha256_file
    from drivesim.policy.run_folder import build_net
    from drivesim.stages.train.run_files import write_json, write_policy_files

    arch = {"conv_layers": [[4, 5, 4], [8, 3, 2]], "features_dim": 16, "lstm_hidden_size": 8, "lstm_layers": 1}
    torch.manual_seed(0)
    net = build_net({"observation_shape": list(observation), "architecture": arch})
    folder.mkdir(parents=True)
    write_policy_files(folder, "overtake", observation, arch, net.state_dict(), 0.15)
    write_json(folder / "config.json", {"train": {"task": "overtake"}, "env_config": {}, "worlds": [], "meshes": None})
    write_json(folder / "manifest.json", {"outputs": {"policy.pt": {"sha256": sha256_file(folder / "policy.pt")}}})
    return folder


class _Clock:
    """Wall time spent inside some functions (patched in this process: the one-worker evaluation runs here)."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self._saved: list[tuple[object, str, object]] = []

    def wrap(self, owner: object, name: str) -> None:
        original = getattr(owner, name)

        def timed(*args, **kwargs):
            tic = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - tic

        self._saved.append((owner, name, original))
        setattr(owner, name, timed)

    def restore(self) -> None:
        for owner, name, original in reversed(self._saved):
            setattr(owner, name, original)


def evaluate(world: Path, policy: str, env: dict, episodes: int, workers: int, record: str) -> dict:
    """One evaluation in a fresh workspace: its wall and CPU time (this process), the time its recording work took
    (keeping the steps, writing the MCAPs, copying them; one worker only), failures and recordings."""
    from drivesim.sim.episode_mcap import EpisodeCapture
    from drivesim.stages.evaluate import record as record_module
    from drivesim.stages.evaluate import replay as replay_module

    clock = _Clock()
    for owner, name in (
        (EpisodeCapture, "add"),
        (record_module.EpisodeRecorder, "end"),
        (replay_module, "finish_recordings"),
    ):
        clock.wrap(owner, name)
    with tempfile.TemporaryDirectory(prefix="bench-record-") as tmp:
        cfg = EvalConfig(
            episodes=episodes, world=str(world), workers=workers, policy=policy, env=EnvConfig(**env), record=record
        )
        tic, cpu = time.perf_counter(), time.process_time()
        try:
            result = run_eval(Workspace(tmp), cfg)
        finally:
            clock.restore()
        wall_s, cpu_s = time.perf_counter() - tic, time.process_time() - cpu
        recordings = list((result.path / "recordings").glob("*.mcap"))
        return {
            "wall_s": wall_s,
            "cpu_s": cpu_s,
            "recording_share": clock.seconds / wall_s,
            "failures": round(result.summary.intervention * result.summary.episodes),
            "recordings": len(recordings),
            "mb": sum(p.stat().st_size for p in recordings) / 1e6,
        }


def bench_policy(world: Path, policy: str, env: dict, episodes: int, workers: int, repeats: int) -> dict:
    """`repeats` pairs (none, failures), alternating the order; the median overhead."""
    evaluate(world, policy, env, min(episodes, 5), workers, "failures")  # warm-up: JIT compilation, file caches
    pairs = []
    for i in range(repeats):
        order = ("none", "failures") if i % 2 == 0 else ("failures", "none")
        runs = {mode: evaluate(world, policy, env, episodes, workers, mode) for mode in order}
        pairs.append(runs)
        for key in ("cpu_s", "wall_s"):
            base, rec = runs["none"][key], runs["failures"][key]
            print(
                f"{Path(policy).name} {key}: none {base:.1f} s, failures {rec:.1f} s ({100 * (rec / base - 1):+.1f} %)"
            )
    out: dict = {"policy": policy}
    for key in ("cpu_s", "wall_s"):
        overheads = [p["failures"][key] / p["none"][key] - 1 for p in pairs]
        out[key] = {
            "none": statistics.median(p["none"][key] for p in pairs),
            "failures": statistics.median(p["failures"][key] for p in pairs),
            "overhead": statistics.median(overheads),
            "each": overheads,
        }
    shares = [p["failures"]["recording_share"] for p in pairs]
    return {
        **out,
        "share": statistics.median(shares),
        "shares": shares,
        **{k: pairs[0]["failures"][k] for k in ("failures", "recordings", "mb")},
    }


def bench_world(
    world_arg: str, episodes: int, workers: int, repeats: int, tmp: Path
) -> tuple[list[str], dict[str, Any]]:
    """Both policies on one world ("small" = the tests' small world); the markdown section of that world and its
    raw figures."""
    if world_arg == "small":
        sys.path.insert(0, str(TESTS))
        from sim_worlds import SMALL_VIEW, write_test_world

        world, env = write_test_world(tmp / "small-world"), dict(SMALL_VIEW)
        title = "the tests' small world (80 x 50 px frames, 40 x 16 observation)"
    else:
        world, env = Path(world_arg).absolute(), {}
        info = json.loads((world / "world.json").read_text())
        camera = json.loads((world / "camera.json").read_text())
        title = (
            f"{world}: {info['frame_count']} frames of {info['path_length_m']:.0f} m at {camera['width_px']} x "
            f"{camera['height_px']} px, 160 x 64 observation"
        )
    shape = EnvConfig(**env).observation_shape
    policies = ["expert", str(random_policy(tmp / f"runs-{len(list(tmp.iterdir()))}" / "overtake-random", shape))]
    load_start = os.getloadavg()[0]
    rows = [bench_policy(world, p, env, episodes, workers, repeats) for p in policies]
    load_end = os.getloadavg()[0]
    lines = [
        f"## {title}",
        "",
        f"Load average {load_start:.1f} at the start, {load_end:.1f} at the end (other jobs shared the machine).",
        "",
        f"| policy | episodes | failures | recorded (cap {FAILURES_CAP}) | MB recorded | CPU s, none / failures | "
        "CPU added (median; each repeat) | wall s, none / failures | wall added (median) | recording's own time |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]

    def pct(values: list[float]) -> str:
        return ", ".join(f"{100 * v:+.1f} %" for v in values)

    for r in rows:
        name = "expert" if r["policy"] == "expert" else "random-weight network"
        cpu, wall = r["cpu_s"], r["wall_s"]
        shares = ", ".join(f"{100 * v:.1f} %" for v in r["shares"])
        lines.append(
            f"| {name} | {episodes} | {r['failures']} | {r['recordings']} | {r['mb']:.1f} | "
            f"{cpu['none']:.1f} / {cpu['failures']:.1f} | {100 * cpu['overhead']:+.1f} % ({pct(cpu['each'])}) | "
            f"{wall['none']:.1f} / {wall['failures']:.1f} | {100 * wall['overhead']:+.1f} % | "
            f"{100 * r['share']:.1f} % ({shares}) |"
        )
    share, cpu_added = max(r["share"] for r in rows), max(r["cpu_s"]["overhead"] for r in rows)
    verdict = "met" if max(share, cpu_added) <= 0.20 else "NOT met"
    lines += [
        "",
        f"Target (issue 24), recording the failures adds at most 20 % to the evaluation's time: {verdict} on this "
        f"world (recording's own time at most {100 * share:.1f} %, CPU time added at most {100 * cpu_added:+.1f} % "
        "in the median).",
        "",
    ]
    raw = {"world": title, "episodes": episodes, "load_average_start_end": [load_start, load_end], "policies": rows}
    return lines, raw


def main() -> None:
    """Run the benchmark and write its markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--world",
        action="append",
        default=None,
        help='world folder, or "small" for the tests\' small world (repeatable; default: small)',
    )
    parser.add_argument("--episodes", default="100", help="episodes per evaluation, one per --world (comma-separated)")
    parser.add_argument("--workers", type=int, default=1, help="worker processes of each evaluation")
    parser.add_argument("--repeats", type=int, default=2, help="(none, failures) pairs per policy")
    args = parser.parse_args()
    worlds = args.world or ["small"]
    counts = [int(v) for v in args.episodes.split(",")]
    counts = counts * len(worlds) if len(counts) == 1 else counts
    sections: list[str] = []
    raw: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="bench-record-world-") as tmp:
        for world, episodes in zip(worlds, counts, strict=True):
            lines, figures = bench_world(world, episodes, args.workers, args.repeats, Path(tmp))
            sections += lines
            raw.append(figures)
    cmd = f"python benchmarks/bench_record.py --episodes {args.episodes} --workers {args.workers}"
    cmd += f" --repeats {args.repeats}" + "".join(f" --world {w}" for w in args.world or [])
    lines = [
        "# record: what `drivesim eval --record failures` adds to an evaluation",
        "",
        f"Machine: {machine_line()}. Date: {datetime.now(UTC).strftime('%Y-%m-%d %H:%M UTC')}. Reproduce: `{cmd}`.",
        "",
        "CPU and wall: the evaluation end to end (`run_eval` with "
        f"{args.workers} worker process(es): the episodes, the figures and the report); each column is the median of "
        f"{args.repeats} (none, failures) pairs run in fresh workspaces, and 'added' the median of the pairs' ratios. "
        "Recording's own time: the wall time spent inside the recording code (keeping each step, encoding and "
        "writing the kept episodes, copying them into the evaluation) as a share of the evaluation that recorded, "
        "measured inside that run, so the other jobs on the machine slow both alike: the steadiest figure here. The "
        "workers keep each step of every episode in memory and encode only the failures they keep (JPEG camera, "
        "protobuf scene, zstd chunks); no episode is run twice.",
        "",
        *sections,
    ]
    write_markdown(RESULTS, lines, {"command": cmd, "worlds": raw})


if __name__ == "__main__":
    main()
