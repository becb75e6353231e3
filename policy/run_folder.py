"""A trained policy's run folder, read back for evaluation and export (INTERFACES §4).

Run folder `runs/<task>-<YYYYmmdd-HHMMSS>/` (written by `drivesim train`):
    config.json        {"train": resolved TrainConfig, "env_config": the env config the policy was trained with,
                        "worlds": [world folders], "meshes": folder | null}
    policy.json        {"format": 1, "task", "observation_shape": [C, H, W], "architecture": {conv_layers,
                        features_dim, input_pool, lstm_hidden_size, lstm_layers, log_std_init},
                        "action": {"low": -1, "high": 1, "max_curvature_1pm": float | null}, "normalization": {...}}
    policy.pt          DrivingNet weights (a dict of tensors; read with torch.load(weights_only=True))

An ensemble run (`drivesim train --ensemble N`, `policy/ensemble.py`) holds config.json, policy.json (with
"ensemble": {"members": N, "runs": [member run names]}), policy.pt (the `EnsembleNet`'s weights), normalization.json
and manifest.json; its members are run folders of their own beside it.
    normalization.json how observations are normalized before the network (per-image standardization, no stats
                        to fit; recorded so a deployment can check it)
    checkpoints/       last.pt (after every update) and step-<N>.pt; progress.csv; tb/ (TensorBoard); curves.png
    manifest.json      written last: a folder without it is an unfinished run (`drivesim train --resume` continues it)

Loading never executes code from the folder: JSON for configs, `torch.load(weights_only=True)` for weights, and the
weights' sha256 must match the manifest (a changed or truncated file is refused with one line).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivesim.pipeline.errors import DrivesimError
from drivesim.pipeline.hashing import sha256_file
from drivesim.pipeline.workspace import MANIFEST_NAME, Workspace
from drivesim.policy.lstm_state import LstmState

POLICY_JSON = "policy.json"
POLICY_WEIGHTS = "policy.pt"
CONFIG_JSON = "config.json"
NORMALIZATION_JSON = "normalization.json"
RUNS_DIR = "runs"
CHECKPOINTS_DIR = "checkpoints"


class RunError(DrivesimError):
    """A run folder is missing, unfinished, damaged or changed after training."""


def _read_json(path: Path, what: str) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError as e:
        raise RunError(f"the run has no {path.name} ({what}); is this a drivesim run folder?", path.parent) from e
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise RunError(f"{path.name} is not valid JSON ({what}); the run folder is damaged", path.parent) from e
    if not isinstance(data, dict):
        raise RunError(f"{path.name} does not hold a JSON object; the run folder is damaged", path.parent)
    return data


@dataclass
class LoadedPolicy(LstmState):
    """A trained policy ready to act: `predict` steps N episodes at once, with explicit LSTM state.

    :param run_dir: the run folder.
    :param task: the task it was trained on (sim/envs/registry.py).
    :param observation_shape: (C, H, W) of the uint8 images it takes.
    :param env_config: the env config it was trained with (to build the same observations).
    :param config_hash: the run's config hash (from its manifest).
    :param net: the `DrivingNet` (torch module).
    :param info: policy.json as read.
    """

    run_dir: Path
    task: str
    observation_shape: tuple[int, int, int]
    env_config: dict
    config_hash: str
    net: Any = field(repr=False)
    info: dict = field(default_factory=dict, repr=False)

    @property
    def lstm_layers(self) -> int:
        """LSTM layers."""
        return int(self.net.lstm_layers)

    @property
    def hidden_size(self) -> int:
        """LSTM cells per layer."""
        return int(self.net.hidden_size)

    def predict(
        self, obs: np.ndarray, state: Any, episode_start: np.ndarray, deterministic: bool = True
    ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """One step for N episodes: obs (N, C, H, W) uint8 -> actions (N, 1) float32 in [-1, 1] and the new state.

        The state of episode n is reset before the step where episode_start[n] is true (state None: all zero).
        Stochastic actions
        (deterministic=False) sample the Gaussian steering distribution.
        """
        import torch

        obs = np.asarray(obs)
        if obs.ndim != 4 or tuple(obs.shape[1:]) != self.observation_shape:
            raise ValueError(
                f"observations must be (N, {', '.join(map(str, self.observation_shape))}) uint8, got {obs.shape}"
            )
        if state is None:
            state = self.initial_state(obs.shape[0])
        with torch.no_grad():
            h, c = (torch.as_tensor(np.asarray(s), dtype=torch.float32) for s in state)
            starts = torch.as_tensor(np.asarray(episode_start, dtype=np.float32).reshape(-1))
            mean, _, (h, c) = self.net.step(torch.from_numpy(np.ascontiguousarray(obs)), (h, c), starts)
            if not deterministic:
                mean = mean + torch.exp(self.net.log_std) * torch.randn_like(mean)
            actions = torch.clamp(mean, -1.0, 1.0)
        return actions.numpy().astype(np.float32), (h.numpy(), c.numpy())

    def export_module(self) -> Any:
        """The deterministic one-step policy as a `torch.nn.Module` for ONNX (see policy_net.ExportModule)."""
        from drivesim.policy.net import ExportModule

        return ExportModule(self.net).eval()


def _check_weights(run_dir: Path, manifest: dict[str, Any]) -> None:
    weights = run_dir / POLICY_WEIGHTS
    if not weights.is_file():
        raise RunError(f"the run has no {POLICY_WEIGHTS}; the run folder is damaged", run_dir)
    recorded = manifest.get("outputs", {}).get(POLICY_WEIGHTS, {}).get("sha256")
    if recorded is None:
        raise RunError(f"the manifest does not list {POLICY_WEIGHTS}; the run folder is damaged", run_dir)
    if sha256_file(weights) != recorded:
        raise RunError(
            f"{POLICY_WEIGHTS} was changed or truncated after training (its sha256 differs from the "
            "manifest); retrain or restore the file",
            run_dir,
        )


MAX_ENSEMBLE_MEMBERS = 16
"""The most members policy.json may name (a damaged one could otherwise ask for any number of networks)."""


def build_net(info: dict[str, Any]) -> Any:
    """A `DrivingNet` with the architecture recorded in policy.json (random weights), or an `EnsembleNet` of
    `info["ensemble"]["members"]` of them when policy.json describes an ensemble."""
    from drivesim.policy.net import EnsembleNet

    if "ensemble" not in info:
        return _driving_net(info)
    members = info["ensemble"]["members"]
    if not isinstance(members, int) or not 2 <= members <= MAX_ENSEMBLE_MEMBERS:
        raise ValueError(f"an ensemble of {members!r} members (2 to {MAX_ENSEMBLE_MEMBERS})")
    return EnsembleNet([_driving_net(info) for _ in range(members)])


def _driving_net(info: dict[str, Any]) -> Any:
    """One `DrivingNet` of the architecture in policy.json, its size checked first."""
    from drivesim.policy.net import DrivingNet
    from drivesim.policy.net_size import check_network_size

    arch = info["architecture"]
    # A damaged or hostile policy.json may describe a network larger than memory: refused before torch allocates it.
    check_network_size(
        info["observation_shape"],
        arch["conv_layers"],
        arch["features_dim"],
        arch["lstm_hidden_size"],
        arch["lstm_layers"],
        arch.get("input_pool", 1),
    )
    return DrivingNet(
        tuple(info["observation_shape"]),
        [tuple(layer) for layer in arch["conv_layers"]],
        features_dim=arch["features_dim"],
        lstm_hidden_size=arch["lstm_hidden_size"],
        lstm_layers=arch["lstm_layers"],
        input_pool=arch.get("input_pool", 1),
        log_std_init=arch.get("log_std_init", -1.0),
    )


def load_weights(net: Any, path: Path) -> None:
    """Load a DrivingNet state dict saved with torch.save into `net`, refusing anything but plain tensors."""
    import pickle
    import zipfile

    import torch

    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, zipfile.BadZipFile, ValueError, OSError) as e:
        raise RunError(
            f"not a readable drivesim policy weights file ({type(e).__name__}); the file is damaged", path
        ) from e
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise RunError("the weights file does not hold a dict of tensors", path)
    try:
        net.load_state_dict(state)
    except RuntimeError as e:
        raise RunError(
            f"the weights do not fit the architecture in {POLICY_JSON}: {str(e).splitlines()[0]}", path
        ) from e


def _load_checkpoint_weights(net: Any, path: Path) -> None:
    """The DrivingNet weights of a training checkpoint (its "policy" entry; tensors and plain values only)."""
    import pickle
    import zipfile

    import torch

    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
        state = checkpoint["policy"]
        net.load_state_dict(state)
    except (pickle.UnpicklingError, RuntimeError, EOFError, zipfile.BadZipFile, ValueError, OSError) as e:
        raise RunError(f"not a readable checkpoint of this run ({type(e).__name__}); the file is damaged", path) from e
    except (KeyError, TypeError) as e:
        raise RunError("not a training checkpoint (no policy weights in it)", path) from e


def load_policy(run_dir: Path | str) -> LoadedPolicy:
    """Read a finished run folder into a `LoadedPolicy`; RunError (one line) when missing, unfinished or damaged.

    `run_dir` may also be one of the run's checkpoints, `<run>/checkpoints/<name>.pt` (e.g. `warm_start.pt`, the
    policy before any PPO update, or `best.pt`): the run's policy with that checkpoint's weights, for baselines."""
    checkpoint = None
    run_dir = Path(run_dir)
    if run_dir.suffix == ".pt" and run_dir.parent.name == CHECKPOINTS_DIR:
        checkpoint, run_dir = run_dir, run_dir.parent.parent
        if not checkpoint.is_file():
            raise RunError("no such checkpoint in the run", checkpoint)
    if not run_dir.is_dir():
        raise RunError("no such run folder", run_dir)
    manifest_path = run_dir / MANIFEST_NAME
    if not manifest_path.is_file():
        raise RunError(
            f"the run is unfinished (no {MANIFEST_NAME}); continue it with `drivesim train --resume {run_dir}`", run_dir
        )
    manifest = _read_json(manifest_path, "the run's manifest")
    info = _read_json(run_dir / POLICY_JSON, "the policy's architecture")
    config = _read_json(run_dir / CONFIG_JSON, "the resolved training config")
    try:
        net = build_net(info)
        observation_shape = tuple(int(v) for v in info["observation_shape"])
        task = str(info["task"])
    except (KeyError, TypeError) as e:
        raise RunError(f"{POLICY_JSON} lacks or garbles {e}; the run folder is damaged", run_dir) from e
    except ValueError as e:
        raise RunError(f"{POLICY_JSON}: {e}; the run folder is damaged or not from drivesim", run_dir) from e
    _check_weights(run_dir, manifest)
    if checkpoint is None:
        load_weights(net, run_dir / POLICY_WEIGHTS)
    else:
        _load_checkpoint_weights(net, checkpoint)
    net.eval()
    return LoadedPolicy(
        run_dir=run_dir,
        task=task,
        observation_shape=observation_shape,  # type: ignore[arg-type]
        env_config=dict(config.get("env_config") or {}),
        config_hash=str(manifest.get("config_hash", "")),
        net=net,
        info=info,
    )


def is_complete_run(run_dir: Path) -> bool:
    """True when the folder holds a finished run (its manifest was written)."""
    return (run_dir / MANIFEST_NAME).is_file() and (run_dir / POLICY_JSON).is_file()


def latest_run(ws: Workspace | Path | str, task: str | None = None) -> Path | None:
    """The newest finished run of the workspace (of `task` when given), or None."""
    root = ws.root if isinstance(ws, Workspace) else Path(ws)
    runs = root / RUNS_DIR
    if not runs.is_dir():
        return None
    candidates = []
    for run_dir in runs.iterdir():
        if not run_dir.is_dir() or not is_complete_run(run_dir):
            continue
        if task is not None and not run_dir.name.startswith(f"{task}-"):
            continue
        try:
            created = json.loads((run_dir / MANIFEST_NAME).read_text()).get("created_utc", "")
        except (json.JSONDecodeError, OSError):
            continue
        candidates.append((created, run_dir.name, run_dir))
    return max(candidates)[2] if candidates else None
