"""The nerfstudio / instant-ngp ``transforms.json`` and the Blender NeRF pair
``transforms_train.json`` / ``transforms_test.json``.
"""

from __future__ import annotations

import json
import math
import numbers
from dataclasses import replace
from pathlib import Path

import numpy as np

from langfield.camera import Camera
from langfield.constants import TRANSFORMS_FILE
from langfield.io.images import IMAGE_EXTS, image_size
from langfield.io.layout import SPLITS, Distortion, Frame, Layout, SceneError, depth_kind, unique_names

_DISTORTION_KEYS = ("k1", "k2", "p1", "p2")


def read_transforms(root: Path) -> Layout:
    path = root / TRANSFORMS_FILE
    meta = _load_json(path)
    frames = [_parse_frame(path, meta, i, frame) for i, frame in enumerate(meta["frames"])]
    layout = _json_layout(root, path, meta, frames)
    return replace(
        layout, view_bounds=_view_bounds(path, meta["frames"]), points_path=_points_path(root, path, meta)
    )


def read_blender(root: Path) -> Layout:
    source = root / "transforms_train.json"
    meta = _load_json(source)
    frames = _split_frames(source, meta, "train")
    test_path = root / "transforms_test.json"  # transforms_val.json is not used
    if test_path.is_file():
        frames += _split_frames(test_path, _load_json(test_path), "test")
    return _json_layout(root, source, meta, frames)


def _split_frames(path: Path, meta: dict, split: str) -> list[Frame]:
    """The frames of one Blender file, whose split is the file's."""
    return [
        replace(_parse_frame(path, meta, i, frame), split=split) for i, frame in enumerate(meta["frames"])
    ]


def _json_layout(root: Path, source: Path, meta: dict, frames: list[Frame]) -> Layout:
    frames = unique_names(root, source, frames)
    aabb = _aabb(source, meta)
    if aabb is not None:
        _check_facing(source, frames, aabb)
    return Layout(root, source, frames, depth_kind(root, source, meta), aabb=aabb)


def _check_facing(source: Path, frames: tuple[Frame, ...], aabb: np.ndarray) -> None:
    """Refuses a frame whose camera sees none of the scene's box. Poses that are world-to-camera, or in
    OpenCV's axes, usually fail this for most frames."""
    for frame in frames:
        if not frame.camera.faces(aabb):
            raise SceneError(
                f"{source}: frame {frame.name!r}: the scene's aabb lies entirely behind the camera; are the "
                "poses world-to-camera, or in OpenCV's axes (z forward) instead of camera-to-world OpenGL's?"
            )


def _load_json(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise SceneError(f"{path}: malformed JSON: {e}") from e
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"{path}: cannot read: {e}") from e
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise SceneError(f"{path}: expected a JSON object with a non-empty 'frames' list")
    return meta


def _parse_frame(path: Path, meta: dict, i: int, frame: object) -> Frame:
    if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
        raise SceneError(f"{path}: frame {i} is not an object with a 'file_path' string")
    where = f"{path}: frame {i} ({frame['file_path']})"
    image_path = _resolve_image(path.parent, frame["file_path"], where)
    c2w = _transform_matrix(frame.get("transform_matrix"), where)
    camera, distortion = _frame_camera(meta, frame, image_path, c2w, where)
    split = frame.get("split")
    if split is not None and split not in SPLITS:
        raise SceneError(f"{where}: split must be 'train' or 'test', got {split!r}")
    return Frame(image_path.stem, camera, image_path, distortion, split)


def _resolve_image(base: Path, file_path: str, where: str) -> Path:
    rel = Path(file_path)  # pathlib drops a leading "./"
    candidates = [base / rel]
    if rel.suffix.lower() not in IMAGE_EXTS:
        candidates += [base / rel.with_name(rel.name + ext) for ext in IMAGE_EXTS]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise SceneError(f"{where}: image file not found (tried {', '.join(str(c) for c in candidates)})")


