"""Plane-sweep stereo on the training views: the start's surface points and the stereo depth maps that
the depth-prior start is fitted to (``--init dense`` and ``--init depth``).

For each depth hypothesis the other views are warped onto the reference view by the plane's homography
(Collins 1996; the fronto-parallel sweep with a ZNCC cost that COLMAP's and MVSNet's pipelines start
from), the best-scoring depth is kept per pixel, refined to sub-plane precision, and kept only where it
is distinct, textured, and agrees with another view's depth map (geometric consistency, as in COLMAP's
fusion). Besides the fronto-parallel planes the sweep also runs two families of planes tilted 30 and 60
degrees about the reference camera's x axis, their lower rows nearer (Gallup et al., "Real-time
plane-sweeping stereo with multiple sweeping directions", CVPR 2007): with baselines of 35-70 degrees
(DTU) a surface that recedes toward the top of the image (a table, the top of an object seen from
above) looks different enough in each view that a fronto-parallel window does not match it, or matches
it at the wrong depth; warped by a plane of its own slant, it does. Each pixel keeps the best-scoring
plane of the three families. Planes tilted the other way (a ceiling, an underside) are seldom what
cameras that look down see, and each family gives a weakly textured pixel another chance match: with
them too, Blender's lego lost 0.5-0.8 dB.
CoR-GS starts from COLMAP's dense MVS of the training views for the same reason; this is its classical
core, with OpenCV warps and box filters on the CPU.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from langfield.camera import Camera, box_corners
from langfield.training.start.matching import box_mean, gray, window_stats, zncc

__all__ = [
    "SWEEP_PLANES",
    "SWEEP_VIEWS",
    "PlaneSweepConfig",
    "dense_points",
    "depth_range",
    "plane_sweep",
    "stereo_depths",
]


SWEEP_VIEWS = ("best", "mean")
# The tilts of the planes swept besides the fronto-parallel ones (degrees about the camera's x axis;
# positive: lower rows nearer, a table seen from above). DTU scan37, seeds 0-2: 20.67 -> 20.85 dB masked.
SWEEP_PLANES = {"tilted": (30.0, 60.0), "fronto": ()}
MIN_FACING = 0.2  # n . r (r: the ray at unit z) under which a family's planes graze the ray: not swept


@dataclass(frozen=True)
class PlaneSweepConfig:
    """Settings of :func:`plane_sweep` and :func:`dense_points`.

    Attributes:
        planes: depth hypotheses, uniform in inverse depth between near and far.
        window: sets the ZNCC window's side, 2 round(window / 2 x width / 400) + 1 pixels and at least
            5: 9 at 400 pixels of width (3.5 rounds to the even 4), 9 at fern's 504, 5 at the room's 160.
        min_score: lowest ZNCC (of the best source view, or the mean over them) to keep a pixel.
        views: how a depth's score combines the source views: "best", the best one's ZNCC (a surface
            that one source sees occluded or foreshortened is judged by the other; Kang, Szeliski and
            Chai, CVPR 2001, keep the best of the views for the same reason), or "mean" over the
            sources that see the pixel.
        min_texture: lowest standard deviation of the reference's grey values in the window (0-1 scale):
            flat patches match every depth.
        consistency: largest relative depth difference to another view's depth map.
        reprojection: largest reprojection error (pixels) of that round trip.
        max_points: cap on the fused points (a voxel grid thins them evenly to it).
        tilts: the plane families swept besides the fronto-parallel one, each turned by this many degrees
            about the reference camera's x axis (positive: the image's lower rows nearer); each family
            sweeps ``planes`` offsets, and a pixel keeps the best-scoring plane of all of them.
    """

    planes: int = 384
    window: int = 7
    min_score: float = 0.7
    min_texture: float = 0.01
    consistency: float = 0.03
    reprojection: float = 1.0
    max_points: int = 60000
    views: str = "best"
    tilts: tuple[float, ...] = SWEEP_PLANES["tilted"]

    def __post_init__(self) -> None:
        if self.views not in SWEEP_VIEWS:
            raise ValueError(f"views must be one of {', '.join(SWEEP_VIEWS)}, got {self.views!r}")
        if not all(math.isfinite(t) and abs(t) < 90 for t in self.tilts):
            raise ValueError(f"tilts must be angles between -90 and 90 degrees, got {self.tilts!r}")


def depth_range(cam: Camera, bounds: np.ndarray) -> tuple[float, float]:
    """(near, far) z-depths of the box ``bounds`` [2, 3] seen from ``cam`` (near kept positive)."""
    _, z = cam.project(box_corners(bounds))
    far = float(z.max())
    if far <= 0:
        raise ValueError(f"camera {cam.name!r}: the scene bounds lie behind it")
    near = max(float(z.min()), far * 0.02)
    return near, far


def _intrinsics(cam: Camera) -> np.ndarray:
    return cam.intrinsics(torch.float64).numpy()


# ---------------------------------------------------------------- plane sweep


def plane_sweep(
    ref: Camera,
    ref_image: np.ndarray,
    sources: list[tuple[Camera, np.ndarray]],
    near: float,
    far: float,
    cfg: PlaneSweepConfig = PlaneSweepConfig(),
) -> tuple[np.ndarray, np.ndarray]:
    """Depth map of ``ref`` by a plane sweep against ``sources``: fronto-parallel planes, and the tilted
    families of ``cfg.tilts``.

    A family of planes n . X = c (X in the reference camera's frame, n its unit normal) is swept over
    ``cfg.planes`` offsets c, uniform in 1/c over the offsets that put some pixel between near and far.
    For each plane, each source image is warped onto the reference by the plane's homography
    H = K_s (R + t n^T / c) K_r^-1 ([R | t] the reference-to-source pose) and scored by zero-normalised
    cross-correlation over a window; the score of a plane is the best source's (``cfg.views`` "best")
    or the mean over the sources that see the pixel ("mean"). Per family the best plane is refined by a
    parabola through its neighbours' scores (in 1/c); a pixel's depth is then c / (n . r) for the best
    family's plane, r its ray at unit z. A family is not swept where its planes meet a pixel's ray at a
    grazing angle (n . r < ``MIN_FACING``) or outside [near, far].

    Args:
        ref: the reference camera; ``ref_image`` its [H, W, 3] image in [0, 1].
        sources: (camera, image) of the other views.
        near, far: z-depth range to sweep, 0 < near < far.
        cfg: settings.

    Returns:
        ``(depth [H, W], score [H, W])``: z-depth (OpenCV: along the viewing axis) and the best score
        in [-1, 1]; score -1 where no source sees the pixel at any depth or the patch is flat.
    """
    if not 0 < near < far or not sources:
        raise ValueError(f"plane_sweep: need 0 < near < far and a source view, got {near}, {far}")
    h, w = ref.height, ref.width
    size = max(5, 2 * round(cfg.window * w / 400 / 2) + 1)  # 3x3 windows match too much noise
    g_ref = gray(ref_image)
    mu_r, var_r = window_stats(g_ref, size)
    flat = np.sqrt(var_r) < cfg.min_texture
    k_ref_inv = np.linalg.inv(_intrinsics(ref))
    r_ref, t_ref = ref.pose_cv()
    sources_ = []
    for cam, image in sources:
        r_src, t_src = cam.pose_cv()
        rel_r = r_src @ r_ref.T
        frame = np.ones((cam.height, cam.width), np.float32)  # warped with the image: where the source sees
        sources_.append((_intrinsics(cam), rel_r, t_src - rel_r @ t_ref, gray(image), frame))
    rows, cols = np.mgrid[0:h, 0:w]
    rays = np.stack([cols + 0.5, rows + 0.5, np.ones((h, w))], axis=-1) @ k_ref_inv.T  # at unit z
    depth = np.full((h, w), np.nan, np.float32)
    best_score = np.full((h, w), -1.0, np.float32)
    for tilt in (0.0, *cfg.tilts):
        angle = math.radians(tilt)
        normal = np.array([0.0, math.sin(angle), math.cos(angle)])
        facing = rays @ normal  # c / facing is the z-depth of plane c on each pixel's ray
        swept = facing >= MIN_FACING
        if not swept.any():
            continue
        inv_offsets = np.linspace(
            1.0 / (near * facing[swept].min()), 1.0 / (far * facing[swept].max()), cfg.planes
        )
        scores = _sweep_scores(cfg, size, g_ref, mu_r, var_r, sources_, k_ref_inv, normal, inv_offsets)
        facing = np.maximum(facing, MIN_FACING)
        if tilt != 0.0:  # the fronto-parallel family meets every pixel within the range
            for i, inv in enumerate(inv_offsets):
                z = 1.0 / (inv * facing)
                scores[i][~swept | (z < near) | (z > far)] = -1.0
        offset, score, interior = _best_depth(scores, inv_offsets)
        score = np.where(interior, score, -1.0)  # the end planes are the range's edges
        better = score > best_score
        depth = np.where(better, offset / facing, depth).astype(np.float32)
        best_score = np.where(better, score, best_score).astype(np.float32)
    best_score = np.where(flat | ~np.isfinite(depth), -1.0, best_score).astype(np.float32)
    return np.where(np.isfinite(depth), depth, far).astype(np.float32), best_score


def _sweep_scores(
    cfg: PlaneSweepConfig,
    size: int,
    g_ref: np.ndarray,
    mu_r: np.ndarray,
    var_r: np.ndarray,
    sources: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
    k_ref_inv: np.ndarray,
    normal: np.ndarray,
    inv_offsets: np.ndarray,
) -> np.ndarray:
    """[P, H, W] each plane n . X = c's score per reference pixel (``plane_sweep``): the best source's
    ZNCC over ``size`` windows, or the mean over the sources that see the pixel; -1 where none does."""
    h, w = g_ref.shape
    # Pixel centres: OpenCV's warp maps integer pixel coordinates, so shift by the half pixel.
    shift = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    unshift = np.linalg.inv(shift)
    parts = [
        (k @ rel_r @ k_ref_inv, k @ np.outer(rel_t, normal) @ k_ref_inv, g, f)
        for k, rel_r, rel_t, g, f in sources
    ]
    best = cfg.views == "best"
    scores = np.full((len(inv_offsets), h, w), -1.0, dtype=np.float32)
    for i, inv_c in enumerate(inv_offsets):
        total = np.full((h, w), -1.0 if best else 0.0, np.float32)  # the best score, or the sum
        count = None if best else np.zeros((h, w), np.float32)  # sources that see the pixel
        for rot_part, trans_part, g_src, frame in parts:
            homography = unshift @ (rot_part + trans_part * inv_c) @ shift
            flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
            warped = cv2.warpPerspective(g_src, homography, (w, h), flags=flags, borderValue=0.0)
            seen = cv2.warpPerspective(frame, homography, (w, h), flags=flags, borderValue=0.0)
            score, var_s = zncc(g_ref, mu_r, var_r, warped, size)
            valid = (box_mean(seen, size) > 0.999) & (var_s > cfg.min_texture**2)
            if best:
                total = np.maximum(total, np.where(valid, score, -1.0))
            else:
                total += np.where(valid, score, 0.0)
                count += valid
        scores[i] = total if best else np.where(count > 0, total / np.maximum(count, 1.0), -1.0)
    return scores


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
    pts = cam.unproject(depth, rows, cols)
    uv, z = other.project(pts)
    c, r = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    inside = (z > 0) & (c >= 0) & (c < other.width) & (r >= 0) & (r < other.height)
    ok = np.zeros(h * w, dtype=bool)
    idx = np.nonzero(inside)[0]
    ci, ri = c[idx], r[idx]
    d_other = other_depth[ri, ci]
    good = other_valid[ri, ci] & (np.abs(d_other - z[idx]) <= cfg.consistency * z[idx])
    idx, ci, ri = idx[good], ci[good], ri[good]
    back = other.unproject(other_depth, ri, ci)
    uv_back, _ = cam.project(back)
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
        points.append(cam.unproject(depths[i], rows, cols))
        colors.append(images[i][rows, cols])
    pts = np.concatenate(points).astype(np.float32)
    cols_ = np.concatenate(colors).astype(np.float32)
    pts, cols_ = thin_evenly(*inside_bounds(pts, cols_, bounds), cfg.max_points)
    stats = {"matched_per_view": matched, "consistent_per_view": kept, "points": len(pts), "depths": depths}
    return pts, cols_, stats


def thin_evenly(points: np.ndarray, colors: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
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


def inside_bounds(
    points: np.ndarray, colors: np.ndarray, bounds: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    keep = np.all((points >= bounds[0]) & (points <= bounds[1]), axis=1)
    return points[keep], colors[keep]
