"""Tests of language-guided outlier pruning (lop.py): LOF (eq. 14, 15), groups, pruning (eq. 16)."""

from __future__ import annotations

import json
import math

import pytest
import torch
from torch import Tensor

from langfield.training.lop import (
    LOP_GAMMA,
    assign_groups,
    local_outlier_factor,
    lop_prune,
    lop_prune_mask,
    lop_scores,
)

PROTOS = [torch.eye(3) * 10 for _ in range(3)]  # three well-separated prototypes per level


def _reference_lof(points: Tensor, k: int) -> Tensor:
    """Brute-force LOF of the paper (eq. 14, 15) with torch.cdist, k = min(k, N - 1)."""
    p = points.double()
    k = min(k, len(p) - 1)
    dist = torch.cdist(p, p)
    dist.fill_diagonal_(math.inf)
    knn_dist, knn_idx = dist.topk(k, dim=1, largest=False)
    lrd = k / knn_dist.sum(1)
    return lrd[knn_idx].sum(1) / (k * lrd)


def _latents_for(groups: Tensor, levels: int = 3) -> Tensor:
    """[N, 3, 3] latents placing Gaussian j in group groups[j] (0..2) of PROTOS at every level."""
    return (torch.eye(3)[groups] * 10)[:, None, :].repeat(1, levels, 1)


def _cluster(n: int, center: tuple[float, float, float], spread: float, seed: int) -> Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.tensor(center) + torch.randn(n, 3, generator=g) * spread


@pytest.mark.parametrize("k", [1, 5, LOP_GAMMA])
def test_lof_matches_bruteforce_reference(k: int):
    points = torch.rand(60, 3, generator=torch.Generator().manual_seed(k))
    ours = local_outlier_factor(points, k)
    assert ours.dtype == torch.float64 and ours.shape == (60,)
    torch.testing.assert_close(ours, _reference_lof(points, k))


def test_grouped_scores_match_per_group_reference():
    g = torch.Generator().manual_seed(1)
    n = 150
    points = torch.rand(n, 3, generator=g)
    groups = torch.randint(0, 3, (n,), generator=g)
    groups[:7] = 2  # group 2 small: fewer members than gamma
    groups[7:] = groups[7:].clamp(max=1)
    scores = lop_scores(points, _latents_for(groups), PROTOS, levels=(0,))
    expected = torch.empty(n, dtype=torch.float64)
    for group in range(3):
        members = groups == group
        expected[members] = _reference_lof(points[members], LOP_GAMMA)
    assert (groups == 2).sum() == 7
    torch.testing.assert_close(scores, expected)


def test_obvious_floaters_of_a_group_are_pruned():
    dense = _cluster(200, (0.0, 0.0, 0.0), 0.1, seed=2)
    floaters = torch.tensor([[4.0, 0, 0], [0, -5.0, 0], [3.0, 3.0, 3.0], [-2.0, 0, 4.0], [0, 6.0, -1.0]])
    points = torch.cat([dense, floaters])
    groups = torch.zeros(len(points), dtype=torch.long)
    result = lop_prune(points, _latents_for(groups), PROTOS, tau=5 / 205)
    assert result.prune.nonzero().flatten().tolist() == list(range(200, 205))
    assert result.threshold > 2.0


def test_floater_inside_another_groups_cluster_is_pruned_by_language():
    # A "chair" Gaussian sitting inside the table's cluster is isolated among the chair's Gaussians: LOP
    # prunes it, though plain LOF over all positions sees it as an inlier.
    chair = _cluster(100, (0.0, 0.0, 0.0), 0.1, seed=3)
    table = _cluster(100, (3.0, 0.0, 0.0), 0.1, seed=4)
    stray_chair = torch.tensor([[3.0, 0.0, 0.0]])
    points = torch.cat([chair, table, stray_chair])
    groups = torch.cat([torch.zeros(100), torch.ones(100), torch.zeros(1)]).long()
    prune = lop_prune_mask(points, _latents_for(groups), PROTOS, tau=1 / 201)
    assert prune.nonzero().flatten().tolist() == [200]
    assert local_outlier_factor(points)[200] < 1.5


def test_small_group_uses_size_minus_one_neighbours():
    points = torch.rand(5, 3, generator=torch.Generator().manual_seed(5))
    scores = lop_scores(points, _latents_for(torch.zeros(5, dtype=torch.long)), PROTOS, gamma=LOP_GAMMA)
    torch.testing.assert_close(scores, _reference_lof(points, 4))
    assert torch.isfinite(scores).all()


