"""The fidelity benches on a tiny synthetic drive: mvs must beat the ground plane, the inserted car must sit where the
true one is and harmonization must bring it closer to the truth; numbers in sane ranges."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivesim.bench.fidelity import ViewOffset, depth_metrics, image_metrics, run_fidelity
from drivesim.pipeline.errors import ConfigError


def test_depth_metrics_values() -> None:
    gt = np.array([[10.0, 20.0], [np.inf, 100.0]], np.float32)
    est = np.array([[11.0, 20.0], [5.0, 5.0]], np.float32)
    m = depth_metrics(est, gt, max_depth_m=80.0)  # sky and beyond max depth are ignored
    assert m["pixels"] == 2
    assert m["abs_rel"] == pytest.approx(0.05)
    assert m["delta1"] == 1.0


def test_image_metrics_over_filled_pixels_only() -> None:
    rng = np.random.default_rng(0)
    truth = rng.integers(0, 256, (40, 50, 3), dtype=np.uint8)
    synth = truth.copy()
    valid = np.ones((40, 50), bool)
    valid[:, :10] = False
    synth[:, :10] = 0  # unfilled pixels do not count against PSNR
    m = image_metrics(synth, truth, valid)
    assert m["psnr_db"] > 90.0
    assert m["filled_fraction"] == pytest.approx(0.8)
    noisy = np.clip(truth.astype(int) + rng.integers(-20, 21, truth.shape), 0, 255).astype(np.uint8)
    assert 15.0 < image_metrics(noisy, truth, valid)["psnr_db"] < 30.0


@pytest.mark.slow
def test_fidelity_bench_mvs_beats_plane(tmp_path) -> None:
    figure = tmp_path / "fidelity.png"
    offsets = (ViewOffset(lateral_m=1.0), ViewOffset(yaw_deg=5.0))
    result = run_fidelity(
        seed=0, n_frames=9, width_px=192, height_px=120, offsets=offsets, n_view_frames=2, figure_path=figure
    )
    json.dumps(result.to_json())  # machine-readable
    assert result.evaluated_frames == [3, 4, 5]
    plane, mvs = result.depth["plane"], result.depth["mvs"]
    assert 0.3 < plane["abs_rel"] < 3.0  # buildings and cars are far off the ground plane
    assert mvs["abs_rel"] < 0.6 * plane["abs_rel"]
    assert mvs["delta1"] > plane["delta1"]
    lateral = {s: result.view("lat +1.0 m", s) for s in ("plane", "mvs", "ground_truth")}
    assert lateral["mvs"]["psnr_db"] > lateral["plane"]["psnr_db"] + 1.0
    assert lateral["ground_truth"]["psnr_db"] >= lateral["mvs"]["psnr_db"] - 0.5  # the upper bound
    for row in result.views:
        assert 10.0 < row["psnr_db"] < 50.0
        assert 0.2 < row["ssim"] <= 1.0
        assert 0.5 < row["filled_fraction"] <= 1.0
    assert figure.stat().st_size > 10_000


@pytest.mark.slow
def test_bench_fidelity_cli_json(tmp_path) -> None:
    from typer.testing import CliRunner

    from drivesim.cli.main import app

    figure = tmp_path / "f.png"
    report = tmp_path / "fidelity.md"
    args = ["-w", str(tmp_path), "bench", "fidelity", "--json", "--frames", "8", "--width", "128", "--height", "80"]
    args += ["--view-frames", "1", "--figure", str(figure), "--markdown", str(report), "--set", "mvs.num_hypotheses=16"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout[result.stdout.index("{") :])
    assert set(data["depth"]) == {"plane", "mvs"}
    assert len(data["views"]) == 5 * 3  # five offsets, three depth sources
    assert figure.is_file() and "| lat +1.0 m | mvs |" in report.read_text()
    bad = CliRunner().invoke(app, ["-w", str(tmp_path), "bench", "fidelity", "--set", "mvs.bogus=1"])
    assert isinstance(bad.exception, ConfigError) and "mvs.bogus" in str(bad.exception)


def test_car_fidelity_places_the_car_and_harmonization_helps() -> None:
    """The inserted car covers the true car's pixels, and harmonization brings it closer to the truth."""
    from drivesim.bench.car_fidelity import OFFSETS_M, VARIANTS, synthetic_rows

    rows, images = synthetic_rows(frames=1, seed=0)
    assert {(r["offset_m"], r["variant"]) for r in rows} == {(o, v) for o in OFFSETS_M for v in VARIANTS}
    assert set(images) == {"truth", *VARIANTS}
    by = {(r["offset_m"], r["variant"]): r for r in rows}
    for offset in OFFSETS_M:
        assert by[offset, "none"]["car_iou"] > 0.9  # right size, right place
        assert by[offset, "harmonization"]["psnr_car_db"] > by[offset, "none"]["psnr_car_db"] + 1.0
        assert by[offset, "harmonization"]["ssim_car"] > by[offset, "none"]["ssim_car"]
        # The scene's sun is high: a light raised towards it matches the truth better than the unlit car.
        assert by[offset, "lighting 45 deg up"]["psnr_car_db"] > by[offset, "none"]["psnr_car_db"] + 1.0
