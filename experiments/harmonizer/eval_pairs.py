"""Intervention and success of the same trained policy evaluated twice on the same seeds: with the cars harmonized
as it was trained (statistical) and with the learned harmonizer (`--set env.harmonizer=learned`).

    .venv/bin/python experiments/harmonizer/eval_pairs.py --pair NAME=OLD_EVAL,NEW_EVAL ...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def figures(folder: Path) -> tuple[dict, float, str]:
    """(intervention with its interval, success, the harmonizer the evaluation drew with) of an eval folder."""
    metrics = json.loads((folder / "metrics.json").read_text())
    if "env" in metrics:  # the settings the episodes ran with (a run's own env config, then the overrides)
        harmonizer = metrics["env"].get("harmonizer", "statistical")
    else:  # older folders: the overrides only, right for policies trained with the statistical harmonizer
        manifest = (folder / "manifest.json").read_text()
        harmonizer = "learned" if '"harmonizer": "learned"' in manifest else "statistical"
    aggregate = metrics["aggregate"]
    return aggregate["intervention"], aggregate["success"]["value"], harmonizer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pair", action="append", required=True, help="NAME=OLD_EVAL,NEW_EVAL (repeatable)")
    parser.add_argument("--out", type=Path, default=None, help="also write the table to this markdown file")
    args = parser.parse_args()
    lines = [
        "| drive | harmonizer in evaluation | intervention [95 % CI] | success |",
        "|---|---|---|---:|",
    ]
    for pair in args.pair:
        name, folders = pair.split("=", 1)
        for folder in folders.split(","):
            iv, success, harmonizer = figures(Path(folder))
            lines.append(
                f"| {name} | {harmonizer} | {iv['value']:.3f} [{iv['ci_low']:.3f}, {iv['ci_high']:.3f}] | "
                f"{100 * success:.1f} % |"
            )
    print("\n".join(lines))
    if args.out is not None:
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
