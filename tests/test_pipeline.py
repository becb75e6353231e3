"""Workspace artifacts, manifests, staleness and config loading."""

from __future__ import annotations

import json
import sys
import types
from pathlib import Path

import pytest

from drivesim.chain.registry import CHAIN
from drivesim.pipeline.config import StageConfig, describe_config, load_config
from drivesim.pipeline.errors import ConfigError, MissingArtifactError
from drivesim.pipeline.stage import BuildContext, StageSpec, StageSummary, deferred_build, run_stage
from drivesim.pipeline.status import status_report
from drivesim.pipeline.workspace import Workspace, artifact_key


class _Image(StageConfig):
    width_px: int = 640
    """Working image width (pixels)."""
    keep_original: bool = False
    """Also store the frames at their recorded resolution."""


class _Demo(StageConfig):
    image: _Image = _Image()
    """Image settings."""
    rate_hz: float = 10.0
    """Frame rate (Hz)."""


def _write(ws: Workspace, name: str, payload: bytes, config: dict | None = None, inputs: dict | None = None) -> None:
    with ws.write_artifact(name, "demo", config or {}, inputs or {}) as build:
        (build.dir / "data.bin").write_bytes(payload)
        build.summary["size"] = len(payload)


def test_artifact_written_atomically_with_manifest(tmp_path: Path) -> None:
    ws = Workspace(tmp_path / "ws")
    _write(ws, "trace", b"abc", config={"x": 1})
    manifest = ws.read_manifest("trace")
    assert manifest is not None
    assert manifest["stage"] == "demo"
    assert manifest["config"] == {"x": 1}
    assert manifest["outputs"]["data.bin"]["size_bytes"] == 3
    assert manifest["summary"] == {"size": 3}
    assert [p.name for p in (tmp_path / "ws").iterdir()] == ["trace"]


def test_failed_build_leaves_previous_artifact_and_no_temporaries(tmp_path: Path) -> None:
    ws = Workspace(tmp_path / "ws")
    _write(ws, "trace", b"first")
    with pytest.raises(KeyboardInterrupt), ws.write_artifact("trace", "demo", {}, {}) as build:
        (build.dir / "data.bin").write_bytes(b"half")
        raise KeyboardInterrupt
    assert (ws.artifact_dir("trace") / "data.bin").read_bytes() == b"first"
    assert sorted(p.name for p in ws.root.iterdir()) == ["trace"]


def test_rebuild_replaces_artifact(tmp_path: Path) -> None:
    ws = Workspace(tmp_path / "ws")
    _write(ws, "trace", b"first")
    _write(ws, "trace", b"second")
    assert (ws.artifact_dir("trace") / "data.bin").read_bytes() == b"second"
    assert sorted(p.name for p in ws.root.iterdir()) == ["trace"]


def test_freshness_follows_key_and_files(tmp_path: Path) -> None:
    ws = Workspace(tmp_path / "ws")
    inputs = {"recording": Workspace.external_input(_external(tmp_path))}
    _write(ws, "trace", b"abc", config={"x": 1}, inputs=inputs)
    key = ws.read_manifest("trace")["key"]
    assert ws.is_fresh("trace", key)
    assert not ws.is_fresh("trace", artifact_key("demo", "other-config-hash", inputs))
    (ws.artifact_dir("trace") / "data.bin").write_bytes(b"truncated!")
    assert not ws.is_fresh("trace", key)


def _external(tmp_path: Path) -> Path:
    path = tmp_path / "drive.bag"
    path.write_bytes(b"recording")
    return path


