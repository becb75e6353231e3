"""An exported policy (`drivesim export onnx`) run on onnxruntime, behind the same interface as `LoadedPolicy`.

The graph (INTERFACES §6) takes `image_u8` (N, 3, H, W) uint8, `h` and `c` (layers, N, hidden) float32 and
`episode_start` (N,) float32, and returns `action` (N, 1) float32 in [-1, 1] with the new `h_out`, `c_out`.
Its metadata (`drivesim.*` keys, JSON values) says the task, input shape, region of interest, action scale, the
training config's hash and the LSTM sizes; `drivesim.digest` is a sha256 over those entries and the rest of the model
(graph and weights), so an edited entry (an ROI, a format) or edited weights are refused when the file is loaded.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from drivesim.pipeline.errors import DrivesimError
from drivesim.policy.lstm_state import LstmState

INPUT_NAMES = ("image_u8", "h", "c", "episode_start")
OUTPUT_NAMES = ("action", "h_out", "c_out")
METADATA_PREFIX = "drivesim."
METADATA_FORMAT = 2
"""The metadata layout this version writes and reads: 2 carries `drivesim.digest` (1 had none: export again)."""
DIGEST_KEY = "digest"


class OnnxPolicyError(DrivesimError):
    """An ONNX file that is not a drivesim policy (unreadable, other inputs, no metadata)."""


def metadata_digest(model: Any) -> str:
    """sha256 (hex) over an ONNX model's `drivesim.*` metadata entries as stored (sorted by key, the digest itself
    left out) and the model without its metadata (graph, weights, opsets), as `drivesim.digest` records it."""
    entries = {p.key: p.value for p in model.metadata_props if p.key.startswith(METADATA_PREFIX)}
    entries.pop(METADATA_PREFIX + DIGEST_KEY, None)
    bare = type(model)()
    bare.CopyFrom(model)
    bare.ClearField("metadata_props")
    digest = hashlib.sha256(json.dumps(sorted(entries.items()), separators=(",", ":")).encode())
    digest.update(bare.SerializeToString(deterministic=True))
    return digest.hexdigest()


def _metadata(raw: dict[str, str], path: Path) -> dict[str, Any]:
    meta = {}
    for key, value in raw.items():
        if key.startswith(METADATA_PREFIX):
            try:
                meta[key[len(METADATA_PREFIX) :]] = json.loads(value)
            except json.JSONDecodeError as e:
                raise OnnxPolicyError(f"metadata {key} is not JSON; export the policy again", path) from e
    missing = [k for k in ("format", "observation_shape", "lstm_layers", "hidden_size") if k not in meta]
    if missing:
        raise OnnxPolicyError(
            f"not a drivesim policy: metadata lacks {', '.join(METADATA_PREFIX + k for k in missing)}; "
            "make one with `drivesim export onnx`",
            path,
        )
    if meta["format"] != METADATA_FORMAT:
        raise OnnxPolicyError(
            f"metadata format {meta['format']!r} is not the one this drivesim reads ({METADATA_FORMAT}); export the "
            "policy again with `drivesim export onnx`",
            path,
        )
    return meta


def _check_digest(model: Any, meta: dict[str, Any], path: Path) -> None:
    """Refuse a policy whose metadata or weights changed after the export (its digest no longer matches)."""
    if meta.get(DIGEST_KEY) != metadata_digest(model):
        raise OnnxPolicyError(
            f"its metadata or weights were changed after the export ({METADATA_PREFIX}{DIGEST_KEY} does not match); "
            "export the policy again with `drivesim export onnx`",
            path,
        )


class OnnxPolicy(LstmState):
    """A `drivesim export onnx` graph on onnxruntime: `initial_state(n)` and `predict(...)` as `LoadedPolicy`.

    :param path: the .onnx file.
    :param intra_op_threads: onnxruntime threads per call (1: what the car's one core gets).
    """

    def __init__(self, path: Path | str, intra_op_threads: int = 1) -> None:
        import onnx
        import onnxruntime as ort

        self.path = Path(path)
        if not self.path.is_file():
            raise OnnxPolicyError("no such ONNX file", self.path)
        options = ort.SessionOptions()
        options.intra_op_num_threads = intra_op_threads
        options.inter_op_num_threads = 1
        data = self.path.read_bytes()  # read once: the bytes checked are the bytes run
        try:
            model = onnx.load_model_from_string(data)
            self.session = ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnx and onnxruntime raise their own types, all with long messages
            raise OnnxPolicyError(f"not a readable ONNX model ({type(e).__name__})", self.path) from e
        inputs = tuple(i.name for i in self.session.get_inputs())
        outputs = tuple(o.name for o in self.session.get_outputs())
        if inputs != INPUT_NAMES or outputs != OUTPUT_NAMES:
            raise OnnxPolicyError(
                f"not a drivesim policy graph: inputs {list(inputs)} and outputs {list(outputs)}, expected "
                f"{list(INPUT_NAMES)} -> {list(OUTPUT_NAMES)}; make one with `drivesim export onnx`",
                self.path,
            )
        self.metadata = _metadata({p.key: p.value for p in model.metadata_props}, self.path)
        _check_digest(model, self.metadata, self.path)
        self.task: str = str(self.metadata.get("task", ""))
        self.observation_shape: tuple[int, int, int] = tuple(int(v) for v in self.metadata["observation_shape"])  # type: ignore[assignment]
        self.lstm_layers = int(self.metadata["lstm_layers"])
        self.hidden_size = int(self.metadata["hidden_size"])
        self.config_hash = str(self.metadata.get("config_hash", ""))
        self.env_config: dict = dict(self.metadata.get("env_config") or {})

    def predict(
        self, obs: np.ndarray, state: Any, episode_start: np.ndarray, deterministic: bool = True
    ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """One step for N episodes: obs (N, C, H, W) uint8 -> actions (N, 1) float32 in [-1, 1] and the new state.

        The graph is the deterministic policy; deterministic=False is refused (the exported graph has no sampling).
        """
        if not deterministic:
            raise ValueError("an exported ONNX policy is deterministic; call predict with deterministic=True")
        obs = np.ascontiguousarray(obs, dtype=np.uint8)
        if obs.ndim != 4 or tuple(obs.shape[1:]) != self.observation_shape:
            raise ValueError(
                f"observations must be (N, {', '.join(map(str, self.observation_shape))}) uint8, got {obs.shape}"
            )
        if state is None:
            state = self.initial_state(obs.shape[0])
        h, c = (np.ascontiguousarray(s, dtype=np.float32) for s in state)
        starts = np.asarray(episode_start, dtype=np.float32).reshape(-1)
        action, h_out, c_out = self.session.run(
            list(OUTPUT_NAMES), {"image_u8": obs, "h": h, "c": c, "episode_start": starts}
        )
        return action.astype(np.float32, copy=False), (h_out, c_out)
