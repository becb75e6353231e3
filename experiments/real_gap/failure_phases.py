"""Where and how overtaking episodes fail, per passing side, for several policies evaluated on the same seeds.

Reads `drivesim eval` folders (their episodes/<seed>.json trajectories) and, per policy and per side the ego passes
on (the side away from the front car), reports:
  - success, and the intervention causes (collision, off lane, over-rotation);
  - for collisions, the phase: "closing" (the ego still more than a car length behind, pass_margin < -L), "alongside"
    (within a car length either way) or "cutting back" (the ego ahead of the front car and turning back);
  - the largest lateral swerve away from the front car over the first 2 s, against the expert's on the same seed
    (a policy that swerves less than the expert did not see, or did not act on, the car).
The action error against the expert on the same states needs the env, not eval folders: `bench_real_gap.py --run`.

    .venv/bin/python experiments/real_gap/failure_phases.py --eval expert=WS/eval/E --eval final=WS/eval/F ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

EARLY_S = 2.0  # the window in which a pass's swerve must have started


def load_episodes(folder: Path) -> dict[int, dict[str, Any]]:
    """seed -> the episode record of one eval folder."""
    episodes = {}
    for path in (folder / "episodes").glob("*.json"):
        record = json.loads(path.read_text())
        episodes[int(record["seed"])] = record
    return episodes


def pass_side(record: dict[str, Any]) -> str:
    """The side the ego passes on: away from the front car's lateral offset (+ = left)."""
    return "right" if record["episode"]["other_lateral_m"] > 0 else "left"


def collision_phase(record: dict[str, Any]) -> str:
    """Where along the pass the collision happened, from the pass margin at its last step."""
    traj = record["trajectory"]
    margin = traj["pass_margin_m"][-1]
    length = record["episode"]["other_length_m"]
    if margin < -length:
        return "closing"
    if margin > 0.0:
        return "cutting back"
    return "alongside"


def early_swerve_m(record: dict[str, Any]) -> float:
    """The largest lateral move away from the front car in the first EARLY_S seconds (m, + = away)."""
    traj = record["trajectory"]
    away = -1.0 if record["episode"]["other_lateral_m"] > 0 else 1.0
    t = np.asarray(traj["t_s"])
    q = np.asarray(traj["q_lat_m"])[t <= EARLY_S]
    return float(np.max(away * (q - q[0]))) if q.size else 0.0


def summarize(episodes: dict[int, dict[str, Any]], expert: dict[int, dict[str, Any]] | None) -> dict[str, Any]:
    """Per side: counts, success, causes, collision phases, early swerve against the expert's."""
    out: dict[str, Any] = {}
    for side in ("left", "right"):
        rows = [r for r in episodes.values() if pass_side(r) == side]
        n = len(rows)
        if not n:
            continue
        term = [r["termination"] for r in rows]
        phases = [collision_phase(r) for r in rows if r["termination"]["collision"]]
        swerve = [early_swerve_m(r) for r in rows]
        entry = {
            "episodes": n,
            "success": sum(r["success"] for r in rows) / n,
            "collision": sum(t["collision"] for t in term) / n,
            "off_lane": sum(t["off_lane"] for t in term) / n,
            "over_rotation": sum(t["over_rotation"] for t in term) / n,
            "collision_phase": {p: phases.count(p) / n for p in ("closing", "alongside", "cutting back")},
            "early_swerve_m": float(np.median(swerve)),
        }
        if expert:
            paired = [(early_swerve_m(r), early_swerve_m(expert[s])) for s, r in episodes.items()
                      if s in expert and pass_side(r) == side]  # fmt: skip
            if paired:
                entry["early_swerve_vs_expert_m"] = float(np.median([a - b for a, b in paired]))
        out[side] = entry
    return out


def markdown(results: dict[str, dict[str, Any]]) -> list[str]:
    """The per-policy, per-side table."""
    lines = [
        "| policy | side passed | episodes | success | collision (closing / alongside / cutting back) | off lane | "
        "over-rotation | early swerve (m) | vs expert (m) |",
        "|---|---|---:|---:|---|---:|---:|---:|---:|",
    ]
    for name, sides in results.items():
        for side, e in sides.items():
            ph = e["collision_phase"]
            vs = e.get("early_swerve_vs_expert_m")
            lines.append(
                f"| {name} | {side} | {e['episodes']} | {e['success']:.3f} | {e['collision']:.3f} "
                f"({ph['closing']:.3f} / {ph['alongside']:.3f} / {ph['cutting back']:.3f}) | {e['off_lane']:.3f} | "
                f"{e['over_rotation']:.3f} | {e['early_swerve_m']:.2f} | {'' if vs is None else f'{vs:+.2f}'} |"
            )
    return lines


def main() -> None:
    """Read the eval folders, print and write the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--eval", action="append", required=True, metavar="NAME=FOLDER", help="an eval folder")
    parser.add_argument("--out", type=Path, default=None, help="write the JSON here (and .md beside it)")
    args = parser.parse_args()
    folders = dict(item.split("=", 1) for item in args.eval)
    loaded = {name: load_episodes(Path(folder)) for name, folder in folders.items()}
    expert = loaded.get("expert")
    results = {name: summarize(eps, None if name == "expert" else expert) for name, eps in loaded.items()}
    lines = markdown(results)
    print("\n".join(lines))
    if args.out:
        args.out.write_text(json.dumps({"evals": folders, "results": results}, indent=1))
        args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
