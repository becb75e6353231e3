"""Overtaking success by the ego's speed over the front car's, for several policies evaluated on the same seeds.

A slow pass keeps the front car beside the ego, out of the camera's view, for seconds before the ego may return to
its lane: a policy that forgets the car cuts back into it. Per policy and relative-speed band: episodes, success, and
the collisions that happen with the ego's centre already ahead of the front car's ("cut back"), with the median time
from the moment the ego's centre drew level to the hit.

    .venv/bin/python experiments/real_gap/by_relative_speed.py --eval expert=WS/eval/E --eval final=WS/eval/F ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

BANDS_MPS = ((0.0, 2.0), (2.0, 4.0), (4.0, 6.0), (6.0, 11.0))


def episode_rows(folder: Path) -> list[dict[str, float]]:
    """Per episode of an eval folder: relative speed (m/s), success, cut-back collision, seconds from level to hit."""
    rows = []
    for path in sorted((folder / "episodes").glob("*.json")):
        record = json.loads(path.read_text())
        start, trajectory = record["episode"], record["trajectory"]
        margin_m = np.asarray(trajectory["pass_margin_m"], dtype=float)
        t_s = np.asarray(trajectory["t_s"], dtype=float)
        cut_back = bool(record["termination"]["collision"]) and margin_m[-1] >= 0.0
        level = np.flatnonzero(margin_m >= 0.0)
        rows.append({
            "relative_mps": start["ego_speed_mps"] - start["other_speed_mps"],
            "success": float(record["success"]),
            "cut_back": float(cut_back),
            "level_to_hit_s": float(t_s[-1] - t_s[level[0]]) if cut_back else np.nan,
        })  # fmt: skip
    return rows


def table(evals: dict[str, Path]) -> list[str]:
    """Markdown lines: a row per policy and relative-speed band."""
    lines = [
        "| policy | relative speed (m/s) | episodes | success | cut-back collisions | level to hit, median (s) |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for name, folder in evals.items():
        rows = episode_rows(folder)
        rel = np.array([r["relative_mps"] for r in rows])
        for low, high in (*BANDS_MPS, (0.0, 99.0)):
            band = [r for r, v in zip(rows, rel, strict=True) if low <= v < high]
            if not band:
                continue
            hits = [r["level_to_hit_s"] for r in band if r["cut_back"]]
            label = "all" if high == 99.0 else f"{low:.0f}-{high:.0f}"
            lines.append(
                f"| {name} | {label} | {len(band)} | {np.mean([r['success'] for r in band]):.3f} | "
                f"{np.mean([r['cut_back'] for r in band]):.3f} | {np.median(hits) if hits else float('nan'):.1f} |"
            )
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--eval", action="append", required=True, help="NAME=EVAL_FOLDER (repeatable)")
    parser.add_argument("--out", type=Path, default=None, help="also write the table to this markdown file")
    args = parser.parse_args()
    evals = {name: Path(folder) for name, folder in (item.split("=", 1) for item in args.eval)}
    lines = table(evals)
    print("\n".join(lines))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
