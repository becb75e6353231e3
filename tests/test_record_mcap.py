"""Foxglove recordings of episodes (`sim/episode_mcap.py`, `drivesim eval --record`), read back with mcap's reader:
the schemas are Foxglove's own, every step has its image, boxes and transforms at the step's time, a failed episode
ends with its cause, the evaluation records the failures it should (capped, whatever the worker count), a replay
writes the same bytes as the worker did, and the report links each recorded failure."""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path

import cv2
import gymnasium
import numpy as np
import pytest
from eval_fakes import FAKE, fake_world, register_fake_envs
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Log_pb2 import Log
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from mcap_protobuf.schema import build_file_descriptor_set
from sim_worlds import SMALL_VIEW, write_test_world
from test_eval_stage import _factory, _make_run

from drivesim.pipeline.errors import ConfigError
from drivesim.pipeline.workspace import Workspace
from drivesim.sim.episode_mcap import EpisodeCapture, Road, write_episode_mcap
from drivesim.sim.footprint import footprint
from drivesim.stages.evaluate import record, replay
from drivesim.stages.evaluate.config import EvalConfig
from drivesim.stages.evaluate.metrics import evaluate_episode
from drivesim.stages.evaluate.rollout import PolicySpec, env_limits, read_episode, run_episode, run_episodes
from drivesim.stages.evaluate.stage import run_eval

FOXGLOVE_TOPICS = {
    "/camera/image": CompressedImage,
    "/tf": FrameTransform,
    "/scene/vehicles": SceneUpdate,
    "/scene/road": SceneUpdate,
    "/log": Log,
}


class _JsonDecoders(McapDecoderFactory):
    """JSON messages as dicts (mcap ships no JSON decoder)."""

    def decoder_for(self, message_encoding, schema):
        return json.loads if message_encoding == "json" else None


