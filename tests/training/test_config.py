"""Each TrainConfig setting is declared once (langfield/training/config.py): its default, help, check,
group and flag; the checks and the `langfield train` flags are generated from the declarations."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import re
from pathlib import Path

import pytest

from langfield.cli import build_parser
from langfield.training.config import CONFIG_FLAGS, GROUPS, TrainConfig, config_from_flags
from langfield.training.settings import Number, OneOf, Satisfies, Whole

SETTINGS = dataclasses.fields(TrainConfig)
ROOT = Path(__file__).resolve().parents[2]


def _train_parser() -> argparse.ArgumentParser:
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices["train"]


def test_every_setting_is_declared_with_help_check_group_and_a_default_it_accepts() -> None:
    assert len(SETTINGS) > 60
    for f in SETTINGS:
        meta = f.metadata
        assert meta["help"] and "\n" not in meta["help"], f.name
        assert meta["group"] in GROUPS, f.name
        assert isinstance(meta["check"], (Whole, Number, OneOf, Satisfies)), f.name
        assert meta["check"].accepts(f.default), f.name


def test_the_train_command_has_exactly_the_declared_flags_with_their_choices() -> None:
    parser = _train_parser()
    by_dest = {a.dest: a for a in parser._actions}
    declared = {f.name: f for f in SETTINGS if f.metadata["flag"]}
    command_own = {"help", "scene", "out", "force", "views", "n_views", "resolution"}
    assert set(by_dest) == set(declared) | command_own
    for name, f in declared.items():
        action = by_dest[name]
        assert action.option_strings[0] == f.metadata["flag"]
        assert action.default is None  # unset: TrainConfig's default
        check = f.metadata["check"]
        if isinstance(check, OneOf) and action.choices is not None:
            assert set(check.values) <= set(action.choices) <= set(check.values + check.aliases), name


def test_flags_left_unset_give_the_defaults_and_set_ones_reach_the_config(tmp_path) -> None:
    parser = _train_parser()
    assert config_from_flags(parser.parse_args(["scene", "--out", str(tmp_path)])) == TrainConfig()
    argv = ["scene", "--out", str(tmp_path), "--lambda-virtual", "0.5", "--no-lop", "--init", "random",
            "--bounds", "0,0,0,1,1,1", "--no-random-background", "--iterations", "7"]  # fmt: skip
    cfg = config_from_flags(parser.parse_args(argv))
    assert cfg == TrainConfig(
        lambda_virtual=0.5, lop=False, init="random", bounds=((0, 0, 0), (1, 1, 1)), random_background=False,
        iterations=7,
    )  # fmt: skip


def _bad_value(check):
    if isinstance(check, Whole):
        return check.low - 1
    if isinstance(check, Number):
        return math.nan
    if isinstance(check, OneOf):
        return "no such choice"
    return 12345  # Satisfies: bounds, refiner


@pytest.mark.parametrize("f", SETTINGS, ids=lambda f: f.name)
def test_each_check_refuses_a_bad_value_naming_the_setting_and_its_flag(f) -> None:
    with pytest.raises(ValueError) as info:
        TrainConfig(**{f.name: _bad_value(f.metadata["check"])})
    message = str(info.value)
    assert f"TrainConfig.{f.name}" in message and "\n" not in message
    if f.metadata["flag"]:
        assert f"({f.metadata['flag']})" in message


def test_no_flag_of_a_setting_is_written_outside_its_declaration() -> None:
    # Training and the commands that set TrainConfig by flag (train, ablate); other commands' flags of
    # the same name (bench's --num-gaussians, demo's --seed) are their own settings.
    flags = set(CONFIG_FLAGS.values())
    declared_in = ROOT / "langfield" / "training" / "config.py"
    sources = [
        *(ROOT / "langfield" / "training").rglob("*.py"),
        *(ROOT / "langfield" / "cli").glob("[ta]*.py"),
    ]
    found = []
    for path in sources:
        if path == declared_in:
            continue
        for literal in re.findall(r"[\"'](--[a-z][a-z0-9-]*)[\"']", path.read_text()):
            if literal in flags:
                found.append(f"{path.relative_to(ROOT)}: {literal}")
    assert found == []


def test_a_recorded_config_of_the_flat_form_loads() -> None:
    # As field.json and sweep run files record it (JSON: bounds as lists), with the numba backend's
    # earlier name and a setting this version no longer has.
    record = json.loads(json.dumps(dataclasses.asdict(TrainConfig(bounds=((0, 0, 0), (1, 2, 3))))))
    record.update(backend="cpu", iterations=10, a_setting_since_removed=1)
    cfg = TrainConfig.from_record(record)
    assert cfg.bounds == ((0.0, 0.0, 0.0), (1.0, 2.0, 3.0))
    assert (cfg.backend, cfg.iterations) == ("cpu", 10)
    assert dataclasses.replace(cfg, backend="auto", iterations=None, bounds=None) == TrainConfig()
