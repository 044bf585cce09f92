"""Pixel geometry and patch matching shared by the start's modules (:mod:`~langfield.training.
initialisation`, :mod:`~langfield.training.prior_alignment`, :mod:`~langfield.training.prior_correction`).

Cameras in OpenCV's convention (x right, y down, z forward), in float64: the start works in metres
across rooms, where float32 poses lose the millimetres the depth checks compare.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from langfield.camera import Camera

__all__ = [
    "backproject",
    "box_mean",
    "cv_pose",
    "gray",
    "intrinsic_matrix",
    "project",
    "window_stats",
    "zncc",
]


def cv_pose(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(R [3, 3], t [3]) world -> camera, float64."""
    w2c = cam.world_to_camera(dtype=torch.float64).numpy()
    return w2c[:3, :3], w2c[:3, 3]


def intrinsic_matrix(cam: Camera) -> np.ndarray:
    return np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])


def project(points: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates [N, 2] and depths z [N] of world points in ``cam``."""
    r, t = cv_pose(cam)
    p = points @ r.T + t
    z = p[:, 2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    uv = np.stack([cam.fx * p[:, 0] / zs + cam.cx, cam.fy * p[:, 1] / zs + cam.cy], axis=-1)
    return uv, z


def backproject(depth: np.ndarray, cam: Camera, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """World points [N, 3] of pixel centres (rows, cols) at z-depth ``depth[rows, cols]``."""
    r, t = cv_pose(cam)
    z = depth[rows, cols]
    x = (cols + 0.5 - cam.cx) / cam.fx * z
    y = (rows + 0.5 - cam.cy) / cam.fy * z
    cam_pts = np.stack([x, y, z], axis=-1)
    return (cam_pts - t) @ r  # R^T (p - t)


def gray(image: np.ndarray) -> np.ndarray:
    """[H, W] float32 grey of an [H, W, 3] RGB image."""
    return cv2.cvtColor(np.ascontiguousarray(image, dtype=np.float32), cv2.COLOR_RGB2GRAY)


def box_mean(x: np.ndarray, size: int) -> np.ndarray:
    """Mean over the ``size`` x ``size`` window around each pixel (mirrored at the border)."""
    return cv2.blur(x, (size, size), borderType=cv2.BORDER_REFLECT_101)


def window_stats(x: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, variance) of ``x`` over the ``size`` x ``size`` window around each pixel."""
    mean = box_mean(x, size)
    return mean, np.maximum(box_mean(x * x, size) - mean * mean, 0.0)


def zncc(
    ref: np.ndarray, ref_mean: np.ndarray, ref_var: np.ndarray, warped: np.ndarray, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """Zero-normalised cross-correlation of ``warped`` with ``ref`` over ``size`` windows.

    Args:
        ref: [H, W] the reference grey image; ``ref_mean``, ``ref_var`` its window mean and variance
            (computed once per reference, :func:`window_stats`).
        warped: [H, W] another view's grey image warped onto the reference.

    Returns:
        ``(score [H, W] in [-1, 1], the warped image's window variance [H, W])``.
    """
    mean, var = window_stats(warped, size)
    cov = box_mean(ref * warped, size) - ref_mean * mean
    return cov / np.sqrt(ref_var * var + 1e-10), var
