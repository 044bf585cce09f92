"""Scene folders: posed photos with optional depth priors, language features and segmentations.

:func:`load_scene` reads one of four layouts (docs/format.md) into a :class:`Scene`:

1. `transforms.json` (nerfstudio / instant-ngp);
2. the Blender NeRF pair `transforms_train.json` / `transforms_test.json`;
3. LLFF: `poses_bounds.npy` beside `images_N/` (the largest N) or `images/`;
4. a COLMAP model `sparse/0/cameras.bin|txt` + `images.bin|txt` beside `images/`.

Every bad input raises :class:`SceneError` naming the file (and frame or argument) and what is wrong;
nothing is guessed silently. Images are read lazily and cached at the working resolution.

Example:
    >>> scene = load_scene("data/lego_sparse", resolution=4)  # doctest: +SKIP
    >>> scene.names("train"), scene.image("r_2").shape  # doctest: +SKIP
    (['r_2', 'r_26', 'r_86'], (100, 100, 3))
"""

from __future__ import annotations

import json
import math
import numbers
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from encoders.cache import feature_cache_paths
from encoders.protocols import DEPTH_KINDS
from langfield.camera import Camera
from langfield.constants import (
    DEPTHS_DIR,
    FEATURES_DIR,
    IMAGES_DIR,
    MASKS_DIR,
    SEGMENTATIONS_DIR,
    TEXT_TABLE_FILE,
    TRANSFORMS_FILE,
)
from langfield.io import colmap as colmap

_IMAGE_EXTS = (".png", ".jpg", ".jpeg")
_TEST_EVERY = 8  # LLFF protocol (RegNeRF, DNGaussian, FSGS): every 8th image is held out
_DEFAULT_N_VIEWS = 3
_SPLITS = ("train", "test")
_DISTORTION_KEYS = ("k1", "k2", "p1", "p2")
_COLMAP_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips y and z; its own inverse
_WHITE = np.ones(3, dtype=np.float32)

Distortion = tuple[float, float, float, float]  # OpenCV k1, k2, p1, p2


class SceneError(ValueError):
    """A scene folder or argument that cannot be used; the message names the file, frame or argument."""


@dataclass(frozen=True)
class View:
    """One image of the scene.

    Attributes:
        name: image file name without extension.
        camera: the camera at the scene's working resolution.
        image_path: the image file.
        split: "train", "test" or None (held back from both, as the LLFF protocol does).
    """

    name: str
    camera: Camera
    image_path: Path
    split: str | None


@dataclass(frozen=True)
class _Frame:
    """One image as the folder describes it, at native resolution, before any choice of views."""

    name: str
    camera: Camera
    image_path: Path
    distortion: Distortion | None = None
    split: str | None = None


@dataclass(frozen=True)
class _Layout:
    """Everything a scene folder says, independent of resolution and training views."""

    root: Path
    source: Path  # the file that describes the cameras, for messages
    frames: tuple[_Frame, ...]
    depth_kind: str | None = None
    aabb: np.ndarray | None = None
    view_bounds: np.ndarray | None = None  # [N, 2] LLFF near, far per view
    background: np.ndarray | None = None


