"""Sweeps on a local Ray (langfield/eval/sweep.py, ``langfield sweep``): the table, a run that raises,
resuming, and a sweep killed half-way."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from langfield.cli import main

ray = pytest.importorskip("ray", reason="needs the cluster extra (pip install -e '.[cluster]')")

from langfield.eval.sweep import SpecError, load_spec, run_sweep  # noqa: E402

W, H = 48, 36
FAILING_RUNNER = '''
from langfield.eval.sweep import train_run

def run(r):
    if r.case == "baseline" and r.seed == 1:
        raise RuntimeError("planned failure of baseline seed 1")
    return train_run(r)
'''


@pytest.fixture
def spec_file(room_factory, tmp_path):
    shutil.copytree(room_factory(W, H), tmp_path / "room")
    path = tmp_path / "sweep.toml"
    path.write_text(
        textwrap.dedent(
            """
            scenes = ["room"]
            cases = ["full", "baseline"]
            seeds = [0, 1]
            [config]
            iterations = 20
            """
        )
    )
    return path


def _files(out):
    return {p.name: p.read_bytes() for p in sorted((out / "runs").glob("*.json"))}


@pytest.mark.slow
def test_sweep_tabulates_reports_a_failure_and_resumes(spec_file, tmp_path, monkeypatch) -> None:
    (tmp_path / "helpers").mkdir()
    (tmp_path / "helpers" / "failing_runner.py").write_text(FAILING_RUNNER)
    # Ray's workers import the runner by name: they inherit PYTHONPATH from this process.
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path / "helpers"), *sys.path]))
    monkeypatch.syspath_prepend(str(tmp_path / "helpers"))
    import failing_runner

    out = tmp_path / "out"
    said: list[str] = []
    summary = run_sweep(load_spec(spec_file), out, runner=failing_runner.run, say=said.append)
    assert said[0].endswith("4 runs, 0 already done, 4 to run")
    assert len(summary["finished"]) == 3 and list(summary["failed"]) == ["room__baseline__seed1"]
    assert "planned failure" in summary["failed"]["room__baseline__seed1"]
    table = (out / "sweep.md").read_text()
    assert "| full | 2 |" in table and "| baseline | 1 |" in table and "planned failure" in table
    full = json.loads((out / "sweep.json").read_text())["summary"]["room"]["full"]
    rows = [json.loads((out / "runs" / f"room__full__seed{s}.json").read_text())["row"] for s in (0, 1)]
    assert full["PSNR"]["n"] == 2
    assert full["PSNR"]["mean"] == pytest.approx((rows[0]["PSNR"] + rows[1]["PSNR"]) / 2)
    before = _files(out)

    said.clear()
    summary = run_sweep(load_spec(spec_file), out, say=said.append)  # resumed: only the failed run again
    assert said[0].endswith("4 runs, 3 already done, 1 to run")
    assert len(summary["finished"]) == 4 and not summary["failed"]
    after = _files(out)
    assert all(after[name] == data for name, data in before.items() if name != "room__baseline__seed1.json")

    spec_file.write_text(spec_file.read_text().replace("iterations = 20", "iterations = 25"))
    with pytest.raises(SpecError, match="other settings"):  # never mixed into, nor written over
        run_sweep(load_spec(spec_file), out, say=said.append)
    assert _files(out) == after


def test_a_run_file_from_before_a_setting_was_added_matches_at_its_default() -> None:
    import dataclasses

    from langfield.eval.sweep import _as_json, _same_config
    from langfield.training.config import TrainConfig

    config = _as_json(dataclasses.asdict(TrainConfig(lambda_depth=0.02)))
    older = {k: v for k, v in config.items() if k != "opacity_noise"}  # written before the setting
    assert _same_config(older, config)
    assert not _same_config(older, {**config, "opacity_noise": 0.1})  # the run had none
    assert not _same_config({**config, "lambda_depth": 0.01}, config)
    assert not _same_config({**config, "a_removed_setting": 1}, config)
    assert not _same_config(None, config)


@pytest.mark.slow
def test_killed_sweep_resumes_without_redoing_finished_runs(spec_file, tmp_path) -> None:
    out = tmp_path / "out"
    run = "import sys; from langfield.cli import main; sys.exit(main())"
    argv = [sys.executable, "-c", run, "sweep", str(spec_file), "--out", str(out)]
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    proc = subprocess.Popen(argv, start_new_session=True, **quiet)
    try:
        deadline = time.monotonic() + 300
        while not list((out / "runs").glob("*.json")) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the driver and the Ray it started
        proc.wait()
    before = _files(out)
    assert 1 <= len(before) < 4  # killed half-way
    said: list[str] = []
    summary = run_sweep(load_spec(spec_file), out, say=said.append)
    assert said[0].endswith(f"4 runs, {len(before)} already done, {4 - len(before)} to run")
    assert len(summary["finished"]) == 4
    after = _files(out)
    assert all(after[name] == data for name, data in before.items())


def test_bad_specs_are_refused_naming_the_key(spec_file, tmp_path, capsys) -> None:
    base = spec_file.read_text()
    cases = [
        (base.replace('cases = ["full", "baseline"]', 'cases = ["nope"]'), "nope"),
        (base.replace("seeds = [0, 1]", 'seeds = ["a"]'), "seeds"),
        (base.replace("iterations = 20", "iteratons = 20"), "iteratons"),
        (base.replace("iterations = 20", "iterations = -3"), "iterations"),
        (base.replace('scenes = ["room"]', 'scenes = ["missing"]'), "missing"),
        (base + "\nextra = 1\n", "extra"),
        ("scenes = [", "not TOML"),
    ]
    for text, word in cases:
        spec_file.write_text(text)
        with pytest.raises((SpecError, ValueError), match=word):
            load_spec(spec_file)
        assert main(["sweep", str(spec_file), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert word in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists()


def test_without_ray_the_command_says_how_to_install_it(spec_file, tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now raises ImportError
    assert main(["sweep", str(spec_file), "--out", str(tmp_path / "out")]) == 2
    assert "pip install 'langfield[cluster]'" in capsys.readouterr().err
    assert main(["preprocess", str(tmp_path), "--address", "local", "--segmenter", "graph"]) == 2
    assert "pip install 'langfield[cluster]'" in capsys.readouterr().err
