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
    command        str    the command that makes it ("drivesim build-world"), named when it must be rebuilt
    outputs        dict   relative file path -> {"size_bytes": int, "mtime_ns": int, "sha256": str}
    artifact_hash  str    sha256 over the outputs: what downstream manifests record as their input hash
    key            str    sha256 of (stage, code_version, config_hash, inputs): equal key = nothing to redo
    summary        dict   stage-specific figures for `drivesim status`
    created_utc    str    ISO 8601

An artifact's files are checked against its manifest wherever it is read (`require`, `check_folder`) and by
`drivesim status`: size and mtime_ns first (one stat per file), the sha256 only for a file whose mtime moved, so a
file changed after the build is found without hashing gigabytes on every command. An artifact whose files changed,
or whose upstream artifact was rebuilt (or is itself stale) since, is refused by its readers with one line naming the
commands that refresh it.

A stage that writes an artifact holds the workspace's lock on it (`lock`: fcntl.flock on `.locks/<name>.lock`), so a
second command writing the same artifact at the same time stops with one line instead of both writing.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import shutil
import stat
import sys
import uuid
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from drivesim.pipeline.errors import (
    ArtifactBusyError,
    DiskFullError,
    DrivesimError,
    MissingArtifactError,
    StaleArtifactError,
)
from drivesim.pipeline.hashing import fingerprint_external, sha256_file, sha256_json
from drivesim.pipeline.json_files import read_json
from drivesim.pipeline.version import code_version

MANIFEST_NAME = "manifest.json"
_MADE_FROM_THE_TRACE = ("preprocessed", "world")
"""Artifacts made from the recording's trace: where one is missing with no trace either, every step is named."""
_TMP_PREFIX = ".tmp-"
_TMP_PID = re.compile(r"-(\d+)-[0-9a-f]{8}(?:-|$)")

DEFAULT_WORKSPACE = Path("drivesim-work")
LOCKS_DIR = ".locks"
"""Folder of the workspace's lock files, one per artifact being written (`Workspace.lock`)."""
_NO_LOCKS = (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS)
"""flock errors of a file system that has no locks."""
_HELD_LOCKS: dict[Path, int] = {}
"""Lock files this process holds, with how many nested `lock` calls hold each (the lock is re-entrant)."""


