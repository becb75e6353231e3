"""Issue 19: can the policy's image encoder, trained on some worlds, read where the ego is in the lane on others?

A supervised probe of perception alone, in minutes instead of a 15-min training run and its evaluation. Views are
rendered through the lane env's own observation path (its region, size and, on the training worlds, the training
mode's augmentations) at random places of each world, the ego put up to --offset-m to either side of the recorded path
and up to --yaw-rad off its heading, and labelled with that offset and heading error (as the picture shows them:
mirrored views flip both). The policy's encoder (the train config's convolutions, feature size and input pooling) with
a linear head is fitted to the training worlds' views; per test world it reports:
  MAE            mean |predicted - true| lateral offset, m (a constant guess of 0 scores offset_m / 2)
  slope, corr    least-squares slope and correlation of the predicted against the true offset (1 / 1: read right;
                 0: not seen at all; negative: read the wrong way)
  side           the share of views more than 1 m aside whose side is read right (0.5: chance)
  binned         the mean prediction in each of 10 bins of the true offset, from -offset_m to +offset_m
  m/rad          how much the read offset follows the heading instead: the heading's coefficient in a least-squares
                 fit of the read offset on the true offset and heading (0: the offset is not confused with the heading)
  yaw MAE, corr  the same for the heading error, degrees
A policy cannot return to its lane on a world where this probe reads the offset flat, whatever its reward says.

    python experiments/lateral_probe/bench_lateral_probe.py --train-world T1 --train-world T2 \
        --test-world U1 --test-world U2 --set gamma=[0.35,1.25] --name NAME --notes "..."

writes results/lateral_probe_<NAME>.json beside this script and (from every lateral_probe_*.json) lateral_probe.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "recovery"))  # the recovery study's world labels
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "_lib"))  # the studies' shared helpers (study.py)
from bench_recovery import label  # noqa: E402  (a short name for a world path: the folder above `world`)
from lateral_probe import VIEW_PARTS  # noqa: E402
from study import add_result_arguments, add_settings_argument, save_result  # noqa: E402

RESULTS = Path(__file__).parent / "results"
TEST_VIEWS = 1500
# Keys of the env config that shape the picture of a test world too (not augmentations, which are training-only).
VIEW_KEYS = ("roi_px", "roi_fov_deg", "roi_horizon_fraction", "observation_width_px", "observation_height_px")


def write_markdown() -> None:
    """experiments/lateral_probe/results/lateral_probe.md from every lateral_probe_*.json."""
    lines = [
        "# Lateral probe: what the policy's encoder reads of its place in the lane",
        "",
        "`experiments/lateral_probe/bench_lateral_probe.py`: a supervised probe of perception alone (issue 19).",
        "",
        "The encoder with a linear head, fitted on the training worlds' views, read on each test world's. MAE: mean",
        "error of the offset, m; slope / corr: of the read against the true offset (1 = read right, 0 = not seen,",
        "negative = read the wrong way); side: views more than 1 m aside whose side is read right; binned: the mean",
        "read offset per tenth of the true offsets, from the right to the left; m/rad: how much the read offset",
        "follows the heading instead (0: not confused); yaw: heading error, degrees.",
        "",
        "Worlds are named by the folder above `world`: seedN = procedural town N (101 never in any training); kraw =",
        "the real KITTI raw drive 2011_09_26_0001 (107 m beside tram tracks); kodo = the real KITTI odometry street",
        "(sequence 06, 60 m); krawA / krawB = KITTI raw's first 54 m / next 53 m (worlds sliced from kraw's);",
        "seed1A / seed1B = town 1's first 54 m / next 50 m (sliced the same way).",
        "",
    ]
    for path in sorted(RESULTS.glob("lateral_probe_*.json")):
        data = json.loads(path.read_text())
        trained = ", ".join(label(w) for w in data["train_worlds"])
        chosen = {**data["env_set"], **{f"policy.{k}": v for k, v in data.get("policy_set", {}).items()}}
        settings = ", ".join(f"{k}={v}" for k, v in chosen.items()) or "the env defaults"
        lines += [f"## {data['name']}", "", f"{data['machine']}, {data['date']}, {data['seconds']:.0f} s. "]
        if data.get("encoder"):
            lines[-1] += f"The encoder of the trained policy {data['encoder']} (frozen), a linear readout fitted on"
            lines[-1] += f" {trained} ({data['views_per_world']} views each), {settings};"
        else:
            lines[-1] += (
                f"Fitted on {trained} ({data['views_per_world']} views each, {data['epochs']} epochs), {settings};"
            )
        lines[-1] += f" offsets up to ±{data['offset_m']:g} m, headings ±{data['yaw_rad']:g} rad."
        if data.get("blank"):
            lines[-1] += f" The {data['blank']} half of every view blanked, training and test."
        lines += ["", "| test world | MAE (m) | slope | corr | side | binned (m) | m/rad | yaw MAE (°) | yaw corr |"]
        lines.append("|---|---|---|---|---|---|---|---|---|")
        for world, r in data["rows"].items():
            binned = " ".join("-" if v is None else f"{v:+.1f}" for v in r["binned_m"])
            confusion = f"{r['offset_per_heading_m_per_rad']:+.1f}" if "offset_per_heading_m_per_rad" in r else "-"
            lines.append(
                f"| {label(world)} | {r['offset_mae_m']:.2f} | {r['offset_slope']:.2f} | {r['offset_corr']:.2f} | "
                f"{r['side_right']:.0%} | {binned} | {confusion} | {r['yaw_mae_deg']:.1f} | {r['yaw_corr']:.2f} |"
            )
        picture = path.with_suffix(".png")
        plot_readings(data, picture)
        lines += ["", data.get("notes", ""), "", f"![read against true offset]({picture.name})", ""]
    (RESULTS / "lateral_probe.md").write_text("\n".join(lines))


def plot_readings(data: dict[str, Any], out: Path) -> None:
    """A picture of one result: the mean read offset against the true one per test world, beside the identity."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    offset_m = data["offset_m"]
    centres = np.linspace(-offset_m, offset_m, len(next(iter(data["rows"].values()))["binned_m"]) + 1)
    centres = 0.5 * (centres[1:] + centres[:-1])
    fig, ax = plt.subplots(figsize=(4.5, 4.0))
    ax.plot([-offset_m, offset_m], [-offset_m, offset_m], color="0.7", linestyle="--", label="read right")
    for world, r in data["rows"].items():
        read = [np.nan if v is None else v for v in r["binned_m"]]
        ax.plot(centres, read, marker="o", label=f"{label(world)} (slope {r['offset_slope']:.2f})")
    ax.set_xlabel("true offset, m (+ = left)")
    ax.set_ylabel("read offset, m")
    ax.set_title(data["name"], fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)


