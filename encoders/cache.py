"""The per-view language feature cache: LangSplat's ``language_features/`` layout (docs/format.md).

One view's cache is two files:

- ``<name>_f.npy``: float [M, D], one CLIP feature per mask (D = 512 for OpenCLIP ViT-B-16);
- ``<name>_s.npy``: int [L, H, W] segment maps; a value is a row of ``_f.npy``, -1 = no mask there.

L is 3 (subpart, part, whole). A LangSplat cache has L = 4 (default, s, m, l) and is read by dropping
level 0. This module reads and validates such caches (:func:`read_feature_cache`), writes them
atomically (:func:`write_feature_cache`) and builds them from any Segmenter and ImageTextEncoder with
eq. 1 of the paper (:func:`build_feature_cache`, :func:`build_scene_cache`).

Every bad cache raises :class:`FeatureCacheError` naming the file and what is wrong; nothing is guessed
silently.

Example:
    >>> from encoders.stubs import StubImageTextEncoder, StubSegmenter
    >>> image = np.random.default_rng(0).random((24, 32, 3), dtype=np.float32)
    >>> cache = build_feature_cache(image, StubSegmenter(), StubImageTextEncoder(image_size=32))
    >>> cache.segments.shape, cache.dim
    ((3, 24, 32), 512)
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm.auto import tqdm

from encoders.protocols import LEVELS, ImageTextEncoder, Segmenter, check_image

__all__ = [
    "UNIT_NORM_TOL",
    "ZERO_NORM",
    "FeatureCache",
    "FeatureCacheError",
    "build_feature_cache",
    "build_scene_cache",
    "feature_cache_paths",
    "mask_crop",
    "read_feature_cache",
    "write_feature_cache",
]

# |norm - 1| allowed for a mask feature; rows normalised in float16 as LangSplat does stay below 4e-4.
UNIT_NORM_TOL = 1e-3
ZERO_NORM = 1e-3  # a row shorter than this is an empty slot, not a feature
_ASPECT_TOL = 0.01  # segment maps at another size are resized only if the aspect ratio agrees this well
_LANGSPLAT_LEVELS = 4  # default, s, m, l (LangSplat preprocess.py)


class FeatureCacheError(ValueError):
    """A feature cache that cannot be used; the message names the file and what is wrong."""


@dataclass
class FeatureCache:
    """The language supervision of one view: mask features and, per level, which mask covers a pixel.

    Construction checks the invariants below and coerces dtypes (features to float32, segments to
    int32); it raises ValueError otherwise.

    Attributes:
        features: [M, D] float32 mask features; every row used by ``segments`` is a unit vector.
        segments: [3, H, W] int32, level order LEVELS (subpart, part, whole); a value is a row of
            ``features``, -1 = no mask at that pixel and level.

    Example:
        >>> cache = FeatureCache(np.eye(2, 4, dtype=np.float32), np.full((3, 2, 2), -1, np.int32))
        >>> cache.segments[2, 0] = 1
        >>> ids, masks = cache.masks("whole"); ids.tolist(), masks.shape
        ([1], (1, 2, 2))
    """

    features: np.ndarray
    segments: np.ndarray

    def __post_init__(self) -> None:
        f = np.asarray(self.features)
        s = np.asarray(self.segments)
        if f.ndim != 2 or not np.issubdtype(f.dtype, np.floating):
            raise ValueError(f"FeatureCache: features must be float [M, D], got {f.dtype} {f.shape}")
        if s.ndim != 3 or s.shape[0] != len(LEVELS) or not np.issubdtype(s.dtype, np.integer):
            raise ValueError(f"FeatureCache: segments must be int [3, H, W], got {s.dtype} {s.shape}")
        if s.size and (s.min() < -1 or s.max() >= f.shape[0]):
            raise ValueError(
                f"FeatureCache: segment values must lie in [-1, {f.shape[0] - 1}], got [{s.min()}, {s.max()}]"
            )
        self.features = f.astype(np.float32, copy=False)
        self.segments = s.astype(np.int32, copy=False)
        used = np.unique(self.segments[self.segments >= 0])
        norms = np.linalg.norm(self.features[used].astype(np.float64), axis=1)
        bad = np.flatnonzero(~(np.abs(norms - 1.0) <= UNIT_NORM_TOL))  # also catches NaN
        if bad.size:
            raise ValueError(
                f"FeatureCache: row {used[bad[0]]} is used by segments but has norm {norms[bad[0]]:.4g}, "
                f"not 1"
            )

    @property
    def hw(self) -> tuple[int, int]:
        """(H, W) of the segment maps."""
        return int(self.segments.shape[1]), int(self.segments.shape[2])

    @property
    def dim(self) -> int:
        """D, the feature dimension."""
        return int(self.features.shape[1])

    @property
    def num_masks(self) -> int:
        """M, the number of feature rows."""
        return int(self.features.shape[0])

    def masks(self, level: int | str) -> tuple[np.ndarray, np.ndarray]:
        """The masks of one level as the segment map draws them.

        Args:
            level: 0, 1, 2 or "subpart", "part", "whole".

        Returns:
            ids [K] int64 rows of ``features`` present at this level (ascending), and masks [K, H, W]
            bool, masks[k] = the pixels whose segment is ids[k] (disjoint within a level).
        """
        seg = self.segments[_level_index(level)]
        ids = np.unique(seg[seg >= 0]).astype(np.int64)
        return ids, seg[None] == ids[:, None, None]

    def pixel_features(self, level: int | str) -> tuple[np.ndarray, np.ndarray]:
        """Per-pixel target features E^l of one level (the L_LF target).

        Args:
            level: 0, 1, 2 or "subpart", "part", "whole".

        Returns:
            features [H, W, D] float32 (zero where no mask) and valid [H, W] bool.
        """
        seg = self.segments[_level_index(level)]
        valid = seg >= 0
        out = np.zeros(seg.shape + (self.dim,), dtype=np.float32)
        out[valid] = self.features[seg[valid]]
        return out, valid


def _level_index(level: int | str) -> int:
    if isinstance(level, str):
        if level not in LEVELS:
            raise ValueError(f"unknown level {level!r}; expected one of {LEVELS}")
        return LEVELS.index(level)
    if not 0 <= int(level) < len(LEVELS):
        raise ValueError(f"level must be in 0..{len(LEVELS) - 1}, got {level}")
    return int(level)


# ----------------------------------------------------------------------------------------- reading


def feature_cache_paths(folder: str | Path, name: str) -> tuple[Path, Path]:
    """(``<folder>/<name>_f.npy``, ``<folder>/<name>_s.npy``) of one view."""
    if not name or name in (".", "..") or "/" in name or os.sep in name:
        raise ValueError(f"feature cache: view name must be a plain file stem, got {name!r}")
    folder = Path(folder)
    return folder / f"{name}_f.npy", folder / f"{name}_s.npy"


def read_feature_cache(
    f_path: str | Path,
    s_path: str | Path,
    *,
    expected_hw: tuple[int, int] | None = None,
    dim: int | None = None,
) -> FeatureCache:
    """Read and validate one view's cache (docs/format.md ``language_features/``).

    Accepted beyond the plain 3-level layout, each as LangSplat writes it:

    - L = 4 (default, s, m, l): level 0 is dropped.
    - ``_s`` stored as float with whole-number values (LangSplat's preprocess.py fills a float32 torch
      tensor and saves it as is); any fractional value is rejected.
    - Rows of norm below ZERO_NORM that no pixel uses (empty slots).

    The result is normalised so that downstream code can use ``features`` wholesale: rows that no kept
    level uses (empty slots, rows of a dropped level 0, masks hidden by others) are removed and the
    segment values renumbered, keeping their order; rows are rescaled to unit norm exactly.

    Args:
        f_path: ``<name>_f.npy``, float [M, D].
        s_path: ``<name>_s.npy``, integer [L, H, W], L in {3, 4}, values in [-1, M).
        expected_hw: (H, W) of the view's image. Segment maps of another size are resized by nearest
            neighbour when the aspect ratios agree within 1 % (LangSplat caches of downscaled
            images), and rejected otherwise.
        dim: the feature dimension D required (e.g. the text encoder's).

    Returns:
        The cache with 3 levels.

    Raises:
        FeatureCacheError: a file is missing or unreadable; a wrong ndim, dtype, level count, size or
            dimension; a segment value below -1 or not a row of ``_f``; a NaN or inf row; a row whose
            norm differs from 1 by more than UNIT_NORM_TOL (unless it is a zero row no pixel uses).
    """
    f_path, s_path = Path(f_path), Path(s_path)
    f = _load_npy(f_path, "mask features")
    s = _load_npy(s_path, "segment maps")

    if f.ndim != 2:
        raise FeatureCacheError(f"{f_path}: mask features must be 2-D [M, D], got shape {f.shape}")
    if not np.issubdtype(f.dtype, np.floating):
        raise FeatureCacheError(f"{f_path}: mask features must be float, got dtype {f.dtype}")
    m, d = f.shape
    if dim is not None and d != dim:
        raise FeatureCacheError(f"{f_path}: features have dimension {d}, but the encoder's is {dim}")

    if s.ndim != 3:
        raise FeatureCacheError(f"{s_path}: segment maps must be 3-D [L, H, W], got shape {s.shape}")
    n_levels, h, w = s.shape
    if n_levels not in (len(LEVELS), _LANGSPLAT_LEVELS):
        raise FeatureCacheError(
            f"{s_path}: has {n_levels} levels; expected 3 (subpart, part, whole) "
            f"or 4 (a LangSplat cache: default, s, m, l)"
        )
    if h == 0 or w == 0:
        raise FeatureCacheError(f"{s_path}: segment maps are empty, shape {s.shape}")
    s = _integer_segments(s, s_path)
    _check_segment_values(s, s_path, f_path, m)

    first = n_levels - len(LEVELS)  # 1 for LangSplat's 4 levels: drop "default"
    kept = s[first:]
    used = np.zeros(m, dtype=bool)
    used[kept[kept >= 0]] = True
    used_all = np.zeros(m, dtype=bool)  # rows used by any level of the file, the dropped one included
    used_all[s[s >= 0]] = True
    norms = _check_rows(f, f_path, s_path, used_all)

    if expected_hw is not None and (h, w) != tuple(expected_hw):
        kept = _resize_segments(kept, tuple(int(v) for v in expected_hw), s_path)
        used = np.zeros(m, dtype=bool)
        used[kept[kept >= 0]] = True

    # Compact: keep the used rows in order and renumber the maps to match.
    new_id = np.full(m + 1, -1, dtype=np.int64)  # slot m maps -1 to -1 via index -1
    new_id[np.flatnonzero(used)] = np.arange(int(used.sum()))
    features = (f[used].astype(np.float64) / norms[used, None]).astype(np.float32)
    segments = new_id[kept].astype(np.int32)
    return FeatureCache(features.reshape(-1, d), segments)


def _load_npy(path: Path, what: str) -> np.ndarray:
    if not path.is_file():
        raise FeatureCacheError(
            f"{path}: missing; a view's feature cache needs both <name>_f.npy and <name>_s.npy ({what})"
        )
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as err:
        raise FeatureCacheError(f"{path}: cannot read as a .npy array of {what} ({err})") from err


def _integer_segments(s: np.ndarray, s_path: Path) -> np.ndarray:
    """Segment maps as int64; float maps pass only if every value is a whole number."""
    if np.issubdtype(s.dtype, np.integer):
        return s.astype(np.int64, copy=False)
    if np.issubdtype(s.dtype, np.floating):
        bad = ~np.isfinite(s) | (s != np.round(s))
        if bad.any():
            lvl, y, x = (int(v) for v in np.argwhere(bad)[0])
            raise FeatureCacheError(
                f"{s_path}: segment maps must hold integer row indices (-1 = no mask), but this {s.dtype} "
                f"map holds {s[lvl, y, x]!r} at level {lvl}, pixel (y={y}, x={x})"
            )
        return s.astype(np.int64)
    raise FeatureCacheError(f"{s_path}: segment maps must be integers (row indices), got dtype {s.dtype}")


def _check_segment_values(s: np.ndarray, s_path: Path, f_path: Path, m: int) -> None:
    low = s < -1
    if low.any():
        lvl, y, x = (int(v) for v in np.argwhere(low)[0])
        raise FeatureCacheError(
            f"{s_path}: segment value {s[lvl, y, x]} at level {lvl}, pixel (y={y}, x={x}) is below -1 "
            f"(-1 = no mask, otherwise a row of {f_path.name})"
        )
    high = s >= m
    if high.any():
        lvl, y, x = (int(v) for v in np.argwhere(high)[0])
        raise FeatureCacheError(
            f"{s_path}: segment value {s[lvl, y, x]} at level {lvl}, pixel (y={y}, x={x}) is not a row of "
            f"{f_path.name}, which has {m} rows (values must lie in -1..{m - 1})"
        )


def _check_rows(f: np.ndarray, f_path: Path, s_path: Path, used: np.ndarray) -> np.ndarray:
    """[M] float64 row norms, after rejecting non-finite rows, used zero rows and non-unit rows."""
    finite = np.isfinite(f).all(axis=1)
    if not finite.all():
        row = int(np.flatnonzero(~finite)[0])
        raise FeatureCacheError(f"{f_path}: row {row} has NaN or inf values")
    norms = np.linalg.norm(f.astype(np.float64), axis=1)
    zero = norms < ZERO_NORM
    if (zero & used).any():
        row = int(np.flatnonzero(zero & used)[0])
        raise FeatureCacheError(
            f"{f_path}: row {row} is a zero vector (norm {norms[row]:.3g}) but {s_path.name} assigns it to "
            f"pixels; a used mask feature must be a unit vector"
        )
    off = ~zero & (np.abs(norms - 1.0) > UNIT_NORM_TOL)
    if off.any():
        row = int(np.flatnonzero(off)[0])
        raise FeatureCacheError(
            f"{f_path}: row {row} has norm {norms[row]:.6g}; mask features must be unit vectors "
            f"(|norm - 1| <= {UNIT_NORM_TOL:g}); were they L2-normalised?"
        )
    return norms


def _resize_segments(seg: np.ndarray, hw: tuple[int, int], s_path: Path) -> np.ndarray:
    """[L, h, w] -> [L, H, W] by nearest neighbour, if the aspect ratios agree within _ASPECT_TOL."""
    _, h, w = seg.shape
    th, tw = hw
    if th < 1 or tw < 1:
        raise FeatureCacheError(f"{s_path}: expected image size must be positive, got {tw}x{th}")
    if abs((w / h) / (tw / th) - 1.0) > _ASPECT_TOL:
        raise FeatureCacheError(
            f"{s_path}: segment maps are {w}x{h} (WxH) but the image is {tw}x{th}; their aspect ratios "
            f"differ by more than {_ASPECT_TOL:.0%}, so the maps cannot belong to this image"
        )
    # Pixel centres of the target sampled in the source grid: the nearest-neighbour rule of cv2.
    ys = np.minimum(((np.arange(th) + 0.5) * h / th).astype(np.int64), h - 1)
    xs = np.minimum(((np.arange(tw) + 0.5) * w / tw).astype(np.int64), w - 1)
    return seg[:, ys[:, None], xs[None, :]]


# ----------------------------------------------------------------------------------------- writing


def write_feature_cache(folder: str | Path, name: str, cache: FeatureCache) -> tuple[Path, Path]:
    """Write ``<name>_f.npy`` (float32) and ``<name>_s.npy`` (int32) atomically.

    Each file is written under a temporary name and renamed (os.replace), so an interrupted write
    never leaves a truncated file; ``_s`` is renamed last.

    Args:
        folder: the ``language_features/`` folder; created if missing.
        name: the view's name (image file name without extension).
        cache: the view's cache.

    Returns:
        The paths written, (f_path, s_path).
    """
    f_path, s_path = feature_cache_paths(folder, name)
    f_path.parent.mkdir(parents=True, exist_ok=True)
    for path, array in (
        (f_path, cache.features.astype(np.float32)),
        (s_path, cache.segments.astype(np.int32)),
    ):
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "wb") as fh:  # a file handle, so np.save does not append ".npy"
                np.save(fh, array, allow_pickle=False)
            os.replace(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
    return f_path, s_path


# ---------------------------------------------------------------------------------------- building


def mask_crop(image: np.ndarray, mask: np.ndarray, size: int) -> np.ndarray:
    """The CLIP input of one mask (eq. 1; LangSplat preprocess.py ``get_seg_img`` + ``pad_img``).

    Pixels outside the mask are blacked out, the mask's bounding box is cropped, padded with black to
    a square with the crop centred, and resized to ``size`` (INTER_AREA when shrinking, which
    averages instead of aliasing; INTER_LINEAR when enlarging). The box includes its last row and
    column: LangSplat slices SAM's XYWH box as ``[y:y+h]``, which drops them and empties a one-pixel
    mask.

    Args:
        image: [H, W, 3] float32 RGB in [0, 1].
        mask: [H, W] bool, at least one pixel set.
        size: side S of the output (encoder.image_size).

    Returns:
        [S, S, 3] float32.
    """
    ys, xs = np.nonzero(mask)
    if ys.size == 0:
        raise ValueError("mask_crop: the mask is empty")
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    crop = np.where(mask[y0:y1, x0:x1, None], image[y0:y1, x0:x1], 0.0).astype(np.float32)
    h, w = crop.shape[:2]
    side = max(h, w)
    square = np.zeros((side, side, 3), dtype=np.float32)
    top, left = (side - h) // 2, (side - w) // 2
    square[top : top + h, left : left + w] = crop
    if side == size:
        return square
    interpolation = cv2.INTER_AREA if side > size else cv2.INTER_LINEAR
    return cv2.resize(square, (size, size), interpolation=interpolation)


def build_feature_cache(
    image: np.ndarray, segmenter: Segmenter, encoder: ImageTextEncoder, *, batch_size: int = 32
) -> FeatureCache:
    """Segment one image and encode every mask with eq. 1 (LangSplat's preprocessing).

    At each level the masks are drawn into the segment map largest first, so where masks of a level
    overlap the smaller one wins: a small mask keeps its own feature instead of vanishing under a
    large one. (LangSplat's ``mask2segmap`` draws in SAM's score order, after a mask NMS that removes
    most nested pairs; area order gives the same maps when masks do not overlap and does not depend
    on scores, which a Segmenter does not return.) Between masks of equal area the later one in the
    segmenter's order wins. Empty masks, and masks whose every pixel a smaller mask covers, get no
    row. Rows are ordered by level, then by the segmenter's mask order.

    Args:
        image: [H, W, 3] float32 RGB in [0, 1].
        segmenter: gives 3 levels of [M_l, H, W] bool masks.
        encoder: embeds [B, S, S, 3] crops, S = encoder.image_size, into [B, D] rows.
        batch_size: crops per encoder call.

    Returns:
        The view's cache: features [M, D] unit rows, segments [3, H, W].
    """
    img = check_image(image, "build_feature_cache")
    if batch_size < 1:
        raise ValueError(f"build_feature_cache: batch_size must be >= 1, got {batch_size}")
    h, w, _ = img.shape
    levels = _checked_levels(segmenter.segment(img), (h, w), type(segmenter).__name__)

    segments = np.full((len(LEVELS), h, w), -1, dtype=np.int32)
    kept_masks: list[np.ndarray] = []
    for lvl, masks in enumerate(levels):
        owner = np.full((h, w), -1, dtype=np.int64)  # index into this level's masks
        areas = masks.sum(axis=(1, 2))
        for k in np.argsort(-areas, kind="stable"):  # largest first, so smaller ones overwrite
            if areas[k] > 0:
                owner[masks[k]] = k
        survivors = np.unique(owner[owner >= 0])  # ascending = the segmenter's order
        row_of = np.full(len(masks) + 1, -1, dtype=np.int64)
        row_of[survivors] = len(kept_masks) + np.arange(len(survivors))
        segments[lvl] = row_of[owner]
        kept_masks.extend(masks[k] for k in survivors)

    size = int(encoder.image_size)
    dim = int(encoder.dim)
    features = np.zeros((len(kept_masks), dim), dtype=np.float32)
    crops = (mask_crop(img, mask, size) for mask in kept_masks)
    for start, batch in _batches(crops, batch_size):
        features[start : start + len(batch)] = _encode(encoder, np.stack(batch), start, dim)
    return FeatureCache(features, segments)


def _checked_levels(levels: Sequence[np.ndarray], hw: tuple[int, int], who: str) -> list[np.ndarray]:
    """The segmenter's output as 3 bool arrays [M_l, H, W], or a ValueError naming the level."""
    if len(levels) != len(LEVELS):
        raise ValueError(f"{who}.segment returned {len(levels)} levels; expected 3 {LEVELS}")
    out = []
    for name, masks in zip(LEVELS, levels, strict=True):
        arr = np.asarray(masks)
        if arr.ndim != 3 or arr.shape[1:] != hw:
            raise ValueError(
                f"{who}.segment: {name} masks must have shape [M, {hw[0]}, {hw[1]}], got {arr.shape}"
            )
        out.append(arr if arr.dtype == bool else arr != 0)
    return out


def _batches(items: Iterator[np.ndarray], size: int) -> Iterator[tuple[int, list[np.ndarray]]]:
    """(start index, list of up to `size` items), so only one batch of crops is in memory at a time."""
    batch: list[np.ndarray] = []
    start = 0
    for item in items:
        batch.append(item)
        if len(batch) == size:
            yield start, batch
            start, batch = start + size, []
    if batch:
        yield start, batch


def _encode(encoder: ImageTextEncoder, crops: np.ndarray, start: int, dim: int) -> np.ndarray:
    """[B, D] unit rows of one batch; a wrong shape, NaN or zero row from the encoder is an error."""
    who = type(encoder).__name__
    out = np.asarray(encoder.encode_images(crops), dtype=np.float64)
    if out.shape != (len(crops), dim):
        raise ValueError(f"{who}.encode_images returned shape {out.shape} for {len(crops)} crops, dim {dim}")
    norms = np.linalg.norm(out, axis=1, keepdims=True)
    bad = ~np.isfinite(norms[:, 0]) | (norms[:, 0] < ZERO_NORM)
    if bad.any():
        raise ValueError(
            f"{who}.encode_images returned a NaN, inf or zero row for mask {start + bad.argmax()}"
        )
    return (out / norms).astype(np.float32)


def build_scene_cache(
    images: Mapping[str, np.ndarray],
    folder: str | Path,
    segmenter: Segmenter,
    encoder: ImageTextEncoder,
    *,
    skip_existing: bool = True,
    progress: bool = True,
    batch_size: int = 32,
) -> dict[str, float]:
    """Build and write the cache of every view, with a progress bar.

    A view is skipped when ``skip_existing`` and its cache already reads back valid at the image's
    size and the encoder's dimension; an invalid or mismatched cache is rebuilt.

    Args:
        images: view name -> [H, W, 3] float32 RGB in [0, 1] (a lazy Mapping works: an image is only
            read when its view is visited).
        folder: the ``language_features/`` folder.
        segmenter: gives the masks.
        encoder: embeds the crops.
        skip_existing: keep views whose valid cache exists.
        progress: show a tqdm bar.
        batch_size: crops per encoder call.

    Returns:
        Seconds spent per view built (skipped views are absent).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    with tqdm(total=len(images), desc="language features", unit="view", disable=not progress) as bar:
        for name in images:
            image = images[name]
            f_path, s_path = feature_cache_paths(folder, name)
            if skip_existing and _valid_cache(f_path, s_path, np.shape(image)[:2], encoder.dim):
                bar.set_postfix_str(f"{name}: kept")
                bar.update()
                continue
            t0 = time.perf_counter()
            cache = build_feature_cache(image, segmenter, encoder, batch_size=batch_size)
            write_feature_cache(folder, name, cache)
            seconds[name] = time.perf_counter() - t0
            bar.set_postfix_str(f"{name}: {cache.num_masks} masks")
            bar.update()
    return seconds


def _valid_cache(f_path: Path, s_path: Path, hw: tuple[int, ...], dim: int) -> bool:
    """Whether both files exist and read back valid at exactly this size and dimension."""
    if not (f_path.is_file() and s_path.is_file()):
        return False
    try:
        return read_feature_cache(f_path, s_path, dim=dim).hw == tuple(hw)
    except FeatureCacheError:
        return False
