"""`drivesim run --backend ray [--address A]` hands preprocess its backend, as `drivesim preprocess --backend` does;
a bad pair is one line (exit 2) before anything runs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from cli_helpers import run_main

import drivesim.chain.run as chain_run
from drivesim.chain.registry import CHAIN
from drivesim.chain.walk import chain_configs


def _capture_chain(monkeypatch: pytest.MonkeyPatch) -> dict[str, Any]:
    """Replace the chain by a recorder of the overrides `drivesim run` gives it."""
    seen: dict[str, Any] = {}

    def fake_run_chain(ws: Any, recording: Any, overrides: dict[str, Any], **kwargs: Any) -> Any:
        seen.update(overrides)
        raise SystemExit(0)

    monkeypatch.setattr(chain_run, "run_chain", fake_run_chain)
    return seen


def test_backend_ray_and_address_reach_preprocess(tmp_path: Path, monkeypatch, capsys) -> None:
    pytest.importorskip("ray")
    seen = _capture_chain(monkeypatch)
    code, err = run_main(tmp_path / "ws", "run", "--backend", "ray", "--address", "auto", monkeypatch=monkeypatch,
                         capsys=capsys)  # fmt: skip
    assert code == 0, err
    assert seen["preprocess"]["backend"] == "ray" and seen["preprocess"]["address"] == "auto"
    configs = {spec.name: cfg for spec, cfg in zip(CHAIN, chain_configs(CHAIN, seen), strict=True)}
    assert configs["preprocess"].backend == "ray" and configs["preprocess"].address == "auto"


def test_without_backend_preprocess_runs_here(tmp_path: Path, monkeypatch, capsys) -> None:
    seen = _capture_chain(monkeypatch)
    code, err = run_main(tmp_path / "ws", "run", monkeypatch=monkeypatch, capsys=capsys)
    assert code == 0, err
    configs = {spec.name: cfg for spec, cfg in zip(CHAIN, chain_configs(CHAIN, seen), strict=True)}
    assert configs["preprocess"].backend == "local" and configs["preprocess"].address is None


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--backend", "gpu"], "--backend 'gpu': choose local or ray"),
        (["--address", "auto"], "--address is the Ray cluster's address: give it with --backend ray"),
    ],
)
def test_a_bad_backend_is_one_line(tmp_path: Path, monkeypatch, capsys, args: list[str], message: str) -> None:
    seen = _capture_chain(monkeypatch)
    code, err = run_main(tmp_path / "ws", "run", *args, monkeypatch=monkeypatch, capsys=capsys)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and message in lines[0], err
    assert not seen and "Traceback" not in err
