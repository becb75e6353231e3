"""Descriptions a user reads stay short and say what a key does: every config field of every stage (the env's
included) has a description of at most 200 characters, every CLI option's help is at most 200 characters, and no
code comment in the product packages carries a date (comments say what and why, not when)."""

from __future__ import annotations

import importlib
import inspect
import io
import pkgutil
import re
import tokenize
from collections.abc import Iterator
from pathlib import Path

import click
import typer.main
from pydantic import BaseModel

import drivesim.stages

REPO = Path(__file__).resolve().parents[1]
PRODUCT_PACKAGES = ("cli", "pipeline", "stages", "sim", "policy", "bench", "chain")
MAX_DESCRIPTION_CHARS = 200
DATE = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")


def config_modules() -> list[str]:
    """Every stage's config module and every other module with user-facing config models (env, pipeline, chain)."""
    stages = [
        f"drivesim.stages.{m.name}.config"
        for m in pkgutil.iter_modules(drivesim.stages.__path__)
        if m.ispkg and (REPO / "stages" / m.name / "config.py").exists()
    ]
    others = ["drivesim.sim.envs.config", "drivesim.pipeline.config", "drivesim.pipeline.stage"]
    return [*stages, *others, "drivesim.chain.run", "drivesim.chain.towns", "drivesim.chain.walk"]


def models(model: type[BaseModel], seen: set[type[BaseModel]]) -> Iterator[type[BaseModel]]:
    """The model and every model nested in its fields (in unions and lists too), each once."""
    if model in seen:
        return
    seen.add(model)
    yield model
    for field in model.model_fields.values():
        stack = [field.annotation]
        while stack:
            annotation = stack.pop()
            if inspect.isclass(annotation) and issubclass(annotation, BaseModel):
                yield from models(annotation, seen)
            stack.extend(getattr(annotation, "__args__", ()))


def config_fields() -> list[tuple[str, str]]:
    """(model.field, description) of every field of every config model."""
    seen: set[type[BaseModel]] = set()
    fields = []
    for name in config_modules():
        module = importlib.import_module(name)
        for obj in vars(module).values():
            if inspect.isclass(obj) and issubclass(obj, BaseModel) and obj.__module__ == module.__name__:
                for model in models(obj, seen):
                    fields += [(f"{model.__name__}.{k}", f.description or "") for k, f in model.model_fields.items()]
    return fields


def test_the_stage_configs_are_all_walked() -> None:
    names = {name.split(".")[0] for name, _ in config_fields()}
    for model in ("TrainConfig", "EvalConfig", "EnvConfig", "DepthConfig", "IngestConfig", "WorldConfig"):
        assert model in names
    assert len(config_fields()) > 200


def test_every_config_field_has_a_short_description() -> None:
    fields = config_fields()
    missing = [name for name, text in fields if not text.strip()]
    too_long = [f"{name} ({len(text)} chars)" for name, text in fields if len(text) > MAX_DESCRIPTION_CHARS]
    assert not missing, f"config fields without a description: {missing}"
    assert not too_long, f"config descriptions over {MAX_DESCRIPTION_CHARS} characters: {too_long}"


def cli_commands() -> list[tuple[str, click.Command]]:
    """(command path, click command) of drivesim itself and every command and group under it."""
    from drivesim.cli.main import app

    commands = []
    stack: list[tuple[str, click.Command]] = [("drivesim", typer.main.get_command(app))]
    while stack:
        path, command = stack.pop()
        commands.append((path, command))
        stack += [(f"{path} {name}", sub) for name, sub in getattr(command, "commands", {}).items()]
    return commands


def option_helps() -> list[tuple[str, str]]:
    """(command option, help) of every option and argument of every drivesim command."""
    return [
        (f"{path} {param.name}", getattr(param, "help", None) or "")
        for path, command in cli_commands()
        for param in command.params
    ]


def test_every_cli_option_help_is_short() -> None:
    helps = option_helps()
    assert any(name == "drivesim eval policy" for name, _ in helps)
    too_long = [f"{name} ({len(text)} chars)" for name, text in helps if len(text) > MAX_DESCRIPTION_CHARS]
    assert not too_long, f"option help texts over {MAX_DESCRIPTION_CHARS} characters: {too_long}"


def dated_comments(source: str) -> list[tuple[int, str]]:
    """(line, comment) of every `#` comment in a Python source that holds a date like 2026-11-27."""
    tokens = tokenize.generate_tokens(io.StringIO(source).readline)
    return [(t.start[0], t.string) for t in tokens if t.type == tokenize.COMMENT and DATE.search(t.string)]


def test_dated_comments_are_found() -> None:
    assert dated_comments("x = 1  # the default until 2026-11-27\ny = '2026-11-27'  # a plain comment\n") == [
        (1, "# the default until 2026-11-27")
    ]


def test_no_code_comment_in_the_product_carries_a_date() -> None:
    found = []
    for package in PRODUCT_PACKAGES:
        for path in sorted((REPO / package).rglob("*.py")):
            found += [f"{path.relative_to(REPO)}:{line}: {text}" for line, text in dated_comments(path.read_text())]
    assert not found, "dated comments (say what and why, not when):\n" + "\n".join(found)


def view_config_fields() -> list[tuple[str, str]]:
    """(field, docstring) of every field of sim/view.py's ViewConfig, read from its source (`drivesim config` shows
    these under the env's view)."""
    import ast

    tree = ast.parse((REPO / "sim" / "view.py").read_text())
    view = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == "ViewConfig")
    fields = []
    for before, node in zip(view.body, view.body[1:], strict=False):
        if isinstance(before, ast.AnnAssign) and isinstance(before.target, ast.Name):
            text = node.value.value if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) else ""
            fields.append((before.target.id, " ".join(str(text).split())))
    return fields


def test_every_view_config_field_has_a_short_description() -> None:
    from drivesim.sim.view import ViewConfig

    fields = view_config_fields()
    assert {name for name, _ in fields} == set(ViewConfig.model_fields)
    missing = [name for name, text in fields if not text]
    too_long = [f"ViewConfig.{name} ({len(text)} chars)" for name, text in fields if len(text) > MAX_DESCRIPTION_CHARS]
    assert not missing, f"ViewConfig fields without a description: {missing}"
    assert not too_long, f"ViewConfig descriptions over {MAX_DESCRIPTION_CHARS} characters: {too_long}"


def command_summaries() -> list[tuple[str, str]]:
    """(command, first paragraph of its help: the summary `drivesim --help` lists) of every drivesim command."""
    return [
        (path, " ".join((command.help or "").split("\n\n")[0].split()))
        for path, command in cli_commands()
        if path != "drivesim"  # the app's own help heads `drivesim --help`; it is in no command list
    ]


def test_every_command_summary_is_one_short_line() -> None:
    summaries = dict(command_summaries())
    assert {"drivesim towns build", "drivesim export onnx", "drivesim bench stereo", "drivesim train"} <= set(summaries)
    too_long = [f"{name} ({len(text)} chars)" for name, text in summaries.items() if len(text) > 100]
    missing = [name for name, text in summaries.items() if not text]
    assert not too_long, f"command summaries over 100 characters (put the details in a second paragraph): {too_long}"
    assert not missing, f"commands without a help text: {missing}"
