"""LLFF: ``poses_bounds.npy`` beside ``images_N/`` (the largest N) or ``images/``."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from langfield.camera import Camera
from langfield.constants import IMAGES_DIR
from langfield.io.images import IMAGE_EXTS, image_size, load_npy
from langfield.io.layout import Frame, Layout, SceneError, depth_kind


def read_llff(root: Path) -> Layout:
    path = root / "poses_bounds.npy"
    data = load_npy(path)
    if data.ndim != 2 or data.shape[1] != 17 or not np.issubdtype(data.dtype, np.number):
        raise SceneError(f"{path}: expected an N x 17 array of numbers, got shape {data.shape}")
    data = data.astype(np.float64)
    if not np.isfinite(data).all():
        raise SceneError(f"{path}: has NaN or inf values")
    bounds = data[:, 15:]
    if not ((bounds[:, 0] >= 0) & (bounds[:, 1] > bounds[:, 0])).all():
        raise SceneError(f"{path}: near/far bounds must satisfy 0 <= near < far")
    folder = _llff_folder(root, path)
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS)
    if len(images) != len(data):
        raise SceneError(f"{path}: {len(data)} poses but {len(images)} images in {folder}")
    height, width = image_size(images[0])
    poses = data[:, :15].reshape(-1, 3, 5)
    frames = [
        _llff_frame(path, image, pose, width, height) for image, pose in zip(images, poses, strict=True)
    ]
    return Layout(root, path, tuple(frames), depth_kind(root, path, {}), view_bounds=bounds)


def _llff_folder(root: Path, path: Path) -> Path:
    """`images_N/` with the largest N (the sparse-view protocols' resolution), else `images/`."""
    scaled = [d for d in root.glob("images_*") if d.is_dir() and re.fullmatch(r"images_\d+", d.name)]
    for folder in [*sorted(scaled, key=lambda d: -int(d.name[7:])), root / IMAGES_DIR]:
        if folder.is_dir():
            return folder
    raise SceneError(f"{path}: no images_N/ or images/ folder beside it")


def _llff_frame(path: Path, image: Path, pose: np.ndarray, width: int, height: int) -> Frame:
    """A camera from an LLFF 3x5 pose [R | t | (H, W, f)] given for full-resolution images."""
    full_h, full_w, focal = (float(x) for x in pose[:, 4])
    scale = width / full_w
    if full_h <= 0 or focal <= 0 or abs(full_h * scale - height) > 1.0:
        raise SceneError(
            f"{path}: pose for {image.name} is for {full_w:g}x{full_h:g} images (f={focal:g}), "
            f"which does not scale to the {width}x{height} images in {image.parent}"
        )
    rot = pose[:, :3]
    # LLFF columns are [down, right, back]; OpenGL wants [right, up, back].
    c2w = np.column_stack([rot[:, 1], -rot[:, 0], rot[:, 2], pose[:, 3]])
    camera = Camera(image.stem, width, height, focal * scale, focal * scale, width / 2.0, height / 2.0, c2w)
    return Frame(image.stem, camera, image)
