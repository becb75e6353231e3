"""A tiny synthetic drive (the synth API) through `drivesim ingest` -> `preprocess` -> `build-world` (the CLI).

The synthetic recording carries its ground-truth vehicle poses, so the world's reference path is checked against
the truth: its length, its heading change and its shape (positions after removing the GPS origin offset).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import drivesim_ok

from drivesim.sim.geometry import yaw_of
from drivesim.sim.image_stack import ImageStack
from drivesim.sim.world import World

pytestmark = pytest.mark.slow

DURATION_S = 1.5
WIDTH_PX, HEIGHT_PX = 320, 200


@pytest.fixture(scope="module")
def chain(tmp_path_factory) -> Path:
    from drivesim.pipeline.config import load_config
    from drivesim.stages.synth import synthesize as synthesize_module
    from drivesim.stages.synth.config import SynthConfig

    root = tmp_path_factory.mktemp("synth")
    cfg = load_config(
        SynthConfig,
        overrides=[
            "seed=3",
            f"drive.duration_s={DURATION_S}",
            f"camera.width_px={WIDTH_PX}",
            f"camera.height_px={HEIGHT_PX}",
            "world.scenery.view_distance_m=60",
            "world.road.length_m=100",
        ],
    )
    recording = root / "drive.mcap"
    synthesize_module.synthesize(cfg, recording)
    ws = root / "ws"
    drivesim_ok(ws, "ingest", str(recording))
    drivesim_ok(ws, "preprocess")
    drivesim_ok(ws, "build-world", "--set", "sim_width_px=80")
    return ws


def test_world_path_matches_ground_truth(chain: Path) -> None:
    world = World.load(chain / "world")
    with np.load(chain / "trace" / "ground_truth.npz") as data:
        gt_t_ns, gt_T = data["t_ns"], data["T_world_vehicle"]
    frame_t = world.path["t_ns"]
    assert world.frame_count == round(DURATION_S * 10)
    assert (world.width_px, world.height_px) == (80, 50)
    gt_x = np.interp(frame_t, gt_t_ns, gt_T[:, 0, 3])
    gt_y = np.interp(frame_t, gt_t_ns, gt_T[:, 1, 3])
    gt_yaw = np.interp(frame_t, gt_t_ns, np.unwrap(yaw_of(gt_T)))
    gt_length_m = np.hypot(np.diff(gt_x), np.diff(gt_y)).sum()
    assert world.path_length_m == pytest.approx(gt_length_m, rel=0.02)  # measured 1 %
    turn = np.unwrap(world.path["yaw_rad"])
    assert turn[-1] - turn[0] == pytest.approx(gt_yaw[-1] - gt_yaw[0], abs=np.radians(1.0))
    # the GPS ENU frame and the synth world share their axes: headings agree directly (measured 0.04 deg)
    assert np.degrees(np.abs(turn - gt_yaw).max()) < 1.0
    # the GPS ENU origin is the first (noisy) fix, not the synth world's origin: compare shapes up to a shift
    dx = (world.path["x_m"] - world.path["x_m"].mean()) - (gt_x - gt_x.mean())
    dy = (world.path["y_m"] - world.path["y_m"].mean()) - (gt_y - gt_y.mean())
    assert np.sqrt(np.mean(dx**2 + dy**2)) < 0.3  # measured 0.06 m


def test_world_frames_are_the_recorded_ones_and_status_is_fresh(chain: Path) -> None:
    world = World.load(chain / "world")
    frames = ImageStack(chain / "trace" / "frames.imgs")
    # the sim frame is the trace frame shrunk 4x by area averaging (then stored as JPEG: 1.5 grey levels on average
    # at this 80x50 size, up to 11 at edges)
    shrunk = frames[7].reshape(HEIGHT_PX // 4, 4, WIDTH_PX // 4, 4, 3).mean(axis=(1, 3))
    error = np.abs(world.frames[7].astype(float) - shrunk)
    assert error.mean() <= 2.5 and error.max() <= 20.0, (error.mean(), error.max())
    assert np.abs(world.frames[8].astype(float) - shrunk).mean() > 2.0 * error.mean()  # and not its neighbour
    report = json.loads(drivesim_ok(chain, "status", "--json").stdout)
    stages = {row["stage"]: row for row in report["stages"]}
    assert stages["build-world"]["state"] == "fresh"
    assert stages["build-world"]["summary"]["frame_count"] == world.frame_count
