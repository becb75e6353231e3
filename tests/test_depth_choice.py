"""The default depth method (`depth.method: auto`): the best the recording supports, lidar > stereo > mvs, the
same whether `drivesim preprocess` runs alone or inside `drivesim run`, and said on the console."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_preprocess_stage_fakes import add_lidar_wall, install_fake_poses, make_trace
from test_stereo_bench import write_wall_folder

from drivesim.chain.run import load_run_preset
from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import InputError
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.ingest.config import IngestConfig
from drivesim.stages.ingest.stage import run_ingest
from drivesim.stages.preprocess import stage
from drivesim.stages.preprocess.artifact import load_preprocessed
from drivesim.stages.preprocess.config import PreprocessConfig
from drivesim.stages.preprocess.depth import choose_method


def test_auto_prefers_lidar_then_stereo_then_the_camera_only_method() -> None:
    assert choose_method("auto", has_lidar=True, has_stereo=True)[0] == "lidar"
    assert choose_method("auto", has_lidar=False, has_stereo=True)[0] == "stereo"
    assert choose_method("auto", has_lidar=False, has_stereo=False)[0] == "mvs"
    assert choose_method("plane", has_lidar=True, has_stereo=True) == ("plane", "asked for")


def test_the_stage_alone_and_every_run_preset_default_to_auto() -> None:
    assert PreprocessConfig().depth.method == "auto"
    assert load_config(PreprocessConfig, preset="preprocess").depth.method == "auto"
    full = load_run_preset("full")
    assert full.get("preprocess", {}).get("depth", {}).get("method", "auto") == "auto"


def test_a_camera_only_trace_gets_mvs_and_a_lidar_trace_lidar(tmp_path: Path, monkeypatch, capsys) -> None:
    install_fake_poses(monkeypatch)
    camera_only = Workspace(tmp_path / "camera")
    make_trace(camera_only)
    assert stage.run_preprocess(camera_only, PreprocessConfig()).summary.depth_method == "mvs"
    assert "depth method: mvs (auto: camera only" in capsys.readouterr().err
    with_lidar = Workspace(tmp_path / "lidar")
    make_trace(with_lidar)
    add_lidar_wall(with_lidar.artifact_dir("trace"), scan_offset_s=0.0, scan_count=12, wall_x_m=25.0)
    result = stage.run_preprocess(with_lidar, PreprocessConfig())
    assert result.summary.depth_method == "lidar"
    assert load_preprocessed(result.path).origin["depth_method"] == "lidar"


def test_a_stereo_trace_gets_stereo_depth_of_the_right_scale(tmp_path: Path, capsys) -> None:
    write_wall_folder(tmp_path / "seq", n=4)  # a textured wall 10 m ahead at frame 0, 0.5 m nearer each frame
    ws = Workspace(tmp_path / "ws")
    run_ingest(ws, tmp_path / "seq", IngestConfig.model_validate({"image": {"width_px": 256}}))
    result = stage.run_preprocess(ws, PreprocessConfig())
    assert result.summary.depth_method == "stereo"
    assert "depth method: stereo (auto: the recording has a rectified second camera)" in capsys.readouterr().err
    depth = load_preprocessed(result.path).depth_m
    for i in range(4):
        assert np.median(depth[i][:, 64:]) == pytest.approx(10.0 - 0.5 * i, rel=0.03)
    # a method asked for still wins over the default
    plane = stage.run_preprocess(ws, PreprocessConfig.model_validate({"depth": {"method": "plane"}}))
    assert plane.summary.depth_method == "plane"


def test_stereo_asked_for_on_a_one_camera_trace_is_refused(tmp_path: Path, monkeypatch) -> None:
    install_fake_poses(monkeypatch)
    ws = Workspace(tmp_path / "ws")
    make_trace(ws)
    with pytest.raises(InputError, match="no second camera"):
        stage.run_preprocess(ws, PreprocessConfig.model_validate({"depth": {"method": "stereo"}}))
