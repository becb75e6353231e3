"""Learning rates annealed over the run's budget.

With a constant learning rate the policy keeps moving by about as much at its last update as at any other, so the
final weights are one draw from a wide band: consecutive checkpoints of one run can differ by several points of
intervention. Falling linearly to a fraction of the start over the budget (as PPO's own Atari runs anneal to zero)
lets the last updates settle. The budget is the run's env steps or its training time limit, whichever is the further
spent, so a time-limited run anneals on the clock; the warm start's time counts as spent, as it does for the limit.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from drivesim.stages.train.config import TrainConfig

__all__ = ["anneal_learning_rates", "budget_spent", "learning_rate_factor"]


def budget_spent(steps: int, total_steps: int, wall_s: float, time_limit_s: float | None) -> float:
    """Share of the run's budget spent, in [0, 1]: env steps or training time, whichever is further."""
    spent = steps / max(total_steps, 1)
    if time_limit_s:
        spent = max(spent, wall_s / time_limit_s)
    return min(max(spent, 0.0), 1.0)


def learning_rate_factor(spent: float, end_fraction: float) -> float:
    """The learning rate's multiple of its start after `spent` of the budget: 1 falling linearly to `end_fraction`."""
    return 1.0 - (1.0 - end_fraction) * spent


def anneal_learning_rates(
    model: Any, cfg: TrainConfig, wall_s: Callable[[], float], time_limit_s: float | None = None
) -> None:
    """Make `model`'s PPO learning rate and those of its update phases (the hooks holding an `optimizer`: the imitation
    regularizer, the lane target) follow the budget spent, down to `cfg.ppo.learning_rate_end_fraction` of their
    start at its end; nothing changes when that is 1.

    :param model: the ChunkedRecurrentPPO, its update phases already added. :param cfg: the run's config.
    :param wall_s: the run's training wall time so far, across resumes [s].
    :param time_limit_s: the run's training time limit [s] where it is not cfg.time_limit_s (a chain's budget).
    """
    learning_rate, end_fraction = cfg.ppo.learning_rate, cfg.ppo.learning_rate_end_fraction
    limit_s = cfg.time_limit_s if time_limit_s is None else time_limit_s
    if end_fraction >= 1.0:
        return

    def factor() -> float:
        spent = budget_spent(model.num_timesteps, cfg.total_steps, wall_s(), limit_s)
        return learning_rate_factor(spent, end_fraction)

    # SB3 reads lr_schedule at the start of every update (`_update_learning_rate`); its own progress counts steps only
    model.lr_schedule = lambda _progress_remaining: learning_rate * factor()
    phases = [
        (hook.optimizer, [group["lr"] for group in hook.optimizer.param_groups])
        for hook in model.update_hooks
        if hasattr(hook, "optimizer")
    ]

    def scale_phases() -> None:
        f = factor()
        for optimizer, start_rates in phases:
            for group, rate in zip(optimizer.param_groups, start_rates, strict=True):
                group["lr"] = rate * f

    model.update_hooks.insert(0, scale_phases)  # before the phases run, after PPO's update
