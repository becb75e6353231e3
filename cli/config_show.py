"""`drivesim config STAGE`: every config key of a stage with its type, value and meaning."""

from __future__ import annotations

import importlib
from typing import Annotated

import typer
import yaml
from rich.table import Table

from drivesim.chain.registry import CHAIN, OFF_CHAIN_CONFIGS
from drivesim.cli.common import ConfigOption, console, set_option
from drivesim.pipeline.config import StageConfig, describe_config, load_config
from drivesim.pipeline.errors import ConfigError


def _stage_configs() -> dict[str, tuple[type[StageConfig], str]]:
    """Stage name -> (config model, preset): the chain registry plus the stages outside it (synth)."""
    configs = {spec.name: (spec.config_model, spec.preset) for spec in CHAIN}
    for name, (module, class_name, preset) in OFF_CHAIN_CONFIGS.items():
        configs[name] = (getattr(importlib.import_module(module), class_name), preset)
    return configs


_STAGE_NAMES = [spec.name for spec in CHAIN] + list(OFF_CHAIN_CONFIGS)


def config_command(
    stage: Annotated[str, typer.Argument(help=f"One of: {', '.join(_STAGE_NAMES)}.")],
    as_yaml: Annotated[
        bool, typer.Option("--yaml", help="Print the resolved config as YAML (a --config file).")
    ] = False,
    config: ConfigOption = None,
    set_: set_option("total_steps=4096") = None,
) -> None:
    """Show a stage's config keys: type, resolved value (preset + --config + --set) and description with units."""
    configs = _stage_configs()
    if stage not in configs:
        raise ConfigError(f"unknown stage {stage!r}; stages with a config: {', '.join(configs)}")
    model, preset = configs[stage]
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
        if "." not in key and key not in resolved:  # a key kept out of the artifact's identity (workers, backend)
            value = getattr(cfg, key, None)
        table.add_row(key, type_name, str(value), doc)
    console.print(table)
