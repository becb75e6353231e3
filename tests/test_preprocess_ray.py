"""`drivesim preprocess --backend ray` on a real Ray cluster on the loopback address (a head node and a worker node on
127.0.0.1): the camera-only (mvs) depth of a synthetic drive equals the one-process depth exactly, frame for frame
(each frame is computed by the same code from the same inputs, and one thread or two does not change a value); chunks
with a temporal window (each chunk also estimates the frames beyond its ends) give the same depth; a worker node killed
mid-run loses no frame; without Ray, --backend ray is one line saying how to install it; --address without
--backend ray is one line; a method other than mvs runs in the driver's process.

Run alone: `.venv/bin/pytest -q tests/test_preprocess_ray.py` (about 70 s on 2 cores at load 11).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from ray_loopback import LOOPBACK, TESTS_DIR, loopback_cluster

from drivesim.pipeline.config import load_config
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.preprocess.artifact import load_preprocessed
from drivesim.stages.preprocess.config import PreprocessConfig

FRAMES = 12
WIDTH_PX, HEIGHT_PX = 160, 100
# mvs, lighter than the default (16 planes instead of 48) so that the test stays short on 2 cores.
MVS = ["depth.method=mvs", "depth.mvs.num_hypotheses=16"]


@pytest.fixture(scope="module")
def cluster() -> Any:
    """A Ray cluster of one head node (1 CPU) on 127.0.0.1 for this module; tests add a worker node to it."""
    with loopback_cluster() as ray_cluster:
        yield ray_cluster


@pytest.fixture(scope="module")
def drive(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A workspace with the trace of a synthetic 12-frame drive (copied aside first: `ws-ray` has the trace only),
    preprocessed in this process; returns (the preprocessed workspace, the copy)."""
    from drivesim.stages.ingest.config import IngestConfig
    from drivesim.stages.ingest.stage import run_ingest
    from drivesim.stages.preprocess.stage import run_preprocess
    from drivesim.stages.synth import synthesize as synthesize_module
    from drivesim.stages.synth.config import SynthConfig

    root = tmp_path_factory.mktemp("ray-depth")
    overrides = ["seed=3", f"drive.duration_s={FRAMES / 10}", f"camera.width_px={WIDTH_PX}"]
    overrides += [f"camera.height_px={HEIGHT_PX}", "world.scenery.view_distance_m=60", "world.road.length_m=100"]
    synthesize_module.synthesize(load_config(SynthConfig, overrides=overrides), root / "drive.mcap")
    run_ingest(Workspace(root / "ws"), root / "drive.mcap", IngestConfig())
    shutil.copytree(root / "ws", root / "ws-ray")
    run_preprocess(Workspace(root / "ws"), load_config(PreprocessConfig, preset="preprocess", overrides=MVS))
    return root / "ws", root / "ws-ray"


