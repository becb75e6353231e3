"""The end of `drivesim run` and `drivesim eval`: the Table I rows (the policy, the expert and the run's warm start on
the same seeds, the paper's columns), the worlds the policy trained on and the report; the report's baselines, its
worst episodes without ties and its note on the task's geometry; the preset a user's recording gets."""

from __future__ import annotations

import json
import math
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import drivesim_with_fakes
from eval_fakes import FAKE, fake_world, pass_record, register_fake_envs
from test_eval_stage import _make_run

from drivesim.pipeline.workspace import Workspace
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.evaluate.metrics import evaluate_episode
from drivesim.stages.evaluate.report import geometry_note, worst_episodes
from drivesim.stages.evaluate.stage import run_eval
from drivesim.stages.evaluate.summary import RESULT_COLUMNS, result_table

NUMBER = r"(\d+\.\d{3})"


def _run_with_warm_start(tmp_path: Path, world: Path) -> Path:
    """A finished run folder (random weights) that trained on `world` and kept another policy as its warm start."""
    import torch

    from drivesim.policy.run_folder import build_net
    from drivesim.stages.train.run_files import write_json

    run = _make_run(tmp_path / "ws" / "runs" / "overtake-1", "overtake")
    config = json.loads((run / "config.json").read_text())
    write_json(run / "config.json", {**config, "worlds": [str(world)]})
    info = json.loads((run / "policy.json").read_text())
    torch.manual_seed(7)  # other weights than the final policy's
    (run / "checkpoints").mkdir()
    torch.save({"policy": build_net(info).state_dict()}, run / "checkpoints" / "warm_start.pt")
    return run


