"""The workspace: one folder per artifact, each written atomically with a manifest.json.

Layout (DESIGN §2): `trace/`, `preprocessed/`, `world/`, `meshes/`, `runs/<task>-<timestamp>/`, `eval/<name>/`,
`export/`. An artifact is built in a hidden temporary sibling (`.tmp-<name>-...`) and moved into place with
`os.replace` only after its manifest is written, so a crash or Ctrl-C never leaves a half-written artifact.

`manifest.json` (stable; scripts may read it):
    stage          str    the stage that wrote it ("ingest", "preprocess", ...)
    artifact       str    the artifact's folder name relative to the workspace ("trace")
    code_version   str    drivesim version that wrote it
    config         dict   the resolved stage config
    config_hash    str    sha256 of that config (canonical JSON)
    inputs         dict   name -> {"kind": "artifact"|"external", "path": str, "hash": str}
                          (artifact paths relative to the workspace, external paths absolute)
    outputs        dict   relative file path -> {"size_bytes": int, "sha256": str}
    artifact_hash  str    sha256 over the outputs: what downstream manifests record as their input hash
    key            str    sha256 of (stage, code_version, config_hash, inputs): equal key = nothing to redo
    summary        dict   stage-specific figures for `drivesim status`
    created_utc    str    ISO 8601
"""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from drivesim.pipeline.errors import DiskFullError, DrivesimError, MissingArtifactError
from drivesim.pipeline.hashing import fingerprint_external, sha256_file, sha256_json
from drivesim.pipeline.version import code_version

MANIFEST_NAME = "manifest.json"
_TMP_PREFIX = ".tmp-"
_TMP_PID = re.compile(r"-(\d+)-[0-9a-f]{8}(?:-|$)")

DEFAULT_WORKSPACE = Path("drivesim-work")


@dataclass(frozen=True)
class InputRef:
    """One input of an artifact: another artifact of the workspace, or an external file/folder."""

    kind: str
    path: str
    hash: str

    def to_json(self) -> dict[str, str]:
        """The manifest form of this input."""
        return {"kind": self.kind, "path": self.path, "hash": self.hash}


@dataclass
class ArtifactBuild:
    """An artifact being written: files go into `dir`; `summary` is recorded in the manifest."""

    dir: Path
    summary: dict[str, Any] = field(default_factory=dict)


def artifact_key(stage: str, config_hash: str, inputs: dict[str, InputRef]) -> str:
    """The identity of a stage run: equal keys mean the artifact would come out the same."""
    return sha256_json(
        {
            "stage": stage,
            "code_version": code_version(),
            "config_hash": config_hash,
            "inputs": {k: v.to_json() for k, v in sorted(inputs.items())},
        }
    )