def read_recording(path: Path) -> tuple[dict[str, tuple[str, str, bytes]], dict[str, list[tuple[int, object]]]]:
    """{topic: (schema name, schema encoding, schema data)} and {topic: [(log_time_ns, decoded message)]}."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True, decoder_factories=[DecoderFactory(), _JsonDecoders()])
        summary = reader.get_summary()
        schemas = {
            c.topic: (summary.schemas[c.schema_id].name, summary.schemas[c.schema_id].encoding,
                      summary.schemas[c.schema_id].data)
            for c in summary.channels.values()
        }  # fmt: skip
        messages: dict[str, list[tuple[int, object]]] = defaultdict(list)
        for _, channel, message, decoded in reader.iter_decoded_messages():
            messages[channel.topic].append((message.log_time, decoded))
    return schemas, messages


class SteerLeft:
    """Full left steering: the ego turns off the road and the episode ends with an intervention."""

    def initial_state(self, n):
        return None

    def predict(self, obs, state, episode_start, deterministic=True):
        return np.array([[0.6]], np.float32), None


@pytest.fixture(scope="module")
def failed_episode(tmp_path_factory):
    """An overtake episode in the real env on the small test world that ends in an intervention, recorded."""
    world = write_test_world(tmp_path_factory.mktemp("record") / "world")
    env = gymnasium.make("drivesim/Overtake-v0", world=str(world), meshes=None, mode="eval", config=SMALL_VIEW)
    limits = env_limits(env)
    capture = EpisodeCapture(7, "overtake")
    episode = run_episode(env, SteerLeft(), 7, "overtake", limits, capture=capture)
    env.close()
    path = write_episode_mcap(capture, Road.from_world(world, limits["max_lateral_m"]), world.parent / "7.mcap", "t")
    return episode, capture, path, limits


def test_the_schemas_are_foxglove_s_own(failed_episode):
    _, _, path, _ = failed_episode
    schemas, _ = read_recording(path)
    assert set(schemas) == {*FOXGLOVE_TOPICS, "/ego/step"}
    for topic, message_class in FOXGLOVE_TOPICS.items():
        name, encoding, data = schemas[topic]
        assert (name, encoding) == (message_class.DESCRIPTOR.full_name, "protobuf")
        assert name.startswith("foxglove.")
        # Byte for byte the schema of the maintained package (its .proto files, dependencies first).
        assert data == build_file_descriptor_set(message_class).SerializeToString()
    assert schemas["/ego/step"][:2] == ("drivesim.EpisodeStep", "jsonschema")


def test_every_step_has_its_image_boxes_and_transforms_at_its_time(failed_episode):
    episode, capture, path, _ = failed_episode
    _, messages = read_recording(path)
    t_s, traj = episode.trajectory["t_s"], episode.trajectory
    steps = episode.steps + 1  # the reset and each step
    assert steps > 5
    times = [round(t * 1e9) for t in t_s]
    for topic in ("/camera/image", "/scene/vehicles", "/ego/step"):
        assert [t for t, _ in messages[topic]] == times, topic
    tf_by_time = defaultdict(dict)
    for t, tf in messages["/tf"]:
        assert tf.timestamp.ToNanoseconds() == t
        tf_by_time[t][(tf.parent_frame_id, tf.child_frame_id)] = tf
    assert sorted(tf_by_time) == times
    for k, t in enumerate(times):
        # The camera: what the policy saw at step k (JPEG: close to it, and closer than to the steps beside it).
        _, image = messages["/camera/image"][k]
        assert image.timestamp.ToNanoseconds() == t and image.format == "jpeg" and image.frame_id == "camera"
        decoded = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]
        assert decoded.shape == capture.steps[k].image_rgb.shape == (16, 40, 3)
        error = {
            j: np.abs(decoded.astype(int) - capture.steps[j].image_rgb).mean()
            for j in (k - 1, k, k + 1)
            if 0 <= j < steps
        }
        assert error[k] < 6 and error[k] == min(error.values()), error
        # The transforms: the ego where the episode file has it, the other car, the camera on the ego.
        frames = tf_by_time[t]
        assert set(frames) == {("world", "ego"), ("world", "other"), ("ego", "camera")}
        ego_tf = frames[("world", "ego")]
        assert ego_tf.translation.x == pytest.approx(traj["ego_x_m"][k], abs=1e-4)
        assert 2 * math.atan2(ego_tf.rotation.z, ego_tf.rotation.w) == pytest.approx(traj["ego_yaw_rad"][k], abs=1e-4)
        assert frames[("world", "other")].translation.y == pytest.approx(traj["other_y_m"][k], abs=1e-4)
        # The boxes and the footprints the clearance is computed from.
        _, update = messages["/scene/vehicles"][k]
        entities = {e.id: e for e in update.entities}
        assert {"ego", "other"} <= set(entities)
        for name in ("ego", "other"):
            entity = entities[name]
            assert entity.timestamp.ToNanoseconds() == t and entity.frame_id == "world"
            cube = entity.cubes[0]
            assert (cube.pose.position.x, cube.pose.position.y) == pytest.approx(
                (traj[f"{name}_x_m"][k], traj[f"{name}_y_m"][k]), abs=1e-4
            )
            size = (episode.episode[f"{name}_length_m"], episode.episode[f"{name}_width_m"])
            assert (cube.size.x, cube.size.y) == pytest.approx(size)
            poly = footprint(traj[f"{name}_x_m"][k], traj[f"{name}_y_m"][k], traj[f"{name}_yaw_rad"][k], *size)
            corners = [(p.x, p.y) for p in entity.lines[0].points]
            assert np.allclose(corners, np.asarray(poly.exterior.coords)[:-1], atol=1e-4)


def test_a_failed_episode_ends_with_its_termination_cause(failed_episode):
    episode, _, path, _ = failed_episode
    _, messages = read_recording(path)
    causes = [k for k in ("collision", "off_lane", "over_rotation") if episode.termination[k]]
    assert causes and evaluate_episode(episode).metrics.intervention
    end = round(episode.trajectory["t_s"][-1] * 1e9)
    [(log_time, log)] = messages["/log"]
    assert log_time == end == max(t for topic in messages.values() for t, _ in topic)
    assert log.level == Log.ERROR and causes[0] in log.message and log.timestamp.ToNanoseconds() == end
    _, last = messages["/ego/step"][-1]
    assert last["done"] and all(last["termination"][c] for c in causes)
    assert last["q_rot_rad"] == pytest.approx(episode.trajectory["q_rot_rad"][-1], abs=1e-6)
    assert set(last["reward"]) >= {"lane", "collision", "total"}
    _, first = messages["/ego/step"][0]
    assert not first["done"] and first["action"] == 0.0  # the reset; then each step's action
    assert messages["/ego/step"][1][1]["action"] == pytest.approx(0.6)


def test_the_road_is_the_path_with_its_lane_bounds_and_off_lane_limits(failed_episode):
    _, _, path, limits = failed_episode
    _, messages = read_recording(path)
    [(t0, road)] = messages["/scene/road"]
    assert t0 == 0
    lines = road.entities[0].lines
    assert len(lines) == 5  # centre, lane edges left and right, off-lane limits left and right
    centre = np.array([(p.x, p.y) for p in lines[0].points])
    widths = sorted(
        float(np.median(np.hypot(*(np.array([(p.x, p.y) for p in li.points]) - centre).T))) for li in lines[1:]
    )
    assert widths == pytest.approx([1.75, 1.75, limits["max_lateral_m"], limits["max_lateral_m"]], abs=1e-3)


def test_eval_records_the_first_failures_capped_and_the_report_links_them(tmp_path, monkeypatch):
    world = fake_world(tmp_path / "world")
    run = _make_run(tmp_path / "runs" / "overtake-1", "overtake")  # random weights: every episode fails
    monkeypatch.setattr(record, "FAILURES_CAP", 3)
    cfg = EvalConfig(episodes=6, world=str(world), workers=1, policy=str(run), **FAKE)
    register_fake_envs()
    result = run_eval(Workspace(tmp_path / "ws"), cfg)
    failed = [json.loads(p.read_text()) for p in sorted((result.path / "episodes").glob("*.json"))]
    assert sum(not e["success"] for e in failed) == 6
    assert sorted(p.name for p in (result.path / "recordings").glob("*")) == ["0.mcap", "1.mcap", "2.mcap"]
    html = (result.path / "report.html").read_text()
    for seed in (0, 1, 2):
        assert f'href="recordings/{seed}.mcap"' in html
    assert 'href="recordings/3.mcap"' not in html
    _, messages = read_recording(result.path / "recordings" / "1.mcap")
    assert messages["/log"][0][1].level == Log.ERROR


def test_the_capped_failures_are_the_lowest_seeds_in_any_finishing_order(tmp_path):
    """Workers finish episodes in any order: each skips a failure only when `cap` lower failures are on disk, so the
    lowest `cap` failing seeds are always there (the finish copies those)."""
    plan = record.RecordPlan("failures", 3, 0, str(tmp_path / "rec"))
    recorder = record.EpisodeRecorder(plan, "overtake", {})
    image = np.zeros((3, 4, 8), np.uint8)
    state = {"t_s": 0.0, "ego_x_m": 0.0, "ego_y_m": 0.0, "ego_yaw_rad": 0.0}
    written = []
    for seed in (5, 3, 9, 1, 7, 2, 8):  # the order two workers might finish them in
        capture = EpisodeCapture(seed, "overtake")
        capture.add(image, {"state": state, "termination": {"collision": True}}, 0.0)
        written.append(recorder.end(capture, intervention=True) is not None)
    assert written == [True, True, True, True, False, True, False]  # 7: 1, 3, 5 were on disk; 8: 1, 2, 3, 5
    assert sorted(record.recorded_seeds(tmp_path / "rec"))[:3] == [1, 2, 3]
    assert recorder.end(EpisodeCapture(0, "overtake"), intervention=False) is None  # not a failure


def test_record_n_all_and_none(tmp_path):
    factory = _factory(fake_world(tmp_path / "world"))
    seeds = [0, 1, 2, 3]
    for value, expected in ((2, [0, 1]), ("all", seeds), ("failures", [0]), ("none", None), (0, None)):
        plan = record.record_plan(value, seeds, tmp_path / f"work-{value}", tmp_path / "world")
        if expected is None:
            assert plan is None
            continue
        episodes = tmp_path / f"episodes-{value}"
        run_episodes(factory, PolicySpec("expert"), "overtake", seeds, episodes, workers=1, record=plan)
        results = [evaluate_episode(read_episode(episodes / f"{s}.json")) for s in seeds]
        assert [r.metrics.intervention for r in results] == [True, False, False, False]  # the expert fails seed 0
        paths = replay.finish_recordings(plan, results, factory, PolicySpec("expert"), "overtake", tmp_path / "out")
        assert [int(p.stem) for p in paths] == expected, value
        assert record.recorded_seeds(tmp_path / f"work-{value}") == set(
            expected
        )  # none replayed: the workers wrote them
    with pytest.raises(ConfigError, match="--record"):
        record.parse_record("worst")


def test_a_replayed_recording_is_the_one_the_worker_wrote(tmp_path):
    """The Ray backend's actors and resumed episodes do not record: those recordings are replayed, identically."""
    world = fake_world(tmp_path / "world")
    factory = _factory(world)
    seeds = [0, 1, 2]
    plan = record.record_plan("all", seeds, tmp_path / "by-worker", world)
    run_episodes(factory, PolicySpec("expert"), "overtake", seeds, tmp_path / "episodes", workers=1, record=plan)
    results = [evaluate_episode(read_episode(tmp_path / "episodes" / f"{s}.json")) for s in seeds]
    to_replay = record.RecordPlan("all", None, 0, str(tmp_path / "replayed"), str(world))
    paths = replay.finish_recordings(to_replay, results, factory, PolicySpec("expert"), "overtake", tmp_path / "out")
    assert [p.name for p in paths] == ["0.mcap", "1.mcap", "2.mcap"]
    for seed in seeds:
        assert (tmp_path / "replayed" / f"{seed}.mcap").read_bytes() == (
            tmp_path / "by-worker" / f"{seed}.mcap"
        ).read_bytes()


