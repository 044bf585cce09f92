"""Scene preprocessing: the language feature cache and the depth prior of every view, from real models.

``langfield preprocess SCENE --models DIR`` runs, for every view of the scene:

- the segmenter and the CLIP image encoder (eq. 1, :func:`encoders.cache.build_feature_cache`) into
  ``language_features/<name>_f.npy`` and ``<name>_s.npy`` (docs/format.md), on the image as the scene gives
  it at full resolution (undistorted, alpha on white), which is how the trainer reads the cache;
- the monocular depth network into ``depths/<name>.npy``, float32 [H, W], on the image as stored
  (the scene undistorts depth maps when it reads them, as it does the image).

A view whose files already read back valid is skipped unless ``overwrite``; every file is written
atomically, so an interrupted run resumes where it stopped. The depth network's output kind goes into
``transforms.json`` as ``depth_kind`` when the file has none; a ``depth_kind`` already there is never
changed, and one that disagrees with the network is an error.

:func:`load_models` finds the exported models (``DIR/clip``, ``DIR/sam``, ``DIR/depth``, or one folder
each) or the classical graph segmenter.

Example:
    >>> m = load_models("models")  # doctest: +SKIP
    >>> report = preprocess_scene("data/room", m.segmenter, m.encoder, m.depth)  # doctest: +SKIP
    >>> report.seconds_per_image  # doctest: +SKIP
    {'segmenter': 4.1, 'encoder': 1.3, 'depth': 0.6}
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from tqdm.auto import tqdm

from encoders.cache import (
    FeatureCacheError,
    build_feature_cache,
    feature_cache_paths,
    read_feature_cache,
    write_feature_cache,
)
from encoders.protocols import DepthEstimator, ImageTextEncoder, Segmenter
from langfield.atomic import atomic_path
from langfield.constants import DEPTHS_DIR, FEATURES_DIR, TRANSFORMS_FILE
from langfield.io.scene import Scene, load_scene

__all__ = ["Models", "PreprocessError", "PreprocessReport", "load_models", "preprocess_scene"]

SegmenterName = Literal["sam", "graph"]
_DEFAULT_DEPTH_KIND = "disparity"  # what Scene assumes for depths/ without a depth_kind


class PreprocessError(ValueError):
    """A scene or model set that cannot be preprocessed; the message names the file or argument."""


@dataclass
class Models:
    """The models of one preprocessing run; a role is None when it is not run.

    Attributes:
        segmenter: masks at three levels (SAM or the graph segmenter).
        encoder: CLIP image (and text) encoder.
        depth: monocular depth network.
        sources: role -> the folder it was loaded from, or "graph".
    """

    segmenter: Segmenter | None = None
    encoder: ImageTextEncoder | None = None
    depth: DepthEstimator | None = None
    sources: dict[str, str] = field(default_factory=dict)


@dataclass
class PreprocessReport:
    """What one :func:`preprocess_scene` call did.

    Attributes:
        scene: the scene folder.
        views: every view visited, in scene order.
        features_written: views whose language features were computed (the rest were already done).
        depths_written: views whose depth prior was computed.
        seconds_per_image: model role ("segmenter", "encoder", "depth") -> mean seconds per image it
            processed; a role that processed no image is absent.
        num_masks: masks kept in the caches written (all levels).
        model_names: model role -> class name of the model that played it.
        depth_kind: the kind of depths/ after the run, or None without a depth model.
        depth_kind_recorded: the file ``depth_kind`` was added to, or None.
        seconds: wall time of the call.
    """

    scene: Path
    views: list[str]
    features_written: list[str] = field(default_factory=list)
    depths_written: list[str] = field(default_factory=list)
    seconds_per_image: dict[str, float] = field(default_factory=dict)
    num_masks: int = 0
    model_names: dict[str, str] = field(default_factory=dict)
    depth_kind: str | None = None
    depth_kind_recorded: Path | None = None
    seconds: float = 0.0

    def summary(self) -> str:
        """One line for the command's output."""
        rate, names = self.seconds_per_image, self.model_names
        parts = []
        if "segmenter" in rate:
            parts.append(
                f"language features of {len(self.features_written)} views ({self.num_masks} masks; "
                f"{names['segmenter']} {rate['segmenter']:.3g} s/image, "
                f"{names['encoder']} {rate['encoder']:.3g} s/image)"
            )
        if "depth" in rate:
            parts.append(
                f"{self.depth_kind} of {len(self.depths_written)} views "
                f"({names['depth']} {rate['depth']:.3g} s/image)"
            )
        done = ", ".join(parts) if parts else "every view was already done"
        recorded = f"; depth_kind recorded in {self.depth_kind_recorded}" if self.depth_kind_recorded else ""
        return (
            f"preprocessed {len(self.views)} views of {self.scene} in {self.seconds:.1f} s: {done}{recorded}"
        )


