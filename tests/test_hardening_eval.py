"""Hardening of evaluation and exported policies: untrusted env entry points, a policy shape other than the one
recorded, edited ONNX metadata, and an evaluation's start-up and worker count for many episodes.

Each test goes through the entry point a user reaches (the CLI's error boundary, `run_eval`, `OnnxPolicy`) and checks
what the user would see: one line and exit code 2, nothing imported or called, nothing written.
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import pytest
from cli_helpers import run_main
from eval_fakes import FAKE, fake_world, pass_record, register_fake_envs

from drivesim.pipeline.config import load_config
from drivesim.pipeline.errors import ConfigError, DrivesimError
from drivesim.pipeline.workspace import Workspace
from drivesim.stages.evaluate import rollout
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.evaluate.rollout import EnvFactory, PolicySpec, run_episodes, write_episode
from drivesim.stages.evaluate.stage import run_eval

# A module that leaves a trace when it is imported and when its function is called.
CANARY = """
from pathlib import Path

HERE = Path(__file__).parent
(HERE / "imported").write_text("yes")


def run(*args, **kwargs):
    (HERE / "called").write_text("yes")
    return None
"""


@pytest.fixture
def canary(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A folder on the import path holding `canary_mod` (writes `imported` on import, `called` when run)."""
    folder = tmp_path / "canary"
    folder.mkdir()
    (folder / "canary_mod.py").write_text(CANARY)
    monkeypatch.syspath_prepend(str(folder))
    monkeypatch.delitem(sys.modules, "canary_mod", raising=False)
    return folder


def _eval_args(world: Path, entry_point: str, env_id: str = "evil/X-v0") -> list[str]:
    return [
        "eval",
        "--policy",
        "expert",
        "--world",
        str(world),
        "--episodes",
        "2",
        "--workers",
        "1",
        "--set",
        f"env_id={env_id}",
        "--set",
        f"env_entry_point={entry_point}",
    ]


def _error_lines(err: str) -> list[str]:
    return [line for line in err.strip().splitlines() if line.strip()]


# ---------------------------------------------------------------- env entry points


def test_os_system_as_entry_point_is_refused_and_never_called(tmp_path, monkeypatch, capsys):
    """`--set env_entry_point=os:system` (the probe): one line naming --trust-entry-point, os.system never called,
    no workspace written."""
    import os

    calls: list[object] = []
    monkeypatch.setattr(os, "system", lambda *a, **k: calls.append((a, k)) or 0)
    world = fake_world(tmp_path / "world")
    ws = tmp_path / "ws"
    code, err = run_main(ws, *_eval_args(world, "os:system"), monkeypatch=monkeypatch, capsys=capsys)
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1, err
    assert "env_entry_point 'os:system'" in lines[0] and "--trust-entry-point" in lines[0]
    assert calls == [] and not ws.exists()


def test_an_untrusted_entry_points_module_is_never_imported(tmp_path, monkeypatch, capsys, canary):
    """From --set and from a --config file: refused before the module is imported (importing runs its code)."""
    world = fake_world(tmp_path / "world")
    code, err = run_main(tmp_path / "ws", *_eval_args(world, "canary_mod:run"), monkeypatch=monkeypatch, capsys=capsys)
    assert code == 2 and len(_error_lines(err)) == 1 and "--trust-entry-point" in err, err
    config = tmp_path / "evil.yaml"
    config.write_text("env_id: evil/Y-v0\nenv_entry_point: canary_mod:run\n")
    args = ["eval", "--policy", "expert", "--world", str(world), "--episodes", "2", "--config", str(config)]
    code, err = run_main(tmp_path / "ws", *args, monkeypatch=monkeypatch, capsys=capsys)
    assert code == 2 and len(_error_lines(err)) == 1 and "--trust-entry-point" in err, err
    assert not (canary / "imported").exists() and not (canary / "called").exists()
    assert "canary_mod" not in sys.modules
    # A worker's env factory refuses it as well (a factory built without the stage's check).
    with pytest.raises(ConfigError, match="trust-entry-point"):
        EnvFactory("evil/Z-v0", {}, entry_point="canary_mod:run")()
    assert not (canary / "imported").exists()


