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

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from encoders.cache import feature_cache_paths
from langfield.camera import Camera
from langfield.constants import (
    DEPTHS_DIR,
    FEATURES_DIR,
    MASKS_DIR,
    SEGMENTATIONS_DIR,
    TEXT_TABLE_FILE,
    TRANSFORMS_FILE,
)
from langfield.io import colmap as colmap
from langfield.io.bounds import clipped_near_far, near_far_box, shared_frustum_box
from langfield.io.colmap import read_colmap
from langfield.io.images import (
    check_map_shape,
    has_alpha,
    load_npy,
    read_mask,
    read_rgba,
    resize,
    undistort,
    undistorted_camera,
)
from langfield.io.layout import SPLITS, Layout, SceneError, listing
from langfield.io.llff import read_llff
from langfield.io.nerf import read_blender, read_transforms

_TEST_EVERY = 8  # LLFF protocol (RegNeRF, DNGaussian, FSGS): every 8th image is held out
_DEFAULT_N_VIEWS = 3
_WHITE = np.ones(3, dtype=np.float32)


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
        points_path: the scene's point cloud (transforms.json's `ply_file_path`), else None.
    """

    def __init__(
        self,
        layout: Layout,
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
        # A distorted photo's view is its undistorted pinhole camera, cut to the pixels the photo covers.
        self._pinhole = [
            f.camera if f.distortion is None else undistorted_camera(f.camera, f.distortion)
            for f in layout.frames
        ]
        self.views = [
            View(f.name, pinhole.scaled(self.resolution), f.image_path, split)
            for f, pinhole, split in zip(layout.frames, self._pinhole, splits, strict=True)
        ]
        self._index = {view.name: i for i, view in enumerate(self.views)}
        embeddings = self.root / TEXT_TABLE_FILE
        self.text_embeddings_path = embeddings if embeddings.is_file() else None
        self.points_path = layout.points_path

    def __repr__(self) -> str:
        counts = {s: len(self.names(s)) for s in SPLITS}
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
        image = read_rgba(self.views[self._position(name)].image_path)
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
        depth = load_npy(path)
        check_map_shape(path, depth.shape, self._layout.frames[i].camera)
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
        inside = read_mask(path, "object mask", self._layout.frames[i].camera).astype(np.float32)
        if not inside.any():  # the masked scores would compare no pixel: a PSNR of inf
            raise SceneError(
                f"{path}: the object mask is empty (no non-zero pixel); mark the object's pixels"
            )
        return self._align(i, inside, cv2.INTER_AREA, cv2.BORDER_CONSTANT) >= 0.5

    def segmentations(self, name: str | int) -> dict[str, np.ndarray]:
        """{phrase: [H, W] bool} from `segmentations/<name>/<phrase>.png` (non-zero = inside)."""
        i = self._position(name)
        folder = self.root / SEGMENTATIONS_DIR / self.views[i].name
        if not folder.is_dir():
            return {}
        masks = {}
        for path in sorted(folder.glob("*.png")):
            inside = read_mask(path, "segmentation mask", self._layout.frames[i].camera).astype(np.uint8)
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
        shared_frustum_box). The box always has max > min on every axis.
        """
        if self.aabb is not None:
            return self.aabb.copy()
        cameras = self.cameras("train")
        if not cameras:
            raise SceneError(f"{self._layout.source}: no training views to bound the scene")
        if self._layout.view_bounds is not None:
            return near_far_box(cameras, *clipped_near_far(self._layout.view_bounds))
        return shared_frustum_box(cameras)

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
        raise SceneError(f"{self._layout.source}: no view {key!r}; known views: {listing(self._index)}")

    def alpha(self, name: str | int) -> np.ndarray | None:
        """[H, W] float32 coverage of the image's alpha channel at working resolution, or None.

        Scenes whose images carry alpha (the Blender data, the built-in scene) have a background that is
        not a surface; the depth loss leaves those pixels out.
        """
        i = self._position(name)
        frame = self._layout.frames[i]
        image = read_rgba(frame.image_path)
        if image.shape[2] != 4:
            return None
        alpha = image[..., 3]
        if frame.distortion is not None:
            alpha = undistort(
                alpha, frame.camera, frame.distortion, cv2.INTER_LINEAR, cv2.BORDER_CONSTANT, self._pinhole[i]
            )
        return np.ascontiguousarray(resize(alpha, self.views[i].camera, cv2.INTER_AREA), dtype=np.float32)

    def _read_image(self, i: int) -> np.ndarray:
        frame = self._layout.frames[i]
        image = read_rgba(frame.image_path)
        height, width = image.shape[:2]
        cam = frame.camera
        if (width, height) != (cam.width, cam.height):
            raise SceneError(
                f"{frame.image_path}: image is {width}x{height} but its camera in "
                f"{self._layout.source} says {cam.width}x{cam.height}"
            )
        if frame.distortion is not None:
            image = undistort(
                image, cam, frame.distortion, cv2.INTER_LINEAR, cv2.BORDER_CONSTANT, self._pinhole[i]
            )
        if image.shape[2] == 4:  # undistorted first so that pixels from outside the frame turn white
            alpha = image[..., 3:]
            image = image[..., :3] * alpha + _WHITE * (1.0 - alpha)
        return np.ascontiguousarray(resize(image, self.views[i].camera, cv2.INTER_AREA), dtype=np.float32)

    def _align(self, i: int, array: np.ndarray, interpolation: int, border: int) -> np.ndarray:
        """A per-pixel map stored for the native image, undistorted and resized to working resolution."""
        frame = self._layout.frames[i]
        if frame.distortion is not None:
            native = resize(array, frame.camera, interpolation)
            array = undistort(native, frame.camera, frame.distortion, interpolation, border, self._pinhole[i])
        return resize(array, self.views[i].camera, interpolation)


