"""Overtaking success by pass side over all episodes, for several policies evaluated on the same seeds: the eval's
own "passing on the left / right" scenarios (its metrics.json), side by side.

    python3 experiments/real_gap/by_side.py expert=WS/eval/E final=WS/eval/F ...
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

SIDES = ("passing on the left", "passing on the right")


def success_by_side(folder: Path) -> list[tuple[float, int]]:
    """(success rate, episodes) per side of `SIDES`, from an eval folder's metrics.json."""
    scenarios = {s["scenario"]: s for s in json.loads((folder / "metrics.json").read_text())["scenarios"]}
    return [(scenarios[side]["success"]["value"], scenarios[side]["episodes"]) for side in SIDES]


def main(args: list[str]) -> int:
    print("| policy | pass left | pass right |\n|---|---:|---:|")
    for arg in args:
        name, folder = arg.split("=", 1)
        cells = " | ".join(f"{rate:.3f} ({n})" for rate, n in success_by_side(Path(folder)))
        print(f"| {name} | {cells} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
