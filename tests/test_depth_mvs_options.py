"""The optional parts of mvs on hand-made cost volumes: best-k over the neighbours that see a pixel, the plane prior
for guessed road pixels, and the guided-filter aggregation."""

from __future__ import annotations

import numpy as np
import torch

from drivesim.stages.preprocess.depth_mvs import (
    _FILLED,
    _PLANE,
    _STEREO,
    _best_k_mean,
    _plane_where_no_better,
    guided_filter,
)


def test_best_k_counts_only_the_neighbours_that_see_the_pixel() -> None:
    costs = torch.ones(3, 2, 1, 2)  # 3 neighbours, 2 hypotheses, pixels A (all see it) and B (only neighbour 0)
    costs[:, :, 0, 0] = torch.tensor([[0.1, 0.5], [0.2, 0.6], [0.3, 0.7]])
    costs[0, :, 0, 1] = torch.tensor([0.1, 0.4])
    plain = _best_k_mean(costs, 2, visible_only=False)
    visible = _best_k_mean(costs, 2, visible_only=True)
    np.testing.assert_allclose(plain[:, 0, 0], visible[:, 0, 0])  # seen by all: the same best-2 mean
    np.testing.assert_allclose(visible[:, 0, 0], [0.15, 0.55], atol=1e-6)
    np.testing.assert_allclose(plain[:, 0, 1], [0.55, 0.7], atol=1e-6)  # the unseen count as mismatches ...
    np.testing.assert_allclose(visible[:, 0, 1], [0.1, 0.4], atol=1e-6)  # ... or are left out


def test_a_guessed_road_pixel_takes_the_plane_unless_its_guess_matches_better() -> None:
    inv_depths = torch.linspace(1 / 2.0, 1 / 80.0, 8)
    sweep = torch.full((8, 1, 3), 0.4)  # textureless: every depth matches equally badly
    sweep[2, 0, 1] = 0.1  # pixel 1: its guessed depth (hypothesis 2) matches clearly better than the plane
    plane_cost = torch.full((1, 3), 0.4)
    guess_m = np.full((1, 3), 1 / float(inv_depths[2]), np.float32)
    plane_m = np.full((1, 3), 12.0, np.float32)
    labels = np.array([[_FILLED, _FILLED, _STEREO]])
    depth, out_labels = _plane_where_no_better(guess_m, labels, plane_m, 80.0, sweep, plane_cost, inv_depths, 0.05)
    np.testing.assert_allclose(depth[0], [12.0, guess_m[0, 1], guess_m[0, 2]])
    assert out_labels.tolist() == [[_PLANE, _FILLED, _STEREO]]  # trusted stereo is never touched


def test_guided_aggregation_smooths_within_a_region_and_keeps_its_edge() -> None:
    guide = torch.zeros(1, 20, 40)
    guide[:, :, 20:] = 1.0  # a strong edge between two flat regions
    noise = torch.from_numpy(np.random.default_rng(0).normal(0, 0.1, (1, 20, 40)).astype(np.float32))
    costs = torch.where(torch.arange(40) < 20, 0.2, 0.8).expand(1, 20, 40) + noise
    filtered = guided_filter(guide, costs, 4, 1e-3)
    assert filtered[0, :, 5:15].std() < 0.3 * noise[0, :, 5:15].std()  # the noise is averaged away
    assert abs(float(filtered[0, :, 18].mean()) - 0.2) < 0.05 and abs(float(filtered[0, :, 21].mean()) - 0.8) < 0.05
