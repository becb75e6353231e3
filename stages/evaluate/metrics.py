"""The evaluation metrics, defined in one place (paper §IV-A "Evaluation metric", §IV-B, Table I, Figs. 4-6).

An episode is recorded as an `EpisodeRecord` (the per-step trajectory of the ego and the front car, the episode's
initial conditions from `info["episode"]`, and the env's final termination flags). Every figure below is computed
from that record, so the definitions here are the only ones: the rollout stores raw trajectories, not metrics.

Per episode (all distances in metres, angles in radians, absolute values):
    collision        any step where the undilated footprints (length x width rectangles centred on each pose,
                     `sim/footprint.py`) overlap by more than 0 m² (the paper's evaluation threshold, 0 %), or the
                     env ended the episode for a collision.
    off_lane         the env ended the episode for leaving the lane (|q_lat| > Z_lat), or |q_lat| exceeded the
                     recorded limit `limits["max_lateral_m"]` at some step.
    over_rotation    the env ended the episode for |q_rot| > Z_rot, or |q_rot| exceeded `limits["max_rotation_rad"]`.
    intervention     collision or off_lane or over_rotation (a human would have taken over); each cause is also
                     counted on its own, so the three causes may sum to more than the interventions.
    success          the env's success flag (overtake: passed the front car by Z_pass and back near the lane centre)
                     and no intervention.
    min_clearance_m  the smallest distance between the two footprints over the episode's steps (0 when they touch
                     or overlap); undefined (NaN) without a front car (lane task).
    max_deviation_m  the largest |q_lat|: lateral shift of the ego from the lane centre (the recorded path).
    max_yaw_rad      the largest |q_rot|: ego heading minus the road heading at the associated frame.
    mean_tracking_error_m  mean of the env's per-step tracking error, for a task that measures one (follow's
                     `info["state"]["tracking_error_m"]`); NaN for the others.
    pass_shortfall_m how far the ego still was from having passed: Z_pass (`limits["pass_distance_m"]`) minus the
                     largest pass margin it reached (`info["state"]["pass_margin_m"]`, centre to centre along the
                     road), 0 once it got Z_pass ahead; NaN for a task without a pass (or a record without both).

Aggregates over episodes, each with a 95 % confidence interval:
    rates (intervention, each cause, success, end of data): Wilson score interval of the binomial proportion
        (`scipy.stats.binomtest(...).proportion_ci(method="wilson")`), good for rates near 0 and small counts.
    means (min clearance, max deviation, max yaw, tracking error): percentile bootstrap of the mean
        (`scipy.stats.bootstrap`, 2000 resamples, fixed random state so the same episodes give the same interval);
        per-episode maxima are skewed, so no normality is assumed.
    min_clearance_m, the headline, is averaged over all episodes with another car, a collision's clearance 0
        included (the paper's Table I is over all trials: a policy that collides or never passes does not look
        safe); the mean over the episodes without a collision is reported beside it, labelled, as
        `min_clearance_no_collision_m`.
    Episodes that end because the recorded data ran out ("end_of_data") stay in every aggregate (their steps were
    driven); their count is reported.

Breakdowns (Fig. 4): episodes are split into four levels, easy / normal / hard / challenging, by the quartiles
(over the evaluated episodes) of three initial conditions from `info["episode"]`: the road curvature ahead
(`road_curvature_1pm`, higher = harder), the front car's speed (`other_speed_mps`, higher = harder) and the initial
lateral difference between the cars (`|initial_lateral_m|`, smaller = harder: the front car is right ahead). The
same seeds give the same initial conditions for every policy, so the levels are comparable between policies.

Along the track (Fig. 6, follow's tracking error): every step is tagged with the world frame it is associated with;
the intervention rate of a frame is the fraction of the episodes visiting it that had an intervention, the
deviation of a frame the mean |q_lat| of the steps there, the tracking error of a frame the mean tracking error.

Clearance analysis (Fig. 5): the histogram of per-step clearances below 2 m, and the recall of trials at clearance
c: the fraction of episodes whose minimum clearance is at most c.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from drivesim.sim.footprint import clearance_m, footprint

LEVELS = ("easy", "normal", "hard", "challenging")

# Breakdown factor -> (key in info["episode"], harder when larger?). Initial lateral difference is harder when small.
BREAKDOWN_FACTORS: dict[str, tuple[str, bool]] = {
    "road_curvature": ("road_curvature_1pm", True),
    "front_car_speed": ("other_speed_mps", True),
    "initial_lateral": ("initial_lateral_m", False),
}

# Per-step trajectory fields an episode record holds (units in the names; `action` is the normalized steering).
TRAJECTORY_FIELDS = (
    "t_s",
    "ego_x_m",
    "ego_y_m",
    "ego_yaw_rad",
    "q_lat_m",
    "q_rot_rad",
    "frame_index",
    "arc_length_m",
    "road_curvature_1pm",
    "other_x_m",
    "other_y_m",
    "other_yaw_rad",
    "tracking_error_m",
    "pass_margin_m",
    "action",
)

BOOTSTRAP_RESAMPLES = 2000
CONFIDENCE = 0.95


@dataclass
class EpisodeRecord:
    """One closed-loop episode as the rollout writes it (`episodes/<seed>.json`).

    :param seed: the reset seed.
    :param task: the task's name (sim/envs/registry.py).
    :param episode: `info["episode"]` at reset (initial conditions, vehicle sizes).
    :param trajectory: per-step arrays (`TRAJECTORY_FIELDS`), the reset state first; NaN where not applicable.
    :param termination: the env's termination flags at the last step.
    :param success: the env's success flag at the last step.
    :param return_: the sum of the rewards.
    :param limits: optional `max_lateral_m` / `max_rotation_rad` of the env (Z_lat, Z_rot).
    """

    seed: int
    task: str
    episode: dict[str, Any]
    trajectory: dict[str, np.ndarray]
    termination: dict[str, bool]
    success: bool
    return_: float = 0.0
    limits: dict[str, float] = field(default_factory=dict)

    @property
    def steps(self) -> int:
        """Number of env steps (the reset state is not a step)."""
        return max(len(self.trajectory["t_s"]) - 1, 0)

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict; floats rounded to 5 decimals, NaN as null."""
        traj = {k: [_round(v) for v in np.asarray(a, dtype=float).tolist()] for k, a in self.trajectory.items()}
        return {
            "format": 1,
            "seed": self.seed,
            "task": self.task,
            "episode": {k: _round(v) if isinstance(v, float) else v for k, v in self.episode.items()},
            "limits": self.limits,
            "steps": self.steps,
            "termination": {k: bool(v) for k, v in self.termination.items()},
            "success": bool(self.success),
            "return": _round(float(self.return_)),
            "trajectory": traj,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> EpisodeRecord:
        """Read back what `to_json` wrote (null -> NaN)."""
        traj = {
            k: np.array([np.nan if v is None else v for v in a], dtype=float) for k, a in data["trajectory"].items()
        }
        return cls(
            seed=int(data["seed"]),
            task=str(data["task"]),
            episode=dict(data["episode"]),
            trajectory=traj,
            termination={k: bool(v) for k, v in data["termination"].items()},
            success=bool(data["success"]),
            return_=float(data.get("return") or 0.0),
            limits=dict(data.get("limits") or {}),
        )


def _round(value: float) -> float | None:
    if value is None or not math.isfinite(value):
        return None
    return round(value, 5)


@dataclass
class EpisodeMetrics:
    """The metrics of one episode (definitions in the module docstring)."""

    seed: int
    steps: int
    intervention: bool
    collision: bool
    off_lane: bool
    over_rotation: bool
    success: bool
    end_of_data: bool
    time_limit: bool
    min_clearance_m: float
    max_deviation_m: float
    max_yaw_rad: float
    mean_tracking_error_m: float
    road_curvature_1pm: float
    other_speed_mps: float
    initial_lateral_m: float
    return_: float
    other_lateral_m: float = float("nan")
    winnable: bool | None = None
    """Overtake: False for a start the hardest swerve cannot escape (sim/envs/winnable.py); None without a label."""
    pass_shortfall_m: float = float("nan")
    """Overtake: Z_pass minus the largest pass margin reached, at least 0 [m]; NaN without a pass."""

    def row(self) -> dict[str, Any]:
        """A flat dict for episodes.csv."""
        return asdict(self)


@dataclass
class EpisodeResult:
    """An episode's metrics with the per-step geometry the plots need.

    :param metrics: the episode's metrics.
    :param clearance_m: (T+1,) footprint distance per recorded state (inf without a front car).
    :param overlap_m2: (T+1,) footprint overlap area per recorded state.
    :param record: the episode record.
    """

    metrics: EpisodeMetrics
    clearance_m: np.ndarray
    overlap_m2: np.ndarray
    record: EpisodeRecord


def footprints_per_step(record: EpisodeRecord) -> tuple[np.ndarray, np.ndarray]:
    """(clearance_m, overlap_m2) of the ego and front-car footprints at every recorded state.

    inf clearance and 0 overlap where there is no front car (NaN pose).
    """
    traj = record.trajectory
    ep = record.episode
    n = len(traj["t_s"])
    clearance = np.full(n, np.inf)
    overlap = np.zeros(n)
    sizes = [_number(ep, k) for k in ("ego_length_m", "ego_width_m", "other_length_m", "other_width_m")]
    if not np.all(np.isfinite(sizes)) or "other_x_m" not in traj:
        return clearance, overlap
    ego_size, other_size = (sizes[0], sizes[1]), (sizes[2], sizes[3])
    for i in range(n):
        other_pose = (traj["other_x_m"][i], traj["other_y_m"][i], traj["other_yaw_rad"][i])
        if not np.all(np.isfinite(other_pose)):
            continue
        ego = footprint(traj["ego_x_m"][i], traj["ego_y_m"][i], traj["ego_yaw_rad"][i], *ego_size)
        other = footprint(*other_pose, *other_size)
        clearance[i] = clearance_m(ego, other)
        overlap[i] = ego.intersection(other).area
    return clearance, overlap


def _number(data: dict[str, Any], key: str) -> float:
    """data[key] as a float; NaN when absent or null."""
    value = data.get(key)
    try:
        return float(value) if value is not None else float("nan")
    except (TypeError, ValueError):
        return float("nan")


def _max_abs(values: np.ndarray) -> float:
    finite = np.abs(values[np.isfinite(values)])
    return float(finite.max()) if finite.size else float("nan")


def evaluate_episode(record: EpisodeRecord) -> EpisodeResult:
    """The metrics of one episode, as the module docstring defines them."""
    traj = record.trajectory
    term = record.termination
    clearance, overlap = footprints_per_step(record)
    max_deviation = _max_abs(traj["q_lat_m"])
    max_yaw = _max_abs(traj["q_rot_rad"])
    collision = bool(np.any(overlap > 0.0)) or bool(term.get("collision", False))
    lateral_limit = record.limits.get("max_lateral_m")
    rotation_limit = record.limits.get("max_rotation_rad")
    off_lane = bool(term.get("off_lane", False)) or (lateral_limit is not None and max_deviation > lateral_limit)
    over_rotation = bool(term.get("over_rotation", False)) or (rotation_limit is not None and max_yaw > rotation_limit)
    intervention = collision or off_lane or over_rotation
    has_other = bool(np.any(np.isfinite(clearance)))
    tracking = traj.get("tracking_error_m")
    mean_tracking = float("nan")
    if tracking is not None and np.any(
        np.isfinite(tracking)
    ):  # a task that measures it (follow's `_task_measurements`)
        mean_tracking = float(np.nanmean(np.abs(tracking)))
    ep = record.episode
    metrics = EpisodeMetrics(
        seed=record.seed,
        steps=record.steps,
        intervention=intervention,
        collision=collision,
        off_lane=off_lane,
        over_rotation=over_rotation,
        success=bool(record.success) and not intervention,
        end_of_data=bool(term.get("end_of_data", False)),
        time_limit=bool(term.get("time_limit", False)),
        min_clearance_m=float(clearance.min()) if has_other else float("nan"),
        max_deviation_m=max_deviation,
        max_yaw_rad=max_yaw,
        mean_tracking_error_m=mean_tracking,
        road_curvature_1pm=_number(ep, "road_curvature_1pm"),
        other_speed_mps=_number(ep, "other_speed_mps"),
        initial_lateral_m=_number(ep, "initial_lateral_m"),
        other_lateral_m=_number(ep, "other_lateral_m"),
        return_=float(record.return_),
        winnable=ep["winnable"] if isinstance(ep.get("winnable"), bool) else None,
        pass_shortfall_m=_pass_shortfall_m(traj.get("pass_margin_m"), record.limits.get("pass_distance_m")),
    )
    return EpisodeResult(metrics=metrics, clearance_m=clearance, overlap_m2=overlap, record=record)


def _pass_shortfall_m(margins_m: np.ndarray | None, pass_distance_m: float | None) -> float:
    """Z_pass minus the largest pass margin of the episode, at least 0; NaN without both."""
    if margins_m is None or pass_distance_m is None:
        return float("nan")
    finite = margins_m[np.isfinite(margins_m)]
    return max(float(pass_distance_m) - float(finite.max()), 0.0) if finite.size else float("nan")


@dataclass(frozen=True)
class Estimate:
    """A value with its 95 % confidence interval over `n` episodes (NaN when n == 0)."""

    value: float
    ci_low: float
    ci_high: float
    n: int

    def to_json(self) -> dict[str, Any]:
        """JSON-ready (NaN as null)."""
        low, high = _round(self.ci_low), _round(self.ci_high)
        return {"value": _round(self.value), "ci_low": low, "ci_high": high, "n": self.n}


def rate_estimate(flags: Sequence[bool] | np.ndarray) -> Estimate:
    """The proportion of True with its Wilson score 95 % interval."""
    from scipy.stats import binomtest

    flags = np.asarray(flags, dtype=bool)
    n = int(flags.size)
    if n == 0:
        return Estimate(float("nan"), float("nan"), float("nan"), 0)
    k = int(flags.sum())
    ci = binomtest(k, n).proportion_ci(confidence_level=CONFIDENCE, method="wilson")
    return Estimate(k / n, float(ci.low), float(ci.high), n)


def mean_estimate(values: Sequence[float] | np.ndarray) -> Estimate:
    """The mean of the finite values with a percentile-bootstrap 95 % interval (fixed random state)."""
    from scipy.stats import bootstrap

    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    n = int(values.size)
    if n == 0:
        return Estimate(float("nan"), float("nan"), float("nan"), 0)
    mean = float(values.mean())
    if n == 1 or np.all(values == values[0]):
        return Estimate(mean, mean, mean, n)
    res = bootstrap(
        (values,),
        np.mean,
        confidence_level=CONFIDENCE,
        n_resamples=BOOTSTRAP_RESAMPLES,
        method="percentile",
        random_state=np.random.default_rng(0),
    )
    return Estimate(mean, float(res.confidence_interval.low), float(res.confidence_interval.high), n)


RATE_KEYS = ("intervention", "collision", "off_lane", "over_rotation", "success", "end_of_data")


def aggregate(metrics: Sequence[EpisodeMetrics]) -> dict[str, Estimate]:
    """Every aggregate of the module docstring, by name."""
    out: dict[str, Estimate] = {key: rate_estimate([getattr(m, key) for m in metrics]) for key in RATE_KEYS}
    out["min_clearance_m"] = mean_estimate([m.min_clearance_m for m in metrics])
    out["min_clearance_no_collision_m"] = mean_estimate([m.min_clearance_m for m in metrics if not m.collision])
    out["max_deviation_m"] = mean_estimate([m.max_deviation_m for m in metrics])
    out["max_yaw_rad"] = mean_estimate([m.max_yaw_rad for m in metrics])
    out["mean_tracking_error_m"] = mean_estimate([m.mean_tracking_error_m for m in metrics])
    return out


STATIC_SPEED_MPS = 0.5
"""A front car slower than this counts as static in the scenario table."""


def scenario_table(metrics: Sequence[EpisodeMetrics]) -> list[dict[str, Any]]:
    """The paper's Table II offline: success and intervention of the episodes whose front car is static / moving,
    and whose ego passes on the left / right (the front car right / left of the lane centre); [] without a car."""
    groups = {
        "front car nearly static (< 0.5 m/s)": lambda m: m.other_speed_mps < STATIC_SPEED_MPS,
        "front car moving": lambda m: m.other_speed_mps >= STATIC_SPEED_MPS,
        "passing on the left": lambda m: m.other_lateral_m < 0.0,
        "passing on the right": lambda m: m.other_lateral_m > 0.0,
    }
    with_car = [m for m in metrics if math.isfinite(m.other_speed_mps) and math.isfinite(m.other_lateral_m)]
    if not with_car:
        return []
    rows = []
    for name, chosen in groups.items():
        members = [m for m in with_car if chosen(m)]
        rows.append(
            {
                "scenario": name,
                "episodes": len(members),
                "success": rate_estimate([m.success for m in members]).to_json(),
                "intervention": rate_estimate([m.intervention for m in members]).to_json(),
            }
        )
    return rows


def winnable_table(metrics: Sequence[EpisodeMetrics]) -> list[dict[str, Any]]:
    """The episodes whose start can be won and those labelled unwinnable (the env's `winnable` label), apart:
    episodes, success, intervention and collision of each; [] when no episode is labelled."""
    labelled = [m for m in metrics if m.winnable is not None]
    if not labelled:
        return []
    rows = []
    for name, flag in (("winnable starts", True), ("unwinnable starts", False)):
        members = [m for m in labelled if m.winnable is flag]
        rows.append(
            {
                "starts": name,
                "episodes": len(members),
                "share": round(len(members) / len(labelled), 5),
                **{k: rate_estimate([getattr(m, k) for m in members]).to_json() for k in WINNABLE_RATES},
            }
        )
    return rows


WINNABLE_RATES = ("success", "intervention", "collision")
"""The rates the winnable / unwinnable table reports for each group."""


def difficulty_levels(values: np.ndarray, harder_when_larger: bool) -> tuple[np.ndarray, list[float]]:
    """Level 0-3 (easy..challenging) of each value by the quartiles of the finite values, and the quartile edges.

    NaN values get level -1. For `harder_when_larger=False` the order is reversed (smallest = challenging).
    """
    values = np.asarray(values, dtype=float)
    levels = np.full(values.shape, -1, dtype=int)
    finite = np.isfinite(values)
    if not finite.any():
        return levels, []
    edges = np.quantile(values[finite], [0.25, 0.5, 0.75])
    bins = np.searchsorted(edges, values[finite], side="right")  # 0..3, ascending in the value
    levels[finite] = bins if harder_when_larger else 3 - bins
    return levels, [float(e) for e in edges]


@dataclass
class LevelBreakdown:
    """One factor's breakdown: per level (easy..challenging) the episode count, intervention rate, max deviation."""

    factor: str
    edges: list[float]
    harder_when_larger: bool
    intervention: list[Estimate]
    max_deviation_m: list[Estimate]

    def to_json(self) -> dict[str, Any]:
        """JSON-ready."""
        return {
            "factor": self.factor,
            "quartile_edges": [_round(e) for e in self.edges],
            "harder_when_larger": self.harder_when_larger,
            "levels": [
                {"level": name, "intervention": i.to_json(), "max_deviation_m": d.to_json()}
                for name, i, d in zip(LEVELS, self.intervention, self.max_deviation_m, strict=True)
            ],
        }


def breakdowns(metrics: Sequence[EpisodeMetrics]) -> list[LevelBreakdown]:
    """The Fig. 4 breakdowns: for each factor, the four levels' intervention rate and mean max deviation."""
    out = []
    for factor, (key, harder_when_larger) in BREAKDOWN_FACTORS.items():
        raw = np.array([getattr(m, key) for m in metrics], dtype=float)
        values = raw if harder_when_larger else np.abs(raw)
        levels, edges = difficulty_levels(values, harder_when_larger)
        interventions, deviations = [], []
        for level in range(len(LEVELS)):
            chosen = [m for m, lv in zip(metrics, levels, strict=True) if lv == level]
            interventions.append(rate_estimate([m.intervention for m in chosen]))
            deviations.append(mean_estimate([m.max_deviation_m for m in chosen]))
        out.append(LevelBreakdown(factor, edges, harder_when_larger, interventions, deviations))
    return out


def along_track(results: Sequence[EpisodeResult], frame_count: int) -> dict[str, np.ndarray]:
    """Per world frame: visiting episodes, intervention rate, mean |q_lat| and mean tracking error (NaN if unvisited).

    Keys: "visits" (episodes), "intervention_rate", "deviation_m", "tracking_error_m" (all (frame_count,)).
    """
    visits = np.zeros(frame_count)
    interventions = np.zeros(frame_count)
    dev_sum = np.zeros(frame_count)
    dev_n = np.zeros(frame_count)
    track_sum = np.zeros(frame_count)
    track_n = np.zeros(frame_count)
    for r in results:
        traj = r.record.trajectory
        frames = traj["frame_index"]
        ok = np.isfinite(frames) & (frames >= 0) & (frames < frame_count)
        idx = frames[ok].astype(int)
        visited = np.unique(idx)
        visits[visited] += 1
        if r.metrics.intervention:
            interventions[visited] += 1
        q_lat = np.abs(traj["q_lat_m"][ok])
        good = np.isfinite(q_lat)
        np.add.at(dev_sum, idx[good], q_lat[good])
        np.add.at(dev_n, idx[good], 1)
        tracking = traj.get("tracking_error_m")
        if tracking is not None:
            err = np.abs(tracking[ok])
            good = np.isfinite(err)
            np.add.at(track_sum, idx[good], err[good])
            np.add.at(track_n, idx[good], 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return {
            "visits": visits,
            "intervention_rate": np.where(visits > 0, interventions / np.maximum(visits, 1), np.nan),
            "deviation_m": np.where(dev_n > 0, dev_sum / np.maximum(dev_n, 1), np.nan),
            "tracking_error_m": np.where(track_n > 0, track_sum / np.maximum(track_n, 1), np.nan),
        }


def step_clearances(results: Sequence[EpisodeResult], below_m: float = 2.0) -> np.ndarray:
    """Every recorded state's clearance below `below_m` (the Fig. 5 histogram's data), over all episodes."""
    if not results:
        return np.zeros(0)
    all_c = np.concatenate([r.clearance_m for r in results])
    return all_c[all_c < below_m]


def clearance_recall(min_clearances_m: np.ndarray, thresholds_m: np.ndarray) -> np.ndarray:
    """Fraction of trials whose minimum clearance is at most each threshold (Fig. 5 right); trials without a car
    (NaN) are left out."""
    values = np.asarray(min_clearances_m, dtype=float)
    values = values[np.isfinite(values)]
    if values.size == 0:
        return np.full(len(thresholds_m), np.nan)
    return np.searchsorted(np.sort(values), np.asarray(thresholds_m), side="right") / values.size


def relative_to_other(record: EpisodeRecord) -> np.ndarray:
    """(T+1, 3) ego pose (x forward, y left, yaw) in the front car's frame at each state (NaN without a car)."""
    t = record.trajectory
    dx = t["ego_x_m"] - t["other_x_m"]
    dy = t["ego_y_m"] - t["other_y_m"]
    c, s = np.cos(t["other_yaw_rad"]), np.sin(t["other_yaw_rad"])
    yaw = np.angle(np.exp(1j * (t["ego_yaw_rad"] - t["other_yaw_rad"])))
    return np.stack([c * dx + s * dy, -s * dx + c * dy, yaw], axis=1)