def load_encoder(run: str) -> tuple[Any, dict[str, Any]]:
    """A run's policy encoder (an ensemble's first member's) and the env config it trained with."""
    from drivesim.policy.run_folder import load_policy

    loaded = load_policy(Path(run))
    net = loaded.net.members[0] if hasattr(loaded.net, "members") else loaded.net
    return net.encoder, dict(loaded.env_config)


def parse_sets(texts: list[str]) -> dict[str, Any]:
    """`KEY=VALUE` env config settings (values parsed as YAML) -> dict."""
    from drivesim.pipeline.config import parse_override

    settings = {}
    for text in texts:
        keys, value = parse_override(text)
        settings[".".join(keys)] = value
    return settings


def main() -> None:
    """Parse the arguments, render, fit, score every test world, write the JSON and the markdown."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train-world", action="append", required=True, help="a world to fit on (repeatable)")
    parser.add_argument("--test-world", action="append", required=True, help="a world to read (repeatable)")
    parser.add_argument(
        "--encoder",
        default=None,
        metavar="RUN",
        help="read a trained policy's own encoder (frozen; a linear readout fitted) in its run's view, instead of "
        "fitting a fresh one",
    )
    add_settings_argument(parser, "--set", "env config (repeatable)")
    add_settings_argument(
        parser,
        "--policy-set",
        "the fitted encoder's architecture, as train's policy.KEY (e.g. input_pool=1; repeatable)",
    )
    parser.add_argument(
        "--blank",
        choices=VIEW_PARTS,
        default=None,
        help="blank that half of every view, training and test (top: the probe sees the near road only; bottom: the "
        "upper half only, the far road and what stands beside it and above)",
    )
    parser.add_argument("--views-per-world", type=int, default=6000, help="training views rendered per world")
    parser.add_argument("--epochs", type=int, default=12, help="passes over the training views")
    parser.add_argument("--offset-m", type=float, default=2.5, help="largest offset to either side, m")
    parser.add_argument("--yaw-rad", type=float, default=0.2, help="largest heading error to either side, rad")
    parser.add_argument("--seed", type=int, default=0, help="seed of the views and of the fit")
    add_result_arguments(parser, "lateral_probe")
    args = parser.parse_args()
    import torch
    from lateral_probe import blank_view_part, fit_probe, fit_readout, render_views, score_probe

    from drivesim.bench.machine import machine_line
    from drivesim.stages.train.config import PolicyConfig

    torch.set_num_threads(1)
    start = time.perf_counter()
    env_set, encoder = parse_sets(args.set), None
    if args.encoder:
        encoder, run_env = load_encoder(args.encoder)
        env_set = {**{k: v for k, v in run_env.items() if k in VIEW_KEYS}, **env_set}
    views = {k: v for k, v in env_set.items() if k in VIEW_KEYS}
    shape = (args.offset_m, args.yaw_rad)
    train = [
        render_views(w, env_set, "train", args.views_per_world, args.seed + 1 + i, *shape)
        for i, w in enumerate(args.train_world)
    ]
    images = blank_view_part(np.concatenate([t[0] for t in train]), args.blank)
    labels = np.concatenate([t[1] for t in train])
    policy = PolicyConfig(**parse_sets(args.policy_set))
    if encoder is None:
        net = fit_probe(images, labels, args.epochs, args.seed, policy)
    else:
        net = fit_readout(encoder, images, labels)
    rows = {}
    for world in args.test_world:
        test_images, test_labels = render_views(world, views, "eval", TEST_VIEWS, 777, *shape)
        rows[world] = score_probe(net, blank_view_part(test_images, args.blank), test_labels, args.offset_m)
        r = rows[world]
        print(f"{label(world)}: offset MAE {r['offset_mae_m']:.2f} m, slope {r['offset_slope']:.2f}, ", end="")
        print(f"side {r['side_right']:.0%}, yaw corr {r['yaw_corr']:.2f}", flush=True)
    result = {
        "name": args.name,
        "machine": machine_line(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "seconds": time.perf_counter() - start,
        "train_worlds": args.train_world,
        "encoder": args.encoder,
        "env_set": env_set,
        "policy_set": parse_sets(args.policy_set),
        **{k: getattr(args, k) for k in ("views_per_world", "epochs", "offset_m", "yaw_rad", "seed", "blank", "notes")},
        "rows": rows,
    }
    save_result(RESULTS, "lateral_probe", result, write_markdown)


if __name__ == "__main__":
    main()
