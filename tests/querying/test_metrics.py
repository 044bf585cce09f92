"""Tests of the image metrics (querying/metrics.py)."""

from __future__ import annotations

import math

import pytest
import torch

from querying.metrics import psnr, ssim


def _rand(*shape: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed))


# ---------------------------------------------------------------- PSNR


def test_psnr_of_identical_images_is_inf() -> None:
    image = _rand(12, 10, 3)
    assert psnr(image, image.clone()) == math.inf


@pytest.mark.parametrize("offset", [0.1, 0.01, 0.5])
def test_psnr_of_a_constant_offset(offset) -> None:
    target = torch.full((8, 8, 3), 0.25)
    assert psnr(target + offset, target) == pytest.approx(-10 * math.log10(offset**2), rel=1e-5)


def test_psnr_matches_its_definition_on_noise() -> None:
    a, b = _rand(16, 20, 3, seed=1), _rand(16, 20, 3, seed=2)
    mse = torch.mean((a.double() - b.double()) ** 2).item()
    assert psnr(a, b) == pytest.approx(-10 * math.log10(mse), rel=1e-5)


def test_psnr_clamps_the_prediction_to_the_image_range() -> None:
    target = torch.ones(4, 4, 3)
    assert psnr(target + 0.5, target) == math.inf
    assert psnr(torch.full((4, 4, 3), -1.0), torch.zeros(4, 4, 3)) == math.inf


def test_psnr_of_one_pixel() -> None:
    assert psnr(torch.full((1, 1, 3), 0.6), torch.full((1, 1, 3), 0.5)) == pytest.approx(20.0, rel=1e-5)


# ---------------------------------------------------------------- SSIM


@pytest.mark.parametrize("shape", [(48, 64, 3), (5, 5, 3), (1, 1, 3), (4, 6, 3), (1, 9, 3)])
def test_ssim_of_identical_images_is_one(shape) -> None:
    image = _rand(*shape)
    assert ssim(image, image.clone()) == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize("shape", [(48, 64, 3), (5, 5, 3), (1, 1, 3)])
def test_ssim_of_noise_is_below_one(shape) -> None:
    value = ssim(_rand(*shape, seed=1), _rand(*shape, seed=2))
    assert math.isfinite(value) and -1.0 <= value < 0.99


def test_ssim_drops_as_noise_grows() -> None:
    image = _rand(32, 32, 3)
    noise = torch.randn(32, 32, 3, generator=torch.Generator().manual_seed(5))
    values = [ssim((image + s * noise).clamp(0, 1), image) for s in (0.01, 0.05, 0.2)]
    assert values[0] > values[1] > values[2]


def test_ssim_is_symmetric() -> None:
    a, b = _rand(20, 20, 3, seed=3), _rand(20, 20, 3, seed=4)
    assert ssim(a, b) == pytest.approx(ssim(b, a), abs=1e-6)


def test_ssim_rejects_images_without_a_channel_axis() -> None:
    with pytest.raises(ValueError, match=r"\[H, W, C\]"):
        ssim(torch.rand(8, 8), torch.rand(8, 8))