def load_scene(
    path: str | Path,
    *,
    resolution: float = 1.0,
    views: Sequence[str | int] | None = None,
    n_views: int | None = None,
) -> Scene:
    """Read a scene folder (transforms.json, Blender pair, LLFF or COLMAP; see the module docstring).

    Training views: explicit `views` (names or indices) are the train split and every other view is
    test. Otherwise the frames' `split` fields, if any frame has one (fewer than 3 training views there
    must be confirmed by `n_views`, else SceneError). Otherwise `n_views` (default 3)
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
    layout = replace(layout, background=_WHITE.copy() if has_alpha(layout.frames[0].image_path) else None)
    return Scene(layout, _choose_splits(layout, views, n_views), float(resolution))


# ---------------------------------------------------------------------------------------------------
# Training-view choice


def _choose_splits(
    layout: Layout, views: Sequence[str | int] | None, n_views: int | None
) -> list[str | None]:
    if n_views is not None and (
        isinstance(n_views, bool) or not isinstance(n_views, numbers.Integral) or n_views < 1
    ):
        raise SceneError(f"n_views must be a positive integer, got {n_views!r}")
    if views is not None:
        return _explicit_splits(layout, views, n_views)
    file_splits = [f.split for f in layout.frames]
    has_splits = any(s is not None for s in file_splits)
    train = [f.name for f, s in zip(layout.frames, file_splits, strict=True) if s == "train"]
    if has_splits and n_views is not None and n_views == len(train):
        return file_splits  # the file's own training views, their number confirmed
    if has_splits and n_views is None:
        if 0 < len(train) < _DEFAULT_N_VIEWS:
            raise SceneError(
                f"{layout.source}: its split has {len(train)} training view(s) ({', '.join(train)}), fewer "
                f"than the {_DEFAULT_N_VIEWS} a run trains on; give n_views={len(train)} (--n-views "
                f"{len(train)}) to train on them on purpose"
            )
        return file_splits
    file_test = [i for i, s in enumerate(file_splits) if s == "test"]
    return _protocol_splits(layout, n_views or _DEFAULT_N_VIEWS, file_test or None)


def _explicit_splits(layout: Layout, views: Sequence[str | int], n_views: int | None) -> list[str | None]:
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
            raise SceneError(f"views: {layout.source} has no view {key!r}; known views: {listing(names)}")
        if index in chosen:
            raise SceneError(f"views: {key!r} names view {names[index]!r} a second time; give each view once")
        chosen.append(index)
    if not chosen:
        raise SceneError("views: no training views given")
    if n_views is not None and n_views != len(chosen):
        raise SceneError(f"n_views={n_views} disagrees with the {len(chosen)} views given")
    return ["train" if i in chosen else "test" for i in range(len(names))]


def _protocol_splits(layout: Layout, n_views: int, test: list[int] | None) -> list[str | None]:
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


def _read_layout(root: Path) -> Layout:
    if not root.is_dir():
        raise SceneError(f"{root}: scene folder not found")
    if (root / TRANSFORMS_FILE).is_file():
        return read_transforms(root)
    if (root / "transforms_train.json").is_file():
        return read_blender(root)
    if (root / "poses_bounds.npy").is_file():
        return read_llff(root)
    try:
        model = colmap.find_model(root)
    except colmap.ColmapError as e:
        raise SceneError(str(e)) from e
    if model is not None:
        return read_colmap(root, *model)
    raise SceneError(
        f"{root}: no scene found; looked for transforms.json, transforms_train.json, poses_bounds.npy "
        "and a COLMAP model (sparse/0/cameras.bin|txt with images.bin|txt)"
    )
