"""Table I on every real drive with a camera and on the demo world: the chain as a user runs it, then the same seeds
for random, straight, expert, the warm start alone and the final policy.

    .venv/bin/python benchmarks/bench_table1.py                                   # every drive, the real budgets
    .venv/bin/python benchmarks/bench_table1.py --drives kitti_odometry_00 --budget-scale 0.002 --episodes 8 \
        --zero-shot-episodes 4 --town -1 --out-dir /tmp/table1-smoke              # a smoke run (no real figure)
    .venv/bin/python benchmarks/bench_table1.py --zero-shot-of benchmarks/results/table1.json   # columns only

For each drive, in a fresh workspace: `drivesim run REC` with no flags (the recording preset; the demo world is
`drivesim run` without a recording), its wall time; then `drivesim eval` of each row's policy on the drive's own
world, seeds 0 to N-1 for every row. Reported, not targets: each final policy zero-shot on the other real drives'
worlds (leave-one-out) and on an unseen procedural town. `--budget-scale` < 1 shrinks the training budgets by --set
(then the chain is no longer the user's); 1 adds no flag. Writes table1.json and table1.md (machine, load, date) into
`--out-dir` (default benchmarks/results).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import resource
import subprocess
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from _lib.report import measured_now, write_json, write_markdown

from drivesim.bench.machine import machine_line
from drivesim.stages.evaluate.summary import RESULT_COLUMNS

REPO = Path(__file__).resolve().parents[1]
REAL = REPO.parent / "shared" / "data" / "real"
DRIVES: dict[str, Path | None] = {
    "kitti_raw_0001": REAL / "kitti_raw" / "2011_09_26" / "2011_09_26_drive_0001_sync",
    "kitti_odometry_06": REAL / "kitti_odometry_straight",
    "kitti_odometry_00": REAL / "kitti_odometry_00_first200",
    "kitti_odometry_07": REAL / "kitti_odometry_07_first160",
    "demo": None,  # the embedded demo drive: `drivesim run` without a recording
}
SCENARIO_ROWS = (
    "passing on the left",
    "passing on the right",
    "front car nearly static (< 0.5 m/s)",
    "front car moving",
)
"""The report's scenario rows (`stages.evaluate.metrics.scenario_table`) the second table shows, in its order."""
ROWS = ("random", "straight", "expert", "warm start", "final policy")
UNSEEN_TOWN = 101
FULL = {
    "total_steps": 1_000_000,
    "time_limit_s": 3600.0,
    "chain_budget_s": 3600.0,
    "buffer_steps": 8192,
    "warm_steps": 8192,
    "warm_rounds": 8,
}


def drivesim(ws: Path, *args: str, timeout_s: float | None = None) -> tuple[subprocess.CompletedProcess[str], float]:
    """`drivesim --workspace ws ARGS` in a subprocess; (its result, wall time in s)."""
    began = time.perf_counter()
    done = subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        env={**os.environ, "COLUMNS": "250"},
        check=False,
    )
    return done, time.perf_counter() - began