def _transform_matrix(value: object, where: str) -> np.ndarray:
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise SceneError(f"{where}: transform_matrix is not a matrix of numbers") from e
    if matrix.shape not in ((4, 4), (3, 4)):
        raise SceneError(f"{where}: transform_matrix must be 4x4 or 3x4, got shape {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise SceneError(f"{where}: transform_matrix has NaN or inf entries")
    return matrix


def _frame_camera(
    meta: dict, frame: dict, image_path: Path, c2w: np.ndarray, where: str
) -> tuple[Camera, Distortion | None]:
    """The frame's camera from its own intrinsics, or the file's where the frame has none."""

    def get(key: str) -> object:
        return frame.get(key, meta.get(key))

    width, height = get("w"), get("h")
    if width is None or height is None:
        image_h, image_w = image_size(image_path)
        width, height = image_w if width is None else width, image_h if height is None else height
    width, height = _positive_int(width, "w", where), _positive_int(height, "h", where)
    fx = _first(_focal(frame, width, "x", where), _focal(meta, width, "x", where))
    if fx is None:
        raise SceneError(f"{where}: no focal length (give fl_x or camera_angle_x)")
    fy = _first(_focal(frame, height, "y", where), _focal(meta, height, "y", where), fx)
    cx = width / 2.0 if get("cx") is None else _number(get("cx"), "cx", where)
    cy = height / 2.0 if get("cy") is None else _number(get("cy"), "cy", where)
    try:
        camera = Camera(image_path.stem, width, height, fx, fy, cx, cy, c2w)
    except ValueError as e:
        raise SceneError(f"{where}: {e}") from e
    return camera, _frame_distortion(get("camera_model"), {k: get(k) for k in _DISTORTION_KEYS}, where)


def _frame_distortion(model: object, values: dict[str, object], where: str) -> Distortion | None:
    """OpenCV (k1, k2, p1, p2) for an OPENCV camera, None for PINHOLE (the default)."""
    model = model or "PINHOLE"
    if model not in ("PINHOLE", "OPENCV"):
        raise SceneError(f"{where}: unsupported camera_model {model!r} (expected PINHOLE or OPENCV)")
    distortion = tuple(0.0 if v is None else _number(v, k, where) for k, v in values.items())
    if model == "PINHOLE" and any(distortion):
        raise SceneError(f"{where}: camera_model PINHOLE with non-zero k1 k2 p1 p2; did you mean OPENCV?")
    return distortion if any(distortion) else None


def _first(*values: float | None) -> float | None:
    return next((v for v in values if v is not None), None)


def _focal(source: dict, size: int, axis: str, where: str) -> float | None:
    """fl_<axis>, or the focal length of camera_angle_<axis> (a full field of view in radians)."""
    if source.get(f"fl_{axis}") is not None:
        return _number(source[f"fl_{axis}"], f"fl_{axis}", where)
    if source.get(f"camera_angle_{axis}") is not None:
        angle = _number(source[f"camera_angle_{axis}"], f"camera_angle_{axis}", where)
        if not 0 < angle < math.pi:
            raise SceneError(f"{where}: camera_angle_{axis} must be in (0, pi) radians, got {angle}")
        return 0.5 * size / math.tan(0.5 * angle)
    return None


def _number(value: object, key: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise SceneError(f"{where}: {key} must be a finite number, got {value!r}")
    return float(value)


def _positive_int(value: object, key: str, where: str) -> int:
    number = _number(value, key, where)
    if number < 1 or number != int(number):
        raise SceneError(f"{where}: {key} must be a positive whole number, got {value!r}")
    return int(number)


def _points_path(root: Path, path: Path, meta: dict) -> Path | None:
    """The point cloud that ``ply_file_path`` names (nerfstudio's key), or None without the key."""
    value = meta.get("ply_file_path")
    if value is None:
        return None
    if not isinstance(value, str) or not (root / value).is_file():
        raise SceneError(f"{path}: ply_file_path {value!r} is not a file in {root}")
    return root / value


def _view_bounds(path: Path, frames: list[dict]) -> np.ndarray | None:
    """[N, 2] per-frame LLFF near and far (``near`` / ``far``, as ``langfield capture`` writes them from
    the sparse points' depths), or None when no frame has them; a frame with one needs both, all do."""
    given = [("near" in f or "far" in f) for f in frames]
    if not any(given):
        return None
    bounds = np.zeros((len(frames), 2))
    for i, frame in enumerate(frames):
        where = f"{path}: frame {i} ({frame['file_path']})"
        if "near" not in frame or "far" not in frame:
            raise SceneError(f"{where}: needs both near and far, as the other frames give them")
        near, far = _number(frame["near"], "near", where), _number(frame["far"], "far", where)
        if not 0 <= near < far:
            raise SceneError(f"{where}: near and far must satisfy 0 <= near < far, got {near}, {far}")
        bounds[i] = near, far
    return bounds


def _aabb(path: Path, meta: dict) -> np.ndarray | None:
    if meta.get("aabb") is None:
        return None
    try:
        box = np.asarray(meta["aabb"], dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise SceneError(f"{path}: aabb is not a 2x3 array of numbers") from e
    if box.shape != (2, 3) or not np.isfinite(box).all() or not (box[1] > box[0]).all():
        raise SceneError(f"{path}: aabb must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min")
    return box
