"""Typed stage configs: defaults < YAML preset < `--config file.yaml` < repeated `--set a.b=c`.

Every stage config is a pydantic model built on `StageConfig`: unknown keys are refused, and each field's
docstring (with its unit) becomes its description, shown by `--help` and `drivesim config show`.
"""

from __future__ import annotations

import importlib.resources
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError

from drivesim.pipeline.errors import ConfigError

ConfigT = TypeVar("ConfigT", bound="StageConfig")


class StageConfig(BaseModel):
    """Base of every stage config: strict keys, docstrings as field descriptions."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True, validate_assignment=True)


def preset_path(name: str) -> Path:
    """Path of the YAML preset `configs/<name>.yaml` shipped with drivesim."""
    return Path(str(importlib.resources.files("drivesim.configs").joinpath(f"{name}.yaml")))


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split `a.b=c` into (["a", "b"], value), the value parsed as YAML (numbers, booleans, lists)."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected KEY=VALUE, e.g. --set image.width_px=640")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key:
        raise ConfigError(f"--set {text!r}: the key is empty")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    return key.split("."), value


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError as e:
        raise ConfigError("config file not found", path) from e
    except yaml.YAMLError as e:
        raise ConfigError(f"not valid YAML: {str(e).splitlines()[0]}", path) from e
    if not isinstance(data, dict):
        raise ConfigError("a config file must hold a mapping of keys to values", path)
    return data


def _merge(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _set_path(data: dict[str, Any], keys: list[str], value: Any) -> None:
    node = data
    for key in keys[:-1]:
        child = node.get(key)
        if not isinstance(child, dict):
            child = {}
            node[key] = child
        node = child
    node[keys[-1]] = value


def _model_at(model: type[BaseModel], loc: tuple[Any, ...]) -> type[BaseModel]:
    """The nested model class that holds the field at `loc` (for naming valid keys)."""
    current = model
    for part in loc:
        field = current.model_fields.get(str(part))
        annotation = getattr(field, "annotation", None)
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            current = annotation
        else:
            break
    return current


def _friendly(error: ValidationError, model: type[BaseModel], source: str) -> ConfigError:
    first = error.errors()[0]
    loc = tuple(first["loc"])
    dotted = ".".join(str(p) for p in loc)
    if first["type"] == "extra_forbidden":
        parent = _model_at(model, loc[:-1])
        valid = ", ".join(sorted(parent.model_fields))
        return ConfigError(f"unknown config key {dotted!r} ({source}); valid keys here: {valid}")
    return ConfigError(f"config key {dotted!r} ({source}): {first['msg']}")


def load_config(
    model: type[ConfigT],
    preset: str | None = None,
    config_file: Path | None = None,
    overrides: list[str] | None = None,
) -> ConfigT:
    """Build a stage config from its defaults, a named preset, a user YAML file and `--set` overrides."""
    data: dict[str, Any] = {}
    sources = []
    if preset is not None:
        path = preset_path(preset)
        if path.is_file():
            data = _merge(data, _read_yaml(path))
            sources.append(f"preset {preset}")
    if config_file is not None:
        data = _merge(data, _read_yaml(Path(config_file)))
        sources.append(str(config_file))
    for text in overrides or []:
        keys, value = parse_override(text)
        _set_path(data, keys, value)
    if overrides:
        sources.append("--set")
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise _friendly(e, model, " + ".join(sources) or "defaults") from None


def _type_name(annotation: Any) -> str:
    if get_origin(annotation) is Literal:
        return " | ".join(str(arg) for arg in get_args(annotation))
    if get_origin(annotation) is not None:  # unions, lists: their own text is clearer than their __name__
        return str(annotation).replace("typing.", "")
    return getattr(annotation, "__name__", str(annotation))


def describe_config(model: type[BaseModel], prefix: str = "") -> list[tuple[str, str, Any, str]]:
    """Every leaf key of a config model as (dotted key, type, default, description)."""
    rows = []
    for name, field in model.model_fields.items():
        key = f"{prefix}{name}"
        annotation = field.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            rows.extend(describe_config(annotation, prefix=key + "."))
        else:
            type_name = _type_name(annotation)
            rows.append((key, type_name, field.get_default(call_default_factory=True), field.description or ""))
    return rows
