"""Training-free language (langfield/training/aggregate.py): rendering-weighted means of view latents."""

from __future__ import annotations

import pytest
import torch

from langfield import TrainConfig, load_scene
from langfield.training.aggregate import (
    MIN_REGISTER_WEIGHT,
    aggregate_latents,
    register_entries,
    with_latents,
)
from langfield.training.setup import build_field
from langfield.training.targets import language_targets

W, H = 40, 30


@pytest.fixture(scope="module")
def scene(room_factory):
    return load_scene(room_factory(W, H))


@pytest.fixture(scope="module")
def field(scene):
    torch.manual_seed(0)
    field = build_field(scene, TrainConfig(num_gaussians=24, init="random"))
    with torch.no_grad():  # opaque, wide Gaussians so that every one is seen by some view
        field.splats["opacity_logits"].fill_(2.0)
        field.splats["log_scales"].add_(1.0)
    return field


def _targets(scene):
    return language_targets(scene, TrainConfig(autoencoder_iterations=20), progress=False)


def _weights_by_forward_passes(field, cam) -> torch.Tensor:
    """[N, H, W] each Gaussian's blending weight at every pixel, from one forward render per Gaussian
    whose latent is 1 in one channel and 0 elsewhere (no gradient involved)."""
    n = field.num_gaussians
    maps = []
    with torch.no_grad():
        for i in range(n):
            latents = torch.zeros(n, 3, 3)
            latents[i, 0, 0] = 1.0
            maps.append(with_latents(field, latents).render(cam, hard_depth=False).latents[0, ..., 0])
    return torch.stack(maps)


@pytest.mark.slow
def test_the_gradient_pass_equals_the_weighted_sums_of_forward_renders(field, scene) -> None:
    targets = _targets(scene)
    names = scene.names("train")
    cameras = {n: scene.camera(n) for n in names}
    latents, weight = aggregate_latents(field, cameras, targets.latents, targets.valid)
    assert all(p.requires_grad for p in field.splats.values())  # the probe froze its own copies only
    total = torch.zeros(field.num_gaussians, 3, 3)
    expected_weight = torch.zeros(field.num_gaussians, 3)
    for name in names:
        w = _weights_by_forward_passes(field, cameras[name])  # [N, H, W]
        valid = targets.valid[name].float()  # [3, H, W]
        total += torch.einsum("nhw,lhwc->nlc", w, targets.latents[name] * valid[..., None])
        expected_weight += torch.einsum("nhw,lhw->nl", w, valid)
    torch.testing.assert_close(weight, expected_weight, rtol=1e-4, atol=1e-4)
    seen = expected_weight > 1e-3
    assert int(seen[:, 0].sum()) >= 5  # the test exercises real sums
    expected = total / total.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    torch.testing.assert_close(latents[seen], expected[seen], rtol=1e-4, atol=1e-4)
    assert torch.allclose(latents[seen].norm(dim=-1), torch.ones(int(seen.sum())), atol=1e-5)


def _hidden_field(scene, cam):
    """A field whose Gaussian 0 lies behind ``cam`` and Gaussian 1 exactly at its centre."""
    hidden = build_field(scene, TrainConfig(num_gaussians=24, init="random"))
    with torch.no_grad():
        hidden.splats["means"][0] = torch.from_numpy(cam.c2w[:3, 3] - cam.forward).float()
        hidden.splats["means"][1] = torch.from_numpy(cam.c2w[:3, 3]).float()
    return hidden


def test_a_gaussian_no_view_sees_and_a_level_without_masks_give_zero(field, scene) -> None:
    targets = _targets(scene)
    name = scene.names("train")[0]
    cam = scene.camera(name)
    hidden = _hidden_field(scene, cam)
    valid = {name: targets.valid[name].clone()}
    valid[name][1] = False  # no masks at the part level
    latents, weight = aggregate_latents(hidden, {name: cam}, targets.latents, valid)
    assert torch.isfinite(latents).all() and torch.isfinite(weight).all()
    assert weight[:2].abs().max() == 0 and latents[:2].abs().max() == 0
    assert weight[:, 1].abs().max() == 0 and latents[:, 1].abs().max() == 0


