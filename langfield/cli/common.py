"""What several commands share: the scene flags, the ablation switches, loading a field with its
scene."""

from __future__ import annotations

import argparse


def views_arg(text: str) -> list[str | int]:
    return [int(v) if v.strip().isdigit() else v.strip() for v in text.split(",") if v.strip()]


def bounds_arg(text: str) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    vals = [float(v) for v in text.split(",")]
    if len(vals) != 6:
        raise argparse.ArgumentTypeError("--bounds takes six numbers: xmin,ymin,zmin,xmax,ymax,zmax")
    return (vals[0], vals[1], vals[2]), (vals[3], vals[4], vals[5])


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


def add_ablation_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--no-depth",
        action="store_true",
        help="no depth loss L_D even if the scene has depths/ (default: L_D when all train views have one)",
    )
    p.add_argument(
        "--no-lad",
        action="store_true",
        help="plain global depth loss only: no per-mask (language-aware) normalisation (eq. 6, 9)",
    )
    p.add_argument("--no-lop", action="store_true", help="no language-guided outlier pruning (eq. 14-16)")


def load_field_and_scene(out: str, scene_path: str | None):
    from langfield.field import LanguageField

    field = LanguageField.load(out)
    return field, field.trained_scene(scene_path)
