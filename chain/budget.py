"""`drivesim run`'s budget for the whole chain: training gets the wall time the stages before it left, less what the
stages after it need.

A run preset's `chain` section (beside the stages' sections):

    chain: {budget_s: 3600, after_training_s: 420}

The stages before training (depth above all) take minutes to most of an hour depending on the drive, the depth
method and the machine; a fixed training time limit then either overruns the hour or leaves it unused. With a budget,
training stops at `start + budget_s - after_training_s` (and at the train config's own `time_limit_s`, whichever
comes first), and its learning rates anneal over that. The deadline is not part of the train config, so a re-run of
the chain still finds its finished run, or continues its unfinished one until the new run's deadline.
"""

from __future__ import annotations

from typing import Any

from pydantic import Field, ValidationError

from drivesim.pipeline.config import ConfigSection, validation_line
from drivesim.pipeline.errors import ConfigError

CHAIN_SECTION = "chain"
"""The run preset's key for the budget (not a stage)."""


class ChainBudget(ConfigSection):
    """The wall-time budget of one `drivesim run`."""

    budget_s: float | None = Field(None, gt=0.0)
    """Wall time of the whole chain, from the command's start to its end [s] (None: each stage's own limits only)."""
    after_training_s: float = Field(420.0, ge=0.0)
    """Kept for what runs after training: its final evaluation, the policy files, eval and export [s]."""
    min_training_s: float = Field(600.0, gt=0.0)
    """Training time given even where the stages before it used up the budget [s] (the chain then overruns it)."""

    def training_stop_by(self, began: float, now: float) -> float | None:
        """The `time.monotonic()` time by which training stops, for a chain that began at `began` and starts
        training at `now`; None without a budget."""
        if self.budget_s is None:
            return None
        return max(began + self.budget_s - self.after_training_s, now + self.min_training_s)


def chain_budget(overrides: dict[str, Any]) -> ChainBudget:
    """The run preset's `chain` section as a ChainBudget (a wrong key or value is one line)."""
    try:
        return ChainBudget.model_validate(overrides.get(CHAIN_SECTION) or {})
    except ValidationError as e:
        raise ConfigError(f"run preset, {CHAIN_SECTION}: {validation_line(e, ChainBudget)}") from e
