"""The ``langfield`` command: capture, train, ablate, sweep, results, render, eval, bench, demo, query, view.

Each subcommand shows a progress bar on long work and ends with a one-line summary. Errors in the
user's input (a missing file, a malformed scene, a bad flag value) are printed as one line naming the
file or argument, with exit status 2.
"""

from __future__ import annotations

import argparse
import sys

from langfield import __version__
from langfield.cli import ablate, bench, capture, demo, models, query, render, results, sweep, train, view
from langfield.cli import eval as eval_command

# The subcommands in the order `langfield --help` lists them.
COMMANDS = (capture, train, ablate, sweep, results, render, eval_command, bench, demo)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="langfield", description=__doc__.split("\n")[0])
    parser.add_argument("--version", action="version", version=f"langfield {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    models.add_parsers(sub)  # export, preprocess
    query.add_parser(sub)
    view.add_parser(sub)
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
