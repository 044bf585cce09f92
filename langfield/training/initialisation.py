"""Start points for the Gaussians from the training photos themselves (no network).

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
  (:mod:`langfield.training.prior_alignment`), each view's prior corrected by a smooth field and the
  views' depths fused where they agree (:mod:`langfield.training.prior_correction`), and back-projected.
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

import math
import time
import warnings
from dataclasses import dataclass, field, replace
from typing import Literal

import cv2
import numpy as np

from langfield.camera import Camera
from langfield.training.pixels import (
    backproject,
    box_mean,
    cv_pose,
    gray,
    intrinsic_matrix,
    project,
    window_stats,
    zncc,
)
from langfield.training.prior_alignment import refine_alignment
from langfield.training.prior_correction import correct_priors, fuse_views

__all__ = [
    "INIT_ALIGNS",
    "INIT_METHODS",
    "PlaneSweepConfig",
    "StartPoints",
    "dense_points",
    "depth_prior_points",
    "plane_sweep",
    "random_points",
    "sfm_points",
    "stereo_depths",
]

InitMethod = Literal["dense", "sfm", "depth", "points", "random"]
INIT_METHODS: tuple[str, ...] = ("dense", "sfm", "depth", "points", "random")
# How the ``depth`` start aligns each view's prior: "views" refines the per-view fits so that the views
# agree with one another (langfield.training.prior_alignment), "smooth" then corrects each view's prior
# by a smooth field (langfield.training.prior_correction), "fused" then moves each pixel to the mean of
# the views that agree on it (one layer per surface), "anchors" keeps each view's own fit.
INIT_ALIGNS: tuple[str, ...] = ("fused", "smooth", "views", "anchors")
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


@dataclass(frozen=True)
class PlaneSweepConfig:
    """Settings of :func:`plane_sweep` and :func:`dense_points`.

    Attributes:
        planes: depth hypotheses, uniform in inverse depth between near and far.
        window: ZNCC window in pixels at 400 pixels of width (scaled with the image, odd, >= 5).
        min_score: lowest mean ZNCC over the source views to keep a pixel.
        min_texture: lowest standard deviation of the reference's grey values in the window (0-1 scale):
            flat patches match every depth.
        consistency: largest relative depth difference to another view's depth map.
        reprojection: largest reprojection error (pixels) of that round trip.
        max_points: cap on the fused points (a voxel grid thins them evenly to it).
    """

    planes: int = 384
    window: int = 7
    min_score: float = 0.7
    min_texture: float = 0.01
    consistency: float = 0.03
    reprojection: float = 1.0
    max_points: int = 60000


def depth_range(cam: Camera, bounds: np.ndarray) -> tuple[float, float]:
    """(near, far) z-depths of the box ``bounds`` [2, 3] seen from ``cam`` (near kept positive)."""
    corners = np.array(
        [[bounds[i][0], bounds[j][1], bounds[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    )
    _, z = project(corners, cam)
    far = float(z.max())
    if far <= 0:
        raise ValueError(f"camera {cam.name!r}: the scene bounds lie behind it")
    near = max(float(z.min()), far * 0.02)
    return near, far


# ---------------------------------------------------------------- plane sweep


def plane_sweep(
    ref: Camera,
    ref_image: np.ndarray,
    sources: list[tuple[Camera, np.ndarray]],
    near: float,
    far: float,
    cfg: PlaneSweepConfig = PlaneSweepConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """Depth map of ``ref`` by a fronto-parallel plane sweep against ``sources``.

    For each of ``cfg.planes`` depths d (uniform in 1/d), each source image is warped onto the
    reference by the homography of the plane z = d, H = K_s (R + t n^T / d) K_r^-1 (n = (0, 0, 1),
    [R | t] the reference-to-source pose), and scored by zero-normalised cross-correlation over a
    window; the score of a depth is the mean over the sources that see the pixel. The best depth is
    refined by a parabola through its neighbours' scores (in 1/d).

    Args:
        ref: the reference camera; ``ref_image`` its [H, W, 3] image in [0, 1].
        sources: (camera, image) of the other views.
        near, far: z-depth range to sweep, 0 < near < far.
        cfg: settings.

    Returns:
        ``(depth [H, W], score [H, W])``: z-depth (OpenCV: along the viewing axis) and the best mean
        ZNCC in [-1, 1]; score -1 where no source sees the pixel at any depth or the patch is flat.
    """
    if not 0 < near < far or not sources:
        raise ValueError(f"plane_sweep: need 0 < near < far and a source view, got {near}, {far}")
    h, w = ref.height, ref.width
    size = max(5, 2 * round(cfg.window * w / 400 / 2) + 1)  # 3x3 windows match too much noise
    g_ref = gray(ref_image)
    mu_r, var_r = window_stats(g_ref, size)
    flat = np.sqrt(var_r) < cfg.min_texture
    k_ref_inv = np.linalg.inv(intrinsic_matrix(ref))
    r_ref, t_ref = cv_pose(ref)
    inv_depths = np.linspace(1.0 / near, 1.0 / far, cfg.planes)
    scores = np.full((cfg.planes, h, w), -1.0, dtype=np.float32)
    prepared = []
    for cam, image in sources:
        r_src, t_src = cv_pose(cam)
        rel_r = r_src @ r_ref.T
        rel_t = t_src - rel_r @ t_ref
        plane_part = intrinsic_matrix(cam) @ np.outer(rel_t, [0.0, 0.0, 1.0]) @ k_ref_inv
        prepared.append((intrinsic_matrix(cam) @ rel_r @ k_ref_inv, plane_part, gray(image), cam))
    # Pixel centres: OpenCV's warp maps integer pixel coordinates, so shift by the half pixel.
    shift = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    unshift = np.linalg.inv(shift)
    for i, inv_d in enumerate(inv_depths):
        total = np.zeros((h, w), np.float32)
        count = np.zeros((h, w), np.float32)
        for rot_part, trans_part, g_src, cam in prepared:
            homography = unshift @ (rot_part + trans_part * inv_d) @ shift
            flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            warped = cv2.warpPerspective(g_src, homography, (w, h), flags=flags, borderValue=0.0)
            seen = cv2.warpPerspective(
                np.ones((cam.height, cam.width), np.float32), homography, (w, h), flags=flags, borderValue=0.0
            )
            score, var_s = zncc(g_ref, mu_r, var_r, warped, size)
            valid = (box_mean(seen, size) > 0.999) & (var_s > cfg.min_texture**2)
            total += np.where(valid, score, 0.0)
            count += valid
        scores[i] = np.where(count > 0, total / np.maximum(count, 1.0), -1.0)
    depth, best_score, interior = _best_depth(scores, inv_depths)
    # The end planes are the range's edges, not surfaces found there.
    best_score = np.where(flat | ~interior, -1.0, best_score).astype(np.float32)
    return depth, best_score


def _best_depth(scores: np.ndarray, inv_depths: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel the best of the planes' ``scores`` [P, H, W], refined below a plane's step by the
    vertex of the parabola through the best score and its neighbours (in 1/d): (z-depth, best score,
    whether the best plane is an interior one with a true maximum)."""
    planes = len(inv_depths)
    best = scores.argmax(axis=0)
    best_score = np.take_along_axis(scores, best[None], 0)[0]
    lo = np.clip(best - 1, 0, planes - 1)
    hi = np.clip(best + 1, 0, planes - 1)
    s_lo = np.take_along_axis(scores, lo[None], 0)[0]
    s_hi = np.take_along_axis(scores, hi[None], 0)[0]
    denom = s_lo - 2 * best_score + s_hi
    interior = (best > 0) & (best < planes - 1) & (denom < -1e-6)
    offset = np.where(interior, 0.5 * (s_lo - s_hi) / np.where(interior, denom, -1.0), 0.0)
    step = inv_depths[1] - inv_depths[0] if planes > 1 else 0.0
    inv = inv_depths[best] + np.clip(offset, -0.5, 0.5) * step
    return (1.0 / inv).astype(np.float32), best_score, interior