def test_drivesim_run_refuses_an_untrusted_entry_point_before_its_first_stage(tmp_path, monkeypatch, capsys, canary):
    """`drivesim run --config` with an eval env_entry_point: one line before anything runs (not after training)."""
    config = tmp_path / "evil.yaml"
    config.write_text("eval:\n  env_id: evil/X-v0\n  env_entry_point: canary_mod:run\n")
    ws = tmp_path / "ws"
    code, err = run_main(ws, "run", "--config", str(config), monkeypatch=monkeypatch, capsys=capsys)
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1 and "--trust-entry-point" in lines[0], err
    assert not ws.exists() and not (canary / "imported").exists()


def test_a_module_named_in_env_id_is_never_imported(tmp_path, monkeypatch, capsys, canary):
    """gymnasium.make("module:Name-v0") imports `module` first: such an env_id is one line, nothing imported."""
    world = fake_world(tmp_path / "world")
    args = ["eval", "--policy", "expert", "--world", str(world), "--set", "env_id=canary_mod:X-v0"]
    code, err = run_main(tmp_path / "ws", *args, monkeypatch=monkeypatch, capsys=capsys)
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1 and "env_id" in lines[0] and "no ':'" in lines[0], err
    assert not (canary / "imported").exists() and not (tmp_path / "ws").exists()


@pytest.mark.parametrize(
    ("entry_point", "says"),
    [
        ("no_colon", "give module:Class"),
        ("no_such_module_xyz:Env", "cannot import no_such_module_xyz"),
        ("canary_mod:missing", "has no missing"),
        ("canary_mod:run", "not a gymnasium.Env subclass"),
        ("gymnasium:make", "not a gymnasium.Env subclass"),
    ],
)
def test_wrong_entry_points_are_one_line_even_when_trusted(tmp_path, monkeypatch, capsys, canary, entry_point, says):
    """With --trust-entry-point a wrong value is still one line and exit 2 (no traceback), and nothing is called."""
    world = fake_world(tmp_path / "world")
    args = [*_eval_args(world, entry_point), "--trust-entry-point"]
    code, err = run_main(tmp_path / "ws", *args, monkeypatch=monkeypatch, capsys=capsys)
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1 and says in lines[0], err
    assert "Traceback" not in err and not (canary / "called").exists()
    assert not (tmp_path / "ws").exists()


def test_a_trusted_env_class_of_ones_own_is_evaluated(tmp_path, monkeypatch, capsys):
    """--trust-entry-point with a real gymnasium.Env subclass: the evaluation runs in it (2 episodes written)."""
    world = fake_world(tmp_path / "world")
    ws = tmp_path / "ws"
    args = [*_eval_args(world, FAKE["env_entry_point"], env_id="mine/FakeOvertake-v0"), "--trust-entry-point"]
    args += ["--record", "none", "--name", "mine"]
    code, err = run_main(ws, *args, monkeypatch=monkeypatch, capsys=capsys)
    assert code == 0, err
    metrics = json.loads((ws / "eval" / "mine" / "metrics.json").read_text())
    assert metrics["aggregate"]["intervention"]["n"] == 2


def test_drivesims_own_env_ids_cannot_be_rebound_to_another_entry_point(tmp_path):
    """An env_entry_point beside a registered id (the task's own) would be ignored silently: refused instead."""
    world = fake_world(tmp_path / "world")
    cfg = EvalConfig(world=str(world), episodes=1, env_entry_point=FAKE["env_entry_point"])
    with pytest.raises(ConfigError, match="registered already"):
        run_eval(Workspace(tmp_path / "ws"), cfg, trust_entry_point=True)
    assert not (tmp_path / "ws").exists()


# ---------------------------------------------------------------- the policy's shape and ONNX metadata