def load_models(
    models_dir: str | Path | None = None,
    *,
    clip: str | Path | None = None,
    sam: str | Path | None = None,
    depth: str | Path | None = None,
    segmenter: SegmenterName = "sam",
) -> Models:
    """Load the exported models of a preprocessing run.

    Each role comes from its own folder if given, else from ``models_dir/clip``, ``models_dir/sam``,
    ``models_dir/depth`` when that folder exists. ``segmenter="graph"`` uses the classical graph
    segmenter (no weights) instead of SAM. Language features need both a segmenter and CLIP; depth is
    optional.

    Args:
        models_dir: a folder holding ``clip/``, ``sam/`` and ``depth/`` exports.
        clip: folder of ``langfield export clip``.
        sam: folder of ``langfield export sam``.
        depth: folder of ``langfield export depth``.
        segmenter: "sam" or "graph".

    Returns:
        The loaded models.

    Raises:
        PreprocessError: no model at all, a segmenter without CLIP or CLIP without a segmenter, a
            missing ``models_dir``, or conflicting arguments; the message names the folder.
        ManifestError: a model folder without a valid manifest (names the file).
        ImportError: a runtime module missing from this install.
    """
    if segmenter not in ("sam", "graph"):
        raise PreprocessError(f"segmenter must be 'sam' or 'graph', got {segmenter!r}")
    root = None if models_dir is None else Path(models_dir)
    if root is not None and not root.is_dir():
        raise PreprocessError(f"{root}: models folder not found")
    if segmenter == "graph" and sam is not None:
        raise PreprocessError(f"--sam {sam} and --segmenter graph contradict each other; give one")

    def folder(given: str | Path | None, role: str) -> Path | None:
        if given is not None:
            return Path(given)
        if root is not None and (root / role).is_dir():
            return root / role
        return None

    clip_dir, sam_dir, depth_dir = folder(clip, "clip"), folder(sam, "sam"), folder(depth, "depth")
    where = f" in {root}" if root is not None else ""
    if clip_dir is None and segmenter == "graph":
        raise PreprocessError(f"--segmenter graph needs a CLIP model: no clip/ folder{where} and no --clip")
    if (clip_dir is None) != (sam_dir is None) and segmenter == "sam":
        have, lack = ("clip", "sam") if sam_dir is None else ("sam", "clip")
        raise PreprocessError(
            f"language features need a segmenter and CLIP: found {have} but no {lack}/ folder{where} and no "
            f"--{lack}" + (" (or pass --segmenter graph)" if lack == "sam" else "")
        )
    if clip_dir is None and depth_dir is None:
        raise PreprocessError(
            f"no models{where}: expected clip/, sam/ and depth/ folders from `langfield export`, "
            f"or --clip, --sam, --depth"
        )

    models = Models()
    if clip_dir is not None:
        from encoders.onnx_clip import OnnxClipEncoder

        models.encoder = OnnxClipEncoder(clip_dir)
        models.sources["encoder"] = str(clip_dir)
        if segmenter == "graph":
            models.segmenter = _runtime("encoders.classical", "GraphSegmenter")()
            models.sources["segmenter"] = "graph"
        else:
            models.segmenter = _runtime("encoders.onnx_sam", "OnnxSamSegmenter")(sam_dir)
            models.sources["segmenter"] = str(sam_dir)
    if depth_dir is not None:
        from encoders.onnx_depth import OnnxDepthEstimator

        models.depth = OnnxDepthEstimator(depth_dir)
        models.sources["depth"] = str(depth_dir)
    return models