class Scene:
    """Posed views of one scene at a working resolution, with a choice of training views.

    Build one with :func:`load_scene`; :meth:`with_training_views` gives the same scene with other
    training views (sharing the image cache).

    Attributes:
        root: the scene folder.
        views: every view, in the order the folder lists them.
        depth_kind: "depth", "disparity" or None (no depth prior).
        aabb: [2, 3] scene box from transforms.json, or None.
        near_far: LLFF (smallest near, largest far), or None.
        background: [3] float32 white when the images carry alpha (composited on it), else None.
        resolution: the downscale factor applied to the native images (1.0 = native).
        text_embeddings_path: `text_embeddings.npz` if the folder has one, else None.
    """

    def __init__(
        self,
        layout: _Layout,
        splits: Sequence[str | None],
        resolution: float = 1.0,
        cache: dict[str, np.ndarray] | None = None,
    ) -> None:
        self._layout = layout
        self._cache: dict[str, np.ndarray] = {} if cache is None else cache
        self.root = layout.root
        self.resolution = float(resolution)
        self.depth_kind = layout.depth_kind
        self.aabb = None if layout.aabb is None else layout.aabb.copy()
        self.background = None if layout.background is None else layout.background.copy()
        bounds = layout.view_bounds
        self.near_far = None if bounds is None else (float(bounds[:, 0].min()), float(bounds[:, 1].max()))
        self.views = [
            View(f.name, f.camera.scaled(self.resolution), f.image_path, split)
            for f, split in zip(layout.frames, splits, strict=True)
        ]
        self._index = {view.name: i for i, view in enumerate(self.views)}
        embeddings = self.root / TEXT_TABLE_FILE
        self.text_embeddings_path = embeddings if embeddings.is_file() else None

    def __repr__(self) -> str:
        counts = {s: len(self.names(s)) for s in _SPLITS}
        return f"Scene({self.root}, {len(self.views)} views, train={counts['train']}, test={counts['test']})"

    def names(self, split: str = "train") -> list[str]:
        """Names of the views in `split` ("train", "test" or "all")."""
        return [v.name for v in self._split(split)]

    def cameras(self, split: str = "train") -> list[Camera]:
        """Cameras of the views in `split` ("train", "test" or "all"), at working resolution."""
        return [v.camera for v in self._split(split)]

    def camera(self, key: str | int) -> Camera:
        """The camera of a view, by name or by index into :attr:`views`."""
        return self.views[self._position(key)].camera

    def image(self, name: str | int) -> np.ndarray:
        """[H, W, 3] float32 RGB in [0, 1] at working resolution; alpha is composited on white.

        The array is the cached one (kept writable so that torch.from_numpy takes it without a
        warning): copy it before changing it in place.
        """
        i = self._position(name)
        key = self.views[i].name
        if key not in self._cache:
            self._cache[key] = self._read_image(i)
        return self._cache[key]

    def forget_image(self, name: str | int) -> None:
        """Drops a view's image from the cache: a pass that reads each image once (preprocessing) keeps
        a scene of hundreds of large photos out of memory."""
        self._cache.pop(self.views[self._position(name)].name, None)

    def stored_image(self, name: str | int) -> np.ndarray:
        """[H, W, 3] float32 RGB of the image file as stored (full size, not undistorted, not cached),
        alpha composited on white: what a depth model is given."""
        image = _read_rgba(self.views[self._position(name)].image_path)
        if image.shape[2] == 4:
            alpha = image[..., 3:]
            image = image[..., :3] * alpha + (1.0 - alpha)
        return np.ascontiguousarray(image, dtype=np.float32)

    def depth(self, name: str | int) -> np.ndarray | None:
        """[H, W] float32 `depths/<name>.npy` at working resolution, or None if there is none.

        The map may be stored at any size with the image's aspect ratio; it is resized bilinearly.
        """
        i = self._position(name)
        path = self.depth_path(i)
        if path is None:
            return None
        depth = _load_npy(path)
        _check_map_shape(path, depth.shape, self._layout.frames[i].camera)
        if not np.issubdtype(depth.dtype, np.number) or not np.isfinite(depth).all():
            raise SceneError(f"{path}: depth map has NaN, inf or non-numeric values")
        return self._align(i, depth.astype(np.float32), cv2.INTER_LINEAR, cv2.BORDER_REPLICATE)

    def depth_path(self, name: str | int) -> Path | None:
        """`depths/<name>.npy` if the view has a depth prior, else None."""
        path = self.root / DEPTHS_DIR / f"{self.views[self._position(name)].name}.npy"
        return path if path.is_file() else None

    def object_mask(self, name: str | int) -> np.ndarray | None:
        """[H, W] bool `masks/<name>.png` (non-zero = object) at working resolution, or None.

        The DTU protocol scores test views with the object alone (masked PSNR / SSIM, docs/format.md).
        """
        i = self._position(name)
        path = self.root / MASKS_DIR / f"{self.views[i].name}.png"
        if not path.is_file():
            return None
        mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if mask is None:
            raise SceneError(f"{path}: cannot read object mask")
        if mask.ndim == 3:
            mask = (mask != 0).any(axis=2)
        _check_map_shape(path, mask.shape, self._layout.frames[i].camera)
        inside = (mask != 0).astype(np.float32)
        return self._align(i, inside, cv2.INTER_AREA, cv2.BORDER_CONSTANT) >= 0.5

    def segmentations(self, name: str | int) -> dict[str, np.ndarray]:
        """{phrase: [H, W] bool} from `segmentations/<name>/<phrase>.png` (non-zero = inside)."""
        i = self._position(name)
        folder = self.root / SEGMENTATIONS_DIR / self.views[i].name
        if not folder.is_dir():
            return {}
        masks = {}
        for path in sorted(folder.glob("*.png")):
            mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            if mask is None:
                raise SceneError(f"{path}: cannot read segmentation mask")
            if mask.ndim == 3:
                mask = (mask != 0).any(axis=2)
            _check_map_shape(path, mask.shape, self._layout.frames[i].camera)
            inside = (mask != 0).astype(np.uint8)
            masks[path.stem] = self._align(i, inside, cv2.INTER_NEAREST, cv2.BORDER_CONSTANT) > 0
        return masks

    def feature_paths(self, name: str | int) -> tuple[Path, Path] | None:
        """(`language_features/<name>_f.npy`, `<name>_s.npy`) if both exist, None if neither does.

        Raises:
            SceneError: one of the pair exists without the other (an interrupted preprocessing).
        """
        paths = feature_cache_paths(self.root / FEATURES_DIR, self.views[self._position(name)].name)
        present = [p.is_file() for p in paths]
        if all(present):
            return paths
        if any(present):
            missing, there = (paths[1], paths[0]) if present[0] else (paths[0], paths[1])
            raise SceneError(
                f"{missing}: missing, though {there.name} is there (rerun `langfield preprocess`)"
            )
        return None

    def check_view(self, name: str | int) -> None:
        """Reads every file of a view (image, depth prior, feature cache, segmentation masks) and checks
        it as training and evaluation will, without keeping the pixels: bad input is found before any
        work is spent on it.

        Raises:
            SceneError: the first file that is missing, unreadable or of the wrong size
                (``FeatureCacheError`` for a feature cache).
        """
        from encoders.cache import read_feature_cache

        i = self._position(name)
        if self.views[i].name not in self._cache:
            self._read_image(i)
        self.depth(i)
        self.segmentations(i)
        self.object_mask(i)
        paths = self.feature_paths(i)
        if paths is not None:
            cam = self.views[i].camera
            read_feature_cache(*paths, expected_hw=(cam.height, cam.width))

    def with_training_views(
        self, views: Sequence[str | int] | None = None, n_views: int | None = None
    ) -> Scene:
        """The same scene with other training views (see :func:`load_scene` for the rules)."""
        splits = _choose_splits(self._layout, views, n_views)
        return Scene(self._layout, splits, self.resolution, self._cache)

    def bounds(self) -> np.ndarray:
        """[2, 3] (min corner, max corner) of the region that holds the scene, float64.

        In order: the `aabb` of transforms.json; for LLFF, the box around the training cameras'
        frustum corners at near and far; else the region the training frustums share (see
        _shared_frustum_box). The box always has max > min on every axis.
        """
        if self.aabb is not None:
            return self.aabb.copy()
        cameras = self.cameras("train")
        if not cameras:
            raise SceneError(f"{self._layout.source}: no training views to bound the scene")
        if self._layout.view_bounds is not None:
            return _near_far_box(cameras, *_clipped_near_far(self._layout.view_bounds))
        return _shared_frustum_box(cameras)

    def _split(self, split: str) -> list[View]:
        if split not in ("train", "test", "all"):
            raise SceneError(f"split must be 'train', 'test' or 'all', got {split!r}")
        return [v for v in self.views if split == "all" or v.split == split]

    def _position(self, key: str | int) -> int:
        if isinstance(key, numbers.Integral) and not isinstance(key, bool):
            if not -len(self.views) <= key < len(self.views):
                raise SceneError(
                    f"{self._layout.source}: view index {key} out of range ({len(self.views)} views)"
                )
            return int(key) % len(self.views)
        if isinstance(key, str) and key in self._index:
            return self._index[key]
        raise SceneError(f"{self._layout.source}: no view {key!r}; known views: {_listing(self._index)}")

    def alpha(self, name: str | int) -> np.ndarray | None:
        """[H, W] float32 coverage of the image's alpha channel at working resolution, or None.

        Scenes whose images carry alpha (the Blender data, the built-in scene) have a background that is
        not a surface; the depth loss leaves those pixels out.
        """
        i = self._position(name)
        frame = self._layout.frames[i]
        image = _read_rgba(frame.image_path)
        if image.shape[2] != 4:
            return None
        alpha = image[..., 3]
        if frame.distortion is not None:
            alpha = _undistort(alpha, frame.camera, frame.distortion, cv2.INTER_LINEAR, cv2.BORDER_CONSTANT)
        return np.ascontiguousarray(_resize(alpha, self.views[i].camera, cv2.INTER_AREA), dtype=np.float32)

    def _read_image(self, i: int) -> np.ndarray:
        frame = self._layout.frames[i]
        image = _read_rgba(frame.image_path)
        height, width = image.shape[:2]
        cam = frame.camera
        if (width, height) != (cam.width, cam.height):
            raise SceneError(
                f"{frame.image_path}: image is {width}x{height} but its camera in "
                f"{self._layout.source} says {cam.width}x{cam.height}"
            )
        if frame.distortion is not None:
            image = _undistort(image, cam, frame.distortion, cv2.INTER_LINEAR, cv2.BORDER_CONSTANT)
        if image.shape[2] == 4:  # undistorted first so that pixels from outside the frame turn white
            alpha = image[..., 3:]
            image = image[..., :3] * alpha + _WHITE * (1.0 - alpha)
        return np.ascontiguousarray(_resize(image, self.views[i].camera, cv2.INTER_AREA), dtype=np.float32)

    def _align(self, i: int, array: np.ndarray, interpolation: int, border: int) -> np.ndarray:
        """A per-pixel map stored for the native image, undistorted and resized to working resolution."""
        frame = self._layout.frames[i]
        if frame.distortion is not None:
            native = _resize(array, frame.camera, interpolation)
            array = _undistort(native, frame.camera, frame.distortion, interpolation, border)
        return _resize(array, self.views[i].camera, interpolation)


