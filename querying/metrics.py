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

    The window shrinks to the image for images smaller than it. When a gradient is recorded (a training
    loss), the five local moments are filtered in one call instead of five: the same window, reflect
    padding and formula as ``kornia.metrics.ssim``, equal to it up to float rounding (tested, values and
    gradients) and about twice as fast for the small images of a training step. Without a gradient,
    kornia computes it as it is.
    """
    p, t = _to_bchw(prediction), _to_bchw(target)
    size = min(window, p.shape[-1], p.shape[-2])
    size = max(size if size % 2 == 1 else size - 1, 1)
    if torch.is_grad_enabled() and (p.requires_grad or t.requires_grad):
        return _ssim_map_stacked(p, t, size)
    return kornia.metrics.ssim(p, t, size)


def _ssim_map_stacked(p: Tensor, t: Tensor, size: int, eps: float = 1e-12) -> Tensor:
    """``kornia.metrics.ssim(p, t, size)`` ("same" padding, max_val 1) with the moments filtered together."""
    c = p.shape[1]
    kernel = kornia.filters.get_gaussian_kernel1d(size, 1.5, dtype=p.dtype)
    moments = kornia.filters.filter2d_separable(torch.cat([p, t, p * p, t * t, p * t], dim=1), kernel, kernel)
    mu1, mu2, m11, m22, m12 = moments.split(c, dim=1)
    mu1_sq, mu2_sq, mu1_mu2 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    num = (2.0 * mu1_mu2 + c1) * (2.0 * (m12 - mu1_mu2) + c2)
    den = (mu1_sq + mu2_sq + c1) * ((m11 - mu1_sq) + (m22 - mu2_sq) + c2)
    return num / (den + eps)


def ssim(prediction: Tensor, target: Tensor) -> float:
    """Mean SSIM of images [H, W, C] with values in [0, 1]."""
    return float(ssim_map(prediction.clamp(0, 1), target).mean())
