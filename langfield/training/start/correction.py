"""Each view's aligned depth prior corrected by a smooth field, then the views fused, for the ``depth`` start.

A monocular prior's error is not one scale and shift per view: it also bends smoothly across the image
(the built-in rooms' priors carry about 3 % of smooth multiplicative noise, a power of 1/z and a blur;
:func:`langfield.synthetic.render.depth_prior`). After the per-view lines
(:mod:`langfield.training.start.alignment`) that bend is most of what is left: on a room of layout 7,
with the lines the views agreed on, 73 % of the pixels' points lie within 6.4 cm of a surface; a
field of this module's kind fitted to the true depths would put 96 % there. This module estimates the
field from the photos and the other views:

- **Photometric offsets in a narrow band.** Per pixel, each log-depth offset in ``[-BAND, BAND]``
  around the aligned prior warps the other views onto this one; the offset whose warp matches best
  (zero-normalised cross-correlation over a window, the mean over the views that see the window) is
  kept where the match is strong (ZNCC > MIN_ZNCC) and distinct (above every offset more than three
  steps away by MIN_MARGIN), the patch textured and the best offset not at the band's ends; a parabola
  refines it below a step. The full plane sweep of the stereo start matches repeated tiles at the wrong
  depth; a band of +-12 % around a prior that is already about right leaves them no room. On 160x120
  rooms 6-10 % of the pixels are kept, with a median error of 0.4-0.6 % of the depth.
- **A smooth field per view,** the log-depth correction ``c(x) = sum_k B_k(x) w_k``, ``B_k`` the
  bicubic interpolation of a GRID coarse grid, fitted to those offsets by ridge least squares and
  refitted on the inliers (residual within 2.5 robust standard deviations). Offsets more than 3 % from
  the field are dropped from the next step.
- **One round of agreement.** Each view's field is refitted to its kept offsets (weight
  OFFSET_WEIGHT) and, elsewhere, to half its log-depth gap to the other views' corrected priors where
  they see the pixel within 6 % (each side of a gap moves half of it, so two views meet).

Then, in the default start, :func:`fuse_views` moves each pixel's depth to the mean log-depth of its
view and the other views that agree within AGREE, where both maps are smooth, so that a surface starts
as one layer rather than one per view.

Where a surface has no texture (a room's plain walls) no offset is kept, and the field there is what
the textured pixels around it and the other views make of it. The GRID is the built-in prior's own
noise grid, so on the rooms the field can follow that noise exactly; a network's bend has no grid, and
the choice is not checked on one. Start points within 6.4 cm of a surface, lines -> corrected: layout 0
0.672 -> 0.747, layout 4 0.726 -> 0.820, layout 7 0.663 -> 0.675, 0.3 s per room; docs/history/figures.md,
"Correcting the priors".
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import cv2
import numpy as np

from langfield.camera import Camera
from langfield.training.start.matching import box_mean, gray, window_stats, zncc

__all__ = ["BAND", "GRID", "band_offsets", "correct_priors", "fuse_views", "smooth_field"]

BAND, STEPS = 0.12, 49  # log-depth offsets searched around the aligned prior, and how many
MIN_ZNCC, MIN_MARGIN, MIN_TEXTURE = 0.8, 0.1, 0.02  # a kept match; texture: std of the grey patch
WINDOW = 7  # ZNCC window at 160 pixels of width, scaled with the image
GRID = (4, 5)  # the field's control points (rows, columns)
RIDGE = 0.01  # on the field's weights, times the summed data weight
INLIER_SIGMAS, KEEP = 2.5, 0.03  # inliers of the field's fit; offsets kept for the agreement round
AGREE, OFFSET_WEIGHT = 0.06, 5.0  # the agreement round: largest gap counted; weight of an offset
MAX_FIT_PIXELS = 40_000  # the agreement term is fitted on a regular grid of at most this many pixels


def _into(cam: Camera, world: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(z, map_x, map_y, inside) of world points [H, W, 3] in ``cam``: cv2.remap coordinates."""
    uv, z = cam.project(world)
    u, v = uv[..., 0] - 0.5, uv[..., 1] - 0.5
    inside = (z > 0) & (u >= 0) & (u <= cam.width - 1) & (v >= 0) & (v <= cam.height - 1)
    return (
        z,
        np.nan_to_num(u, nan=-1.0).astype(np.float32),
        np.nan_to_num(v, nan=-1.0).astype(np.float32),
        inside,
    )


