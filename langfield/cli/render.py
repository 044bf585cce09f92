"""``langfield render``: a trained field's views as PNGs."""

from __future__ import annotations

import argparse
import time

from langfield.cli.common import load_field_and_scene


def cmd_render(args: argparse.Namespace) -> int:
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


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Registers ``langfield render``."""
    p = sub.add_parser("render", help="render a trained field's views to PNGs")
    p.add_argument("out", help="folder of a trained field")
    p.add_argument(
        "--split", choices=["train", "test", "all"], default="test", help="views to render (default test)"
    )
    p.add_argument("--save", required=True, help="folder for <view>_rgb.png and <view>_depth.png")
    p.add_argument("--scene", default=None, help="scene folder (default: the one recorded in field.json)")
    p.set_defaults(func=cmd_render)