def test_group_of_exactly_gamma_plus_one_uses_gamma_neighbours():
    points = torch.rand(LOP_GAMMA + 1, 3, generator=torch.Generator().manual_seed(6))
    groups = torch.zeros(LOP_GAMMA + 1, dtype=torch.long)
    torch.testing.assert_close(
        lop_scores(points, _latents_for(groups), PROTOS), _reference_lof(points, LOP_GAMMA)
    )


def test_singleton_group_has_lof_one_and_is_never_pruned():
    dense = _cluster(50, (0.0, 0.0, 0.0), 0.1, seed=7)
    lonely = torch.tensor([[50.0, 50.0, 50.0]])  # far away, but alone in its group
    points = torch.cat([dense, lonely])
    groups = torch.cat([torch.zeros(50), torch.ones(1)]).long()
    result = lop_prune(points, _latents_for(groups), PROTOS, tau=0.5)
    assert result.scores[50] == 1.0
    assert not result.prune[50]


def test_group_of_identical_positions_is_finite_and_neutral():
    points = torch.full((30, 3), 0.25)
    scores = lop_scores(points, _latents_for(torch.zeros(30, dtype=torch.long)), PROTOS)
    assert torch.isfinite(scores).all()
    torch.testing.assert_close(scores, torch.ones(30, dtype=torch.float64))
    assert not lop_prune_mask(points, _latents_for(torch.zeros(30, dtype=torch.long)), PROTOS, tau=0.5).any()


def test_many_duplicates_next_to_spread_points_stay_finite():
    duplicates = torch.zeros(40, 3)  # more than gamma copies: zero neighbour distances
    spread = _cluster(20, (0.5, 0.0, 0.0), 0.2, seed=8)
    points = torch.cat([duplicates, spread])
    groups = torch.zeros(60, dtype=torch.long)
    result = lop_prune(points, _latents_for(groups), PROTOS)
    assert torch.isfinite(result.scores).all() and torch.isfinite(result.level_scores).all()
    assert result.num_pruned == 3  # floor(0.05 x 60)
    assert not result.prune[:40].any()  # the densest points are not the outliers


def test_all_gaussians_in_one_group_equals_plain_lof():
    points = torch.rand(80, 3, generator=torch.Generator().manual_seed(9))
    groups = torch.zeros(80, dtype=torch.long)
    torch.testing.assert_close(lop_scores(points, _latents_for(groups), PROTOS), local_outlier_factor(points))


def test_empty_groups_are_ignored():
    points = torch.rand(60, 3, generator=torch.Generator().manual_seed(10))
    groups = torch.zeros(60, dtype=torch.long)
    many = [torch.cat([torch.eye(3) * 10, torch.full((20, 3), -50.0) + torch.arange(20.0)[:, None]])] * 3
    result = lop_prune(points, _latents_for(groups), many)
    assert result.groups == (1, 1, 1)
    torch.testing.assert_close(result.scores, local_outlier_factor(points))


def test_level_without_prototypes_does_not_vote():
    points = torch.cat([_cluster(60, (0.0, 0.0, 0.0), 0.1, seed=11), torch.tensor([[3.0, 0.0, 0.0]])])
    latents = _latents_for(torch.zeros(61, dtype=torch.long))
    protos = [PROTOS[0], torch.zeros(0, 3), PROTOS[2]]
    result = lop_prune(points, latents, protos, tau=1 / 61)
    assert result.groups == (1, 0, 1)
    assert (result.level_scores[1] == 1.0).all()
    assert result.pruned_by_level[1] == 0 and sum(result.pruned_by_level) == 1
    assert result.prune.nonzero().flatten().tolist() == [60]
    # No level with prototypes at all: nothing votes, nothing is pruned.
    none = lop_prune(points, latents, [torch.zeros(0, 3)] * 3, tau=0.5)
    assert none.num_pruned == 0 and (none.scores == 1.0).all()


def test_score_is_max_over_voting_levels():
    g = torch.Generator().manual_seed(12)
    points = torch.rand(90, 3, generator=g)
    latents = torch.eye(3)[torch.randint(0, 3, (90, 3), generator=g)] * 10
    result = lop_prune(points, latents, PROTOS)
    torch.testing.assert_close(result.scores, result.level_scores.max(0).values)
    only_whole = lop_scores(points, latents, PROTOS, levels=(2,))
    torch.testing.assert_close(only_whole, result.level_scores[2])


def test_prunes_the_top_tau_scores():
    g = torch.Generator().manual_seed(13)
    points = torch.rand(400, 3, generator=g)
    latents = torch.eye(3)[torch.randint(0, 3, (400, 3), generator=g)] * 10
    result = lop_prune(points, latents, PROTOS, tau=0.05)
    assert result.num_pruned == 20
    assert result.scores[result.prune].min() >= result.scores[~result.prune].max()
    assert result.threshold == result.scores[result.prune].min().item()
    assert sum(result.pruned_by_level) == 20