def _runtime(module: str, name: str) -> Any:
    """``module.name``, imported when first needed, or an ImportError that says which is missing."""
    import importlib

    try:
        return getattr(importlib.import_module(module), name)
    except ModuleNotFoundError as exc:
        if exc.name == module:
            raise ImportError(f"{module}.{name} is not part of this langfield install ({exc})") from exc
        raise


def preprocess_scene(
    scene_dir: str | Path,
    segmenter: Segmenter | None,
    encoder: ImageTextEncoder | None,
    depth: DepthEstimator | None = None,
    overwrite: bool = False,
    progress: bool = True,
) -> PreprocessReport:
    """Write ``language_features/`` and ``depths/`` for every view of a scene (docs/format.md).

    Args:
        scene_dir: the scene folder (any layout :func:`~langfield.io.scene.load_scene` reads).
        segmenter: masks at three levels; None with ``encoder`` None to compute depth only.
        encoder: CLIP image encoder (eq. 1); its ``dim`` is the cache's D.
        depth: monocular depth network, or None for no depth prior.
        overwrite: recompute views whose files are already valid.
        progress: show a progress bar.

    Returns:
        The report (views written, seconds per image for each model).

    Raises:
        PreprocessError: nothing to compute, only one of segmenter / encoder, a ``depth_kind`` in the
            scene that disagrees with the depth model, or a model output of the wrong shape.
        SceneError: an unreadable scene (names the file).
    """
    t_start = time.perf_counter()
    scene, report, todo = plan_scene(scene_dir, segmenter, encoder, depth, overwrite)
    seconds = {"segmenter": 0.0, "encoder": 0.0, "depth": 0.0}
    with tqdm(total=len(report.views), desc="preprocess", unit="view", disable=not progress) as bar:
        for name in report.views:
            features, depth_map = todo.get(name, (False, False))
            done = preprocess_view(scene, name, segmenter, encoder, depth, features, depth_map)
            add_view(report, name, done, seconds)
            bar.set_postfix_str(name)
            bar.update()
    finish_report(report, seconds, t_start)
    return report


@dataclass
class ViewDone:
    """What :func:`preprocess_view` wrote for one view: masks kept (None: no features written), whether
    a depth map was written, and the seconds each model role took."""

    num_masks: int | None
    depth: bool
    seconds: dict[str, float]


def plan_scene(
    scene_dir: str | Path,
    segmenter: Segmenter | None,
    encoder: ImageTextEncoder | None,
    depth: DepthEstimator | None,
    overwrite: bool,
) -> tuple[Scene, PreprocessReport, dict[str, tuple[bool, bool]]]:
    """Checks the models and the scene, records ``depth_kind`` and finds what each view needs: (the
    scene, an empty report, {view: (features to compute, depth to compute)} for the views not done)."""
    if (segmenter is None) != (encoder is None):
        raise PreprocessError("preprocess_scene: language features need both a segmenter and an encoder")
    if segmenter is None and depth is None:
        raise PreprocessError("preprocess_scene: no model given (segmenter + encoder, and/or depth)")
    root = Path(scene_dir)
    scene = load_scene(root, views=[0])  # any split will do: every view is preprocessed
    names = scene.names("all")
    report = PreprocessReport(root, names)
    roles = {"segmenter": segmenter, "encoder": encoder, "depth": depth}
    report.model_names = {role: type(m).__name__ for role, m in roles.items() if m is not None}
    depth_todo = set() if depth is None else {n for n in names if overwrite or not _depth_done(scene, n)}
    if depth is not None:
        report.depth_kind, report.depth_kind_recorded = _record_depth_kind(scene, depth.kind, depth_todo)
    todo = {}
    for name in names:
        features = encoder is not None and (overwrite or not _features_done(scene, name, encoder.dim))
        if features or name in depth_todo:
            todo[name] = (features, name in depth_todo)
    return scene, report, todo


