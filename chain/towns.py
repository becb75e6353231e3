"""Procedural towns the tool builds itself: for a seed N, a synthetic drive through town N and its world, at
`<workspace>/towns/seed<N>/world`, for training on more places than the user's own recording.

A town is a small workspace of its own, `<workspace>/towns/seed<N>/`, made by the chain's stages through the chain
walker (`chain.walk.walk_chain`): synth (`drivesim synth --seed N`, `duration_s` of drive) -> ingest ->
preprocess -> build-world, each with its own preset and this config's per-stage overrides. Every stage is skipped
when its artifact is fresh, so building a town again costs nothing and a changed setting redoes only what it changes;
every artifact is written in a temporary folder and moved into place when whole, so Ctrl-C leaves no half-written
town (the stages done are kept, the next build continues).

`drivesim towns build 1 2 3` builds (or refreshes) towns; before the train stage, `drivesim train` and `drivesim run`
build the missing towns its config's `towns` key names (`training_towns`, with this config's preset
`configs/towns.yaml`; a town that exists is used as it is) and hand their worlds to the stage.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pydantic import Field, field_validator

from drivesim.chain.walk import deep_merge
from drivesim.pipeline.config import StageConfig, load_config
from drivesim.pipeline.workspace import MANIFEST_NAME, Workspace

if TYPE_CHECKING:
    from drivesim.stages.train.config import TrainConfig

TOWNS_DIR = "towns"
PRESET = "towns"
TOWN_STAGES = ("ingest", "preprocess", "build-world")
"""The chain's stages a town goes through after synth, in order."""


