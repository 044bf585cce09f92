"""Assigning projected Gaussians to 16x16 pixel tiles, sorted front to back inside each tile."""

from __future__ import annotations

import math

import torch
from torch import Tensor

TILE_SIZE = 16
ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped (3DGS)


def opacity_aware_radii(radii: Tensor, conics: Tensor, opacities: Tensor) -> Tensor:
    """Shrinks 3-sigma radii [N] to where ``opacity * G`` can still reach ALPHA_MIN.

    Beyond ``q = 2 ln(255 o)`` a Gaussian's alpha is below 1/255 and is skipped anyway, so the
    tighter box changes no pixel; it only spares work for faint Gaussians (o = 0.1 -> 2.5 sigma).
    """
    with torch.no_grad():
        o = torch.clamp(opacities.detach().reshape(-1).double(), min=1e-30)
        q_max = 2.0 * torch.log(torch.clamp(o / ALPHA_MIN, min=1.0))
        a, b, c = conics.detach().double().unbind(-1)
        det = torch.clamp(a * c - b * b, min=1e-30)
        # Largest eigenvalue of the covariance = 1 / smallest eigenvalue of the conic.
        mid = 0.5 * (a + c)
        lam_min_conic = torch.clamp(mid - torch.sqrt(torch.clamp(mid * mid - det, min=0.0)), min=1e-30)
        r = torch.ceil(torch.sqrt(q_max / lam_min_conic))
        r = torch.nan_to_num(r, nan=0.0, posinf=1e7).clamp(max=1e7)
        return torch.where(q_max > 0, torch.minimum(radii.double(), r), torch.zeros_like(r)).to(torch.int32)


def bin_gaussians(
    means2d: Tensor, radii: Tensor, depths: Tensor, width: int, height: int, tile_size: int = TILE_SIZE
) -> tuple[Tensor, Tensor]:
    """Lists, for every tile, the Gaussians whose box touches it, nearest first.

    Args:
        means2d: [N, 2] pixel centres.
        radii: [N] int pixel radii; 0 means culled.
        depths: [N] camera z used for the front-to-back order.
        width, height: image size.

    Returns:
        tile_offsets: [n_tiles + 1] int64; tile t owns ``gaussian_ids[tile_offsets[t]:tile_offsets[t+1]]``.
        gaussian_ids: [M] int64 Gaussian index of every (tile, Gaussian) intersection.
        Tiles are numbered row-major with ``ceil(width / tile_size)`` tiles per row.
    """
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    n_tiles = tiles_x * tiles_y
    with torch.no_grad():
        visible = torch.nonzero(radii > 0).squeeze(1)
        if visible.numel() == 0:
            return torch.zeros(n_tiles + 1, dtype=torch.int64), torch.zeros(0, dtype=torch.int64)
        m = means2d.detach()[visible].double()
        r = radii[visible].double()
        x0 = torch.clamp(torch.floor((m[:, 0] - r) / tile_size), 0, tiles_x).long()
        x1 = torch.clamp(torch.floor((m[:, 0] + r) / tile_size) + 1, 0, tiles_x).long()
        y0 = torch.clamp(torch.floor((m[:, 1] - r) / tile_size), 0, tiles_y).long()
        y1 = torch.clamp(torch.floor((m[:, 1] + r) / tile_size) + 1, 0, tiles_y).long()
        nx, ny = (x1 - x0).clamp(min=0), (y1 - y0).clamp(min=0)
        counts = nx * ny
        keep = counts > 0
        visible, x0, y0, nx, counts = visible[keep], x0[keep], y0[keep], nx[keep], counts[keep]
        if visible.numel() == 0:
            return torch.zeros(n_tiles + 1, dtype=torch.int64), torch.zeros(0, dtype=torch.int64)

        owner = torch.repeat_interleave(torch.arange(visible.numel()), counts)
        first = torch.cumsum(counts, 0) - counts
        local = torch.arange(owner.numel()) - first[owner]
        tile_x = x0[owner] + local % nx[owner]
        tile_y = y0[owner] + local // nx[owner]
        tile_id = tile_y * tiles_x + tile_x

        # Sort by (tile, depth): depth rank among the visible Gaussians breaks ties deterministically.
        depth_rank = torch.empty_like(visible)
        depth_rank[torch.argsort(depths[visible], stable=True)] = torch.arange(visible.numel())
        key = tile_id * visible.numel() + depth_rank[owner]
        order = torch.argsort(key)
        gaussian_ids = visible[owner[order]]
        tile_offsets = torch.zeros(n_tiles + 1, dtype=torch.int64)
        tile_offsets[1:] = torch.cumsum(torch.bincount(tile_id, minlength=n_tiles), 0)
        return tile_offsets, gaussian_ids