def _consistent(
    depth: np.ndarray, cam: Camera, other_depth: np.ndarray, other_valid: np.ndarray, other: Camera,
    cfg: PlaneSweepConfig,
) -> np.ndarray:  # fmt: skip
    """[H, W] bool: pixels whose point lands on ``other``'s depth map at the same depth (relative
    difference below ``cfg.consistency``) and projects back within ``cfg.reprojection`` pixels."""
    h, w = depth.shape
    rows, cols = np.mgrid[0:h, 0:w]
    rows, cols = rows.ravel(), cols.ravel()
    pts = backproject(depth, cam, rows, cols)
    uv, z = project(pts, other)
    c, r = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    inside = (z > 0) & (c >= 0) & (c < other.width) & (r >= 0) & (r < other.height)
    ok = np.zeros(h * w, dtype=bool)
    idx = np.nonzero(inside)[0]
    ci, ri = c[idx], r[idx]
    d_other = other_depth[ri, ci]
    good = other_valid[ri, ci] & (np.abs(d_other - z[idx]) <= cfg.consistency * z[idx])
    idx, ci, ri = idx[good], ci[good], ri[good]
    back = backproject(other_depth, other, ri, ci)
    uv_back, _ = project(back, cam)
    err = np.hypot(uv_back[:, 0] - (cols[idx] + 0.5), uv_back[:, 1] - (rows[idx] + 0.5))
    ok[idx[err <= cfg.reprojection + math.sqrt(0.5)]] = True
    return ok.reshape(h, w)


