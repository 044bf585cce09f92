"""Image metrics on [H, W, C] tensors in [0, 1] (the evaluation's: PSNR, and SSIM by kornia)."""

from __future__ import annotations

import kornia
import torch
from torch import Tensor


def to_bchw(image: Tensor) -> Tensor:
    """[1, C, H, W] float32 of an [H, W, C] image."""
    if image.dim() != 3:
        raise ValueError(f"expected an image of shape [H, W, C], got {tuple(image.shape)}")
    return image.permute(2, 0, 1)[None].float()


def psnr(prediction: Tensor, target: Tensor) -> float:
    """Peak signal-to-noise ratio in dB of images [H, W, C] with values in [0, 1]."""
    mse = torch.mean((prediction.float().clamp(0, 1) - target.float()) ** 2).item()
    return float("inf") if mse == 0 else float(-10.0 * torch.log10(torch.tensor(mse)))


def ssim_window(height: int, width: int, window: int = 11) -> int:
    """SSIM's Gaussian window (11, as 3DGS evaluates), shrunk to an odd size that fits the image."""
    size = min(window, width, height)
    return max(size if size % 2 == 1 else size - 1, 1)


def ssim(prediction: Tensor, target: Tensor) -> float:
    """Mean SSIM of images [H, W, C] with values in [0, 1] (``kornia.metrics.ssim``)."""
    p, t = to_bchw(prediction.clamp(0, 1)), to_bchw(target)
    return float(kornia.metrics.ssim(p, t, ssim_window(p.shape[-2], p.shape[-1])).mean())
