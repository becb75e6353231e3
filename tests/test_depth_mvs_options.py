"""The optional parts of mvs on hand-made cost volumes: best-k over the neighbours that see a pixel, the plane prior
for guessed road pixels, and the guided-filter aggregation."""

from __future__ import annotations

import numpy as np
import torch

from drivesim.stages.preprocess.depth_mvs import (
    _FILLED,
    _PLANE,
    _STEREO,
    _box,
    _k_smallest_mean,
    _plane_where_no_better,
    _visible_best_k_mean,
    guided_filter,
)


def test_best_k_counts_only_the_neighbours_that_see_the_pixel() -> None:
    costs = torch.ones(3, 2, 1, 2)  # 3 neighbours, 2 hypotheses, pixels A (all see it) and B (only neighbour 0)
    costs[:, :, 0, 0] = torch.tensor([[0.1, 0.5], [0.2, 0.6], [0.3, 0.7]])
    costs[0, :, 0, 1] = torch.tensor([0.1, 0.4])
    plain = _k_smallest_mean(iter(costs), 2)
    visible = _visible_best_k_mean(costs, 2)
    np.testing.assert_allclose(plain[:, 0, 0], visible[:, 0, 0])  # seen by all: the same best-2 mean
    np.testing.assert_allclose(visible[:, 0, 0], [0.15, 0.55], atol=1e-6)
    np.testing.assert_allclose(plain[:, 0, 1], [0.55, 0.7], atol=1e-6)  # the unseen count as mismatches ...
    np.testing.assert_allclose(visible[:, 0, 1], [0.1, 0.4], atol=1e-6)  # ... or are left out


def test_streamed_k_smallest_mean_equals_the_sorted_one() -> None:
    costs = torch.rand(5, 7, 4, 6, generator=torch.Generator().manual_seed(0))
    for k in (1, 2, 3, 5):
        expected = torch.topk(costs, k, dim=0, largest=False).values.mean(dim=0)
        torch.testing.assert_close(_k_smallest_mean(iter(costs), k), expected)


def test_the_cpu_box_filter_is_the_running_sum_window_mean_with_replicated_borders() -> None:
    x = torch.rand(2, 3, 9, 11, generator=torch.Generator().manual_seed(1))
    size = 5
    padded = torch.nn.functional.pad(x, (2, 2, 2, 2), mode="replicate")
    expected = torch.nn.functional.avg_pool2d(padded, size, stride=1)
    torch.testing.assert_close(_box(x, size), expected, atol=1e-6, rtol=1e-5)


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
