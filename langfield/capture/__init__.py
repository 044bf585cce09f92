"""From a person's own photos or video to a scene folder: frames, poses, training views.

:func:`capture` reads a folder of photos or a video (:mod:`langfield.capture.frames`), poses the
frames with COLMAP (:mod:`langfield.capture.poses`), normalises them as nerfstudio does and chooses
training views for spread (:mod:`langfield.capture.views`), and writes an ordinary scene folder that
``load_scene``, ``langfield train``, ``preprocess``, ``eval`` and ``view`` read
(:mod:`langfield.capture.scene_folder`), with ``capture.json``, the capture's report. The folder is
built beside OUT and moved into place at the end: an interrupted capture leaves no half scene.

Example:
    >>> report = capture("my_photos/", "my_scene/")  # doctest: +SKIP
    >>> report["scene"]["train"]  # doctest: +SKIP
    ['IMG_0012', 'IMG_0019', 'IMG_0031']
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from langfield.atomic import check_writable_folder
from langfield.capture.frames import (
    CaptureInputError,
    FrameChoice,
    InputSummary,
    focal_pixels,
    inspect_input,
    store_photos,
    stored_size,
    video_frames,
)
from langfield.capture.poses import MIN_FRAMES, PoseModel, PoseResult, Progress, solve_poses
from langfield.capture.scene_folder import write_scene
from langfield.capture.views import normalise, spread_views

__all__ = ["REPORT_FILE", "CaptureError", "CaptureOptions", "capture"]

REPORT_FILE = "capture.json"
OTHER_MODELS_DIR = "other_models"


class CaptureError(ValueError):
    """The frames could not be posed well enough for a scene; the message says why and what to try."""


@dataclass(frozen=True)
class CaptureOptions:
    """Settings of :func:`capture` (each is a flag of ``langfield capture``; docs/capture.md).

    Attributes:
        frames: how many frames to keep from a video (photos are all kept).
        max_size: longer side, in pixels, of the stored frames (never enlarged).
        camera: one camera for every frame ("single"), one per frame ("per-image"), or "auto": single
            for a video and for photos of one size, per-image otherwise.
        matching: "exhaustive", "sequential" (with keyframe loops), or "auto": sequential for a video,
            exhaustive for photos.
        train_views: how many training views to choose for spread.
        views: the training views by name instead (file stems; a video's frames are named by time).
        all_models: also write every smaller model, one scene each, under ``other_models/``.
        force: replace an existing OUT.
        verbose: COLMAP's own log on the terminal.
    """

    frames: int = 48
    max_size: int = 1008
    camera: Literal["auto", "single", "per-image"] = "auto"
    matching: Literal["auto", "exhaustive", "sequential"] = "auto"
    train_views: int = 3
    views: tuple[str, ...] | None = None
    all_models: bool = False
    force: bool = False
    verbose: bool = False


def _no_bar(stage: str, total: int) -> Callable[[int], None]:
    return lambda n: None


def check_options(options: CaptureOptions) -> None:
    """Refuses settings that cannot work whatever the input, naming the flag."""
    if options.frames < MIN_FRAMES:
        raise CaptureInputError(f"--frames must be at least {MIN_FRAMES}, got {options.frames}")
    if options.max_size < 64:
        raise CaptureInputError(f"--max-size must be at least 64 pixels, got {options.max_size}")
    if options.train_views < 1:
        raise CaptureInputError(f"--train-views must be at least 1, got {options.train_views}")
    if options.camera not in ("auto", "single", "per-image"):
        raise CaptureInputError(f"--camera must be auto, single or per-image, got {options.camera!r}")
    if options.matching not in ("auto", "exhaustive", "sequential"):
        raise CaptureInputError(
            f"--matching must be auto, exhaustive or sequential, got {options.matching!r}"
        )
    if options.views is not None:
        if not options.views:
            raise CaptureInputError("--views: no view named")
        twice = sorted({v for v in options.views if options.views.count(v) > 1})
        if twice:
            raise CaptureInputError(f"--views names {', '.join(twice)} more than once")


def _check_options_for(options: CaptureOptions, summary: InputSummary) -> None:
    """Refuses settings that the input cannot meet: photo names, one camera for photos of several sizes."""
    if summary.kind == "photos" and options.views is not None:
        unknown = [v for v in options.views if v not in summary.names]
        if unknown:
            raise CaptureInputError(
                f"--views: no photo named {', '.join(unknown)} in {summary.paths[0].parent}"
            )
    if summary.kind == "photos" and options.camera == "single" and len(set(summary.sizes)) > 1:
        sizes = sorted({f"{w}x{h}" for w, h in summary.sizes})
        raise CaptureInputError(
            f"--camera single: the photos have {len(sizes)} sizes ({', '.join(sizes)}); "
            "use --camera per-image"
        )


def capture(
    source: str | Path,
    out: str | Path,
    options: CaptureOptions = CaptureOptions(),
    *,
    progress: Progress = _no_bar,
) -> dict:
    """Poses the photos or video at ``source`` and writes the scene folder ``out``.

    Everything is checked before any work: the input (every photo decoded, the video opened), the
    options, and ``out`` (new, or ``options.force``).

    Args:
        source: a folder of photos or a video file.
        out: the scene folder to write.
        options: :class:`CaptureOptions`.
        progress: ``progress(stage, total)`` returns a function that advances that stage's bar.

    Returns:
        The report, also written as ``out/capture.json``.

    Raises:
        CaptureInputError: unusable input, option or output folder (before any work).
        CaptureError: fewer than 3 frames could be posed together; the message says what to try.
    """
    start = time.perf_counter()
    source, out = Path(source), Path(out)
    check_options(options)
    summary = inspect_input(source)
    _check_options_for(options, summary)
    _check_out(out, options.force, source)
    staging = out.parent / f".{out.name}.capture-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    try:
        report = _run(summary, staging, options, progress, start)
        _move_into_place(staging / "scene", out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return report


def _check_out(out: Path, force: bool, source: Path) -> None:
    check_writable_folder(out, "scene")
    if source.resolve() == out.resolve() or out.resolve() in source.resolve().parents:
        raise CaptureInputError(f"{out}: holds the input {source}; give another --out")
    if out.exists() and not force and (not out.is_dir() or any(out.iterdir())):
        raise CaptureInputError(f"{out}: already exists; give --force to replace it")


def _run(
    summary: InputSummary, staging: Path, options: CaptureOptions, progress: Progress, start: float
) -> dict:
    seconds: dict[str, float] = {}
    frames_dir = staging / "frames"
    frames_dir.mkdir(parents=True)
    t0 = time.perf_counter()
    names, choice = _frames(summary, frames_dir, options, progress)
    seconds["frames"] = time.perf_counter() - t0
    files = [f"{n}.png" for n in names]
    stems = dict(zip(files, names, strict=True))
    camera = options.camera
    if camera == "auto":
        camera = "single" if summary.kind == "video" or len(set(summary.sizes)) == 1 else "per-image"
    matching = options.matching
    if matching == "auto":
        matching = "sequential" if summary.kind == "video" else "exhaustive"
    t0 = time.perf_counter()
    work = staging / "colmap"
    work.mkdir()
    priors = _focal_priors(summary, options.max_size)
    result = solve_poses(
        frames_dir,
        files,
        work,
        camera=camera,
        matching=matching,
        focal_priors=priors,
        verbose=options.verbose,
        progress=progress,
    )
    seconds["poses"] = time.perf_counter() - t0
    _check_registered(result, len(files))
    t0 = time.perf_counter()
    report = {
        "input": {
            "path": str(summary.paths[0].parent if summary.kind == "photos" else summary.paths[0]),
            "kind": summary.kind,
            "frames": summary.frames,
            "fps": summary.fps,
        },
        "options": {**asdict(options), "camera": camera, "matching": matching},
        "focal_priors_px": {stems[f]: round(v, 2) for f, v in priors.items()},
        "frames": None
        if choice is None
        else {
            "decoded": choice.decoded,
            "median_sharpness": choice.median_sharpness,
            "kept": choice.kept,
            "dropped": choice.dropped,
        },
        "attempt": result.attempt,
        "attempts": result.attempts,
        "models": [_model_report(m, stems) for m in result.models],
        "unregistered": [stems[f] for f in result.unregistered],
    }
    report["scene"] = _write_model(staging / "scene", result.models[0], options, frames_dir, stems)
    if options.all_models:
        for k, model in enumerate(result.models[1:], start=1):
            folder = staging / "scene" / OTHER_MODELS_DIR / f"model_{k}"
            report["models"][k]["scene"] = f"{OTHER_MODELS_DIR}/model_{k}"
            report["models"][k].update(_write_model(folder, model, options, frames_dir, stems, strict=False))
    seconds["write"] = time.perf_counter() - t0
    seconds["total"] = time.perf_counter() - start
    report["seconds"] = {k: round(v, 2) for k, v in seconds.items()}
    (staging / "scene" / REPORT_FILE).write_text(json.dumps(report, indent=2))
    return report


def _frames(
    summary: InputSummary, frames_dir: Path, options: CaptureOptions, progress: Progress
) -> tuple[list[str], FrameChoice | None]:
    """The frames written to ``frames_dir``: every photo, or the video's frames kept (and its choice)."""
    if summary.kind == "photos":
        advance = progress("photos", len(summary.names))
        return store_photos(summary, frames_dir, options.max_size, lambda: advance(1)), None
    advance = progress("video frames", 2 * max(summary.frames, 1))
    choice = video_frames(
        summary.paths[0], frames_dir, options.frames, options.max_size, tick=lambda: advance(1)
    )
    names = [r["name"] for r in choice.kept]
    if len(names) < MIN_FRAMES:
        raise CaptureError(
            f"{summary.paths[0]}: only {len(names)} sharp, distinct frame(s) of {choice.decoded}; "
            "a capture needs 3 (film more slowly, or a longer video)"
        )
    return names, choice


def _focal_priors(summary: InputSummary, max_size: int) -> dict[str, float]:
    """File name -> focal length in pixels at the stored size, for the photos whose EXIF gives one."""
    priors = {}
    for name, focal, size in zip(summary.names, summary.focal_35mm, summary.sizes, strict=False):
        if focal is not None:
            priors[f"{name}.png"] = focal_pixels(focal, *stored_size(*size, max_size))
    return priors


def _model_report(model: PoseModel, stems: dict[str, str]) -> dict:
    return {
        "frames": [stems[n] for n in model.names],
        "points": len(model.points),
        "reprojection_error": round(model.reprojection_error, 4),
    }


def _check_registered(result: PoseResult, frames: int) -> None:
    largest = len(result.models[0].names) if result.models else 0
    if largest >= MIN_FRAMES:
        return
    tried = "; ".join(f"{a['name']}: {a['registered']}" for a in result.attempts)
    raise CaptureError(
        f"only {largest} of {frames} frames could be posed together (attempts {tried}); a scene needs "
        f"{MIN_FRAMES}: give photos that overlap more (each part of the scene in 3 or more of them), "
        "sharper or more textured ones, or more of them"
    )


def _write_model(
    folder: Path,
    model: PoseModel,
    options: CaptureOptions,
    frames_dir: Path,
    stems: dict[str, str],
    strict: bool = True,
) -> dict:
    """One model as a scene: normalised, its training views chosen, written to ``folder``."""
    normalisation = normalise([model.cam_from_world[n] for n in model.names], model.points)
    train = _training_views(model, normalisation, options, stems, strict)
    written = write_scene(folder, model, normalisation, train, frames_dir, stems)
    return {**written, "normalisation": normalisation.as_dict()}


def _training_views(
    model: PoseModel, normalisation, options: CaptureOptions, stems: dict[str, str], strict: bool
) -> list[str]:
    by_stem = {stems[n]: n for n in model.names}
    if options.views is not None and (strict or all(v in by_stem for v in options.views)):
        missing = [v for v in options.views if v not in by_stem]
        if missing:
            raise CaptureError(
                f"--views: {', '.join(missing)} not among the posed frames ({', '.join(by_stem)})"
            )
        return [by_stem[v] for v in options.views]
    count = options.train_views
    if count > len(model.names):
        if strict:
            raise CaptureError(f"--train-views {count}: only {len(model.names)} frames were posed together")
        count = len(model.names)
    c2w = np.array([normalisation.camera_to_world(model.cam_from_world[n]) for n in model.names])
    centre = np.median(normalisation.points(model.points), axis=0) if len(model.points) else np.zeros(3)
    return [model.names[i] for i in spread_views(c2w, centre, count)]


def _move_into_place(built: Path, out: Path) -> None:
    """Renames the finished folder onto ``out``; an existing ``out`` (``--force``) is removed only
    after the new one is in place."""
    old = None
    if out.exists():
        old = out.parent / f".{out.name}.replaced-{os.getpid()}"
        os.replace(out, old)
    os.replace(built, out)
    if old is not None and old.is_dir():
        shutil.rmtree(old, ignore_errors=True)
    elif old is not None:
        old.unlink()
