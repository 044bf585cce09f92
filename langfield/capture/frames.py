"""The capture's input: a folder of photos or a video, read with OpenCV, and the frames kept from it.

A video gives more frames than structure from motion needs, many of them blurred by the hand's
motion or repeating the last one while the camera rests. :func:`video_frames` keeps ``count`` of them:

1. every frame is decoded once (OpenCV) and measured on a grey copy at most 480 pixels wide:
   its sharpness is the variance of the Laplacian (Pech-Pacheco et al. 2000, the measure common
   frame-picking tools use), and a 64 x 48 thumbnail is kept for the duplicate test;
2. the video is cut into ``count`` equal stretches of frames and the sharpest frame of each stretch is
   its candidate (as instant-ngp's and nerfstudio's frame samplers pick evenly in time, here the
   sharpest of each stretch instead of its first);
3. a candidate is dropped as *blurred* when its sharpness is below ``blur_ratio`` (0.3) of the
   video's median frame (even the sharpest frame of its stretch is then blurred beyond use), and as a
   *near-duplicate* when its thumbnail differs from the last kept frame's by less than
   ``duplicate_difference`` (1 % of the grey range, mean absolute difference): the camera did not
   move;
4. a second decoding pass stores the kept frames, each named by its time stamp (``t012.345s`` is
   12.345 s into the video).

Photos are kept as they are (the user chose them), in file-name order, named by their file stems;
a photo's EXIF 35 mm-equivalent focal length (Pillow reads it; OpenCV does not) becomes COLMAP's
focal-length prior, which few photos need most. Every frame is stored at most ``max_size`` pixels on
its longer side.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "PHOTO_EXTS",
    "VIDEO_EXTS",
    "CaptureInputError",
    "FrameChoice",
    "InputSummary",
    "inspect_input",
    "store_photos",
    "video_frames",
]

# What a photo folder's files may be; OpenCV decides whether it can read each (HEIC only where its
# build has a decoder, which Debian's and PyPI's builds do not).
PHOTO_EXTS = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", ".heic", ".heif")
VIDEO_EXTS = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg")
_MEASURE_WIDTH = 480  # the sharpness is measured at this width, so that it compares across videos
_THUMB = (64, 48)


class CaptureInputError(ValueError):
    """An input or flag that the capture cannot use; the message names the file or flag."""


@dataclass(frozen=True)
class InputSummary:
    """What :func:`inspect_input` found, before any work.

    Attributes:
        kind: "photos" or "video".
        paths: the photos in name order, or the one video.
        names: the photos' stems (frame names); empty for a video (named once chosen).
        sizes: (width, height) of each photo, or of the video's frames.
        frames: the video's frame count as its container states it (photos: their number).
        fps: the video's frame rate (0 for photos).
        focal_35mm: each photo's EXIF 35 mm-equivalent focal length in millimetres, or None.
    """

    kind: str
    paths: tuple[Path, ...]
    names: tuple[str, ...]
    sizes: tuple[tuple[int, int], ...]
    frames: int
    fps: float = 0.0
    focal_35mm: tuple[float | None, ...] = ()


@dataclass(frozen=True)
class FrameChoice:
    """The frames a video gave: those kept and every candidate dropped, with the reason."""

    kept: list[dict] = field(default_factory=list)  # {"name", "index", "time", "sharpness"}
    dropped: list[dict] = field(default_factory=list)  # the same, with "reason"
    decoded: int = 0
    median_sharpness: float = 0.0


def inspect_input(path: str | Path) -> InputSummary:
    """Checks that ``path`` is a folder of at least 3 readable photos or a video OpenCV can decode.

    Every photo is decoded once here (a damaged file is named before any other work); a video is
    opened and its first frame decoded.

    Raises:
        CaptureInputError: the path is missing, holds too few or unreadable photos, photos whose names
            repeat, or is a video that OpenCV cannot open.
    """
    path = Path(path)
    if path.is_dir():
        return _inspect_photos(path)
    if path.is_file():
        return _inspect_video(path)
    raise CaptureInputError(f"{path}: no such folder of photos or video file")


def _inspect_photos(folder: Path) -> InputSummary:
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_EXTS)
    if len(files) < 3:
        raise CaptureInputError(
            f"{folder}: {len(files)} photo(s) ({', '.join(PHOTO_EXTS)}); a capture needs at least 3"
        )
    seen: dict[str, Path] = {}
    sizes = []
    for file in files:
        if file.stem in seen:
            raise CaptureInputError(f"{file}: same name as {seen[file.stem].name}; rename one of them")
        seen[file.stem] = file
        image = _read_photo(file)
        sizes.append((image.shape[1], image.shape[0]))
    focal = tuple(exif_focal_35mm(f) for f in files)
    return InputSummary("photos", tuple(files), tuple(seen), tuple(sizes), len(files), focal_35mm=focal)


# 35 mm-equivalent focal lengths of real lenses, from a fisheye's to a long telephoto's: a tag outside
# it (0, a camera that writes the true focal length there, a corrupted value) is no prior at all.
EXIF_FOCAL_RANGE = (8.0, 2000.0)


def exif_focal_35mm(path: Path) -> float | None:
    """The photo's EXIF FocalLengthIn35mmFilm (tag 0xA405) in millimetres, or None where it has none or
    one outside ``EXIF_FOCAL_RANGE``."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            value = image.getexif().get_ifd(0x8769).get(0xA405)
    except (OSError, UnidentifiedImageError, ValueError):
        return None
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    low, high = EXIF_FOCAL_RANGE
    return value if math.isfinite(value) and low <= value <= high else None


