"""Issue 19 diagnosis: does a policy react to the other car at the first step, on each world?

For each policy (a run folder, or one of its checkpoints) and each world, over seeds 0 .. N-1, every overtake episode
is reset in eval mode (the same start states `drivesim eval` draws) and the policy's first action (zero LSTM state,
deterministic) is set against the privileged expert's. Where the expert steers clearly to one side (|a| >= 0.5: the
front car is close to the ego's line and it swerves to pass), the row counts how often the policy steers to the same
side by at least 0.25. A low share on one world says the policy does not read the car from that world's images at
the start; a high share does not promise success there (the policy must still hold the lane afterwards), so read it
beside the world's `drivesim eval` figures.

    python experiments/first_action/bench_first_action.py --policy RUN --policy RUN/checkpoints/warm_start.pt \
        --world town=W1 --world real=W2 --episodes 200 --name NAME

writes experiments/first_action/results/first_action_<NAME>.json and (from every first_action_*.json) first_action.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "transfer"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "_lib"))  # the studies' shared helpers (study.py)
from bench_transfer import machine  # noqa: E402  (the same machine line as the transfer tables)
from study import add_result_arguments, add_settings_argument  # noqa: E402

RESULTS = Path(__file__).parent / "results"
CLEAR_STEER = 0.5  # the expert's |action| above which it is swerving to pass
SAME_SIDE = 0.25  # the policy's action counted as a swerve to that side


def first_actions(
    policy_path: str, world: str, episodes: int, overrides: dict[str, float]
) -> tuple[np.ndarray, np.ndarray]:
    """(expert, policy) first actions over seeds 0 .. episodes-1 of the policy's task in `world`, with the policy's
    env config and `overrides` over it (as `drivesim eval --set env.KEY=VALUE`)."""
    from drivesim.policy.run_folder import load_policy
    from drivesim.sim.envs.registry import task_spec

    policy = load_policy(policy_path)
    env = task_spec(policy.task).env_class()(world, None, mode="eval", config={**policy.env_config, **overrides})
    expert, learned = np.zeros(episodes), np.zeros(episodes)
    for seed in range(episodes):
        obs, _ = env.reset(seed=seed)
        expert[seed] = float(env.expert_action()[0])
        action, _ = policy.predict(obs[None], None, np.ones(1, dtype=bool))
        learned[seed] = float(action[0, 0])
    return expert, learned


def agreement(expert: np.ndarray, learned: np.ndarray) -> dict:
    """Side agreement where the expert swerves, the mean absolute difference and the correlation."""
    swerve = np.abs(expert) >= CLEAR_STEER
    same = (np.sign(learned) == np.sign(expert)) & (np.abs(learned) >= SAME_SIDE)
    return {
        "swerve_starts": int(swerve.sum()),
        "same_side": float(same[swerve].mean()) if swerve.any() else None,
        "mean_abs_diff": float(np.abs(expert - learned).mean()),
        "correlation": float(np.corrcoef(expert, learned)[0, 1]) if learned.std() > 0 else None,
    }


def write_markdown() -> None:
    """experiments/first_action/results/first_action.md from every first_action_*.json."""
    lines = [
        "# First-step reaction to the other car (issue 19 diagnosis)",
        "",
        f"Each cell: share of the starts where the expert swerves (|a| >= {CLEAR_STEER}) at which the policy steers to "
        f"the same side (by >= {SAME_SIDE}); in brackets the correlation of the two first actions over all starts.",
        "Reproduce: `python experiments/first_action/bench_first_action.py --policy P ... --world LABEL=W ... "
        "--episodes N --name NAME`.",
        "",
    ]
    for path in sorted(RESULTS.glob("first_action_*.json")):
        r = json.loads(path.read_text())
        labels = list(r["worlds"])
        lines += [
            f"## {r['name']}",
            "",
            f"Measured {r['measured_utc']} on {r['machine']}; {r['episodes']} starts per world (seeds 0-"
            f"{r['episodes'] - 1}). Worlds: " + ", ".join(f"{k} `{v}`" for k, v in r["worlds"].items()) + ". "
            f"Env config over each policy's own: {r.get('env_overrides') or 'none'}.",
            "",
            "| policy | " + " | ".join(labels) + " |",
            "|---|" + "---|" * len(labels),
        ]
        for policy, cells in r["rows"].items():
            texts = []
            for label in labels:
                c = cells[label]
                side = "—" if c["same_side"] is None else f"{c['same_side']:.0%}"
                corr = "—" if c["correlation"] is None else f"{c['correlation']:.2f}"
                texts.append(f"{side} ({corr}) of {c['swerve_starts']}")
            lines.append(f"| `{policy}` | " + " | ".join(texts) + " |")
        if r.get("notes"):
            lines += ["", r["notes"]]
        lines.append("")
    (RESULTS / "first_action.md").write_text("\n".join(lines))


def main() -> None:
    """Measure every policy in every world and write the tables."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", action="append", required=True, help="a run folder or RUN/checkpoints/NAME.pt")
    parser.add_argument("--world", action="append", required=True, help="LABEL=WORLD_FOLDER")
    parser.add_argument("--episodes", type=int, default=200, help="starts per world (seeds 0 .. N-1)")
    add_result_arguments(parser, "first_action")
    add_settings_argument(
        parser,
        "--env-set",
        "an env config value over every policy's own, e.g. min_path_length_m=60 (the same starts for policies "
        "trained with different values)",
    )
    args = parser.parse_args()
    worlds = dict(item.split("=", 1) for item in args.world)
    overrides = {key: float(value) for key, value in (item.split("=", 1) for item in args.env_set)}
    rows = {}
    for policy in args.policy:
        rows[policy] = {}
        for label, world in worlds.items():
            rows[policy][label] = agreement(*first_actions(policy, world, args.episodes, overrides))
            print(policy, label, rows[policy][label], flush=True)
    result = {
        "name": args.name,
        "episodes": args.episodes,
        "worlds": worlds,
        "env_overrides": overrides,
        "rows": rows,
        "machine": machine(),
        "measured_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "notes": args.notes,
    }
    (RESULTS / f"first_action_{args.name}.json").write_text(json.dumps(result, indent=1))
    write_markdown()


if __name__ == "__main__":
    main()
