"""Tests of training (langfield.training: setup, loop, losses): determinism, loss, densification, config
checks, meta, callbacks."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from langfield import LanguageField, TrainConfig, load_scene, train
from langfield.model import gaussians as G
from langfield.training import setup as T
from langfield.training.loop import evaluate_psnr
from langfield.training.losses import color_loss
from langfield.training.stages import STAGES, StageClock


@pytest.fixture(scope="module")
def scene_dir(room_factory):
    return room_factory(64, 48)


@pytest.fixture(scope="module")
def scene(scene_dir):
    return load_scene(scene_dir)


def _train(scene, **cfg) -> LanguageField:
    return train(scene, TrainConfig(**cfg), progress=False)


# ---------------------------------------------------------------- determinism and progress


@pytest.mark.slow
def test_same_seed_and_config_give_identical_fields(scene) -> None:
    # Densification (with its random split samples) runs too, so it is covered by the check.
    cfg = dict(iterations=20, num_gaussians=300, seed=3, refine_start=5, refine_every=5, grad_threshold=1e-7)
    a, b = _train(scene, **cfg), _train(scene, **cfg)
    assert a.num_gaussians == b.num_gaussians != 300
    for key in a.splats:
        assert torch.equal(a.splats[key], b.splats[key]), key
    for (name, pa), pb in zip(a.color.state_dict().items(), b.color.state_dict().values(), strict=True):
        assert torch.equal(pa, pb), name


def test_stage_clock_times_every_stage_without_changing_the_training(scene) -> None:
    cfg = dict(iterations=12, num_gaussians=300, seed=3, refine_start=5, refine_every=5, grad_threshold=1e-7)
    clock = StageClock()
    timed = train(scene, TrainConfig(**cfg, virtual_every=2), progress=False, clock=clock)
    plain = _train(scene, **cfg, virtual_every=2)
    for key in plain.splats:  # the clock only reads the time
        assert torch.equal(timed.splats[key], plain.splats[key]), key
    report = clock.report()
    assert report["iterations"] == 12 and report["seconds"] > 0
    stages = report["stages"]
    assert set(stages) == {*STAGES, "other"}
    for name in (
        "render",
        "hash grids",
        "colour loss",
        "virtual view",
        "other terms",
        "backward",
        "optimizer",
    ):
        assert stages[name]["seconds"] > 0, name
    assert sum(v["share"] for v in stages.values()) == pytest.approx(1.0)
    assert report["seconds"] <= timed.meta.train_seconds + 1e-9  # the loop's own clock counts the same


def test_stage_clock_switched_off_counts_nothing_and_refuses_unknown_stages() -> None:
    off = StageClock(enabled=False)
    with off.stage("render"), off.stage("not a stage"):
        pass
    off.add_iteration(1.0)
    assert off.report()["iterations"] == 0 and off.report()["stages"]["render"]["share"] is None
    with (
        pytest.raises(ValueError, match="unknown training stage 'rendering'"),
        StageClock().stage("rendering"),
    ):
        pass


@pytest.mark.slow
def test_different_seeds_give_different_fields(scene) -> None:
    a = _train(scene, iterations=0, num_gaussians=300, seed=0)
    b = _train(scene, iterations=0, num_gaussians=300, seed=1)
    assert not torch.equal(a.splats["means"], b.splats["means"])


@pytest.mark.slow
def test_zero_iterations_returns_the_initial_field(scene) -> None:
    field = _train(scene, iterations=0, num_gaussians=300, seed=2, init="random")
    init = G.init_gaussians(np.asarray(field.meta["bounds"]), 300, seed=2)
    for key in init:
        assert torch.equal(field.splats[key], init[key]), key
    assert field.meta["iterations"] == 0 and field.meta["num_gaussians"] == 300


def test_zero_iterations_from_the_photos_returns_their_start_points(scene) -> None:
    from langfield.training.start import start_points

    field = _train(scene, iterations=0, num_gaussians=300, seed=2, init="dense")
    cams = scene.cameras("train")
    bounds = np.asarray(field.meta["bounds"])
    start = start_points("dense", cams, [scene.image(c.name) for c in cams], bounds, 300, seed=2)
    assert torch.equal(field.splats["means"], torch.from_numpy(start.points))
    assert field.meta["num_gaussians"] == 300 and field.meta["init"]["used"] == "dense"
    assert field.meta["init"]["photo_points"] > 0


@pytest.mark.slow
def test_training_lowers_the_colour_loss(scene) -> None:
    before = _train(scene, iterations=0, num_gaussians=500)
    after = _train(scene, iterations=60, num_gaussians=500)
    assert evaluate_psnr(after, scene, "train") > evaluate_psnr(before, scene, "train") + 1.0
    assert evaluate_psnr(after, scene, "test") > evaluate_psnr(before, scene, "test")


@pytest.mark.slow
def test_densification_changes_the_count_and_keeps_optimizers_in_step(scene, monkeypatch) -> None:
    captured: dict[str, torch.optim.Optimizer] = {}
    make_optimizers = T.make_optimizers

    def capture(field, extent, cfg):
        captured.update(make_optimizers(field, extent, cfg))
        return captured

    monkeypatch.setattr(T, "make_optimizers", capture)
    counts = []
    field = train(
        scene,
        TrainConfig(iterations=40, num_gaussians=600, refine_start=10, refine_every=10, grad_threshold=2e-4),
        progress=False,
        callback=lambda step, seconds, f: counts.append(f.num_gaussians),
        callback_every=5,
    )
    n = field.num_gaussians
    assert n != 600 and len(set(counts)) > 1
    assert field.meta["num_gaussians"] == n and field.meta["num_gaussians_init"] == 600
    for name, p in field.splats.items():
        assert p.shape[0] == n, name
        opt = captured[name]
        assert opt.param_groups[0]["params"][0] is p, name
        state = opt.state[p]
        assert state["exp_avg"].shape == p.shape and state["exp_avg_sq"].shape == p.shape, name
    cam = scene.camera(scene.names("test")[0])
    r = field.render(cam)
    assert r.means2d.shape == (n, 2) and torch.isfinite(r.rgb).all()
    color_loss(r.rgb, torch.from_numpy(scene.image(cam.name))).backward()
    for opt in captured.values():
        opt.step()  # Adam accepts the edited parameters and moments
    assert all(torch.isfinite(p).all() for p in field.splats.values())


def test_no_densify_keeps_the_count(scene) -> None:
    field = _train(scene, iterations=30, num_gaussians=400, refine_start=5, refine_every=5, densify=False)
    assert field.num_gaussians == 400


# ---------------------------------------------------------------- configuration checks


def test_bounds_override_is_used(scene) -> None:
    bounds = ((-1.0, -0.5, 0.0), (1.0, 0.5, 1.5))
    field = _train(scene, iterations=0, num_gaussians=300, bounds=bounds)
    assert field.meta["bounds"] == [list(bounds[0]), list(bounds[1])]
    means = field.splats["means"].detach().numpy()
    assert (means >= np.array(bounds[0]) - 1e-6).all() and (means <= np.array(bounds[1]) + 1e-6).all()


@pytest.mark.parametrize(
    "bounds",
    [
        ((1.0, 0.0, 0.0), (-1.0, 1.0, 1.0)),  # max < min
        ((0.0, 0.0, 0.0), (0.0, 1.0, 1.0)),  # flat
        ((float("nan"), 0.0, 0.0), (1.0, 1.0, 1.0)),
        ((0.0, 0.0), (1.0, 1.0)),  # not 3D
    ],
    ids=["max_below_min", "flat", "nan", "2d"],
)
def test_invalid_bounds_raise(scene, bounds) -> None:
    with pytest.raises(ValueError, match="bounds"):
        _train(scene, iterations=0, num_gaussians=300, bounds=bounds)


def test_scene_without_training_views_raises(scene_dir, tmp_path) -> None:
    folder = tmp_path / "all_test"
    shutil.copytree(scene_dir / "images", folder / "images")
    meta = json.loads((scene_dir / "transforms.json").read_text())
    for frame in meta["frames"]:
        frame["split"] = "test"
    (folder / "transforms.json").write_text(json.dumps(meta))
    scene = load_scene(folder)
    assert scene.names("train") == []
    with pytest.raises(ValueError, match="no training views"):
        _train(scene, iterations=1, num_gaussians=300)


def test_negative_iterations_raise(scene) -> None:
    with pytest.raises(ValueError, match="iterations"):
        _train(scene, iterations=-1, num_gaussians=300)


@pytest.mark.slow
def test_opacity_penalty_fades_gaussians(scene) -> None:
    cfg = dict(iterations=30, num_gaussians=400, densify=False, seed=4)
    plain, penalised = _train(scene, lambda_opacity=0.0, **cfg), _train(scene, lambda_opacity=1.0, **cfg)
    mean_plain = G.opacities(plain.splats).mean().item()
    mean_penalised = G.opacities(penalised.splats).mean().item()
    assert mean_penalised < 0.8 * mean_plain
    assert all(torch.isfinite(p).all() for p in penalised.splats.values())


@pytest.mark.parametrize("weight", [-0.1, float("nan"), float("inf")])
def test_invalid_opacity_penalty_raises(scene, weight) -> None:
    with pytest.raises(ValueError, match="lambda_opacity"):
        _train(scene, iterations=1, num_gaussians=50, lambda_opacity=weight)


# ---------------------------------------------------------------- meta


def test_meta_records_timings_and_sizes(scene) -> None:
    field = _train(scene, iterations=20, num_gaussians=500, densify=False)
    m = field.meta
    assert m["iterations"] == 20
    assert m["train_seconds"] > 0
    assert m["iterations_per_second"] == pytest.approx(20 / m["train_seconds"])
    assert m["num_gaussians_init"] == 500 and m["num_gaussians"] == field.num_gaussians == 500
    log2 = m["color_field"]["grid"]["log2_table_size"]
    assert log2 < 19
    assert field.color.grid.table.shape[1] == 2**log2  # the recorded size is the one in use


def test_training_length_is_sized_by_the_views_unless_forced() -> None:
    per, low, high = T.ITERATIONS_PER_VIEW, T.MIN_ITERATIONS, T.MAX_ITERATIONS
    assert T.training_length(None, 3) == {
        "iterations": max(3 * per, low),
        "forced": False,
        "rule": T.training_length(None, 3)["rule"],
    }
    assert T.training_length(None, 1)["iterations"] == low  # the floor
    assert T.training_length(None, 10_000)["iterations"] == high  # the cap
    assert T.training_length(None, 8)["iterations"] == min(max(8 * per, low), high)
    assert T.training_length(7, 3) == {"iterations": 7, "forced": True, "rule": "--iterations"}
    assert T.training_length(0, 3)["iterations"] == 0


def test_train_without_iterations_runs_the_scene_sized_length(scene, monkeypatch, tmp_path) -> None:
    monkeypatch.setattr(T, "ITERATIONS_PER_VIEW", 2)
    monkeypatch.setattr(T, "MIN_ITERATIONS", 1)
    cfg = TrainConfig(num_gaussians=300, densify=False, language=False, depth=False)
    assert cfg.iterations is None
    field = train(scene, cfg, progress=False)
    assert field.meta["iterations"] == 6  # 2 per view x 3 training views
    assert field.meta["training_length"]["forced"] is False
    assert field.meta["config"]["iterations"] == 6
    field.save(tmp_path / "f")
    assert LanguageField.load(tmp_path / "f").meta["training_length"]["iterations"] == 6
    forced = train(
        scene,
        TrainConfig(iterations=4, num_gaussians=300, densify=False, language=False, depth=False),
        progress=False,
    )
    assert forced.meta["iterations"] == 4 and forced.meta["training_length"]["forced"] is True


def test_default_sizes_follow_the_scene(scene) -> None:
    field = _train(scene, iterations=0)
    pixels = 64 * 48
    n = G.num_gaussians_for_scene(np.asarray(field.meta["bounds"]), pixels, 3)
    assert field.meta["num_gaussians_init"] == field.num_gaussians == n
    log2 = field.meta["color_field"]["grid"]["log2_table_size"]
    assert log2 < 19 and 2**log2 >= n
    assert field.meta["iterations_per_second"] is None  # no time was spent training


def test_table_size_override_is_used(scene) -> None:
    field = _train(scene, iterations=0, num_gaussians=300, log2_table_size=13)
    assert field.meta["color_field"]["grid"]["log2_table_size"] == 13
    assert field.color.grid.table.shape[1] == 2**13


# ---------------------------------------------------------------- color_loss


@pytest.mark.parametrize("shape", [(48, 64, 3), (5, 5, 3), (1, 1, 3), (1, 7, 3)])
def test_color_loss_is_zero_for_identical_images(shape) -> None:
    image = torch.rand(shape, generator=torch.Generator().manual_seed(0))
    assert color_loss(image, image.clone()).item() == pytest.approx(0.0, abs=1e-6)


def test_color_loss_is_positive_for_different_images() -> None:
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(16, 16, 3, generator=g), torch.rand(16, 16, 3, generator=g)
    assert color_loss(a, b).item() > 0.1
    assert color_loss(a, (a + 0.05).clamp(0, 1)).item() > 0


def test_color_loss_weights_l1_and_dssim() -> None:
    g = torch.Generator().manual_seed(1)
    a, b = torch.rand(16, 16, 3, generator=g), torch.rand(16, 16, 3, generator=g)
    l1 = (a - b).abs().mean().item()
    assert color_loss(a, b, lambda_dssim=0.0).item() == pytest.approx(l1, rel=1e-5)


@pytest.mark.parametrize(
    "rendered, target",
    [
        (torch.full((1, 1, 3), 0.3), torch.full((1, 1, 3), 0.7)),  # one pixel
        (torch.full((8, 8, 3), 0.5), torch.full((8, 8, 3), 0.5)),  # constant, identical
        (torch.full((8, 8, 3), 0.2), torch.full((8, 8, 3), 0.9)),  # constant, different
        (torch.zeros(8, 8, 3), torch.zeros(8, 8, 3)),  # black
    ],
    ids=["1x1", "constant_same", "constant_different", "black"],
)
def test_color_loss_gradient_is_finite(rendered, target) -> None:
    x = rendered.clone().requires_grad_(True)
    loss = color_loss(x, target)
    loss.backward()
    assert math.isfinite(loss.item())
    assert x.grad is not None and torch.isfinite(x.grad).all()


# ---------------------------------------------------------------- callback


@pytest.mark.parametrize(
    "iterations, every, expected",
    [(25, 10, [10, 20, 25]), (20, 10, [10, 20]), (7, 0, [7]), (0, 5, [0])],
    ids=["remainder", "exact", "end_only", "no_iterations"],
)
def test_callback_steps(scene, iterations, every, expected) -> None:
    calls = []
    field = train(
        scene,
        TrainConfig(iterations=iterations, num_gaussians=300, densify=False),
        progress=False,
        callback=lambda step, seconds, f: calls.append((step, seconds, f)),
        callback_every=every,
    )
    assert [c[0] for c in calls] == expected
    seconds = [c[1] for c in calls]
    assert seconds == sorted(seconds) and all(s >= 0 for s in seconds)
    assert seconds[-1] == field.meta["train_seconds"]
    assert calls[-1][2] is field