def load_scene(
    path: str | Path,
    *,
    resolution: float = 1.0,
    views: Sequence[str | int] | None = None,
    n_views: int | None = None,
) -> Scene:
    """Read a scene folder (transforms.json, Blender pair, LLFF or COLMAP; see the module docstring).

    Training views: explicit `views` (names or indices) are the train split and every other view is
    test. Otherwise the frames' `split` fields, if any frame has one. Otherwise `n_views` (default 3)
    spread evenly over the non-test frames, where test is every 8th frame (0, 8, 16, ...), as in the
    RegNeRF / DNGaussian protocol; frames in neither split get split None. An explicit `n_views`
    overrides the file's splits but keeps its test frames, if it has any. A scene too small to hold
    out every 8th frame and still give `n_views` has no test views.

    Args:
        path: the scene folder.
        resolution: downscale factor >= 1 (2 halves width and height).
        views: names or indices of the training views.
        n_views: number of training views to spread over the non-test frames.

    Returns:
        The scene at the working resolution.

    Raises:
        SceneError: a missing or malformed file, or a bad argument; the message names it.
    """
    if (
        isinstance(resolution, bool)
        or not isinstance(resolution, numbers.Real)
        or not math.isfinite(resolution)
    ):
        raise SceneError(f"resolution must be a finite number >= 1, got {resolution!r}")
    if resolution < 1:
        raise SceneError(f"resolution must be >= 1 (a downscale factor), got {resolution!r}")
    layout = _read_layout(Path(path))
    layout = replace(layout, background=_WHITE.copy() if _has_alpha(layout.frames[0].image_path) else None)
    return Scene(layout, _choose_splits(layout, views, n_views), float(resolution))


