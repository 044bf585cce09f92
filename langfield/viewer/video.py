"""Fly-through videos of a field: frames along a camera path, written with OpenCV's video writer.

A frame is the colour render; with a query, the query's heat map over the render (the normalised
relevancy at the level the mask pipeline chose in that frame, turbo colour map) is set beside it. A
frame where the phrase is found nowhere shows the render without heat. The file is written beside
its destination and moved into place when complete, so an interrupted render leaves no half video.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch
from tqdm import tqdm

from langfield.camera import Camera
from querying.relevancy import normalize_map, smooth_map
from querying.visualize import heatmap_overlay

if TYPE_CHECKING:
    from langfield.field import LanguageField
    from langfield.query import Query, QueryView

# Containers OpenCV's writer is asked for, with the codec each gets (mp4v: MPEG-4 part 2, which every
# OpenCV build writes without an external encoder).
CODECS = {".mp4": "mp4v", ".avi": "MJPG"}


def check_video_path(path: str | Path, overwrite: bool) -> Path:
    """The video's path, refused before any work: a container OpenCV writes, a folder that exists, and
    no file there unless ``overwrite``."""
    path = Path(path)
    if path.suffix.lower() not in CODECS:
        raise ValueError(f"--video {path}: the file must end in {' or '.join(CODECS)}")
    if not path.parent.is_dir():
        raise ValueError(f"--video {path}: folder {path.parent} does not exist")
    if path.exists() and not overwrite:
        raise ValueError(f"--video {path}: the file exists (pass --overwrite to replace it)")
    return path


def render_rgb(field: LanguageField, camera: Camera) -> np.ndarray:
    """``float [H, W, 3]`` the colour render at ``camera``, in [0, 1] (no latents rendered)."""
    with torch.no_grad():
        return field.render(camera, language=False).rgb.clamp(0.0, 1.0).numpy()


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    return (rgb * 255.0 + 0.5).astype(np.uint8)


def heat_of(view: QueryView, level: int | None = None) -> torch.Tensor:
    """``[H, W]`` the heat map of a one-phrase query's view: the normalised relevancy at the level the
    mask pipeline chose (or at ``level``, smoothed and stretched the same way); zero where the phrase is
    found nowhere in the view."""
    heat = view.normalized if level is None else normalize_map(smooth_map(view.maps[level]))
    return heat if bool(view.found) else torch.zeros_like(heat)


def path_frames(
    field: LanguageField, cameras: Sequence[Camera], query: Query | None = None, progress: bool = True
) -> Iterator[np.ndarray]:
    """``uint8 [H, W, 3]`` RGB frames (``[H, 2W, 3]`` with a query) along ``cameras``."""
    for cam in tqdm(cameras, desc="render", disable=not progress, leave=False):
        rgb = render_rgb(field, cam)
        frame = to_uint8(rgb)
        if query is not None:
            frame = np.concatenate([frame, heatmap_overlay(rgb, heat_of(query.view(cam)))], axis=1)
        yield frame


def _even(frame: np.ndarray) -> np.ndarray:
    """The frame padded by one edge row / column where its size is odd (MPEG-4 wants even sizes)."""
    h, w = frame.shape[:2]
    return np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def write_video(path: Path, frames: Iterator[np.ndarray], fps: float) -> int:
    """Writes the RGB frames as a video at ``path`` (atomically); returns the number of frames."""
    staging = path.with_name(f".{path.stem}.partial{path.suffix}")
    writer = None
    count = 0
    try:
        for frame in frames:
            frame = _even(frame)
            if writer is None:
                size = (frame.shape[1], frame.shape[0])
                fourcc = cv2.VideoWriter_fourcc(*CODECS[path.suffix.lower()])
                writer = cv2.VideoWriter(str(staging), fourcc, fps, size)
                if not writer.isOpened():
                    raise OSError(f"{path}: OpenCV cannot write {path.suffix} video here")
            writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
            count += 1
        if writer is not None:
            writer.release()
            writer = None
            os.replace(staging, path)
    finally:
        if writer is not None:
            writer.release()
        staging.unlink(missing_ok=True)
    return count


def read_video(path: str | Path) -> list[np.ndarray]:
    """Every frame of a video as ``uint8 [H, W, 3]`` RGB (for tests and the README's frame)."""
    capture = cv2.VideoCapture(str(path))
    frames = []
    try:
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
    finally:
        capture.release()
    return frames
