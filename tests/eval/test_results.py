"""``langfield results`` (langfield/eval/results.py): benchmark specs run as sweeps and rendered into
docs/results.md with their command and commit; ``--no-run``; bad specs; the commit a run records."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from langfield.cli import main
from langfield.eval import sweep
from langfield.eval.results import NOT_RUN, PAGE, load_benchmarks

W, H = 48, 36  # the sweep tests' room
TINY = """\
# The tiny room, for the tests.
scenes = ["../scenes/room"]
cases = ["full"]
seeds = [0]
[config]
iterations = 20
"""


@pytest.fixture
def root(room_factory, tmp_path) -> Path:
    """A repository root: benchmarks/tiny.toml on a tiny room; no results yet."""
    shutil.copytree(room_factory(W, H), tmp_path / "scenes" / "room")
    (tmp_path / "benchmarks").mkdir()
    (tmp_path / "benchmarks" / "tiny.toml").write_text(TINY)
    return tmp_path


def test_page_shows_the_table_with_its_command_commit_and_machine(root, capsys) -> None:
    (spec,) = load_benchmarks(root)
    out = root / "results" / "tiny"
    # The run as a sweep's Ray task makes it, in this process: a worker's start costs half a minute.
    sweep.write_run(out, spec.runs[0], sweep.train_run(spec.runs[0]), sweep.source_commit())
    assert main(["results", "--root", str(root), "--no-run"]) == 0
    run = json.loads((out / "runs" / "room__full__seed0.json").read_text())
    assert run["commit"] == sweep.source_commit() and run["machine"]["cpus"] == os.cpu_count()
    page = (root / PAGE).read_text()
    assert "The tiny room, for the tests." in page
    assert "- Command: `langfield sweep benchmarks/tiny.toml --out results/tiny`" in page
    assert f"- Commit: `{run['commit'][:10]}`" in page
    m = run["machine"]
    cpu = ", ".join(part for part in (m["cpu"], m["generation"], m["simd"]) if part)
    assert f"- Machine: {os.cpu_count()} CPUs ({cpu}), {m['threads']} threads" in page
    if Path("/proc/cpuinfo").is_file():  # which generation of the brand, and its vector width
        assert m["generation"].startswith("family ") and m["simd"]
    row = run["row"]
    assert (
        f"| full | 1 | {row['mIoU']:.3f} ± 0.000 | {row['mAcc']:.3f} ± 0.000 | {row['PSNR']:.2f} ± 0.00 |"
        in page
    )
    assert NOT_RUN not in page
    assert "tiny: 1 of 1 runs finished" in capsys.readouterr().out

    pytest.importorskip("ray", reason="needs the cluster extra (pip install -e '.[cluster]')")
    assert main(["results", "--root", str(root)]) == 0  # the finished run is kept, not trained again
    assert "1 runs, 1 already done, 0 to run" in capsys.readouterr().out
    assert (root / PAGE).read_text().split("\n## tiny")[1] == page.split("\n## tiny")[1]


def test_no_run_without_results_says_so_and_names_the_command(root, capsys) -> None:
    (root / "benchmarks" / "other.toml").write_text(TINY.replace("seeds = [0]", "seeds = [0, 1]"))
    shutil.rmtree(root / "scenes")  # rendering needs no scene
    assert main(["results", "--root", str(root), "--no-run"]) == 0
    out = capsys.readouterr().out
    assert f"no results in {root / 'results' / 'tiny'}: not yet run" in out
    assert f"no results in {root / 'results' / 'other'}: not yet run" in out
    page = (root / PAGE).read_text()
    for name in ("tiny", "other"):
        section = page.split(f"\n## {name}\n")[1].split("\n## ")[0]
        assert f"`langfield sweep benchmarks/{name}.toml --out results/{name}`" in section
        assert f"- Results: {NOT_RUN}" in section
    assert not (root / "results").exists()


@pytest.mark.parametrize(
    ("text", "word"),
    [
        (TINY + "extra = 1\n", "extra"),
        (TINY.replace("../scenes/room", "../scenes/missing"), "missing"),
        (TINY.replace("iterations = 20", "iterations = -1"), "iterations"),
    ],
)
def test_a_bad_spec_stops_everything_naming_its_file(root, text, word, capsys) -> None:
    (root / "benchmarks" / "zz_bad.toml").write_text(text)
    assert main(["results", "--root", str(root)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "zz_bad.toml" in err and word in err, err
    assert not (root / "results").exists() and not (root / PAGE).exists()


def test_runs_made_with_other_settings_are_refused_before_any_run(root, capsys) -> None:
    runs = root / "results" / "tiny" / "runs"
    runs.mkdir(parents=True)
    (runs / "room__full__seed0.json").write_text(json.dumps({"config": {}, "scene_args": {}, "row": {}}))
    assert main(["results", "--root", str(root), "--no-run"]) == 2
    assert "other settings" in capsys.readouterr().err
    assert not (root / PAGE).exists()


def _git(repo: Path, *args: str) -> str:
    who = ["-c", "user.name=test", "-c", "user.email=test@example.com"]
    return subprocess.run(
        ["git", "-C", str(repo), *who, *args], check=True, capture_output=True, text=True
    ).stdout


def test_source_commit_is_the_checkouts_head_and_marks_changed_code(tmp_path, monkeypatch) -> None:
    if shutil.which("git") is None:
        pytest.skip("needs git")
    repo = tmp_path / "repo"
    (repo / "langfield" / "eval").mkdir(parents=True)
    (repo / "langfield" / "eval" / "sweep.py").write_text("x = 1\n")
    (repo / "README.md").write_text("readme\n")
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "commit", "-q", "-m", "start")
    head = _git(repo, "rev-parse", "HEAD").strip()
    monkeypatch.setattr(sweep, "__file__", str(repo / "langfield" / "eval" / "sweep.py"))
    assert sweep.source_commit() == head
    (repo / "README.md").write_text("changed\n")  # documentation: the figures are the same
    assert sweep.source_commit() == head
    (repo / "langfield" / "eval" / "sweep.py").write_text("x = 2\n")
    assert sweep.source_commit() == head + "-dirty"


def test_source_commit_is_unknown_for_a_copy_outside_its_own_checkout(tmp_path, monkeypatch) -> None:
    outer = tmp_path / "project"
    package = outer / "venv" / "site-packages" / "langfield"
    (package / "eval").mkdir(parents=True)
    monkeypatch.setattr(sweep, "__file__", str(package / "eval" / "sweep.py"))
    assert sweep.source_commit() == "unknown"  # no checkout at all
    if shutil.which("git") is not None:
        (outer / "a.txt").write_text("a\n")
        _git(outer, "init", "-q")
        _git(outer, "add", "a.txt")
        _git(outer, "commit", "-q", "-m", "another project")
        assert sweep.source_commit() == "unknown"  # another project's checkout holds it


def test_the_checked_in_specs_are_valid() -> None:
    specs = load_benchmarks(Path(__file__).resolve().parents[2], check_scenes=False)
    assert {s.path.stem for s in specs} >= {"fern", "dtu_scan37", "lego", "room"}