def preprocess_view(
    scene: Scene,
    name: str,
    segmenter: Segmenter | None,
    encoder: ImageTextEncoder | None,
    depth: DepthEstimator | None,
    features: bool,
    depth_map: bool,
) -> ViewDone:
    """Computes and writes one view's feature cache (``features``) and depth prior (``depth_map``)."""
    seconds = {}
    num_masks = None
    if features:
        timed_segmenter, timed_encoder = _TimedSegmenter(segmenter), _TimedEncoder(encoder)
        cache = build_feature_cache(scene.image(name), timed_segmenter, timed_encoder)
        write_feature_cache(scene.root / FEATURES_DIR, name, cache)
        num_masks = cache.num_masks
        seconds.update(segmenter=timed_segmenter.seconds, encoder=timed_encoder.seconds)
    if depth_map:
        t0 = time.perf_counter()
        prior = depth.estimate(scene.stored_image(name))
        seconds["depth"] = time.perf_counter() - t0
        _write_depth(scene, name, prior, type(depth).__name__)
    scene.forget_image(name)
    return ViewDone(num_masks, depth_map, seconds)


def add_view(report: PreprocessReport, name: str, done: ViewDone, seconds: dict[str, float]) -> None:
    """Adds one view's :class:`ViewDone` to the report and the per-role seconds."""
    if done.num_masks is not None:
        report.features_written.append(name)
        report.num_masks += done.num_masks
    if done.depth:
        report.depths_written.append(name)
    for role, t in done.seconds.items():
        seconds[role] += t


def finish_report(report: PreprocessReport, seconds: dict[str, float], t_start: float) -> None:
    """Seconds per image of each role that ran, in view order, and the wall time."""
    order = {n: i for i, n in enumerate(report.views)}
    report.features_written.sort(key=order.get)
    report.depths_written.sort(key=order.get)
    if report.features_written:
        n = len(report.features_written)
        report.seconds_per_image["segmenter"] = seconds["segmenter"] / n
        report.seconds_per_image["encoder"] = seconds["encoder"] / n
    if report.depths_written:
        report.seconds_per_image["depth"] = seconds["depth"] / len(report.depths_written)
    report.seconds = time.perf_counter() - t_start


class _TimedSegmenter:
    """A Segmenter that adds up the seconds spent in the wrapped one."""

    def __init__(self, inner: Segmenter) -> None:
        self.inner, self.seconds = inner, 0.0

    def segment(self, image: np.ndarray) -> list[np.ndarray]:
        t0 = time.perf_counter()
        try:
            return self.inner.segment(image)
        finally:
            self.seconds += time.perf_counter() - t0


class _TimedEncoder:
    """An ImageTextEncoder that adds up the seconds spent encoding images in the wrapped one."""

    def __init__(self, inner: ImageTextEncoder) -> None:
        self.inner, self.seconds = inner, 0.0
        self.dim, self.image_size = inner.dim, inner.image_size

    def encode_images(self, images: np.ndarray) -> np.ndarray:
        t0 = time.perf_counter()
        try:
            return self.inner.encode_images(images)
        finally:
            self.seconds += time.perf_counter() - t0

    def encode_text(self, phrases: Any) -> np.ndarray:
        return self.inner.encode_text(phrases)


