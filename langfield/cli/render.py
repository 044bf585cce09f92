"""``langfield render``: a trained field's views as PNGs, or a fly-through video along a camera path."""

from __future__ import annotations

import argparse
import sys
import time

from langfield.cli.common import load_field_and_scene


def cmd_render(args: argparse.Namespace) -> int:
    if args.video is not None:
        return _render_video(args)
    if args.save is None:
        raise ValueError("--save: the folder for the PNGs is required (or pass --path and --video)")
    if args.query is not None:
        raise ValueError("--query: a heat map goes into a video only (pass --path and --video)")
    import torch

    from langfield.atomic import check_writable_folder
    from langfield.eval.evaluate import write_render_pngs

    save = check_writable_folder(args.save, "--save")
    field, scene = load_field_and_scene(args.out, args.scene)
    names = scene.names(args.split)
    t0 = time.perf_counter()
    with torch.no_grad():
        for name in names:
            r = field.render(scene.camera(name))
            write_render_pngs(save, name, r.rgb.numpy(), r.depth.numpy(), r.alpha.numpy())
    dt = time.perf_counter() - t0
    print(
        f"rendered {len(names)} {args.split} views in {dt:.2f} s "
        f"({1000 * dt / max(len(names), 1):.0f} ms/view); RGB and depth PNGs in {save}"
    )
    return 0


def _render_video(args: argparse.Namespace) -> int:
    from encoders.text_table import UnknownPhraseError
    from langfield.viewer.paths import PATHS
    from langfield.viewer.video import check_video_path, path_frames, write_video

    if args.save is not None:
        raise ValueError("--save: PNGs or a video, not both (drop --save or --video)")
    if args.frames < 2:
        raise ValueError(f"--frames: at least 2, got {args.frames}")
    if not args.fps > 0:
        raise ValueError(f"--fps: a positive number, got {args.fps}")
    video = check_video_path(args.video, args.overwrite)
    field, scene = load_field_and_scene(args.out, args.scene)
    query = None
    if args.query is not None:
        try:
            query = field.query(args.query, args.text_encoder, scene=scene)
        except UnknownPhraseError as err:
            print(f"langfield render: error: {err}", file=sys.stderr)
            return 2
    cameras = scene.cameras("all")
    path = PATHS[args.path](cameras, args.frames, fallback=field.meta.centre)
    t0 = time.perf_counter()
    count = write_video(video, path_frames(field, path, query), args.fps)
    dt = time.perf_counter() - t0
    h, w = cameras[0].height, cameras[0].width * (2 if query is not None else 1)
    print(
        f"rendered the {args.path} path of {count} frames ({w}x{h}, {args.fps:g} fps) in {dt:.1f} s "
        f"({1000 * dt / count:.0f} ms/frame){' with the heat map of ' + repr(args.query) if query else ''}: "
        f"{video}"
    )
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Registers ``langfield render``."""
    p = sub.add_parser("render", help="render a trained field's views to PNGs, or a fly-through video")
    p.add_argument("out", help="folder of a trained field")
    p.add_argument(
        "--split", choices=["train", "test", "all"], default="test", help="views to render (default test)"
    )
    p.add_argument("--save", default=None, help="folder for <view>_rgb.png and <view>_depth.png")
    p.add_argument("--scene", default=None, help="scene folder (default: the one recorded in field.json)")
    video = p.add_argument_group("video along a camera path (instead of --save)")
    video.add_argument(
        "--path",
        choices=["orbit", "interpolate"],
        default="orbit",
        help="orbit: around what the cameras look at; interpolate: through every camera (default orbit)",
    )
    video.add_argument("--video", default=None, help="the video file to write (.mp4 or .avi)")
    video.add_argument("--query", default=None, help="a phrase: its heat map beside the colour render")
    video.add_argument("--frames", type=int, default=120, help="number of frames (default 120)")
    video.add_argument("--fps", type=float, default=30.0, help="frames per second (default 30)")
    video.add_argument(
        "--text-encoder",
        default=None,
        help="a text_embeddings.npz or a CLIP model folder (default: the field's)",
    )
    video.add_argument("--overwrite", action="store_true", help="replace an existing video file")
    p.set_defaults(func=cmd_render)
