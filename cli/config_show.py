"""`drivesim config STAGE`: every config key of a stage with its type, value and meaning."""

from __future__ import annotations

import importlib
from typing import Annotated, Any

import typer
import yaml
from pydantic import BaseModel
from rich.table import Table

from drivesim.chain.registry import CHAIN, OFF_CHAIN_CONFIGS
from drivesim.cli.common import ConfigOption, console, set_option
from drivesim.pipeline.config import StageConfig, describe_config, load_config, preset_path
from drivesim.pipeline.errors import ConfigError
from drivesim.sim.envs.config import EnvConfig
from drivesim.sim.envs.registry import TASK_NAMES, task_spec


def _stage_configs() -> dict[str, tuple[type[StageConfig], str]]:
    """Stage name -> (config model, preset): the chain registry plus the stages outside it (synth)."""
    configs = {spec.name: (spec.config_model, spec.preset) for spec in CHAIN}
    for name, (module, class_name, preset) in OFF_CHAIN_CONFIGS.items():
        configs[name] = (getattr(importlib.import_module(module), class_name), preset)
    return configs


_STAGE_NAMES = [spec.name for spec in CHAIN] + list(OFF_CHAIN_CONFIGS)


def _env_config_paths(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Dotted paths of the `EnvConfig` fields of a config model (train: envs.config; eval: env)."""
    paths = []
    for name, field in model.model_fields.items():
        annotation = field.annotation
        if isinstance(annotation, type) and issubclass(annotation, EnvConfig):
            paths.append(f"{prefix}{name}")
        elif isinstance(annotation, type) and issubclass(annotation, BaseModel):
            paths.extend(_env_config_paths(annotation, f"{prefix}{name}."))
    return paths


def _task_preset(stage: str, preset: str, task: str | None) -> str:
    """The task's own preset of the stage (`configs/train/<task>.yaml`) when there is one, else the stage's."""
    if task is None or not preset_path(f"{stage}/{task}").is_file():
        return preset
    return f"{stage}/{task}"


def _task_env_only(
    cfg: StageConfig, rows: list[tuple[str, str, Any, str]], resolved: dict[str, Any], task_values: bool
) -> list[tuple[str, str, Any, str]]:
    """With a task: the rows and `resolved` keep only the env keys that task reads (`config_keys()`); with
    `task_values`, valued as the task runs them (its `default_config()` under the keys set). Without a task: as
    they are."""
    task = getattr(cfg, "task", None)
    if task not in TASK_NAMES:
        return rows
    env_class = task_spec(task).env_class()
    keep = set(env_class.config_keys())
    for path in _env_config_paths(type(cfg)):
        *parents, name = path.split(".")
        env, node = cfg, resolved
        for part in parents:
            env, node = getattr(env, part), node[part]
        values = getattr(env, name)
        if task_values:
            values = env_class.config_with(values.model_dump(exclude_unset=True))
            node[name] = values.model_dump(mode="json")
        node[name] = {k: v for k, v in node[name].items() if k in keep}
        rows = [r for r in rows if not r[0].startswith(f"{path}.") or r[0].removeprefix(f"{path}.") in keep]
    return rows


def config_command(
    stage: Annotated[str, typer.Argument(help=f"One of: {', '.join(_STAGE_NAMES)}.")],
    as_yaml: Annotated[
        bool, typer.Option("--yaml", help="Print the resolved config as YAML (a --config file).")
    ] = False,
    config: ConfigOption = None,
    set_: set_option("total_steps=4096") = None,
    task: Annotated[
        str | None,
        typer.Option(
            "--task",
            help="For a stage with a task (train, eval): that task's preset, env keys and values "
            f"({', '.join(TASK_NAMES)}).",
            show_default=False,
        ),
    ] = None,
) -> None:
    """Show a stage's config keys: type, resolved value (preset + --config + --set) and description with units; the
    env keys are those of the config's task (`--task`)."""
    configs = _stage_configs()
    if stage not in configs:
        raise ConfigError(f"unknown stage {stage!r}; stages with a config: {', '.join(configs)}")
    model, preset = configs[stage]
    if task is not None and "task" not in model.model_fields:
        raise ConfigError(f"--task: the {stage} config has no task; drop --task (stages with one: train, eval)")
    if task is not None and task not in TASK_NAMES:
        raise ConfigError(f"--task {task!r}: choose one of {', '.join(TASK_NAMES)}")
    overrides = [*([f"task={task}"] if task is not None else []), *(set_ or [])]
    cfg = load_config(model, preset=_task_preset(stage, preset, task), config_file=config, overrides=overrides)
    resolved = cfg.model_dump(mode="json")
    # As YAML (a --config file) the env keys stay those given: eval's apply over a run's own.
    rows = _task_env_only(cfg, describe_config(model), resolved, task_values=not as_yaml)
    if as_yaml:
        print(yaml.safe_dump(resolved, sort_keys=False), end="")
        return
    table = Table(title=f"drivesim {stage} config (override with --set KEY=VALUE or --config FILE.yaml)")
    table.add_column("key", style="bold")
    table.add_column("type")
    table.add_column("value")
    table.add_column("description", overflow="fold")
    for key, type_name, _default, doc in rows:
        value = resolved
        for part in key.split("."):
            value = value.get(part) if isinstance(value, dict) else None
        if "." not in key and key not in resolved:  # a key kept out of the artifact's identity (workers, backend)
            value = getattr(cfg, key, None)
        table.add_row(key, type_name, str(value), doc)
    console.print(table)