def test_status_reports_missing_fresh_and_stale(tmp_path: Path) -> None:
    ws = Workspace(tmp_path / "ws")
    recording = _external(tmp_path)
    _write(ws, "trace", b"abc", inputs={"recording": Workspace.external_input(recording)})
    _write(ws, "preprocessed", b"p", inputs={"trace": ws.artifact_input("trace")})
    states = {row["stage"]: row["state"] for row in status_report(ws, CHAIN)["stages"]}
    assert states["ingest"] == "fresh" and states["preprocess"] == "fresh" and states["build-world"] == "missing"

    _write(ws, "trace", b"new content")  # upstream rebuilt: downstream is stale
    report = {row["stage"]: row for row in status_report(ws, CHAIN)["stages"]}
    assert report["preprocess"]["state"] == "stale"
    assert "input trace changed" in report["preprocess"]["reasons"]

    recording.write_bytes(b"another recording")
    _write(ws, "trace", b"abc", inputs={"recording": Workspace.external_input(tmp_path / "drive.bag")})
    recording.write_bytes(b"edited again")
    report = {row["stage"]: row for row in status_report(ws, CHAIN)["stages"]}
    assert report["ingest"]["state"] == "stale"
    assert json.loads(json.dumps(status_report(ws, CHAIN)))["format"] == 1


class _DemoSummary(StageSummary):
    width_px: int
    """The configured width (px)."""


def test_a_spec_with_defaults_and_a_deferred_build_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """command and preset default to the stage's name; the build module is imported when the stage runs, not before."""
    spec = StageSpec(
        name="demo",
        artifact="demo-out",
        config_model=_Demo,
        summary_model=_DemoSummary,
        build=deferred_build("drivesim_demo_build:build"),  # no such module yet
    )
    assert (spec.command, spec.preset, spec.requires) == ("drivesim demo", "demo", ())

    def build(ctx: BuildContext) -> _DemoSummary:
        (ctx.dir / "width.txt").write_text(str(ctx.config.image.width_px))  # type: ignore[attr-defined]
        return _DemoSummary(width_px=ctx.config.image.width_px)  # type: ignore[attr-defined]

    monkeypatch.setitem(sys.modules, "drivesim_demo_build", types.SimpleNamespace(build=build))
    ws = Workspace(tmp_path / "ws")
    result = run_stage(ws, spec, _Demo(image=_Image(width_px=320)))
    assert result.summary == _DemoSummary(width_px=320) and not result.skipped
    assert (result.path / "width.txt").read_text() == "320"
    assert ws.read_manifest("demo-out")["command"] == "drivesim demo"  # type: ignore[index]
    assert run_stage(ws, spec, _Demo(image=_Image(width_px=320))).skipped


def test_require_names_the_command_to_run(tmp_path: Path) -> None:
    with pytest.raises(MissingArtifactError, match="drivesim ingest PATH"):
        Workspace(tmp_path).require("trace", "drivesim ingest PATH")


def test_config_layers_and_overrides(tmp_path: Path) -> None:
    cfg_file = tmp_path / "c.yaml"
    cfg_file.write_text("rate_hz: 20\nimage:\n  width_px: 320\n")
    cfg = load_config(_Demo, config_file=cfg_file, overrides=["image.keep_original=true"])
    assert cfg.rate_hz == 20.0
    assert cfg.image.width_px == 320
    assert cfg.image.keep_original is True
    cfg = load_config(_Demo, config_file=cfg_file, overrides=["image.width_px=480"])
    assert cfg.image.width_px == 480


def test_unknown_key_names_key_and_valid_ones() -> None:
    with pytest.raises(ConfigError) as err:
        load_config(_Demo, overrides=["image.widht_px=3"])
    assert "image.widht_px" in str(err.value)
    assert "keep_original, width_px" in str(err.value)


def test_bad_value_and_bad_file_are_config_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="rate_hz"):
        load_config(_Demo, overrides=["rate_hz=fast"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("- a list\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(_Demo, config_file=bad)
    with pytest.raises(ConfigError, match="not found"):
        load_config(_Demo, config_file=tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        load_config(_Demo, overrides=["rate_hz"])


def test_field_docstrings_become_descriptions() -> None:
    rows = {key: (default, doc) for key, _, default, doc in describe_config(_Demo)}
    assert rows["image.width_px"] == (640, "Working image width (pixels).")
    assert rows["rate_hz"][1] == "Frame rate (Hz)."
