"""The import rules of DESIGN §1, checked by parsing every module's imports (function-level ones included).

- `pipeline/` imports nothing of ours but `pipeline`; `sim/` imports only `sim`.
- A stage's modules (`stages/<x>/...`) import `pipeline`, `sim`, their own stage, the shared modules at the top of
  `stages/` (the chain registry, the policy format) and an upstream stage's schema module, never another stage's
  run module; nothing under `stages/`, `sim/` or `pipeline/` imports the CLI or the benches.

Run alone: `.venv/bin/pytest -q tests/test_import_rules.py`.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

# Upstream schema modules (one per artifact, read by its writer and its readers).
SCHEMA_MODULES = {"drivesim.stages.ingest.trace", "drivesim.stages.preprocess.artifact"}
# Packages at the top of stages/ that are shared, not stages: the policy (its network, run files and ONNX runtime).
SHARED_PACKAGES = {"policy"}


def _module_name(file: Path) -> str:
    parts = list(file.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(["drivesim", *parts])


def imported_modules(file: Path) -> set[str]:
    """Every `drivesim...` module `file` imports, absolute or relative, at module or function level.

    `from drivesim.stages.x import y` counts as `drivesim.stages.x.y` (y may be a module).
    """
    name = _module_name(file)
    package = name if file.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(file.read_text(), filename=str(file))):
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
    return {m for m in found if m == "drivesim" or m.startswith("drivesim.")}


def _files(folder: str) -> list[Path]:
    return sorted((REPO / folder).rglob("*.py"))


def _violations(folder: str, allowed) -> list[str]:
    return [
        f"{file.relative_to(REPO)} imports {module}"
        for file in _files(folder)
        for module in sorted(imported_modules(file))
        if not allowed(file, module)
    ]


def _under(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def test_pipeline_imports_only_pipeline() -> None:
    assert _violations("pipeline", lambda file, m: _under(m, "drivesim.pipeline")) == []


def test_sim_imports_only_sim() -> None:
    assert _violations("sim", lambda file, m: _under(m, "drivesim.sim")) == []


def _stage_import_allowed(file: Path, module: str) -> bool:
    if _under(module, "drivesim.pipeline") or _under(module, "drivesim.sim") or module == "drivesim.stages":
        return True
    if not _under(module, "drivesim.stages"):
        return False  # the CLI, the benches
    parts = file.relative_to(REPO / "stages").parts
    if len(parts) == 1:
        return True  # the shared modules at the top of stages/ (chain registry and walker, policy format)
    target = module.split(".")[2]
    if target == parts[0] or target in SHARED_PACKAGES or (REPO / "stages" / f"{target}.py").is_file():
        return True  # its own stage, a shared top-level module or package
    if module.count(".") == 2:
        return True  # a stage package itself (its modules are checked)
    return any(_under(module, schema) for schema in SCHEMA_MODULES)


def test_no_stage_imports_another_stages_run_module() -> None:
    assert _violations("stages", _stage_import_allowed) == []


@pytest.mark.parametrize(
    ("file", "module", "allowed"),
    [
        ("stages/world/build.py", "drivesim.stages.preprocess.run", False),
        ("stages/world/build.py", "drivesim.stages.preprocess.artifact", True),
        ("stages/world/build.py", "drivesim.stages.world.config", True),
        ("stages/world/build.py", "drivesim.cli.common", False),
        ("stages/world/build.py", "drivesim.diagnostics.fidelity", False),
        ("stages/chain.py", "drivesim.stages.world.stage", True),
        ("stages/evaluate/rollout.py", "drivesim.stages.policy.run_folder", True),
        ("stages/evaluate/rollout.py", "drivesim.stages.policy.onnx_runtime", True),
        ("stages/evaluate/rollout.py", "drivesim.stages.train.run", False),
    ],
)
def test_the_rule_itself(file: str, module: str, allowed: bool) -> None:
    assert _stage_import_allowed(REPO / file, module) is allowed


def test_function_level_imports_are_seen() -> None:
    # stage.py imports its run module inside the build function (so the registry stays light)
    assert "drivesim.stages.preprocess.run" in imported_modules(REPO / "stages/preprocess/stage.py")
