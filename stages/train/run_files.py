"""Writing a run folder's files: policy weights and description, checkpoints, progress.csv, curves.png.

(The folder's layout is documented in `policy/run_folder.py`, which reads it.) Every file is written to a
temporary sibling and moved into place, so a kill at any moment leaves the previous version whole.
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import Any

import torch

from drivesim.policy.net import STANDARDIZE_EPS
from drivesim.policy.run_folder import NORMALIZATION_JSON, POLICY_JSON, POLICY_WEIGHTS

CHECKPOINTS = "checkpoints"
LAST_CHECKPOINT = "last.pt"
WARM_START_CHECKPOINT = "warm_start.pt"
PROGRESS_CSV = "progress.csv"
CURVES_PNG = "curves.png"


def write_atomic(path: Path, data: bytes) -> None:
    """Write bytes to `path` through a temporary sibling and os.replace."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def write_json(path: Path, value: Any) -> None:
    """Write JSON (indented) atomically."""
    write_atomic(path, (json.dumps(value, indent=2, default=str) + "\n").encode())


def torch_save_atomic(path: Path, value: Any) -> None:
    """torch.save to `path` atomically (the value must hold only tensors, numbers, strings, lists and dicts)."""
    buffer = io.BytesIO()
    torch.save(value, buffer)
    write_atomic(path, buffer.getvalue())


def write_policy_files(
    run_dir: Path,
    task: str,
    observation_shape: tuple[int, ...],
    arch: dict[str, Any],
    net_state: dict[str, torch.Tensor],
    max_curvature_1pm: float | None,
    reward_normalization: dict[str, Any] | None = None,
) -> None:
    """policy.json, normalization.json and policy.pt (DrivingNet weights) of a run.

    normalization.json: the observations' per-image standardization (inside the network; nothing to fit) and the
    training-only reward normalization's running return statistics (not needed to act).
    """
    normalization = {
        "kind": "per_image_standardization",
        "pool": int(arch.get("input_pool", 1)),
        "std_floor": STANDARDIZE_EPS,
        "note": "inside the network: average-pool by `pool`, minus the image's mean, over max(its std, "
        "std_floor * 255)",
    }
    write_json(
        run_dir / POLICY_JSON,
        {
            "format": 1,
            "task": task,
            "observation_shape": list(observation_shape),
            "observation_dtype": "uint8",
            "architecture": arch,
            "action": {
                "low": -1.0,
                "high": 1.0,
                "max_curvature_1pm": max_curvature_1pm,
                "meaning": "normalized steering: curvature = action * max_curvature_1pm",
            },
            "normalization": normalization,
        },
    )
    write_json(run_dir / NORMALIZATION_JSON, {"observation": normalization, "reward": reward_normalization or {}})
    torch_save_atomic(run_dir / POLICY_WEIGHTS, {k: v.contiguous() for k, v in net_state.items()})


def read_progress(path: Path, up_to_steps: int | None = None) -> list[dict[str, str]]:
    """Rows of progress.csv (those at or below `up_to_steps` env steps when given: a resumed run drops the rest)."""
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if up_to_steps is not None:
        rows = [r for r in rows if float(r.get("steps") or 0) <= up_to_steps]
    return rows


def write_progress(path: Path, rows: list[dict[str, Any]]) -> None:
    """Rewrite progress.csv with the union of the rows' columns (new reward terms may appear later)."""
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=columns, restval="")
    writer.writeheader()
    writer.writerows(rows)
    write_atomic(path, out.getvalue().encode())


def _column(rows: list[dict[str, Any]], key: str) -> tuple[list[float], list[float], list[float]]:
    steps, wall, values = [], [], []
    for row in rows:
        value = row.get(key)
        if value in (None, ""):
            continue
        steps.append(float(row["steps"]))
        wall.append(float(row["wall_s"]) / 60.0)
        values.append(float(value))
    return steps, wall, values


def plot_curves(rows: list[dict[str, Any]], path: Path, title: str) -> None:
    """curves.png: return, success and each termination cause (training and evaluation) against steps and time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(rows[0]) if rows else []
    for row in rows:
        keys += [k for k in row if k not in keys]
    panels = [
        ("return", ["ep_return_mean", "eval_return_mean"]),
        ("success rate", ["ep_success_rate", "eval_success_rate"]),
        ("termination rate", [k for k in keys if k.startswith(("term_", "eval_term_"))]),
    ]
    fig, axes = plt.subplots(len(panels), 2, figsize=(11, 8), squeeze=False)
    for i, (name, columns) in enumerate(panels):
        for column in columns:
            steps, wall, values = _column(rows, column)
            if not values:
                continue
            style = "o--" if column.startswith("eval_") else "-"
            axes[i][0].plot(steps, values, style, label=column, markersize=3)
            axes[i][1].plot(wall, values, style, label=column, markersize=3)
        axes[i][0].set_ylabel(name)
        axes[i][0].legend(fontsize=7, loc="best")
        axes[i][0].grid(alpha=0.3)
        axes[i][1].grid(alpha=0.3)
    axes[-1][0].set_xlabel("env steps")
    axes[-1][1].set_xlabel("wall time [min]")
    fig.suptitle(title)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=90)
    plt.close(fig)
    write_atomic(path, buffer.getvalue())
