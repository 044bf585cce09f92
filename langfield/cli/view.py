"""``langfield view OUT``: the browser viewer with live text queries (:mod:`langfield.viewer.server`)."""

from __future__ import annotations

import argparse
import time


def cmd_view(args: argparse.Namespace) -> int:
    from langfield.field import LanguageField

    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port: a port number 0-65535, got {args.port}")
    field = LanguageField.load(args.out)
    scene = scene_for(field, args.scene)
    from langfield.viewer.server import Viewer

    viewer = Viewer(
        field, scene, host=args.host, port=args.port, text_encoder=args.text_encoder, save=args.save
    )
    cameras = f", {len(scene.names('all'))} cameras" if scene is not None else ""
    print(
        f"langfield view: {field.num_gaussians} Gaussians"
        f"{cameras} at {viewer.url} "
        f"(open it in a browser; Ctrl-C stops)"
    )
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        print("langfield view: stopped")
    finally:
        viewer.close()
    return 0


def scene_for(field, path: str | None):
    """The scene whose cameras are shown: ``--scene`` (which must load), else the one field.json records
    if it still loads (a field whose scene has moved is shown without cameras, saying so), else none."""
    if path is not None:
        return field.trained_scene(path)
    if not field.meta.scene:
        return None
    try:
        return field.trained_scene()
    except (OSError, ValueError) as err:
        print(f"langfield view: no cameras shown ({err}); pass --scene to show them")
        return None


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Registers ``langfield view``."""
    p = sub.add_parser("view", help="browser viewer of a trained field, with live text queries")
    p.add_argument("out", help="folder of a trained field")
    p.add_argument(
        "--port", type=int, default=8080, help="port to serve on (default 8080; the next free one if taken)"
    )
    p.add_argument(
        "--host", default="127.0.0.1", help="address to bind (default 127.0.0.1: this machine only)"
    )
    p.add_argument(
        "--scene", default=None, help="scene folder, for the cameras (default: the one in field.json)"
    )
    p.add_argument(
        "--text-encoder",
        default=None,
        help="a text_embeddings.npz or a CLIP model folder (default: the field's own, see field.json)",
    )
    p.add_argument(
        "--save", default="selections", help="folder for the exported selections' PLYs (default selections)"
    )
    p.set_defaults(func=cmd_view)
