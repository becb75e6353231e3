"""JSON files the tool reads back (manifests, saved configs), parsed with a limit on nesting and no NaN or Infinity.

Python's parser recurses once per nesting level, so a hand-made file nested a few thousand deep ends in a
RecursionError with thousands of lines of traceback; NaN and Infinity are not JSON but Python reads them. Both are a
`JsonFileError` (a ValueError) here, which the readers report as a damaged file. (`sim/world_checks.py` applies the
same rules to a world's files; `sim/` may import only `sim`.)
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np

MAX_JSON_DEPTH = 32
"""Deepest nesting of arrays and objects accepted; drivesim's own files nest at most five levels."""
_STRING = re.compile(rb'"(?:\\.|[^"\\])*"')


class JsonFileError(ValueError):
    """A JSON file nested too deeply or holding NaN or Infinity."""


def json_nesting_depth(raw: bytes) -> int:
    """How deeply the arrays and objects of a JSON text nest (0 for a scalar), strings ignored."""
    bare = np.frombuffer(_STRING.sub(b'""', raw), dtype=np.uint8)
    step = np.isin(bare, np.frombuffer(b"[{", np.uint8)).astype(np.int64)
    step -= np.isin(bare, np.frombuffer(b"]}", np.uint8))
    return int(np.cumsum(step).max()) if step.size else 0


def _refuse_constant(name: str) -> Any:
    raise JsonFileError(f"{name} is not a number JSON allows")


def loads_checked(raw: bytes | str) -> Any:
    """Parse a JSON text; JsonFileError when nested deeper than MAX_JSON_DEPTH or holding NaN/Infinity, and
    json.JSONDecodeError / UnicodeDecodeError (ValueErrors too) when it is not JSON."""
    data = raw.encode("utf-8", "surrogatepass") if isinstance(raw, str) else raw
    if json_nesting_depth(data) > MAX_JSON_DEPTH:
        raise JsonFileError(f"nested more than {MAX_JSON_DEPTH} levels deep")
    return json.loads(data, parse_constant=_refuse_constant)


def read_json(path: Path) -> Any:
    """The JSON value in the file at `path` (see `loads_checked`; OSError when it cannot be read)."""
    return loads_checked(Path(path).read_bytes())
