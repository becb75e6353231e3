"""Overtaking success by pass side over all episodes, for several policies evaluated on the same seeds.

Left: the front car starts right of the lane centre (other_lateral_m < 0), so the ego passes on its left.

    python3 experiments/real_gap/by_side.py expert=WS/eval/E final=WS/eval/F ...
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path


def success_by_side(folder: Path) -> dict[str, tuple[float, int]]:
    """Side -> (success rate, episodes) from an eval folder's episodes.csv."""
    with open(folder / "episodes.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    out = {}
    for side in ("left", "right"):
        chosen = [r for r in rows if (float(r["other_lateral_m"]) < 0) == (side == "left")]
        won = sum(r["success"] == "True" for r in chosen)
        out[side] = (won / max(len(chosen), 1), len(chosen))
    return out


def main(args: list[str]) -> int:
    print("| policy | pass left | pass right |\n|---|---:|---:|")
    for arg in args:
        name, folder = arg.split("=", 1)
        sides = success_by_side(Path(folder))
        print(f"| {name} | " + " | ".join(f"{rate:.3f} ({n})" for rate, n in sides.values()) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