# ---------------------------------------------------------------------------------------------------
# Training-view choice


def _choose_splits(
    layout: _Layout, views: Sequence[str | int] | None, n_views: int | None
) -> list[str | None]:
    if n_views is not None and (
        isinstance(n_views, bool) or not isinstance(n_views, numbers.Integral) or n_views < 1
    ):
        raise SceneError(f"n_views must be a positive integer, got {n_views!r}")
    if views is not None:
        return _explicit_splits(layout, views, n_views)
    file_splits = [f.split for f in layout.frames]
    has_splits = any(s is not None for s in file_splits)
    if has_splits and n_views is None:
        return file_splits
    file_test = [i for i, s in enumerate(file_splits) if s == "test"]
    return _protocol_splits(layout, n_views or _DEFAULT_N_VIEWS, file_test or None)


def _explicit_splits(layout: _Layout, views: Sequence[str | int], n_views: int | None) -> list[str | None]:
    names = [f.name for f in layout.frames]
    if isinstance(views, (str, numbers.Integral)):
        views = [views]
    chosen: list[int] = []
    for key in views:
        if isinstance(key, numbers.Integral) and not isinstance(key, bool):
            if not -len(names) <= key < len(names):
                raise SceneError(f"views: index {key} out of range for {len(names)} views in {layout.source}")
            index = int(key) % len(names)
        elif isinstance(key, str) and key in names:
            index = names.index(key)
        else:
            raise SceneError(f"views: {layout.source} has no view {key!r}; known views: {_listing(names)}")
        if index not in chosen:
            chosen.append(index)
    if not chosen:
        raise SceneError("views: no training views given")
    if n_views is not None and n_views != len(chosen):
        raise SceneError(f"n_views={n_views} disagrees with the {len(chosen)} views given")
    return ["train" if i in chosen else "test" for i in range(len(names))]