def stereo_depths(
    cameras: list[Camera],
    images: list[np.ndarray],
    bounds: np.ndarray,
    cfg: PlaneSweepConfig = PlaneSweepConfig(),
) -> tuple[list[np.ndarray], list[int]]:
    """Each view's plane-sweep z-depth where it is matched and agrees with another view's.

    Args:
        cameras, images: the training views ([H, W, 3] images in [0, 1]); at least two.
        bounds: [2, 3] box the scene lies in (the sweep's depth range).
        cfg: settings.

    Returns:
        ``(depths, matched)``: per view an [H, W] float32 z-depth map (OpenCV: along the viewing axis),
        NaN where the sweep found no distinct match or no other view agrees; and per view the number of
        matched pixels before the consistency check.
    """
    sweeps, valid = [], []
    for i, cam in enumerate(cameras):
        near, far = depth_range(cam, bounds)
        sources = [(c, im) for j, (c, im) in enumerate(zip(cameras, images, strict=True)) if j != i]
        depth, score = plane_sweep(cam, images[i], sources, near, far, cfg)
        sweeps.append(depth)
        valid.append(score >= cfg.min_score)
    depths = []
    for i, cam in enumerate(cameras):
        agree = np.zeros_like(valid[i])
        for j, other in enumerate(cameras):
            if j != i:
                agree |= _consistent(sweeps[i], cam, sweeps[j], valid[j], other, cfg)
        depths.append(np.where(valid[i] & agree, sweeps[i], np.nan).astype(np.float32))
    return depths, [int(v.sum()) for v in valid]


