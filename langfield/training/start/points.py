"""Where the Gaussians start: :func:`start_points` for each ``--init`` method.

Three views leave most of a random start in free space, and the geometry between the views never
forms from it. With the poses known, the photos alone give surface points:

- ``dense`` (the default): plane-sweep stereo on every training view against the others (Collins 1996;
  the fronto-parallel sweep with a ZNCC cost that COLMAP's and MVSNet's pipelines start from):
  for each depth hypothesis the other views are warped onto the reference view by the plane's
  homography, the best-scoring depth is kept per pixel, refined to sub-plane precision, and kept only
  where it is distinct, textured, and agrees with another view's depth map (geometric consistency,
  as in COLMAP's fusion). CoR-GS starts from COLMAP's dense MVS of the training views for the same
  reason; this is its classical core, with OpenCV warps and box filters on the CPU.
- ``sfm``: SIFT features matched across the training views and triangulated with the known poses by
  pycolmap (COLMAP's extraction, exhaustive matching and ``triangulate_points``), as FSGS and CoR-GS
  do; sparse on three views (about a hundred points on LLFF fern).
- ``depth``: the scene's depth prior of each training view, aligned per view by scale and shift to
  the dense points it sees, the views' lines then refined to agree with one another
  (:mod:`langfield.training.start.alignment`), each view's prior corrected by a smooth field and the
  views' depths fused where they agree (:mod:`langfield.training.start.correction`), and back-projected.
- ``points``: the scene's own point cloud (``sparse_pc.ply``, which ``langfield capture`` writes from
  COLMAP's model of every frame it posed, as nerfstudio's splatfacto starts from it); it holds points
  that only the test views saw, so a held-out score with it is not a three-view score.
- ``random``: uniform in the bounds (DNGaussian), also the fallback when a method finds too few
  points, with a warning.

The start has the number of Gaussians asked for. Photos that resolve fewer points than that are
topped up near their own surfaces (copies of their points moved by about one neighbour spacing), and
every method adds a sparse random fill inside the bounds (``fill`` of the photo points' count), so
regions no photo pair resolves can still be claimed by densification.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from langfield.camera import Camera
from langfield.training.start.depth_prior import INIT_ALIGNS, depth_prior_points
from langfield.training.start.stereo import PlaneSweepConfig, dense_points, inside_bounds, thin_evenly

__all__ = ["INIT_ALIGNS", "INIT_METHODS", "MIN_POINTS", "StartPoints", "random_points", "start_points"]

InitMethod = Literal["dense", "sfm", "depth", "points", "random"]
INIT_METHODS: tuple[str, ...] = ("dense", "sfm", "depth", "points", "random")
# Below this many photo points a start is not trusted: random instead, with a warning.
MIN_POINTS = 200


@dataclass(frozen=True)
class StartPoints:
    """Where the Gaussians start.

    Attributes:
        points: [N, 3] float32 world positions (photo points first, then the random fill).
        colors: [N, 3] float32 colours in [0, 1] from the images (grey for the random fill).
        method: the method that produced the photo points ("random" after a fallback).
        stats: what the report records (counts per stage, seconds).
        depths: the training views' stereo z-depth maps ([H, W], NaN where unresolved) when the
            method computed them (:func:`stereo_depths`), else None.
    """

    points: np.ndarray
    colors: np.ndarray
    method: str
    stats: dict = field(default_factory=dict)
    depths: tuple[np.ndarray, ...] | None = None


def random_points(bounds: np.ndarray, n: int, seed: int) -> np.ndarray:
    """[n, 3] float32 uniform in the box, seeded (the points of ``gaussians.init_gaussians``)."""
    import torch

    lo = torch.from_numpy(np.asarray(bounds[0], dtype=np.float64)).float()
    hi = torch.from_numpy(np.asarray(bounds[1], dtype=np.float64)).float()
    return (lo + torch.rand(n, 3, generator=torch.Generator().manual_seed(int(seed))) * (hi - lo)).numpy()


def start_points(
    method: InitMethod,
    cameras: list[Camera],
    images: list[np.ndarray],
    bounds: np.ndarray,
    num: int,
    *,
    seed: int = 0,
    fill: float = 0.1,
    priors: list[np.ndarray] | None = None,
    depth_kind: str | None = None,
    sweep: PlaneSweepConfig | None = None,
    align: str = "fused",
    scene_points: tuple[np.ndarray, np.ndarray] | None = None,
) -> StartPoints:
    """The start of training: ``num`` points by ``method`` (module docstring), the last ``fill`` of
    them random in ``bounds``.

    Args:
        method: "dense", "sfm", "depth", "points" or "random".
        cameras, images: the training views.
        bounds: [2, 3] scene box.
        num: the number of Gaussians to start with (photo points are thinned or topped up to
            ``num / (1 + fill)``).
        seed, fill: seed of the random points; their count as a fraction of the photo points.
        priors, depth_kind, align: the training views' depth priors and how they are aligned
            (``method="depth"``, :func:`depth_prior_points`).
        sweep: plane-sweep settings (default :class:`PlaneSweepConfig`).
        scene_points: the scene's point cloud ([P, 3], colours [P, 3] in [0, 1]) for "points".

    Returns:
        :class:`StartPoints`; ``method`` is "random" when the photos gave fewer than MIN_POINTS points
        (a warning says so).
    """
    if method not in INIT_METHODS:
        raise ValueError(f"init must be one of {', '.join(INIT_METHODS)}, got {method!r}")
    bounds = np.asarray(bounds, dtype=np.float64)
    sweep = sweep or PlaneSweepConfig()
    t0 = time.perf_counter()
    stats: dict = {"method": method}
    wanted = max(1, round(num / (1.0 + fill)))
    photo, colors, depth_maps = _photo_points(
        method, cameras, images, bounds, wanted, stats, priors, depth_kind, sweep, align, scene_points
    )
    used = method
    if method != "random" and len(photo) < MIN_POINTS:
        warnings.warn(
            f"init {method!r}: the training views gave {len(photo)} points (fewer than {MIN_POINTS}); "
            "starting from random points instead",
            stacklevel=2,
        )
        used, photo, colors = "random", photo[:0], colors[:0]
    # The start has exactly `num` Gaussians: photos that gave fewer than `wanted` points are topped up
    # near their own surfaces (capacity where the geometry is, not in free space), then `fill` random.
    n_photo = len(photo)
    if used != "random" and n_photo < wanted:
        photo, colors = _top_up(photo, colors, wanted, bounds, seed)
    n_random = num - len(photo)
    rand = random_points(bounds, n_random, seed)
    points = np.concatenate([photo, rand]).astype(np.float32)
    colors = np.concatenate([colors, np.full((n_random, 3), 0.5, np.float32)]).astype(np.float32)
    stats.update(
        used=used,
        photo_points=n_photo,
        near_surface_points=len(photo) - n_photo,
        random_points=n_random,
        seconds=time.perf_counter() - t0,
    )
    return StartPoints(points, colors, used, stats, depth_maps if used != "random" else None)


def _photo_points(
    method: str,
    cameras: list[Camera],
    images: list[np.ndarray],
    bounds: np.ndarray,
    wanted: int,
    stats: dict,
    priors: list[np.ndarray] | None,
    depth_kind: str | None,
    sweep: PlaneSweepConfig,
    align: str,
    scene_points: tuple[np.ndarray, np.ndarray] | None,
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...] | None]:
    """The points ``method`` finds (at most ``wanted``), their colours and the stereo depth maps it
    computed; each stage's stats go into ``stats``."""
    depth_maps = None
    photo = colors = np.zeros((0, 3), np.float32)
    if method in ("dense", "depth"):
        photo, colors, stats["dense"] = dense_points(
            cameras, images, bounds, replace(sweep, max_points=wanted)
        )
        if "depths" in stats["dense"]:  # not when there is one view
            depth_maps = tuple(stats["dense"].pop("depths"))
    if method == "sfm":
        from langfield.training.start.sfm import sfm_points  # pycolmap: loaded only when asked for

        photo, colors, stats["sfm"] = sfm_points(cameras, images)
        photo, colors = thin_evenly(*inside_bounds(photo, colors, bounds), wanted)
    if method == "points":
        photo, colors, stats["points"] = _file_points(scene_points, bounds, wanted)
    if method == "depth":
        photo, colors, stats["depth"] = depth_prior_points(
            cameras, images, priors, depth_kind, photo, depth_maps, align=align
        )
        photo, colors = thin_evenly(*inside_bounds(photo, colors, bounds), wanted)
    return photo, colors, depth_maps


