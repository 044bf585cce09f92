"""LAD and LOP inside training: switches, logging, optimizer state, the ablation command, the hard cases."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from langfield.cli import main
from langfield.eval.geometry import aligned_depth_error, count_floaters, depth_errors
from langfield.field import LanguageField
from langfield.io.scene import load_scene
from langfield.training.config import TrainConfig
from langfield.training.lad import LADTarget, depth_loss, lad_loss
from langfield.training.loop import train
from langfield.training.strategy import TrainingStrategy


@pytest.fixture(scope="module")
def room(room_factory) -> Path:
    return room_factory(64, 48, n_test=2)


@pytest.fixture(scope="module")
def trained(room):
    cfg = TrainConfig(iterations=40, lop_every=15, autoencoder_iterations=50, densify=False)
    return train(load_scene(room), cfg, progress=False)


def test_lop_rounds_are_logged_and_remove_gaussians(trained):
    rounds = trained.meta["lop"]
    assert [r["iteration"] for r in rounds] == [15, 30]
    assert all(r["removed"] > 0 for r in rounds)
    assert rounds[1]["before"] == rounds[0]["before"] - rounds[0]["removed"]
    assert trained.num_gaussians == rounds[1]["before"] - rounds[1]["removed"]
    # no more than tau of the Gaussians per round
    assert all(r["removed"] <= 0.05 * r["before"] for r in rounds)


def test_no_round_where_less_than_half_an_interval_of_the_run_follows(room):
    # 30 iterations, every 15: the round at 30 would be the last step, with no training to fill its
    # holes; one at 15 has 15 iterations after it.
    cfg = TrainConfig(iterations=30, lop_every=15, autoencoder_iterations=50, densify=False)
    field = train(load_scene(room), cfg, progress=False)
    assert [r["iteration"] for r in field.meta["lop"]] == [15]
    strategy = SimpleNamespace(cfg=TrainConfig(iterations=1500, lop_every=1000), use_lop=True)
    due = [t for t in range(1, 1501) if TrainingStrategy.lop_due(strategy, t)]
    assert due == [1000]
    strategy.cfg = TrainConfig(iterations=1499, lop_every=1000)  # 499 after it: under half
    assert not any(TrainingStrategy.lop_due(strategy, t) for t in range(1, 1500))


@pytest.mark.slow
def test_training_goes_on_after_pruning_with_optimizer_state_in_step(room):
    # Pruning at 10 and 20 with densification on: the next Adam steps and refinements must still fit.
    cfg = TrainConfig(iterations=25, lop_every=10, autoencoder_iterations=30, refine_start=5, refine_every=5)
    field = train(load_scene(room), cfg, progress=False)
    n = field.num_gaussians
    assert all(p.shape[0] == n for p in field.splats.values())
    assert all(torch.isfinite(p).all() for p in field.splats.values())


def test_depth_is_on_for_a_scene_with_priors_and_recorded(trained, tmp_path):
    assert trained.meta["depth"] == {"lad": True, "kind": "disparity"}
    trained.save(tmp_path / "f")
    meta = json.loads((tmp_path / "f" / "field.json").read_text())
    assert meta["config"]["lop"] is True and meta["config"]["lad"] is True
    assert len(LanguageField.load(tmp_path / "f").meta["lop"]) == 2


@pytest.mark.parametrize(
    ("flags", "expect"),
    [
        (["--no-depth"], {"depth": None, "lop": True}),
        (["--no-lad"], {"depth": {"lad": False, "kind": "disparity"}, "lop": True}),
        (["--no-lop"], {"lop": None}),
    ],
)
@pytest.mark.slow
def test_ablation_switches_are_recorded_in_field_json(room, tmp_path, flags, expect):
    out = tmp_path / "out"
    assert main(["train", str(room), "--out", str(out), "--iterations", "3", *flags]) == 0
    meta = json.loads((out / "field.json").read_text())
    if "depth" in expect:
        assert meta["depth"] == expect["depth"]
    if expect.get("lop") is None:
        assert meta["lop"] is None and meta["config"]["lop"] is False
    assert meta["config"]["depth"] is (False if "--no-depth" in flags else None)
    assert meta["config"]["lad"] is ("--no-lad" not in flags)


def test_depth_gradient_reaches_the_means(room):
    # L_D alone must move the Gaussians (hard depth: means only; soft depth: all geometry).
    scene = load_scene(room)
    field = train(scene, TrainConfig(iterations=0, autoencoder_iterations=10), progress=False)
    name = scene.names("train")[0]
    out = field.render(scene.camera(name), hard_depth=True)
    target = LADTarget.from_view(
        torch.full((3, *out.depth.shape), -1, dtype=torch.int64),
        torch.from_numpy(scene.depth(name)),
        "disparity",
    )
    depth_loss(target, out.depth_hard, out.depth).backward()
    assert field.splats["means"].grad.abs().sum() > 0


def test_one_pixel_mask():
    # A one-pixel mask has no depth structure: it is not a usable mask, adds nothing and pulls nothing.
    seg = torch.full((3, 8, 8), -1, dtype=torch.int64)
    seg[0, 3, 3] = 0
    prior = torch.rand(8, 8) + 1
    target = LADTarget.from_view(seg, prior, "depth", min_pixels=1)
    depth = torch.rand(8, 8, requires_grad=True)
    loss = lad_loss(target, depth)
    loss.backward()
    assert target.num_masks == 0 and loss.item() == 0.0 and torch.equal(depth.grad, torch.zeros(8, 8))
    # Beside a mask with structure it changes nothing either.
    seg[0, :3] = 1  # rows 0-2; the one-pixel mask stays at (3, 3)
    without = seg.clone()
    without[0, 3, 3] = -1
    with_pixel = lad_loss(LADTarget.from_view(seg, prior, "depth", min_pixels=1), depth)
    assert (
        with_pixel.item()
        == lad_loss(LADTarget.from_view(without, prior, "depth", min_pixels=1), depth).item()
    )
    assert with_pixel.item() > 0


def test_mask_with_constant_depth():
    # A constant prior says nothing about shape; a constant render matches it exactly: L_D is 0.
    seg = torch.zeros(3, 8, 8, dtype=torch.int64)
    target = LADTarget.from_view(seg, torch.full((8, 8), 2.0), "depth")
    depth = torch.full((8, 8), 3.0, requires_grad=True)
    loss = depth_loss(target, depth, depth)
    loss.backward()
    assert target.num_masks == 0 and loss.item() == 0.0 and torch.equal(depth.grad, torch.zeros(8, 8))


def test_level_with_no_masks():
    seg = torch.full((3, 8, 8), -1, dtype=torch.int64)
    seg[2] = (torch.arange(64).reshape(8, 8) >= 32).long()  # only the whole level has masks
    prior = torch.rand(8, 8) + 1
    depth = torch.rand(8, 8, requires_grad=True)
    loss = lad_loss(LADTarget.from_view(seg, prior, "depth", min_pixels=4), depth)
    loss.backward()
    assert torch.isfinite(loss) and loss > 0 and torch.isfinite(depth.grad).all()


def test_prior_with_nan_is_rejected_at_load(room, tmp_path):
    # The scene loader rejects NaN/inf priors with the file's name (LADTarget masks them if given).
    import shutil

    copy = tmp_path / "room"
    shutil.copytree(room, copy)
    scene = load_scene(copy)
    name = scene.names("train")[0]
    prior = np.load(copy / "depths" / f"{name}.npy")
    prior[0, 0] = np.nan
    np.save(copy / "depths" / f"{name}.npy", prior)
    with pytest.raises(ValueError, match=rf"depths/{name}\.npy: depth map has NaN"):
        train(load_scene(copy), TrainConfig(iterations=1, autoencoder_iterations=5), progress=False)


def test_aligned_depth_error_ignores_scale_and_shift():
    g = np.random.default_rng(0)
    truth = g.uniform(1, 3, (12, 16))
    alpha = np.ones_like(truth)
    err = aligned_depth_error(0.5 * truth - 0.2, alpha, truth)
    assert err["abs_rel"] < 1e-9
    assert aligned_depth_error(g.uniform(1, 3, truth.shape), alpha, truth)["abs_rel"] > 0.05
    assert aligned_depth_error(truth, np.zeros_like(truth), truth) is None  # nothing covered


def test_geometry_figures_on_the_synthetic_scene(trained, room):
    scene = load_scene(room)
    errors = depth_errors(trained, scene)
    assert errors is not None and np.isfinite(errors["abs_rel"])
    # Every Gaussian on the floor (z = 0, inside the room): none is a floater; five moved far outside
    # the room: exactly those five are.
    field = copy.deepcopy(trained)
    n = field.num_gaussians
    with torch.no_grad():
        grid = torch.rand(n, 2, generator=torch.Generator().manual_seed(0)) * 2.4 - 1.2
        field.splats["means"][:] = torch.cat([grid, torch.zeros(n, 1)], dim=1)
        assert count_floaters(field, scene)["floaters"] == 0
        field.splats["means"][:5] = torch.tensor([50.0, 50.0, 50.0])
    floaters = count_floaters(field, scene)
    assert floaters["floaters"] == 5 and floaters["fraction"] == pytest.approx(5 / n)


def test_every_ablation_case_changes_the_defaults():
    from dataclasses import replace

    from langfield.eval.ablate import CASES, DEFAULT_CASES

    base = TrainConfig()
    assert set(DEFAULT_CASES) <= set(CASES)
    for case, change in CASES.items():
        if case != "full":
            assert replace(base, **change) != base, case  # a case equal to the defaults trains full again


def test_ablate_help_names_every_case():
    import argparse

    from langfield.cli import build_parser
    from langfield.eval.ablate import CASES

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    cases_help = next(a.help for a in sub.choices["ablate"]._actions if a.dest == "cases")
    listed = cases_help.split("(default")[0]
    assert [c for c in CASES if c not in listed.replace(",", " ").split()] == []


def test_cases_that_would_train_full_again_are_skipped(room):
    from langfield.eval.ablate import run_ablation

    base = TrainConfig(iterations=1, num_gaussians=100, init="random", lop=False, random_background=False)
    # The base already has both changes.
    with pytest.warns(UserWarning, match=r"no-random-background.*no-lop|no-lop.*no-random-background"):
        rows = run_ablation(
            load_scene(room), base, ("full", "no-random-background", "no-lop"), progress=False
        )
    assert set(rows) == {"full"}


@pytest.mark.slow
def test_ablate_command_writes_one_table(room, tmp_path):
    out = tmp_path / "ablate"
    code = main(["ablate", str(room), "--out", str(out), "--iterations", "4", "--cases", "full,no-depth"])
    assert code == 0
    table = json.loads((out / "ablation.json").read_text())
    assert set(table["rows"]) == {"full", "no-depth"}
    assert table["rows"]["full"]["depth_abs_rel"] is not None
    assert "| no-depth |" in (out / "ablation.md").read_text()
    assert main(["ablate", str(room), "--out", str(out), "--cases", "nope"]) == 2


def test_observed_fraction_is_one_on_the_training_views_and_high_on_the_room(room):
    from langfield.eval.geometry import observed_fraction

    scene = load_scene(room)
    train = observed_fraction(scene, split="train")
    assert train is not None and train["mean"] == pytest.approx(1.0, abs=1e-3)  # each pixel sees itself
    test = observed_fraction(scene)
    assert set(test["views"]) == set(scene.names("test")) and 0.5 < test["mean"] <= 1.0
    # Fewer witnesses never see more: with one training view no test view's fraction grows, some drop.
    one = observed_fraction(load_scene(room, views=[scene.names("train")[0]]))
    drops = [one["views"][n] - test["views"][n] for n in scene.names("test")]
    assert max(drops) <= 1e-9 and min(drops) < -0.01
