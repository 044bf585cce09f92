"""A scene's box when no ``aabb`` is given: where the training cameras' frusta meet, or near and
far planes.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from langfield.camera import Camera
from langfield.io.layout import GL_TO_CV

# ---------------------------------------------------------------------------------------------------
# Bounds


def near_far_box(cameras: Sequence[Camera], near: float, far: float) -> np.ndarray:
    """[2, 3] box around the cameras' frustum corners at depths `near` and `far`."""
    points = np.concatenate([_frustum_points(cam, np.array([near, far]), steps=2) for cam in cameras])
    return _padded_box(points, 1e-6 * max(far, 1e-3))


def shared_frustum_box(cameras: Sequence[Camera], steps: int = 9) -> np.ndarray:
    """[2, 3] box around the region the cameras share.

    When the cameras converge on a focus point (an object-centric capture such as the Blender scenes),
    the object sits around that point: the depth range is [0.5 d, 1.5 d], with d the median distance
    from the cameras to the focus, and points must be seen by every camera. Otherwise (forward-facing
    captures) the range is [0.2 d, 2 d] and two cameras suffice. Points on a `steps`^3 grid in each
    frustum are kept if enough cameras see them; if none are, all of them are kept.
    """
    d, converging = _focus_distance(cameras)
    near, far, needed = (0.5, 1.5, len(cameras)) if converging else (0.2, 2.0, min(2, len(cameras)))
    depths = np.linspace(near * d, far * d, steps)
    points = np.concatenate([_frustum_points(cam, depths, steps) for cam in cameras])
    seen = np.sum([_sees(cam, points) for cam in cameras], axis=0)
    shared = points[seen >= needed]
    return _padded_box(shared if len(shared) else points, 1e-3 * d)


def _focus_distance(cameras: Sequence[Camera]) -> tuple[float, bool]:
    """Median distance from the cameras to the least-squares closest point to their optical axes,
    and whether that point is well defined (the cameras converge on it).

    When that point is ill-defined (one camera, near-parallel axes, or a point behind the cameras,
    as in forward-facing captures) the distance falls back to 5x the cameras' spread, a typical
    depth-to-baseline ratio for hand-held captures, or 1 for a single camera.
    """
    centres = np.stack([cam.center for cam in cameras])
    axes = np.stack([cam.forward for cam in cameras])
    if len(cameras) >= 2:
        # Each axis contributes the projector onto the plane normal to it; the focus minimises the
        # summed squared distances to the axes.
        proj = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
        lhs, rhs = proj.sum(axis=0), np.einsum("nij,nj->i", proj, centres)
        if np.linalg.eigvalsh(lhs).min() > 1e-4 * len(cameras):
            focus = np.linalg.solve(lhs, rhs)
            ahead = np.einsum("ni,ni->n", focus - centres, axes)
            distance = float(np.median(np.linalg.norm(focus - centres, axis=1)))
            if np.median(ahead) > 0 and distance > 1e-9:
                return distance, True
    spread = float(np.max(np.linalg.norm(centres[:, None] - centres[None], axis=-1)))
    return (5.0 * spread if spread > 1e-9 else 1.0), False


def _frustum_points(cam: Camera, depths: np.ndarray, steps: int) -> np.ndarray:
    """[steps * steps * len(depths), 3] world points on a pixel grid (edges included) at z-depths."""
    u, v = np.linspace(0.0, cam.width, steps), np.linspace(0.0, cam.height, steps)
    uu, vv, zz = np.meshgrid(u, v, np.asarray(depths, dtype=np.float64), indexing="ij")
    local = np.stack([(uu - cam.cx) / cam.fx * zz, (vv - cam.cy) / cam.fy * zz, zz], axis=-1).reshape(-1, 3)
    c2w = cam.c2w @ GL_TO_CV  # local points are in OpenCV camera coordinates
    return local @ c2w[:3, :3].T + c2w[:3, 3]


def _sees(cam: Camera, points: np.ndarray) -> np.ndarray:
    """[N] bool: the points project inside the image, in front of the camera."""
    w2c = np.linalg.inv(cam.c2w @ GL_TO_CV)
    local = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = local[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cam.fx * local[:, 0] / z + cam.cx
        v = cam.fy * local[:, 1] / z + cam.cy
    tol = 1e-6 * max(cam.width, cam.height)  # grid points lie exactly on their own frustum's edges
    return (z > 0) & (u >= -tol) & (u <= cam.width + tol) & (v >= -tol) & (v <= cam.height + tol)


def clipped_near_far(view_bounds: np.ndarray) -> tuple[float, float]:
    """(min near, max far), with far clipped to 3x the median far so one outlier cannot blow it up."""
    near = float(view_bounds[:, 0].min())
    far = min(float(view_bounds[:, 1].max()), 3.0 * float(np.median(view_bounds[:, 1])))
    return near, far


def _padded_box(points: np.ndarray, eps: float) -> np.ndarray:
    """[2, 3] axis-aligned box of the points, widened to at least `eps` on every axis."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    mid, half = (lo + hi) / 2.0, np.maximum((hi - lo) / 2.0, eps / 2.0)
    return np.stack([mid - half, mid + half])