@dataclass(frozen=True)
class Staleness:
    """Why an artifact no longer matches what the workspace holds, and what to rebuild.

    :param reasons: why it is stale (empty when it is not).
    :param rebuild: the artifacts to rebuild, upstream first, ending with the artifact itself (empty when fresh).
    """

    reasons: tuple[str, ...] = ()
    rebuild: tuple[str, ...] = ()


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
        self._hashes: dict[tuple[str, int, int], str] = {}  # (path, size, mtime_ns) -> sha256, for one command

    def artifact_dir(self, name: str) -> Path:
        """Folder of artifact `name` (it may not exist yet)."""
        return self.root / name

    def read_manifest(self, name: str) -> dict[str, Any] | None:
        """The manifest of artifact `name`, or None when it is missing or unreadable (see `manifest_unreadable`)."""
        path = self.artifact_dir(name) / MANIFEST_NAME
        try:
            manifest = read_json(path)
        except (OSError, ValueError):  # unreadable, not JSON, nested too deeply, NaN
            return None
        return manifest if manifest_is_valid(manifest) else None

    def manifest_unreadable(self, name: str) -> bool:
        """True when artifact `name` has a manifest.json that is damaged (not JSON, or not a manifest's shape)."""
        return (self.artifact_dir(name) / MANIFEST_NAME).exists() and self.read_manifest(name) is None

    def require(self, name: str, how_to_make: str) -> Path:
        """The folder of an artifact a stage needs, or a clear error saying which command makes it: missing,
        unreadable, changed since it was written, or stale (an upstream artifact rebuilt since, or stale itself)."""
        if self.read_manifest(name) is None:
            if self.manifest_unreadable(name):
                raise MissingArtifactError(
                    f"the {name} artifact's {MANIFEST_NAME} is unreadable (damaged); rebuild it with `{how_to_make}`",
                    self.artifact_dir(name),
                )
            if name in _MADE_FROM_THE_TRACE and self.read_manifest("trace") is None:
                raise MissingArtifactError(
                    f"no {name} artifact in workspace {self.root}, nor a recording read into it: run `drivesim run "
                    "RECORDING` (every stage), or `drivesim ingest RECORDING`, `drivesim preprocess` and "
                    "`drivesim build-world` one by one"
                )
            raise MissingArtifactError(f"no {name} artifact in workspace {self.root}; run `{how_to_make}` first")
        staleness = self.staleness(name, externals=False)
        if staleness.reasons:
            commands = self.refresh_commands(staleness.rebuild, {name: how_to_make})
            raise StaleArtifactError(
                f"the {name} artifact is stale ({'; '.join(staleness.reasons)}); refresh it with {commands}",
                self.artifact_dir(name),
            )
        return self.artifact_dir(name)

    def changed_outputs(self, folder: Path, manifest: dict[str, Any]) -> list[str]:
        """The files of the artifact in `folder` that are missing or differ from what its manifest recorded.

        Size and mtime_ns first (one stat per file); the sha256 only for a file whose mtime moved (a copy, a `touch`,
        a rewrite of the same size, a manifest written before mtimes were recorded), so an unchanged artifact costs no
        hashing. A file whose bytes are the same gets its new mtime recorded, so it is hashed once, not every time.
        """
        changed, same_bytes = [], {}
        for rel, meta in manifest.get("outputs", {}).items():
            path = Path(folder) / rel
            try:
                info = path.stat()
            except OSError:
                changed.append(rel)
                continue
            if not stat.S_ISREG(info.st_mode) or info.st_size != meta.get("size_bytes"):
                changed.append(rel)
            elif info.st_mtime_ns != meta.get("mtime_ns"):
                if self._sha256(path, info) == meta.get("sha256"):
                    same_bytes[rel] = info.st_mtime_ns
                else:
                    changed.append(rel)
        if same_bytes:
            _record_mtimes(Path(folder) / MANIFEST_NAME, same_bytes, manifest)
        return changed

    def _sha256(self, path: Path, info: os.stat_result) -> str:
        key = (str(path), info.st_size, info.st_mtime_ns)
        if key not in self._hashes:
            try:
                self._hashes[key] = sha256_file(path)
            except OSError:
                return ""
        return self._hashes[key]

    def staleness(
        self,
        name: str,
        manifest: dict[str, Any] | None = None,
        *,
        externals: bool = True,
        _seen: dict[str, Staleness] | None = None,
    ) -> Staleness:
        """Why artifact `name` no longer matches the workspace, and what to rebuild (upstream first).

        Stale: an output file changed since it was written; an artifact input missing, rebuilt since (another
        artifact_hash) or itself stale, followed upstream; with `externals`, an external input (a recording) gone or
        changed. Readers pass `externals=False`: an artifact stays a faithful product of the recording it was made
        from when that recording is moved away later. The code version is not checked here (`drivesim status` shows
        it): a new drivesim reads the artifacts of an older one.
        """
        seen = {} if _seen is None else _seen  # each artifact judged once per call; a loop of inputs ends here
        if name in seen:
            return seen[name]
        seen[name] = Staleness()
        manifest = self.read_manifest(name) if manifest is None else manifest
        if manifest is None:
            return Staleness(("manifest missing or unreadable",), (name,))
        reasons: list[str] = []
        rebuild: list[str] = []
        for key, ref in sorted(manifest.get("inputs", {}).items()):
            if ref["kind"] == "artifact":
                upstream = self.read_manifest(ref["path"])
                if upstream is None:
                    reasons.append(f"input {ref['path']} is missing")
                    continue
                up = self.staleness(ref["path"], upstream, externals=externals, _seen=seen)
                if up.reasons:
                    reasons.append(f"input {ref['path']} is stale ({up.reasons[0]})")
                    rebuild += [r for r in up.rebuild if r not in rebuild]
                elif upstream.get("artifact_hash") != ref["hash"]:
                    reasons.append(f"input {ref['path']} changed")
            elif externals:
                path = Path(ref["path"])
                if not path.exists():
                    reasons.append(f"input {key} {path} is gone")
                elif fingerprint_external(path) != ref["hash"]:
                    reasons.append(f"input {key} {path} changed")
        changed = self.changed_outputs(self.artifact_dir(name), manifest)
        if changed:
            more = f" and {len(changed) - 1} more" if len(changed) > 1 else ""
            reasons.append(f"file {changed[0]}{more} changed since it was written")
        seen[name] = Staleness(tuple(reasons), (*rebuild, name) if reasons else ())
        return seen[name]

    def refresh_commands(self, rebuild: tuple[str, ...], hints: dict[str, str] | None = None) -> str:
        """The commands that rebuild `rebuild` in order, as one phrase: "`drivesim preprocess`, then `drivesim
        build-world`". Each artifact's command: from `hints`, else the one its manifest recorded."""
        commands: list[str] = []
        for name in rebuild:
            manifest = self.read_manifest(name) or {}
            command = (hints or {}).get(name) or manifest.get("command") or f"drivesim {manifest.get('stage', name)}"
            if command not in commands:
                commands.append(command)
        return ", then ".join(f"`{c}`" for c in commands)

    def check_input(self, path: Path) -> None:
        """Refuse (one line) an input given by path whose files changed since its artifact's manifest was written:
        an artifact folder (`--world PATH`, a run folder, a mesh library), or one file of an artifact (an ONNX file in
        an export folder, a run's checkpoint). Anything that is not part of an artifact passes unchecked."""
        path = Path(path)
        if path.is_dir():
            self.check_folder(path)
            return
        for folder in (path.parent, path.parent.parent):
            if (folder / MANIFEST_NAME).is_file():
                self.check_folder(folder, only=str(path.relative_to(folder)))
                return

    def check_folder(self, folder: Path, only: str | None = None) -> None:
        """Refuse (one line) an artifact folder given by path whose files (or its file `only`) changed since its
        manifest was written; a folder without a manifest (not an artifact) passes unchecked."""
        folder = Path(folder)
        if not (folder / MANIFEST_NAME).is_file():
            return
        try:
            manifest = read_json(folder / MANIFEST_NAME)
        except (OSError, ValueError):
            manifest = None
        if not manifest_is_valid(manifest):
            return  # no outputs recorded to check against: the folder's own reader (the world loader) judges it
        if only is not None:
            if only not in manifest["outputs"]:
                return
            manifest = {**manifest, "outputs": {only: manifest["outputs"][only]}}
        changed = self.changed_outputs(folder, manifest)
        if changed:
            command = manifest.get("command") or f"drivesim {manifest.get('stage') or 'run'}"
            more = f" (and {len(changed) - 1} more files)" if len(changed) > 1 else ""
            raise StaleArtifactError(
                f"file {changed[0]}{more} changed since the {manifest.get('artifact') or 'this'} artifact was written "
                f"(its size or sha256 differs from {MANIFEST_NAME}); rebuild it with `{command}`",
                folder,
            )

    @contextmanager
    def lock(self, name: str) -> Iterator[None]:
        """Hold the workspace's lock on artifact `name` while writing it: a second process that asks for it stops
        with one line (ArtifactBusyError, exit 2) naming the holder. Re-entrant within a process; released when the
        process ends, however it ends (fcntl.flock)."""
        path = self.root / LOCKS_DIR / f"{name.replace('/', '_')}.lock"
        if path in _HELD_LOCKS:
            _HELD_LOCKS[path] += 1
            try:
                yield
            finally:
                _HELD_LOCKS[path] -= 1
            return
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            if _flock(fd):
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"pid {os.getpid()}: drivesim {' '.join(sys.argv[1:])[:200]}\n".encode(), 0)
            else:
                holder = os.pread(fd, 400, 0).decode(errors="replace").strip() or "another process"
                raise ArtifactBusyError(
                    f"another drivesim ({_printable(holder)}) is writing the {name} artifact of this workspace; "
                    "wait for it to finish (or stop it), or write elsewhere (--workspace, or eval's --name)",
                    self.artifact_dir(name),
                )
            _HELD_LOCKS[path] = 1
            try:
                yield
            finally:
                del _HELD_LOCKS[path]
        finally:
            os.close(fd)  # releases the lock

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
        """True when artifact `name` exists, was made with this key, and its files are as it wrote them."""
        manifest = self.read_manifest(name)
        if manifest is None or manifest.get("key") != key:
            return False
        return not self.changed_outputs(self.artifact_dir(name), manifest)

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
        command: str = "",
    ) -> Iterator[ArtifactBuild]:
        """Build artifact `name` in a temporary folder; on success write its manifest and move it into place.

        `command` is what a user types to make it (recorded, and named when it must be rebuilt).

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
            manifest = _manifest(build, name, stage, config, inputs, command)
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


def _manifest(
    build: ArtifactBuild, name: str, stage: str, config: dict[str, Any], inputs: dict[str, InputRef], command: str
) -> dict[str, Any]:
    """The manifest of the artifact `name` that `build` wrote: what made it (stage, command, code, config, inputs),
    its files with their sizes and hashes, the key that says when it is fresh, and the stage's summary."""
    outputs = {}
    for path in sorted(build.dir.rglob("*")):
        if path.is_file() and path.name != MANIFEST_NAME:
            rel = str(path.relative_to(build.dir))
            info = path.stat()
            outputs[rel] = {"size_bytes": info.st_size, "mtime_ns": info.st_mtime_ns, "sha256": sha256_file(path)}
    config_hash = sha256_json(config)
    return {
        "stage": stage,
        "artifact": name,
        "command": command or f"drivesim {stage}",
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


def _flock(fd: int) -> bool:
    """Take an exclusive lock on the open file `fd` without waiting: False when another process holds it. On a file
    system without locks (some network mounts) the writer goes on unguarded, as before locks existed."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as e:
        if e.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
            return False
        if e.errno not in _NO_LOCKS:
            raise
    return True


def _record_mtimes(path: Path, mtimes: dict[str, int], manifest: dict[str, Any]) -> None:
    """Record the new mtime_ns of output files whose bytes were found unchanged in the manifest at `path`, when it is
    still the manifest that was checked (written atomically, its own mtime kept: `drivesim status` orders runs by it).
    Best effort: a read-only workspace is hashed again next time."""
    with suppress(OSError, ValueError, TypeError, KeyError):
        info = path.stat()
        current = json.loads(path.read_text())
        if current.get("outputs") != manifest.get("outputs"):
            return
        for rel, mtime_ns in mtimes.items():
            current["outputs"][rel]["mtime_ns"] = mtime_ns
        tmp = path.with_name(f"{_TMP_PREFIX}{path.name}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
        try:
            tmp.write_text(json.dumps(current, indent=2, default=str) + "\n")
            os.utime(tmp, ns=(info.st_atime_ns, info.st_mtime_ns))
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)


def _printable(text: str) -> str:
    """`text` with control characters (a newline in a file name) shown as `?`, so a message stays one line."""
    return "".join(c if c.isprintable() else "?" for c in text)


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
