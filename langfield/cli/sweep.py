"""``langfield sweep SPEC.toml --out DIR``: scenes x cases x seeds on Ray (:mod:`langfield.eval.sweep`)."""

from __future__ import annotations

import argparse
import sys


def cmd_sweep(args: argparse.Namespace) -> int:
    from langfield.atomic import check_writable_folder
    from langfield.cluster import require_ray
    from langfield.eval.sweep import load_spec, run_sweep

    try:
        require_ray()
    except RuntimeError as err:
        print(f"langfield sweep: error: {err}", file=sys.stderr)
        return 2
    out = check_writable_folder(args.out, "--out")
    spec = load_spec(args.spec)
    summary = run_sweep(spec, out, address=args.address)
    failed = f", {len(summary['failed'])} failed (listed in the table)" if summary["failed"] else ""
    done = f"{len(summary['finished'])} of {summary['runs']} runs finished"
    print(f"sweep: {done}{failed}; table in {out}/sweep.md")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Registers ``langfield sweep``."""
    p = sub.add_parser("sweep", help="scenes x cases x seeds as Ray tasks, one table (langfield[cluster])")
    p.add_argument("spec", help="the sweep's TOML file (scenes, cases, seeds, [config]; docs/cluster.md)")
    p.add_argument("--out", required=True, help="folder for runs/*.json, sweep.json and sweep.md (resumed)")
    p.add_argument(
        "--address",
        default=None,
        help="Ray cluster: auto (the one this machine is part of) or ray://HOST:10001 "
        "(default: a local Ray started in the process)",
    )
    p.set_defaults(func=cmd_sweep)