def _drivesim(ws: Path, *args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """`drivesim --workspace ws ARGS` in a subprocess with this process's environment (the cluster's included)."""
    return subprocess.run(
        [sys.executable, "-m", "drivesim.cli.main", "--workspace", str(ws), *args],
        capture_output=True,
        text=True,
        timeout=240,
        env={**os.environ, **(env or {})},
    )


def test_preprocess_on_ray_gives_the_local_depth_frame_for_frame(cluster: Any, drive: tuple[Path, Path]) -> None:
    local_ws, ray_ws = drive
    worker = cluster.add_node(num_cpus=1, node_ip_address=LOOPBACK)
    cluster.wait_for_nodes()
    try:
        args = [a for s in MVS for a in ("--set", s)]
        result = _drivesim(ray_ws, "preprocess", *args, "--backend", "ray", "--address", cluster.address)
    finally:
        cluster.remove_node(worker)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "depth (mvs, on Ray)" in result.stderr and "preprocessed 12 frames" in result.stdout
    local = load_preprocessed(local_ws / "preprocessed")
    on_ray = load_preprocessed(ray_ws / "preprocessed")
    assert on_ray.depth_m.shape == (FRAMES, HEIGHT_PX, WIDTH_PX)
    for i in range(FRAMES):
        assert np.array_equal(on_ray.depth_m[i], local.depth_m[i]), f"frame {i} differs"
    depth_m = np.asarray(local.depth_m)  # read one frame at a time from its image stack; 12 frames here
    near = depth_m[depth_m < 80.0]
    assert near.size > 0.3 * depth_m.size and 2.0 < np.median(near) < 40.0  # a real depth map, not a constant
    # The backend is not part of what the artifact is: the local backend finds the Ray run's artifact fresh.
    from drivesim.stages.preprocess.stage import run_preprocess

    cfg = load_config(PreprocessConfig, preset="preprocess", overrides=MVS)
    assert run_preprocess(Workspace(ray_ws), cfg).skipped


def test_a_killed_worker_node_loses_no_frame(cluster: Any, drive: tuple[Path, Path]) -> None:
    """Chunks of 1 frame with a temporal window of 1 (each chunk also estimates the frame beyond each end); the
    worker node is killed once both nodes have returned a chunk, and its chunks run again on the head."""
    import ray

    from drivesim.stages.preprocess.depth_mvs import mvs_depth
    from drivesim.stages.preprocess.depth_ray import MvsDrive, mvs_depth_ray

    local_ws, _ = drive
    pre = load_preprocessed(local_ws / "preprocessed")
    trace = local_ws / "trace"
    calib = json.loads((trace / "calibration.json").read_text())
    cfg = load_config(PreprocessConfig, overrides=[*MVS, "depth.mvs.temporal_window=1"]).depth
    job = MvsDrive(
        str(trace), (0, FRAMES, 1), np.asarray(calib["K"]), pre.poses["T_world_camera"],
        np.asarray(calib["T_vehicle_camera"]), calib.get("camera_height_m"), cfg,
    )  # fmt: skip
    expected = np.zeros((FRAMES, HEIGHT_PX, WIDTH_PX), np.float32)
    local_figures = mvs_depth(job.frames(), job.K, job.T_world_camera, job.T_vehicle_camera, job.camera_height_m,
                              cfg, expected)  # fmt: skip

    worker = cluster.add_node(num_cpus=1, node_ip_address=LOOPBACK)
    cluster.wait_for_nodes()
    done: list[Any] = []
    killed: list[int] = []

    def kill_the_worker_node_once_both_ran(chunk: Any) -> None:
        done.append(chunk)
        if not killed and len({c.node for c in done}) == 2:
            cluster.remove_node(worker, allow_graceful=False)
            killed.append(len(done))

    out = np.full_like(expected, np.nan)
    figures = mvs_depth_ray(job, out, cluster.address, frames_per_chunk=1, on_chunk=kill_the_worker_node_once_both_ran)
    assert not ray.is_initialized()  # the run's connection is closed; the cluster is the fixture's
    order = [(c.start, "head" if c.node == cluster.head_node.node_id else "worker") for c in done]
    assert killed and killed[0] < FRAMES, f"the worker node was not killed mid-run: {order}"
    assert sorted(c.start for c in done) == list(range(FRAMES)), order  # every chunk written once
    assert figures["ray_nodes"] == 2 and figures["ray_chunks"] == FRAMES
    for i in range(FRAMES):
        assert np.array_equal(out[i], expected[i]), f"frame {i} differs"
    assert {k: v for k, v in figures.items() if not k.startswith("ray_")} == local_figures


def test_without_ray_backend_ray_is_one_line_saying_how_to_install(tmp_path: Path) -> None:
    from test_preprocess_stage_fakes import make_trace

    hidden = tmp_path / "no-ray"
    (hidden / "ray").mkdir(parents=True)
    (hidden / "ray" / "__init__.py").write_text("raise ImportError(\"No module named 'ray'\")\n")
    make_trace(Workspace(tmp_path / "ws"))
    result = _drivesim(
        tmp_path / "ws", "preprocess", "--backend", "ray", env={"PYTHONPATH": f"{hidden}{os.pathsep}{TESTS_DIR}"}
    )
    assert result.returncode == 2, result.stdout + result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "pip install 'drivesim[ray]'" in lines[0], result.stderr
    assert not (tmp_path / "ws" / "preprocessed").exists()


def test_address_without_backend_ray_is_one_line(tmp_path: Path) -> None:
    result = _drivesim(tmp_path / "ws", "preprocess", "--address", "127.0.0.1:6379")
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.strip() == "error: --address is the Ray cluster's address: give it with --backend ray"


def test_a_method_other_than_mvs_runs_in_this_process(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Plane depth with the Ray backend never reaches Ray: the address (nobody listens there) is not even tried."""
    pytest.importorskip("ray", reason="the Ray backend needs `pip install 'drivesim[ray]'` (scripts/setup.sh)")
    from test_preprocess_stage_fakes import FRAME_COUNT, install_fake_poses, make_trace

    from drivesim.stages.preprocess.stage import run_preprocess

    ws = Workspace(tmp_path / "ws")
    make_trace(ws)
    install_fake_poses(monkeypatch)
    cfg = PreprocessConfig.model_validate({"depth": {"method": "plane"}, "backend": "ray", "address": "127.0.0.1:9"})
    result = run_preprocess(ws, cfg)
    assert result.summary.depth_method == "plane" and result.summary.frame_count == FRAME_COUNT
    assert "backend" not in ws.read_manifest("preprocessed")["config"]  # not part of the artifact's identity
