"""The train stage's typed summary: the figures it records in its manifest and `drivesim status` shows.

Its own module, so the stage's build code and its `stage.py` (the spec) both import it without a circle.
"""

from __future__ import annotations

from drivesim.pipeline.stage import StageSummary


class TrainSummary(StageSummary):
    """A finished training run."""

    task: str
    """lane, follow or overtake."""
    run: str
    """The run folder's name."""
    steps: int
    """Env steps trained (warm start not counted)."""
    updates: int
    """PPO gradient passes (epochs summed over updates)."""
    episodes: int
    """Training episodes finished."""
    wall_s: float
    """Training wall time across resumes [s]."""
    steps_per_s: float
    """Env steps per second of `learn()` in the last session [1/s]."""
    time_rollout_s: float
    """Time collecting rollouts in the last session (simulator included) [s]."""
    time_simulator_s: float
    """Time inside the envs' step in the last session [s]."""
    time_optimization_s: float
    """Time in PPO updates in the last session [s]."""
    eval_success_rate: float | None = None
    """Success rate of the last evaluation on held-back seeds."""
    eval_return_mean: float | None = None
    """Mean return of the last evaluation."""
    policy_steps: int = 0
    """Env steps of the weights in the run's policy files (the last update's, or the best evaluation's with
    eval.keep_best)."""
    policy_eval_success_rate: float | None = None
    """Success rate on held-back seeds of those weights (None: the last update's weights, not chosen by evaluation)."""
    warm_start: bool = False
    """Whether the policy was warm-started from the expert."""
    worlds: list[str] = []
    """World folders trained on."""
    time_limit_s: float | None = None
    """Training time limit the run stopped at [s]: the config's, or what `drivesim run`'s budget left (None: none)."""
