"""A supervised probe of perception alone: can the policy's image encoder, fitted on some worlds' views, read the
ego's lateral offset and heading error in others'? (`bench_lateral_probe.py`
beside it is its report.)

Views are rendered through the lane env's own observation path at random places, offsets and headings, and labelled
with that offset and heading as the picture shows them; the encoder is the policy's (the train config's defaults) with
a linear head. A policy cannot return to its lane on a world where this probe reads the offset flat.
"""

from __future__ import annotations

from typing import Any

import numpy as np

BINS = 10
YAW_LABEL_SCALE = 10.0  # the heading error (~0.1 rad) scaled to the offset's size (~1 m) in the loss
BATCH = 256
VIEWS_PER_EPISODE = 8


def render_views(
    world: str, env_config: dict[str, Any], mode: str, count: int, seed: int, offset_m: float, yaw_rad: float
) -> tuple[np.ndarray, np.ndarray]:
    """`count` observations (N, 3, H, W) uint8 of `world` at random places, offsets and headings, and their labels
    (N, 2): lateral offset m (+ = left) and heading error rad, as the picture shows them. A new episode (its
    augmentations) every VIEWS_PER_EPISODE views."""
    import gymnasium

    import drivesim.sim.envs  # noqa: F401  (registers the envs)

    config = {"min_path_length_m": 30.0, **env_config}
    env = gymnasium.make("drivesim/Lane-v0", world=world, meshes=None, mode=mode, config=config).unwrapped
    rng = np.random.default_rng(seed)
    images, labels = [], []
    for episode in range(-(-count // VIEWS_PER_EPISODE)):
        env.reset_state(seed * 1_000_003 + episode)  # the episode's augmentations; no view rendered
        ref = env.sim.reference
        for _ in range(VIEWS_PER_EPISODE):
            arc_m = rng.uniform(ref.start_m + 3.0, ref.end_m - 3.0)
            images.append(env.place_ego(arc_m, rng.uniform(-offset_m, offset_m), rng.uniform(-yaw_rad, yaw_rad)))
            labels.append(env.lane_position())
    return np.stack(images[:count]), np.asarray(labels[:count], dtype=np.float32)


VIEW_PARTS = ("top", "bottom")


def blank_view_part(images: np.ndarray, part: str | None) -> np.ndarray:
    """`images` (N, C, H, W) uint8 with their `part` set to black, as a copy: "top" blanks the upper half of every view
    (a probe then sees the near road only), "bottom" the lower half (it sees the far road and what stands beside it and
    above: roadside, trees, buildings, sky); None returns `images` themselves."""
    if part is None:
        return images
    if part not in VIEW_PARTS:
        raise ValueError(f"view part {part!r}: give one of {', '.join(VIEW_PARTS)}")
    out, half = images.copy(), images.shape[2] // 2
    if part == "top":
        out[:, :, :half] = 0
    else:
        out[:, :, half:] = 0
    return out


def fit_probe(images: np.ndarray, labels: np.ndarray, epochs: int, seed: int, policy: Any = None) -> Any:
    """The policy's encoder (`policy`, a PolicyConfig; default the train config's) with a linear head, fitted to
    (offset, heading) by Adam."""
    import torch
    from torch import nn

    from drivesim.policy.net import ImageEncoder
    from drivesim.stages.train.config import TrainConfig

    torch.manual_seed(seed)
    policy = TrainConfig().policy if policy is None else policy
    encoder = ImageEncoder(images.shape[1:], policy.conv_layers, policy.features_dim, policy.input_pool)
    net = nn.Sequential(encoder, nn.Linear(policy.features_dim, 2))
    x, y = torch.from_numpy(images), torch.from_numpy(labels) * torch.tensor([1.0, YAW_LABEL_SCALE])
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    for _ in range(epochs):
        order = torch.randperm(len(x))
        for start in range(0, len(x), BATCH):
            batch = order[start : start + BATCH]
            loss = nn.functional.smooth_l1_loss(net(x[batch]), y[batch])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    return net


def fit_readout(encoder: Any, images: np.ndarray, labels: np.ndarray, ridge: float = 1e-3) -> Any:
    """A linear readout of a trained, frozen encoder (a policy's): ridge regression of (offset, heading) on its
    features; returns the encoder with that head, as `fit_probe` does."""
    import torch
    from torch import nn

    encoder = encoder.eval().requires_grad_(False)
    with torch.no_grad():
        features = torch.cat([encoder(torch.from_numpy(images[i : i + BATCH])) for i in range(0, len(images), BATCH)])
    # Ridge regression in closed form (scikit-learn's Ridge does the same, but is not a dependency for five lines).
    design = torch.cat([features, torch.ones(len(features), 1)], dim=1).double()
    target = torch.from_numpy(labels).double() * torch.tensor([1.0, YAW_LABEL_SCALE], dtype=torch.float64)
    gram = design.T @ design + ridge * len(design) * torch.eye(design.shape[1], dtype=torch.float64)
    weights = torch.linalg.solve(gram, design.T @ target)
    head = nn.Linear(features.shape[1], 2)
    with torch.no_grad():
        head.weight.copy_(weights[:-1].T.float())
        head.bias.copy_(weights[-1].float())
    return nn.Sequential(encoder, head)


def score_probe(net: Any, images: np.ndarray, labels: np.ndarray, offset_m: float) -> dict[str, Any]:
    """The probe's reading of one world's views against their labels: the offset's mean error (m), the slope and
    correlation of the read against the true offset, the share of views more than 1 m aside whose side is read right,
    the mean read offset in each of BINS bins of the true one (-offset_m to +offset_m), how much of the read offset
    follows the heading instead (the heading's coefficient, m per rad, in a least-squares fit of the read offset on
    the true offset and heading), and the heading's mean error (degrees) and correlation."""
    import torch

    with torch.no_grad():
        predicted = net(torch.from_numpy(images)).numpy() / np.array([1.0, YAW_LABEL_SCALE])
    true_q, read_q = labels[:, 0], predicted[:, 0]
    aside = np.abs(true_q) > 1.0
    both = np.stack([true_q, labels[:, 1], np.ones(len(true_q))], axis=1)
    bins = np.clip(((true_q + offset_m) / (2 * offset_m) * BINS).astype(int), 0, BINS - 1)
    return {
        "offset_mae_m": float(np.mean(np.abs(read_q - true_q))),
        "offset_slope": float(np.polyfit(true_q, read_q, 1)[0]),
        "offset_corr": correlation(true_q, read_q),
        "side_right": float(np.mean(np.sign(read_q[aside]) == np.sign(true_q[aside]))),
        "binned_m": [float(np.mean(read_q[bins == b])) if np.any(bins == b) else None for b in range(BINS)],
        "offset_per_heading_m_per_rad": float(np.linalg.lstsq(both, read_q, rcond=None)[0][1]),
        "yaw_mae_deg": float(np.degrees(np.mean(np.abs(predicted[:, 1] - labels[:, 1])))),
        "yaw_corr": correlation(labels[:, 1], predicted[:, 1]),
    }


def correlation(true: np.ndarray, read: np.ndarray) -> float:
    """Pearson's correlation; 0 where the reading does not vary (a constant reads nothing)."""
    if np.std(read) == 0.0 or np.std(true) == 0.0:
        return 0.0
    return float(np.corrcoef(true, read)[0, 1])