class Workspace:
    """A drivesim workspace folder holding one sub-folder per artifact.

    :param root: the workspace folder; created on first write.
    """

    def __init__(self, root: Path | str = DEFAULT_WORKSPACE) -> None:
        self.root = Path(root).absolute()

    def artifact_dir(self, name: str) -> Path:
        """Folder of artifact `name` (it may not exist yet)."""
        return self.root / name

    def read_manifest(self, name: str) -> dict[str, Any] | None:
        """The manifest of artifact `name`, or None when it is missing or unreadable (see `manifest_unreadable`)."""
        path = self.artifact_dir(name) / MANIFEST_NAME
        try:
            manifest = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError):
            return None
        return manifest if manifest_is_valid(manifest) else None

    def manifest_unreadable(self, name: str) -> bool:
        """True when artifact `name` has a manifest.json that is damaged (not JSON, or not a manifest's shape)."""
        return (self.artifact_dir(name) / MANIFEST_NAME).exists() and self.read_manifest(name) is None

    def require(self, name: str, how_to_make: str) -> Path:
        """The folder of an artifact a stage needs, or a clear error saying which command makes it."""
        if self.read_manifest(name) is None:
            if self.manifest_unreadable(name):
                raise MissingArtifactError(
                    f"the {name} artifact's {MANIFEST_NAME} is unreadable (damaged); rebuild it with `{how_to_make}`",
                    self.artifact_dir(name),
                )
            raise MissingArtifactError(f"no {name} artifact in workspace {self.root}; run `{how_to_make}` first")
        return self.artifact_dir(name)

    def artifact_input(self, name: str) -> InputRef:
        """An InputRef to artifact `name` for a downstream manifest."""
        manifest = self.read_manifest(name)
        if manifest is None:
            raise MissingArtifactError(f"no readable {name} artifact in workspace {self.root}; rebuild it")
        return InputRef(kind="artifact", path=name, hash=manifest["artifact_hash"])

    @staticmethod
    def external_input(path: Path) -> InputRef:
        """An InputRef to a recording outside the workspace, identified by a fast fingerprint."""
        return InputRef(kind="external", path=str(Path(path).absolute()), hash=fingerprint_external(Path(path)))

    def is_fresh(self, name: str, key: str) -> bool:
        """True when artifact `name` exists, was made with this key, and its files are all present."""
        manifest = self.read_manifest(name)
        if manifest is None or manifest.get("key") != key:
            return False
        folder = self.artifact_dir(name)
        return all(
            (folder / rel).is_file() and (folder / rel).stat().st_size == meta["size_bytes"]
            for rel, meta in manifest.get("outputs", {}).items()
        )

    def fresh_manifest(
        self, name: str, stage: str, config: dict[str, Any], inputs: dict[str, InputRef]
    ) -> dict[str, Any] | None:
        """The manifest of artifact `name` when it is fresh for this stage, config and inputs, else None."""
        key = artifact_key(stage, sha256_json(config), inputs)
        return self.read_manifest(name) if self.is_fresh(name, key) else None

    def other_settings(self, name: str, config: dict[str, Any], limit: int = 3) -> str:
        """How the config of the existing artifact `name` differs from `config` ("episodes: 1000, here 100"), or ""
        when there is no readable artifact or it was made with the same config."""
        manifest = self.read_manifest(name)
        if manifest is None or not isinstance(manifest.get("config"), dict):
            return ""
        old = manifest["config"]
        if sha256_json(old) == sha256_json(config):
            return ""
        keys = sorted(k for k in set(old) | set(config) if sha256_json(old.get(k)) != sha256_json(config.get(k)))
        shown = [f"{k}: {_short(old.get(k))}, here {_short(config.get(k))}" for k in keys[:limit]]
        return "; ".join(shown) + (f"; and {len(keys) - limit} more" if len(keys) > limit else "")

    def clean_stale_temporaries(self) -> None:
        """Remove temporary folders left by a process that was killed before it could clean up."""
        if not self.root.is_dir():
            return
        for tmp in self.root.glob(f"{_TMP_PREFIX}*"):
            match = _TMP_PID.search(tmp.name)
            if match and _pid_alive(int(match.group(1))):
                continue
            shutil.rmtree(tmp, ignore_errors=True)

    @contextmanager
    def write_artifact(
        self,
        name: str,
        stage: str,
        config: dict[str, Any],
        inputs: dict[str, InputRef],
    ) -> Iterator[ArtifactBuild]:
        """Build artifact `name` in a temporary folder; on success write its manifest and move it into place.

        On any exception, KeyboardInterrupt included, the temporary folder is removed and an existing artifact
        of that name is left as it was.
        """
        self.root.mkdir(parents=True, exist_ok=True)
        self.clean_stale_temporaries()
        safe_name = name.replace("/", "_")
        tmp = self.root / f"{_TMP_PREFIX}{safe_name}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        build = ArtifactBuild(dir=tmp)
        try:
            yield build
            manifest = self._manifest(name, stage, config, inputs, build)
            (tmp / MANIFEST_NAME).write_text(json.dumps(manifest, indent=2, default=str) + "\n")
            self._move_into_place(tmp, self.artifact_dir(name))
        except OSError as e:
            written = _folder_bytes(tmp)
            shutil.rmtree(tmp, ignore_errors=True)
            if e.errno == errno.ENOSPC:
                so_far = f"; {_size_text(written)} of it were written when the disk filled" if written else ""
                raise DiskFullError(
                    f"disk full while writing the {name} artifact{so_far}; {_size_text(_free_bytes(self.root))} are "
                    "free there now: free more space (or use --workspace on another disk) and run again (a run or "
                    "an evaluation continues where it stopped); no half-written artifact was kept",
                    self.root,
                ) from e
            raise
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise

    def _manifest(
        self, name: str, stage: str, config: dict[str, Any], inputs: dict[str, InputRef], build: ArtifactBuild
    ) -> dict[str, Any]:
        outputs = {}
        for path in sorted(build.dir.rglob("*")):
            if path.is_file() and path.name != MANIFEST_NAME:
                rel = str(path.relative_to(build.dir))
                outputs[rel] = {"size_bytes": path.stat().st_size, "sha256": sha256_file(path)}
        config_hash = sha256_json(config)
        return {
            "stage": stage,
            "artifact": name,
            "code_version": code_version(),
            "config": config,
            "config_hash": config_hash,
            "inputs": {k: v.to_json() for k, v in sorted(inputs.items())},
            "outputs": outputs,
            "artifact_hash": sha256_json({"outputs": {k: v["sha256"] for k, v in outputs.items()}}),
            "key": artifact_key(stage, config_hash, inputs),
            "summary": build.summary,
            "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        }

    @staticmethod
    def _move_into_place(tmp: Path, final: Path) -> None:
        final.parent.mkdir(parents=True, exist_ok=True)
        old = None
        if final.exists():
            # os.replace cannot replace a non-empty folder: move the old one aside first.
            old = final.with_name(f"{_TMP_PREFIX}old-{os.getpid()}-{uuid.uuid4().hex[:8]}-{final.name}")
            os.replace(final, old)
        try:
            os.replace(tmp, final)
        except OSError as e:
            if old is not None:
                os.replace(old, final)
            raise DrivesimError(f"could not move the new artifact into place: {e}", final) from e
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def _short(value: Any, width: int = 40) -> str:
    text = json.dumps(value, default=str)
    return text if len(text) <= width else text[: width - 3] + "..."


def manifest_is_valid(manifest: Any) -> bool:
    """True when `manifest` has the shape described in this module's docstring (the keys readers index)."""
    if not isinstance(manifest, dict) or not isinstance(manifest.get("artifact_hash"), str):
        return False
    outputs, inputs = manifest.get("outputs", {}), manifest.get("inputs", {})
    if not isinstance(outputs, dict) or not isinstance(inputs, dict):
        return False
    if not all(isinstance(m, dict) and isinstance(m.get("size_bytes"), int) for m in outputs.values()):
        return False
    if not all(
        isinstance(ref, dict) and all(isinstance(ref.get(k), str) for k in ("kind", "path", "hash"))
        for ref in inputs.values()
    ):
        return False
    return all(
        isinstance(manifest.get(k, default), t)
        for k, t, default in (("summary", dict, {}), ("key", str, ""), ("stage", str, ""), ("artifact", str, ""))
    )


def _folder_bytes(folder: Path) -> int:
    """Bytes in the files under `folder` (0 when it cannot be read)."""
    total = 0
    for path in folder.rglob("*"):
        with suppress(OSError):
            total += path.stat().st_size if path.is_file() else 0
    return total


def _size_text(size_bytes: int) -> str:
    return f"{size_bytes / 1e6:.1f} MB" if size_bytes >= 1e6 else f"{size_bytes / 1e3:.0f} kB"


def _free_bytes(folder: Path) -> int:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return 0


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