def _protocol_splits(layout: _Layout, n_views: int, test: list[int] | None) -> list[str | None]:
    count = len(layout.frames)
    if test is None:
        test = list(range(0, count, _TEST_EVERY))
        if count - len(test) < n_views:  # too few frames to hold any out
            test = []
    rest = [i for i in range(count) if i not in test]
    if len(rest) < n_views:
        raise SceneError(f"n_views={n_views} but {layout.source} has only {len(rest)} non-test views")
    picks = np.round(np.linspace(0, len(rest) - 1, n_views)).astype(int)
    train = {rest[p] for p in picks}
    return ["train" if i in train else "test" if i in test else None for i in range(count)]


# ---------------------------------------------------------------------------------------------------
# Format readers


def _read_layout(root: Path) -> _Layout:
    if not root.is_dir():
        raise SceneError(f"{root}: scene folder not found")
    if (root / TRANSFORMS_FILE).is_file():
        return _read_transforms(root)
    if (root / "transforms_train.json").is_file():
        return _read_blender(root)
    if (root / "poses_bounds.npy").is_file():
        return _read_llff(root)
    try:
        model = colmap.find_model(root)
    except colmap.ColmapError as e:
        raise SceneError(str(e)) from e
    if model is not None:
        return _read_colmap(root, *model)
    raise SceneError(
        f"{root}: no scene found; looked for transforms.json, transforms_train.json, poses_bounds.npy "
        "and a COLMAP model (sparse/0/cameras.bin|txt with images.bin|txt)"
    )


def _read_transforms(root: Path) -> _Layout:
    path = root / TRANSFORMS_FILE
    meta = _load_json(path)
    frames = [_parse_frame(path, meta, i, frame) for i, frame in enumerate(meta["frames"])]
    return _json_layout(root, path, meta, frames)


