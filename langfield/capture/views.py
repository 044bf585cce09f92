"""The capture's world frame and its choice of training views.

:func:`normalise` puts the posed frames in the frame nerfstudio's data parser makes (its
``auto_orient_and_center_poses`` with ``orientation_method="up"`` and ``center_method="poses"``, then
``auto_scale_poses``): the cameras' mean up direction becomes +z, their mean centre the origin, and
the largest camera coordinate 1.

:func:`spread_views` chooses the training views for spread, as the few-shot room-tour system chooses
its views for angular diversity. Two frames are as far apart as the larger of two angles: between
their viewing directions, and between their centres as seen from the scene's centre (the median of
the sparse points). The first view is the medoid (the frame nearest all others in sum), each next the
frame farthest from those chosen (farthest-point sampling): three views from a sweep are its middle
and its two ends, so that the other frames lie between training views rather than beyond them.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["Normalisation", "frame_distances", "normalise", "spread_views"]

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


class Normalisation:
    """x -> scale * (rotation @ x + translation), from COLMAP's world to the scene's."""

    def __init__(self, rotation: np.ndarray, translation: np.ndarray, scale: float) -> None:
        self.rotation, self.translation, self.scale = rotation, translation, float(scale)

    def points(self, xyz: np.ndarray) -> np.ndarray:
        return self.scale * (np.asarray(xyz, np.float64) @ self.rotation.T + self.translation)

    def camera_to_world(self, cam_from_world: np.ndarray) -> np.ndarray:
        """[4, 4] OpenGL camera-to-world in the scene's frame of a [3, 4] COLMAP world-to-camera."""
        w2c = np.eye(4)
        w2c[:3] = cam_from_world
        c2w = np.linalg.inv(w2c) @ GL_TO_CV
        out = np.eye(4)
        out[:3, :3] = self.rotation @ c2w[:3, :3]
        out[:3, 3] = self.points(c2w[:3, 3])
        return out

    def as_dict(self) -> dict:
        return {
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "scale": self.scale,
        }


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation that turns unit vector ``a`` onto unit vector ``b`` (about their common normal)."""
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -1.0 + 1e-9:  # opposite: half a turn about any axis normal to a
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def normalise(cam_from_world: Sequence[np.ndarray], points: np.ndarray | None = None) -> Normalisation:
    """The nerfstudio normalisation of cameras given as [3, 4] COLMAP world-to-camera matrices.

    When the cameras barely move (a turn on the spot), the points' spread sets the scale instead.
    """
    c2w = [np.linalg.inv(np.vstack([p, [0.0, 0.0, 0.0, 1.0]])) @ GL_TO_CV for p in cam_from_world]
    up = np.mean([m[:3, 1] for m in c2w], axis=0)
    norm = np.linalg.norm(up)
    rotation = _rotation_between(up / norm, np.array([0.0, 0.0, 1.0])) if norm > 1e-9 else np.eye(3)
    centres = np.array([m[:3, 3] for m in c2w])
    translation = -rotation @ centres.mean(axis=0)
    extent = np.abs(centres @ rotation.T + translation).max()
    if extent < 1e-6 and points is not None and len(points):
        extent = np.abs(np.asarray(points) @ rotation.T + translation).max()
    return Normalisation(rotation, translation, 1.0 / extent if extent > 1e-12 else 1.0)


def frame_distances(c2w: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """[N, N] radians: the larger of the angle between viewing directions and the angle between the
    centres about ``centre``, for OpenGL camera-to-world matrices ``c2w`` [N, 4, 4]."""
    forward = -c2w[:, :3, 2]
    about = c2w[:, :3, 3] - centre
    about = about / np.maximum(np.linalg.norm(about, axis=1, keepdims=True), 1e-12)

    def angles(u: np.ndarray) -> np.ndarray:
        return np.arccos(np.clip(u @ u.T, -1.0, 1.0))

    return np.maximum(angles(forward), angles(about))


def spread_views(c2w: np.ndarray, centre: np.ndarray, count: int) -> list[int]:
    """Indices of ``count`` frames chosen for spread (the module's docstring), in input order."""
    n = len(c2w)
    if not 1 <= count <= n:
        raise ValueError(f"spread_views: cannot choose {count} of {n} frames")
    distance = frame_distances(np.asarray(c2w, np.float64), np.asarray(centre, np.float64))
    chosen = [int(np.argmin(distance.sum(axis=1)))]
    while len(chosen) < count:
        nearest = distance[:, chosen].min(axis=1)
        nearest[chosen] = -1.0
        chosen.append(int(np.argmax(nearest)))
    return sorted(chosen)
