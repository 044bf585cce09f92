"""``langfield capture``: a folder of photos or a video -> a posed scene folder (docs/capture.md)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from typing import Any

__all__ = ["add_parser", "cmd_capture"]


def add_parser(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "capture",
        help="pose your own photos or a video (COLMAP) and write a scene folder to train on",
        description="Pose a folder of photos or a video with COLMAP (pycolmap) and write a scene folder "
        "(images/, transforms.json, sparse_pc.ply, capture.json) that train, preprocess, eval and view read.",
    )
    p.add_argument("input", help="a folder of photos (jpg, png, ...) or a video file (mp4, mov, ...)")
    p.add_argument("--out", required=True, help="the scene folder to write (new, or --force)")
    p.add_argument("--frames", type=int, default=48, help="frames to keep from a video (default 48)")
    p.add_argument(
        "--max-size", type=int, default=1008, help="longer side of the stored frames in pixels (default 1008)"
    )
    p.add_argument(
        "--camera",
        choices=("auto", "single", "per-image"),
        default="auto",
        help="one camera for all frames, or one each "
        "(default auto: single for a video or photos of one size)",
    )
    p.add_argument(
        "--matching",
        choices=("auto", "exhaustive", "sequential"),
        default="auto",
        help="image pairs to match (default auto: sequential with keyframe loops for a video, "
        "exhaustive for photos)",
    )
    views = p.add_mutually_exclusive_group()
    views.add_argument(
        "--train-views", type=int, default=3, help="training views chosen for spread (default 3)"
    )
    views.add_argument(
        "--views", default=None, help="the training views by name instead, comma-separated (photo file stems)"
    )
    p.add_argument(
        "--all-models",
        action="store_true",
        help="also write each smaller model COLMAP made, under other_models/",
    )
    p.add_argument("--force", action="store_true", help="replace OUT if it exists")
    p.add_argument("--verbose", action="store_true", help="show COLMAP's own log")
    p.set_defaults(func=cmd_capture)


def _bars() -> tuple[Callable[[str, int], Callable[[int], None]], Callable[[], None]]:
    """A progress factory for :func:`langfield.capture.capture` (one tqdm bar per stage), and a
    function that closes the last bar."""
    from tqdm import tqdm

    open_bars: list = []

    def progress(stage: str, total: int) -> Callable[[int], None]:
        for bar in open_bars:
            bar.close()
        open_bars.clear()
        # disable=None: bars on a terminal only, so that a log or a pipe gets the summary alone.
        bar = tqdm(total=total, desc=stage, dynamic_ncols=True, leave=False, file=sys.stderr, disable=None)
        open_bars.append(bar)
        return bar.update

    def close() -> None:
        for bar in open_bars:
            bar.close()

    return progress, close


def cmd_capture(args: argparse.Namespace) -> int:
    from langfield.capture import CaptureOptions, capture

    views = None
    if args.views is not None:
        views = tuple(v.strip() for v in args.views.split(",") if v.strip())
    options = CaptureOptions(
        frames=args.frames,
        max_size=args.max_size,
        camera=args.camera,
        matching=args.matching,
        train_views=args.train_views,
        views=views,
        all_models=args.all_models,
        force=args.force,
        verbose=args.verbose,
    )
    progress, close = _bars()
    try:
        report = capture(args.input, args.out, options, progress=progress)
    finally:
        close()
    for line in summary_lines(report, args.out):
        print(line)
    return 0


def summary_lines(report: dict, out: str) -> list[str]:
    """The few lines printed after a capture: frames, models, views, time."""
    lines = []
    frames = report["frames"]
    if frames is not None:
        lines.append(
            f"video: {frames['decoded']} frames decoded, {len(frames['kept'])} kept, "
            f"{len(frames['dropped'])} dropped (blurred or near-duplicate)"
        )
    models = report["models"]
    total = sum(len(m["frames"]) for m in models) + len(report["unregistered"])
    lines.append(
        f"poses: {len(models[0]['frames'])} of {total} frames in the largest model "
        f"(attempt '{report['attempt']}', {models[0]['points']} points, "
        f"{models[0]['reprojection_error']:.2f} px mean reprojection error)"
    )
    for k, model in enumerate(models[1:], start=1):
        where = (
            f" -> {out}/{model['scene']}" if "scene" in model else " (not written; --all-models writes it)"
        )
        lines.append(f"  model {k}: {len(model['frames'])} frames: {', '.join(model['frames'])}{where}")
    if report["unregistered"]:
        lines.append(f"  not posed: {', '.join(report['unregistered'])}")
    scene = report["scene"]
    lines.append(
        f"captured in {report['seconds']['total']:.1f} s: train {', '.join(scene['train'])}; "
        f"{len(scene['test'])} test views; scene in {out}"
    )
    if len(scene["train"]) < 3:  # load_scene asks a run on fewer views to be confirmed
        n = len(scene["train"])
        lines.append(f"  {n} training view(s): train with --n-views {n}")
    return lines
