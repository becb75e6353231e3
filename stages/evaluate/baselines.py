"""The baselines an evaluation shows beside a trained policy: the privileged expert and the run's warm start (its
`checkpoints/warm_start.pt`, the policy before any PPO update), each on the evaluation's first
`baseline_episodes` seeds, with the policy's own figures on those same seeds.

Their episodes are written into the evaluation's work folder (`baselines/<key>/episodes/`), so an interrupted
evaluation resumes them too; their figures go to metrics.json's `baselines` rows and the report's table.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivesim.stages.evaluate.metrics import EpisodeResult, aggregate

BASELINES_DIR = "baselines"
WARM_START_CHECKPOINT = Path("checkpoints") / "warm_start.pt"
ROW_METRICS = (
    "intervention",
    "success",
    "collision",
    "off_lane",
    "over_rotation",
    "min_clearance_m",
    "max_deviation_m",
    "max_yaw_rad",
)
"""The figures of every Table I row (each an estimate with its 95 % interval)."""


@dataclass(frozen=True)
class Baseline:
    """One baseline policy: its row label, the policy text `PolicySpec.parse` reads, its work folder's name."""

    label: str
    policy: str
    key: str


def baselines_for(policy_kind: str, policy_path: str | None) -> list[Baseline]:
    """The baselines beside a policy: the expert beside anything but the expert itself, and beside a run folder (or
    one of its checkpoints other than the warm start) the run's warm start when the run kept one."""
    found: list[Baseline] = []
    if policy_kind != "expert":
        found.append(Baseline("expert", "expert", "expert"))
    if policy_kind == "run" and policy_path is not None:
        path = Path(policy_path)
        run_dir = path.parent.parent if path.suffix == ".pt" else path
        warm = run_dir / WARM_START_CHECKPOINT
        if warm.is_file() and path.resolve() != warm.resolve():
            found.append(Baseline("warm start", str(warm), "warm_start"))
    return found


def figures(results: Sequence[EpisodeResult]) -> dict[str, Any]:
    """`episodes` and the `ROW_METRICS` estimates (JSON) of a set of episodes."""
    agg = aggregate([r.metrics for r in results])
    return {"episodes": len(results), **{k: agg[k].to_json() for k in ROW_METRICS}}


def baseline_rows(
    policy_label: str, policy_results: Sequence[EpisodeResult], ran: Sequence[tuple[Baseline, list[EpisodeResult]]]
) -> list[dict[str, Any]]:
    """metrics.json's `baselines`: the policy on the baselines' seeds first, then each baseline, all on the same
    seeds; [] without baselines."""
    if not ran:
        return []
    seeds = [r.metrics.seed for r in ran[0][1]]
    wanted = set(seeds)
    same = [r for r in policy_results if r.metrics.seed in wanted]
    rows = [{"row": f"{policy_label} (same seeds)", "policy": policy_label, **figures(same)}]
    for baseline, results in ran:
        rows.append({"row": baseline.label, "policy": baseline.policy, **figures(results)})
    first, last = (seeds[0], seeds[-1]) if seeds else (None, None)
    for row in rows:
        row["seeds"] = [first, last]
    return rows
