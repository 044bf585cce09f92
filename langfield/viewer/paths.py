"""Smooth camera paths through a scene, for fly-through videos (``langfield render --path``).

Both paths keep the intrinsics of the first camera and turn around one *target*: the point closest, in
least squares, to every camera's optical axis (where the captures look). When the axes are nearly
parallel (a forward-facing capture such as LLFF) that point is ill-defined along them, and the
``fallback`` point (the field's bounds centre) is used instead.

- :func:`orbit` circles the target about the cameras' mean up axis at their mean distance and height.
  Captures that surround the scene (their azimuths span more than half a turn) get a full turn;
  forward-facing ones get a swing across their own arc widened by half, there and back, so that the
  path never looks at the side of the scene no photo saw.
- :func:`interpolate` passes through the cameras themselves, ordered by azimuth around the target:
  positions on a Catmull-Rom spline, rotations by spherical interpolation, frames spaced by distance.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import viser.transforms as tf

from langfield.camera import Camera

# Smallest eigenvalue (per camera) of sum(I - d d^T) below which the optical axes count as parallel:
# about the axes' spread of 13 degrees.
PARALLEL_AXES = 0.05
# A forward-facing orbit swings over the cameras' arc times this, and at least MIN_SWING radians each
# way (LLFF fern's cameras span 11 degrees about its bounds' centre: a swing of 8 each way).
SWING_WIDEN = 1.5
MIN_SWING = np.deg2rad(5.0)


def look_target(cameras: Sequence[Camera], fallback: np.ndarray | None = None) -> np.ndarray:
    """[3] the point the cameras look at: closest to all optical axes, or ``fallback`` (else the point
    one mean camera distance ahead of the cameras) when the axes are nearly parallel."""
    centers = np.stack([c.center for c in cameras])
    dirs = np.stack([c.forward for c in cameras])
    projectors = np.eye(3)[None] - dirs[:, :, None] * dirs[:, None, :]  # [C, 3, 3]
    a = projectors.sum(0)
    b = np.einsum("cij,cj->i", projectors, centers)
    if np.linalg.eigvalsh(a)[0] / len(cameras) >= PARALLEL_AXES:
        return np.linalg.solve(a, b)
    if fallback is not None:
        return np.asarray(fallback, dtype=np.float64)
    spread = float(np.linalg.norm(centers - centers.mean(0), axis=1).mean())
    return centers.mean(0) + dirs.mean(0) * max(spread * 4.0, 1.0)


def _basis(cameras: Sequence[Camera]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit up axis (the cameras' mean) and two unit axes spanning the plane orthogonal to it."""
    up = np.mean([c.c2w[:3, 1] for c in cameras], axis=0)
    up /= max(np.linalg.norm(up), 1e-12)
    seed = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, seed)
    e1 /= np.linalg.norm(e1)
    return up, e1, np.cross(up, e1)


