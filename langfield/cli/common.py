"""What several commands share: the scene flags, the ablation switches, loading a field with its
scene."""

from __future__ import annotations

import argparse


def views_arg(text: str) -> list[str | int]:
    return [int(v) if v.strip().isdigit() else v.strip() for v in text.split(",") if v.strip()]


def scene_args(args: argparse.Namespace) -> dict:
    return {"resolution": args.resolution, "views": args.views, "n_views": args.n_views}


def add_scene_flags(p: argparse.ArgumentParser) -> None:
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "--views",
        type=views_arg,
        default=None,
        help="training views: comma-separated names or indices (the rest are test views)",
    )
    group.add_argument(
        "--n-views",
        type=int,
        default=None,
        help="number of training views spread evenly (LLFF protocol; default: the file's split, else 3)",
    )
    p.add_argument(
        "--resolution", type=float, default=1.0, help="downscale factor of the images (2 halves them)"
    )


def load_field_and_scene(out: str, scene_path: str | None):
    from langfield.field import LanguageField

    field = LanguageField.load(out)
    return field, field.trained_scene(scene_path)
