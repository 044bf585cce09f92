"""Reading a view's image and its maps: 8- and 16-bit, grey or colour, with alpha; resizing and
undistortion to the working camera.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from langfield.camera import Camera
from langfield.io.layout import Distortion, SceneError

IMAGE_EXTS = (".png", ".jpg", ".jpeg")


# ---------------------------------------------------------------------------------------------------
# Pixels


def load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise SceneError(f"{path}: cannot read .npy: {e}") from e


def _read_raw(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SceneError(f"{path}: cannot read image")
    return image


def image_size(path: Path) -> tuple[int, int]:
    """(height, width) of an image file."""
    return _read_raw(path).shape[:2]


def has_alpha(path: Path) -> bool:
    image = _read_raw(path)
    return image.ndim == 3 and image.shape[2] in (2, 4)


def read_rgba(path: Path) -> np.ndarray:
    """[H, W, 3 or 4] float32 RGB(A) in [0, 1] from an 8- or 16-bit, grey or colour image."""
    raw = _read_raw(path)
    scale = np.iinfo(raw.dtype).max if np.issubdtype(raw.dtype, np.integer) else 1.0
    image = raw.astype(np.float32) / np.float32(scale)
    if image.ndim == 2:
        image = image[..., None]
    channels = image.shape[2]
    if channels in (1, 2):  # grey, grey + alpha
        return np.concatenate([np.repeat(image[..., :1], 3, axis=2), image[..., 1:]], axis=2)
    if channels == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    if channels == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    raise SceneError(f"{path}: unsupported image with {channels} channels")


def read_mask(path: Path, what: str, camera: Camera) -> np.ndarray:
    """[H, W] bool, non-zero = inside, of a mask image (grey or colour) at its stored size, checked
    against the view's native camera; ``what`` names it in the errors."""
    mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if mask is None:
        raise SceneError(f"{path}: cannot read {what}")
    if mask.ndim == 3:
        mask = (mask != 0).any(axis=2)
    check_map_shape(path, mask.shape, camera)
    return mask != 0


def check_map_shape(path: Path, shape: tuple[int, ...], cam: Camera) -> None:
    """A per-pixel map must be 2-D with the image's aspect ratio (any size; it is resized)."""
    expected = f"({cam.height}, {cam.width}) or the same aspect ratio"
    if len(shape) != 2 or min(shape) < 1:
        raise SceneError(f"{path}: expected a 2-D array of shape {expected}, got shape {shape}")
    aspect, image_aspect = shape[1] / shape[0], cam.width / cam.height
    if abs(aspect - image_aspect) > 0.01 * image_aspect:
        raise SceneError(f"{path}: shape {shape} does not fit its image; expected {expected}")


def resize(array: np.ndarray, cam: Camera, interpolation: int) -> np.ndarray:
    if array.shape[:2] == (cam.height, cam.width):
        return array
    return cv2.resize(array, (cam.width, cam.height), interpolation=interpolation)


def _matrix(cam: Camera) -> np.ndarray:
    return np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])


def undistorted_camera(cam: Camera, distortion: Distortion) -> Camera:
    """The pinhole camera of ``cam``'s undistorted image, cut to the pixels the photo covers.

    As nerfstudio's loaders undistort (``cv2.getOptimalNewCameraMatrix`` with alpha 0, then a crop to
    its valid region): keeping the photo's camera matrix instead leaves blank pixels along the edges,
    which training fits as dark Gaussians and evaluation scores. On LLFF fern posed by ``langfield
    capture`` (k1 0.057, 0.8 % of the pixels blank) that cost 2.9 dB of novel-view PSNR against the
    same poses with the distortion ignored.
    """
    new, (x, y, width, height) = cv2.getOptimalNewCameraMatrix(
        _matrix(cam), np.asarray(distortion, np.float64), (cam.width, cam.height), 0
    )
    if width < 1 or height < 1:  # a distortion no crop can undo: keep the camera matrix
        return cam
    return replace(
        cam,
        width=int(width),
        height=int(height),
        fx=float(new[0, 0]),
        fy=float(new[1, 1]),
        cx=float(new[0, 2] - x),
        cy=float(new[1, 2] - y),
    )


def undistort(
    array: np.ndarray,
    cam: Camera,
    distortion: Distortion,
    interpolation: int,
    border: int,
    target: Camera | None = None,
) -> np.ndarray:
    """The map of native camera ``cam`` undistorted into the pinhole camera ``target`` (default ``cam``
    itself, as cv2.undistort), with a choice of resampling."""
    target = cam if target is None else target
    size = (target.width, target.height)
    map_x, map_y = cv2.initUndistortRectifyMap(
        _matrix(cam), np.asarray(distortion), None, _matrix(target), size, cv2.CV_32FC1
    )
    warp = cv2.INTER_NEAREST if interpolation == cv2.INTER_NEAREST else cv2.INTER_LINEAR
    return cv2.remap(array, map_x, map_y, warp, borderMode=border)