def _file_points(
    scene_points: tuple[np.ndarray, np.ndarray] | None, bounds: np.ndarray, wanted: int
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The scene's point cloud inside ``bounds``, thinned to ``wanted``, and what the stats record."""
    if scene_points is None:
        raise ValueError("init 'points' needs the scene's point cloud")
    inside, colors = inside_bounds(*scene_points, bounds)
    points, colors = thin_evenly(inside, colors, wanted)
    return points, colors, {"file_points": len(scene_points[0]), "inside_bounds": len(inside)}


def _top_up(
    points: np.ndarray, colors: np.ndarray, wanted: int, bounds: np.ndarray, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """``wanted`` points: ``points`` and copies of them (drawn evenly, with their colours) moved by a
    normal offset of each one's neighbour spacing, kept inside ``bounds``."""
    import torch

    from langfield.model.gaussians import mean_sq_neighbor_distance

    extra = wanted - len(points)
    rng = np.random.default_rng(seed)
    source = rng.integers(0, len(points), extra)
    spacing = np.sqrt(np.maximum(mean_sq_neighbor_distance(torch.from_numpy(points)).numpy(), 1e-12))
    moved = points[source] + rng.standard_normal((extra, 3)).astype(np.float32) * spacing[source, None]
    moved = np.clip(moved, bounds[0], bounds[1]).astype(np.float32)
    return np.concatenate([points, moved]), np.concatenate([colors, colors[source]])
