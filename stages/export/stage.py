"""The export stage under the stage contract: `SPEC`, its summary, and `run_export` (what the CLI calls).

Artifact `export/`: `policy.onnx` (one graph: uint8 image, LSTM state and episode start in; steering and the new
state out; metadata inside) and `check.json` (torch vs onnxruntime over a rollout with a reset, latency on one core).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from drivesim.pipeline.errors import DrivesimError
from drivesim.pipeline.stage import BuildContext, StageResult, StageSpec, StageSummary, run_stage
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.export.config import ExportConfig

EXPORT_DIR = "export"
ONNX_NAME = "policy.onnx"
CHECK_NAME = "check.json"


class ExportError(DrivesimError):
    """The exported graph does not reproduce the torch policy, or there is no run to export."""


class ExportSummary(StageSummary):
    """What the export made and how well it matches torch."""

    run: str
    """The exported run folder's name."""
    task: str
    """The policy's task."""
    max_abs_diff: float
    """Largest absolute difference of the steering, torch vs onnxruntime, over the check rollout."""
    max_rel_diff_state: float
    """Largest difference of the LSTM state (h, c) relative to its magnitude (at least 1) over the rollout."""
    latency_median_ms: float
    """Median onnxruntime time of one single-episode step on one thread (ms)."""
    latency_p99_ms: float
    """99th percentile of that time (ms)."""
    size_bytes: int
    """Size of policy.onnx."""
    export_s: float
    """Time to write and check the graph (s), without the rollout check and timing."""


def roi_of(env_config: dict[str, Any]) -> list[int] | None:
    """The region of interest (x0, y0, w, h) of the sim image the policy sees, as the run's env config records it
    (training resolves it; null for a run over worlds whose regions differ, or whose region is given in degrees:
    then `env_config.roi_fov_deg` and `roi_horizon_fraction` place it on the camera, `drivesim.sim.envs.roi`)."""
    roi = env_config.get("roi_px")
    return None if roi is None else [int(v) for v in roi]


def policy_metadata(policy: Any) -> dict[str, Any]:
    """The ONNX metadata of a LoadedPolicy: task, input, region of interest, action scale, config hash, env config."""
    action = dict(policy.info.get("action") or {})
    return {
        "task": policy.task,
        "run": policy.run_dir.name,
        "observation_shape": list(policy.observation_shape),
        "observation_dtype": "uint8",
        "roi_px": roi_of(policy.env_config),
        "action_scale": {
            "low": action.get("low", -1.0),
            "high": action.get("high", 1.0),
            "max_curvature_1pm": action.get("max_curvature_1pm"),
        },
        "config_hash": policy.config_hash,
        "env_config": policy.env_config,
    }


def _build(ctx: BuildContext) -> ExportSummary:
    import numpy as np

    from drivesim.policy.onnx_runtime import OnnxPolicy
    from drivesim.policy.run_folder import load_policy
    from drivesim.stages.export.onnx_export import check_images, compare_rollout, export_onnx, time_steps

    cfg = ctx.config
    assert isinstance(cfg, ExportConfig)
    policy = load_policy(ctx.external["run"])
    module = policy.export_module()
    path = ctx.dir / ONNX_NAME
    began = time.perf_counter()
    export_onnx(module, policy.observation_shape, policy_metadata(policy), path, opset=cfg.opset)
    export_s = time.perf_counter() - began

    onnx_policy = OnnxPolicy(path)
    rng = np.random.default_rng(cfg.seed)
    images = check_images(rng, cfg.check_steps, cfg.check_episodes, policy.observation_shape)
    check = compare_rollout(module, onnx_policy, images, cfg.check_reset_step)
    max_abs_diff = float(check["max_abs_diff_action"])
    state_diff = float(check["max_rel_diff_state"])
    if not (max_abs_diff <= cfg.tolerance and state_diff <= cfg.tolerance):  # also catches NaN
        raise ExportError(
            f"onnxruntime differs from torch by {max_abs_diff:.3g} in the steering and {state_diff:.3g} "
            f"(relative) in the LSTM state, over tolerance {cfg.tolerance:g} in the {cfg.check_steps}-step check; "
            "nothing was written",
            policy.run_dir,
        )
    timing_images = check_images(rng, cfg.latency_steps, 1, policy.observation_shape)[:, 0]
    latency = time_steps(onnx_policy, timing_images)
    size = path.stat().st_size
    (ctx.dir / CHECK_NAME).write_text(
        json.dumps(
            {
                "run": str(policy.run_dir),
                "max_abs_diff": max_abs_diff,
                "tolerance": cfg.tolerance,
                "rollout": check,
                "latency": {**latency, "budget_ms_at_30hz": 1000.0 / 30},
                "size_bytes": size,
                "export_s": export_s,
            },
            indent=2,
        )
        + "\n"
    )
    ctx.notes.append(
        f"torch vs onnxruntime over {cfg.check_steps} steps with a reset: max abs diff {max_abs_diff:.2g}; "
        f"{latency['median_ms']:.2f} ms per step on one thread (30 Hz budget 33 ms)"
    )
    return ExportSummary(
        run=policy.run_dir.name,
        task=policy.task,
        max_abs_diff=max_abs_diff,
        max_rel_diff_state=state_diff,
        latency_median_ms=float(latency["median_ms"]),
        latency_p99_ms=float(latency["p99_ms"]),
        size_bytes=size,
        export_s=export_s,
    )


SPEC: StageSpec[ExportSummary] = StageSpec(
    name="export",
    artifact=EXPORT_DIR,
    command="drivesim export onnx",
    config_model=ExportConfig,
    summary_model=ExportSummary,
    build=_build,  # requires no artifact: the run folder is one of many under runs/, passed as an external input
)


def resolve_run(ws: Workspace, cfg: ExportConfig) -> Path:
    """The run folder to export: `cfg.run`, else the workspace's newest finished run (ExportError when none)."""
    from drivesim.policy.run_folder import latest_run

    if cfg.run is not None:
        run = Path(cfg.run)
        if not run.is_absolute() and not run.exists() and (ws.root / run).exists():
            run = ws.root / run
        return run.absolute()
    newest = latest_run(ws)
    if newest is None:
        raise ExportError(f"no finished training run in {ws.root / 'runs'}; run `drivesim train` first or give --run")
    return newest


def run_export(ws: Workspace, cfg: ExportConfig, force: bool = False) -> StageResult[ExportSummary]:
    """Export `cfg.run` (default: the newest finished run) into `export/` with its checks."""
    run = resolve_run(ws, cfg)
    if not run.is_dir():
        raise ExportError("no such run folder", run)
    cfg = cfg.model_copy(update={"run": str(run)})
    return run_stage(ws, SPEC, cfg, force=force, external={"run": run})
