"""Patch matching shared by the start's stereo and its prior correction: grey images, box means and
zero-normalised cross-correlation over windows (OpenCV's filters, mirrored at the border).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = [
    "box_mean",
    "gray",
    "window_stats",
    "zncc",
]


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