def test_tau_one_keeps_at_least_one_gaussian():
    # A configuration where every Gaussian has LOF > 1 at some level (found by search, gamma = 2).
    points = torch.tensor(
        [[1.0, 9, 0], [0, 1, 4], [6, 3, 5], [9, 0, 0], [2, 5, 7], [2, 5, 4]], dtype=torch.float32
    )
    labels = torch.tensor([[0, 0, 1], [1, 0, 1], [0, 1, 0], [0, 1, 0], [0, 0, 0], [0, 1, 1]])
    latents = torch.eye(3)[labels] * 10
    result = lop_prune(points, latents, PROTOS, gamma=2, tau=1.0)
    assert (result.scores > 1.0).all()
    assert result.num_pruned == 5
    assert not result.prune[result.scores.argmin()]


def test_only_gaussians_with_lof_above_one_are_pruned():
    points = torch.rand(3, 3, generator=torch.Generator().manual_seed(14))
    groups = torch.zeros(3, dtype=torch.long)
    result = lop_prune(points, _latents_for(groups), PROTOS, tau=1.0)
    assert result.num_pruned == int((result.scores > 1.0).sum()) <= 2
    assert (result.scores[result.prune] > 1.0).all()


def test_tau_zero_prunes_nothing():
    points = torch.cat([_cluster(100, (0.0, 0.0, 0.0), 0.1, seed=15), torch.tensor([[9.0, 9.0, 9.0]])])
    result = lop_prune(points, _latents_for(torch.zeros(101, dtype=torch.long)), PROTOS, tau=0.0)
    assert result.num_pruned == 0 and math.isinf(result.threshold)
    assert result.scores[100] > 2.0  # scored, just not pruned


def test_no_gaussians():
    result = lop_prune(torch.zeros(0, 3), torch.zeros(0, 3, 3), PROTOS)
    assert result.prune.shape == (0,) and result.prune.dtype == torch.bool
    assert result.scores.shape == (0,) and result.groups == (0, 0, 0)
    assert local_outlier_factor(torch.zeros(0, 3)).shape == (0,)


def test_one_gaussian():
    result = lop_prune(torch.ones(1, 3), _latents_for(torch.zeros(1, dtype=torch.long)), PROTOS, tau=1.0)
    assert result.num_pruned == 0
    assert result.scores.tolist() == [1.0]
    assert local_outlier_factor(torch.ones(1, 3)).tolist() == [1.0]


def test_assign_groups_picks_nearest_prototype():
    g = torch.Generator().manual_seed(16)
    latents = torch.randn(500, 3, 3, generator=g)
    protos = [torch.randn(7, 3, generator=g), torch.randn(4, 3, generator=g), torch.zeros(0, 3)]
    groups = assign_groups(latents, protos)
    for level in range(2):
        brute = ((latents[:, level, None, :] - protos[level][None]) ** 2).sum(-1).argmin(1)
        assert torch.equal(groups[level], brute)
    assert (groups[2] == -1).all()


def test_result_as_dict_is_json_ready():
    points = torch.cat([_cluster(100, (0.0, 0.0, 0.0), 0.1, seed=17), torch.tensor([[5.0, 5.0, 5.0]])])
    result = lop_prune(points, _latents_for(torch.zeros(101, dtype=torch.long)), PROTOS)
    record = json.loads(json.dumps(result.as_dict()))
    assert record["pruned"] == 5 and record["total"] == 101
    assert sum(record["pruned_by_level"]) == 5 and record["groups"] == [1, 1, 1]


def test_deterministic():
    g = torch.Generator().manual_seed(18)
    points = torch.rand(300, 3, generator=g)
    latents = torch.eye(3)[torch.randint(0, 3, (300, 3), generator=g)] * 10
    assert torch.equal(lop_prune_mask(points, latents, PROTOS), lop_prune_mask(points, latents, PROTOS))


def test_bad_inputs_raise():
    points = torch.rand(10, 3)
    latents = _latents_for(torch.zeros(10, dtype=torch.long))
    with pytest.raises(ValueError, match="tau"):
        lop_prune(points, latents, PROTOS, tau=1.5)
    with pytest.raises(ValueError, match="finite"):
        lop_prune(torch.full((10, 3), math.nan), latents, PROTOS)
    with pytest.raises(ValueError, match="positions"):
        lop_prune(torch.rand(10, 2), latents, PROTOS)
    with pytest.raises(ValueError, match="latents"):
        lop_prune(torch.rand(9, 3), latents, PROTOS)
    with pytest.raises(ValueError, match="prototype"):
        lop_prune(points, latents, PROTOS[:2])
    with pytest.raises(ValueError, match="gamma"):
        lop_prune(points, latents, PROTOS, gamma=0)
