"""The ``langfield`` command: train, render, eval, bench, demo.

Each subcommand shows a progress bar on long work and ends with a one-line summary. Errors in the
user's input (a missing file, a malformed scene, a bad flag value) are printed as one line naming the
file or argument, with exit status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

from langfield import __version__


def _views_arg(text: str) -> list[str | int]:
    return [int(v) if v.strip().isdigit() else v.strip() for v in text.split(",") if v.strip()]


def _bounds_arg(text: str) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    vals = [float(v) for v in text.split(",")]
    if len(vals) != 6:
        raise argparse.ArgumentTypeError("--bounds takes six numbers: xmin,ymin,zmin,xmax,ymax,zmax")
    return (vals[0], vals[1], vals[2]), (vals[3], vals[4], vals[5])


def _scene_args(args: argparse.Namespace) -> dict:
    return {"resolution": args.resolution, "views": args.views, "n_views": args.n_views}


def _add_scene_flags(p: argparse.ArgumentParser) -> None:
    group = p.add_mutually_exclusive_group()
    group.add_argument(
        "--views",
        type=_views_arg,
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


def _add_ablation_flags(p: argparse.ArgumentParser) -> None:
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


def _load_field_and_scene(out: str, scene_path: str | None):
    from langfield.field import LanguageField

    field = LanguageField.load(out)
    return field, field.trained_scene(scene_path)


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
    for name in ("lambda_opacity", "language_start", "autoencoder_spread", "language_decode"):
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
    "lambda_anisotropy",
)


def cmd_train(args: argparse.Namespace) -> int:
    from langfield.field import check_output_folder
    from langfield.io.scene import load_scene
    from langfield.training.trainer import evaluate_psnr, summary_line, train

    cfg = train_config(args)
    out = Path(args.out)
    check_output_folder(out, args.force)
    scene = load_scene(args.scene, **_scene_args(args))
    field = train(scene, cfg)  # checks every file of the scene before the first iteration
    field.meta["scene_args"] = _scene_args(args)
    field.save(out, overwrite=args.force)
    test_psnr = evaluate_psnr(field, scene)
    print(summary_line(field, test_psnr) + f"; saved to {out}")
    return 0


def cmd_ablate(args: argparse.Namespace) -> int:
    from langfield.eval.ablate import DEFAULT_CASES, format_table, run_ablation
    from langfield.io.scene import load_scene
    from langfield.training.trainer import TrainConfig

    cases = tuple(c.strip() for c in args.cases.split(",")) if args.cases else DEFAULT_CASES
    base = TrainConfig(iterations=args.iterations, seed=args.seed, backend=args.backend)
    if args.lambda_opacity is not None:
        base = replace(base, lambda_opacity=args.lambda_opacity)
    scene = load_scene(args.scene, **_scene_args(args))
    rows = run_ablation(scene, base, cases, out_dir=args.out, overwrite=args.force)
    print(format_table(rows))
    length = next(iter(rows.values()), {}).get("iterations", 0)
    print(f"ablation of {len(rows)} cases, {length} iterations each; table in {args.out}/ablation.md")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    import torch

    from langfield.atomic import check_writable_folder
    from langfield.eval.evaluate import write_render_pngs

    save = check_writable_folder(args.save, "--save")
    field, scene = _load_field_and_scene(args.out, args.scene)
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


def cmd_eval(args: argparse.Namespace) -> int:
    from langfield.atomic import check_writable_file, check_writable_folder
    from langfield.eval.evaluate import evaluate, write_report

    json_path = check_writable_file(args.json, "--json report")
    check_writable_file(json_path.with_suffix(".md"), "Markdown summary")
    pictures = check_writable_folder(json_path.parent / (json_path.stem + "_renders"), "pictures")
    field, scene = _load_field_and_scene(args.out, args.scene)
    report = evaluate(field, scene, split=args.split, save_dir=pictures, oracle=args.oracle)
    md = write_report(report, json_path, pictures)
    psnr_txt = (
        f"PSNR {report['PSNR']:.2f} dB, SSIM {report['SSIM']:.3f}"
        if report["PSNR"] is not None
        else f"no {args.split} views"
    )
    if report.get("masked_PSNR") is not None:
        psnr_txt += f" (object masks: {report['masked_PSNR']:.2f} dB, SSIM {report['masked_SSIM']:.3f})"
    query_txt = (
        f", mIoU {report['mIoU']:.3f}, mAcc {report['mAcc']:.3f}" if report.get("mIoU") is not None else ""
    )
    oracle = report.get("oracle")
    if oracle and oracle["mIoU"] is not None:
        ratio = "" if oracle["ratio"] is None else f", {oracle['ratio']:.2f} of it"
        query_txt += f" (oracle on the true features: mIoU {oracle['mIoU']:.3f}{ratio})"
    selection = report.get("selection_3d")
    if selection and selection["precision"] is not None:
        query_txt += (
            f", 3D selection precision {selection['precision']:.3f} "
            f"(on surfaces {selection['surface_precision']:.3f}) recall {selection['recall']:.3f}"
        )
    print(
        f"{len(report['views'])} {args.split} views: {psnr_txt}{query_txt}{_cosine_text(report)}; "
        f"{report['num_gaussians']} Gaussians, "
        f"{report['field_bytes'] / 1e6:.1f} MB; report {json_path} and {md}"
    )
    return 0


def _cosine_text(report: dict) -> str:
    cos = report.get("feature_cosine")
    if not cos or any(v is None for v in cos.values()):
        return ""
    return ", feature cosine " + " / ".join(f"{v:.3f}" for v in cos.values()) + " (" + "/".join(cos) + ")"


def cmd_bench(args: argparse.Namespace) -> int:
    from langfield.eval.bench import format_table, run_bench
    from langfield.io.scene import load_scene
    from langfield.synthetic import make_room

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene_path = args.scene or make_room(out / "scene", width=160, height=120)
    scene = load_scene(scene_path, resolution=args.resolution)
    extra = {}
    for factor in args.also_resolution or []:
        other = load_scene(scene_path, resolution=args.resolution * factor)
        cam = other.cameras("train")[0]
        extra[f"{cam.width}x{cam.height}"] = other
    json_path = Path(args.json) if args.json else out / "bench.json"
    plot = json_path.with_suffix(".png")
    result = run_bench(
        scene,
        iterations=args.iterations,
        every=args.every,
        num_gaussians=args.num_gaussians,
        json_path=json_path,
        plot_path=plot,
        overhead_iterations=args.overhead_iterations,
        language_iterations=args.language_iterations,
        language_repeats=args.language_repeats,
        extra_scenes=extra,
    )
    print(format_table(result))
    b = result["backends"]
    print(
        f"cpu backend {b['torch']['step_ms'] / b['cpu']['step_ms']:.1f}x faster than torch per step; "
        f"results in {json_path}" + (f" and {plot}" if result["curve"] else "")
    )
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from langfield.eval.evaluate import evaluate, write_report
    from langfield.io.scene import load_scene
    from langfield.synthetic import make_room
    from langfield.training.trainer import TrainConfig, summary_line, train, training_length

    if args.layout < 0:
        raise ValueError(f"--layout: a whole number >= 0, got {args.layout}")
    out = Path(args.out)
    t0 = time.perf_counter()
    scene_dir = make_room(
        out / "scene", seed=args.seed, layout=args.layout, width=args.width, height=args.height
    )
    print(f"[1/5] built-in scene written to {scene_dir}")
    scene = load_scene(scene_dir)
    length = training_length(args.iterations, len(scene.names("train")))["iterations"]
    print(f"[2/5] training on {len(scene.names('train'))} views ({length} iterations)")
    field = train(scene, TrainConfig(iterations=args.iterations, seed=args.seed))
    field.meta["scene_args"] = {"resolution": 1.0, "views": None, "n_views": None}
    field.save(out / "field", overwrite=True)  # the demo's folder is its own: a rerun replaces it
    pictures = out / "renders"
    print(f"[3/5] rendering and scoring {len(scene.names('test'))} novel views to {pictures}")
    report = evaluate(field, scene, save_dir=pictures)
    md = write_report(report, out / "report.json", pictures)
    print(f"[4/5] report: {out / 'report.json'} and {md}")
    queries = out / "queries"
    print(f"[5/5] text queries on the novel views ('couch' is a synonym the table knows) -> {queries}")
    from langfield.cli.query import cmd_query

    query_args = argparse.Namespace(
        out=str(out / "field"),
        phrases=list(DEMO_PHRASES),
        views="test",
        save=str(queries),
        scene=str(scene_dir),
        text_encoder=None,
        exact=False,
    )
    cmd_query(query_args)
    miou = report.get("mIoU")
    query_txt = f", novel-view mIoU {miou:.3f}, mAcc {report['mAcc']:.3f}" if miou is not None else ""
    print(
        summary_line(field, report["PSNR"]) + f", SSIM {report['SSIM']:.3f}{query_txt}; "
        f"demo took {time.perf_counter() - t0:.0f} s; pictures in {pictures} and {queries}"
    )
    return 0


DEMO_PHRASES = ("sofa", "couch", "lamp", "mug")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="langfield", description=__doc__.split("\n")[0])
    parser.add_argument("--version", action="version", version=f"langfield {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("train", help="train a field on a scene's training views")
    p.add_argument("scene", help="scene folder (transforms.json, Blender pair, LLFF or COLMAP)")
    p.add_argument("--out", required=True, help="output folder for the trained field")
    p.add_argument(
        "--force", action="store_true", help="replace a field already in OUT (kept intact until then)"
    )
    p.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="training iterations (default: sized by the scene, 500 per training view in [1000, 6000])",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the start and the view order (default 0)")
    p.add_argument("--backend", choices=["auto", "torch", "cpu"], default="auto", help="rasterizer backend")
    p.add_argument(
        "--num-gaussians", type=int, default=None, help="initial Gaussians (default: sized to the scene)"
    )
    p.add_argument(
        "--init",
        choices=["dense", "sfm", "depth", "random"],
        default="dense",
        help="where the Gaussians start: plane-sweep stereo on the training views (default), COLMAP's "
        "sparse SIFT points, the depth prior aligned to the dense points, or random in the bounds",
    )
    p.add_argument(
        "--bounds", type=_bounds_arg, default=None, help="xmin,ymin,zmin,xmax,ymax,zmax to initialise in"
    )
    p.add_argument(
        "--no-densify", action="store_true", help="keep the initial Gaussians (no clone/split/prune)"
    )
    p.add_argument(
        "--language-features",
        choices=["hashgrid", "per-gaussian"],
        default="hashgrid",
        help="language latents from hash grids (SOVGaussian) or one per Gaussian (LangSplat baseline)",
    )
    p.add_argument(
        "--language-grid-scale",
        type=float,
        default=0.25,
        help="language grid's finest resolution as a fraction of the colour grid's (default 0.25; 1: same)",
    )
    p.add_argument(
        "--language-start",
        type=float,
        default=None,
        help="fraction of the run before the language term starts (default 0.33, the half-size start)",
    )
    p.add_argument(
        "--autoencoder-spread",
        type=float,
        default=None,
        help="weight of the autoencoder's term that spreads unlike concepts over the latent sphere "
        "(default 0.01; 0: the paper's eq. 2 alone)",
    )
    p.add_argument(
        "--language-decode",
        choices=["codebook", "continuous"],
        default=None,
        help="read a rendered latent as the nearest training-mask latent of its level (codebook, the "
        "default) or decode it as it is (continuous, the paper)",
    )
    p.add_argument(
        "--lambda-opacity",
        type=float,
        default=None,
        help="weight of the L1 opacity penalty that fades unneeded Gaussians (default: TrainConfig's)",
    )
    p.add_argument(
        "--drop-gamma",
        type=float,
        default=None,
        help="Gaussian dropout: a fraction gamma t / T left out at iteration t (DropGaussian; 0: off)",
    )
    p.add_argument(
        "--lambda-virtual",
        type=float,
        default=None,
        help="weight of the virtual-view consistency term (Binocular-guided 3DGS; 0: off)",
    )
    p.add_argument(
        "--virtual-baseline",
        type=float,
        default=None,
        help="sideways shift of the virtual camera as a fraction of the median rendered depth",
    )
    p.add_argument(
        "--virtual-directions",
        choices=["horizontal", "any"],
        default=None,
        help="virtual cameras shifted left or right (a stereo pair), or in any direction of the image plane",
    )
    p.add_argument(
        "--virtual-every",
        type=int,
        default=None,
        help="the virtual-view term on every n-th iteration (it renders a second view)",
    )
    p.add_argument(
        "--half-resolution-until",
        type=float,
        default=None,
        help="fraction of the run that renders the training views at half their width and height",
    )
    p.add_argument(
        "--carve-free-space",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="remove Gaussians in front of the surfaces the training views' stereo resolves",
    )
    p.add_argument(
        "--lambda-visibility",
        type=float,
        default=None,
        help="weight of the free-space term: a view's surface may not lie in front of another view's",
    )
    p.add_argument(
        "--virtual-resolution",
        type=float,
        default=None,
        help="the virtual-view term's image size as a fraction of the training view's (0 < F <= 1)",
    )
    p.add_argument(
        "--random-background",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="a random background colour behind the Gaussians each iteration",
    )
    p.add_argument(
        "--dark-backdrop",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="treat a photo's black backdrop (tall dark regions at the border, DTU's) as empty space",
    )
    p.add_argument(
        "--lambda-empty",
        type=float,
        default=None,
        help="weight of the rendered alpha on the empty space the photos show (alpha, a black backdrop)",
    )
    p.add_argument(
        "--opacity-decay",
        type=float,
        default=None,
        help="every opacity times this factor each iteration (Binocular-guided 3DGS: 0.995; 1: off)",
    )
    p.add_argument(
        "--lambda-smooth", type=float, default=None, help="weight of edge-aware depth smoothness (0: off)"
    )
    p.add_argument(
        "--lambda-anisotropy",
        type=float,
        default=None,
        help="weight of the penalty on Gaussians longer than 10x their width (0: off)",
    )
    p.add_argument(
        "--refiner",
        default=None,
        help="an ONNX image-refiner folder (manifest kind 'refiner'): cleans renders of virtual views "
        "that then supervise training, weighted by its confidence (default: none)",
    )
    p.add_argument(
        "--no-language",
        action="store_true",
        help="train colour only, even if the scene has language_features/ (default: language when it has)",
    )
    _add_ablation_flags(p)
    _add_scene_flags(p)
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("ablate", help="train the paper's ablation cases on one scene and tabulate them")
    p.add_argument("scene", help="scene folder")
    p.add_argument("--out", default="ablate_out", help="folder for the fields and ablation.json/.md")
    p.add_argument("--force", action="store_true", help="replace the case fields already in OUT")
    p.add_argument(
        "--iterations", type=int, default=None, help="iterations per case (default: sized by the scene)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of every case (default 0)")
    p.add_argument("--backend", choices=["auto", "torch", "cpu"], default="auto", help="rasterizer backend")
    p.add_argument(
        "--lambda-opacity",
        type=float,
        default=None,
        help="opacity penalty weight of every case (default: TrainConfig's; the no-opacity-reg case sets 0)",
    )
    p.add_argument(
        "--cases",
        default=None,
        help="comma-separated cases: full, no-lop, no-lad, no-depth, per-gaussian, paper-language, "
        "baseline, no-opacity-reg, random-init, sfm-init, depth-init, no-dropout, no-virtual, "
        "no-random-background, no-empty-space, no-opacity-decay, anisotropy, smooth, carve, visibility, "
        "full-resolution, virtual-every-step, half-size-virtual (default: full, no-lop, no-lad, "
        "no-depth, per-gaussian, paper-language, random-init, no-dropout, no-virtual, "
        "no-random-background, no-empty-space, no-opacity-decay; those a scene cannot use skipped)",
    )
    _add_scene_flags(p)
    p.set_defaults(func=cmd_ablate)

    p = sub.add_parser("render", help="render a trained field's views to PNGs")
    p.add_argument("out", help="folder of a trained field")
    p.add_argument(
        "--split", choices=["train", "test", "all"], default="test", help="views to render (default test)"
    )
    p.add_argument("--save", required=True, help="folder for <view>_rgb.png and <view>_depth.png")
    p.add_argument("--scene", default=None, help="scene folder (default: the one recorded in field.json)")
    p.set_defaults(func=cmd_render)

    p = sub.add_parser("eval", help="score a trained field on the scene's test views")
    p.add_argument("out", help="folder of a trained field")
    p.add_argument("scene", nargs="?", default=None, help="scene folder (default: the one in field.json)")
    p.add_argument("--json", required=True, help="report path; a Markdown summary is written beside it")
    p.add_argument(
        "--split", choices=["test", "train"], default="test", help="views to score (default: the test views)"
    )
    p.add_argument(
        "--oracle",
        action="store_true",
        help="also score the queries on each view's own mask features (its feature cache): the query "
        "pipeline's ceiling, beside the field's mIoU and their ratio",
    )
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("bench", help="time the backends and trace quality against training time")
    p.add_argument("--scene", default=None, help="scene folder (default: the built-in scene at 160x120)")
    p.add_argument(
        "--resolution", type=float, default=1.0, help="downscale factor of the images (2 halves them)"
    )
    p.add_argument(
        "--json", default=None, help="result JSON (default OUT/bench.json); a PNG plot goes beside it"
    )
    p.add_argument("--out", default="bench_out", help="working folder (default bench_out)")
    p.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="training iterations of the curve (default: sized by the scene; 0: skip)",
    )
    p.add_argument("--every", type=int, default=250, help="curve checkpoint interval")
    p.add_argument("--num-gaussians", type=int, default=20000, help="Gaussians of the backend timing")
    p.add_argument(
        "--overhead-iterations",
        type=int,
        default=1000,
        help="run length for the L_D + LOP cost against a plain run (0: skip; default 1000)",
    )
    p.add_argument(
        "--language-iterations",
        type=int,
        default=100,
        help="run length for the language field's cost against an RGB-only run (0: skip; default 100)",
    )
    p.add_argument(
        "--language-repeats",
        type=int,
        default=3,
        help="interleaved pairs of those runs; the medians are compared (default 3)",
    )
    p.add_argument(
        "--also-resolution",
        type=float,
        action="append",
        default=None,
        help="a further downscale factor to trace the curve at (repeatable), e.g. 2 for half size",
    )
    p.set_defaults(func=cmd_bench)

    p = sub.add_parser("demo", help="generate the built-in scene, train on 3 views, render and report")
    p.add_argument(
        "--out", default="demo_out", help="the demo's own folder, replaced on a rerun (default demo_out)"
    )
    p.add_argument(
        "--iterations", type=int, default=None, help="training iterations (default: sized by the scene)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the scene and the training (default 0)")
    p.add_argument(
        "--layout",
        type=int,
        default=0,
        help="the room's furniture: 0 the built-in room, other numbers random arrangements (default 0)",
    )
    p.add_argument("--width", type=int, default=160, help="image width of the built-in scene (default 160)")
    p.add_argument("--height", type=int, default=120, help="image height of the built-in scene (default 120)")
    p.set_defaults(func=cmd_demo)

    from langfield.cli.models import add_parsers
    from langfield.cli.query import add_parser as add_query_parser

    add_parsers(sub)  # export, preprocess
    add_query_parser(sub)
    return parser


def _join_negative_values(argv: list[str]) -> list[str]:
    """``--bounds -1,-1,0,1,1,1`` -> ``--bounds=-1,...``: argparse takes a leading '-' for an option."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        if argv[i] == "--bounds" and i + 1 < len(argv):
            out.append(f"--bounds={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(_join_negative_values(argv))
    try:
        return args.func(args)
    except (OSError, ValueError) as err:  # bad input, a path that cannot be written: one line
        print(f"langfield {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"langfield {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
