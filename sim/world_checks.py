"""The checks a world folder passes before the simulator uses it: its JSON files read safely and shaped as the schema
in `sim/world.py` says, finite camera and path values, and depth that is a depth.

Every problem is a `WorldError` (a ValueError) whose text names the file and says what is wrong, so a damaged or
hand-edited world is one line for the user instead of a NaN that trains silently, a LinAlgError or a RecursionError.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

# Deeper nesting than this is refused before parsing: the world's JSON files are two levels deep, and Python's
# parser would exhaust the interpreter's recursion limit at about a thousand.
MAX_JSON_DEPTH = 32
# Depth frames checked on load (evenly spaced, first and last included), so a long drive still loads in milliseconds.
DEPTH_FRAMES_CHECKED = 64
_STRING = re.compile(rb'"(?:\\.|[^"\\])*"')


class WorldError(ValueError):
    """A world folder whose files are damaged or not what `drivesim build-world` writes."""


def json_nesting_depth(text: bytes) -> int:
    """How deeply the arrays and objects of a JSON text nest (0 for a scalar), strings ignored."""
    bare = np.frombuffer(_STRING.sub(b'""', text), dtype=np.uint8)
    step = np.isin(bare, np.frombuffer(b"[{", np.uint8)).astype(np.int64)
    step -= np.isin(bare, np.frombuffer(b"]}", np.uint8))
    return int(np.cumsum(step).max()) if step.size else 0


def read_json_object(path: Path, required: tuple[str, ...] = ()) -> dict[str, Any]:
    """The JSON object in `path`, refused (WorldError) when unreadable, nested too deeply, holding NaN or Infinity,
    not an object, or lacking one of the `required` keys."""
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise WorldError(f"{path}: unreadable ({e.strerror or type(e).__name__})") from e
    if json_nesting_depth(raw) > MAX_JSON_DEPTH:
        raise WorldError(f"{path}: nested more than {MAX_JSON_DEPTH} levels deep; rebuild the world")
    try:
        value = json.loads(raw, parse_constant=_refuse_constant)
    except (UnicodeDecodeError, json.JSONDecodeError, _NonFiniteError) as e:
        raise WorldError(f"{path}: not valid JSON ({_first_line(e)}); rebuild the world") from e
    if not isinstance(value, dict):
        raise WorldError(f"{path}: holds a JSON {type(value).__name__}, not an object; rebuild the world")
    missing = [key for key in required if key not in value]
    if missing:
        raise WorldError(f"{path}: lacks {', '.join(missing)}; rebuild the world")
    return value


class _NonFiniteError(ValueError):
    """NaN or Infinity in a JSON text (Python's parser accepts them; JSON does not)."""


def _refuse_constant(name: str) -> float:
    raise _NonFiniteError(f"{name} is not a number JSON allows")


def _first_line(e: Exception) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def finite_number(where: Path, key: str, value: Any, positive: bool = False, optional: bool = False) -> float | None:
    """`value` as a float, refused unless it is a finite number (and > 0 when `positive`; None when `optional`)."""
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise WorldError(f"{where}: {key} is {value!r}, not a finite number; rebuild the world")
    if positive and value <= 0:
        raise WorldError(f"{where}: {key} is {value!r}, it must be positive; rebuild the world")
    return float(value)


def image_size(where: Path, key: str, value: Any) -> int:
    """A width or height in pixels: a whole number from 1 to 100,000."""
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 100_000:
        raise WorldError(f"{where}: {key} is {value!r}, not an image size in pixels; rebuild the world")
    return value


def _finite_matrix(where: Path, key: str, value: Any, size: int) -> np.ndarray:
    """`value` as a finite size x size float matrix; WorldError naming `key` otherwise."""
    try:
        M = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as e:
        raise WorldError(f"{where}: {key} is not a {size}x{size} matrix of numbers; rebuild the world") from e
    if M.shape != (size, size) or not np.all(np.isfinite(M)):
        raise WorldError(f"{where}: {key} is not a finite {size}x{size} matrix; rebuild the world")
    return M


def intrinsics(where: Path, value: Any) -> np.ndarray:
    """K as a 3x3 pinhole matrix: finite, positive focal lengths, last row 0 0 1 (so it is invertible)."""
    K = _finite_matrix(where, "K", value, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise WorldError(f"{where}: K has no positive focal lengths or no last row 0 0 1; rebuild the world")
    return K


def rigid_transform(where: Path, key: str, value: Any) -> np.ndarray:
    """A 4x4 rigid transform: finite, orthonormal rotation with det +1, last row 0 0 0 1."""
    T = _finite_matrix(where, key, value, 4)
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0 or not np.allclose(T[3], [0, 0, 0, 1]):
        raise WorldError(f"{where}: {key} is not a rigid transform; rebuild the world")
    return T


def check_path_values(where: Path, path: dict[str, np.ndarray], float_keys: tuple[str, ...]) -> None:
    """Every per-frame path array finite (NaN or Inf there would put the car nowhere)."""
    for key in (*float_keys, "T_world_vehicle", "T_world_camera"):
        values = np.asarray(path[key])
        if not np.issubdtype(values.dtype, np.number) or not np.all(np.isfinite(values)):
            raise WorldError(f"{where}: {key} holds non-finite or non-numeric values; rebuild the world")


def check_depth(where: Path, depth_m: np.ndarray) -> None:
    """Depth not NaN and not negative (zero and infinity pass: the renderer treats them as no surface) on
    DEPTH_FRAMES_CHECKED evenly spaced frames."""
    n = depth_m.shape[0]
    for i in np.unique(np.linspace(0, n - 1, min(n, DEPTH_FRAMES_CHECKED)).round().astype(int)):
        frame = np.asarray(depth_m[i])
        if np.isnan(frame).any():
            raise WorldError(f"{where}: frame {i} has NaN depth; rebuild the world")
        if (frame < 0).any():
            raise WorldError(f"{where}: frame {i} has negative depth ({float(frame.min()):.3g} m); rebuild the world")