def test_with_latents_shares_the_geometry_and_renders_the_given_latents(field, scene) -> None:
    constant = torch.nn.functional.normalize(torch.tensor([1.0, 2.0, 2.0]), dim=0)
    other = with_latents(field, constant.expand(field.num_gaussians, 3, 3))
    assert other.splats["means"] is field.splats["means"] and other.language is None
    with torch.no_grad():
        out = other.render(scene.camera(0), hard_depth=False)
    covered = out.alpha > 0.999
    assert covered.any()
    torch.testing.assert_close(
        out.latents[:, covered], constant.expand(3, int(covered.sum()), 3), atol=1e-3, rtol=0
    )


def test_no_gaussians_and_a_view_without_targets(field, scene) -> None:
    targets = _targets(scene)
    name = scene.names("train")[0]
    empty = with_latents(field, torch.zeros(field.num_gaussians, 3, 3))
    keep = torch.zeros(field.num_gaussians, dtype=torch.bool)
    empty.splats = torch.nn.ParameterDict(
        {k: torch.nn.Parameter(v.detach()[keep]) for k, v in empty.splats.items()}
    )
    latents, weight = aggregate_latents(empty, {name: scene.camera(name)}, targets.latents, targets.valid)
    assert latents.shape == (0, 3, 3) and weight.shape == (0, 3)
    with pytest.raises(ValueError, match="no target latents for views"):
        aggregate_latents(field, {"elsewhere": scene.camera(name)}, targets.latents, targets.valid)


def _random_entries(scene, names, sizes, seed=0) -> dict[str, torch.Tensor]:
    """Per view [L, H, W]: each pixel a random entry of its level, or -1 (no mask); blocks of 10 x 10
    pixels, so that masks cover several pixels as segments do."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for name in names:
        cam = scene.camera(name)
        levels = []
        for size in sizes:
            coarse = torch.randint(-1, size, (cam.height // 10 + 1, cam.width // 10 + 1), generator=g)
            levels.append(coarse.repeat_interleave(10, 0).repeat_interleave(10, 1)[: cam.height, : cam.width])
        out[name] = torch.stack(levels)
    return out


@pytest.mark.parametrize("chunk_values", [1, 40 * 30 * 3, 1 << 24])
def test_registered_entries_are_the_masks_with_the_most_weight(field, scene, chunk_values) -> None:
    """Against each Gaussian's weight per pixel from forward renders: per entry the summed weight, the
    entry with the most (the first of equal ones), -1 below MIN_REGISTER_WEIGHT; entries in chunks of
    one channel, of three, and all at once."""
    names = scene.names("train")
    cameras = {n: scene.camera(n) for n in names}
    sizes = [4, 3, 0]  # the whole level has no entries
    entries = _random_entries(scene, names, sizes)
    got = register_entries(field, cameras, entries, sizes, chunk_values=chunk_values)
    assert got.shape == (field.num_gaussians, 3) and got.dtype == torch.long
    per_entry = [torch.zeros(field.num_gaussians, size) for size in sizes]
    for name in names:
        w = _weights_by_forward_passes(field, cameras[name])  # [N, H, W]
        for level, size in enumerate(sizes):
            for e in range(size):
                per_entry[level][:, e] += (w * (entries[name][level] == e)).sum(dim=(1, 2))
    for level, size in enumerate(sizes):
        if size == 0:
            assert (got[:, level] == -1).all()
            continue
        total = per_entry[level].sum(dim=1)
        expected = torch.where(total >= MIN_REGISTER_WEIGHT, per_entry[level].argmax(dim=1), -1)
        assert torch.equal(got[:, level], expected)
        assert int((expected >= 0).sum()) >= 5 and len(torch.unique(expected[expected >= 0])) >= 2


def test_registration_leaves_unseen_gaussians_and_empty_fields_out(field, scene) -> None:
    name = scene.names("train")[0]
    cam = scene.camera(name)
    hidden = _hidden_field(scene, cam)
    entries = _random_entries(scene, [name], [2, 2, 2])
    entries[name][1] = -1  # no masks at the part level
    got = register_entries(hidden, {name: cam}, entries, [2, 2, 2])
    assert (got[:2] == -1).all() and (got[:, 1] == -1).all()
    keep = torch.zeros(field.num_gaussians, dtype=torch.bool)
    empty = with_latents(field, torch.zeros(field.num_gaussians, 3, 3))
    empty.splats = torch.nn.ParameterDict(
        {k: torch.nn.Parameter(v.detach()[keep]) for k, v in empty.splats.items()}
    )
    assert register_entries(empty, {name: cam}, entries, [2, 2, 2]).shape == (0, 3)
    with pytest.raises(ValueError, match="no mask entries for views"):
        register_entries(field, {"elsewhere": cam}, entries, [2, 2, 2])