def _read_blender(root: Path) -> _Layout:
    source = root / "transforms_train.json"
    meta = _load_json(source)
    frames = _split_frames(source, meta, "train")
    test_path = root / "transforms_test.json"  # transforms_val.json is not used
    if test_path.is_file():
        frames += _split_frames(test_path, _load_json(test_path), "test")
    return _json_layout(root, source, meta, frames)


def _split_frames(path: Path, meta: dict, split: str) -> list[_Frame]:
    """The frames of one Blender file, whose split is the file's."""
    return [
        replace(_parse_frame(path, meta, i, frame), split=split) for i, frame in enumerate(meta["frames"])
    ]


def _json_layout(root: Path, source: Path, meta: dict, frames: list[_Frame]) -> _Layout:
    frames = _unique_names(root, source, frames)
    return _Layout(root, source, frames, _depth_kind(root, source, meta), aabb=_aabb(source, meta))


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


def _parse_frame(path: Path, meta: dict, i: int, frame: object) -> _Frame:
    if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
        raise SceneError(f"{path}: frame {i} is not an object with a 'file_path' string")
    where = f"{path}: frame {i} ({frame['file_path']})"
    image_path = _resolve_image(path.parent, frame["file_path"], where)
    c2w = _transform_matrix(frame.get("transform_matrix"), where)
    camera, distortion = _frame_camera(meta, frame, image_path, c2w, where)
    split = frame.get("split")
    if split is not None and split not in _SPLITS:
        raise SceneError(f"{where}: split must be 'train' or 'test', got {split!r}")
    return _Frame(image_path.stem, camera, image_path, distortion, split)


def _resolve_image(base: Path, file_path: str, where: str) -> Path:
    rel = Path(file_path)  # pathlib drops a leading "./"
    candidates = [base / rel]
    if rel.suffix.lower() not in _IMAGE_EXTS:
        candidates += [base / rel.with_name(rel.name + ext) for ext in _IMAGE_EXTS]
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
        image_h, image_w = _image_size(image_path)
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


def _depth_kind(root: Path, path: Path, meta: dict) -> str | None:
    kind = meta.get("depth_kind")
    if kind is None:
        # Monocular depth models (DPT, MiDaS, Depth Anything) output disparity, so that is the default.
        return "disparity" if (root / DEPTHS_DIR).is_dir() else None
    if kind not in DEPTH_KINDS:
        raise SceneError(f"{path}: depth_kind must be 'depth' or 'disparity', got {kind!r}")
    return kind


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


def _unique_names(root: Path, source: Path, frames: list[_Frame]) -> tuple[_Frame, ...]:
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


def _read_llff(root: Path) -> _Layout:
    path = root / "poses_bounds.npy"
    data = _load_npy(path)
    if data.ndim != 2 or data.shape[1] != 17 or not np.issubdtype(data.dtype, np.number):
        raise SceneError(f"{path}: expected an N x 17 array of numbers, got shape {data.shape}")
    data = data.astype(np.float64)
    if not np.isfinite(data).all():
        raise SceneError(f"{path}: has NaN or inf values")
    bounds = data[:, 15:]
    if not ((bounds[:, 0] >= 0) & (bounds[:, 1] > bounds[:, 0])).all():
        raise SceneError(f"{path}: near/far bounds must satisfy 0 <= near < far")
    folder = _llff_folder(root, path)
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_EXTS)
    if len(images) != len(data):
        raise SceneError(f"{path}: {len(data)} poses but {len(images)} images in {folder}")
    height, width = _image_size(images[0])
    poses = data[:, :15].reshape(-1, 3, 5)
    frames = [
        _llff_frame(path, image, pose, width, height) for image, pose in zip(images, poses, strict=True)
    ]
    return _Layout(root, path, tuple(frames), _depth_kind(root, path, {}), view_bounds=bounds)


