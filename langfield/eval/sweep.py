"""``langfield sweep SPEC.toml``: scenes x cases x seeds, each run a Ray task, gathered into one table.

A spec (TOML; paths relative to the spec's folder)::

    scenes = ["room", "../data/llff_fern"]   # scene folders (their folder names must differ)
    cases = ["full", "baseline"]             # langfield ablate's cases, or names under [custom]
    seeds = [0, 1, 2]
    cpus_per_run = 1                         # the CPUs each run declares to Ray (default 1)

    [config]                                 # TrainConfig fields for every run
    iterations = 300

    [scene_args]                             # load_scene's arguments: resolution, n_views, views
    resolution = 2

    [custom.low-threshold]                   # a case of your own: TrainConfig fields over [config]
    grad_threshold = 0.0006

Everything is checked before the first run: the spec's keys, every scene (loaded, and its files read as
``langfield train`` reads them), every case's settings. Each run is the ablation's row
(:func:`langfield.eval.ablate.run_case`), written to ``OUT/runs/<scene>__<case>__seed<seed>.json`` as
soon as it finishes, with its settings, the git commit of the driver's langfield (:func:`source_commit`)
and the worker's CPUs (:func:`machine`); ``OUT/sweep.json`` and ``OUT/sweep.md`` (mean and spread over
the seeds per scene and case) are rewritten after every run. A run that raises is written with its error
and shown in the table; the others go on. Run again with the same OUT, a sweep skips the runs already
written (failed ones run again), so an interrupted sweep resumes where it stopped.

Ray is the optional extra ``langfield[cluster]``. With no address a local Ray is started in the process
(the embedded default; every CPU of the machine); ``--address auto`` joins the cluster this machine is
part of, ``ray://host:10001`` a remote one (docs/cluster.md).
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from langfield.atomic import atomic_path
from langfield.cluster import ray_session
from langfield.eval.ablate import CASES, run_case
from langfield.training.config import TrainConfig, check_config

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

SPEC_KEYS = {"scenes", "cases", "seeds", "cpus_per_run", "config", "scene_args", "custom"}
SCENE_ARGS = {"resolution", "n_views", "views"}
# The ablation table's columns, summarised over the seeds.
# PSNR_near / _between / _beyond: per view class (langfield.eval.view_classes), masked where the scene
# has masks.
COLUMNS = (
    "mIoU", "mAcc", "PSNR", "SSIM", "masked_PSNR", "PSNR_near", "PSNR_between", "PSNR_beyond",
    "depth_abs_rel", "floaters", "depth_agreement", "num_gaussians", "train_seconds", "ms_per_iteration",
)  # fmt: skip


class SpecError(ValueError):
    """A sweep spec that cannot run; the message names the file and the key."""


@dataclass(frozen=True)
class Run:
    """One training of a sweep: a scene, a case, a seed and the full settings."""

    scene: str  # the scene folder, absolute
    case: str
    seed: int
    config: dict[str, Any]  # TrainConfig's fields
    scene_args: dict[str, Any] = field(default_factory=dict)

    @property
    def key(self) -> str:
        return f"{Path(self.scene).name}__{self.case}__seed{self.seed}"


@dataclass
class Spec:
    path: Path
    runs: list[Run]
    cpus_per_run: int


def _case_settings(raw: dict, where: str) -> dict[str, dict]:
    custom = raw.get("custom", {})
    if not isinstance(custom, dict) or not all(isinstance(v, dict) for v in custom.values()):
        raise SpecError(f"{where}: [custom.NAME] tables of TrainConfig fields")
    cases = raw.get("cases", ["full"])
    if not isinstance(cases, list) or not cases:
        raise SpecError(f"{where}: cases must be a non-empty list")
    unknown = [c for c in cases if c not in CASES and c not in custom]
    if unknown:
        known = ", ".join(CASES)
        raise SpecError(f"{where}: cases {unknown} are neither ablation cases ({known}) nor [custom]")
    return {c: custom[c] if c in custom else CASES[c] for c in cases}


def _config(base: dict, overrides: dict, seed: int, where: str) -> TrainConfig:
    names = {f.name for f in fields(TrainConfig)}
    unknown = sorted((set(base) | set(overrides)) - names)
    if unknown:
        raise SpecError(f"{where}: {unknown} are not TrainConfig fields")
    try:
        cfg = replace(TrainConfig(**base), **overrides, seed=seed)
        check_config(cfg)
    except (TypeError, ValueError) as err:
        raise SpecError(f"{where}: {err}") from None
    return cfg


def load_spec(path: str | Path, check_scenes: bool = True) -> Spec:
    """Reads and checks a spec (see the module's docstring); ``check_scenes`` also reads every file of
    every scene as training will."""
    from langfield.io.scene import load_scene
    from langfield.training.targets import check_inputs

    path = Path(path)
    if not path.is_file():
        raise SpecError(f"{path}: no such spec file")
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as err:
        raise SpecError(f"{path}: not TOML: {err}") from None
    unknown = sorted(set(raw) - SPEC_KEYS)
    if unknown:
        raise SpecError(f"{path}: unknown keys {unknown} (known: {', '.join(sorted(SPEC_KEYS))})")
    scenes = raw.get("scenes")
    if not isinstance(scenes, list) or not scenes or not all(isinstance(s, str) for s in scenes):
        raise SpecError(f"{path}: scenes must be a non-empty list of folders")
    folders = [(path.parent / s).resolve() for s in scenes]
    if len({f.name for f in folders}) != len(folders):
        raise SpecError(f"{path}: scenes: two scene folders share a name")
    seeds = raw.get("seeds", [0])
    if not isinstance(seeds, list) or not seeds or not all(type(s) is int for s in seeds):
        raise SpecError(f"{path}: seeds must be a non-empty list of integers")
    cpus = raw.get("cpus_per_run", 1)
    if type(cpus) is not int or cpus < 1:
        raise SpecError(f"{path}: cpus_per_run must be an integer >= 1")
    scene_args = raw.get("scene_args", {})
    if not isinstance(scene_args, dict) or set(scene_args) - SCENE_ARGS:
        raise SpecError(f"{path}: [scene_args] takes only {', '.join(sorted(SCENE_ARGS))}")
    base = raw.get("config", {})
    cases = _case_settings(raw, str(path))
    runs = []
    for folder in folders:
        scene = load_scene(folder, **scene_args) if check_scenes else None
        for case, overrides in cases.items():
            cfg = _config(base, overrides, seeds[0], f"{path}: case {case!r}")
            if scene is not None:
                check_inputs(scene, cfg, progress=False)
            for seed in seeds:
                settings = {f.name: getattr(replace(cfg, seed=seed), f.name) for f in fields(TrainConfig)}
                runs.append(Run(str(folder), case, seed, settings, dict(scene_args)))
    return Spec(path, runs, cpus)


def train_run(run: Run) -> dict:
    """Trains and scores one run (in a Ray worker); its row, or its error: never raises."""
    t0 = time.perf_counter()
    try:
        from langfield.io.scene import load_scene

        scene = load_scene(run.scene, **run.scene_args)
        row = run_case(scene, TrainConfig(**run.config), progress=False)
        return {"row": row, "seconds": time.perf_counter() - t0, "machine": machine()}
    except Exception as err:  # any failure of one run is reported, never fatal to the sweep
        tail = traceback.format_exc().strip().splitlines()[-6:]
        seconds = time.perf_counter() - t0
        return {"error": f"{type(err).__name__}: {err}", "traceback": tail, "seconds": seconds}


def machine() -> dict[str, Any]:
    """What ran a training: the machine's CPUs, their model, the vendor's family and model numbers (one
    brand name covers generations years apart), their vector width, OpenMP's wait settings and the
    threads PyTorch was given."""
    import torch

    from langfield.eval.bench import cpuinfo_field, fma_lanes

    cpuinfo = Path("/proc/cpuinfo")
    text = cpuinfo.read_text() if cpuinfo.is_file() else ""
    family, model = cpuinfo_field(text, "cpu family"), cpuinfo_field(text, "model")
    generation = f"family {family} model {model}" if family and model else ""
    return {
        "cpus": os.cpu_count(),
        "cpu": cpuinfo_field(text, "model name") or platform.machine(),
        "generation": generation,
        "simd": fma_lanes(text)[1] if text else "",
        "openmp": {k: os.environ.get(k) for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")},
        "threads": torch.get_num_threads(),
    }


def source_commit() -> str:
    """The git commit of the checkout langfield runs from, ``-dirty`` when its tracked files other than
    documentation differ from it; ``unknown`` when langfield is not run from a git checkout of its own
    (an installed copy)."""
    package = Path(__file__).resolve().parents[1]

    def git(*args: str) -> str | None:
        try:
            argv = ["git", "-C", str(package), *args]
            done = subprocess.run(argv, capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):  # no git on this machine
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    top = git("rev-parse", "--show-toplevel")
    head = git("rev-parse", "HEAD")
    # A checkout of another project that happens to hold an installed langfield is not ours.
    if top is None or head is None or Path(top).resolve() != package.parent:
        return "unknown"
    # Documentation (docs/results.md above all, rewritten from these runs) changes no figure.
    changed = git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)*.md")
    return head + ("-dirty" if changed else "")


def _with_threads(runner: Callable[[Run], dict], cpus: int) -> Callable[[Run], dict]:
    def run(r: Run) -> dict:
        import torch

        torch.set_num_threads(cpus)  # the CPUs the task declared, not every core of the worker's node
        return runner(r)

    return run


def _as_json(value: Any) -> Any:
    return json.loads(json.dumps(value, default=float))


def _same_config(recorded: Any, config: dict[str, Any]) -> bool:
    """Whether a run file's recorded settings are ``config``: a setting added since the run was written
    is absent from its record and matches at its default (a new setting's default keeps the behaviour
    it did not have before); a setting removed since never matches."""
    if not isinstance(recorded, dict) or not set(recorded) <= set(config):
        return False
    defaults = _as_json(dataclasses.asdict(TrainConfig()))
    return all(recorded.get(k, defaults[k]) == v for k, v in config.items())


def finished_runs(spec: Spec, out: Path) -> dict[str, dict]:
    """The spec's runs already written in ``out`` (failed ones left out: they run again).

    Raises:
        SpecError: a run file of ``out`` was written with other settings (its results are never
            mixed into this sweep's table, nor overwritten).
    """
    done = {}
    for run in spec.runs:
        path = out / "runs" / f"{run.key}.json"
        if not path.is_file():
            continue
        result = json.loads(path.read_text())
        same_scene = result.get("scene_args") == _as_json(run.scene_args)
        if not (same_scene and _same_config(result.get("config"), _as_json(run.config))):
            raise SpecError(f"{path}: was run with other settings than {spec.path} gives; use another --out")
        if "row" in result:
            done[run.key] = result
    return done


def run_sweep(
    spec: Spec,
    out: str | Path,
    address: str | None = None,
    runner: Callable[[Run], dict] = train_run,
    say: Callable[[str], None] = print,
) -> dict:
    """Runs the spec's runs not yet in ``out`` on Ray (see the module's docstring); the summary."""
    out = Path(out)
    results = finished_runs(spec, out)
    todo = [r for r in spec.runs if r.key not in results]
    say(f"sweep {spec.path}: {len(spec.runs)} runs, {len(results)} already done, {len(todo)} to run")
    (out / "runs").mkdir(parents=True, exist_ok=True)
    commit = source_commit()
    with ray_session(address, needed=bool(todo)) as ray:
        task = ray.remote(_with_threads(runner, spec.cpus_per_run)).options(
            num_cpus=spec.cpus_per_run, max_retries=0
        )
        pending = {task.remote(r): r for r in todo}
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            run = pending.pop(ready[0])
            result = results[run.key] = write_run(out, run, _gather(ray, ready[0]), commit)
            summary = write_summary(spec, out, results)
            said = result.get("error") or f"PSNR {result['row']['PSNR']:.2f} dB"
            say(f"[{len(summary['finished'])}/{len(spec.runs)}] {run.key}: {said}")
    return write_summary(spec, out, results)


def write_run(out: Path, run: Run, result: dict, commit: str) -> dict:
    """``result`` of ``run`` (:func:`train_run`'s) with the settings it ran with and the commit, written
    to ``out/runs/<key>.json``; returned as written."""
    result = {
        **result,
        "run": {"scene": run.scene, "case": run.case, "seed": run.seed},
        "config": _as_json(run.config),
        "scene_args": _as_json(run.scene_args),
        "commit": commit,
        "finished": time.time(),
    }
    _write_json(out / "runs" / f"{run.key}.json", result)
    return result


def _gather(ray, ref) -> dict:
    try:
        return ray.get(ref)
    except Exception as err:  # the task raised, or its worker died (killed, out of memory)
        cause = getattr(err, "cause", None)  # a RayTaskError carries the task's own exception
        if isinstance(cause, BaseException):
            return {"error": f"{type(cause).__name__}: {cause}"}
        lines = [line for line in str(err).strip().splitlines() if line.strip()]
        return {"error": f"{type(err).__name__}: {lines[-1] if lines else ''}"}


def _write_json(path: Path, value: dict) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(value, indent=2, default=float) + "\n")


def _stats(values: list) -> dict | None:
    values = [v for v in values if v is not None]
    if not values:
        return None
    a = np.asarray(values, dtype=np.float64)
    return {"mean": float(a.mean()), "std": float(a.std(ddof=1)) if len(a) > 1 else 0.0, "n": len(a)}


def summarise(spec: Spec, results: dict[str, dict]) -> dict:
    """Per scene and case, each column's mean and spread (sample std) over the finished seeds, and the
    failed runs with their errors."""
    table: dict[str, dict[str, dict]] = {}
    failed = {}
    for run in spec.runs:
        result = results.get(run.key)
        if result is not None and "error" in result:
            failed[run.key] = result["error"]
        rows = table.setdefault(Path(run.scene).name, {}).setdefault(run.case, {"rows": [], "seeds": []})
        if result is not None and "row" in result:
            rows["rows"].append(result["row"])
            rows["seeds"].append(run.seed)
    summary = {
        scene: {
            case: {"seeds": v["seeds"], **{c: _stats([r.get(c) for r in v["rows"]]) for c in COLUMNS}}
            for case, v in cases.items()
        }
        for scene, cases in table.items()
    }
    finished = sorted(k for k, r in results.items() if "row" in r)
    return {"spec": str(spec.path), "runs": len(spec.runs), "finished": finished, "failed": failed,
            "summary": summary}  # fmt: skip


def format_summary(summary: dict, level: int = 1) -> str:
    """The summary as Markdown: one table per scene, ``mean ± std (n)``, then the failed runs; its title
    a heading of ``level``, each scene one level below."""

    def cell(s: dict | None, digits: int) -> str:
        return "n/a" if s is None else f"{s['mean']:.{digits}f} ± {s['std']:.{digits}f}"

    digits = {"mIoU": 3, "mAcc": 3, "SSIM": 3, "depth_agreement": 3, "depth_abs_rel": 4}
    title, sub = "#" * level, "#" * (level + 1)
    lines = [f"{title} Sweep ({len(summary['finished'])} of {summary['runs']} runs finished)", ""]
    for scene, cases in summary["summary"].items():
        lines += [f"{sub} {scene}", "", "| case | seeds | " + " | ".join(COLUMNS) + " |"]
        lines.append("|" + "---|" * (len(COLUMNS) + 2))
        for case, v in cases.items():
            cells = [cell(v[c], digits.get(c, 2 if "PSNR" in c else 0)) for c in COLUMNS]
            lines.append(f"| {case} | {len(v['seeds'])} | " + " | ".join(cells) + " |")
        lines.append("")
    if summary["failed"]:
        lines += [f"{sub} Failed runs", ""] + [f"- {k}: {e}" for k, e in summary["failed"].items()] + [""]
    return "\n".join(lines)


def write_summary(spec: Spec, out: Path, results: dict[str, dict]) -> dict:
    summary = summarise(spec, results)
    _write_json(out / "sweep.json", summary)
    with atomic_path(out / "sweep.md") as tmp:
        tmp.write_text(format_summary(summary))
    return summary
