"""The training views' depth priors aligned to one another, for the ``depth`` start.

A monocular prior is relative: each view needs its own scale and shift (of the depth, or of 1/z for a
disparity) before it gives points. :func:`~langfield.training.start.depth_prior_points` fits
them to depths the view already knows (its plane-sweep stereo), one view at a time; three views' stereo
resolves 5-7 % of a room's pixels, often wrong matches of repeated tiles, and one bad view ruins a third
of the start (a room of layout 7: the middle view's points 17 % within 6.4 cm of a surface, against 70 %
for the line fitted to the true depths; docs/history/figures.md, "Aligning the priors to one another").

With the poses known the aligned priors must also agree with each other, wherever they are textured or
not: a pixel of view i at its aligned depth, projected into view j, should land at j's aligned depth
there (the geometric consistency that COLMAP's fusion and
:func:`~langfield.training.start.stereo_depths` test point by point; here it is the cost of the
alignment). The baseline between the
views fixes the scale that one view alone cannot.

- The cost, per ordered pair of views (i, j), is the mean of ``min(|log z_j - log D_j|, CAP)`` over a
  grid of pixels of i: z_j the depth in j of the pixel's point, D_j j's aligned prior where it lands.
- The pixels counted for a pair are those that land in j's image at the start of each round; one that
  leaves it later counts CAP. Counting every pixel would favour nearer depths (more of them come into
  view); counting those in view at each trial would favour pushing the hard ones out of sight.
- Per view, the same truncated error at its anchors (the known depths it was fitted to) is added.
- Each view's line is parametrised by its depths at the prior's 10th and 90th percentiles. Each round
  first tries one common factor on every view's depths (the move that one view at a time cannot make
  when all are off together), then searches view by view on a grid of its two log-depths around the
  current line; the grid narrows each round. A search, not a gradient: the truncated cost has none far
  from the answer, and each view has only two numbers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from langfield.camera import Camera

__all__ = ["CAP", "alignment_cost", "refine_alignment"]

CAP = 0.1  # truncation of the log-depth error: 10 %, beyond which a pixel is simply inconsistent
SAMPLES = 1200  # pixels per view in the cross-view cost (a regular grid)
MAX_ANCHORS = 2000
ROUNDS, STEPS, SPAN, SHRINK = 4, 15, math.log(1.5), 0.4

Line = tuple[float, float]


def _line_depth(prior: np.ndarray, line: Line, depth_kind: str) -> np.ndarray:
    """z-depth of prior values under ``z = a p + b`` (depth) or ``1/z = a p + b`` (disparity); NaN where
    that is not a positive finite depth."""
    t = line[0] * prior.astype(np.float64) + line[1]
    if depth_kind == "disparity":
        with np.errstate(divide="ignore", invalid="ignore"):
            z = 1.0 / t
    else:
        z = t
    return np.where(np.isfinite(z) & (z > 0), z, np.nan)


def _line_through(depth_kind: str, p: tuple[float, float], z: tuple[float, float]) -> Line:
    """The line of ``depth_kind`` through (p[0], z[0]) and (p[1], z[1])."""
    y = (1.0 / z[0], 1.0 / z[1]) if depth_kind == "disparity" else z
    a = (y[1] - y[0]) / (p[1] - p[0])
    return float(a), float(y[0] - a * p[0])


def _truncated(err: np.ndarray) -> np.ndarray:
    return np.where(np.isfinite(err), np.minimum(np.abs(err), CAP), CAP)


class _Views:
    """The cost of a set of lines (one per view): the views' pixel grids, poses and anchors, fixed."""

    def __init__(self, cameras, priors, depth_kind, anchors) -> None:
        self.cameras, self.depth_kind = cameras, depth_kind
        self.priors = [p.astype(np.float32) for p in priors]
        self.grids, self.poses, self.anchors = [], [], []
        for cam, prior, anchor in zip(cameras, self.priors, anchors, strict=True):
            step = max(1, round(math.sqrt(cam.width * cam.height / SAMPLES)))
            rows, cols = np.mgrid[step // 2 : cam.height : step, step // 2 : cam.width : step]
            rows, cols = rows.ravel(), cols.ravel()
            keep = np.isfinite(prior[rows, cols])
            rows, cols = rows[keep], cols[keep]
            rays = cam.pixel_rays(rows, cols)[:, :2]
            self.grids.append((rays, prior[rows, cols].astype(np.float64)))
            self.poses.append(cam.pose_cv())
            if anchor is not None:
                x, z = anchor
                stride = max(1, len(x) // MAX_ANCHORS)
                anchor = (np.asarray(x, np.float64)[::stride], np.asarray(z, np.float64)[::stride])
            self.anchors.append(anchor)

    def freeze(self, lines: Sequence[Line]) -> None:
        """Fixes, per ordered pair (i, j), the pixels of i's grid that the cost counts: those that land
        in j's image under ``lines``. Counting every pixel would favour lines that bring more of them
        into view (nearer depths); counting only those in view, lines that push the hard ones out."""
        self.counted, self.landed = {}, {}
        n = len(lines)
        for i in range(n):
            for j in range(n):
                if i != j:
                    self.counted[i, j] = np.ones(len(self.grids[i][1]), dtype=bool)
                    self.counted[i, j] = np.isfinite(self._errors(i, j, lines[i], lines[j]))
        self.landed = {}  # made while every pixel counted

    def _errors(self, i: int, j: int, line_i: Line, line_j: Line) -> np.ndarray:
        """Log-depth disagreement of the counted pixels of i's grid with view j (inf where a pixel leaves
        j's image or has no depth)."""
        log_depth, sampled, inside = self._landing(i, j, line_i)
        err = np.full(len(log_depth), np.inf)
        if inside.any():
            with np.errstate(divide="ignore", invalid="ignore"):
                err[inside] = log_depth[inside] - np.log(_line_depth(sampled, line_j, self.depth_kind))
        return np.where(np.isfinite(err), err, np.inf)

    def _landing(self, i: int, j: int, line_i: Line) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where the counted pixels of i's grid land in view j under ``line_i``: their log-depths in j,
        j's prior there (at the pixels inside j's image) and which are inside. A view's search holds the
        other views' lines, so their pixels land where they did: kept until the next :meth:`freeze`."""
        key = (i, j, line_i)
        if key not in self.landed:
            self.landed[key] = self._land(i, j, line_i)
        return self.landed[key]

    def _land(self, i: int, j: int, line_i: Line) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rays, values = self.grids[i]
        rays, values = rays[self.counted[i, j]], values[self.counted[i, j]]
        z = _line_depth(values, line_i, self.depth_kind)
        r_i, t_i = self.poses[i]
        world = (np.concatenate([rays * z[:, None], z[:, None]], axis=-1) - t_i) @ r_i
        cam = self.cameras[j]
        uv, depth = cam.project(world)
        u, v = uv[:, 0], uv[:, 1]
        inside = (depth > 0) & (u >= 0) & (u <= cam.width) & (v >= 0) & (v <= cam.height)
        inside &= np.isfinite(z)
        sampled = np.zeros(0, np.float32)
        if inside.any():
            sampled = cv2.remap(
                self.priors[j],
                (u[inside] - 0.5).astype(np.float32)[None],
                (v[inside] - 0.5).astype(np.float32)[None],
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_REPLICATE,
            )[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.log(np.where(inside, depth, 1.0)), sampled, inside

    def cross(self, i: int, j: int, line_i: Line, line_j: Line) -> float:
        """Mean truncated log-depth disagreement of the counted pixels of i's grid with view j."""
        err = self._errors(i, j, line_i, line_j)
        return float(_truncated(err).mean()) if len(err) else 0.0

    def anchored(self, j: int, line: Line) -> float:
        """Mean truncated log-depth error of view j's line at its anchors (0 without anchors)."""
        if self.anchors[j] is None or len(self.anchors[j][0]) == 0:
            return 0.0
        x, z = self.anchors[j]
        with np.errstate(divide="ignore", invalid="ignore"):
            return float(_truncated(np.log(_line_depth(x, line, self.depth_kind)) - np.log(z)).mean())

    def cost(self, lines: Sequence[Line], only: int | None = None) -> float:
        """The total cost, or the part of it that depends on view ``only``'s line."""
        n = len(lines)
        pairs = sum(
            self.cross(i, j, lines[i], lines[j])
            for i in range(n)
            for j in range(n)
            if i != j and only in (None, i, j)
        )
        return pairs + sum(self.anchored(j, lines[j]) for j in range(n) if only in (None, j))


Handle = tuple[tuple[float, float], np.ndarray] | None


def _lines(depth_kind: str, current: list[Line], handles: list[Handle]) -> list[Line]:
    return [
        line if h is None else _line_through(depth_kind, h[0], tuple(np.exp(h[1])))
        for line, h in zip(current, handles, strict=True)
    ]


def _search_common(views: _Views, current: list[Line], handles: list[Handle], steps: np.ndarray):
    """Every searchable view's depths times one common factor: the move that one view at a time cannot
    make when all the views are off together (their anchors then all disagree)."""
    best = (views.cost(current), current, handles)
    for step in steps:
        moved = [None if h is None else (h[0], h[1] + step) for h in handles]
        lines = _lines(views.depth_kind, current, moved)
        cost = views.cost(lines)
        if cost < best[0]:
            best = (cost, lines, moved)
    return best[1], best[2]


def _search_view(views: _Views, current: list[Line], handles: list[Handle], k: int, steps: np.ndarray):
    """View k's two log-depths on a grid around their current values, the other views fixed."""
    if handles[k] is None:
        return current, handles
    ends, best_log = handles[k]
    best = views.cost(current, only=k)
    for d0 in steps:
        for d1 in steps:
            trial = best_log + np.array([d0, d1])
            candidate = list(current)
            candidate[k] = _line_through(views.depth_kind, ends, tuple(np.exp(trial)))
            cost = views.cost(candidate, only=k)
            if cost < best:
                best, best_log, current = cost, trial, candidate
    handles = list(handles)
    handles[k] = (ends, best_log)
    return current, handles


def alignment_cost(
    cameras: Sequence[Camera],
    priors: Sequence[np.ndarray],
    depth_kind: str,
    lines: Sequence[Line],
    anchors: Sequence[tuple[np.ndarray, np.ndarray] | None] | None = None,
) -> float:
    """The cost :func:`refine_alignment` lowers (module docstring), of the given lines."""
    views = _Views(cameras, priors, depth_kind, anchors or [None] * len(cameras))
    views.freeze(lines)
    return views.cost(lines)


def refine_alignment(
    cameras: Sequence[Camera],
    priors: Sequence[np.ndarray],
    depth_kind: str,
    lines: Sequence[Line | None],
    anchors: Sequence[tuple[np.ndarray, np.ndarray] | None] | None = None,
) -> list[Line | None]:
    """Each view's prior line refined so that the views agree with each other and with their anchors.

    Args:
        cameras: the training views.
        priors: their ``[H, W]`` depth priors (NaN where unknown).
        depth_kind: "depth" (``z = a p + b``) or "disparity" (``1/z = a p + b``).
        lines: each view's ``(a, b)`` fitted alone, or None for a view without one (left out).
        anchors: per view the ``(prior values, z-depths)`` its line was fitted to, or None.

    Returns:
        The refined lines, in order; None where ``lines`` had None. A view whose prior is constant, or
        whose line gives no positive depth at the prior's 10th or 90th percentile, keeps its line;
        fewer than two views with lines return them unchanged.
    """
    if depth_kind not in ("depth", "disparity"):
        raise ValueError(f"depth_kind must be 'depth' or 'disparity', got {depth_kind!r}")
    if not len(cameras) == len(priors) == len(lines):
        raise ValueError("refine_alignment: one prior and one line per camera")
    anchors = list(anchors) if anchors is not None else [None] * len(cameras)
    used = [k for k, line in enumerate(lines) if line is not None]
    result = list(lines)
    if len(used) < 2:
        return result
    views = _Views(
        [cameras[k] for k in used], [priors[k] for k in used], depth_kind, [anchors[k] for k in used]
    )
    current = [tuple(map(float, lines[k])) for k in used]
    handles = []  # per view: (prior at the two percentiles, log-depths there) or None (kept as is)
    for prior, line in zip(views.priors, current, strict=True):
        finite = prior[np.isfinite(prior)]
        if finite.size < 2:
            handles.append(None)
            continue
        ends = tuple(float(q) for q in np.quantile(finite, [0.1, 0.9]))
        depths = _line_depth(np.array(ends), line, depth_kind)
        usable = ends[1] > ends[0] and np.isfinite(depths).all()
        handles.append((ends, np.log(depths)) if usable else None)
    span = SPAN
    offsets = np.linspace(-1.0, 1.0, STEPS)
    for _ in range(ROUNDS):
        views.freeze(current)
        current, handles = _search_common(views, current, handles, offsets * span)
        for k in range(len(handles)):
            current, handles = _search_view(views, current, handles, k, offsets * span)
        span *= SHRINK
    for k, line in zip(used, current, strict=True):
        result[k] = line
    return result
