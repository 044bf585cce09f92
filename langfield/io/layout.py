"""What every scene-folder reader produces: the frames (image, camera, split) of a layout, and
the error they raise.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from encoders.protocols import DEPTH_KINDS
from langfield.camera import Camera
from langfield.constants import DEPTHS_DIR

SPLITS = ("train", "test")
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips y and z; its own inverse

Distortion = tuple[float, float, float, float]  # OpenCV k1, k2, p1, p2


class SceneError(ValueError):
    """A scene folder or argument that cannot be used; the message names the file, frame or argument."""


@dataclass(frozen=True)
class Frame:
    """One image as the folder describes it, at native resolution, before any choice of views."""

    name: str
    camera: Camera
    image_path: Path
    distortion: Distortion | None = None
    split: str | None = None


@dataclass(frozen=True)
class Layout:
    """Everything a scene folder says, independent of resolution and training views."""

    root: Path
    source: Path  # the file that describes the cameras, for messages
    frames: tuple[Frame, ...]
    depth_kind: str | None = None
    aabb: np.ndarray | None = None
    view_bounds: np.ndarray | None = None  # [N, 2] LLFF near, far per view
    background: np.ndarray | None = None
    points_path: Path | None = None  # the scene's point cloud (transforms.json's ply_file_path)


def depth_kind(root: Path, path: Path, meta: dict) -> str | None:
    kind = meta.get("depth_kind")
    if kind is None:
        # Monocular depth models (DPT, MiDaS, Depth Anything) output disparity, so that is the default.
        return "disparity" if (root / DEPTHS_DIR).is_dir() else None
    if kind not in DEPTH_KINDS:
        raise SceneError(f"{path}: depth_kind must be 'depth' or 'disparity', got {kind!r}")
    return kind


def unique_names(root: Path, source: Path, frames: list[Frame]) -> tuple[Frame, ...]:
    """The frames, named by path relative to the folder (no extension) when file names alone repeat."""
    if len({f.name for f in frames}) == len(frames):
        return tuple(frames)
    renamed = [replace(f, name=_relative_stem(root, f.image_path)) for f in frames]
    seen: dict[str, Path] = {}
    for f in renamed:
        if f.name in seen:
            raise SceneError(f"{source}: two frames use the same image name ({seen[f.name]}, {f.image_path})")
        seen[f.name] = f.image_path
    return tuple(replace(f, camera=replace(f.camera, name=f.name)) for f in renamed)


def _relative_stem(root: Path, path: Path) -> str:
    try:
        return path.relative_to(root).with_suffix("").as_posix()
    except ValueError:
        return path.with_suffix("").as_posix()


def listing(names: Sequence[str] | dict[str, int], limit: int = 20) -> str:
    names = list(names)
    shown = ", ".join(names[:limit])
    return shown + (f", ... ({len(names)} in all)" if len(names) > limit else "")