def dense_points(
    cameras: list[Camera],
    images: list[np.ndarray],
    bounds: np.ndarray,
    cfg: PlaneSweepConfig = PlaneSweepConfig(),
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Surface points of the training views by plane sweep and geometric consistency
    (:func:`stereo_depths` back-projected, then thinned to ``cfg.max_points``).

    Args:
        cameras, images: the training views ([H, W, 3] images in [0, 1]); at least two.
        bounds: [2, 3] box the scene lies in (the sweep's depth range, and points outside are dropped).
        cfg: settings.

    Returns:
        ``(points [N, 3], colors [N, 3], stats)``; ``stats["depths"]`` holds the depth maps (taken out
        by :func:`start_points` before the stats are recorded).
    """
    if len(cameras) < 2:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), {"reason": "one view"}
    depths, matched = stereo_depths(cameras, images, bounds, cfg)
    points, colors, kept = [], [], []
    for i, cam in enumerate(cameras):
        rows, cols = np.nonzero(np.isfinite(depths[i]))
        kept.append(len(rows))
        points.append(backproject(depths[i], cam, rows, cols))
        colors.append(images[i][rows, cols])
    pts = np.concatenate(points).astype(np.float32)
    cols_ = np.concatenate(colors).astype(np.float32)
    pts, cols_ = _thin(*_inside(pts, cols_, bounds), cfg.max_points)
    stats = {"matched_per_view": matched, "consistent_per_view": kept, "points": len(pts), "depths": depths}
    return pts, cols_, stats


def _thin(points: np.ndarray, colors: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``max_points``, evenly: one point per cell of the finest voxel grid that keeps no more
    cells than that (a bisection on the cell size), so dense regions lose points and sparse ones not."""
    if len(points) <= max_points:
        return points, colors
    lo = points.min(axis=0)
    extent = float((points.max(axis=0) - lo).max()) or 1.0
    fine, coarse = extent / 1e5, extent  # cells of these sizes keep too many / too few points
    first = np.arange(1)
    for _ in range(40):
        size = math.sqrt(fine * coarse)
        keys = np.floor((points - lo) / size).astype(np.int64)
        _, index = np.unique(keys, axis=0, return_index=True)
        if len(index) > max_points:
            fine = size
        else:
            coarse, first = size, index
        if coarse / fine < 1.02:
            break
    first = np.sort(first)
    return points[first], colors[first]


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
    sweep: PlaneSweepConfig = PlaneSweepConfig(),
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
        sweep: plane-sweep settings.
        scene_points: the scene's point cloud ([P, 3], colours [P, 3] in [0, 1]) for "points".

    Returns:
        :class:`StartPoints`; ``method`` is "random" when the photos gave fewer than MIN_POINTS points
        (a warning says so).
    """
    if method not in INIT_METHODS:
        raise ValueError(f"init must be one of {', '.join(INIT_METHODS)}, got {method!r}")
    bounds = np.asarray(bounds, dtype=np.float64)
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
        photo, colors, stats["sfm"] = sfm_points(cameras, images)
        photo, colors = _thin(*_inside(photo, colors, bounds), wanted)
    if method == "points":
        photo, colors, stats["points"] = _file_points(scene_points, bounds, wanted)
    if method == "depth":
        photo, colors, stats["depth"] = depth_prior_points(
            cameras, images, priors, depth_kind, photo, depth_maps, align=align
        )
        photo, colors = _thin(*_inside(photo, colors, bounds), wanted)
    return photo, colors, depth_maps


def _file_points(
    scene_points: tuple[np.ndarray, np.ndarray] | None, bounds: np.ndarray, wanted: int
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The scene's point cloud inside ``bounds``, thinned to ``wanted``, and what the stats record."""
    if scene_points is None:
        raise ValueError("init 'points' needs the scene's point cloud")
    inside, colors = _inside(*scene_points, bounds)
    points, colors = _thin(inside, colors, wanted)
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


def _inside(points: np.ndarray, colors: np.ndarray, bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    keep = np.all((points >= bounds[0]) & (points <= bounds[1]), axis=1)
    return points[keep], colors[keep]


def depth_prior_points(
    cameras: list[Camera],
    images: list[np.ndarray],
    priors: list[np.ndarray] | None,
    depth_kind: str | None,
    anchors: np.ndarray,
    stereo: list[np.ndarray] | tuple[np.ndarray, ...] | None = None,
    min_anchors: int = 50,
    align: str = "fused",
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Every pixel of each training view's depth prior, aligned to metric depths and back-projected.

    A monocular prior is relative: per view, the scale and shift that map it to known depths (z for
    ``depth``, 1/z for ``disparity``) are fitted by :func:`_trimmed_fit`. The known depths are the
    view's own ``stereo`` z-depth map where it resolves at least ``min_anchors`` pixels (pixel-aligned,
    so nothing occluded in this view enters the fit), else the ``anchors`` [N, 3] projected into the
    view; views with fewer than ``min_anchors`` of either are skipped. With ``align="views"`` the lines
    are then refined so that the views' aligned priors agree with one another
    (:func:`langfield.training.prior_alignment.refine_alignment`); ``"smooth"`` also corrects each
    view's aligned prior by a smooth field, from photo-consistency and the other views
    (:func:`langfield.training.prior_correction.correct_priors`); ``"fused"`` then moves each pixel's
    depth to the mean of the views that agree on it (:func:`~langfield.training.prior_correction.fuse_views`);
    ``"anchors"`` keeps each view's own fit.

    Returns:
        ``(points [N, 3], colors [N, 3], stats)`` with the per-view fit in ``stats``.
    """
    if priors is None or depth_kind is None:
        raise ValueError("init 'depth' needs every training view's depth prior (depths/ and depth_kind)")
    if align not in INIT_ALIGNS:
        raise ValueError(f"align must be one of {', '.join(INIT_ALIGNS)}, got {align!r}")
    lines, known, fits = [], [], []
    for i, (cam, prior) in enumerate(zip(cameras, priors, strict=True)):
        x, z, source = _prior_anchors(cam, prior, anchors, None if stereo is None else stereo[i], min_anchors)
        if x is None:
            lines.append(None)
            known.append(None)
            fits.append(None)
            continue
        a, b, inliers = _trimmed_fit(x, 1.0 / z if depth_kind == "disparity" else z)
        lines.append((a, b))
        known.append((x, z))
        fits.append({"scale": float(a), "shift": float(b), "anchors": inliers, "from": source})
    stats: dict = {"fits": fits}
    if align in ("views", "smooth", "fused"):
        t0 = time.perf_counter()
        refined = refine_alignment(cameras, priors, depth_kind, lines, known)
        for fit, line in zip(fits, refined, strict=True):
            if fit is not None and line is not None:
                fit.update(anchor_scale=fit["scale"], anchor_shift=fit["shift"], scale=line[0], shift=line[1])
        stats["align_seconds"] = time.perf_counter() - t0
        lines = refined
    depths = []
    for prior, line in zip(priors, lines, strict=True):
        if line is None:
            depths.append(np.full(prior.shape, np.nan))
            continue
        target = line[0] * prior.astype(np.float64) + line[1]
        depth = 1.0 / np.where(target > 1e-12, target, np.nan) if depth_kind == "disparity" else target
        depths.append(np.where(depth > 0, depth, np.nan))
    if align in ("smooth", "fused"):
        depths, stats["correction"] = correct_priors(cameras, images, depths)
    if align == "fused":
        depths, stats["fusion"] = fuse_views(cameras, depths)
    points, colors = [], []
    for cam, image, depth in zip(cameras, images, depths, strict=True):
        valid = np.isfinite(depth) & (depth > 0)
        rows, cols = np.nonzero(valid)
        points.append(backproject(depth, cam, rows, cols))
        colors.append(image[rows, cols])
    if not points:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), stats
    return np.concatenate(points).astype(np.float32), np.concatenate(colors).astype(np.float32), stats


def _prior_anchors(
    cam: Camera, prior: np.ndarray, anchors: np.ndarray, stereo: np.ndarray | None, min_anchors: int
) -> tuple[np.ndarray | None, np.ndarray | None, str]:
    """(prior values, their metric z-depths, "stereo" or "points") for one view's fit; (None, None, "")
    when neither source has ``min_anchors``."""
    if stereo is not None:
        known = np.isfinite(stereo) & (stereo > 0)
        if known.sum() >= min_anchors:
            return prior[known].astype(np.float64), stereo[known].astype(np.float64), "stereo"
    uv, z = project(anchors.astype(np.float64), cam)
    c, r = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    seen = (z > 0) & (c >= 0) & (c < cam.width) & (r >= 0) & (r < cam.height)
    if seen.sum() < min_anchors:
        return None, None, ""
    return prior[r[seen], c[seen]].astype(np.float64), z[seen], "points"


def _trimmed_fit(
    x: np.ndarray, y: np.ndarray, k: float = 2.0, max_passes: int = 10
) -> tuple[float, float, int]:
    """``y ~ a x + b`` by least squares over the inliers: the points whose residual is at most ``k``
    robust standard deviations (1.4826 x the median absolute residual of all points), refitted until
    the inliers stop changing (at most ``max_passes`` fits).

    Three views' stereo has outliers far off (repeated stripes and tiles match at the wrong depth, a
    few at half of it); in disparity they pull hardest, and two passes at 3x the inliers' median left
    the room's start 4-5 % too near (median). The median of all residuals is not pulled by them (it
    breaks down at half the points), so the inliers do not shrink pass after pass either
    (docs/figures.md, "A start from the depth prior").

    Returns:
        ``(a, b, inlier count)``.
    """
    keep = np.ones(len(x), dtype=bool)
    a = b = 0.0
    for _ in range(max_passes):
        a, b = np.polyfit(x[keep], y[keep], 1)
        residual = np.abs(a * x + b - y)
        new = residual <= k * 1.4826 * np.median(residual) + 1e-12
        if new.sum() < 2 or np.array_equal(new, keep):
            break
        keep = new
    return float(a), float(b), int(keep.sum())


def sfm_points(cameras: list[Camera], images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, dict]:
    """Sparse SIFT points triangulated with the known poses (pycolmap); see :mod:`langfield.training.sfm`."""
    from langfield.training.sfm import sfm_points as triangulate

    return triangulate(cameras, images)
