"""The reference rasterizer: pure PyTorch, one tile at a time, differentiated by autograd.

Written to be read and to be the oracle every other backend is tested against. Per tile, every
pixel meets every listed Gaussian in one dense [pixels, Gaussians] block:

    alpha_i = min(0.99, o_i exp(-q_i / 2)),   q_i = d^T conic_i d,  d = pixel - mean_i
    T_i     = prod_{j < i} (1 - alpha_j)                             (front to back)
    C       = sum_i alpha_i T_i c_i + T_final * background

Contributions with alpha < 1/255 are skipped, and a pixel stops at the Gaussian that would bring its
transmittance below 1e-4 (that Gaussian and all behind it are left out), exactly as 3DGS does.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from langfield.raster.binning import ALPHA_MIN, TILE_SIZE

ALPHA_MAX = 0.99
T_MIN = 1e-4


def composite_tile(
    pixels: Tensor,
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    geometry_channels: int | None = None,
) -> tuple[Tensor, Tensor]:
    """Front-to-back compositing of G depth-sorted Gaussians over P pixels.

    Args:
        pixels: [P, 2] pixel-centre coordinates.
        means2d: [G, 2], conics: [G, 3], opacities: [G], colors: [G, C], nearest Gaussian first.
        geometry_channels: channels from this index on see the blending weights detached, so their
            loss trains only their own values, never the geometry (None: all channels do).

    Returns:
        color: [P, C] accumulated colour without background; t_final: [P] remaining transmittance.
    """
    d = pixels[:, None, :] - means2d[None, :, :]
    dx, dy = d[..., 0], d[..., 1]
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    q = a * dx * dx + 2.0 * b * dx * dy + c * dy * dy
    alpha = torch.clamp(opacities[None, :] * torch.exp(-0.5 * q), max=ALPHA_MAX)
    alpha = torch.where((alpha >= ALPHA_MIN) & (q >= 0), alpha, torch.zeros_like(alpha))
    with torch.no_grad():
        # Transmittance after each Gaussian is non-increasing, so this mask is a prefix per pixel.
        keep = torch.cumprod(1.0 - alpha, dim=1) >= T_MIN
    alpha = alpha * keep
    trans_after = torch.cumprod(1.0 - alpha, dim=1)
    trans_before = torch.cat([torch.ones_like(trans_after[:, :1]), trans_after[:, :-1]], dim=1)
    weights = alpha * trans_before
    k = colors.shape[1] if geometry_channels is None else geometry_channels
    color = torch.cat([weights @ colors[:, :k], weights.detach() @ colors[:, k:]], dim=1)
    return color, trans_after[:, -1]


def rasterize_torch(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    tile_offsets: Tensor,
    gaussian_ids: Tensor,
    width: int,
    height: int,
    background: Tensor,
    geometry_channels: int | None = None,
) -> tuple[Tensor, Tensor]:
    """Composites binned Gaussians into an image.

    Args:
        means2d: [N, 2], conics: [N, 3], opacities: [N], colors: [N, C].
        tile_offsets, gaussian_ids: from :func:`langfield.raster.binning.bin_gaussians`.
        background: [C] colour behind everything.
        geometry_channels: channels from this index on pass no gradient to the geometry (means2d,
            conics, opacities); None: all channels do.

    Returns:
        image: [H, W, C] and alpha: [H, W] (= 1 - final transmittance).
    """
    n_channels = colors.shape[1]
    tiles_x = math.ceil(width / TILE_SIZE)
    image = background.reshape(1, 1, -1).expand(height, width, n_channels).clone()
    alpha = colors.new_zeros(height, width)
    offsets = tile_offsets.tolist()
    for tile in range(len(offsets) - 1):
        start, end = offsets[tile], offsets[tile + 1]
        if start == end:
            continue
        x0, y0 = (tile % tiles_x) * TILE_SIZE, (tile // tiles_x) * TILE_SIZE
        x1, y1 = min(x0 + TILE_SIZE, width), min(y0 + TILE_SIZE, height)
        ys, xs = torch.meshgrid(
            torch.arange(y0, y1, dtype=colors.dtype) + 0.5,
            torch.arange(x0, x1, dtype=colors.dtype) + 0.5,
            indexing="ij",
        )
        pixels = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)
        ids = gaussian_ids[start:end]
        color, t_final = composite_tile(
            pixels, means2d[ids], conics[ids], opacities[ids], colors[ids], geometry_channels
        )
        # The background's share is a blending weight too: detached for the channels past the geometry's.
        behind = t_final[:, None].expand(-1, n_channels)
        if geometry_channels is not None and geometry_channels < n_channels:
            behind = torch.cat([behind[:, :geometry_channels], behind[:, geometry_channels:].detach()], dim=1)
        color = color + behind * background[None, :]
        image[y0:y1, x0:x1] = color.reshape(y1 - y0, x1 - x0, n_channels)
        alpha[y0:y1, x0:x1] = (1.0 - t_final).reshape(y1 - y0, x1 - x0)
    if gaussian_ids.numel() == 0:
        # Nothing visible: keep the outputs in the graph so a loss on them backpropagates zeros.
        anchor = 0.0 * (means2d.sum() + conics.sum() + opacities.sum() + colors.sum())
        image, alpha = image + anchor, alpha + anchor
    return image, alpha
