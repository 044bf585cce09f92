"""``langfield train``: the flags, the TrainConfig they give, and the command."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import Any

from langfield.cli.common import add_ablation_flags, add_scene_flags, bounds_arg, scene_args
from langfield.io.field_meta import LANGUAGE_DECODES


def train_config(args: argparse.Namespace):
    """The TrainConfig the flags of ``langfield train`` give (checked: a bad value names its flag)."""
    from langfield.training.trainer import TrainConfig

    cfg = TrainConfig(
        language=False if args.no_language else None,
        language_features=args.language_features,
        language_grid_scale=args.language_grid_scale,
        iterations=args.iterations,
        seed=args.seed,
        backend=args.backend,
        num_gaussians=args.num_gaussians,
        init=args.init,
        bounds=args.bounds,
        densify=not args.no_densify,
        depth=False if args.no_depth else None,
        lad=not args.no_lad,
        lop=not args.no_lop,
        refiner=args.refiner,
    )
    # Flags left unset keep TrainConfig's defaults.
    given = {name: getattr(args, name) for name in SPARSE_VIEW_FLAGS if getattr(args, name) is not None}
    language = ("language_start", "autoencoder_spread", "language_balance", "language_decode")
    for name in ("lambda_opacity", "init_align", *language):
        if getattr(args, name) is not None:
            given[name] = getattr(args, name)
    return replace(cfg, **given)


# TrainConfig settings of the sparse-view regularisers that `langfield train` sets by flag.
SPARSE_VIEW_FLAGS = (
    "drop_gamma",
    "lambda_virtual",
    "virtual_baseline",
    "virtual_directions",
    "virtual_every",
    "virtual_resolution",
    "half_resolution_until",
    "random_background",
    "dark_backdrop",
    "lambda_empty",
    "opacity_decay",
    "lambda_visibility",
    "carve_free_space",
    "lambda_smooth",
    "lambda_spread",
    "lambda_anisotropy",
)


def cmd_train(args: argparse.Namespace) -> int:
    from langfield.field import check_output_folder
    from langfield.io.scene import load_scene
    from langfield.training.trainer import evaluate_psnr, summary_line, train

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


def _flag(*names: str, **options: Any) -> tuple[tuple[str, ...], dict[str, Any]]:
    return names, options


# The flags of `langfield train`, in the order --help lists them (tests check them against TrainConfig).
TRAIN_FLAGS = (
    _flag("scene", help="scene folder (transforms.json, Blender pair, LLFF or COLMAP)"),
    _flag("--out", required=True, help="output folder for the trained field"),
    _flag("--force", action="store_true", help="replace a field already in OUT (kept intact until then)"),
    _flag(
        "--iterations",
        type=int,
        default=None,
        help="training iterations (default: sized by the scene, 500 per training view in [1000, 6000])",
    ),
    _flag("--seed", type=int, default=0, help="seed of the start and the view order (default 0)"),
    _flag(
        "--backend",
        choices=["auto", "torch", "numba", "cpu"],
        default="auto",
        help="rasterizer backend (cpu: numba's earlier name)",
    ),
    _flag("--num-gaussians", type=int, default=None, help="initial Gaussians (default: sized to the scene)"),
    _flag(
        "--init",
        choices=["auto", "dense", "sfm", "depth", "points", "random"],
        default="auto",
        help="where the Gaussians start: plane-sweep stereo on the training views, COLMAP's sparse SIFT "
        "points, the depth prior aligned to the stereo points, the scene's point cloud (sparse_pc.ply "
        "of langfield capture), or random in the bounds (default auto: "
        "depth when every training view has a depth prior, else dense)",
    ),
    _flag(
        "--init-align",
        choices=["fused", "smooth", "views", "anchors"],
        default=None,
        help="how the depth start aligns each view's prior: a line refined until the views agree with "
        "one another, a smooth correction from photo-consistency and the other views, then each pixel "
        "fused with the views that agree on it (fused, the default), the correction without the fusion "
        "(smooth), the line alone (views), or the line fitted to the view's own stereo (anchors)",
    ),
    _flag("--bounds", type=bounds_arg, default=None, help="xmin,ymin,zmin,xmax,ymax,zmax to initialise in"),
    _flag("--no-densify", action="store_true", help="keep the initial Gaussians (no clone/split/prune)"),
    _flag(
        "--language-features",
        choices=["hashgrid", "per-gaussian"],
        default="hashgrid",
        help="language latents from hash grids (SOVGaussian) or one per Gaussian (LangSplat baseline)",
    ),
    _flag(
        "--language-grid-scale",
        type=float,
        default=0.25,
        help="language grid's finest resolution as a fraction of the colour grid's (default 0.25; 1: same)",
    ),
    _flag(
        "--language-start",
        type=float,
        default=None,
        help="fraction of the run before the language term starts (default 0.33, the half-size start)",
    ),
    _flag(
        "--autoencoder-spread",
        type=float,
        default=None,
        help="weight of the autoencoder's term that spreads unlike concepts over the latent sphere "
        "(default 0.01; 0: the paper's eq. 2 alone)",
    ),
    _flag(
        "--language-balance",
        type=float,
        default=None,
        help="L_LF weighs each pixel by its mask's area to the power minus this (default 0.25; 0: every "
        "pixel alike, the paper's; 1: every mask alike)",
    ),
    _flag(
        "--language-decode",
        choices=list(LANGUAGE_DECODES),
        default=None,
        help="read rendered latents through the training masks' latents: by vote among the entries of "
        "the Gaussians at each pixel (vote, the default) or as the nearest entry (codebook); or decode "
        "them as they are (continuous, the paper)",
    ),
    _flag(
        "--lambda-opacity",
        type=float,
        default=None,
        help="weight of the L1 opacity penalty that fades unneeded Gaussians (default: TrainConfig's)",
    ),
    _flag(
        "--drop-gamma",
        type=float,
        default=None,
        help="Gaussian dropout: a fraction gamma t / T left out at iteration t (DropGaussian; 0: off)",
    ),
    _flag(
        "--lambda-virtual",
        type=float,
        default=None,
        help="weight of the virtual-view consistency term (Binocular-guided 3DGS; 0: off)",
    ),
    _flag(
        "--virtual-baseline",
        type=float,
        default=None,
        help="sideways shift of the virtual camera as a fraction of the median rendered depth",
    ),
    _flag(
        "--virtual-directions",
        choices=["horizontal", "any"],
        default=None,
        help="virtual cameras shifted left or right (a stereo pair), or in any direction of the image plane",
    ),
    _flag(
        "--virtual-every",
        type=int,
        default=None,
        help="the virtual-view term on every n-th iteration (it renders a second view)",
    ),
    _flag(
        "--half-resolution-until",
        type=float,
        default=None,
        help="fraction of the run that renders the training views at half their width and height",
    ),
    _flag(
        "--carve-free-space",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="remove Gaussians in front of the surfaces the training views' stereo resolves",
    ),
    _flag(
        "--lambda-visibility",
        type=float,
        default=None,
        help="weight of the free-space term: a view's surface may not lie in front of another view's",
    ),
    _flag(
        "--virtual-resolution",
        type=float,
        default=None,
        help="the virtual-view term's image size as a fraction of the training view's (0 < F <= 1)",
    ),
    _flag(
        "--random-background",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="a random background colour behind the Gaussians each iteration",
    ),
    _flag(
        "--dark-backdrop",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="treat a photo's black backdrop (tall dark regions at the border, DTU's) as empty space",
    ),
    _flag(
        "--lambda-empty",
        type=float,
        default=None,
        help="weight of the rendered alpha on the empty space the photos show (alpha, a black backdrop)",
    ),
    _flag(
        "--opacity-decay",
        type=float,
        default=None,
        help="every opacity times this factor each iteration (Binocular-guided 3DGS: 0.995; 1: off)",
    ),
    _flag("--lambda-smooth", type=float, default=None, help="weight of edge-aware depth smoothness (0: off)"),
    _flag(
        "--lambda-spread",
        type=float,
        default=None,
        help="weight of the depth spread: each pixel's blending weights gathered at one depth (0: off)",
    ),
    _flag(
        "--lambda-anisotropy",
        type=float,
        default=None,
        help="weight of the penalty on Gaussians longer than 10x their width (0: off)",
    ),
    _flag(
        "--refiner",
        default=None,
        help="an ONNX image-refiner folder (manifest kind 'refiner'): cleans renders of virtual views "
        "that then supervise training, weighted by its confidence (default: none)",
    ),
    _flag(
        "--no-language",
        action="store_true",
        help="train colour only, even if the scene has language_features/ (default: language when it has)",
    ),
)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Registers ``langfield train``."""
    p = sub.add_parser("train", help="train a field on a scene's training views")
    for names, options in TRAIN_FLAGS:
        p.add_argument(*names, **options)
    add_ablation_flags(p)
    add_scene_flags(p)
    p.set_defaults(func=cmd_train)