def _azimuths(cameras: Sequence[Camera], target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cameras' azimuths about the target (radians), and the basis (up, e1, e2)."""
    up, e1, e2 = _basis(cameras)
    offsets = np.stack([c.center for c in cameras]) - target
    return np.arctan2(offsets @ e2, offsets @ e1), np.stack([up, e1, e2])


def _largest_gap(azimuths: np.ndarray) -> tuple[float, float]:
    """(start, span) of the cameras' arc: it begins after the largest gap between sorted azimuths."""
    a = np.sort(np.mod(azimuths, 2 * np.pi))
    gaps = np.diff(np.concatenate([a, a[:1] + 2 * np.pi]))
    k = int(np.argmax(gaps))
    start = a[(k + 1) % len(a)]
    return float(start), float(2 * np.pi - gaps[k])


def _with_intrinsics(reference: Camera, c2w: np.ndarray, name: str) -> Camera:
    r = reference
    return Camera(name, r.width, r.height, r.fx, r.fy, r.cx, r.cy, c2w)


def _check(cameras: Sequence[Camera], n_frames: int) -> None:
    if len(cameras) == 0:
        raise ValueError("a camera path needs at least one camera")
    if n_frames < 2:
        raise ValueError(f"a camera path needs at least 2 frames, got {n_frames}")


def orbit(cameras: Sequence[Camera], n_frames: int, fallback: np.ndarray | None = None) -> list[Camera]:
    """``n_frames`` cameras circling the cameras' target (see the module's docstring); the path is a
    loop: its last frame leads back into its first."""
    _check(cameras, n_frames)
    target = look_target(cameras, fallback)
    azimuths, (up, e1, e2) = _azimuths(cameras, target)
    offsets = np.stack([c.center for c in cameras]) - target
    height = float((offsets @ up).mean())
    radius = float(np.linalg.norm(offsets - np.outer(offsets @ up, up), axis=1).mean())
    radius = max(radius, 1e-3 * max(np.linalg.norm(offsets, axis=1).max(), 1.0))
    t = np.arange(n_frames) / n_frames
    start, span = _largest_gap(azimuths)
    if len(cameras) > 1 and span > np.pi:
        angles = azimuths[0] + 2 * np.pi * t
    else:
        half = max(0.5 * span * SWING_WIDEN, MIN_SWING)
        angles = start + 0.5 * span + half * np.sin(2 * np.pi * t)
    frames = []
    for i, angle in enumerate(angles):
        eye = target + radius * (np.cos(angle) * e1 + np.sin(angle) * e2) + height * up
        c2w = Camera.look_at(eye, target, up).c2w
        frames.append(_with_intrinsics(cameras[0], c2w, f"orbit_{i:04d}"))
    return frames


def _catmull_rom(points: np.ndarray, segment: int, u: float) -> np.ndarray:
    """The uniform Catmull-Rom spline through ``points`` on ``segment`` (between points segment and
    segment + 1) at ``u`` in [0, 1]; the ends repeat the first and last points."""
    n = len(points)
    p0, p1, p2, p3 = (points[min(max(segment + k, 0), n - 1)] for k in (-1, 0, 1, 2))
    u2, u3 = u * u, u * u * u
    return 0.5 * (
        2 * p1 + (p2 - p0) * u + (2 * p0 - 5 * p1 + 4 * p2 - p3) * u2 + (3 * p1 - p0 - 3 * p2 + p3) * u3
    )


def interpolate(
    cameras: Sequence[Camera], n_frames: int, fallback: np.ndarray | None = None
) -> list[Camera]:
    """``n_frames`` cameras from one end of the cameras' arc to the other through every camera (see the
    module's docstring); the first and last frames are the first and last cameras in that order."""
    _check(cameras, n_frames)
    if len(cameras) == 1:
        return [_with_intrinsics(cameras[0], cameras[0].c2w, f"path_{i:04d}") for i in range(n_frames)]
    target = look_target(cameras, fallback)
    azimuths, _ = _azimuths(cameras, target)
    start, _ = _largest_gap(azimuths)
    order = np.argsort(np.mod(azimuths - start, 2 * np.pi), kind="stable")
    ordered = [cameras[i] for i in order]
    points = np.stack([c.center for c in ordered])
    rotations = [tf.SO3.from_matrix(c.c2w[:3, :3]) for c in ordered]
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1) + 1e-9  # equal steps when cameras coincide
    cumulative = np.concatenate([[0.0], np.cumsum(lengths)])
    ref = ordered[0]
    frames = []
    for i, s in enumerate(np.linspace(0.0, cumulative[-1], n_frames)):
        seg = int(min(np.searchsorted(cumulative, s, side="right") - 1, len(ordered) - 2))
        u = float((s - cumulative[seg]) / lengths[seg])
        delta = (rotations[seg].inverse() @ rotations[seg + 1]).log()
        rot = rotations[seg] @ tf.SO3.exp(u * delta)
        c2w = np.eye(4)
        c2w[:3, :3] = rot.as_matrix()
        c2w[:3, 3] = _catmull_rom(points, seg, u)
        frames.append(_with_intrinsics(ref, c2w, f"path_{i:04d}"))
    return frames


PATHS = {"orbit": orbit, "interpolate": interpolate}
