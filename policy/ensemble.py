"""An ensemble policy's files, made from finished runs of one recipe (`drivesim train --ensemble N` trains them,
`--ensemble-of RUN`, once per run, takes runs already trained): one policy whose steering is the mean of theirs
(`EnsembleNet`).

The members must see the same observations: the same task, image shape, network architecture and env config (the
view, its region of interest); they differ in their seeds (or anything else of their training). Each member stays a
run folder of its own; the ensemble's folder holds the members' weights together, so it evaluates and exports alone.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from drivesim.pipeline.errors import DrivesimError
from drivesim.policy.run_folder import (
    CONFIG_JSON,
    NORMALIZATION_JSON,
    POLICY_JSON,
    POLICY_WEIGHTS,
    LoadedPolicy,
    load_policy,
)


class EnsembleError(DrivesimError):
    """Runs that cannot act as one policy (a different task, image, architecture or view)."""


def load_members(run_dirs: list[Path]) -> list[LoadedPolicy]:
    """The finished runs `run_dirs` loaded (RunError with one line for a bad one), checked to act on the same
    observations as the first (EnsembleError naming the first difference)."""
    if len(run_dirs) < 2:
        raise EnsembleError(f"an ensemble needs at least 2 runs, got {len(run_dirs)}")
    members = [load_policy(run) for run in run_dirs]
    first = members[0]
    for member in members[1:]:
        for what, mine, theirs in (
            ("task", member.task, first.task),
            ("observation shape", member.observation_shape, first.observation_shape),
            ("network architecture", member.info.get("architecture"), first.info.get("architecture")),
            ("env config (the view)", _view_config(member.env_config), _view_config(first.env_config)),
        ):
            if mine != theirs:
                raise EnsembleError(
                    f"its {what} differs from {first.run_dir.name}'s: an ensemble's members must see the same "
                    "observations (train them with one recipe and different seeds)",
                    member.run_dir,
                )
        if "ensemble" in member.info:
            raise EnsembleError("is an ensemble already: give its member runs instead", member.run_dir)
    if "ensemble" in first.info:
        raise EnsembleError("is an ensemble already: give its member runs instead", first.run_dir)
    return members


ACTING_KEYS = (
    "roi_px", "roi_fov_deg", "roi_horizon_fraction", "observation_width_px", "observation_height_px",
    "max_curvature_1pm", "dt_s",
)  # fmt: skip
"""The env config entries that shape the observation or give the action its meaning: equal in every member (the
training-only ones, such as the augmentations, may differ)."""


def _view_config(env_config: dict[str, Any]) -> dict[str, Any]:
    """The `ACTING_KEYS` of an env config."""
    return {k: env_config.get(k) for k in ACTING_KEYS}


def write_ensemble_files(folder: Path, members: list[LoadedPolicy], train_config: dict[str, Any]) -> None:
    """policy.pt, policy.json, config.json and normalization.json of the ensemble of `members` into `folder`."""
    import torch

    from drivesim.policy.net import EnsembleNet

    # Plain writes: `folder` is the stage's build folder, moved into place whole once the manifest is written.
    net = EnsembleNet([m.net for m in members])
    torch.save({k: v.contiguous() for k, v in net.state_dict().items()}, folder / POLICY_WEIGHTS)
    runs = [str(m.run_dir) for m in members]
    info = {**members[0].info, "ensemble": {"members": len(members), "runs": [Path(r).name for r in runs]}}
    _write_json(folder / POLICY_JSON, info)
    configs = [json.loads((m.run_dir / CONFIG_JSON).read_text()) for m in members]
    worlds: list[str] = []
    for config in configs:
        worlds += [w for w in config.get("worlds", []) if w not in worlds]
    _write_json(
        folder / CONFIG_JSON,
        {
            "train": train_config,
            "env_config": configs[0].get("env_config", {}),
            "observation_shape": configs[0].get("observation_shape"),
            "worlds": worlds,
            "meshes": configs[0].get("meshes"),
            "ensemble_of": runs,
        },
    )
    shutil.copyfile(members[0].run_dir / NORMALIZATION_JSON, folder / NORMALIZATION_JSON)


def _write_json(path: Path, value: Any) -> None:
    path.write_text(json.dumps(value, indent=2, default=str) + "\n")
