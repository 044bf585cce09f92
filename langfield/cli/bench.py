"""``langfield bench``: the backends timed and quality traced against training time."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

# bench's own flags of these names size the curve's run (0: none) and the backend timing, so the
# training settings of the same names are not offered here.
_OWN = ("iterations", "num_gaussians")


def curve_settings(args: argparse.Namespace) -> dict[str, Any]:
    """The training settings given as ``langfield train``'s flags, for the curve's run; checked as a
    TrainConfig (a bad value names its flag) before any work."""
    from langfield.training.config import CONFIG_FLAGS, TrainConfig
    from langfield.training.settings import given_flags

    given = given_flags(args, (n for n in CONFIG_FLAGS if n not in _OWN))
    TrainConfig(**given)
    return given


def cmd_bench(args: argparse.Namespace) -> int:
    from langfield.eval.bench import format_table, run_bench
    from langfield.io.scene import load_scene
    from langfield.synthetic import make_room

    settings = curve_settings(args)
    seed = settings.pop("seed", 0)
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
        seed=seed,
        settings=settings,
    )
    print(format_table(result))
    b = result["backends"]
    print(
        f"numba backend {b['torch']['step_ms'] / b['numba']['step_ms']:.1f}x faster than torch per step; "
        f"results in {json_path}" + (f" and {plot}" if result["curve"] else "")
    )
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Registers ``langfield bench``."""
    from langfield.training.config import CONFIG_FLAGS, add_train_flags

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
    # The curve's run takes langfield train's settings (--seed also seeds the other timed runs).
    add_train_flags(p, tuple(n for n in CONFIG_FLAGS if n not in _OWN))
    p.set_defaults(func=cmd_bench)
