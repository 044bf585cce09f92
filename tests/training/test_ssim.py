"""Tests of the training loss's SSIM (langfield/training/ssim.py) against kornia's."""

from __future__ import annotations

import kornia
import pytest
import torch

from langfield.training.ssim import ssim_map


def _rand(*shape: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize(
    "shape, window",
    [((48, 64, 3), 11), ((5, 5, 3), 5), ((4, 6, 3), 3), ((1, 1, 3), 1), ((2, 30, 3), 1)],
)
def test_ssim_window_shrinks_to_the_image(shape, window) -> None:
    a, b = _rand(*shape, seed=1), _rand(*shape, seed=2)
    m = ssim_map(a, b)
    assert m.shape == (1, shape[2], shape[0], shape[1])
    expected = kornia.metrics.ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], window)
    torch.testing.assert_close(m, expected)


@pytest.mark.parametrize("shape", [(48, 64, 3), (5, 7, 3), (2, 30, 3), (1, 1, 3)])
def test_ssim_map_with_gradient_matches_kornia_values_and_gradients(shape) -> None:
    # The training path filters the five moments in one call; kornia filters them one by one.
    a = _rand(*shape, seed=6).requires_grad_(True)
    b = _rand(*shape, seed=7).requires_grad_(True)
    m = ssim_map(a, b)
    window = min(11, shape[0], shape[1])
    window = max(window if window % 2 else window - 1, 1)
    a_ref, b_ref = a.detach().clone().requires_grad_(True), b.detach().clone().requires_grad_(True)
    expected = kornia.metrics.ssim(a_ref.permute(2, 0, 1)[None], b_ref.permute(2, 0, 1)[None], window)
    torch.testing.assert_close(m, expected)
    weights = torch.rand(expected.shape, generator=torch.Generator().manual_seed(8))
    (m * weights).sum().backward()
    (expected * weights).sum().backward()
    # Float rounding only: tiny windows cancel (sigma^2 = E[x^2] - mu^2), so the bound scales with the
    # gradient's size.
    for grad, ref in ((a.grad, a_ref.grad), (b.grad, b_ref.grad)):
        torch.testing.assert_close(grad, ref, rtol=1e-3, atol=1e-4 * float(ref.abs().max()))