def focal_pixels(focal_35mm: float, width: int, height: int) -> float:
    """The focal length in pixels of a 35 mm-equivalent one: the equivalent keeps the diagonal field of
    view of a 36 x 24 mm frame (43.27 mm diagonal)."""
    return focal_35mm * math.hypot(width, height) / math.hypot(36.0, 24.0)


def _read_photo(path: Path) -> np.ndarray:
    """[H, W, 3] uint8 BGR, EXIF orientation applied (OpenCV's default)."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise CaptureInputError(f"{path}: OpenCV cannot read this image (damaged, or a format it lacks)")
    return image


def _inspect_video(path: Path) -> InputSummary:
    if path.suffix.lower() not in VIDEO_EXTS:
        raise CaptureInputError(
            f"{path}: not a folder of photos, and {path.suffix or 'no extension'} is not a video "
            f"extension ({', '.join(VIDEO_EXTS)})"
        )
    capture = cv2.VideoCapture(str(path))
    try:
        ok, frame = capture.read() if capture.isOpened() else (False, None)
        if not ok or frame is None:
            raise CaptureInputError(f"{path}: OpenCV cannot decode this video")
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(capture.get(cv2.CAP_PROP_FPS))
    finally:
        capture.release()
    size = (frame.shape[1], frame.shape[0])
    return InputSummary("video", (path,), (), (size,), count, fps if math.isfinite(fps) and fps > 0 else 0.0)


def stored_size(width: int, height: int, max_size: int) -> tuple[int, int]:
    """(width, height) scaled so that the longer side is at most ``max_size`` (never enlarged)."""
    scale = min(1.0, max_size / max(width, height))
    return max(1, round(width * scale)), max(1, round(height * scale))


def _store(image: np.ndarray, path: Path, max_size: int) -> tuple[int, int]:
    width, height = stored_size(image.shape[1], image.shape[0], max_size)
    if (width, height) != (image.shape[1], image.shape[0]):
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    if not cv2.imwrite(str(path), image):
        raise OSError(f"{path}: cannot write the image")
    return width, height


def store_photos(summary: InputSummary, folder: Path, max_size: int, tick: Callable[[], None]) -> list[str]:
    """Writes each photo as ``folder/<name>.png`` at most ``max_size`` on its longer side; the names."""
    for name, path in zip(summary.names, summary.paths, strict=True):
        _store(_read_photo(path), folder / f"{name}.png", max_size)
        tick()
    return list(summary.names)


def _measure(frame: np.ndarray) -> tuple[float, np.ndarray]:
    """(sharpness, thumbnail) of a BGR frame: the Laplacian's variance at 480 pixels of width and a
    64 x 48 grey thumbnail in [0, 1]."""
    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    if grey.shape[1] > _MEASURE_WIDTH:
        height = max(1, round(grey.shape[0] * _MEASURE_WIDTH / grey.shape[1]))
        grey = cv2.resize(grey, (_MEASURE_WIDTH, height), interpolation=cv2.INTER_AREA)
    sharpness = float(cv2.Laplacian(grey, cv2.CV_64F).var())
    thumb = cv2.resize(grey, _THUMB, interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
    return sharpness, thumb


def _decode(path: Path, on_frame: Callable[[int, float, np.ndarray], bool]) -> int:
    """Calls ``on_frame(index, seconds, bgr)`` for every frame until it returns False; the count."""
    capture = cv2.VideoCapture(str(path))
    fps = capture.get(cv2.CAP_PROP_FPS)
    fps = fps if math.isfinite(fps) and fps > 0 else 30.0
    index = 0
    try:
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            if not on_frame(index, index / fps, frame):
                index += 1
                break
            index += 1
    finally:
        capture.release()
    return index


def frame_name(seconds: float) -> str:
    """A frame's name from its time stamp: ``t012.345s`` (milliseconds, at least three integer digits)."""
    return f"t{seconds:07.3f}s"


