"""The import rules of DESIGN §1, checked by parsing every module's imports (function-level ones included).

The packages form layers, lowest first; a package imports only its own layer's packages and those below it:

    pipeline, sim      the stage contract and shared infrastructure; the simulator (each imports only itself)
    policy             the driving policy's network, run files and ONNX runtime (pipeline, sim)
    stages             one package per stage (pipeline, sim, policy; see below)
    chain              the chain registry, its walker and the procedural towns (everything above)
    bench              the measurements behind `drivesim bench` (everything above)
    cli                the typer commands (everything)

A stage's modules (`stages/<x>/...`) import their own stage, an upstream stage's schema module and ingest's SfM
pipeline, never another stage's run module; `stages/` holds nothing but stage packages. No module reaches itself
through its imports (`if TYPE_CHECKING:` imports, which never run, aside).

Run alone: `.venv/bin/pytest -q tests/test_import_rules.py`.
"""

from __future__ import annotations

import ast
from collections.abc import Callable
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

LAYERS: dict[str, set[str]] = {
    "pipeline": {"pipeline"},
    "sim": {"sim"},
    "policy": {"pipeline", "sim", "policy"},
    "stages": {"pipeline", "sim", "policy", "stages"},
    "chain": {"pipeline", "sim", "policy", "stages", "chain"},
    "bench": {"pipeline", "sim", "policy", "stages", "chain", "bench"},
    "cli": {"pipeline", "sim", "policy", "stages", "chain", "bench", "cli", "configs"},
}
"""Each code folder -> the folders it may import from."""

# Upstream modules another stage may import: the artifact schemas (one per artifact, read by its writer and its
# readers) and the one SfM pipeline (ingest's videos, preprocess's camera-only recordings).
SCHEMA_MODULES = {"drivesim.stages.ingest.trace", "drivesim.stages.preprocess.artifact", "drivesim.stages.ingest.sfm"}


