"""The best policy of a run: the weights of the periodic evaluation with the highest success rate so far.

PPO on a task whose reward and success disagree for a while can drift after its best evaluation (the overtake
curves of experiments/learning did), so a run keeps those weights in `checkpoints/best.pt` and, with
`eval.keep_best`, writes them as the run's policy. Ties on success go to the higher mean return, then to the
later evaluation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from drivesim.stages.train.run_files import torch_save_atomic

BEST_CHECKPOINT = "best.pt"


@dataclass
class BestPolicy:
    """Tracks the best evaluation of a run and keeps its weights.

    :param path: the checkpoint file (checkpoints/best.pt).
    :param success_rate: eval success rate of the kept weights (None: nothing kept yet).
    :param return_mean: their eval mean return.
    :param steps: env steps at which they were evaluated.
    """

    path: Path
    success_rate: float | None = None
    return_mean: float = float("-inf")
    steps: int = -1

    @classmethod
    def load(cls, path: Path) -> BestPolicy:
        """The tracker of a run folder, with the score of the weights already kept there (a resumed run)."""
        if not path.is_file():
            return cls(path)
        kept = torch.load(path, map_location="cpu", weights_only=True)
        return cls(path, float(kept["eval_success_rate"]), float(kept["eval_return_mean"]), int(kept["num_timesteps"]))

    def offer(self, figures: dict[str, Any], steps: int, checkpoint: Callable[[], dict[str, Any]]) -> bool:
        """Keep `checkpoint()` (weights and statistics) when the evaluation `figures` (eval_success_rate,
        eval_return_mean) beat the kept ones; True when kept."""
        if "eval_success_rate" not in figures:
            return False
        success, ret = float(figures["eval_success_rate"]), float(figures.get("eval_return_mean", float("-inf")))
        if self.success_rate is not None and (success, ret) < (self.success_rate, self.return_mean):
            return False
        torch_save_atomic(
            self.path, {**checkpoint(), "num_timesteps": steps, "eval_success_rate": success, "eval_return_mean": ret}
        )
        self.success_rate, self.return_mean, self.steps = success, ret, steps
        return True

    def weights(self) -> dict[str, Any]:
        """The kept checkpoint (policy weights under "policy", return statistics)."""
        return torch.load(self.path, map_location="cpu", weights_only=True)