def test_the_foxglove_layout_shows_what_the_recordings_hold(failed_episode):
    """docs/foxglove_layout.json: the camera, the 3D scene following the ego, plots of clearance and steering, the
    log; every topic and plotted field it names is in a recording."""
    layout = json.loads((Path(__file__).resolve().parents[1] / "docs" / "foxglove_layout.json").read_text())
    _, _, path, _ = failed_episode
    schemas, messages = read_recording(path)
    panels = layout["configById"]
    assert {name.split("!")[0] for name in panels} == {"Image", "3D", "Plot", "RosOut"}
    placed = json.dumps(layout["layout"])
    assert all(f'"{name}"' in placed for name in panels)
    image = next(v for k, v in panels.items() if k.startswith("Image!"))
    assert schemas[image["imageMode"]["imageTopic"]][0] == "foxglove.CompressedImage"
    scene = next(v for k, v in panels.items() if k.startswith("3D!"))
    assert scene["followTf"] == "ego" and set(scene["topics"]) <= set(schemas)
    step = messages["/ego/step"][-1][1]
    plotted = [p["value"] for k, v in panels.items() if k.startswith("Plot!") for p in v["paths"]]
    assert {"/ego/step.clearance_m", "/ego/step.action"} <= set(plotted)
    for value in plotted:
        topic, _, field_path = value.partition(".")
        node = step
        for part in field_path.split("."):
            node = node[part]
        assert topic in schemas and (node is None or isinstance(node, float | int)), value


