"""The recordings an evaluation keeps (`drivesim eval --record`): the chosen episodes' MCAPs copied into the
evaluation's folder, those the workers did not write (Ray actors, resumed episodes) replayed first, identically.

Above both `record.py` (the recorder) and `rollout.py` (the episodes), so neither imports the other's caller.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from drivesim.sim.episode_mcap import EpisodeCapture
from drivesim.stages.evaluate.metrics import EpisodeResult
from drivesim.stages.evaluate.record import RECORDINGS_DIR, EpisodeRecorder, RecordPlan, chosen_seeds
from drivesim.stages.evaluate.rollout import env_limits, run_episode


def finish_recordings(
    plan: RecordPlan | None,
    results: Sequence[EpisodeResult],
    env_factory: Any,
    policy_spec: Any,
    task: str,
    out_dir: Path,
) -> list[Path]:
    """Copy the chosen recordings into `out_dir/recordings/` (replaying the missing ones); returns their paths.

    :param plan: what to record (None: nothing).
    :param results: every episode of the evaluation.
    :param env_factory: builds the env for a replay. :param policy_spec: the policy for a replay.
    :param task: the task. :param out_dir: the evaluation's folder.
    """
    if plan is None:
        return []
    chosen = chosen_seeds(plan, results)
    folder = Path(plan.folder)
    missing = [s for s in chosen if not (folder / f"{s}.mcap").is_file()]
    if missing:
        _replay(plan, missing, env_factory, policy_spec, task)
    target = out_dir / RECORDINGS_DIR
    target.mkdir(parents=True, exist_ok=True)
    paths = []
    for seed in chosen:
        paths.append(Path(shutil.copy2(folder / f"{seed}.mcap", target / f"{seed}.mcap")))
    return paths


def _replay(plan: RecordPlan, seeds: Sequence[int], env_factory: Any, policy_spec: Any, task: str) -> None:
    env = env_factory()
    try:
        policy = policy_spec.load(env)
        limits = env_limits(env)
        recorder = EpisodeRecorder(plan, task, limits)
        for seed in seeds:
            capture = EpisodeCapture(seed, task)
            run_episode(env, policy, seed, task, limits, capture=capture)
            recorder.write(capture)
    finally:
        env.close()
