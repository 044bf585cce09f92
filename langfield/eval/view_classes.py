"""Where each test view stands against the training views: ``near`` one, ``between`` them, or ``beyond``.

A scene's mean PSNR mixes views a training view almost sees with views that extrapolate, and three
views leave most test views of a wide capture in the second kind. The evaluation reports each class
apart, so that extrapolation is visible (issue 41).

The measures, all relative to the training cameras' own spread (their mean pairwise centre distance,
the *baseline*, so that a scene's scale does not matter):

- ``nearest``: the distance from the test camera's centre to the nearest training camera's centre, in
  baselines, and ``angle`` the angle (degrees) between their viewing directions;
- ``outside``: the distance from the test centre to the convex hull of the training centres (0 inside
  it), in baselines.

``near``: ``nearest <= NEAR`` and ``angle <= NEAR_ANGLE`` (a training view sees almost what it sees);
``between``: else ``outside <= BETWEEN`` (interpolation: within the training cameras' span); ``beyond``:
the rest (extrapolation). One training view has no baseline: every view is then ``beyond`` unless it
sits at that camera (``near``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from langfield.camera import Camera, camera_spacing

VIEW_CLASSES = ("near", "between", "beyond")
NEAR, NEAR_ANGLE = 0.25, 15.0  # baselines; degrees
BETWEEN = 0.25  # baselines outside the training centres' hull


def hull_distance(point: np.ndarray, vertices: np.ndarray, iterations: int = 2000) -> float:
    """Euclidean distance from ``point`` [3] to the convex hull of ``vertices`` [N, 3]: the nearest
    convex combination, by accelerated projected gradient on the weights (FISTA with the Euclidean
    projection onto the simplex); exact to about 1e-6 of the hull's size for the cameras of a scene."""
    v = np.asarray(vertices, dtype=np.float64)
    p = np.asarray(point, dtype=np.float64)
    lipschitz = max(float(np.linalg.eigvalsh(v @ v.T).max()), 1e-12)
    weights = momentum = np.full(len(v), 1.0 / len(v))
    t = 1.0
    for _ in range(iterations):
        step = _onto_simplex(momentum - (v @ (momentum @ v - p)) / lipschitz)
        t_next = (1.0 + np.sqrt(1.0 + 4.0 * t * t)) / 2.0
        momentum = step + (t - 1.0) / t_next * (step - weights)
        if np.abs(step - weights).max() < 1e-12:
            weights = step
            break
        weights, t = step, t_next
    return float(np.linalg.norm(weights @ v - p))


def _onto_simplex(x: np.ndarray) -> np.ndarray:
    """The Euclidean projection of ``x`` onto {w >= 0, sum w = 1} (the sort-based rule of Held, Wolfe
    and Crowder 1974)."""
    u = np.sort(x)[::-1]
    cumulative = np.cumsum(u) - 1.0
    k = np.nonzero(u - cumulative / np.arange(1, len(x) + 1) > 0)[0][-1]
    return np.maximum(x - cumulative[k] / (k + 1), 0.0)


def classify_views(train: Sequence[Camera], test: Sequence[Camera]) -> dict[str, dict]:
    """``{test name: {"class", "nearest", "angle", "outside"}}`` (module docstring)."""
    centres = np.stack([c.center for c in train])
    forwards = np.stack([c.forward for c in train])
    baseline = camera_spacing(centres)
    out = {}
    for cam in test:
        gaps = np.linalg.norm(centres - cam.center, axis=1)
        k = int(np.argmin(gaps))
        angle = float(np.degrees(np.arccos(np.clip(forwards[k] @ cam.forward, -1.0, 1.0))))
        if baseline > 0:
            nearest = float(gaps[k] / baseline)
            outside = hull_distance(cam.center, centres) / baseline
        else:  # one training view: at it, or beyond it
            nearest = outside = 0.0 if gaps[k] < 1e-9 else float("inf")
        if nearest <= NEAR and angle <= NEAR_ANGLE:
            kind = "near"
        elif outside <= BETWEEN:
            kind = "between"
        else:
            kind = "beyond"
        out[cam.name] = {"class": kind, "nearest": round(nearest, 4), "angle": round(angle, 2),
                         "outside": round(outside, 4)}  # fmt: skip
    return out


def by_class(views: Sequence[dict], keys: Sequence[str] = ("PSNR", "SSIM", "masked_PSNR")) -> dict:
    """Per view class, the number of views and the mean of each of ``keys`` the views have (report
    records carrying ``view_class``)."""
    out = {}
    for kind in VIEW_CLASSES:
        members = [v for v in views if v.get("view_class", {}).get("class") == kind]
        entry: dict = {"views": len(members)}
        for key in keys:
            values = [v[key] for v in members if v.get(key) is not None]
            entry[key] = float(np.mean(values)) if values else None
        out[kind] = entry
    return out
