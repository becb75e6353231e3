"""The export stage's config (`configs/export.yaml` holds only what differs from these defaults)."""

from __future__ import annotations

from drivesim.pipeline.config import StageConfig


class ExportConfig(StageConfig):
    """How `drivesim export onnx` writes and checks the ONNX policy."""

    run: str | None = None
    """The run folder to export; None: the workspace's newest finished run."""
    opset: int = 17
    """ONNX opset version of the graph."""
    check_steps: int = 200
    """Steps of the torch-vs-onnxruntime rollout check."""
    check_reset_step: int = 100
    """Step of the check rollout at which the first episode restarts (episode_start = 1)."""
    check_episodes: int = 2
    """Episodes stepped side by side in the check (only the first one restarts in the middle)."""
    tolerance: float = 1e-4
    """Largest difference torch vs onnxruntime the export accepts: steering (absolute), LSTM state (relative)."""
    latency_steps: int = 300
    """Timed single-episode steps on one onnxruntime thread (after 20 warm-up steps)."""
    seed: int = 0
    """Seed of the check rollout's images."""
