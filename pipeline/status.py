"""Each artifact of the stage chain as fresh, stale or missing (the chain itself is `drivesim.chain.registry.CHAIN`).

`drivesim status --json` prints `status_report(ws, CHAIN)`, a stable format (version 1) that scripts may read:
    {"format": 1, "workspace": str, "stages": [
        {"stage": str, "artifact": str, "state": "fresh" | "stale" | "missing",
         "reasons": [str, ...], "created_utc": str | null, "summary": {...}}, ...]}
`summary` is what the stage recorded in its manifest (for the trace: frame_count, duration_s, width_px,
height_px, sensors: {name: {"topic": str, "type": str, "message_count": int}}).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from drivesim.pipeline.stage import StageSpec
from drivesim.pipeline.version import code_version
from drivesim.pipeline.workspace import MANIFEST_NAME, Workspace

STATUS_FORMAT_VERSION = 1


def stale_reasons(ws: Workspace, manifest: dict[str, Any], hints: dict[str, str] | None = None) -> list[str]:
    """Why an existing artifact no longer matches its inputs, its own files or the code (empty when fresh); the last
    reason names the commands that refresh it (`hints`: artifact -> command, over the ones the manifests recorded)."""
    reasons = []
    if manifest.get("code_version") != code_version():
        reasons.append(f"made by drivesim {manifest.get('code_version')}, this is {code_version()}")
    staleness = ws.staleness(manifest.get("artifact", ""), manifest)
    reasons += staleness.reasons
    if staleness.rebuild:
        reasons.append(f"refresh: {ws.refresh_commands(staleness.rebuild, hints)}")
    return reasons


def newest_complete(ws: Workspace, collection: str) -> str | None:
    """The newest complete artifact of a collection (`runs/<task>-<ts>`): a sub-folder with a manifest, or None."""
    folder = ws.artifact_dir(collection)
    if not folder.is_dir():
        return None
    complete = [sub for sub in folder.iterdir() if sub.is_dir() and (sub / MANIFEST_NAME).is_file()]
    if not complete:
        return None
    newest = max(complete, key=lambda sub: ((sub / MANIFEST_NAME).stat().st_mtime, sub.name))
    return f"{collection}/{newest.name}"


def status_report(ws: Workspace, chain: Sequence[StageSpec]) -> dict[str, Any]:
    """Every stage of `chain` (the registry `drivesim.chain.registry.CHAIN`) with its state, reasons and summary.

    A collection stage (many runs or evaluations) shows its newest complete artifact.
    """
    stages = []
    hints = {spec.artifact: spec.command for spec in chain if not spec.collection}
    for spec in chain:
        artifact = (newest_complete(ws, spec.artifact) or spec.artifact) if spec.collection else spec.artifact
        manifest = ws.read_manifest(artifact)
        if manifest is None and ws.manifest_unreadable(artifact):
            stages.append(
                {
                    "stage": spec.name,
                    "artifact": artifact,
                    "state": "stale",
                    "reasons": [f"manifest unreadable; rebuild it with `{spec.command}`"],
                    "created_utc": None,
                    "summary": {},
                }
            )
            continue
        if manifest is None:
            stages.append(
                {
                    "stage": spec.name,
                    "artifact": artifact,
                    "state": "missing",
                    "reasons": [f"run `{spec.command}`"],
                    "created_utc": None,
                    "summary": {},
                }
            )
            continue
        reasons = stale_reasons(ws, manifest, {**hints, artifact: spec.command})
        stages.append(
            {
                "stage": spec.name,
                "artifact": artifact,
                "state": "stale" if reasons else "fresh",
                "reasons": reasons,
                "created_utc": manifest.get("created_utc"),
                "summary": manifest.get("summary", {}),
            }
        )
    return {"format": STATUS_FORMAT_VERSION, "workspace": str(ws.root), "stages": stages}
