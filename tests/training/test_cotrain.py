"""Co-training (langfield/training/cotrain.py, CoR-GS): the unmatched Gaussians, co-pruning with the
optimizers kept in step, the agreement term, and a run with both."""

from __future__ import annotations

import pytest
import torch

from langfield import TrainConfig, load_scene, train
from langfield.training.cotrain import co_prune, coprune_due, coreg_terms, unmatched
from langfield.training.setup import prepare


@pytest.fixture(scope="module")
def scene(room_factory):
    return load_scene(room_factory(64, 48))


def _run(scene, **cfg):
    base = dict(iterations=30, num_gaussians=300, co_train=True, language=False, depth=False)
    return prepare(scene, TrainConfig(**{**base, **cfg}), progress=False)


def test_unmatched_points_are_those_without_another_within_the_distance() -> None:
    points = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [5.0, 5.0, 5.0], [5.0, 5.0, 5.0]])
    others = torch.tensor([[0.05, 0.0, 0.0], [1.0, 0.2, 0.0]])
    assert unmatched(points, others, 0.1).tolist() == [False, True, True, True]
    assert unmatched(points, others, 0.25).tolist() == [False, False, True, True]
    assert unmatched(points, others[:0], 1.0).tolist() == [True] * 4  # nothing to match
    assert unmatched(points[:0], others, 1.0).shape == (0,)
    assert not unmatched(points, points, 1e-9).any()  # each point matches itself, duplicates too


def test_the_partner_starts_where_the_field_starts_with_its_own_state_and_no_language(scene) -> None:
    run = _run(scene, language=None)
    partner = run.partner
    assert torch.equal(partner.field.splats["means"], run.field.splats["means"])
    assert partner.field.splats["means"] is not run.field.splats["means"]
    assert partner.field.language is None and partner.targets is None
    a, b = run.field.color.state_dict(), partner.field.color.state_dict()
    assert any(not torch.equal(a[k], b[k]) for k in a)  # seed + 1: the two fields differ where unfixed
    assert partner.strategy.field is partner.field and partner.strategy.state is not run.strategy.state
    assert partner.rendered is not run.rendered and partner.drop_generator is not run.drop_generator
    assert not set(map(id, partner.optimizers.values())) & set(map(id, run.optimizers.values()))
    splits = [r.strategy.state["generator"].initial_seed() for r in (run, partner)]
    assert splits[0] != splits[1]  # the split children land apart
    assert run.coprune_distance > 0
    assert prepare(scene, TrainConfig(iterations=5), progress=False).partner is None


def test_co_pruning_removes_what_the_other_field_lacks_and_keeps_the_optimizers_in_step(scene) -> None:
    run = _run(scene)
    partner = run.partner
    n = run.field.num_gaussians
    moved = torch.zeros(n, dtype=torch.bool)
    moved[:7] = True
    with torch.no_grad():  # seven of the partner's Gaussians leave: both fields lose those seven
        partner.field.splats["means"][moved] += 100.0 * run.coprune_distance
    for r in (run, partner):  # Adam's moments exist, as after a step
        color = r.field.render(scene.camera(scene.names("train")[0]), language=False).rgb
        color.mean().backward()
        for opt in r.optimizers.values():
            opt.step()
    kept = [{k: p[~moved].clone() for k, p in r.field.splats.items()} for r in (run, partner)]
    moments = [{k: r.optimizers[k].state[p]["exp_avg"][~moved].clone() for k, p in r.field.splats.items()}
               for r in (run, partner)]  # fmt: skip
    record = co_prune(run, 100)
    assert record == {"iteration": 100, "removed": 7, "partner_removed": 7}
    for r, values, moment in zip((run, partner), kept, moments, strict=True):
        for name, p in r.field.splats.items():  # the kept rows, with their own Adam moments
            assert torch.equal(p.detach(), values[name]), name
            assert torch.equal(r.optimizers[name].state[p]["exp_avg"], moment[name]), name
        assert all(len(v) == n - 7 for v in r.strategy.state.values() if isinstance(v, torch.Tensor))


def test_co_pruning_keeps_a_field_it_would_empty(scene) -> None:
    run = _run(scene)
    with torch.no_grad():
        run.partner.field.splats["means"] += 100.0 * run.coprune_distance
    n = run.field.num_gaussians
    assert co_prune(run, 100) == {"iteration": 100, "removed": 0, "partner_removed": 0}
    assert run.field.num_gaussians == run.partner.field.num_gaussians == n


def test_co_pruning_runs_every_interval_after_densification_begins_and_not_at_the_end(scene) -> None:
    run = _run(scene, iterations=1500, coprune_every=500, refine_start=300)
    assert [i for i in range(1, 1501) if coprune_due(run, i)] == [500, 1000]
    off = _run(scene, coprune_every=0)  # prepared once: each prepare sweeps the start
    assert not any(coprune_due(off, i) for i in range(1, 31))


def test_the_agreement_term_is_zero_for_equal_fields_and_pulls_both_when_they_differ(scene) -> None:
    run = _run(scene)
    partner = run.partner
    partner.field.color.load_state_dict(run.field.color.state_dict())
    same = [float(t.detach()) for t in coreg_terms(run, None, None)]
    assert same == pytest.approx([0.0, 0.0], abs=1e-6)
    with torch.no_grad():
        partner.field.splats["opacity_logits"] -= 1.0
    main, other = coreg_terms(run, None, None)
    assert float(main.detach()) > 1e-3
    assert float(main.detach()) == pytest.approx(float(other.detach()), rel=1e-5)
    main.backward()  # each field's term reaches that field alone: the other render is held fixed
    assert float(run.field.splats["opacity_logits"].grad.abs().sum()) > 0
    assert partner.field.splats["opacity_logits"].grad is None
    other.backward()
    assert float(partner.field.splats["opacity_logits"].grad.abs().sum()) > 0


@pytest.mark.slow
def test_a_co_trained_run_records_its_rounds_and_the_agreement_term(scene) -> None:
    cfg = TrainConfig(
        iterations=30, num_gaussians=300, co_train=True, coprune_every=10, refine_start=5, refine_every=5,
        grad_threshold=1e-7, language=False, depth=False,
    )  # fmt: skip
    field = train(scene, cfg, progress=False)
    record = field.meta["co_training"]
    assert [r["iteration"] for r in record["co_pruned"]] == [10, 20]
    assert record["partner_gaussians"] > 0 and record["coprune_distance"] > 0
    logged = [e for e in field.meta["loss_terms"]]
    assert logged[-1]["steps"]["coreg"] == 30 - round(cfg.half_resolution_until * 30)  # every full-size step
    assert all(torch.isfinite(p).all() for p in field.splats.values())
    again = train(scene, cfg, progress=False)
    assert torch.equal(again.splats["means"], field.splats["means"])  # both fields' draws are seeded