def band_offsets(
    cameras: Sequence[Camera], images: Sequence[np.ndarray], depths: Sequence[np.ndarray]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per view the best photometric log-depth offset around ``depths`` and where it is kept.

    Args:
        cameras, images: the training views, ``[H, W, 3]`` images in [0, 1]; at least two.
        depths: their aligned z-depth priors ``[H, W]`` (NaN where unknown).

    Returns:
        Per view ``(offset [H, W], kept [H, W] bool)``: ``depth * exp(offset)`` is the best match.
    """
    grays = [gray(im) for im in images]
    steps = np.linspace(-BAND, BAND, STEPS)
    out = []
    for i, cam in enumerate(cameras):
        size = max(5, 2 * round((WINDOW * cam.width / 160 - 1) / 2) + 1)
        ref = grays[i]
        mu_r, var_r = window_stats(ref, size)
        known = np.isfinite(depths[i]) & (depths[i] > 0)
        base = np.where(known, depths[i], 1.0)
        scores = np.full((STEPS, cam.height, cam.width), -1.0, np.float32)
        for k, step in enumerate(steps):
            world = cam.unproject(base * math.exp(step))
            total = np.zeros((cam.height, cam.width), np.float32)
            count = np.zeros_like(total)
            for j, other in enumerate(cameras):
                if j == i:
                    continue
                _, mx, my, inside = _into(other, world)
                warped = cv2.remap(grays[j], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
                score, _ = zncc(ref, mu_r, var_r, warped, size)
                seen = box_mean(inside.astype(np.float32), size) > 0.999
                total += np.where(seen, score, 0.0)
                count += seen
            scores[k] = np.where(count > 0, total / np.maximum(count, 1.0), -1.0)
        best = scores.argmax(axis=0)
        top = np.take_along_axis(scores, best[None], axis=0)[0]
        index = np.arange(STEPS)[:, None, None]
        rival = np.where(np.abs(index - best[None]) > 3, scores, -2.0).max(axis=0)
        inner = np.clip(best, 1, STEPS - 2)
        s0, s1, s2 = (np.take_along_axis(scores, (inner + d)[None], axis=0)[0] for d in (-1, 0, 1))
        vertex = np.clip(0.5 * (s0 - s2) / np.minimum(s0 - 2.0 * s1 + s2, -1e-6), -0.5, 0.5)
        offset = steps[inner] + vertex * (steps[1] - steps[0])
        kept = (
            known
            & (top > MIN_ZNCC)
            & (top - rival > MIN_MARGIN)
            & (best > 1)
            & (best < STEPS - 2)
            & (np.sqrt(var_r) > MIN_TEXTURE)
        )
        out.append((offset, kept))
    return out


def _basis(height: int, width: int) -> np.ndarray:
    """[H, W, K] the bicubic interpolation of each of the GRID's control points."""
    planes = []
    for k in range(GRID[0] * GRID[1]):
        unit = np.zeros(GRID)
        unit.flat[k] = 1.0
        planes.append(cv2.resize(unit, (width, height), interpolation=cv2.INTER_CUBIC))
    return np.stack(planes, axis=-1)


def smooth_field(
    basis: np.ndarray, values: np.ndarray, weights: np.ndarray, robust: bool = False
) -> np.ndarray:
    """The field ``basis @ w`` [H, W] fitted to ``values`` where ``weights`` > 0, by ridge least squares
    (RIDGE times the summed weight); ``robust``: refitted on the inliers, the values within
    INLIER_SIGMAS robust standard deviations of the fit, until they stop changing. Zero without data."""
    use = (weights > 0) & np.isfinite(values)
    for _ in range(8):
        if use.sum() < basis.shape[-1]:
            return np.zeros(basis.shape[:2])
        a = basis[use] * np.sqrt(weights[use])[:, None]
        y = values[use] * np.sqrt(weights[use])
        coef = np.linalg.solve(a.T @ a + RIDGE * weights[use].sum() * np.eye(a.shape[1]), a.T @ y)
        field = basis @ coef
        if not robust:
            return field
        data = (weights > 0) & np.isfinite(values)
        residual = np.abs(field - values)
        new = data & (residual <= INLIER_SIGMAS * 1.4826 * np.median(residual[data]) + 1e-12)
        if np.array_equal(new, use):
            break
        use = new
    return field


def _smooth(depth: np.ndarray) -> np.ndarray:
    """[H, W] bool: the map's log-depth spans less than AGREE over the pixel's 3 x 3 neighbourhood (no
    depth edge there, and every neighbour known)."""
    known = np.isfinite(depth) & (depth > 0)
    log = np.log(np.where(known, depth, 1.0)).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    span = cv2.dilate(log, kernel) - cv2.erode(log, kernel)
    whole = cv2.erode(known.astype(np.uint8), kernel, borderType=cv2.BORDER_REPLICATE) > 0
    return whole & (span < AGREE)


def _gaps(cameras, depths, i: int, smooth=None) -> tuple[np.ndarray, np.ndarray]:
    """Mean log-depth gap of view i's pixels to the other views' depths along i's rays, and the count
    of views that see the pixel within AGREE: the depth along the ray at which j's depth map agrees,
    by three fixed-point steps (exact for a view behind this one on the same axis). With ``smooth``
    (per view [H, W] uint8, :func:`_smooth`) a view counts only where its map is smooth at the sample."""
    own = depths[i]
    total = np.zeros(own.shape)
    count = np.zeros(own.shape)
    for j, other in enumerate(cameras):
        if j == i:
            continue
        z = own.copy()
        good = np.zeros(own.shape, dtype=bool)
        for _ in range(3):
            zj, mx, my, inside = _into(other, cameras[i].unproject(np.nan_to_num(z, nan=1.0)))
            seen = cv2.remap(
                depths[j].astype(np.float32), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )
            with np.errstate(divide="ignore", invalid="ignore"):
                moved = z * seen / zj
                good = inside & np.isfinite(moved) & (moved > 0) & (np.abs(np.log(moved / own)) < AGREE)
            if smooth is not None:
                good &= cv2.remap(smooth[j], mx, my, cv2.INTER_NEAREST) > 0
            z = np.where(good, moved, own)
        with np.errstate(divide="ignore", invalid="ignore"):
            total += np.where(good, np.log(z / own), 0.0)
        count += good
    return np.where(count > 0, total / np.maximum(count, 1.0), 0.0), count


def correct_priors(
    cameras: Sequence[Camera], images: Sequence[np.ndarray], depths: Sequence[np.ndarray]
) -> tuple[list[np.ndarray], dict]:
    """The training views' aligned z-depth priors corrected by a smooth field each (module docstring).

    Args:
        cameras, images: the training views (``[H, W, 3]`` images in [0, 1]).
        depths: per view the aligned prior's z-depth ``[H, W]``, NaN where unknown; a view whose map has
            no finite depth is passed through.

    Returns:
        ``(corrected depths, stats)``; stats: per view the kept fraction of pixels (``matched``) and the
        field's range of log-depth (``correction``: its 5th and 95th percentiles), and ``seconds``.
        Fewer than two views with depths return them unchanged.
    """
    if not len(cameras) == len(images) == len(depths):
        raise ValueError("correct_priors: one image and one depth map per camera")
    t0 = time.perf_counter()
    used = [k for k, d in enumerate(depths) if np.isfinite(d).any()]
    result = [np.asarray(d, np.float64) for d in depths]
    stats: dict = {"views": [None] * len(cameras)}
    if len(used) < 2:
        stats["seconds"] = time.perf_counter() - t0
        return result, stats
    cams = [cameras[k] for k in used]
    base = [result[k] for k in used]
    offsets = band_offsets(cams, [images[k] for k in used], base)
    bases = [_basis(c.height, c.width) for c in cams]
    fields = []
    for k, (offset, kept) in enumerate(offsets):
        field = smooth_field(bases[k], offset, kept.astype(np.float64), robust=True)
        fields.append(field)
        offsets[k] = (offset, kept & (np.abs(offset - field) < KEEP))
    current = [d * np.exp(f) for d, f in zip(base, fields, strict=True)]
    refitted = []
    for k, cam in enumerate(cams):
        gap, count = _gaps(cams, current, k)
        offset, kept = offsets[k]
        stride = max(1, math.ceil(math.sqrt(cam.height * cam.width / MAX_FIT_PIXELS)))
        sampled = np.zeros(count.shape, dtype=bool)
        sampled[::stride, ::stride] = True
        values = np.where(kept, offset - fields[k], 0.5 * gap)
        weights = np.where(kept, OFFSET_WEIGHT, (sampled & (count > 0)).astype(np.float64))
        refitted.append(fields[k] + smooth_field(bases[k], values, weights))
    for k, field, (_, kept) in zip(used, refitted, offsets, strict=True):
        result[k] = result[k] * np.exp(field)
        finite = field[np.isfinite(result[k])]
        q = np.quantile(finite, [0.05, 0.95]) if finite.size else (0.0, 0.0)
        stats["views"][k] = {
            "matched": float(kept.mean()),
            "correction": [float(q[0]), float(q[1])],
        }
    stats["seconds"] = time.perf_counter() - t0
    return result, stats


def fuse_views(cameras: Sequence[Camera], depths: Sequence[np.ndarray]) -> tuple[list[np.ndarray], dict]:
    """Each view's z-depth moved to the mean log-depth of itself and the other views that see the pixel
    within AGREE (where along the pixel's ray their depth maps meet it, as in the agreement round).

    Each view's start points come from its own map, so views that disagree by a few percent put one
    layer per view on a surface; fused, the surface starts as one layer at the views' mean. Only where
    the maps are smooth (:func:`_smooth`, this view's at the pixel and the other's at the sample):
    across a depth edge the interpolated depth is neither side's, and averaging it blurs the outline.
    Rooms of 3 layouts x 3 seeds: docs/history/figures.md, "One layer per surface".

    Args:
        cameras: the views.
        depths: per view ``[H, W]`` z-depth, NaN where unknown (such pixels stay NaN; a view with no
            finite depth is passed through and lends nothing).

    Returns:
        ``(fused depths, stats)``; stats: per view the share of its pixels another view agreed with
        (``fused``, None for a view passed through) and ``seconds``.
    """
    if len(cameras) != len(depths):
        raise ValueError("fuse_views: one depth map per camera")
    t0 = time.perf_counter()
    result = [np.asarray(d, np.float64) for d in depths]
    used = [k for k, d in enumerate(result) if np.isfinite(d).any()]
    stats: dict = {"views": [None] * len(cameras)}
    if len(used) >= 2:
        cams = [cameras[k] for k in used]
        current = [result[k] for k in used]
        smooth = [_smooth(d).astype(np.uint8) for d in current]  # cv2.remap samples uint8, not bool
        for k, index in enumerate(used):
            gap, count = _gaps(cams, current, k, smooth)
            count = np.where(smooth[k] > 0, count, 0.0)
            # the mean of 1 + count log-depths: this view's and the agreeing views'
            result[index] = current[k] * np.exp(gap * count / (count + 1.0))
            stats["views"][index] = {"fused": float((count > 0).mean())}
    stats["seconds"] = time.perf_counter() - t0
    return result, stats
