"""Several recordings, one training set: `drivesim run a.bag b.mcap c/` (or `--recordings-file drives.txt`).

The first recording is the workspace's own, exactly as with one recording (`trace/`, `preprocessed/`, `world/`,
`runs/`, `eval/`, `export/`). Each further recording gets a small workspace of its own, `<workspace>/drives/<name>/`,
named after its file (`b.mcap` -> `drives/b`), made by the chain's world-making stages (ingest -> preprocess ->
build-world, each skipped when fresh) with the same per-stage settings as the first. Training adds their worlds to
the workspace's world (before the config's towns), the evaluation runs in every recording's world (a row per
recording and the pooled figures), and `drives/drives.json` records the set so that a later `drivesim eval` without
--world evaluates in the same worlds.

Everything the user named is checked before anything is written: a missing recording, two recordings with the same
name, the same recording given twice, an unreadable or empty list file are one line each.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from drivesim.chain.towns import TOWN_STAGES
from drivesim.chain.walk import StageRun, run_ingest, walk_chain
from drivesim.pipeline.errors import ConfigError, InputError
from drivesim.pipeline.workspace import Workspace

DRIVES_DIR = "drives"
SET_FILE = "drives.json"
WORLD_STAGES = TOWN_STAGES
"""The chain's stages each recording goes through on its own, in order; the rest of the chain runs once."""


@dataclass(frozen=True)
class Drive:
    """One recording of a set.

    :param name: its name in progress lines, folders and the evaluation's tables (the file's stem).
    :param recording: the recording file or folder (absolute).
    :param root: the workspace it is made into: the main one for the first recording, `drives/<name>/` after it.
    """

    name: str
    recording: Path
    root: Path

    @property
    def world(self) -> Path:
        """Its world folder (it may not exist yet)."""
        return self.root / "world"


def recording_name(path: Path) -> str:
    """The name of a recording: its file's stem (`drive_0005.bag` -> `drive_0005`; a folder keeps its whole name),
    with characters outside `A-Za-z0-9._-` written as `_`, as the evaluation labels a world."""
    stem = Path(str(path).rstrip("/") or "/").stem
    return re.sub(r"[^A-Za-z0-9._-]+", "_", stem).strip("._") or "recording"


def read_list_file(path: Path) -> list[Path]:
    """The recordings a list file names: one path per line, blank lines and lines starting with `#` skipped; a
    relative path is taken from the list file's folder. An unreadable or empty file is one line."""
    from drivesim.pipeline.input_paths import refuse_special_file

    path = Path(path)
    refuse_special_file(path, "a text file with one recording path per line")  # a FIFO would block the read
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        why = e.strerror if isinstance(e, OSError) and e.strerror else type(e).__name__
        raise InputError(
            f"cannot read the recordings list ({why}); give a text file with one recording path per line", path
        ) from e
    lines = [line.strip() for line in text.splitlines()]
    paths = [Path(line) for line in lines if line and not line.startswith("#")]
    if not paths:
        raise InputError("the recordings list names no recording; write one recording path per line", path)
    return [p if p.is_absolute() else path.parent / p for p in paths]


def plan_drives(ws: Workspace, recordings: Sequence[Path]) -> list[Drive]:
    """The set's drives in order, the first in the workspace itself; every recording checked first (it exists, no
    two share a name, none is given twice) so that bad input is one line before anything is written."""
    from drivesim.pipeline.hashing import fingerprint_external

    drives: list[Drive] = []
    seen: dict[str, str] = {}  # name -> fingerprint
    for i, given in enumerate(recordings):
        path = Path(given).absolute()
        if not path.exists():
            raise InputError("no such recording; check the path (each recording of the set must exist)", path)
        name = recording_name(path)
        for other in drives:
            if path.resolve() == other.recording.resolve():
                raise ConfigError(f"{path} is given twice; give each recording once")
        if name in {d.name for d in drives}:
            first = next(d.recording for d in drives if d.name == name)
            raise ConfigError(
                f"two recordings are named {name!r} ({first} and {path}); each recording's world is named after "
                "its file: rename or link one of them under another name"
            )
        fingerprint = fingerprint_external(path)  # a FIFO or device is refused here, before it is opened
        for other_name, other_fingerprint in seen.items():
            if fingerprint == other_fingerprint:
                raise ConfigError(f"{path} holds the same recording as {other_name!r}; give each recording once")
        seen[name] = fingerprint
        root = ws.root if i == 0 else ws.root / DRIVES_DIR / name
        drives.append(Drive(name, path, root))
    return drives


def build_drive_worlds(
    drives: Sequence[Drive],
    overrides: dict[str, Any],
    force: bool = False,
    on_stage: Callable[[StageRun], None] | None = None,
) -> list[StageRun]:
    """Every drive's world through the world-making stages (`WORLD_STAGES`), one drive after the other, each stage
    skipped when fresh; returns what each stage did, tagged with its drive's name.

    :param overrides: the run preset's per-stage overrides (those of the world-making stages are used).
    """
    from drivesim.chain.registry import stage_by_name

    chain = tuple(stage_by_name(name) for name in WORLD_STAGES)
    assert all(spec is not None for spec in chain), "a world-making stage is missing from the chain registry"
    world_overrides = {k: v for k, v in overrides.items() if k in WORLD_STAGES}
    done: list[StageRun] = []
    for drive in drives:

        def tagged(stage_run: StageRun, name: str = drive.name) -> None:
            stage_run = replace(stage_run, recording=name)
            done.append(stage_run)
            if on_stage is not None:
                on_stage(stage_run)

        walk_chain(
            Workspace(drive.root),
            drive.recording,
            world_overrides,
            chain,  # type: ignore[arg-type]
            {"ingest": run_ingest},
            force=force,
            on_stage=tagged,
        )
    return done


def set_file(ws: Workspace) -> Path:
    """`<workspace>/drives/drives.json`: the recordings of the workspace's last run on several recordings."""
    return ws.root / DRIVES_DIR / SET_FILE


def write_set(ws: Workspace, drives: Sequence[Drive]) -> None:
    """Record the set (names, recordings, worlds) for a later `drivesim eval`; written whole or not at all."""
    path = set_file(ws)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {
        "recordings": [
            {"name": d.name, "recording": str(d.recording), "world": str(d.world.relative_to(ws.root))} for d in drives
        ]
    }
    tmp = path.with_name(f".{SET_FILE}.{os.getpid()}")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)


def forget_set(ws: Workspace) -> None:
    """Remove the record of an earlier set: the workspace's run is on one recording now."""
    path = set_file(ws)
    if path.is_file():
        path.unlink()


def set_worlds(ws: Workspace) -> list[Path]:
    """The world folders of the workspace's recording set (the workspace's own world first), each checked to exist;
    [] when the workspace's last run was on one recording."""
    from drivesim.pipeline.json_files import read_json

    path = set_file(ws)
    if not path.is_file():
        return []
    try:
        entries = read_json(path)["recordings"]
        worlds = [ws.root / str(entry["world"]) for entry in entries]
        hint = " ".join(["drivesim run", *(str(entry["recording"]) for entry in entries)])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(
            "unreadable record of the workspace's recordings; run `drivesim run` on them again, or give --world",
            path,
        ) from e
    # Each world required whole (its manifest checked) in its own workspace; a missing one names the set's command.
    return [Workspace(w.parent).require(w.name, hint) for w in worlds]


def expand_recordings(given: Iterable[Path], list_file: Path | None) -> list[Path]:
    """The recordings named on the command line, then those of the list file (when given), in order."""
    paths = list(given)
    if list_file is not None:
        paths += read_list_file(list_file)
    return paths
