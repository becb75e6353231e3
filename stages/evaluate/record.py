"""Which evaluation episodes are recorded for Foxglove (`drivesim eval --record`), and where.

One MCAP per episode, `eval/<name>/recordings/<seed>.mcap` (its topics: `drivesim.sim.episode_mcap`), not one per
evaluation, because:
- every episode's timeline is its sim time from 0 s: in one file the episodes would lie on top of each other;
- the worker process that ran an episode writes its file the moment the episode ends, atomically and beside
  `episodes/<seed>.json` in the resumable work folder, without coordinating with the other workers; an interrupted
  evaluation keeps the recordings it made;
- the report links each failed episode to its own file, and Foxglove opens just that episode.

`--record` modes: `failures` (the default): the episodes with an intervention (collision, off lane, over-rotation),
at most `FAILURES_CAP` of them, those with the lowest seeds; `all`: every episode (no cap: the user asked for it);
`N` (a number): the first N episodes by seed whatever their outcome; `none` or `0`: nothing.

Cost: while recording, a worker keeps each step of the episode it runs (the observation it rendered anyway, the
state, rewards and flags: a few MB for 300 steps) and encodes and writes the MCAP only for an episode that is kept, so
no episode is run twice. A worker skips a failure when `FAILURES_CAP` failures of lower seeds are on disk already,
and the finish keeps the lowest seeds: the recorded set does not depend on the worker count. A kept episode whose file
is missing (the Ray backend's actors do not record; episodes resumed from a run without recording) is replayed once
after the evaluation; an episode depends only on its seed, so the replay is the same episode.
"""

from __future__ import annotations

import html
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from drivesim.pipeline.errors import ConfigError
from drivesim.sim.episode_mcap import EpisodeCapture, Road, write_episode_mcap
from drivesim.stages.evaluate.metrics import EpisodeResult

FAILURES_CAP = 50
"""Most failed episodes `--record failures` writes (about 1-3 MB each at the default 160 x 64 view, 300 steps)."""
RECORDINGS_DIR = "recordings"
LAYOUT_HINT = "docs/foxglove_layout.json"
TOPICS_SNIPPET = (
    "python -c \"import sys, mcap.reader as r; s = r.make_reader(open(sys.argv[1], 'rb')).get_summary(); "
    'print(*sorted(c.topic for c in s.channels.values()))" FILE.mcap'
)
"""A command that lists an episode file's topics with the installed `mcap` package (it has no command-line tool)."""
_MODES = ("failures", "all", "none")


@dataclass(frozen=True)
class RecordPlan:
    """What an evaluation records (picklable: the worker processes get it).

    :param mode: "failures", "all" or "first".
    :param count: the cap of "failures", N of "first", None for "all".
    :param first_seed: the evaluation's first seed ("first" records seeds first_seed .. first_seed + N - 1).
    :param folder: where the workers write `<seed>.mcap`.
    :param world: the world folder (its path.npz, world.json and camera.json are drawn), None for none.
    """

    mode: str
    count: int | None
    first_seed: int
    folder: str
    world: str | None = None

    def may_keep(self, seed: int) -> bool:
        """Whether episode `seed` can be kept before it runs (so its steps are worth keeping in memory)."""
        return self.mode != "first" or seed < self.first_seed + (self.count or 0)


def parse_record(value: str | int) -> tuple[str, int | None] | None:
    """(mode, count) of a `--record` value, None for nothing; ConfigError for a value that is none of them."""
    text = str(value).strip().lower()
    if text.isdigit():
        return None if int(text) == 0 else ("first", int(text))
    if text not in _MODES:
        raise ConfigError(f"--record {value!r}: use failures, all, none or a number of episodes")
    return None if text == "none" else (text, FAILURES_CAP if text == "failures" else None)


def record_plan(value: str | int, seeds: Sequence[int], folder: Path, world: Path | None) -> RecordPlan | None:
    """The plan of `--record value` for an evaluation of `seeds` (None when nothing is recorded)."""
    parsed = parse_record(value)
    if parsed is None or not seeds:
        return None
    has_path = world is not None and (Path(world) / "path.npz").is_file()
    return RecordPlan(parsed[0], parsed[1], min(seeds), str(folder), str(world) if has_path else None)


