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
from drivesim.pipeline.input_paths import special_kind

ConfigT = TypeVar("ConfigT", bound="StageConfig")


STRICT_MODEL_CONFIG = ConfigDict(
    extra="forbid", use_attribute_docstrings=True, validate_assignment=True, allow_inf_nan=False
)
"""What every config model (stage configs and their sections) shares: unknown keys refused, docstrings as field
descriptions, assignments validated, and no NaN or infinite float anywhere (`.nan`/`.inf` in YAML)."""


class StageConfig(BaseModel):
    """Base of every stage config: strict keys, finite floats, docstrings as field descriptions."""

    model_config = STRICT_MODEL_CONFIG


class ConfigSection(BaseModel):
    """Base of a nested section of a stage config (`ppo`, `policy`, ...): the same strict rules."""

    model_config = STRICT_MODEL_CONFIG


# Deeper YAML nesting than this is refused: configs are three levels deep, and PyYAML's composer recurses once per
# level, so a file nested a thousand deep would end in a RecursionError.
MAX_CONFIG_DEPTH = 32


class _UniqueKeyLoader(yaml.SafeLoader):
    """A YAML safe loader that refuses a mapping holding the same key twice (PyYAML keeps the last one silently) and
    nesting deeper than MAX_CONFIG_DEPTH."""

    _depth = 0

    def compose_node(self, parent: yaml.Node | None, index: Any) -> yaml.Node | None:  # noqa: D102
        self._depth += 1
        try:
            if self._depth > MAX_CONFIG_DEPTH:
                mark = self.peek_event().start_mark
                raise yaml.composer.ComposerError(None, None, f"nested more than {MAX_CONFIG_DEPTH} levels deep", mark)
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1


def _construct_unique_mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False) -> dict:
    loader.flatten_mapping(node)
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            hash(key)
        except TypeError:
            continue  # an unhashable key: construct_mapping below reports it
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None,
                None,
                f"duplicate key {key!r} (first on line {seen[key] + 1})",
                key_node.start_mark,
            )
        seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_unique_mapping)


def load_yaml_text(text: str) -> Any:
    """Parse YAML like `yaml.safe_load`, but a duplicate key is an error (yaml.YAMLError)."""
    return yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506  (a SafeLoader subclass)


def read_config_text(path: Path) -> str:
    """The text of a config file the user named, or ConfigError (one line) for a folder, a binary file, a file
    that does not exist or cannot be read."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError("is a folder; --config takes a YAML file", path)
    kind = special_kind(path)
    if kind is not None:  # a FIFO would block the read forever, a device never end
        raise ConfigError(f"is {kind}, not a regular file; --config takes a YAML file", path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError as e:
        raise ConfigError("config file not found", path) from e
    except PermissionError as e:
        raise ConfigError("permission denied reading the config file", path) from e
    except OSError as e:
        raise ConfigError(f"cannot read the config file: {e.strerror or e}", path) from e
    if b"\0" in raw[:8192]:
        raise ConfigError("is a binary file, not a YAML config", path)
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise ConfigError(f"is not UTF-8 text (byte {e.start}); --config takes a YAML file", path) from e


def preset_path(name: str) -> Path:
    """Path of the YAML preset `configs/<name>.yaml` shipped with drivesim."""
    return Path(str(importlib.resources.files("drivesim.configs").joinpath(f"{name}.yaml")))


def parse_override(text: str) -> tuple[list[str], Any]:
    """Split `a.b=c` into (["a", "b"], value), the value parsed as YAML (numbers, booleans, lists)."""
    if "=" not in text:
        raise ConfigError(f"--set {text!r}: expected KEY=VALUE (`drivesim config STAGE` lists the keys)")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key:
        raise ConfigError(f"--set {text!r}: the key is empty")
    try:
        value = load_yaml_text(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    return key.split("."), value


def _yaml_error_line(error: yaml.YAMLError) -> str:
    problem = getattr(error, "problem", None)
    mark = getattr(error, "problem_mark", None)
    if problem:
        return f"{problem} (line {mark.line + 1})" if mark is not None else str(problem)
    return str(error).splitlines()[0]


def _read_yaml(path: Path) -> dict[str, Any]:
    text = read_config_text(path)
    try:
        data = load_yaml_text(text) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"not valid YAML: {_yaml_error_line(e)}", path) from e
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


def validation_line(error: ValidationError, model: type[BaseModel] | None = None, source: str = "") -> str:
    """A pydantic ValidationError as one line: the first bad key, what is wrong, and how many more are."""
    errors = error.errors()
    first = errors[0]
    loc = tuple(first["loc"])
    dotted = ".".join(str(p) for p in loc)
    where = f" ({source})" if source else ""
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    msg = str(first["msg"]).removeprefix("Value error, ")
    if first["type"] == "extra_forbidden" and model is not None:
        parent = _model_at(model, loc[:-1])
        valid = ", ".join(sorted(parent.model_fields))
        return f"unknown config key {dotted!r}{where}; valid keys here: {valid}"
    if not dotted:
        return f"config{where}: {msg}{more}"
    return f"config key {dotted!r}{where}: {msg}{more}"


def _friendly(error: ValidationError, model: type[BaseModel], source: str) -> ConfigError:
    return ConfigError(validation_line(error, model, source))


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
    return _layer_and_validate(model, data, sources, config_file, overrides)


def load_config_over(
    model: type[ConfigT], base: dict[str, Any], config_file: Path | None = None, overrides: list[str] | None = None
) -> ConfigT:
    """A config from `base` (a saved config, e.g. a run's), then a user YAML file and `--set` overrides on top: only
    the keys the user gives change."""
    return _layer_and_validate(model, dict(base), ["saved config"], config_file, overrides)


def _layer_and_validate(
    model: type[ConfigT],
    data: dict[str, Any],
    sources: list[str],
    config_file: Path | None,
    overrides: list[str] | None,
) -> ConfigT:
    """`data` with a user YAML file and `--set` overrides on top, validated (one-line ConfigError naming the
    sources)."""
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
