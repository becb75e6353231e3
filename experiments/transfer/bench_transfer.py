"""Issue 19: a trained policy and its baselines on the worlds it trained on and on worlds it never saw.

For one training run (`drivesim train ...`, its folder given with --run) this evaluates, with `drivesim eval` on the
same seeds (0 .. N-1 in every world, eval mode: any overlap is a collision):
  random      uniform random steering
  straight    no steering at all (how much of a lane task the drive's own geometry passes)
  expert      the privileged expert (sees the other car's state; the warm start's teacher)
  warm start  the run's policy before any PPO update (checkpoints/warm_start.pt), when the run had one
  final       the run's last update's weights (what the run reports)
  best        the weights of the run's best periodic evaluation on its held-back seeds (checkpoints/best.pt)
in each world of two groups: the run's training worlds (from its config.json) and the unseen worlds given with
--unseen (never in the run's training set: checked). Rows pool each group (episodes per world are equal), with the
per-world figures in the JSON. The run's held-back success over training time is drawn from its progress.csv.

    python experiments/transfer/bench_transfer.py --run RUN --unseen W1 --unseen W2 --real W3 --episodes 500 --name NAME

writes experiments/transfer/results/transfer_<NAME>.json, transfer_<NAME>.png and (from every transfer_*.json)
experiments/transfer/results/transfer.md. With --curve it also evaluates the run's warm start, its numbered checkpoints
(`checkpoints/step-*.pt`, every `checkpoint_every_steps`) and its final weights on the unseen and real worlds
(--curve-episodes each): success over training minutes, warm start included, and the first minute at or above
--target (issue 19's time to a good policy).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "_lib"))  # the studies' shared helpers (study.py)
from study import add_result_arguments, add_settings_argument  # noqa: E402

RESULTS = Path(__file__).parent / "results"
DRIVESIM = Path(sys.executable).parent / "drivesim"
POLICIES = ("random", "straight", "expert", "warm start", "final", "best")
GROUPS = ("train", "unseen", "real")


def machine() -> str:
    """A one-line description of this machine (CPU model, cores, load)."""
    model = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{os.cpu_count()}-core CPU ({model}), no GPU, {platform.machine()}, load average {os.getloadavg()[0]:.1f}"


def policy_argument(run: Path, policy: str) -> str | None:
    """What `drivesim eval --policy` takes for a row, or None when the run lacks it (no warm start)."""
    paths = {"warm start": run / "checkpoints" / "warm_start.pt", "best": run / "checkpoints" / "best.pt"}
    if policy in ("random", "straight", "expert"):
        return policy
    if policy == "final":
        return str(run)
    return str(paths[policy]) if paths[policy].is_file() else None


def evaluate(
    workspace: Path, task: str, policy: str, world: Path, episodes: int, name: str, overrides: list[str]
) -> dict:
    """`drivesim eval` of one policy in one world (with `--set` of each override); its metrics.json."""
    out = workspace / "eval" / name / "metrics.json"
    if not out.is_file():
        command = [
            str(DRIVESIM), "--workspace", str(workspace), "eval", "--task", task, "--policy", policy,
            "--world", str(world), "--episodes", str(episodes), "--record", "none", "--name", name,
            *(arg for value in overrides for arg in ("--set", value)),
        ]  # fmt: skip
        print(" ".join(command), flush=True)
        subprocess.run(command, check=True)
    return json.loads(out.read_text())


def pooled(per_world: list[dict]) -> dict:
    """Figures of a group of worlds with the same episodes each: rates and means over all their episodes."""
    n = sum(m["episodes"] for m in per_world)
    out = {"episodes": n}
    for key in ("success", "intervention", "collision", "off_lane", "min_clearance_m"):
        values = [(m["aggregate"][key]["value"], m["aggregate"][key]["n"]) for m in per_world]
        total = sum(k for _, k in values)
        out[key] = sum(v * k for v, k in values if v is not None) / total if total else None
    return out


def progress_curve(run: Path) -> list[tuple[float, int, float]]:
    """(training minutes, env steps, held-back success) of every periodic evaluation of the run ([] for an ensemble
    run, whose members hold the curves)."""
    if not (run / "progress.csv").is_file():
        return []
    rows = list(csv.DictReader((run / "progress.csv").open()))
    return [
        (float(r["wall_s"]) / 60.0, int(float(r["steps"])), float(r["eval_success_rate"]))
        for r in rows
        if r.get("eval_success_rate") not in (None, "")
    ]


def checkpoint_points(run: Path) -> list[tuple[float, int, str]]:
    """(training minutes, PPO env steps, `drivesim eval --policy` argument) of the warm start, every numbered
    checkpoint and the final weights, in training order."""
    import torch

    points = []
    folder = run / "checkpoints"
    for path in [folder / "warm_start.pt", *sorted(folder.glob("step-*.pt"))]:
        if path.is_file():
            checkpoint = torch.load(path, map_location="cpu", weights_only=False)
            points.append((float(checkpoint["wall_s"]) / 60.0, int(checkpoint.get("num_timesteps", 0)), str(path)))
    summary = json.loads((run / "manifest.json").read_text()).get("summary", {})
    final = (float(summary.get("wall_s", math.nan)) / 60.0, int(summary.get("steps", 0)), str(run))
    if points and points[-1][1] == final[1]:  # the run ended at a checkpoint: the final weights are those
        points.pop()
    return [*points, final]


def distinct_points(curve: list[dict]) -> list[dict]:
    """The curve's points without a checkpoint that repeats the next point's step count (a run that ended at a
    checkpoint evaluated its final weights twice before checkpoint_points dropped the repeat)."""
    return [p for i, p in enumerate(curve) if i + 1 == len(curve) or curve[i + 1]["steps"] != p["steps"]]


def unseen_curve(args: argparse.Namespace, run: Path, task: str, workspace: Path) -> list[dict]:
    """Success on the unseen and real worlds of every checkpoint point (checkpoint_points)."""
    curve = []
    for minutes, steps, argument in checkpoint_points(run):
        point: dict = {"minutes": minutes, "steps": steps, "policy": argument}
        for group, worlds in (("unseen", args.unseen), ("real", args.real)):
            per_world = [
                evaluate(
                    workspace,
                    task,
                    argument,
                    world.absolute(),
                    args.curve_episodes,
                    f"{args.name}-curve-{Path(argument).stem}-{steps}-{world.parent.name}-{world.name}",
                    args.eval_set,
                )  # fmt: skip
                for world in worlds
            ]
            if per_world:
                point[group] = pooled(per_world)
        curve.append(point)
    return curve


def time_to_target(curve: list[dict], target: float) -> float | None:
    """Training minutes of the first checkpoint whose unseen-town success is at least `target` (None: never)."""
    hits = [p["minutes"] for p in curve if p.get("unseen") and p["unseen"]["success"] >= target]
    return min(hits) if hits else None


def plot(result: dict, path: Path) -> None:
    """Held-back success over training time, with the baselines' unseen-world success as lines (an ensemble, which
    has no training curve of its own: `plot_ensemble`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if result.get("ensemble_of"):
        plot_ensemble(result, path)
        return
    fig, ax = plt.subplots(figsize=(9, 3.6))
    curve = result["curve"]
    if curve:
        ax.plot([c[0] for c in curve], [c[2] for c in curve], "o-", label="held-back success (training worlds)")
    for group, style in (("unseen", "s-"), ("real", "^-")):
        points = [p for p in distinct_points(result.get("unseen_curve", [])) if p.get(group)]
        if points:
            label = f"checkpoints on {'unseen towns' if group == 'unseen' else 'the unseen real drive'}"
            ax.plot([p["minutes"] for p in points], [p[group]["success"] for p in points], style, label=label)
    colours = {"random": "grey", "straight": "tab:brown", "expert": "black", "warm start": "tab:orange",
               "final": "tab:green"}  # fmt: skip
    for policy, colour in colours.items():
        row = result["rows"].get(policy)
        if row and row.get("unseen"):
            ax.axhline(row["unseen"]["success"], color=colour, ls="--", lw=1, label=f"{policy}: unseen towns")
        if row and row.get("real") and policy in ("expert", "warm start", "final"):
            ax.axhline(row["real"]["success"], color=colour, ls=":", lw=1.5, label=f"{policy}: unseen real drive")
    ax.set_xlabel("training minutes (warm start included)")
    ax.set_ylabel("success")
    ax.set_ylim(-0.02, 1.02)  # a line at 0 % stays visible above the axis
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the axes: it hides no point
    ax.set_title(f"{result['name']}: {result.get('task', 'overtake')}, held-back success and baselines")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_ensemble(result: dict, path: Path) -> None:
    """Success per unseen world: each member's final policy (from its own transfer_*.json, where one exists), the
    ensemble's, and the baselines evaluated with it, as bars."""
    import matplotlib.pyplot as plt
    import numpy as np

    by_run = {r["run"]: r for r in (json.loads(p.read_text()) for p in RESULTS.glob("transfer_*.json"))}
    members = [by_run.get(run) for run in result["ensemble_of"]]
    worlds = [
        (group, w) for group in ("unseen", "real") for w in (result["rows"]["final"].get(f"{group}_per_world") or {})
    ]
    bars = [(f"seed {arm_and_seed(m['name'])[1]}" if m else "member", "tab:blue", m) for m in members]
    bars.append(("ensemble", "tab:green", result))
    bars += [(p, "tab:brown" if p == "straight" else "grey", result) for p in ("random", "straight", "expert")
             if result["rows"].get(p)]  # fmt: skip
    fig, ax = plt.subplots(figsize=(9, 3.6))
    width = 0.8 / len(bars)
    for k, (label, colour, source) in enumerate(bars):
        policy = label if label in ("random", "straight", "expert") else "final"
        values = []
        for group, world in worlds:
            cell = (((source or {}).get("rows", {}).get(policy) or {}).get(f"{group}_per_world") or {}).get(world)
            values.append(np.nan if cell is None else cell["success"])
        alpha = 0.45 if label.startswith(("seed", "member")) else 1.0
        offset = (k - (len(bars) - 1) / 2) * width
        member = label.startswith(("seed", "member"))
        ax.bar(np.arange(len(worlds)) + offset, values, width, color=colour, alpha=alpha, edgecolor="white",
               label=label if not member or k == 0 else None)  # fmt: skip
    ax.set_xticks(np.arange(len(worlds)), [f"{Path(w).parent.name} ({g})" for g, w in worlds])
    ax.set_ylabel("success")
    ax.set_ylim(0, 1.02)
    ax.grid(axis="y", alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    labels = ["members (one bar each)" if lab.startswith(("seed", "member")) else lab for lab in labels]
    ax.legend(handles, labels, fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_title(
        f"{result['name']}:\nthe ensemble beside its {len(members)} members, {result['episodes']} episodes per world",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _cell(group: dict | None) -> str:
    if not group:
        return "—"
    clearance = group["min_clearance_m"]
    clearance_text = "—" if clearance is None else f"{clearance:.2f} m"
    return f"{group['success']:.1%} / {group['intervention']:.3f} / {clearance_text}"


def _per_world_lines(result: dict) -> list[str]:
    """Per-world success of every row, for groups of more than one world (the table pools them)."""
    lines = []
    for group in GROUPS:
        for policy in POLICIES:
            per_world = (result["rows"].get(policy) or {}).get(f"{group}_per_world") or {}
            if len(per_world) > 1:
                cells = ", ".join(
                    f"{Path(w).parent.name}/{Path(w).name} {m['success']:.1%}" for w, m in per_world.items()
                )
                lines.append(f"- {group}, {policy}: {cells}")
    return ["", "Per world (success):", *lines] if lines else []


def arm_and_seed(name: str) -> tuple[str, int]:
    """('lane-towns-kitti06', 2) from 'lane-towns-kitti06-seed2'; a name without '-seedN' is seed 0."""
    match = re.fullmatch(r"(.*)-seed(\d+)", name)
    return (match.group(1), int(match.group(2))) if match else (name, 0)


def _seed_table(results: list[dict]) -> list[str]:
    """Final-policy success of every arm run with more than one seed, per seed and the mean over seeds."""
    arms: dict[str, dict[int, dict]] = {}
    real_worlds: dict[str, str] = {}
    tasks: dict[str, str] = {}
    for r in results:
        arm, seed = arm_and_seed(r["name"])
        if (r["rows"].get("final") or {}).get("unseen") is not None:
            arms.setdefault(arm, {})[seed] = r["rows"]["final"]
            real_worlds[arm] = ", ".join(Path(w).parent.name for w in r["real_worlds"]) or "—"
            tasks[arm] = r.get("task", "overtake")
    arms = {arm: seeds for arm, seeds in arms.items() if len(seeds) > 1}
    if not arms:
        return []
    lines = [
        "## Arms run with several seeds (the final policy's success; the mean over the seeds)",
        "",
        "| arm | seeds | unseen synthetic towns, per seed | mean | unseen real drives (pooled) | per seed | mean |",
        "|---|---|---|---|---|---|---|",
    ]
    for arm, seeds in sorted(arms.items()):
        order = sorted(seeds)
        cells = []
        for group in ("unseen", "real"):
            if group == "real":
                cells.append(real_worlds[arm])
            values = [(seeds[s].get(group) or {}).get("success") for s in order]
            known = [v for v in values if v is not None]
            cells.append(" / ".join("—" if v is None else f"{v:.1%}" for v in values))
            cells.append(f"{sum(known) / len(known):.1%}" if known else "—")
        lines.append(f"| {arm} | {', '.join(map(str, order))} | {' | '.join(cells)} |")
    return [*lines, "", *_baseline_lines(results, {(tasks[arm], real_worlds[arm]) for arm in arms}), ""]


def _ensemble_table(results: list[dict]) -> list[str]:
    """Every ensemble run's success beside its members' (each member's own final-policy row, where one exists):
    on the unseen towns and on each unseen real drive."""
    by_run = {r["run"]: r for r in results}
    ensembles = [r for r in results if r.get("ensemble_of") and (r["rows"].get("final") or {}).get("unseen")]
    if not ensembles:
        return []
    lines = [
        "## Ensembles (`drivesim train --ensemble N`: the mean of N seeds' steering) beside their members",
        "",
        "| ensemble | members | unseen synthetic towns: ensemble (members) | unseen real drives: ensemble (members) |",
        "|---|---|---|---|",
    ]
    for r in ensembles:
        members = [by_run.get(run) for run in r["ensemble_of"]]
        names = [arm_and_seed(m["name"])[1] if m else "?" for m in members]
        cells = []
        for group in ("unseen", "real"):
            per_world = r["rows"]["final"].get(f"{group}_per_world") or {}
            parts = []
            for world, metrics in per_world.items():
                theirs = [((m or {}).get("rows", {}).get("final") or {}).get(f"{group}_per_world", {}).get(world)
                          for m in members]  # fmt: skip
                member_text = " / ".join("—" if t is None else f"{t['success']:.1%}" for t in theirs)
                parts.append(f"{Path(world).parent.name}: **{metrics['success']:.1%}** ({member_text})")
            cells.append("; ".join(parts) or "—")
        lines.append(f"| {r['name']} | {len(members)} (seeds {', '.join(map(str, names))}) | {' | '.join(cells)} |")
    return [*lines, ""]


def _baseline_lines(results: list[dict], real_sets: set[tuple[str, str]]) -> list[str]:
    """Random, straight and expert success on the same unseen worlds and seeds, each from the first result that
    evaluated it for each (task, set of real worlds) in `real_sets` (the arms above share their worlds, so one
    evaluation serves all arms of a task)."""
    lines, done = [], set()
    for policy in ("random", "straight", "expert"):
        for r in results:
            key = (r.get("task", "overtake"), ", ".join(Path(w).parent.name for w in r["real_worlds"]) or "—")
            task, real = key
            row = r["rows"].get(policy) or {}
            if key not in real_sets or (key, policy) in done or row.get("unseen") is None:
                continue
            real_success = (row.get("real") or {}).get("success")
            real_text = "—" if real_success is None else f"{real_success:.1%}"
            per_world = row.get("real_per_world") or {}
            if len(per_world) > 1:
                real_text += (
                    " (" + ", ".join(f"{Path(w).parent.name} {m['success']:.1%}" for w, m in per_world.items()) + ")"
                )
            lines.append(
                f"- {task}, {policy} (from {r['name']}, {r['episodes']} episodes per world): unseen synthetic towns "
                f"{row['unseen']['success']:.1%}, unseen real drives ({real}) {real_text}"
            )
            done.add((key, policy))
    return ["Baselines on the same worlds and seeds:", "", *sorted(lines)] if lines else []


def write_markdown() -> None:
    """experiments/transfer/results/transfer.md from every transfer_*.json."""
    lines = [
        "# Learning that transfers: baselines on training worlds and on worlds never seen (issue 19)",
        "",
        "Each cell: success / intervention / minimum clearance over all episodes, pooled over the group's worlds,",
        "the same seeds (0 .. N-1) in every world, `drivesim eval` (eval mode: any overlap is a collision).",
        "Reproduce: `python experiments/transfer/bench_transfer.py --run RUN --unseen W ... --real W --episodes N "
        "--name NAME`.",
        "",
    ]
    paths = sorted(RESULTS.glob("transfer_*.json"))
    lines += _seed_table([json.loads(path.read_text()) for path in paths])
    lines += _ensemble_table([json.loads(path.read_text()) for path in paths])
    for path in paths:
        r = json.loads(path.read_text())
        lines += [
            f"## {r['name']}",
            "",
            f"Measured {r['measured_utc']} on {r['machine']}. Run: `{r['run']}` ({r['trained_min']:.1f} min of "
            f"training, warm start included; {r['steps']} PPO env steps). Episodes per world: {r['episodes']}.",
            f"Training worlds: {', '.join(r['train_worlds'])}. Unseen: {', '.join(r['unseen_worlds'])}. "
            f"Real, unseen: {', '.join(r['real_worlds']) or '—'}.",
            "",
            "| policy | training worlds | unseen synthetic towns | unseen real drive |",
            "|---|---|---|---|",
        ]
        for policy in POLICIES:
            row = r["rows"].get(policy)
            if row is None:
                continue
            lines.append(
                f"| {policy} | {_cell(row.get('train'))} | {_cell(row.get('unseen'))} | {_cell(row.get('real'))} |"
            )
        lines += _per_world_lines(r)
        if r.get("unseen_curve"):
            points = "; ".join(
                f"{p['minutes']:.0f} min ({p['steps']} steps): {p['unseen']['success']:.0%}"
                + (f", real {p['real']['success']:.0%}" if p.get("real") else "")
                for p in distinct_points(r["unseen_curve"])
                if p.get("unseen")
            )
            reached = r.get("time_to_target_min")
            target = f"{r.get('target', 0.9):.0%}"
            lines += [
                "",
                f"Success on the unseen towns over training ({r.get('curve_episodes')} episodes per world and point): "
                f"{points}. Time to {target} on unseen towns: "
                + (f"{reached:.0f} min." if reached is not None else f"not reached in {r['trained_min']:.0f} min."),
            ]
        lines += ["", f"![held-back success]({path.stem}.png)", ""]
        if r.get("notes"):
            lines += [r["notes"], ""]
    (RESULTS / "transfer.md").write_text("\n".join(lines))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="a finished run folder of drivesim train")
    parser.add_argument("--unseen", type=Path, action="append", default=[], help="an unseen synthetic world")
    parser.add_argument("--real", type=Path, action="append", default=[], help="an unseen real world")
    parser.add_argument("--episodes", type=int, default=1000, help="episodes per world and policy")
    add_result_arguments(parser, "transfer")
    parser.add_argument("--policies", nargs="*", default=list(POLICIES), choices=POLICIES)
    parser.add_argument("--groups", nargs="*", default=list(GROUPS), choices=GROUPS, help="world groups to evaluate")
    parser.add_argument("--workspace", type=Path, default=None, help="scratch workspace for the evaluations")
    parser.add_argument("--curve", action="store_true", help="evaluate every checkpoint on the unseen worlds too")
    parser.add_argument("--curve-episodes", type=int, default=100, help="episodes per world and checkpoint")
    parser.add_argument("--target", type=float, default=0.9, help="the unseen success whose time is reported")
    add_settings_argument(
        parser,
        "--eval-set",
        "passed to every `drivesim eval` as --set, e.g. env.min_path_length_m=40 so that a 60 m real drive is "
        "accepted as the run accepted it in training (random and expert take the task's preset otherwise)",
    )
    args = parser.parse_args()
    run = args.run.absolute()
    config = json.loads((run / "config.json").read_text())
    task = config["train"]["task"]
    train_worlds = [Path(w) for w in config["worlds"]]
    for world in [*args.unseen, *args.real]:
        if any(world.absolute().samefile(t) for t in train_worlds):
            raise SystemExit(f"{world}: the run trained in this world; it cannot be an unseen one")
    workspace = args.workspace or Path(tempfile.gettempdir()) / f"drivesim-bench-transfer-{args.name}"
    groups = {"train": train_worlds, "unseen": args.unseen, "real": args.real}
    start = time.time()
    out_path = RESULTS / f"transfer_{args.name}.json"
    result = json.loads(out_path.read_text()) if out_path.is_file() else {"rows": {}}
    for policy in args.policies:
        argument = policy_argument(run, policy)
        if argument is None:
            continue
        row = result["rows"].setdefault(policy, {})
        for group, worlds in groups.items():
            if not worlds or group not in args.groups:
                continue
            per_world = []
            for world in worlds:
                label = f"{args.name}-{policy.replace(' ', '_')}-{world.parent.name}-{world.name}"
                metrics = evaluate(workspace, task, argument, world.absolute(), args.episodes, label, args.eval_set)
                per_world.append(metrics)
            row[group] = pooled(per_world)
            row[f"{group}_per_world"] = {str(w): pooled([m]) for w, m in zip(worlds, per_world, strict=True)}
    if args.curve:
        result["unseen_curve"] = unseen_curve(args, run, task, workspace)
        result["curve_episodes"], result["target"] = args.curve_episodes, args.target
        result["time_to_target_min"] = time_to_target(result["unseen_curve"], args.target)
    manifest = json.loads((run / "manifest.json").read_text())
    summary = manifest.get("summary", {})
    result.update(
        name=args.name,
        run=str(run),
        task=task,
        episodes=args.episodes,
        train_worlds=[str(w) for w in train_worlds],
        unseen_worlds=[str(w) for w in args.unseen],
        real_worlds=[str(w) for w in args.real],
        trained_min=float(summary.get("wall_s", math.nan)) / 60.0,
        steps=int(summary.get("steps", 0)),
        curve=progress_curve(run),
        ensemble_of=config.get("ensemble_of"),
        machine=machine(),
        measured_utc=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        eval_minutes=(time.time() - start) / 60.0,
        notes=args.notes or result.get("notes", ""),
    )
    out_path.write_text(json.dumps(result, indent=1))
    plot(result, RESULTS / f"transfer_{args.name}.png")
    write_markdown()
    print(f"wrote {out_path} and {RESULTS / 'transfer.md'}")


if __name__ == "__main__":
    main()