class TownsConfig(StageConfig):
    """`drivesim towns build`: the synthetic drive of each town and the chain's settings for it."""

    duration_s: float = Field(30.0, gt=0.0, le=3600.0)
    """Length of each town's drive (synth `drive.duration_s`) [s]; 30 s at 10 m/s is about 300 m of road."""
    stages: dict[str, dict[str, Any]] = {}
    """Overrides of the town chain's stage configs, as in a run preset: synth, ingest, preprocess, build-world
    (e.g. {preprocess: {depth: {method: mvs}}}); each stage's own preset is the base."""

    per_town: dict[int, dict[str, dict[str, Any]]] = {}
    """Overrides for single towns, by seed, applied over `stages` (same form): the preset makes towns 8 and 9
    tree-lined this way (configs/towns.yaml)."""

    @field_validator("stages")
    @classmethod
    def _known_stages(cls, value: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
        unknown = sorted(set(value) - {"synth", *TOWN_STAGES})
        if unknown:
            raise ValueError(f"unknown stage(s) {', '.join(unknown)}; a town's stages: synth, {', '.join(TOWN_STAGES)}")
        return value

    @field_validator("per_town")
    @classmethod
    def _known_towns_and_stages(cls, value: dict[int, dict[str, dict[str, Any]]]) -> dict[int, dict[str, Any]]:
        for seed, stages in value.items():
            if seed < 0:
                raise ValueError(f"per_town: town seed {seed}: seeds are 0 or more")
            cls._known_stages(stages)
        return value


@dataclass
class TownStage:
    """One stage of one town's build, for progress lines.

    :param seed: the town. :param stage: the stage's name. :param skipped: fresh, nothing redone.
    :param wall_s: its wall time [s]. :param path: its artifact.
    """

    seed: int
    stage: str
    skipped: bool
    wall_s: float
    path: Path


def town_dir(ws: Workspace, seed: int) -> Path:
    """The town's own workspace folder, `<workspace>/towns/seed<N>`."""
    return ws.root / TOWNS_DIR / f"seed{seed}"


def town_world(ws: Workspace, seed: int) -> Path:
    """The town's world folder, `<workspace>/towns/seed<N>/world` (it may not exist yet)."""
    return town_dir(ws, seed) / "world"


def is_built(ws: Workspace, seed: int) -> bool:
    """True when the town's world exists whole (its manifest is readable)."""
    return Workspace(town_dir(ws, seed)).read_manifest("world") is not None


def check_seeds(seeds: Iterable[int]) -> list[int]:
    """The seeds in order, each once; a negative seed is refused with one line."""
    from drivesim.pipeline.errors import ConfigError

    out: list[int] = []
    for seed in seeds:
        if int(seed) < 0:
            raise ConfigError(f"town seed {seed}: seeds are 0 or more")
        if int(seed) not in out:
            out.append(int(seed))
    return out


def town_overrides(cfg: TownsConfig, seed: int) -> dict[str, Any]:
    """The per-stage overrides of town `seed`'s chain: the seed and drive length, then the config's stages, then
    the config's overrides for this town."""
    base: dict[str, Any] = {"synth": {"seed": seed, "drive": {"duration_s": cfg.duration_s}}}
    return deep_merge(deep_merge(base, cfg.stages), cfg.per_town.get(seed, {}))


def build_town(
    ws: Workspace, seed: int, cfg: TownsConfig, force: bool = False, on_stage: Callable[[TownStage], None] | None = None
) -> Path:
    """Build (or refresh) town `seed` through the chain walker; returns its world folder."""
    from drivesim.chain.registry import stage_by_name
    from drivesim.chain.walk import StageRun, run_ingest, walk_chain

    chain = tuple(stage_by_name(name) for name in TOWN_STAGES)
    assert all(spec is not None for spec in chain), "a town stage is missing from the chain registry"

    def forward(done: StageRun) -> None:
        if on_stage is not None:
            on_stage(TownStage(seed, done.stage, done.skipped, done.wall_s, Path(done.path)))

    town_ws = Workspace(town_dir(ws, seed))
    overrides = town_overrides(cfg, seed)
    walk_chain(town_ws, None, overrides, chain, {"ingest": run_ingest}, force=force, on_stage=forward)  # type: ignore[arg-type]
    return town_world(ws, seed)


def build_towns(
    ws: Workspace,
    seeds: Iterable[int],
    cfg: TownsConfig | None = None,
    force: bool = False,
    on_stage: Callable[[TownStage], None] | None = None,
) -> list[Path]:
    """Build (or refresh) every town of `seeds`, one after the other; returns their world folders in order.

    :param cfg: the towns config (default: the preset `configs/towns.yaml`).
    :param force: redo every stage even when fresh.
    :param on_stage: called after each stage of each town (progress).
    """
    cfg = cfg if cfg is not None else load_config(TownsConfig, preset=PRESET)
    return [build_town(ws, seed, cfg, force=force, on_stage=on_stage) for seed in check_seeds(seeds)]


def ensure_towns(
    ws: Workspace, seeds: Iterable[int], on_stage: Callable[[TownStage], None] | None = None
) -> list[Path]:
    """The world folders of towns `seeds`: a town that exists is used as it is, a missing one is built first with
    the preset (`configs/towns.yaml`). Progress lines go to stderr unless `on_stage` takes them."""
    seeds = check_seeds(seeds)
    missing = [s for s in seeds if not is_built(ws, s)]
    if missing:
        build_towns(ws, missing, on_stage=on_stage or _print_stage)
    return [town_world(ws, s) for s in seeds]


def training_towns(ws: Workspace, cfg: TrainConfig, worlds: list[Path] | None = None) -> list[Path]:
    """The world folders of the towns a train config names, each built first when missing (upstream work of the
    train stage, through the world-making stages); none with the cost-free env or no `towns`.

    :param worlds: the run's `--world` folders; without them the workspace's world is required first, so that a
        missing world is one line before any town is built.
    """
    if not cfg.towns or cfg.envs.source == "cost_free":
        return []
    if not worlds:
        ws.require("world", "drivesim build-world")
    return ensure_towns(ws, cfg.towns)


def _print_stage(done: TownStage) -> None:
    from drivesim.pipeline.progress import console

    state = "fresh, skipped" if done.skipped else f"done in {done.wall_s:.1f} s"
    console.print(f"town seed{done.seed}: {done.stage}: {state} -> {done.path}", highlight=False, soft_wrap=True)


def has_manifest(world: Path) -> bool:
    """True when `world` has a manifest (a world folder `drivesim build-world` finished)."""
    return (Path(world) / MANIFEST_NAME).is_file()