def _hw(scene: Scene, name: str) -> tuple[int, int]:
    cam = scene.camera(name)  # resolution 1: the stored image's size
    return cam.height, cam.width


def _features_done(scene: Scene, name: str, dim: int) -> bool:
    """Both cache files exist and read back valid at the image's size and the encoder's dimension."""
    f_path, s_path = feature_cache_paths(scene.root / FEATURES_DIR, name)
    if not (f_path.is_file() and s_path.is_file()):
        return False
    try:
        return read_feature_cache(f_path, s_path, dim=dim).hw == _hw(scene, name)
    except FeatureCacheError:
        return False


def _depth_path(scene: Scene, name: str) -> Path:
    return scene.root / DEPTHS_DIR / f"{name}.npy"


def _depth_done(scene: Scene, name: str) -> bool:
    """The depth file exists and is a finite float [H, W] map of the image's size."""
    path = _depth_path(scene, name)
    if not path.is_file():
        return False
    try:
        arr = np.load(path, allow_pickle=False)
    except (OSError, ValueError):
        return False
    return (
        arr.shape == _hw(scene, name)
        and np.issubdtype(arr.dtype, np.floating)
        and bool(np.isfinite(arr).all())
    )


def _write_depth(scene: Scene, name: str, prior: np.ndarray, who: str) -> None:
    arr = np.asarray(prior)
    hw = _hw(scene, name)
    if arr.shape != hw or not np.issubdtype(arr.dtype, np.floating) or not np.isfinite(arr).all():
        raise PreprocessError(
            f"{who}.estimate returned {arr.dtype} {arr.shape} for view {name!r}; expected finite float {hw}"
        )
    # A file handle, so np.save does not append ".npy".
    with atomic_path(_depth_path(scene, name)) as tmp, open(tmp, "wb") as fh:
        np.save(fh, arr.astype(np.float32), allow_pickle=False)


def _record_depth_kind(scene: Scene, kind: str, todo: set[str]) -> tuple[str, Path | None]:
    """Check the scene's depth_kind against the model's and add it to the scene's JSON if absent.

    Runs before any depth map is written, so a run interrupted later still has its kind recorded.

    Returns:
        (the kind, the file it was added to or None).
    """
    root = scene.root
    source = next(
        (root / n for n in (TRANSFORMS_FILE, "transforms_train.json") if (root / n).is_file()), None
    )
    meta = _read_json(source) if source is not None else {}
    if "depth_kind" in meta:
        if meta["depth_kind"] != kind:
            raise PreprocessError(
                f"{source}: depth_kind is {meta['depth_kind']!r} but the depth model outputs {kind!r}; "
                f"the maps in {root / DEPTHS_DIR} would disagree with it (move them away and remove the key, "
                f"or use a {meta['depth_kind']} model)"
            )
        return kind, None
    kept = [n for n in scene.names("all") if n not in todo and _depth_path(scene, n).is_file()]
    if kept and kind != _DEFAULT_DEPTH_KIND:
        raise PreprocessError(
            f"{root / DEPTHS_DIR}: holds maps without a depth_kind (read as {_DEFAULT_DEPTH_KIND}), e.g. "
            f"{kept[0]}.npy, but the depth model outputs {kind!r}; pass --overwrite to replace them all"
        )
    if source is None:
        if kind != _DEFAULT_DEPTH_KIND:
            raise PreprocessError(
                f"{root}: has no transforms.json to record depth_kind {kind!r} in; this layout's depth "
                f"maps are read as {_DEFAULT_DEPTH_KIND}, so use a disparity model"
            )
        return kind, None
    meta["depth_kind"] = kind
    with atomic_path(source) as tmp:
        tmp.write_text(json.dumps(meta, indent=2, ensure_ascii=False) + "\n")
    return kind, source


def _read_json(path: Path) -> dict:
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise PreprocessError(f"{path}: cannot read JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise PreprocessError(f"{path}: expected a JSON object")
    return meta
