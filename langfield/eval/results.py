"""``langfield results``: the benchmark specs run as sweeps, and the page of current figures rendered
from what they wrote.

Everything sits under one root (the repository's): ``benchmarks/NAME.toml`` is a sweep spec
(:mod:`langfield.eval.sweep`), run as ``langfield sweep benchmarks/NAME.toml --out results/NAME``, so a
second call resumes where the first stopped and a finished run is never redone. ``docs/results.md`` is
the page, one section per spec: its description (the spec's opening comment), the command, the commit
and machine its runs were made at, their dates and the sweep's table. A spec with no finished run says
so, with the command that runs it. ``results/`` is committed with the page: its runs are the page's
source.

Every spec is read and checked before the first run; so are the runs already in ``results/NAME``
(a run made with other settings than the spec now gives is refused, never mixed in). The built-in
room is no download: a spec that names ``results/scenes/room`` has it written there first
(:func:`langfield.synthetic.make_room`'s defaults, the demo's scene).
"""

from __future__ import annotations

import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path

from langfield.atomic import atomic_path
from langfield.eval.sweep import (
    Spec,
    SpecError,
    finished_runs,
    format_summary,
    load_spec,
    run_sweep,
    source_commit,
    summarise,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

BENCHMARKS = Path("benchmarks")
RESULTS = Path("results")
PAGE = Path("docs/results.md")
ROOM = RESULTS / "scenes" / "room"
NOT_RUN = "not yet run at this commit"


def out_folder(root: Path, spec: Spec) -> Path:
    return root / RESULTS / spec.path.stem


def sweep_command(root: Path, spec: Spec) -> str:
    """The command that runs one spec, as typed at ``root``."""
    return f"langfield sweep {spec.path.relative_to(root)} --out {out_folder(root, spec).relative_to(root)}"


def load_benchmarks(root: str | Path, check_scenes: bool = True) -> list[Spec]:
    """Every ``benchmarks/*.toml`` under ``root``, checked, with the runs already in their folders.

    ``check_scenes`` reads every scene's files as training will (and writes the built-in room where a
    spec names it); rendering from finished runs needs neither.

    Raises:
        SpecError: the first spec that cannot run, or whose folder holds runs of other settings; the
            message names its file.
    """
    root = Path(root).resolve()
    paths = sorted((root / BENCHMARKS).glob("*.toml"))
    if not paths:
        raise SpecError(f"{root / BENCHMARKS}: no benchmark specs (*.toml)")
    clash = root / BENCHMARKS / f"{ROOM.parent.name}.toml"
    if clash.exists():
        raise SpecError(f"{clash}: its results would share {ROOM.parent} with the built scenes; rename it")
    if check_scenes and any(_names_room(root, p) for p in paths):
        _write_room(root / ROOM)
    specs = []
    for path in paths:
        try:
            spec = load_spec(path, check_scenes=check_scenes)
        except SpecError:
            raise
        except (OSError, ValueError) as err:  # a scene that cannot be read
            raise SpecError(f"{path}: {err}") from None
        finished_runs(spec, out_folder(root, spec))
        specs.append(spec)
    return specs


def _names_room(root: Path, path: Path) -> bool:
    try:
        scenes = tomllib.loads(path.read_text()).get("scenes", [])
    except (OSError, tomllib.TOMLDecodeError):
        return False  # load_spec reports it
    room = (root / ROOM).resolve()
    return isinstance(scenes, list) and any(
        isinstance(s, str) and (path.parent / s).resolve() == room for s in scenes
    )


def _write_room(folder: Path) -> None:
    """The built-in room at ``folder``, unless there; written beside it and renamed, so that an
    interrupted write never leaves half a scene."""
    from langfield.synthetic import make_room

    if folder.is_dir():
        return
    partial = folder.with_name(folder.name + ".partial")
    shutil.rmtree(partial, ignore_errors=True)
    make_room(partial)
    partial.rename(folder)


def run_benchmarks(
    root: str | Path, specs: list[Spec], address: str | None = None, say: Callable[[str], None] = print
) -> None:
    """Runs each spec's sweep into ``results/NAME`` (its finished runs kept)."""
    for spec in specs:
        run_sweep(spec, out_folder(Path(root).resolve(), spec), address=address, say=say)


HEADER = """\
# Results

This page is generated; do not edit it. `langfield results` (or `make results`) at the repository's
root runs every spec in `benchmarks/` as a sweep into `results/NAME/` and rewrites this page; a second
call resumes, and `langfield results --no-run` renders the page from the runs in `results/`, which are
committed with it. Each table is the sweep's own: per scene and case, the mean ± sample standard
deviation over the seeds finished (`langfield ablate`'s columns, [cli.md](cli.md)). Past measurements,
each at the commit it names, are the lab notebook [history/figures.md](history/figures.md); why each
default differs from the paper: [decisions.md](decisions.md).

Rendered at commit {commit} on {day}.
"""
FOOTER = """\
## Speed

`langfield bench` times the rasterizer backends, the cost per iteration of the language field and of
L_D + LOP, the time to quality and the query latency. It takes no spec and is not run here:
`langfield bench --scene ../shared/data/llff_fern --overhead-iterations 0 --language-iterations 0`
writes `bench_out/bench.json`. The tables above give each run's training seconds and ms per iteration.
"""


def render_page(root: str | Path, specs: list[Spec]) -> str:
    """docs/results.md: how the page is made, one section per spec, then where speed is measured."""
    root = Path(root).resolve()
    commit = source_commit()
    lines = [HEADER.format(commit=_commit(commit), day=_day(time.time()))]
    for spec in specs:
        lines += _section(root, spec, commit)
    return "\n".join([*lines, FOOTER])


def _section(root: Path, spec: Spec, commit: str) -> list[str]:
    out = out_folder(root, spec)
    lines = [f"## {spec.path.stem}", "", *_description(spec.path), ""]
    lines += [f"- Command: `{sweep_command(root, spec)}`"]
    runs = finished_runs(spec, out)
    if not runs:
        return lines + [f"- Results: {NOT_RUN} ({_commit(commit)}).", ""]
    commits = sorted({r.get("commit") or "unknown" for r in runs.values()})
    machines = sorted({_machine(r.get("machine")) for r in runs.values()})
    days = sorted({_day(r["finished"]) for r in runs.values() if "finished" in r})
    lines += [
        f"- Commit: {', '.join(_commit(c) for c in commits)}"
        + ("" if commits == [commit] else f" (this page: {_commit(commit)})"),
        f"- Machine: {'; '.join(machines)}",
        f"- Date: {_span(days)}",
        "",
        format_summary(summarise(spec, runs), level=3),
    ]
    return lines


def _description(path: Path) -> list[str]:
    """The spec's opening comment lines, without their ``#``."""
    lines = []
    for line in path.read_text().splitlines():
        if not line.startswith("#"):
            break
        lines.append(line.lstrip("#").strip())
    return lines


def _machine(m: dict | None) -> str:
    if not m:
        return "unknown"
    cpu = ", ".join(part for part in (m["cpu"], m.get("generation"), m.get("simd")) if part)
    return f"{m['cpus']} CPUs ({cpu}), {m['threads']} threads per run"


def _commit(commit: str) -> str:
    """A commit as Markdown: its first 10 digits, and whether the tree had changes."""
    head, dirty, _ = commit.partition("-dirty")
    return f"`{head[:10]}`" + (" with uncommitted changes" if dirty else "")


def _span(days: list[str]) -> str:
    if not days:
        return "unknown"
    return days[0] if days[0] == days[-1] else f"{days[0]} to {days[-1]}"


def _day(seconds: float) -> str:
    return time.strftime("%Y-%m-%d", time.gmtime(seconds))


def write_page(root: str | Path, text: str) -> Path:
    path = Path(root).resolve() / PAGE
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path
