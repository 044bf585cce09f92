"""Gaussian parameters: creation, random initialisation inside the scene bounds, and activations.

The parameters live in a :class:`torch.nn.ParameterDict` laid out like gsplat's ``splats``; every entry is
per-Gaussian, ``[N, ...]``, so densification can edit all of them alike:

- ``"means"``: [N, 3] centres in world coordinates.
- ``"log_scales"``: [N, 3] log of the standard deviations along the Gaussian's axes.
- ``"quats"``: [N, 4] rotations as unnormalised quaternions (w, x, y, z).
- ``"opacity_logits"``: [N, 1] logits of the opacities.

Later stages may add more per-Gaussian entries (e.g. ``"lang"`` [N, 9]).
"""

from __future__ import annotations

import math

import numpy as np
import open3d.core as o3c
import torch
from torch import Tensor, nn

# Smallest quaternion norm treated as a rotation; shorter ones become the identity.
QUAT_EPS = 1e-8

# 3DGS clamps the mean squared neighbour distance here (simple_knn's distCUDA2 result) so that duplicate
# points do not get log(0) scales.
_MIN_SQ_DIST = 1e-7


def init_gaussians(bounds: np.ndarray, num: int, *, seed: int, init_opacity: float = 0.1) -> nn.ParameterDict:
    """Random Gaussians inside an axis-aligned box (DNGaussian's random initialisation).

    Positions are uniform in the box (seeded, deterministic); rotations are the identity; each scale is
    the root mean squared distance to the 3 nearest neighbours, isotropic (3DGS's ``distCUDA2``); the
    opacity is ``init_opacity`` (3DGS and DNGaussian: 0.1).

    Args:
        bounds: [2, 3] box ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]`` with max > min.
        num: number of Gaussians (>= 1).
        seed: seed of the positions.
        init_opacity: initial opacity in (0, 1).

    Returns:
        ParameterDict with "means" [N, 3], "log_scales" [N, 3], "quats" [N, 4], "opacity_logits" [N, 1],
        float32.

    Example:
        >>> p = init_gaussians(np.array([[-1.0, -1, -1], [1, 1, 1]]), 100, seed=0)
        >>> p["means"].shape, p["quats"][0].tolist()
        (torch.Size([100, 3]), [1.0, 0.0, 0.0, 0.0])
    """
    lo, hi = _check_bounds(bounds)
    if num < 1:
        raise ValueError(f"need at least one Gaussian, got num={num}")
    gen = torch.Generator().manual_seed(int(seed))
    lo_t, hi_t = torch.from_numpy(lo).float(), torch.from_numpy(hi).float()
    means = lo_t + torch.rand(num, 3, generator=gen) * (hi_t - lo_t)
    return gaussians_at(means, init_opacity=init_opacity, lone_scale=0.01 * float(np.linalg.norm(hi - lo)))


def gaussians_at(points: Tensor, *, init_opacity: float = 0.1, lone_scale: float = 0.01) -> nn.ParameterDict:
    """Gaussians centred at ``points`` [N, 3] (3DGS's initialisation from a point cloud): identity
    rotations, isotropic scales from the 3 nearest neighbours (``distCUDA2``), opacity ``init_opacity``.

    ``lone_scale``: the scale of a single point, which has no neighbours.
    """
    if points.dim() != 2 or points.shape[1] != 3 or points.shape[0] < 1:
        raise ValueError(f"need points [N >= 1, 3], got {tuple(points.shape)}")
    if not 0.0 < init_opacity < 1.0:
        raise ValueError(f"init_opacity must be in (0, 1), got {init_opacity}")
    means = points.detach().float().clone()
    num = means.shape[0]
    if num > 1:
        log_scales = log_scales_from_neighbors(means)
    else:
        # A lone Gaussian has no neighbours; give it a hundredth of the box, like 3DGS's percent_dense.
        log_scales = torch.full((1, 3), math.log(lone_scale))
    quats = torch.zeros(num, 4)
    quats[:, 0] = 1.0
    opacity_logits = torch.full((num, 1), math.log(init_opacity / (1.0 - init_opacity)))
    return nn.ParameterDict(
        {
            "means": nn.Parameter(means),
            "log_scales": nn.Parameter(log_scales),
            "quats": nn.Parameter(quats),
            "opacity_logits": nn.Parameter(opacity_logits),
        }
    )


def log_scales_from_neighbors(points: Tensor, k: int = 3) -> Tensor:
    """Isotropic log-scales from neighbour distances, as 3DGS initialises them.

    ``scale = sqrt(max(mean squared distance to the k nearest neighbours, 1e-7))``; the clamp keeps
    duplicate points finite.

    Args:
        points: [N, 3] positions, N >= 2.
        k: neighbours to average over (3DGS: 3).

    Returns:
        [N, 3] log-scales, float32.
    """
    sq = mean_sq_neighbor_distance(points, k=k)
    return (0.5 * torch.log(sq.clamp_min(_MIN_SQ_DIST)))[:, None].repeat(1, 3)


