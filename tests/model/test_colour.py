"""Tests of the colour field."""

from __future__ import annotations

import pytest
import torch

from langfield.model.colour import ColorField, fibonacci_directions, frequency_encoding
from langfield.model.hashgrid import HashGridConfig

CFG = HashGridConfig(n_levels=8, log2_table_size=12, base_resolution=4, finest_resolution=64)


def _field(seed: int = 0) -> ColorField:
    torch.manual_seed(seed)
    return ColorField(CFG, torch.zeros(3), 1.0)


def _dirs(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)


def _points(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g) * 2 - 1


def test_shapes_and_range() -> None:
    rgb = _field()(_points(50), _dirs(50))
    assert rgb.shape == (50, 3)
    assert (rgb > 0).all() and (rgb < 1).all()


def test_frequency_encoding_width() -> None:
    assert frequency_encoding(_dirs(4), 4).shape == (4, 27)
    assert frequency_encoding(_dirs(4), 0).shape == (4, 3)
    assert frequency_encoding(_dirs(4), -1).shape == (4, 0)


def test_without_the_direction_the_colour_is_the_same_from_every_side() -> None:
    torch.manual_seed(0)
    field = ColorField(CFG, torch.zeros(3), 1.0, n_freqs=-1)
    p = _points(20)
    a, b = field(p, _dirs(20, seed=1)), field(p, _dirs(20, seed=2))
    assert torch.equal(a, b)
    with pytest.raises(ValueError, match="n_freqs"):
        ColorField(CFG, torch.zeros(3), 1.0, n_freqs=-2)


def test_colour_depends_on_view_direction() -> None:
    field = _field()
    p = _points(20)
    a, b = field(p, _dirs(20, seed=1)), field(p, _dirs(20, seed=2))
    assert (a - b).abs().max() > 1e-4


def test_gradients_reach_table_and_mlp() -> None:
    field = _field()
    means = _points(30).requires_grad_(True)
    field(means, _dirs(30)).sum().backward()
    assert field.grid.table.grad is not None and field.grid.table.grad.abs().sum() > 0
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in field.mlp_parameters())
    assert means.grad is not None and torch.isfinite(means.grad).all()


def test_parameter_groups_partition_the_module() -> None:
    field = _field()
    grid_ids = {id(p) for p in field.grid_parameters()}
    mlp_ids = {id(p) for p in field.mlp_parameters()}
    assert grid_ids == {id(field.grid.table)}
    assert not grid_ids & mlp_ids
    assert grid_ids | mlp_ids == {id(p) for p in field.parameters()}


def test_tiny_fit_lowers_the_loss_tenfold() -> None:
    field = _field()
    p, d = _points(500), _dirs(500)
    target = 0.5 + 0.4 * torch.stack(
        [torch.sin(2 * p[:, 0]), torch.cos(3 * p[:, 1]), torch.sin(p[:, 0] + 2 * p[:, 2])], dim=-1
    )
    # DNGaussian's learning rates: grid 5e-3, MLP 5e-4.
    opt = torch.optim.Adam(
        [
            {"params": list(field.grid_parameters()), "lr": 5e-3},
            {"params": list(field.mlp_parameters()), "lr": 5e-4},
        ]
    )
    losses = []
    for _ in range(200):
        loss = (field(p, d) - target).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] / 10


def test_bake_dc_is_the_mean_over_fixed_directions() -> None:
    field = _field()
    p = _points(7)
    dirs = fibonacci_directions(16)
    want = torch.stack([field(p, dirs[i].expand(7, 3)) for i in range(16)]).mean(0)
    got = field.bake_dc(p, n_dirs=16, chunk=3)
    torch.testing.assert_close(got, want)
    assert field.bake_dc(p).shape == (7, 3)
    assert field.bake_dc(p[:0]).shape == (0, 3)


def test_fibonacci_directions_are_unit_and_spread() -> None:
    d = fibonacci_directions(64)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(64))
    assert d.mean(0).abs().max() < 0.05


def test_rejects_mismatched_shapes() -> None:
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        _field()(_points(4), _dirs(5))
