"""Short trainings whose every tensor is saved, to show that a change leaves training bit for bit as it was.

    python scripts/training_fingerprint.py run OUT [--data ../shared/data]   # at each commit, alone
    python scripts/training_fingerprint.py compare OUT_BEFORE OUT_AFTER

Three runs: the built-in room (96x72) with every optional term and carving on, the room with defaults,
LLFF fern at half size; each short (120-150 iterations) but with densification and LOP rounds in it.
Run them with nothing else on the machine: the first training of a process has been seen to differ in its
last bits when another job competed for the cores.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from langfield import TrainConfig, load_scene, train
from langfield.eval.evaluate import evaluate
from langfield.synthetic import make_room

RUNS = ("room", "room_default", "fern")


def _strip_times(d):
    if isinstance(d, dict):
        return {k: _strip_times(v) for k, v in d.items() if "second" not in k and "time" not in k}
    return [_strip_times(x) for x in d] if isinstance(d, list) else d


def _save(out: Path, name: str, field, scene) -> None:
    tensors = {f"splats.{k}": v.detach().clone() for k, v in field.splats.items()}
    tensors.update({f"color.{k}": v.detach().clone() for k, v in field.color.state_dict().items()})
    if field.language is not None:
        tensors.update({f"lang.{k}": v.detach().clone() for k, v in field.language.state_dict().items()})
    if field.entries is not None:
        tensors["entries"] = field.entries.clone()
    torch.save(tensors, out / f"{name}.pt")
    record = {"report": evaluate(field, scene)}
    record.update({k: field.meta.get(k) for k in ("num_gaussians", "lop", "carved", "iterations", "init")})
    (out / f"{name}.json").write_text(json.dumps(_strip_times(record), indent=1, sort_keys=True, default=str))


def run(out: Path, data: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    scene = load_scene(make_room(out / "room_scene", seed=0, layout=0, width=96, height=72))
    every = {
        "lambda_visibility": 0.1,
        "lambda_smooth": 0.01,
        "lambda_spread": 0.01,
        "lambda_anisotropy": 0.01,
    }
    short = {"iterations": 120, "seed": 0, "refine_start": 30, "refine_every": 30, "lop_every": 40}
    cfg = TrainConfig(**short, **every, carve_free_space=True)
    _save(out, "room", train(scene, cfg, progress=False), scene)
    _save(out, "room_default", train(scene, TrainConfig(**short), progress=False), scene)
    fern = load_scene(data / "llff_fern", resolution=2.0)
    cfg = TrainConfig(iterations=150, seed=0, refine_start=50, refine_every=50)
    _save(out, "fern", train(fern, cfg, progress=False), fern)


def compare(before: Path, after: Path) -> bool:
    same = True
    for name in RUNS:
        a, b = torch.load(before / f"{name}.pt"), torch.load(after / f"{name}.pt")
        differ = sorted(set(a) ^ set(b)) + [k for k in a if k in b and not torch.equal(a[k], b[k])]
        records_equal = (before / f"{name}.json").read_text() == (after / f"{name}.json").read_text()
        print(f"{name}: {len(a)} tensors {'equal' if not differ else 'DIFFER ' + str(differ[:4])}; "
              f"report and record {'equal' if records_equal else 'DIFFER'}")  # fmt: skip
        same &= not differ and records_equal
    print("bit-identical" if same else "not identical")
    return same


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run")
    r.add_argument("out")
    r.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    c = sub.add_parser("compare")
    c.add_argument("before")
    c.add_argument("after")
    args = p.parse_args()
    if args.command == "run":
        run(Path(args.out), Path(args.data))
        return 0
    return 0 if compare(Path(args.before), Path(args.after)) else 1


if __name__ == "__main__":
    sys.exit(main())
