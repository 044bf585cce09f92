"""``langfield ablate``: the paper's ablation cases on one scene, tabulated."""

from __future__ import annotations

import argparse

from langfield.cli.common import add_scene_flags, scene_args


def cmd_ablate(args: argparse.Namespace) -> int:
    from langfield.eval.ablate import DEFAULT_CASES, format_table, run_ablation
    from langfield.io.scene import load_scene
    from langfield.training.config import config_from_flags

    cases = tuple(c.strip() for c in args.cases.split(",")) if args.cases else DEFAULT_CASES
    base = config_from_flags(args)  # the settings every case starts from; the cases change one each
    scene = load_scene(args.scene, **scene_args(args))
    rows = run_ablation(scene, base, cases, out_dir=args.out, overwrite=args.force)
    print(format_table(rows))
    length = next(iter(rows.values()), {}).get("iterations", 0)
    print(f"ablation of {len(rows)} cases, {length} iterations each; table in {args.out}/ablation.md")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Registers ``langfield ablate``."""
    from langfield.training.config import add_train_flags

    p = sub.add_parser("ablate", help="train the paper's ablation cases on one scene and tabulate them")
    p.add_argument("scene", help="scene folder")
    p.add_argument("--out", default="ablate_out", help="folder for the fields and ablation.json/.md")
    p.add_argument("--force", action="store_true", help="replace the case fields already in OUT")
    # TrainConfig's flags for every case; the no-opacity-reg case sets lambda_opacity 0 whatever is given.
    add_train_flags(p, ("iterations", "seed", "backend", "lambda_opacity"))
    p.add_argument(
        "--cases",
        default=None,
        help="comma-separated cases: full, no-lop, no-lad, no-depth, per-gaussian, paper-language, "
        "baseline, no-opacity-reg, random-init, sfm-init, depth-init, mean-sweep, fronto-sweep, no-dropout, "
        "no-virtual, "
        "no-random-background, no-empty-space, no-opacity-decay, anisotropy, smooth, carve, visibility, "
        "full-resolution, virtual-every-step, half-size-virtual, opacity-noise, orbit, orbit-wide, "
        "both-motions, direction-frequencies, no-direction, depth-baseline, virtual-occlusion, crossview, "
        "co-training, "
        "stereo (default: full, no-lop, no-lad, no-depth, per-gaussian, paper-language, random-init, "
        "no-dropout, no-virtual, no-random-background, no-empty-space, no-opacity-decay; those a scene "
        "cannot use skipped)",
    )
    add_scene_flags(p)
    p.set_defaults(func=cmd_ablate)
