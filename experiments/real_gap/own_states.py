"""How far a trained overtake policy's steering is from the expert's on the policy's own states, by phase of the pass.

`bench_real_gap.py` measures the action error on the expert's states. Here the policy drives, and at every step the
privileged expert says what it would do from that very state. Steps fall into three phases: the other car in the
policy's view ("car in view"), not in view and not yet passed by the task's pass distance ("beside, out of view"),
and passed but not yet back in the lane ("passed, returning": an evaluation episode ends once back). The signed
error is taken toward the side the pass goes to (+: the policy steers further out than the expert, -: back towards
the lane sooner), so a policy that turns back too early while the car is beside it shows a negative mean there.

    .venv/bin/python experiments/real_gap/own_states.py --world W --meshes M --run RUN --episodes 40 --name NAME
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_real_gap import load_policies, make_env, render_with_mask  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
PHASES = ("car in view", "beside, out of view", "passed, returning")


def phase_of(env: Any, car_visible: bool) -> str:
    """The phase of the pass at the env's current state."""
    if car_visible:
        return PHASES[0]
    return PHASES[1] if env._m["pass_margin_m"] < env.config.pass_distance_m else PHASES[2]


def policy_episode(env: Any, seed: int, policy: Any) -> dict[str, Any]:
    """One episode driven by `policy`: per step its phase, |policy - expert| and the error signed toward the pass's
    side; the episode's side and end."""
    env.reset_state(seed)
    side = 1.0 if env.expert_target_offset() > 0.0 else -1.0  # + = the ego passes on the left
    state, start, steps, info, unseen = None, True, [], {}, 0
    while True:
        rgb, mask = render_with_mask(env)
        obs = env.observation_from(rgb)
        action, state = policy.predict(obs[None], state, np.array([start]))
        start = False
        steer = float(action[0, 0])
        expert = float(env.expert_action()[0])
        unseen = 0 if mask.any() else unseen + 1
        steps.append((phase_of(env, bool(mask.any())), abs(steer - expert), (steer - expert) * side, unseen))
        _, terminated, truncated, info = env.advance(np.array([steer], dtype=np.float32))
        if terminated or truncated:
            break
    end = next((k for k, v in info.get("termination", {}).items() if v), "success")
    return {"seed": seed, "side": "left" if side > 0 else "right", "end": end, "steps": steps}


def summarize(episodes: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean |error| and mean signed error per phase (all episodes, and the failed ones alone), and the success rate."""
    out: dict[str, Any] = {"episodes": len(episodes)}
    out["success"] = float(np.mean([e["end"] == "success" for e in episodes]))
    for group, members in (("all", episodes), ("failed", [e for e in episodes if e["end"] != "success"])):
        rows = {}
        for phase in (*PHASES, "all steps"):
            steps = [s for e in members for s in e["steps"] if phase == "all steps" or s[0] == phase]
            rows[phase] = {
                "steps": len(steps),
                "abs_error": float(np.mean([s[1] for s in steps])) if steps else None,
                "signed_error": float(np.mean([s[2] for s in steps])) if steps else None,
            }
        out[group] = rows
    return out


UNSEEN_BINS = ((1, 5), (6, 10), (11, 16), (17, 10_000))
"""Steps since the other car was last in view (beside, out of view): 16 is the LSTM's training chunk."""


def by_time_out_of_view(episodes: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Beside and out of view: the mean signed error by steps since the car was last in view."""
    out = {}
    for low, high in UNSEEN_BINS:
        steps = [s for e in episodes for s in e["steps"] if s[0] == PHASES[1] and low <= s[3] <= high]
        signed = float(np.mean([s[2] for s in steps])) if steps else None
        out[f"{low}-{high}" if high < 10_000 else f"{low}+"] = {"steps": len(steps), "signed_error": signed}
    return out


def markdown(name: str, args: argparse.Namespace, results: dict[str, dict[str, Any]]) -> str:
    """The results as a markdown report."""
    lines = [
        f"# Action error on the policy's own states, by phase of the pass ({name})",
        "",
        f"`python experiments/real_gap/own_states.py --world {args.world} --run {args.run} --episodes "
        f"{args.episodes}`: each policy drives seeds 0-{args.episodes - 1} in eval mode; at every step the expert's "
        "action from the same state. Signed error toward the pass's side: + = further out than the expert, - = back "
        "towards the lane sooner.",
        "",
        "| policy | episodes | success | group | phase | steps | mean abs error | mean signed error |",
        "|---|---:|---:|---|---|---:|---:|---:|",
    ]
    for policy, summary in results.items():
        for group in ("all", "failed"):
            for phase, row in summary[group].items():
                if row["steps"]:
                    lines.append(
                        f"| {policy} | {summary['episodes']} | {summary['success']:.3f} | {group} | {phase} | "
                        f"{row['steps']} | {row['abs_error']:.3f} | {row['signed_error']:+.3f} |"
                    )
    lines += [
        "",
        "Beside and out of view, by steps since the car was last in view (10 steps a second; the LSTM trains on "
        "16-step chunks): steps, mean signed error",
        "",
        "| policy | " + " | ".join(results[next(iter(results))]["by_time_out_of_view"]) + " |",
        "|---|" + "---:|" * len(UNSEEN_BINS),
    ]
    for policy, summary in results.items():
        cells = [
            f"{r['steps']}: {r['signed_error']:+.3f}" if r["steps"] else "0"
            for r in summary["by_time_out_of_view"].values()
        ]
        lines.append(f"| {policy} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--world", required=True)
    parser.add_argument("--meshes", required=True)
    parser.add_argument("--run", required=True, help="a run folder: its final policy and its warm start")
    parser.add_argument("--episodes", type=int, default=40)
    parser.add_argument("--name", required=True, help="results/own_states_<name>.{md,json}")
    args = parser.parse_args()
    env = make_env(args.world, args.meshes, {})
    results = {}
    for label, policy in load_policies(args.run).items():
        episodes = [policy_episode(env, seed, policy) for seed in range(args.episodes)]
        results[label] = {**summarize(episodes), "by_time_out_of_view": by_time_out_of_view(episodes)}
        print(label, json.dumps(results[label]["all"]), flush=True)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"own_states_{args.name}.json").write_text(json.dumps(results, indent=2, allow_nan=False) + "\n")
    (RESULTS / f"own_states_{args.name}.md").write_text(markdown(args.name, args, results))


if __name__ == "__main__":
    main()