def test_sim_render_mcap_records_the_rendered_episode(failed_episode, tmp_path):
    """`drivesim sim render --mcap`: the expert's episode at the world's full image size, one image per step."""
    from drivesim.sim.envs.render_episode import render_episode

    _, _, path, _ = failed_episode
    summary = render_episode("overtake", path.parent / "world", None, tmp_path / "out", seed=2, mcap=True)
    schemas, messages = read_recording(tmp_path / "out" / "episode.mcap")
    assert len(messages["/camera/image"]) == len(messages["/scene/vehicles"]) == summary["steps"] + 1
    _, image = messages["/camera/image"][0]
    assert cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR).shape == (50, 80, 3)  # full image
    [(_, log)] = messages["/log"]
    assert summary["outcome"] in log.message
    # The segment between the footprints is the env's clearance where it is drawn (below 3 m), removed elsewhere.
    drawn = 0
    for (_, step), (_, update) in zip(messages["/ego/step"], messages["/scene/vehicles"], strict=True):
        segment = [e for e in update.entities if e.id == "clearance"]
        if step["clearance_m"] is not None and step["clearance_m"] < 3.0:
            a, b = segment[0].lines[0].points
            assert math.hypot(a.x - b.x, a.y - b.y) == pytest.approx(step["clearance_m"], abs=1e-3)
            drawn += 1
        else:
            assert not segment and [d.id for d in update.deletions] == ["clearance"]
    assert drawn > 0  # the expert passes the other car
