"""A slow fake driving env for the signal tests: eval_fakes' FakeDrivingEnv with a pause in each step, so an
evaluation is still running when the test kills it."""

from __future__ import annotations

import time

from eval_fakes import FakeDrivingEnv

STEP_PAUSE_S = 0.015
"""Pause per step: an episode of up to 120 steps lasts about 1.8 s."""


class SlowFakeDrivingEnv(FakeDrivingEnv):
    """FakeDrivingEnv that takes STEP_PAUSE_S per step."""

    def step(self, action):
        time.sleep(STEP_PAUSE_S)
        return super().step(action)