def mean_sq_neighbor_distance(points: Tensor, k: int = 3) -> Tensor:
    """Mean squared distance of every point to its ``k`` nearest other points (open3d's kNN search).

    Args:
        points: [N, 3] positions, N >= 2.
        k: neighbours to average over; fewer are used if N - 1 < k.

    Returns:
        [N] mean squared distances, float32; 0 for points whose neighbours all coincide with them.
    """
    pts = np.ascontiguousarray(points.detach().cpu().numpy(), dtype=np.float32)
    k = min(k, len(pts) - 1)
    nns = o3c.nns.NearestNeighborSearch(o3c.Tensor(pts))
    nns.knn_index()
    # k + 1 because each point finds itself; with duplicate points the zero may belong to a twin, which
    # gives the same distances.
    _, sq_dist = nns.knn_search(o3c.Tensor(pts), k + 1)
    sq = torch.from_numpy(sq_dist.numpy().astype(np.float32))  # [N, k + 1], ascending, squared
    return sq[:, 1:].mean(dim=1)


def scales(params: nn.ParameterDict) -> Tensor:
    """Standard deviations along the Gaussians' axes, [N, 3] = exp(log_scales)."""
    return torch.exp(params["log_scales"])


def opacities(params: nn.ParameterDict) -> Tensor:
    """Opacities in (0, 1), [N, 1] = sigmoid(opacity_logits)."""
    return torch.sigmoid(params["opacity_logits"])


def quats_normalized(params: nn.ParameterDict) -> Tensor:
    """Unit quaternions (w, x, y, z), [N, 4], from ``params["quats"]`` via :func:`normalize_quats`."""
    return normalize_quats(params["quats"])


def normalize_quats(quats: Tensor, eps: float = QUAT_EPS) -> Tensor:
    """Normalise quaternions; any shorter than ``eps`` (e.g. all zero) becomes the identity.

    The squared norm is clamped before the square root, so neither the value nor the gradient is NaN at
    zero (the gradient of ``||q||`` at 0 would be 0/0).

    Args:
        quats: [..., 4] quaternions (w, x, y, z).
        eps: smallest norm treated as a rotation.

    Returns:
        [..., 4] unit quaternions.
    """
    sq = (quats * quats).sum(dim=-1, keepdim=True)
    unit = quats / sq.clamp_min(eps * eps).sqrt()
    identity = torch.zeros_like(quats)
    identity[..., 0] = 1.0
    return torch.where(sq < eps * eps, identity, unit)


START_PER_PIXEL = 0.15  # start Gaussians per training pixel (num_gaussians_for_scene)


def num_gaussians_for_scene(bounds: np.ndarray, image_pixels: int, n_views: int) -> int:
    """Initial number of Gaussians for a scene: 15 % of the training pixels, in [2000, 50000].

    Start points are only useful where the images can tell them apart, so the count follows the
    supervision, not the volume: ``0.15 x image_pixels x n_views``. Densification adds Gaussians where
    the images ask for detail. Images of 333 x 333 pixels or more (fern, DTU, lego with 3 views) reach
    the 50,000 cap. On the built-in scene (3 views of 160x120) the first pruning keeps about 40 % of the
    start whatever its size, so a bigger start pays for the first 600 iterations for nothing: 8,640
    instead of 14,400 measured over three seeds in docs/history/figures.md ("A smaller start").
    Reference points: DNGaussian initialises 10k random points for Blender (8 views of 800x800), 1k for
    DTU and 50 x the COLMAP cloud's largest side for LLFF.
    The bounds are checked but do not enter the rule.

    Args:
        bounds: [2, 3] box the Gaussians are drawn in.
        image_pixels: pixels of one training image, ``width * height``.
        n_views: number of training images.

    Returns:
        The number of Gaussians.

    Example:
        >>> num_gaussians_for_scene(np.array([[-1.0, -1, -1], [1, 1, 1]]), 160 * 120, 3)
        8640
    """
    _check_bounds(bounds)
    if image_pixels < 1 or n_views < 1:
        raise ValueError(f"image_pixels and n_views must be positive, got {image_pixels}, {n_views}")
    return int(min(max(round(START_PER_PIXEL * image_pixels * n_views), 2000), 50000))


def learning_rates(extent: float) -> dict[str, float]:
    """Adam learning rates of the Gaussian parameters (3DGS defaults, also DNGaussian's).

    From 3DGS's ``OptimizationParams`` (arguments/__init__.py), kept by DNGaussian: position 1.6e-4 scaled
    by the scene extent (``spatial_lr_scale``), scaling 5e-3, rotation 1e-3, opacity 5e-2. DNGaussian's
    sparse-view scripts lower scaling to 3e-3 and raise the position lr; callers may override.

    Args:
        extent: scene extent (radius) in world units, > 0.

    Returns:
        {"means", "log_scales", "quats", "opacity_logits"} -> learning rate.
    """
    if not extent > 0:
        raise ValueError(f"extent must be positive, got {extent}")
    return {"means": 1.6e-4 * extent, "log_scales": 5e-3, "quats": 1e-3, "opacity_logits": 5e-2}


def _check_bounds(bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate a [2, 3] box and return its (min, max) corners as float64."""
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (2, 3) or not np.isfinite(b).all() or (b[1] <= b[0]).any():
        raise ValueError(f"bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, got {b}")
    return b[0], b[1]