def budget_overrides(scale: float) -> list[str]:
    """--set arguments that shrink the recording preset's budgets by `scale` (none at 1)."""
    if scale >= 1.0:
        return []
    buffer = max(128, int(FULL["buffer_steps"] * scale) // 64 * 64)
    sets = {
        "train.total_steps": max(buffer, int(FULL["total_steps"] * scale)),
        "train.time_limit_s": max(60.0, FULL["time_limit_s"] * scale),
        "chain.budget_s": max(600.0, FULL["chain_budget_s"] * scale),
        "train.ppo.buffer_steps": buffer,
        "train.ppo.minibatch_steps": min(512, buffer // 2),
        "train.warm_start.iterations": max(1, round(FULL["warm_rounds"] * scale)),
        "train.warm_start.steps_per_iteration": max(128, int(FULL["warm_steps"] * scale)),
        "train.eval.every_steps": 0,
        "eval.episodes": max(4, int(1000 * scale)),
        "eval.baseline_episodes": max(2, int(200 * scale)),
    }
    return [a for key, value in sets.items() for a in ("--set", f"{key}={value}")]


def preset_budgets(scale: float) -> dict[str, float | None]:
    """The recording preset's budgets a chain runs with (after `budget_overrides(scale)`): the chain's wall-time
    budget, training's own time limit and the learning rates' end fraction."""
    from drivesim.chain.run import RECORDING_PRESET, load_run_preset

    preset = load_run_preset(RECORDING_PRESET, overrides=budget_overrides(scale)[1::2])
    train = preset.get("train", {})
    return {
        "chain_budget_s": preset.get("chain", {}).get("budget_s"),
        "train_time_limit_s": train.get("time_limit_s"),
        "learning_rate_end_fraction": train.get("ppo", {}).get("learning_rate_end_fraction"),
    }


def _budget_text(budgets: dict[str, float | None] | None) -> str:
    """A drive's preset budgets in words ("" when not recorded)."""
    if not budgets:
        return ""
    chain_s, limit_s = budgets.get("chain_budget_s"), budgets.get("train_time_limit_s")
    parts = [f"the chain {chain_s / 60:.0f} min" if chain_s else "no chain budget"]
    parts.append(f"training at most {limit_s / 60:.0f} min" if limit_s else "no training time limit")
    end_fraction = budgets.get("learning_rate_end_fraction")
    if end_fraction is not None:
        annealed = "zero" if end_fraction == 0 else f"{end_fraction:g} of their start"
        parts.append("constant learning rates" if end_fraction >= 1 else f"learning rates annealed to {annealed}")
    return "; preset: " + ", ".join(parts)


def _one_line(done: subprocess.CompletedProcess[str]) -> str:
    lines = (done.stderr.strip() or done.stdout.strip() or f"exit {done.returncode}").splitlines()
    return lines[-1][:300]


def children_cpu_s() -> float:
    """CPU time (user + system) of this process's finished children so far [s]."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_chain(name: str, recording: Path | None, ws: Path, scale: float) -> dict[str, Any]:
    """The chain as a user runs it on one drive: its wall time, the share of the machine's cores it got (other
    processes on a busy machine take the rest), its run folder, or the one line it failed with."""
    args = ["run", *([] if recording is None else [str(recording)]), *budget_overrides(scale)]
    cpu_before_s = children_cpu_s()
    done, wall_s = drivesim(ws, *args)
    entry: dict[str, Any] = {"drive": name, "recording": None if recording is None else str(recording)}
    entry.update(command="drivesim run" + ("" if recording is None else " REC") + (" (scaled)" if scale < 1 else ""))
    entry["budgets"] = preset_budgets(scale)
    entry["chain_wall_s"] = round(wall_s, 1)
    entry["chain_cpu_share"] = round((children_cpu_s() - cpu_before_s) / max(wall_s * (os.cpu_count() or 1), 1e-9), 3)
    if done.returncode != 0:
        return {**entry, "error": _one_line(done)}
    runs = sorted((ws / "runs").glob("overtake-*"))
    entry["run"] = str(runs[-1]) if runs else None
    if runs:  # the worlds the run trained on, named by their workspace's folder (the drive's name here)
        worlds = json.loads((runs[-1] / "config.json").read_text()).get("worlds", [])
        entry["trained_on"] = [Path(w).parent.name for w in worlds]
    entry["stages"] = [line.strip() for line in done.stdout.splitlines() if ": done in " in line]
    return {**entry, **training_budget(entry.get("run"))}


def training_budget(run: str | None) -> dict[str, float]:
    """The PPO env steps a run trained for, their rate over its whole training time (the warm start's included) and
    that time, from its progress.csv's last row; empty when the run folder or the file is gone."""
    progress = Path(run) / "progress.csv" if run else None
    if progress is None or not progress.is_file():
        return {}
    with progress.open() as f:
        rows = list(csv.DictReader(f))
    if not rows:
        return {}
    steps, wall_s = float(rows[-1]["steps"]), float(rows[-1]["wall_s"])
    return {
        "train_env_steps": int(steps),
        "train_env_steps_per_s": round(steps / wall_s, 1) if wall_s > 0 else 0.0,
        "train_wall_s": round(wall_s, 1),
    }


def evaluate(ws: Path, policy: str, name: str, episodes: int, world: Path | None = None) -> dict[str, Any]:
    """`drivesim eval` of one policy (seeds 0..episodes-1, no baselines): its metrics.json figures or its error."""
    # --force: these names belong to this benchmark, and a re-run measures again (another world, other code)
    args = ["eval", "--policy", policy, "--episodes", str(episodes), "--name", name, "--record", "none", "--force"]
    args += ["--set", "baseline_episodes=0"] + ([] if world is None else ["--world", str(world)])
    done, wall_s = drivesim(ws, *args)
    if done.returncode != 0:
        return {"error": _one_line(done), "eval_wall_s": round(wall_s, 1)}
    data = json.loads((ws / "eval" / name / "metrics.json").read_text())
    figures = {key: data["aggregate"][key] for key, _ in RESULT_COLUMNS}
    scenarios = {row["scenario"]: row["success"] for row in data.get("scenarios") or []}
    return {"episodes": data["episodes"], **figures, "scenarios": scenarios, "eval_wall_s": round(wall_s, 1)}


def row_policies(run: str) -> dict[str, str]:
    """Each row's policy for `drivesim eval --policy`."""
    warm = str(Path(run) / "checkpoints" / "warm_start.pt")
    return {"random": "random", "straight": "straight", "expert": "expert", "warm start": warm, "final policy": run}


def _cell(estimate: dict[str, Any] | None, interval: bool = False) -> str:
    if not estimate or estimate.get("value") is None:
        return "n/a"
    text = f"{estimate['value']:.3f}"
    return text + (f" [{estimate['ci_low']:.3f}, {estimate['ci_high']:.3f}]" if interval else "")


def markdown(result: dict[str, Any]) -> list[str]:
    """table1.md's lines."""
    heads = " | ".join(h for _, h in RESULT_COLUMNS)
    lines = [
        "# Table I on real drives: `drivesim run REC` as a user runs it, then the same seeds for every row",
        "",
        f"Machine: {result['machine']}. Date: {result['date']}. Code: {result['commit']}. Budget scale "
        f"{result['budget_scale']} ({'the preset as shipped' if result['budget_scale'] >= 1 else 'NOT the user run'}); "
        f"{result['episodes']} episodes per row. `python benchmarks/bench_table1.py` redoes it.",
        "",
        *_measured_lines(result),
        f"| drive | row | episodes | {heads} |",
        "|---|---|---:|" + "---:|" * len(RESULT_COLUMNS),
    ]
    for drive in result["drives"]:
        if "error" in drive:
            lines.append(f"| {drive['drive']} | chain failed: {drive['error']} | | " + "| " * len(RESULT_COLUMNS))
            continue
        for row in ROWS:
            r = drive["rows"].get(row, {})
            if "error" in r:
                lines.append(f"| {drive['drive']} | {row}: {r['error']} | | " + "| " * len(RESULT_COLUMNS))
                continue
            cells = " | ".join(_cell(r.get(k), k == "intervention") for k, _ in RESULT_COLUMNS)
            lines.append(f"| {drive['drive']} | {row} | {r.get('episodes', '')} | {cells} |")
    lines += [""] + [
        f"{d['drive']}: the warm start and the final policy trained on {', '.join(d['trained_on'])} only; random, "
        "straight and the expert are not trained."
        for d in result["drives"]
        if d.get("trained_on")
    ]
    lines += [
        "",
        "Reported only (not targets): the chain's wall time (ingest to export, its own evaluation and baselines "
        "included; the rows above are extra evaluations); the final policy zero-shot elsewhere.",
        "",
    ]
    lines += [
        "| drive | chain wall time | PPO env steps (per s of the training, its warm start included) | "
        "zero-shot: other real drives (success / intervention) | "
        f"unseen town {result.get('town') or '(not run)'} (success / intervention) | "
        "pass-left / right, static / dynamic success | zero-shot measured |",
        "|---|---:|---:|---|---|---|---|",
    ]
    for drive in result["drives"]:
        wall = f"{drive['chain_wall_s'] / 60:.1f} min"
        steps = drive.get("train_env_steps")
        budget = f"{steps / 1000:.0f}k ({drive['train_env_steps_per_s']:.0f})" if steps else "not recorded"
        if steps and drive.get("train_wall_s"):
            budget += f" in {drive['train_wall_s'] / 60:.1f} min"
        zero = "; ".join(
            f"{other}: {_cell(r.get('success'))} / {_cell(r.get('intervention'))}"
            if "error" not in r
            else f"{other}: {r['error']}"
            for other, r in drive.get("zero_shot", {}).items()
        )
        town = drive.get("unseen_town") or {}
        town_text = "n/a"
        if town:
            figures = f"{_cell(town.get('success'))} / {_cell(town.get('intervention'))}"
            town_text = town.get("error", figures)
        scen = (drive.get("rows", {}).get("final policy") or {}).get("scenarios") or {}
        split = " / ".join(_cell(scen.get(k)) for k in SCENARIO_ROWS)
        m = drive.get("zero_shot_measured")
        when = f"{m['date_utc']} UTC, code {m['commit']}, {m['episodes']} episodes" if m else "n/a"
        lines.append(f"| {drive['drive']} | {wall} | {budget} | {zero or 'n/a'} | {town_text} | {split} | {when} |")
    return lines + [""]


def merge_results(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Several runs' table1.json in one: each drive from the last result that has it, with when, where and on which
    code it was measured (its own entry, else its result's); the newest result's header."""
    drives: dict[str, dict[str, Any]] = {}
    for result in results:
        for drive in result["drives"]:
            own = drive.get("measured") or {**result["measured"], "commit": result.get("commit", "unknown")}
            zero_shot = drive.get("zero_shot_measured")
            if not zero_shot and (drive.get("zero_shot") or drive.get("unseen_town")):
                zero_shot = result.get("zero_shot_measured")
            budget = {} if "train_wall_s" in drive else training_budget(drive.get("run"))
            drives[drive["drive"]] = {**drive, **budget, "measured": own, "zero_shot_measured": zero_shot}
    newest = max(results, key=lambda r: r["measured"]["date_utc"])
    return {**newest, "commit": "per drive, below", "drives": [drives[name] for name in DRIVES if name in drives]}


def _measured_lines(result: dict[str, Any]) -> list[str]:
    """One line per drive saying when, at which load and on which code its row was measured."""
    lines = []
    for drive in result["drives"]:
        m = drive.get("measured")
        if m:
            loads = m.get("load_average_1_5_15_min")
            load = f"load {loads[0]} at the start" if loads else m.get("load_note", "load not recorded")
            budgets = _budget_text(drive.get("budgets"))
            share = drive.get("chain_cpu_share")
            cores = "" if share is None else f", the chain used {100 * share:.0f} % of the cores"
            lines.append(f"- {drive['drive']}: {m['date_utc']} UTC, {load}{cores}, code {m.get('commit')}{budgets}")
    return ["Each drive's chain started:", "", *lines, ""] if lines else []


def _git_commit() -> str:
    done = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return done.stdout.strip() or "unknown"


def zero_shot_columns(result: dict[str, Any], work: Path, town: int, episodes: int) -> None:
    """Each trained drive's final policy on the other real drives' worlds and on an unseen town (`town` < 0: none),
    `episodes` each, into its entry's "zero_shot" and "unseen_town" (a drive's world is its workspace's, the parent
    of its run folder's runs/)."""
    trained = [d for d in result["drives"] if "error" not in d and d.get("run")]
    workspaces = {d["drive"]: Path(d["run"]).parents[1] for d in trained}
    real_worlds = {name: ws / "world" for name, ws in workspaces.items() if name != "demo"}
    town_ws = work / "towns"
    build_town = bool(trained) and town >= 0
    town_done, _ = drivesim(town_ws, "towns", "build", str(town)) if build_town else (None, 0.0)
    town_world = town_ws / "towns" / f"seed{town}" / "world"
    result["town"] = town if build_town else None
    stamp = {**measured_now(), "commit": _git_commit(), "episodes": episodes}
    if build_town or len(real_worlds) > 1:
        result["zero_shot_measured"] = stamp
    for drive in trained:
        ws = workspaces[drive["drive"]]
        drive["zero_shot_measured"] = stamp
        drive["zero_shot"] = {
            other: evaluate(ws, drive["run"], f"table1-zero-shot-{other}", episodes, world)
            for other, world in real_worlds.items()
            if other != drive["drive"]
        }
        if town_done is not None and town_done.returncode == 0:
            drive["unseen_town"] = evaluate(ws, drive["run"], "table1-town", episodes, town_world)
        elif town_done is not None:
            drive["unseen_town"] = {"error": _one_line(town_done)}


def main() -> None:
    """Run the chains, the rows' evaluations and the zero-shot columns; write table1.json and table1.md."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--drives", default=",".join(DRIVES), help=f"comma-separated, of {', '.join(DRIVES)}")
    parser.add_argument("--budget-scale", type=float, default=1.0, help="shrink the training budgets (1: as shipped)")
    parser.add_argument("--episodes", type=int, default=1000, help="episodes of each row, same seeds")
    parser.add_argument("--zero-shot-episodes", type=int, default=200, help="episodes per zero-shot world")
    parser.add_argument("--town", type=int, default=UNSEEN_TOWN, help="unseen town seed (-1: no town column)")
    parser.add_argument("--work", type=Path, default=None, help="where the workspaces go (default: a temporary one)")
    parser.add_argument("--out-dir", type=Path, default=REPO / "benchmarks" / "results")
    parser.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        default=None,
        help="only combine these table1.json files (a later file's drive wins)",
    )
    parser.add_argument(
        "--zero-shot-of",
        type=Path,
        default=None,
        help="only add the zero-shot columns to this table1.json, from its drives' own workspaces",
    )
    args = parser.parse_args()
    if args.zero_shot_of:
        result = json.loads(args.zero_shot_of.read_text())
        zero_shot_columns(result, args.work or args.zero_shot_of.parent / "zero-shot-work", args.town,
                          args.zero_shot_episodes)  # fmt: skip
        write_json(args.out_dir / "table1.json", result)
        write_markdown(args.out_dir / "table1.md", markdown(result))
        return
    if args.merge:
        merged = merge_results([json.loads(path.read_text()) for path in args.merge])
        write_json(args.out_dir / "table1.json", merged)
        write_markdown(args.out_dir / "table1.md", markdown(merged))
        return
    names = [n.strip() for n in args.drives.split(",") if n.strip()]
    unknown = [n for n in names if n not in DRIVES]
    if unknown:
        sys.exit(f"unknown drive(s) {', '.join(unknown)}; choose from {', '.join(DRIVES)}")
    work = args.work or Path(os.environ.get("TMPDIR", "/tmp")) / f"table1-{os.getpid()}"
    result: dict[str, Any] = {
        "measured": measured_now(),  # when the chains started, and the load then
        "machine": machine_line(),
        "date": f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC",
        "commit": _git_commit(),
        "budget_scale": args.budget_scale,
        "episodes": args.episodes,
        "drives": [],
    }
    for name in names:
        recording = DRIVES[name]
        if recording is not None and not recording.exists():
            result["drives"].append({"drive": name, "chain_wall_s": 0.0, "error": f"no such recording {recording}"})
            continue
        print(f"{name}: drivesim run ...", flush=True)
        measured = {**measured_now(), "commit": result["commit"]}
        entry = {**run_chain(name, recording, work / name, args.budget_scale), "measured": measured}
        if "error" not in entry and entry.get("run"):
            entry["rows"] = {
                row: evaluate(work / name, policy, f"table1-{row.replace(' ', '-')}", args.episodes)
                for row, policy in row_policies(entry["run"]).items()
            }
        print(f"{name}: chain {entry['chain_wall_s'] / 60:.1f} min {entry.get('error', '')}", flush=True)
        result["drives"].append(entry)
    zero_shot_columns(result, work, args.town, args.zero_shot_episodes)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    write_json(args.out_dir / "table1.json", result)
    write_markdown(args.out_dir / "table1.md", markdown(result))


if __name__ == "__main__":
    main()
