"""A slower fake driving env for the Ray tests: episodes long enough (about 0.5 s) that a node can be killed while
its actor is in the middle of one. Importable by Ray workers (the tests put tests/ on their PYTHONPATH)."""

from __future__ import annotations

import time
from typing import Any

import gymnasium
from eval_fakes import FakeDrivingEnv

SLOW_ENV_ID = "drivesim-test/SlowFakeOvertake-v0"
SLOW_ENTRY_POINT = "ray_fakes:SlowFakeDrivingEnv"


class SlowFakeDrivingEnv(FakeDrivingEnv):
    """FakeDrivingEnv (same episodes for the same seeds) whose every step also waits `STEP_DELAY_S`."""

    STEP_DELAY_S = 0.004

    def step(self, action: Any):
        time.sleep(self.STEP_DELAY_S)
        return super().step(action)


def register_slow_env() -> None:
    """Register the slow env under its test id (idempotent)."""
    if SLOW_ENV_ID not in gymnasium.registry:
        gymnasium.register(SLOW_ENV_ID, entry_point=SLOW_ENTRY_POINT)