def _llff_folder(root: Path, path: Path) -> Path:
    """`images_N/` with the largest N (the sparse-view protocols' resolution), else `images/`."""
    scaled = [d for d in root.glob("images_*") if d.is_dir() and re.fullmatch(r"images_\d+", d.name)]
    for folder in [*sorted(scaled, key=lambda d: -int(d.name[7:])), root / IMAGES_DIR]:
        if folder.is_dir():
            return folder
    raise SceneError(f"{path}: no images_N/ or images/ folder beside it")


def _llff_frame(path: Path, image: Path, pose: np.ndarray, width: int, height: int) -> _Frame:
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
    return _Frame(image.stem, camera, image)


def _read_colmap(root: Path, cameras_path: Path, images_path: Path) -> _Layout:
    try:
        cameras = colmap.read_cameras(cameras_path)
        images = colmap.read_images(images_path)
    except colmap.ColmapError as e:
        raise SceneError(str(e)) from e
    if not images:
        raise SceneError(f"{images_path}: COLMAP model has no images")
    frames = [
        _colmap_frame(root, cameras_path, images_path, cameras, image)
        for image in sorted(images.values(), key=lambda im: im.name)
    ]
    return _Layout(
        root, images_path, _unique_names(root, images_path, frames), _depth_kind(root, images_path, {})
    )


def _colmap_frame(
    root: Path,
    cameras_path: Path,
    images_path: Path,
    cameras: dict[int, colmap.ColmapCamera],
    image: colmap.ColmapImage,
) -> _Frame:
    where = f"{images_path}: image {image.name!r}"
    if image.camera_id not in cameras:
        raise SceneError(f"{where} uses camera {image.camera_id}, which {cameras_path} does not define")
    fx, fy, cx, cy, distortion = _colmap_intrinsics(cameras_path, cameras[image.camera_id])
    image_path = root / IMAGES_DIR / image.name
    if not image_path.is_file():
        raise SceneError(f"{image_path}: image file not found (listed in {images_path})")
    try:
        # COLMAP stores world-to-camera in the OpenCV convention; Camera wants camera-to-world, OpenGL.
        c2w = np.linalg.inv(image.world_to_camera()) @ _GL_TO_CV
        camera = Camera(
            image_path.stem,
            cameras[image.camera_id].width,
            cameras[image.camera_id].height,
            fx,
            fy,
            cx,
            cy,
            c2w,
        )
    except (ValueError, np.linalg.LinAlgError) as e:
        raise SceneError(f"{where}: {e}") from e
    return _Frame(image_path.stem, camera, image_path, distortion)


def _colmap_intrinsics(
    path: Path, cam: colmap.ColmapCamera
) -> tuple[float, float, float, float, Distortion | None]:
    """(fx, fy, cx, cy, distortion) of a COLMAP camera; radial models map onto OpenCV k1 k2 p1 p2."""
    p = cam.params
    match cam.model:
        case "SIMPLE_PINHOLE":
            fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], (0.0, 0.0, 0.0, 0.0)
        case "PINHOLE":
            fx, fy, cx, cy, dist = *p, (0.0, 0.0, 0.0, 0.0)
        case "SIMPLE_RADIAL":
            fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], (p[3], 0.0, 0.0, 0.0)
        case "RADIAL":
            fx, fy, cx, cy, dist = p[0], p[0], p[1], p[2], (p[3], p[4], 0.0, 0.0)
        case "OPENCV":
            fx, fy, cx, cy, dist = *p[:4], tuple(p[4:])
        case _:
            raise SceneError(
                f"{path}: camera {cam.id} uses camera model {cam.model}, which is not supported "
                f"(supported: {', '.join(_COLMAP_MODELS)})"
            )
    return fx, fy, cx, cy, dist if any(dist) else None


# ---------------------------------------------------------------------------------------------------
# Pixels


def _load_npy(path: Path) -> np.ndarray:
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise SceneError(f"{path}: cannot read .npy: {e}") from e


