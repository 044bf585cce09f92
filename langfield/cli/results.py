"""``langfield results``: every benchmark spec run as a sweep, then docs/results.md rendered from the
runs (:mod:`langfield.eval.results`)."""

from __future__ import annotations

import argparse
import sys


def cmd_results(args: argparse.Namespace) -> int:
    from langfield.cluster import require_ray
    from langfield.eval.results import load_benchmarks, out_folder, render_page, run_benchmarks, write_page
    from langfield.eval.sweep import finished_runs

    if not args.no_run:
        try:
            require_ray()
        except RuntimeError as err:
            print(f"langfield results: error: {err}", file=sys.stderr)
            return 2
    specs = load_benchmarks(args.root, check_scenes=not args.no_run)
    if not args.no_run:
        run_benchmarks(args.root, specs, address=args.address)
    page = write_page(args.root, render_page(args.root, specs))
    for spec in specs:
        out = out_folder(page.parents[1], spec)
        done = len(finished_runs(spec, out))
        said = f"{done} of {len(spec.runs)} runs finished" if done else f"no results in {out}: not yet run"
        print(f"{spec.path.stem}: {said}")
    print(f"results: {len(specs)} benchmarks; page in {page}")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Registers ``langfield results``."""
    p = sub.add_parser(
        "results", help="run benchmarks/*.toml as sweeps (resumed) and rewrite docs/results.md from them"
    )
    p.add_argument(
        "--root", default=".", help="the folder holding benchmarks/, results/ and docs/ (default: here)"
    )
    p.add_argument(
        "--no-run", action="store_true", help="render the page from the runs already in results/, run none"
    )
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster for the runs: auto or ray://HOST:10001 (default: a local Ray started here)",
    )
    p.set_defaults(func=cmd_results)
