"""Content hashes for files, configs and external inputs."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from drivesim.pipeline.input_paths import refuse_special_file

_CHUNK_BYTES = 1 << 20


def sha256_file(path: Path) -> str:
    """sha256 hex digest of a file's bytes."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def sha256_json(value: Any) -> str:
    """sha256 of a JSON-serialisable value in canonical form (sorted keys, no spaces)."""
    text = json.dumps(value, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def fingerprint_external(path: Path) -> str:
    """A fast identity for an external input (a recording that may be many GB).

    Hashing a 1-hour bag would take longer than ingesting it, so a file is identified by its size and the
    sha256 of its first and last MiB; a folder by the sorted fingerprints of its files.
    A FIFO, socket or device, given or inside the folder, is refused (InputError) before anything opens it.
    """
    path = Path(path)
    refuse_special_file(path, "a recording file or folder")
    if path.is_dir():
        entries = sorted(path.rglob("*"))
        for p in entries:
            refuse_special_file(p, "a recording whose files are regular files")
        parts = [(str(p.relative_to(path)), fingerprint_external(p)) for p in entries if p.is_file()]
        return sha256_json(parts)
    size = path.stat().st_size
    h = hashlib.sha256(str(size).encode())
    with open(path, "rb") as f:
        h.update(f.read(_CHUNK_BYTES))
        if size > 2 * _CHUNK_BYTES:
            f.seek(size - _CHUNK_BYTES)
            h.update(f.read(_CHUNK_BYTES))
    return h.hexdigest()
