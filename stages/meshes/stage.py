"""The meshes stage under the stage contract: `SPEC`, its typed summary and `run_meshes`.

Light to import; the work is in `stages/meshes/build.py` (trimesh), imported when the stage runs.
"""

from __future__ import annotations

from pathlib import Path

from drivesim.pipeline.stage import StageResult, StageSpec, deferred_build, run_stage
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.meshes.config import MeshesConfig
from drivesim.stages.meshes.summary import MeshesSummary

SPEC: StageSpec[MeshesSummary] = StageSpec(
    name="meshes",
    artifact="meshes",
    command="drivesim meshes build",
    config_model=MeshesConfig,
    summary_model=MeshesSummary,
    build=deferred_build("drivesim.stages.meshes.build:build_meshes"),  # trimesh
)


def run_meshes(ws: Workspace, cfg: MeshesConfig, force: bool = False) -> StageResult[MeshesSummary]:
    """Build `<ws>/meshes/` (atomically; no-op when fresh unless `force`). Imported files are external inputs."""
    external = {f"import-{i}": Path(imp.path) for i, imp in enumerate(cfg.imports)}
    return run_stage(ws, SPEC, cfg, force=force, external=external)


def current_imports(ws: Workspace) -> list[dict]:
    """The imports recorded in the workspace's meshes artifact (empty when there is none)."""
    manifest = ws.read_manifest(SPEC.artifact) or {}
    return list((manifest.get("config") or {}).get("imports", []))
