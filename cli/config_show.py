"""`drivesim config STAGE`: every config key of a stage with its type, value and meaning."""

from __future__ import annotations

import importlib
from typing import Annotated

import typer
import yaml
from rich.table import Table

from drivesim.cli.common import ConfigOption, SetOption, console
from drivesim.pipeline.config import describe_config, load_config
from drivesim.pipeline.errors import ConfigError

# stage -> (module, config class, preset name)
STAGE_CONFIGS = {
    "ingest": ("drivesim.stages.ingest.config", "IngestConfig", "ingest"),
    "synth": ("drivesim.stages.synth.config", "SynthConfig", "synth"),
    "preprocess": ("drivesim.stages.preprocess.config", "PreprocessConfig", "preprocess"),
    "build-world": ("drivesim.stages.world.config", "WorldConfig", "world"),
    "train": ("drivesim.stages.train.config", "TrainConfig", "train/overtake"),
    "eval": ("drivesim.stages.evaluate.config", "EvalConfig", "eval"),
}


def config_command(
    stage: Annotated[str, typer.Argument(help=f"One of: {', '.join(STAGE_CONFIGS)}.")],
    as_yaml: Annotated[
        bool, typer.Option("--yaml", help="Print the resolved config as YAML (a --config file).")
    ] = False,
    config: ConfigOption = None,
    set_: SetOption = None,
) -> None:
    """Show a stage's config keys: type, resolved value (preset + --config + --set) and description with units."""
    if stage not in STAGE_CONFIGS:
        raise ConfigError(f"unknown stage {stage!r}; stages with a config: {', '.join(STAGE_CONFIGS)}")
    module, class_name, preset = STAGE_CONFIGS[stage]
    model = getattr(importlib.import_module(module), class_name)
    cfg = load_config(model, preset=preset, config_file=config, overrides=set_)
    resolved = cfg.model_dump(mode="json")
    if as_yaml:
        print(yaml.safe_dump(resolved, sort_keys=False), end="")
        return
    table = Table(title=f"drivesim {stage} config (override with --set KEY=VALUE or --config FILE.yaml)")
    table.add_column("key", style="bold")
    table.add_column("type")
    table.add_column("value")
    table.add_column("description", overflow="fold")
    for key, type_name, _default, doc in describe_config(model):
        value = resolved
        for part in key.split("."):
            value = value.get(part) if isinstance(value, dict) else None
        table.add_row(key, type_name, str(value), doc)
    console.print(table)
