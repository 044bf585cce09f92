"""Assigning projected Gaussians to 16x16 pixel tiles, sorted front to back inside each tile."""

from __future__ import annotations

import math

import torch
from torch import Tensor

TILE_SIZE = 16
ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped (3DGS)
# A tile is listed when the ellipse q = 2 ln(255 o) comes within this factor of its pixel centres: the
# compositors' own cut is alpha >= 1/255, and the CPU kernel's polynomial exp is accurate to ~1e-7.
Q_MARGIN = 1.001


def opacity_aware_extents(radii: Tensor, conics: Tensor, opacities: Tensor) -> tuple[Tensor, Tensor]:
    """Where each Gaussian can still reach alpha 1/255: its q bound and its box's half-widths.

    Beyond ``q = 2 ln(255 o)`` a Gaussian's alpha is below 1/255 and is skipped anyway, so bounds
    drawn there change no pixel; they only spare work for faint and for elongated Gaussians.

    Args:
        radii: [N] int 3-sigma radii (0: culled); conics: [N, 3] (a, b, c) of [[a, b], [b, c]];
            opacities: [N].

    Returns:
        q_max: [N] float64, ``2 ln(255 o)`` (<= 0: the Gaussian never reaches 1/255);
        extents: [N, 2] int64 half-widths in x and y of the box around the ellipse ``q <= q_max``
            (``sqrt(q_max Sigma_xx)``, ``sqrt(q_max Sigma_yy)``), at most the 3-sigma radius; 0 where
            the Gaussian is culled or never reaches 1/255.
    """
    with torch.no_grad():
        o = torch.clamp(opacities.detach().reshape(-1).double(), min=1e-30)
        q_max = 2.0 * torch.log(torch.clamp(o / ALPHA_MIN, min=1.0))
        a, b, c = conics.detach().double().unbind(-1)
        det = torch.clamp(a * c - b * b, min=1e-30)
        # The covariance is the conic's inverse: Sigma_xx = c / det, Sigma_yy = a / det.
        half = torch.sqrt(q_max[:, None] * torch.stack([c, a], dim=1) / det[:, None])
        half = torch.nan_to_num(torch.ceil(half), nan=0.0, posinf=1e7).clamp(min=0.0, max=1e7)
        half = torch.minimum(half, radii.double()[:, None])
        live = (q_max > 0) & (radii > 0)
        return q_max, torch.where(live[:, None], half, torch.zeros_like(half)).long()


def ellipse_min_q(x0: Tensor, x1: Tensor, y0: Tensor, y1: Tensor, conics: Tensor) -> Tensor:
    """Smallest ``q = a x^2 + 2 b x y + c y^2`` over the rectangles [x0, x1] x [y0, y1] (offsets from
    the Gaussians' centres), all float64 [M]; conics [M, 3].

    q is convex, so its minimum is 0 when the centre lies inside, else on an edge, where it is a 1D
    quadratic minimised at its stationary point clamped to the edge.
    """
    a, b, c = conics.unbind(-1)
    best = torch.full_like(x0, math.inf)
    for y in (y0, y1):
        x = torch.minimum(torch.maximum(-b * y / a, x0), x1)
        best = torch.minimum(best, a * x * x + 2.0 * b * x * y + c * y * y)
    for x in (x0, x1):
        y = torch.minimum(torch.maximum(-b * x / c, y0), y1)
        best = torch.minimum(best, a * x * x + 2.0 * b * x * y + c * y * y)
    inside = (x0 <= 0) & (x1 >= 0) & (y0 <= 0) & (y1 >= 0)
    return torch.where(inside, torch.zeros_like(best), best)