def _cli(ws: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return drivesim_with_fakes(ws, *args, timeout_s=300, OMP_NUM_THREADS="1")


def test_eval_of_a_run_shows_the_expert_and_the_warm_start_on_the_same_seeds(tmp_path: Path) -> None:
    register_fake_envs()
    world = fake_world(tmp_path / "drive_a")
    run = _run_with_warm_start(tmp_path, world)
    cfg = EvalConfig(world=str(world), policy=str(run), episodes=6, baseline_episodes=4, workers=1, **FAKE)
    result = run_eval(Workspace(tmp_path / "ws"), cfg, trust_entry_point=True)
    data = json.loads((result.path / "metrics.json").read_text())
    rows = {row["row"]: row for row in data["baselines"]}
    assert list(rows) == ["overtake-1 (same seeds)", "expert", "warm start"]
    assert all(row["episodes"] == 4 and row["seeds"] == [0, 3] for row in rows.values())
    assert rows["warm start"]["policy"] == str(run / "checkpoints" / "warm_start.pt")
    # The fake env's expert steers around the front car; a random-weight network does not, on the same starts.
    policy_rate = rows["overtake-1 (same seeds)"]["intervention"]["value"]
    assert rows["expert"]["intervention"]["value"] <= 0.25 < policy_rate
    for row in rows.values():
        for key in ("intervention", "success", "collision", "off_lane", "over_rotation"):
            assert 0.0 <= row[key]["value"] <= 1.0 and row[key]["n"] == 4
        assert row["max_deviation_m"]["value"] >= 0.0
    # The policy's own row on the same seeds is its first 4 episodes of the 6.
    first_four = [json.loads((result.path / "episodes" / f"{s}.json").read_text())["success"] for s in range(4)]
    assert rows["overtake-1 (same seeds)"]["success"]["value"] == pytest.approx(sum(first_four) / 4)
    assert data["trained_on"] == [{"world": "drive_a", "path": str(world.resolve())}]
    assert "1-2 m from the lane centre" in data["geometry_note"]
    report = (result.path / "report.html").read_text()
    assert "Beside the expert and the warm start, on the same seeds" in report
    assert "<th>trained on</th><td>drive_a</td>" in report and "Our task&#x27;s geometry" in report

    table = result_table(result.path)
    assert table is not None and table.trained_on == ["drive_a"] and table.report == result.path / "report.html"
    names = [row.name for row in table.rows]
    assert names == [
        "overtake-1 (all episodes)",
        "overtake-1 (same seeds)",
        "expert",
        "warm start",
        "paper, garage",
        "paper, outdoor",
    ]
    assert table.rows[0].episodes == 6 and table.rows[-1].episodes is None
    assert re.fullmatch(rf"{NUMBER} \[{NUMBER}, {NUMBER}\]", table.rows[0].cells["intervention"])
    assert table.rows[-2].cells["intervention"] == "0.129" and table.rows[-1].cells["max_yaw_rad"] == "0.082"
    assert table.rows[-2].cells["success"] == ""  # the paper gives no success rate


def test_no_baselines_beside_the_expert_or_with_baseline_episodes_0(tmp_path: Path) -> None:
    register_fake_envs()
    world = fake_world(tmp_path / "world")
    ws = Workspace(tmp_path / "ws")
    expert = run_eval(ws, EvalConfig(world=str(world), episodes=2, workers=1, **FAKE), trust_entry_point=True)
    data = json.loads((expert.path / "metrics.json").read_text())
    assert data["baselines"] == [] and data["trained_on"] is None
    assert [row.name for row in result_table(expert.path).rows][0] == "expert (all episodes)"
    run = _run_with_warm_start(tmp_path, world)
    cfg = EvalConfig(world=str(world), policy=str(run), episodes=2, baseline_episodes=0, workers=1, **FAKE)
    none = run_eval(ws, cfg, trust_entry_point=True)
    assert json.loads((none.path / "metrics.json").read_text())["baselines"] == []


def test_drivesim_eval_ends_with_the_table_the_worlds_trained_on_and_the_report(tmp_path: Path) -> None:
    world = fake_world(tmp_path / "drive_a")
    run = _run_with_warm_start(tmp_path, world)
    args = ["eval", "--world", str(world), "--policy", str(run), "--episodes", "3", "--workers", "1"]
    args += ["--set", "baseline_episodes=2", "--set", f"env_id={FAKE['env_id']}"]
    args += ["--set", f"env_entry_point={FAKE['env_entry_point']}", "--trust-entry-point"]
    done = _cli(tmp_path / "ws", *args)
    assert done.returncode == 0, done.stderr[-2000:]
    out = done.stdout
    lines = {line.split("│")[1].strip(): line for line in out.splitlines() if line.count("│") > 5}
    for name in ("overtake-1 (all episodes)", "overtake-1 (same seeds)", "expert", "warm start", "paper, garage"):
        assert name in lines, out
    cells = [c.strip() for c in lines["expert"].split("│")[2:-1]]
    assert cells[0] == "2" and len(cells) == 1 + len(RESULT_COLUMNS)
    assert re.fullmatch(rf"{NUMBER} \[{NUMBER}, {NUMBER}\]", cells[1]) and 0 <= float(cells[2]) <= 1
    assert "trained on: drive_a" in out and "Our task's geometry" in out
    report_lines = [line for line in out.splitlines() if line.startswith("report: ")]
    assert len(report_lines) == 1 and Path(report_lines[0][len("report: ") :]).is_file()


def _with_pass(seed: int, lateral_m: float, reached_m: float, winnable: bool | None, pass_distance_m: float = 6.0):
    """An episode whose largest pass margin is `reached_m` (so `pass_distance_m - reached_m` still to pass)."""
    record = pass_record(lateral_m, seed=seed, limits={"pass_distance_m": pass_distance_m})
    steps = len(record.trajectory["t_s"])
    record.trajectory["pass_margin_m"] = np.linspace(-10.0, reached_m, steps)
    record.episode["winnable"] = winnable
    return evaluate_episode(record)


def test_worst_episodes_put_winnable_failures_first_then_the_farthest_from_passing_then_the_seed() -> None:
    results = [
        _with_pass(1, 0.0, -2.0, winnable=False),  # collision, 8 m still to pass, but unwinnable
        _with_pass(2, 0.0, 1.0, winnable=True),  # collision, 5 m to pass
        _with_pass(3, 0.0, -1.0, winnable=True),  # collision, 7 m to pass
        _with_pass(4, 0.0, 1.0, winnable=True),  # the same as seed 2 but for the seed
        _with_pass(5, 3.0, 9.0, winnable=True),  # passed: a success, not among the worst
    ]
    assert [r.metrics.pass_shortfall_m for r in results[:3]] == [8.0, 5.0, 7.0]
    assert results[4].metrics.success and results[4].metrics.pass_shortfall_m == 0.0
    assert [r.metrics.seed for r in worst_episodes(results)] == [3, 2, 4, 1]
    assert [r.metrics.seed for r in worst_episodes(results, count=2)] == [3, 2]


def test_pass_shortfall_is_nan_without_a_pass_margin_or_a_pass_distance() -> None:
    record = pass_record(0.0, seed=1)  # no limits: no Z_pass recorded
    assert math.isnan(evaluate_episode(record).metrics.pass_shortfall_m)


def test_geometry_note_names_what_differs_from_the_papers_setup() -> None:
    note = geometry_note("overtake", {})
    assert note.startswith("Our task's geometry where it differs from the paper's: ") and "\n" not in note
    assert "6-15 m ahead" not in note  # the paper's range: not a difference
    assert "the front car 1-2 m from the lane centre, heading along the road (paper: 1-2 m from the ego" in note
    assert "a training collision at any overlap (paper 5 %)" in note and "passed 6 m ahead" in note
    farther = geometry_note("overtake", {"front_distance_m": [8.0, 20.0], "front_side": "left"})
    assert "the front car 8-20 m ahead (paper 6-15 m), 1-2 m from the lane centre, on the left" in farther
    assert "above 5 % overlap" not in geometry_note("overtake", {"collision_overlap_train": 0.05})
    assert geometry_note("lane", {}) == ""


# ---------------------------------------------------------------- the preset a run gets


def test_a_recording_gets_the_recording_preset_and_the_demo_preset_only_when_asked(monkeypatch) -> None:
    from drivesim.chain import run as chain_run

    monkeypatch.setattr(chain_run, "gpu_available", lambda: False)
    assert chain_run.choose_run_preset(None) == "recording"
    assert chain_run.choose_run_preset("demo") == "demo"
    recording = chain_run.load_run_preset(chain_run.choose_run_preset(None))
    demo = chain_run.load_run_preset("demo")
    assert demo["train"]["time_limit_s"] < recording["train"]["time_limit_s"] <= 3600
    assert recording["chain"]["budget_s"] == 3600  # the whole chain in an hour: training gets what is left of it
    assert recording["train"]["total_steps"] > demo["train"]["total_steps"]
    assert recording["eval"]["episodes"] == 1000 and recording["eval"]["baseline_episodes"] == 200
    assert recording["train"]["warm_start"]["method"] == "expert" and recording["train"]["towns"] == []
    assert recording["train"]["ppo"]["learning_rate_end_fraction"] == 0.0  # annealed: the final weights settle
    assert "device" not in recording["train"]  # no GPU: the stage's own default (cpu)


def test_the_recording_preset_uses_a_gpu_when_torch_sees_one_and_the_user_can_override_it(monkeypatch) -> None:
    from drivesim.chain import run as chain_run

    monkeypatch.setattr(chain_run, "gpu_available", lambda: True)
    recording = chain_run.load_run_preset("recording")
    assert recording["train"]["device"] == "cuda"
    assert recording["train"]["envs"]["config"]["render_device"] == "cuda"
    assert recording["train"]["total_steps"] == 1000000  # the preset's other keys kept
    assert "device" not in chain_run.load_run_preset("demo")["train"]  # the demo stays as measured, on the CPU
    back = chain_run.load_run_preset("recording", overrides=["train.device=cpu", "train.envs.config.render_device=cpu"])
    assert back["train"]["device"] == "cpu" and back["train"]["envs"]["config"]["render_device"] == "cpu"


@pytest.mark.parametrize(
    ("args", "preset"),
    [(["run", "REC"], "recording"), (["run"], "recording"), (["run", "REC", "--preset", "demo"], "demo")],
)
def test_drivesim_run_chooses_the_preset(tmp_path: Path, monkeypatch, args: list[str], preset: str) -> None:
    from typer.testing import CliRunner

    from drivesim.chain import run as chain_run
    from drivesim.cli.main import app

    monkeypatch.setattr(chain_run, "gpu_available", lambda: False)
    seen: dict[str, object] = {}

    def fake_chain(ws, recording, overrides, **kwargs):
        seen.update(recording=recording, overrides=overrides)
        return chain_run.ChainRun(stages=[])

    monkeypatch.setattr(chain_run, "run_chain", fake_chain)
    args = [str(tmp_path / "rec.bag") if a == "REC" else a for a in args]
    done = CliRunner().invoke(app, ["--workspace", str(tmp_path / "ws"), *args])
    assert done.exit_code == 0, done.output
    assert seen["overrides"] == chain_run.load_run_preset(preset)


def test_drivesim_run_ends_with_the_table_the_worlds_and_one_report_line(tmp_path: Path, monkeypatch) -> None:
    from typer.testing import CliRunner

    from drivesim.chain import run as chain_run
    from drivesim.chain.walk import StageRun
    from drivesim.cli.main import app

    register_fake_envs()
    world = fake_world(tmp_path / "drive_a")
    run = _run_with_warm_start(tmp_path, world)
    cfg = EvalConfig(world=str(world), policy=str(run), episodes=3, baseline_episodes=2, workers=1, **FAKE)
    evaluated = run_eval(Workspace(tmp_path / "ws"), cfg, trust_entry_point=True)
    stages = [StageRun("train", run, False, 1.0), StageRun("eval", evaluated.path, False, 2.0)]
    monkeypatch.setattr(chain_run, "gpu_available", lambda: False)
    monkeypatch.setattr(
        chain_run, "run_chain", lambda *a, **k: chain_run.ChainRun(stages, report_html=evaluated.path / "report.html")
    )
    done = CliRunner().invoke(app, ["--workspace", str(tmp_path / "ws"), "run", str(tmp_path / "rec.bag")])
    assert done.exit_code == 0, done.output
    rows = {line.split("│")[1].strip(): line for line in done.output.splitlines() if line.count("│") > 5}
    assert {"overtake-1 (all episodes)", "expert", "warm start", "paper, outdoor"} <= set(rows), done.output
    assert "trained on: drive_a" in done.output
    assert [line for line in done.output.splitlines() if line.startswith("report: ")] == [
        f"report: {evaluated.path / 'report.html'}"
    ]


def test_the_policys_same_seeds_row_is_left_out_when_it_is_every_episode(tmp_path: Path) -> None:
    """With as many baseline episodes as episodes (the demo's 100 and 100), the policy's "same seeds" row would repeat
    its "all episodes" row: the table shows it once, beside the expert and the warm start."""
    register_fake_envs()
    world = fake_world(tmp_path / "drive_a")
    run = _run_with_warm_start(tmp_path, world)
    cfg = EvalConfig(world=str(world), policy=str(run), episodes=3, baseline_episodes=3, workers=1, **FAKE)
    result = run_eval(Workspace(tmp_path / "ws"), cfg, trust_entry_point=True)
    names = [row.name for row in result_table(result.path).rows]
    assert names[:3] == ["overtake-1 (all episodes)", "expert", "warm start"]
