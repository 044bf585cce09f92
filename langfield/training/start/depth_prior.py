"""The depth-prior start (``--init depth``): each training view's monocular prior made metric and
back-projected, every pixel a point.

The stages, in order: the plane-sweep stereo (:mod:`~langfield.training.start.stereo`) gives known
depths; each view's prior is fitted to them by a scale and shift (:func:`_trimmed_fit`, the "anchors"
alignment); the views' fits are refined until the views agree with one another
(:mod:`~langfield.training.start.alignment`, "views"); each view's prior is corrected by a smooth field
from photo-consistency and the other views (:mod:`~langfield.training.start.correction`, "smooth");
each pixel is moved to the mean of the views that agree on it (:func:`~langfield.training.start.
correction.fuse_views`, "fused", the default); then every pixel is back-projected.
"""

from __future__ import annotations

import time

import numpy as np

from langfield.camera import Camera
from langfield.training.start.alignment import refine_alignment
from langfield.training.start.correction import correct_priors, fuse_views

__all__ = ["INIT_ALIGNS", "depth_prior_points"]

# How the depth start aligns each view's prior, from the least to the most agreement between views:
# "anchors" keeps each view's own fit, "views" refines the fits so that the views agree, "smooth" then
# corrects each view's prior by a smooth field, "fused" then moves each pixel to the mean of the views
# that agree on it (one layer per surface).
INIT_ALIGNS: tuple[str, ...] = ("fused", "smooth", "views", "anchors")


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
    (:func:`langfield.training.start.alignment.refine_alignment`); ``"smooth"`` also corrects each
    view's aligned prior by a smooth field, from photo-consistency and the other views
    (:func:`langfield.training.start.correction.correct_priors`); ``"fused"`` then moves each pixel's
    depth to the mean of the views that agree on it (:func:`~langfield.training.start.correction.fuse_views`);
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
        points.append(cam.unproject(depth, rows, cols))
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
    uv, z = cam.project(anchors.astype(np.float64))
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
    (docs/history/figures.md, "A start from the depth prior").

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