def bin_gaussians(
    means2d: Tensor,
    radii: Tensor,
    conics: Tensor,
    opacities: Tensor,
    depths: Tensor,
    width: int,
    height: int,
    tile_size: int = TILE_SIZE,
) -> tuple[Tensor, Tensor]:
    """Lists, for every tile, the Gaussians that can reach alpha 1/255 at one of its pixels, nearest first.

    The candidates are the tiles under each Gaussian's box (:func:`opacity_aware_extents`); a tile is
    kept when the ellipse ``q <= Q_MARGIN q_max`` reaches the rectangle of its pixel centres inside
    the image (:func:`ellipse_min_q`). An elongated Gaussian's box holds many tiles the ellipse never
    touches (Speedy-Splat's "AccuTile", Hanson et al. 2025, makes the same cut); leaving them out
    changes no pixel.

    Args:
        means2d: [N, 2] pixel centres; radii: [N] int 3-sigma radii (0: culled); conics: [N, 3];
            opacities: [N]; depths: [N] camera z used for the front-to-back order.
        width, height: image size.

    Returns:
        tile_offsets: [n_tiles + 1] int64; tile t owns ``gaussian_ids[tile_offsets[t]:tile_offsets[t+1]]``.
        gaussian_ids: [M] int64 Gaussian index of every (tile, Gaussian) intersection.
        Tiles are numbered row-major with ``ceil(width / tile_size)`` tiles per row.
    """
    tiles_x, tiles_y = math.ceil(width / tile_size), math.ceil(height / tile_size)
    n_tiles = tiles_x * tiles_y
    empty = torch.zeros(n_tiles + 1, dtype=torch.int64), torch.zeros(0, dtype=torch.int64)
    with torch.no_grad():
        q_max, extents = opacity_aware_extents(radii, conics, opacities)
        visible = torch.nonzero((extents > 0).all(dim=1)).squeeze(1)
        if visible.numel() == 0:
            return empty
        m = means2d.detach()[visible].double()
        rx, ry = extents[visible, 0].double(), extents[visible, 1].double()
        x0 = torch.clamp(torch.floor((m[:, 0] - rx) / tile_size), 0, tiles_x).long()
        x1 = torch.clamp(torch.floor((m[:, 0] + rx) / tile_size) + 1, 0, tiles_x).long()
        y0 = torch.clamp(torch.floor((m[:, 1] - ry) / tile_size), 0, tiles_y).long()
        y1 = torch.clamp(torch.floor((m[:, 1] + ry) / tile_size) + 1, 0, tiles_y).long()
        nx, ny = (x1 - x0).clamp(min=0), (y1 - y0).clamp(min=0)
        counts = nx * ny
        owner = torch.repeat_interleave(torch.arange(visible.numel()), counts)
        first = torch.cumsum(counts, 0) - counts
        local = torch.arange(owner.numel()) - first[owner]
        tile_x = x0[owner] + local % nx[owner]
        tile_y = y0[owner] + local // nx[owner]

        # The rectangle of the tile's pixel centres inside the image, relative to the Gaussian's centre.
        px0 = (tile_x * tile_size).double() + 0.5
        px1 = torch.clamp(tile_x * tile_size + tile_size, max=width).double() - 0.5
        py0 = (tile_y * tile_size).double() + 0.5
        py1 = torch.clamp(tile_y * tile_size + tile_size, max=height).double() - 0.5
        mo = m[owner]
        q = ellipse_min_q(px0 - mo[:, 0], px1 - mo[:, 0], py0 - mo[:, 1], py1 - mo[:, 1],
                          conics.detach().double()[visible][owner])  # fmt: skip
        reach = q <= Q_MARGIN * q_max[visible][owner]
        owner, tile_id = owner[reach], (tile_y * tiles_x + tile_x)[reach]
        if owner.numel() == 0:
            return empty

        # Sort by (tile, depth): depth rank among the visible Gaussians breaks ties deterministically.
        depth_rank = torch.empty_like(visible)
        depth_rank[torch.argsort(depths[visible], stable=True)] = torch.arange(visible.numel())
        key = tile_id * visible.numel() + depth_rank[owner]
        order = torch.argsort(key)
        gaussian_ids = visible[owner[order]]
        tile_offsets = torch.zeros(n_tiles + 1, dtype=torch.int64)
        tile_offsets[1:] = torch.cumsum(torch.bincount(tile_id, minlength=n_tiles), 0)
        return tile_offsets, gaussian_ids
