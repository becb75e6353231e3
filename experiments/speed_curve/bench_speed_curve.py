"""Issue 21: a speed change must leave learning as it was. The same training, on the same seed, with the code before
and after the change, side by side (one core each); the held-back success over env steps of both, and both final
policies evaluated on a world neither trained on.

The training is pure-RL overtake (no warm start, no imitation: nothing but the simulator and PPO) on the given
worlds, `--steps` env steps, a held-back evaluation every `--eval-every` steps (`--eval-episodes` episodes, the
run's own held-back seeds). "Before" is a folder holding the earlier `drivesim` package (e.g. `git archive REV` of
the earlier commit into DIR/drivesim), put first on PYTHONPATH; "after" is this checkout.

    python experiments/speed_curve/bench_speed_curve.py --before /tmp/before --world T1 --world T2 --world T3 \
        --unseen T101

Writes results/learning_speed_ab.md and learning_speed_ab.png beside this script (with --report-only, from the run
folders of an earlier call's --workdir).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
from datetime import UTC, datetime
from pathlib import Path

from drivesim.bench.machine import machine_line

RESULTS = Path(__file__).parent / "results"
DRIVESIM = Path(sys.executable).parent / "drivesim"
VERSIONS = ("before", "after")
BASELINES = ("random", "expert")
_CLI = "import sys; from drivesim.cli.main import main; sys.argv[0] = 'drivesim'; main()"


def train_command(workspace: Path, worlds: list[Path], args: argparse.Namespace) -> list[str]:
    """The `drivesim train` command line of one side (run through `python -c` so that PYTHONPATH picks the code)."""
    sets = [
        "towns=[]", "imitation.epochs=0", f"total_steps={args.steps}", "learner_threads=1",
        f"eval.every_steps={args.eval_every}", f"eval.episodes={args.eval_episodes}", f"seed={args.seed}",
    ]  # fmt: skip
    return [
        sys.executable, "-c", _CLI, "--workspace", str(workspace), "train", "overtake",
        *(arg for world in worlds for arg in ("--world", str(world))), *(arg for s in sets for arg in ("--set", s)),
    ]  # fmt: skip


def run_both(args: argparse.Namespace) -> None:
    """Both trainings at once, each pinned to its own core when `taskset` exists."""
    processes = []
    for core, version in enumerate(VERSIONS):
        workspace = args.workdir / version
        shutil.rmtree(workspace, ignore_errors=True)
        workspace.mkdir(parents=True)
        env = dict(os.environ)
        if version == "before":
            env["PYTHONPATH"] = f"{args.before.resolve()}{os.pathsep}{env.get('PYTHONPATH', '')}"
        command = train_command(workspace, args.world, args)
        if shutil.which("taskset"):
            command = ["taskset", "-c", str(core % (os.cpu_count() or 1)), *command]
        log = (workspace / "train.log").open("w")
        processes.append(subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT))
    for process in processes:
        if process.wait() != 0:
            sys.exit(f"a training failed (exit {process.returncode}); see {args.workdir}/*/train.log")


def run_folder(workspace: Path) -> Path:
    """The one training run in a workspace."""
    runs = sorted((workspace / "runs").glob("overtake-*"))
    if len(runs) != 1:
        sys.exit(f"{workspace}: expected one overtake run, found {len(runs)}")
    return runs[0]


def curves(run: Path) -> dict[str, list[tuple[int, float]]]:
    """(env steps, rate) of the held-back evaluations ('eval') and of the training episodes of each update ('train')."""
    rows = list(csv.DictReader((run / "progress.csv").open()))
    return {
        "eval": [(int(float(r["steps"])), float(r["eval_success_rate"])) for r in rows if r.get("eval_success_rate")],
        "train": [(int(float(r["steps"])), float(r["ep_success_rate"])) for r in rows if r.get("ep_success_rate")],
        "wall_s": [float(rows[-1]["wall_s"])] if rows else [],
    }


def evaluate(policy: str, world: Path, episodes: int, workdir: Path, name: str) -> dict:
    """`drivesim eval` (this checkout's simulator) of a policy (a run folder, random or expert) on `world`: its
    metrics.json."""
    out = workdir / "eval-ws" / "eval" / name / "metrics.json"
    if not out.is_file():
        subprocess.run(
            [str(DRIVESIM), "--workspace", str(workdir / "eval-ws"), "eval", "--task", "overtake", "--policy", policy,
             "--world", str(world), "--episodes", str(episodes), "--record", "none", "--name", name],
            check=True,
        )  # fmt: skip
    return json.loads(out.read_text())


def plot(data: dict, path: Path) -> None:
    """Held-back and training success over env steps, both versions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for version, colour in zip(VERSIONS, ("tab:gray", "tab:blue"), strict=True):
        steps, rate = zip(*data[version]["eval"], strict=True) if data[version]["eval"] else ((), ())
        ax.plot(steps, [100 * r for r in rate], "o-", color=colour, label=f"{version}: held-back evaluation")
        steps, rate = zip(*data[version]["train"], strict=True) if data[version]["train"] else ((), ())
        ax.plot(steps, [100 * r for r in rate], ":", color=colour, label=f"{version}: training episodes")
    ax.set_xlabel("env steps")
    ax.set_ylabel("success [%]")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("pure-RL overtake, same seed: the code before and after the speed change")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def markdown(data: dict, args: argparse.Namespace, command: str) -> str:
    """The results file."""
    lines = [
        "# Learning before and after a speed change (issue 21)",
        "",
        f"- machine: {machine_line()}",
        f"- date: {datetime.now(UTC):%Y-%m-%d %H:%M} UTC",
        f"- command: `{command}`",
        f"- training: pure-RL overtake (no warm start, no imitation), seed {args.seed}, {args.steps} env steps, worlds "
        + ", ".join(f"`{w}`" for w in args.world)
        + f"; held-back evaluation every {args.eval_every} steps, {args.eval_episodes} episodes; one core each, "
        f"side by side; before: the code in `{args.before}`",
        f"- final policies: {args.final_episodes} evaluation episodes each on `{args.unseen}` (never trained on), "
        "evaluated with this checkout's simulator, the same seeds; random steering and the privileged expert beside "
        "them (no warm start: these runs have none)",
        "",
        "| env steps | " + " | ".join(f"held-back success, {v}" for v in VERSIONS) + " |",
        "|---:|---:|---:|",
    ]
    by_step = {v: dict(data[v]["eval"]) for v in VERSIONS}
    for step in sorted(set(by_step["before"]) | set(by_step["after"])):
        cells = [f"{100 * by_step[v][step]:.0f} %" if step in by_step[v] else "" for v in VERSIONS]
        lines.append(f"| {step} | " + " | ".join(cells) + " |")
    lines += ["", "| policy | success | intervention | collision | off lane | min clearance, all episodes [m] | "
              "training wall time [min] |", "|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for v in (*VERSIONS, *BASELINES):
        a = data[v]["final"]["aggregate"]
        wall = f"{data[v]['wall_s'][0] / 60:.1f}" if data[v].get("wall_s") else ""
        lines.append(
            f"| {v} | {100 * a['success']['value']:.1f} % | {a['intervention']['value']:.3f} | "
            f"{100 * a['collision']['value']:.1f} % | {100 * a['off_lane']['value']:.1f} % | "
            f"{a['min_clearance_m']['value']:.2f} | {wall} |"
        )
    lines += ["", "![curves](learning_speed_ab.png)", ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", type=Path, required=True, help="folder holding the earlier drivesim package")
    parser.add_argument("--world", type=Path, action="append", required=True, help="a training world (repeat)")
    parser.add_argument("--unseen", type=Path, required=True, help="a world neither run trains on")
    parser.add_argument("--steps", type=int, default=245_760)
    parser.add_argument("--eval-every", type=int, default=40_960)
    parser.add_argument("--eval-episodes", type=int, default=100)
    parser.add_argument("--final-episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/speed-curve"))
    parser.add_argument("--report-only", action="store_true", help="only evaluate and report the runs in --workdir")
    parser.add_argument("--out", type=Path, default=RESULTS / "learning_speed_ab.md")
    args = parser.parse_args()
    if not (args.before / "drivesim" / "sim").is_dir():
        sys.exit(f"--before {args.before}: no drivesim/sim folder in it; git archive the earlier commit there first")
    if args.unseen in args.world:
        sys.exit("--unseen is one of the training worlds: give a world neither run trains on")
    if not args.report_only:
        run_both(args)
    data = {}
    for version in VERSIONS:
        run = run_folder(args.workdir / version)
        data[version] = curves(run)
        data[version]["final"] = evaluate(str(run), args.unseen, args.final_episodes, args.workdir, f"final-{version}")
    for baseline in BASELINES:  # the same seeds, for scale
        data[baseline] = {"final": evaluate(baseline, args.unseen, args.final_episodes, args.workdir, baseline)}
    plot(data, args.out.with_suffix(".png"))
    command = "python experiments/speed_curve/bench_speed_curve.py " + " ".join(sys.argv[1:])
    args.out.write_text(markdown(data, args, command))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
