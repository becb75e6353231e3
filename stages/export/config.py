"""The export stage's config (`configs/export.yaml` holds only what differs from these defaults)."""

from __future__ import annotations

from pydantic import Field

from drivesim.pipeline.config import StageConfig


class ExportConfig(StageConfig):
    """How `drivesim export onnx` writes and checks the ONNX policy."""

    run: str | None = None
    """The run folder to export; None: the workspace's newest finished run."""
    opset: int = Field(17, ge=14, le=20)
    """ONNX opset version of the graph (14 to 20: what torch's TorchScript exporter writes for this network)."""
    check_steps: int = Field(200, ge=1)
    """Steps of the torch-vs-onnxruntime rollout check."""
    check_reset_step: int = Field(100, ge=0)
    """Step of the check rollout at which the first episode restarts (episode_start = 1)."""
    check_episodes: int = Field(2, ge=1, le=1024)
    """Episodes stepped side by side in the check (only the first one restarts in the middle)."""
    tolerance: float = Field(1e-4, gt=0.0)
    """Largest difference torch vs onnxruntime the export accepts: steering (absolute), LSTM state (relative)."""
    latency_steps: int = Field(300, ge=1)
    """Timed single-episode steps on one onnxruntime thread (after 20 warm-up steps)."""
    seed: int = Field(0, ge=0)
    """Seed of the check rollout's images."""