def test_an_empty_conv_layer_list_is_refused_not_replaced_by_a_default():
    """`--set policy.conv_layers=[]` was recorded as [] while a hidden default was trained: now one line."""
    from drivesim.stages.train.config import TrainConfig

    with pytest.raises(ConfigError, match="policy.conv_layers") as info:
        load_config(TrainConfig, preset="train/lane", overrides=["policy.conv_layers=[]"])
    assert "\n" not in info.value.one_line()


def test_the_policy_network_is_built_from_exactly_the_layers_recorded():
    """The SB3 policy records and builds the layers it is given; an empty list is refused, never defaulted."""
    import numpy as np
    import torch
    from gymnasium import spaces

    from drivesim.stages.train.sb3_policy import DrivingLstmPolicy

    obs = spaces.Box(0, 255, (3, 32, 48), np.uint8)
    act = spaces.Box(-1.0, 1.0, (1,), np.float32)
    policy = DrivingLstmPolicy(obs, act, lambda _: 1e-3, conv_layers=[[4, 5, 2]], features_dim=8, lstm_hidden_size=8)
    convs = [m for m in policy.modules() if isinstance(m, torch.nn.Conv2d)]
    assert policy.arch["conv_layers"] == [[4, 5, 2]]
    assert [(c.out_channels, c.kernel_size[0], c.stride[0]) for c in convs] == [(4, 5, 2)]
    with pytest.raises(ValueError, match="conv_layers"):
        DrivingLstmPolicy(obs, act, lambda _: 1e-3, conv_layers=[], features_dim=8, lstm_hidden_size=8)


@pytest.fixture
def exported_onnx(tmp_path: Path) -> Path:
    """A small trained-run policy exported by `export_onnx` with its metadata."""
    from test_eval_stage import _make_run

    from drivesim.policy.run_folder import load_policy
    from drivesim.stages.export.onnx_export import export_onnx
    from drivesim.stages.export.stage import policy_metadata

    loaded = load_policy(_make_run(tmp_path / "runs" / "overtake-1", "overtake"))
    path = tmp_path / "policy.onnx"
    export_onnx(loaded.export_module(), (3, 64, 160), policy_metadata(loaded), path)
    return path


def _edited(path: Path, out: Path, key: str | None = None, value: object = None, weights: bool = False) -> Path:
    """A copy of an exported policy with one metadata entry set to `value` (JSON) or its first weight changed."""
    import onnx
    from onnx import numpy_helper

    model = onnx.load(str(path))
    if key is not None:
        for prop in model.metadata_props:
            if prop.key == key:
                prop.value = json.dumps(value)
    if weights:
        init = model.graph.initializer[0]
        array = numpy_helper.to_array(init).copy()
        array.flat[0] += 0.5
        init.CopyFrom(numpy_helper.from_array(array, init.name))
    onnx.save(model, str(out))
    return out


def test_edited_onnx_metadata_or_weights_are_refused_with_one_line(exported_onnx, tmp_path):
    """An unknown format, an edited region of interest or edited weights: refused on load, one line each."""
    from drivesim.policy.onnx_runtime import OnnxPolicy

    policy = OnnxPolicy(exported_onnx)
    assert policy.metadata["format"] == 2 and len(policy.metadata["digest"]) == 64
    cases = {
        "format": (_edited(exported_onnx, tmp_path / "format.onnx", "drivesim.format", 3), "format 3"),
        "roi": (_edited(exported_onnx, tmp_path / "roi.onnx", "drivesim.roi_px", [0, 0, 10, 10]), "digest"),
        "weights": (_edited(exported_onnx, tmp_path / "weights.onnx", weights=True), "digest"),
        "no digest": (_edited(exported_onnx, tmp_path / "nodigest.onnx", "drivesim.digest", None), "digest"),
    }
    for name, (path, says) in cases.items():
        with pytest.raises(DrivesimError, match=says) as info:
            OnnxPolicy(path)
        assert "\n" not in info.value.one_line() and str(path) in info.value.one_line(), name


