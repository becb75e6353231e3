"""The chain registry: every stage of a user's recording, in order, as its `StageSpec` (written once, in its
`stages/<x>/stage.py`). `drivesim status`, `drivesim config` and `drivesim run` read it.

Adding a stage: one `stages/<x>/stage.py` defining `SPEC`, one line in `CHAIN` below, one thin CLI command.
Importing this module stays light: each stage module imports its heavy parts inside its build function.
"""

from __future__ import annotations

from drivesim.pipeline.stage import StageSpec
from drivesim.stages.evaluate.stage import SPEC as EVAL
from drivesim.stages.export.stage import SPEC as EXPORT
from drivesim.stages.ingest.stage import SPEC as INGEST
from drivesim.stages.meshes.stage import SPEC as MESHES
from drivesim.stages.preprocess.stage import SPEC as PREPROCESS
from drivesim.stages.train.stage import SPEC as TRAIN
from drivesim.stages.world.stage import SPEC as BUILD_WORLD

# The chain of a user's recording, in order. Owners of new stages add their SPEC here with a one-line edit:
# meshes after build-world, export after eval.
CHAIN: tuple[StageSpec, ...] = (
    INGEST,
    PREPROCESS,
    BUILD_WORLD,
    MESHES,
    TRAIN,
    EVAL,
    EXPORT,
)

# Configs outside the chain: synth makes a recording file (the chain's input), not an artifact of the workspace,
# so it has a config and a preset but no place in the chain. stage name -> (config module, class, preset).
OFF_CHAIN_CONFIGS: dict[str, tuple[str, str, str]] = {
    "synth": ("drivesim.stages.synth.config", "SynthConfig", "synth"),
}


def make_hints() -> dict[str, str]:
    """Artifact -> the command that makes it, for the one-line "run X first" errors."""
    return {spec.artifact: spec.command for spec in CHAIN}


def stage_by_name(name: str) -> StageSpec | None:
    """The chain's stage called `name` (its CLI command), or None."""
    return next((spec for spec in CHAIN if spec.name == name), None)