def video_frames(
    path: Path,
    folder: Path,
    count: int,
    max_size: int,
    *,
    blur_ratio: float = 0.3,
    duplicate_difference: float = 0.01,
    tick: Callable[[], None] = lambda: None,
) -> FrameChoice:
    """Keeps up to ``count`` sharp, distinct frames of the video, written as ``folder/<name>.png``
    (the steps are in the module's docstring). ``tick`` is called once per decoded frame of each pass."""
    sharpness: list[float] = []
    thumbs: list[np.ndarray] = []
    times: list[float] = []

    def measure(index: int, seconds: float, frame: np.ndarray) -> bool:
        s, t = _measure(frame)
        sharpness.append(s)
        thumbs.append(t)
        times.append(seconds)
        tick()
        return True

    decoded = _decode(path, measure)
    if decoded < 3:
        raise CaptureInputError(f"{path}: only {decoded} frame(s) could be decoded; a capture needs 3")
    bounds = np.linspace(0, decoded, min(count, decoded) + 1).round().astype(int)
    candidates = [int(a + np.argmax(sharpness[a:b])) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    median = float(np.median(sharpness))
    choice = FrameChoice(decoded=decoded, median_sharpness=median)
    last = None
    for i in candidates:
        record = {
            "name": frame_name(times[i]),
            "index": i,
            "time": round(times[i], 3),
            "sharpness": sharpness[i],
        }
        if sharpness[i] < blur_ratio * median:
            choice.dropped.append(
                {**record, "reason": f"blurred (sharpness below {blur_ratio} of the median frame)"}
            )
        elif last is not None and float(np.abs(thumbs[i] - thumbs[last]).mean()) < duplicate_difference:
            choice.dropped.append({**record, "reason": f"near-duplicate of {frame_name(times[last])}"})
        else:
            choice.kept.append(record)
            last = i
    wanted = {r["index"]: r["name"] for r in choice.kept}
    final = max(wanted, default=-1)  # the sharpest candidate is never below the median: one is kept

    def save(index: int, seconds: float, frame: np.ndarray) -> bool:
        if index in wanted:
            _store(frame, folder / f"{wanted[index]}.png", max_size)
        tick()
        return index < final

    _decode(path, save)
    return choice