def _read_raw(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise SceneError(f"{path}: cannot read image")
    return image


def _image_size(path: Path) -> tuple[int, int]:
    """(height, width) of an image file."""
    return _read_raw(path).shape[:2]


def _has_alpha(path: Path) -> bool:
    image = _read_raw(path)
    return image.ndim == 3 and image.shape[2] in (2, 4)


def _read_rgba(path: Path) -> np.ndarray:
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


def _check_map_shape(path: Path, shape: tuple[int, ...], cam: Camera) -> None:
    """A per-pixel map must be 2-D with the image's aspect ratio (any size; it is resized)."""
    expected = f"({cam.height}, {cam.width}) or the same aspect ratio"
    if len(shape) != 2 or min(shape) < 1:
        raise SceneError(f"{path}: expected a 2-D array of shape {expected}, got shape {shape}")
    aspect, image_aspect = shape[1] / shape[0], cam.width / cam.height
    if abs(aspect - image_aspect) > 0.01 * image_aspect:
        raise SceneError(f"{path}: shape {shape} does not fit its image; expected {expected}")


def _resize(array: np.ndarray, cam: Camera, interpolation: int) -> np.ndarray:
    if array.shape[:2] == (cam.height, cam.width):
        return array
    return cv2.resize(array, (cam.width, cam.height), interpolation=interpolation)


def _undistort(
    array: np.ndarray, cam: Camera, distortion: Distortion, interpolation: int, border: int
) -> np.ndarray:
    """What cv2.undistort does (same camera matrix before and after), with a choice of resampling."""
    k = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
    size = (cam.width, cam.height)
    map_x, map_y = cv2.initUndistortRectifyMap(k, np.asarray(distortion), None, k, size, cv2.CV_32FC1)
    warp = cv2.INTER_NEAREST if interpolation == cv2.INTER_NEAREST else cv2.INTER_LINEAR
    return cv2.remap(array, map_x, map_y, warp, borderMode=border)


def _listing(names: Sequence[str] | dict[str, int], limit: int = 20) -> str:
    names = list(names)
    shown = ", ".join(names[:limit])
    return shown + (f", ... ({len(names)} in all)" if len(names) > limit else "")


# ---------------------------------------------------------------------------------------------------
# Bounds


def _near_far_box(cameras: Sequence[Camera], near: float, far: float) -> np.ndarray:
    """[2, 3] box around the cameras' frustum corners at depths `near` and `far`."""
    points = np.concatenate([_frustum_points(cam, np.array([near, far]), steps=2) for cam in cameras])
    return _padded_box(points, 1e-6 * max(far, 1e-3))


def _shared_frustum_box(cameras: Sequence[Camera], steps: int = 9) -> np.ndarray:
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
    c2w = cam.c2w @ _GL_TO_CV  # local points are in OpenCV camera coordinates
    return local @ c2w[:3, :3].T + c2w[:3, 3]


def _sees(cam: Camera, points: np.ndarray) -> np.ndarray:
    """[N] bool: the points project inside the image, in front of the camera."""
    w2c = np.linalg.inv(cam.c2w @ _GL_TO_CV)
    local = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = local[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = cam.fx * local[:, 0] / z + cam.cx
        v = cam.fy * local[:, 1] / z + cam.cy
    tol = 1e-6 * max(cam.width, cam.height)  # grid points lie exactly on their own frustum's edges
    return (z > 0) & (u >= -tol) & (u <= cam.width + tol) & (v >= -tol) & (v <= cam.height + tol)


def _clipped_near_far(view_bounds: np.ndarray) -> tuple[float, float]:
    """(min near, max far), with far clipped to 3x the median far so one outlier cannot blow it up."""
    near = float(view_bounds[:, 0].min())
    far = min(float(view_bounds[:, 1].max()), 3.0 * float(np.median(view_bounds[:, 1])))
    return near, far


def _padded_box(points: np.ndarray, eps: float) -> np.ndarray:
    """[2, 3] axis-aligned box of the points, widened to at least `eps` on every axis."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    mid, half = (lo + hi) / 2.0, np.maximum((hi - lo) / 2.0, eps / 2.0)
    return np.stack([mid - half, mid + half])