def test_eval_of_an_edited_onnx_policy_is_one_line_and_writes_nothing(exported_onnx, tmp_path, monkeypatch, capsys):
    """The probe through the CLI: an ONNX file whose roi_px was edited is refused before any episode."""
    register_fake_envs()
    edited = _edited(exported_onnx, tmp_path / "edited.onnx", "drivesim.roi_px", [1, 2, 3, 4])
    world = fake_world(tmp_path / "world")
    ws = tmp_path / "ws"
    args = [*_eval_args(world, FAKE["env_entry_point"], env_id=FAKE["env_id"]), "--policy", str(edited)]
    code, err = run_main(ws, *args, monkeypatch=monkeypatch, capsys=capsys)
    lines = _error_lines(err)
    assert code == 2 and len(lines) == 1 and "digest" in lines[0] and str(edited) in lines[0], err
    assert not (ws / "eval" / "overtake-edited").exists()


# ---------------------------------------------------------------- start-up and workers for many episodes


def test_finished_seeds_are_read_once_not_once_per_seed(tmp_path, monkeypatch):
    """Resuming N episodes reads each episode file once (it was read N times per file: quadratic start-up)."""
    folder = tmp_path / "episodes"
    seeds = list(range(30))
    for seed in seeds:
        write_episode(folder, replace(pass_record(1.5), seed=seed))
    reads: list[Path] = []
    original = rollout.read_episode
    monkeypatch.setattr(rollout, "read_episode", lambda path: reads.append(path) or original(path))
    assert run_episodes(EnvFactory(FAKE["env_id"]), PolicySpec("expert"), "overtake", seeds, folder) == 0
    assert len(reads) == len(seeds) and len(set(reads)) == len(seeds)


def test_seeds_to_run_of_ten_thousand_episodes_is_fast(tmp_path):
    """10,000 seeds, every tenth on disk (and one damaged file): the seeds left, in order, in well under the 5 s
    start-up target (the quadratic scan took about 20 minutes)."""
    import time

    folder = tmp_path / "episodes"
    record = pass_record(1.5)
    for seed in range(0, 10_000, 10):
        write_episode(folder, replace(record, seed=seed))
    (folder / "20.json").write_text("{")  # damaged: run again
    began = time.perf_counter()
    todo = rollout.seeds_to_run(folder, list(range(10_000)))
    elapsed_s = time.perf_counter() - began
    assert len(todo) == 9_001 and todo[:10] == [1, 2, 3, 4, 5, 6, 7, 8, 9, 11] and todo[-1] == 9_999
    assert 20 in todo and 30 not in todo
    assert elapsed_s < 3.0


def test_workers_are_capped_by_cores_with_one_line(tmp_path, monkeypatch):
    """`--workers 1000` on a machine with one core: one worker, and a note saying why."""
    register_fake_envs()
    monkeypatch.setattr(rollout, "default_workers", lambda: 1)
    world = fake_world(tmp_path / "world")
    cfg = EvalConfig(episodes=3, world=str(world), workers=1000, record="none", **FAKE)
    result = run_eval(Workspace(tmp_path / "ws"), cfg)
    assert result.summary.workers == 1 and result.summary.episodes == 3
    notes = [n for n in result.notes if "--workers 1000 lowered to 1" in n]
    assert len(notes) == 1 and "1 cores" in notes[0]


def test_workers_are_capped_by_available_memory(monkeypatch):
    """With 8 cores but memory for two workers, 16 requested become 2, and the line says memory."""
    import psutil

    class Memory:
        available = 2 * rollout.WORKER_MEMORY_BYTES + 1

    monkeypatch.setattr(rollout, "default_workers", lambda: 8)
    monkeypatch.setattr(psutil, "virtual_memory", lambda: Memory())
    workers, note = rollout.capped_workers(16, 1000)
    assert workers == 2 and note is not None and "memory" in note and "lowered to 2" in note
    assert rollout.capped_workers(None, 1000) == (2, None)  # the default (one per core) is capped without a word
    assert rollout.capped_workers(16, 1) == (1, None)  # fewer episodes than workers: no line
