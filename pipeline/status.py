"""The stage chain and each artifact's state: fresh, stale or missing.

`drivesim status --json` prints `status_report()`, a stable format (version 1) that scripts may read:
    {"format": 1, "workspace": str, "stages": [
        {"stage": str, "artifact": str, "state": "fresh" | "stale" | "missing",
         "reasons": [str, ...], "created_utc": str | null, "summary": {...}}, ...]}
`summary` is what the stage recorded in its manifest (for the trace: frame_count, duration_s, width_px,
height_px, sensors: {name: {"topic": str, "type": str, "message_count": int}}).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivesim.pipeline.hashing import fingerprint_external
from drivesim.pipeline.version import code_version
from drivesim.pipeline.workspace import Workspace

STATUS_FORMAT_VERSION = 1


@dataclass(frozen=True)
class StageInfo:
    """One stage of the chain: the command, the artifact it writes, and how a user makes it."""

    stage: str
    artifact: str
    make_hint: str


CHAIN: tuple[StageInfo, ...] = (
    StageInfo("ingest", "trace", "drivesim ingest PATH"),
    StageInfo("preprocess", "preprocessed", "drivesim preprocess"),
    StageInfo("build-world", "world", "drivesim build-world"),
    StageInfo("meshes", "meshes", "drivesim meshes build"),
    StageInfo("train", "runs", "drivesim train overtake"),
    StageInfo("eval", "eval", "drivesim eval"),
    StageInfo("export", "export", "drivesim export onnx"),
)


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
        if not file.is_file() or file.stat().st_size != meta["size_bytes"]:
            reasons.append(f"file {rel} is missing or changed")
            break
    return reasons


def status_report(ws: Workspace) -> dict[str, Any]:
    """Every stage of the chain with its state, reasons and the summary its manifest recorded."""
    stages = []
    for info in CHAIN:
        manifest = ws.read_manifest(info.artifact)
        if manifest is None:
            stages.append(
                {
                    "stage": info.stage,
                    "artifact": info.artifact,
                    "state": "missing",
                    "reasons": [f"run `{info.make_hint}`"],
                    "created_utc": None,
                    "summary": {},
                }
            )
            continue
        reasons = stale_reasons(ws, manifest)
        stages.append(
            {
                "stage": info.stage,
                "artifact": info.artifact,
                "state": "stale" if reasons else "fresh",
                "reasons": reasons,
                "created_utc": manifest.get("created_utc"),
                "summary": manifest.get("summary", {}),
            }
        )
    return {"format": STATUS_FORMAT_VERSION, "workspace": str(ws.root), "stages": stages}
