"""Image metrics on [H, W, C] tensors in [0, 1]."""

from __future__ import annotations

import kornia
import torch
from torch import Tensor


def _to_bchw(image: Tensor) -> Tensor:
    if image.dim() != 3:
        raise ValueError(f"expected an image of shape [H, W, C], got {tuple(image.shape)}")
    return image.permute(2, 0, 1)[None].float()


def psnr(prediction: Tensor, target: Tensor) -> float:
    """Peak signal-to-noise ratio in dB of images [H, W, C] with values in [0, 1]."""
    mse = torch.mean((prediction.float().clamp(0, 1) - target.float()) ** 2).item()
    return float("inf") if mse == 0 else float(-10.0 * torch.log10(torch.tensor(mse)))


def ssim_map(prediction: Tensor, target: Tensor, window: int = 11) -> Tensor:
    """Per-pixel SSIM [1, C, H, W] (kornia, Gaussian window of 11, as 3DGS evaluates).

    The window shrinks to the image for images smaller than it.
    """
    p, t = _to_bchw(prediction), _to_bchw(target)
    size = min(window, p.shape[-1], p.shape[-2])
    size = size if size % 2 == 1 else size - 1
    return kornia.metrics.ssim(p, t, max(size, 1))


def ssim(prediction: Tensor, target: Tensor) -> float:
    """Mean SSIM of images [H, W, C] with values in [0, 1]."""
    return float(ssim_map(prediction.clamp(0, 1), target).mean())
