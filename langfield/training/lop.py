"""Language-guided outlier pruning (LOP): remove floaters that are isolated among their semantic peers.

Sparse views leave Gaussians floating in front of the surfaces. LOP groups the Gaussians by meaning and
looks for the ones that lie far from the rest of their group:

1. Prototypes P^l: the distinct autoencoded mask features of all training views at level l.
2. Each Gaussian's group at level l is its nearest prototype, argmin_k ||P_k^l - phi_j^l||.
3. Inside each group, with gamma nearest neighbours by position (open3d), the local reachability
   density LRD(m) = gamma / sum_{u in kNN(m)} d(m, u) (eq. 14) and the local outlier factor
   LOF(m) = sum_{u in kNN(m)} LRD(u) / (gamma LRD(m)) (eq. 15). These are the paper's simplified forms
   (plain distances, not the reachability distances of Breunig et al.).
4. The top tau of the Gaussians by LOF are pruned (eq. 16).

Choices where the paper is silent:

- Voting of the levels: a Gaussian's score is the *maximum* over the voting levels of its LOF in that
  level's group, and the top tau x N scores overall are pruned. A floater is a Gaussian isolated from
  the Gaussians of the same meaning; being isolated at one level of meaning (e.g. from the rest of "the
  chair") is enough evidence, and one ranking keeps the total at most tau x N (a union of per-level top
  tau could prune up to 3 tau x N).
- Only Gaussians with a score above 1 are candidates: LOF <= 1 means "at least as dense as its
  neighbours", an inlier by definition, so tau is an upper bound on the fraction pruned.
- Small groups: a group of n <= gamma Gaussians uses k = n - 1 neighbours; a Gaussian alone in its group
  has no neighbours and gets LOF 1 (no evidence), so it is never pruned on that level's account.
  Groups are found with one kNN search per level over (x, y, z, group x separation) points, so
  neighbours never cross groups and no Python loop runs over groups.
- Duplicate positions: the mean neighbour distance (1 / LRD) is floored at ``DISTANCE_FLOOR`` x the
  diagonal of the Gaussians' bounding box (and at ``ABSOLUTE_DISTANCE_FLOOR``), so LRD stays finite; a
  group of identical positions has LOF 1 everywhere.
- At least one Gaussian always remains: at most N - 1 are pruned, whatever tau.
- A level without prototypes does not vote.

Example:
    >>> g = torch.Generator().manual_seed(0)
    >>> positions = torch.cat([torch.randn(200, 3, generator=g) * 0.1, torch.tensor([[5.0, 5.0, 5.0]])])
    >>> latents = torch.zeros(201, 3, 3)  # every Gaussian in the same group at every level
    >>> prototypes = [torch.zeros(1, 3)] * 3
    >>> prune = lop_prune_mask(positions, latents, prototypes, tau=0.005)
    >>> prune.nonzero().flatten().tolist()
    [200]
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d.core as o3c
import torch
from torch import Tensor

__all__ = [
    "ABSOLUTE_DISTANCE_FLOOR",
    "DISTANCE_FLOOR",
    "LOP_GAMMA",
    "LOP_INTERVAL",
    "LOP_LEVELS",
    "LOP_TAU",
    "LOPResult",
    "assign_groups",
    "local_outlier_factor",
    "lop_prune",
    "lop_prune_mask",
    "lop_scores",
]

LOP_GAMMA = 20  # neighbours per Gaussian (the paper's gamma)
LOP_TAU = 0.05  # fraction pruned (the paper's tau)
LOP_INTERVAL = 1000  # iterations between two prunings (the paper's interval; for the trainer)
LOP_LEVELS = (0, 1, 2)  # subpart, part, whole
DISTANCE_FLOOR = 1e-6  # x bounding-box diagonal: smallest mean neighbour distance (1 / LRD) counted
ABSOLUTE_DISTANCE_FLOOR = 1e-12  # when every position is the same
_CHUNK = 16384  # Gaussians per block when computing latent-to-prototype distances


@dataclass(frozen=True)
class LOPResult:
    """The outcome of one LOP pass.

    Attributes:
        prune: [N] bool, True = remove this Gaussian.
        scores: [N] float64, max over the voting levels of the Gaussian's LOF (1 where no level votes).
        level_scores: [len(levels), N] float64 LOF of each Gaussian in its group at each voting level.
        levels: the voting levels, in the order of ``level_scores``.
        groups: non-empty groups per voting level.
        pruned_by_level: per voting level, pruned Gaussians whose highest LOF came from that level.
        threshold: lowest score pruned (inf when nothing is pruned).
    """

    prune: Tensor
    scores: Tensor
    level_scores: Tensor
    levels: tuple[int, ...]
    groups: tuple[int, ...]
    pruned_by_level: tuple[int, ...]
    threshold: float

    @property
    def num_pruned(self) -> int:
        return int(self.prune.sum())

    def as_dict(self) -> dict[str, object]:
        """Counts for logging (JSON-serialisable)."""
        return {
            "pruned": self.num_pruned,
            "total": int(self.prune.numel()),
            "levels": list(self.levels),
            "groups": list(self.groups),
            "pruned_by_level": list(self.pruned_by_level),
            "threshold": self.threshold if math.isfinite(self.threshold) else None,
        }


def _check_positions(positions: Tensor) -> None:
    if positions.ndim != 2 or positions.shape[1] != 3 or not positions.is_floating_point():
        raise ValueError(
            f"positions must be a float [N, 3] tensor, got {positions.dtype} {tuple(positions.shape)}"
        )
    if not bool(torch.isfinite(positions).all()):
        raise ValueError("positions must be finite (a NaN position means training has diverged)")


def _distance_floor(positions: np.ndarray) -> float:
    """``DISTANCE_FLOOR`` x the bounding-box diagonal, at least ``ABSOLUTE_DISTANCE_FLOOR``."""
    if len(positions) == 0:
        return ABSOLUTE_DISTANCE_FLOOR
    diagonal = float(np.linalg.norm(positions.max(0) - positions.min(0)))
    return max(DISTANCE_FLOOR * diagonal, ABSOLUTE_DISTANCE_FLOOR)


def _grouped_lof(positions: np.ndarray, groups: np.ndarray, gamma: int, floor: float) -> np.ndarray:
    """LOF (eq. 14, 15) of every point among the points of its own group, all groups in one kNN search.

    Each point is lifted to (x, y, z, group x separation) with the separation larger than any distance
    inside the bounding box: same-group points keep their exact distances (the 4th coordinates are equal),
    other groups are farther than all of them. One search for gamma + 1 neighbours (self included) then
    returns every point's in-group neighbours first, and the out-of-group ones that fill up small groups
    are dropped.

    Args:
        positions: [N, 3] float64.
        groups: [N] int64 group of each point.
        gamma: neighbours per point (fewer in groups of gamma or fewer points).
        floor: smallest mean neighbour distance.

    Returns:
        [N] float64 LOF, 1 for points alone in their group.
    """
    n = len(positions)
    if n == 0:
        return np.zeros(0)
    separation = 2.0 * float(np.linalg.norm(positions.max(0) - positions.min(0))) + 1.0
    _, compact = np.unique(groups, return_inverse=True)
    lifted = np.concatenate([positions, (compact.reshape(-1) * separation)[:, None]], axis=1)
    points = o3c.Tensor(np.ascontiguousarray(lifted))
    search = o3c.nns.NearestNeighborSearch(points)
    search.knn_index()
    k = min(gamma + 1, n)
    idx, dist2 = search.knn_search(points, k)
    idx = idx.numpy().reshape(n, k)
    dist = np.sqrt(dist2.numpy().reshape(n, k))
    rows = np.arange(n)[:, None]
    # In-group neighbours other than self; with duplicates self may be missing, so keep the first gamma.
    neighbour = (groups[idx] == groups[:, None]) & (idx != rows)
    neighbour &= np.cumsum(neighbour, axis=1) <= gamma
    count = neighbour.sum(1)
    mean_dist = np.where(neighbour, dist, 0.0).sum(1) / np.maximum(count, 1)
    lrd = 1.0 / np.maximum(mean_dist, floor)  # eq. 14: gamma / sum of distances
    neighbour_lrd = np.where(neighbour, lrd[idx], 0.0).sum(1)
    lof = neighbour_lrd / (np.maximum(count, 1) * lrd)  # eq. 15
    return np.where(count > 0, lof, 1.0)


def local_outlier_factor(positions: Tensor, k: int = LOP_GAMMA) -> Tensor:
    """LOF of every point among all the others (eq. 14, 15), one group.

    LRD(m) = k / sum_{u in kNN(m)} d(m, u), LOF(m) = sum_{u in kNN(m)} LRD(u) / (k LRD(m)), with
    k = min(k, N - 1) and neighbour distances floored as described in the module docstring.

    Args:
        positions: [N, 3] float points.
        k: neighbours per point (the paper's gamma).

    Returns:
        [N] float64 LOF (1 = as dense as its neighbours, larger = more isolated); 1 when N = 1.

    Example:
        >>> pts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [9, 9, 0]])
        >>> int(local_outlier_factor(pts, k=2).argmax())
        4
    """
    _check_positions(positions)
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    p = positions.detach().cpu().to(torch.float64).numpy()
    lof = _grouped_lof(p, np.zeros(len(p), dtype=np.int64), k, _distance_floor(p))
    return torch.from_numpy(lof).to(positions.device)


def assign_groups(
    latents: Tensor, prototypes: Sequence[Tensor], levels: Sequence[int] = LOP_LEVELS
) -> Tensor:
    """Each Gaussian's group at each level: the index of its nearest prototype (LOP's step 2).

    Args:
        latents: [N, L, 3] language latents phi of the Gaussians (L = 3 levels).
        prototypes: one [P_l, 3] tensor per level of ``latents``: the distinct autoencoded mask features
            of all training views at that level.
        levels: levels to assign.

    Returns:
        [len(levels), N] int64 group (prototype index) per level; -1 at a level without prototypes.
    """
    if latents.ndim != 3 or not latents.is_floating_point():
        raise ValueError(
            f"latents must be a float [N, L, D] tensor, got {latents.dtype} {tuple(latents.shape)}"
        )
    if len(prototypes) != latents.shape[1]:
        raise ValueError(
            f"need one prototype tensor per level: {latents.shape[1]} levels, got {len(prototypes)}"
        )
    n = latents.shape[0]
    out = torch.full((len(levels), n), -1, dtype=torch.int64)
    for row, level in enumerate(levels):
        if not 0 <= level < latents.shape[1]:
            raise ValueError(f"level {level} out of range 0..{latents.shape[1] - 1}")
        protos = prototypes[level].detach().cpu().to(torch.float32)
        if protos.ndim != 2 or protos.shape[1] != latents.shape[2]:
            raise ValueError(
                f"prototypes[{level}] must be [P, {latents.shape[2]}], got {tuple(protos.shape)}"
            )
        if protos.shape[0] == 0 or n == 0:
            continue
        phi = latents[:, level].detach().cpu().to(torch.float32)
        if not bool(torch.isfinite(phi).all()):
            raise ValueError(f"latents at level {level} must be finite")
        for start in range(0, n, _CHUNK):
            out[row, start : start + _CHUNK] = torch.cdist(phi[start : start + _CHUNK], protos).argmin(1)
    return out


def _level_scores(
    positions: Tensor, latents: Tensor, prototypes: Sequence[Tensor], levels: Sequence[int], gamma: int
) -> tuple[Tensor, tuple[int, ...]]:
    """[len(levels), N] float64 LOF per voting level (1 where a level has no prototypes), and the
    number of non-empty groups per level."""
    _check_positions(positions)
    if latents.shape[0] != positions.shape[0]:
        raise ValueError(f"{positions.shape[0]} positions but {latents.shape[0]} latents")
    if gamma < 1:
        raise ValueError(f"gamma must be >= 1, got {gamma}")
    groups = assign_groups(latents, prototypes, levels)
    p = positions.detach().cpu().to(torch.float64).numpy()
    floor = _distance_floor(p)
    scores = np.ones((len(levels), len(p)))
    counts = []
    for row in range(len(levels)):
        g = groups[row].numpy()
        counts.append(int(len(np.unique(g))) if g.size and g[0] >= 0 else 0)
        if counts[-1]:
            scores[row] = _grouped_lof(p, g, gamma, floor)
    return torch.from_numpy(scores), tuple(counts)


def lop_scores(
    positions: Tensor,
    latents: Tensor,
    prototypes: Sequence[Tensor],
    levels: Sequence[int] = LOP_LEVELS,
    gamma: int = LOP_GAMMA,
) -> Tensor:
    """Each Gaussian's outlier score: max over ``levels`` of its LOF inside its group at that level.

    Args:
        positions: [N, 3] Gaussian means.
        latents: [N, 3, 3] language latents phi (Gaussian, level, latent).
        prototypes: one [P_l, 3] tensor per level (see :func:`assign_groups`).
        levels: the voting levels.
        gamma: neighbours per Gaussian.

    Returns:
        [N] float64 scores (1 where no level votes), on ``positions``' device.
    """
    level_scores, _ = _level_scores(positions, latents, prototypes, levels, gamma)
    return _max_over_levels(level_scores).to(positions.device)


def _max_over_levels(level_scores: Tensor) -> Tensor:
    if level_scores.shape[0] == 0:
        return torch.ones(level_scores.shape[1], dtype=torch.float64)
    return level_scores.max(0).values


def lop_prune(
    positions: Tensor,
    latents: Tensor,
    prototypes: Sequence[Tensor],
    gamma: int = LOP_GAMMA,
    tau: float = LOP_TAU,
    levels: Sequence[int] = LOP_LEVELS,
) -> LOPResult:
    """One LOP pass (eq. 14-16): scores every Gaussian and marks the top tau for removal.

    At most floor(tau x N) Gaussians are pruned, only ones with a score above 1, and never all of them
    (at most N - 1). Ties at the threshold are broken by index (lowest first), deterministically.

    Args:
        positions: [N, 3] Gaussian means.
        latents: [N, 3, 3] language latents phi (Gaussian, level, latent).
        prototypes: one [P_l, 3] tensor per level (see :func:`assign_groups`).
        gamma: neighbours per Gaussian.
        tau: fraction to prune, in [0, 1].
        levels: the voting levels.

    Returns:
        A :class:`LOPResult`; its ``prune`` mask is on ``positions``' device.
    """
    if not 0.0 <= tau <= 1.0:
        raise ValueError(f"tau must be in [0, 1], got {tau}")
    levels = tuple(int(v) for v in levels)
    level_scores, groups = _level_scores(positions, latents, prototypes, levels, gamma)
    scores = _max_over_levels(level_scores)
    n = scores.numel()
    budget = min(math.floor(tau * n + 1e-9), max(n - 1, 0))
    budget = min(budget, int((scores > 1.0).sum()))
    prune = torch.zeros(n, dtype=torch.bool)
    threshold = math.inf
    pruned_by_level = [0] * len(levels)
    if budget > 0:
        order = torch.argsort(-scores, stable=True)[:budget]
        prune[order] = True
        threshold = float(scores[order[-1]])
        top_level = level_scores[:, order].argmax(0)
        pruned_by_level = torch.bincount(top_level, minlength=len(levels)).tolist()
    return LOPResult(
        prune=prune.to(positions.device),
        scores=scores,
        level_scores=level_scores,
        levels=levels,
        groups=groups,
        pruned_by_level=tuple(pruned_by_level),
        threshold=threshold,
    )


def lop_prune_mask(
    positions: Tensor,
    latents: Tensor,
    prototypes: Sequence[Tensor],
    gamma: int = LOP_GAMMA,
    tau: float = LOP_TAU,
    levels: Sequence[int] = LOP_LEVELS,
) -> Tensor:
    """[N] bool, True = prune: the ``prune`` mask of :func:`lop_prune`."""
    return lop_prune(positions, latents, prototypes, gamma, tau, levels).prune