class EpisodeRecorder:
    """A worker's recorder: a capture for each episode that may be kept, the MCAP for each one that is.

    :param plan: what to record. :param task: the task (in the log line). :param limits: the env's Z_lat / Z_rot.
    """

    def __init__(self, plan: RecordPlan, task: str, limits: dict[str, float]) -> None:
        self.plan = plan
        self.task = task
        self.folder = Path(plan.folder)
        self.road = None if plan.world is None else Road.from_world(Path(plan.world), limits.get("max_lateral_m"))

    def begin(self, seed: int) -> EpisodeCapture | None:
        """An empty capture for episode `seed`, or None when it cannot be kept."""
        return EpisodeCapture(seed, self.task) if self.plan.may_keep(seed) else None

    def end(self, capture: EpisodeCapture | None, intervention: bool) -> Path | None:
        """Write the episode's MCAP when the plan keeps it; returns its path, else None."""
        if capture is None or not self._keeps(capture.seed, intervention):
            return None
        return self.write(capture)

    def write(self, capture: EpisodeCapture) -> Path:
        """Write `folder/<seed>.mcap`."""
        path = self.folder / f"{capture.seed}.mcap"
        return write_episode_mcap(capture, self.road, path, f"{self.task} seed {capture.seed}")

    def _keeps(self, seed: int, intervention: bool) -> bool:
        if self.plan.mode != "failures":
            return True
        if not intervention:
            return False
        lower = [s for s in recorded_seeds(self.folder) if s < seed]
        return len(lower) < (self.plan.count or 0)


def chosen_seeds(plan: RecordPlan, results: Sequence[EpisodeResult]) -> list[int]:
    """The seeds the evaluation records, in seed order."""
    seeds = sorted(r.metrics.seed for r in results)
    if plan.mode == "all":
        return seeds
    if plan.mode == "first":
        return [s for s in seeds if s < plan.first_seed + (plan.count or 0)]
    failed = sorted(r.metrics.seed for r in results if r.metrics.intervention)
    return failed[: plan.count]


def recorded_seeds(folder: Path) -> set[int]:
    """The seeds with a `<seed>.mcap` in `folder`."""
    if not Path(folder).is_dir():
        return set()
    return {int(p.stem) for p in Path(folder).glob("*.mcap") if re.fullmatch(r"\d+", p.stem)}


def recording_link(out_dir: Path, seed: int) -> str:
    """An HTML link to episode `seed`'s recording in the report (relative to `out_dir`), or "—"."""
    if not (Path(out_dir) / RECORDINGS_DIR / f"{seed}.mcap").is_file():
        return "—"
    return f'<a href="{RECORDINGS_DIR}/{seed}.mcap">{seed}.mcap</a>'


def recordings_html(out_dir: Path, results: Sequence[EpisodeResult]) -> str:
    """The report's section on the recordings: the recorded episodes by outcome (failures first), each linked, and
    how to open them."""
    seeds = recorded_seeds(Path(out_dir) / RECORDINGS_DIR)
    if not seeds:
        return ""
    by_cause: dict[str, list[int]] = {}
    for r in sorted(results, key=lambda r: r.metrics.seed):
        if r.metrics.seed not in seeds:
            continue
        causes = [k for k in ("collision", "off_lane", "over_rotation") if getattr(r.metrics, k)]
        by_cause.setdefault(", ".join(causes) or ("success" if r.metrics.success else "no intervention"), []).append(
            r.metrics.seed
        )
    rows = "".join(
        f"<tr><td>{html.escape(cause)}</td><td>{len(s)}</td><td>{' '.join(recording_link(out_dir, x) for x in s)}"
        "</td></tr>"
        for cause, s in sorted(by_cause.items(), key=lambda item: item[0] in ("success", "no intervention"))
    )
    return (
        f"<h2>Recordings (Foxglove)</h2><table><tr><th>outcome</th><th>episodes</th><th>recording</th></tr>{rows}"
        f"</table><p class=ci>One MCAP per episode in <code>{RECORDINGS_DIR}/</code>: camera, both cars as boxes with "
        f"their footprints, the road, and plots of action, rewards and clearance. Open one in the Foxglove app with "
        f"the layout <code>{LAYOUT_HINT}</code>, or list its topics with the <code>mcap</code> Python package drivesim "
        f"installs: <code>{html.escape(TOPICS_SNIPPET)}</code>.</p>"
    )