def _module_name(file: Path) -> str:
    parts = list(file.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(["drivesim", *parts])


def _type_checking_lines(tree: ast.AST) -> set[int]:
    """Line numbers inside `if TYPE_CHECKING:` blocks (imports there are for the type checker only)."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                lines.update(range(child.lineno, (child.end_lineno or child.lineno) + 1))
    return lines


def _is_deferred_build(node: ast.AST) -> bool:
    """A call `deferred_build("module:function")`: the stage contract imports that module when the stage runs."""
    return (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id == "deferred_build"
        and len(node.args) == 1
        and isinstance(node.args[0], ast.Constant)
        and isinstance(node.args[0].value, str)
    )


def imported_modules(file: Path, at_run_time: bool = False) -> set[str]:
    """Every `drivesim...` module `file` imports, absolute or relative, at module or function level.

    `from drivesim.stages.x import y` counts as `drivesim.stages.x.y` (y may be a module); a stage's
    `deferred_build("drivesim.stages.x.run:f")` counts as importing `drivesim.stages.x.run`. With `at_run_time`, the
    imports under `if TYPE_CHECKING:` are left out.
    """
    name = _module_name(file)
    package = name if file.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(file.read_text(), filename=str(file))
    skipped = _type_checking_lines(tree) if at_run_time else set()
    found: set[str] = set()
    for node in ast.walk(tree):
        if getattr(node, "lineno", None) in skipped:
            continue
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join([*base, node.module] if node.module else base)
            else:
                module = node.module or ""
            found.add(module)
            found.update(f"{module}.{alias.name}" for alias in node.names)
        elif _is_deferred_build(node):
            found.add(node.args[0].value.partition(":")[0])  # type: ignore[attr-defined]
    return {m for m in found if m == "drivesim" or m.startswith("drivesim.")}


def test_a_deferred_build_counts_as_an_import() -> None:
    assert "drivesim.stages.world.build" in imported_modules(REPO / "stages/world/stage.py")
    assert "drivesim.stages.world.build" in _module_graph()["drivesim.stages.world.stage"]


def _files(folder: str) -> list[Path]:
    return sorted((REPO / folder).rglob("*.py"))


def _violations(folder: str, allowed: Callable[[Path, str], bool]) -> list[str]:
    return [
        f"{file.relative_to(REPO)} imports {module}"
        for file in _files(folder)
        for module in sorted(imported_modules(file))
        if not allowed(file, module)
    ]


def _under(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def _layer_allows(file: Path, module: str) -> bool:
    folder = file.relative_to(REPO).parts[0]
    return module == "drivesim" or module.split(".")[1] in LAYERS[folder]


@pytest.mark.parametrize("folder", sorted(LAYERS))
def test_no_package_imports_a_layer_above_it(folder: str) -> None:
    assert _violations(folder, _layer_allows) == []


def _stage_import_allowed(file: Path, module: str) -> bool:
    if not _layer_allows(file, module):
        return False  # the chain, the benches, the CLI
    if not _under(module, "drivesim.stages") or module == "drivesim.stages":
        return True  # pipeline, sim, policy
    own = file.relative_to(REPO / "stages").parts[0]
    if module.split(".")[2] == own:
        return True  # its own stage
    if module.count(".") == 2:
        return True  # a stage package itself (its modules are checked)
    return any(_under(module, schema) for schema in SCHEMA_MODULES)


def test_no_stage_imports_another_stages_run_module() -> None:
    assert _violations("stages", _stage_import_allowed) == []


def test_stages_holds_only_stage_packages() -> None:
    """Every entry of stages/ is a stage's package (a shared module belongs a layer down, in pipeline/ or policy/)."""
    entries = [p for p in (REPO / "stages").iterdir() if p.name not in ("__init__.py", "__pycache__")]
    assert len(entries) >= 8
    assert [p.name for p in entries if not (p / "__init__.py").is_file()] == []


@pytest.mark.parametrize(
    ("rule", "file", "module", "allowed"),
    [
        ("stage", "stages/world/build.py", "drivesim.stages.preprocess.run", False),
        ("stage", "stages/world/build.py", "drivesim.stages.preprocess.artifact", True),
        ("stage", "stages/world/build.py", "drivesim.stages.world.config", True),
        ("stage", "stages/world/build.py", "drivesim.cli.common", False),
        ("stage", "stages/world/build.py", "drivesim.bench.fidelity", False),
        ("stage", "stages/train/stage.py", "drivesim.chain.towns", False),
        ("stage", "stages/train/stage.py", "drivesim.chain.registry", False),
        ("stage", "stages/evaluate/rollout.py", "drivesim.policy.run_folder", True),
        ("stage", "stages/evaluate/rollout.py", "drivesim.policy.onnx_runtime", True),
        ("stage", "stages/evaluate/rollout.py", "drivesim.stages.train.run", False),
        ("layer", "policy/run_folder.py", "drivesim.stages.train.config", False),
        ("layer", "policy/run_folder.py", "drivesim.pipeline.workspace", True),
        ("layer", "sim/warp.py", "drivesim.policy.net", False),
        ("layer", "chain/run.py", "drivesim.stages.train.stage", True),
        ("layer", "chain/run.py", "drivesim.cli.common", False),
        ("layer", "bench/fidelity.py", "drivesim.cli.common", False),
        ("layer", "cli/bench.py", "drivesim.bench.fidelity", True),
    ],
)
def test_the_rules_themselves(rule: str, file: str, module: str, allowed: bool) -> None:
    """The stage rule and the layer rule on imports whose answer is known."""
    check = {"stage": _stage_import_allowed, "layer": _layer_allows}[rule]
    assert check(REPO / file, module) is allowed


def _module_graph() -> dict[str, set[str]]:
    """Module -> the modules of ours it imports when it runs (a `from x import name` resolved to module x)."""
    modules = {_module_name(file): file for folder in LAYERS for file in _files(folder)}

    def resolve(module: str) -> str | None:
        while module and module not in modules:
            module = module.rpartition(".")[0]
        return module or None

    return {
        name: {r for m in imported_modules(file, at_run_time=True) if (r := resolve(m)) and r != name}
        for name, file in modules.items()
    }


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The groups of modules that reach each other through their imports (strongly connected, 2 or more)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for target in sorted(graph.get(node, ())):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            group = [stack.pop()]
            while group[-1] != node:
                group.append(stack.pop())
            if len(group) > 1:
                cycles.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return cycles


def test_no_module_reaches_itself_through_its_imports() -> None:
    assert import_cycles(_module_graph()) == []


def test_the_cycle_finder_finds_a_circle() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert import_cycles(graph) == [["a", "b", "c"]]
    assert import_cycles({"a": {"b"}, "b": set()}) == []


def test_function_level_imports_are_seen() -> None:
    # stage.py imports its run module inside the build function (so the registry stays light)
    assert "drivesim.stages.preprocess.run" in imported_modules(REPO / "stages/preprocess/stage.py")


def test_type_checking_imports_do_not_count_at_run_time() -> None:
    assert "drivesim.stages.evaluate.record" in imported_modules(REPO / "stages/evaluate/rollout.py")
    run_time = imported_modules(REPO / "stages/evaluate/rollout.py", at_run_time=True)
    assert "drivesim.stages.evaluate.record.RecordPlan" not in run_time
