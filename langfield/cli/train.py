"""``langfield train``: the flags, the TrainConfig they give, and the command."""

from __future__ import annotations

import argparse
from pathlib import Path

from langfield.cli.common import add_scene_flags, scene_args


def train_config(args: argparse.Namespace):
    """The TrainConfig the flags of ``langfield train`` give (checked: a bad value names its flag)."""
    from langfield.training.config import config_from_flags

    return config_from_flags(args)


def cmd_train(args: argparse.Namespace) -> int:
    from langfield.field import check_output_folder
    from langfield.io.scene import load_scene
    from langfield.training.loop import evaluate_psnr, summary_line, train

    cfg = train_config(args)
    out = Path(args.out)
    check_output_folder(out, args.force)
    scene = load_scene(args.scene, **scene_args(args))
    field = train(scene, cfg)  # checks every file of the scene before the first iteration
    field.meta["scene_args"] = scene_args(args)
    field.save(out, overwrite=args.force)
    test_psnr = evaluate_psnr(field, scene)
    print(summary_line(field, test_psnr) + f"; saved to {out}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Registers ``langfield train``."""
    from langfield.training.config import add_train_flags

    p = sub.add_parser("train", help="train a field on a scene's training views")
    p.add_argument("scene", help="scene folder (transforms.json, Blender pair, LLFF or COLMAP)")
    p.add_argument("--out", required=True, help="output folder for the trained field")
    p.add_argument(
        "--force", action="store_true", help="replace a field already in OUT (kept intact until then)"
    )
    add_scene_flags(p)
    add_train_flags(p)  # every TrainConfig setting that has a flag, declared in langfield.training.config
    p.set_defaults(func=cmd_train)
