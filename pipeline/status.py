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
from pathlib import Path
from typing import Any

from drivesim.pipeline.hashing import fingerprint_external
from drivesim.pipeline.stage import StageSpec
from drivesim.pipeline.version import code_version
from drivesim.pipeline.workspace import MANIFEST_NAME, Workspace

STATUS_FORMAT_VERSION = 1


def stale_reasons(ws: Workspace, manifest: dict[str, Any]) -> list[str]:
    """Why an existing artifact no longer matches its inputs or code (empty when fresh)."""
    reasons = []
    if manifest.get("code_version") != code_version():
        reasons.append(f"made by drivesim {manifest.get('code_version')}, this is {code_version()}")
    for name, ref in manifest.get("inputs", {}).items():
        if ref["kind"] == "artifact":
            upstream = ws.read_manifest(ref["path"])
            if upstream is None:
                reasons.append(f"input {ref['path']} is missing")
            elif upstream.get("artifact_hash") != ref["hash"]:
                reasons.append(f"input {ref['path']} changed")
        else:
            path = Path(ref["path"])
            if not path.exists():
                reasons.append(f"input {name} {path} is gone")
            elif fingerprint_external(path) != ref["hash"]:
                reasons.append(f"input {name} {path} changed")
    folder = ws.artifact_dir(manifest.get("artifact", ""))
    for rel, meta in manifest.get("outputs", {}).items():
        file = folder / rel
        if not file.is_file() or file.stat().st_size != meta.get("size_bytes"):
            reasons.append(f"file {rel} is missing or changed")
            break
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
        reasons = stale_reasons(ws, manifest)
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
