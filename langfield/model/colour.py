"""The colour field: c_j = MLP_C(h_color(p_j), enc(d)) (SOVGaussian's colour branch).

A hash grid encodes each Gaussian's centre, a frequency encoding its view direction, and a small ReLU MLP
maps both to RGB. DNGaussian's neural renderer is the template (hash grid 16 x 2, colour MLP of 64 units,
grid lr 5e-3, MLP lr 5e-4); the direction encoding is NeRF's, whose 4 frequencies for directions the
trainer leaves out by default (``TrainConfig.color_freqs = 0``: the direction itself, a colour that
varies smoothly with it): three views give each point three directions, and the frequencies fit them
at the cost of the directions between and beyond (docs/decisions.md).
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import torch
from torch import Tensor, nn

from langfield.model.hashgrid import HashGrid, HashGridConfig

# Directions averaged by bake_dc: a Fibonacci sphere spreads them almost evenly.
_BAKE_DIRECTIONS = 64


def frequency_encoding(d: Tensor, n_freqs: int) -> Tensor:
    """NeRF positional encoding of unit vectors: ``[d, sin(2^k pi d), cos(2^k pi d)]`` for k < n_freqs.

    Args:
        d: [N, 3] unit view directions.
        n_freqs: number of frequencies (NeRF uses 4 for directions); -1 leaves the direction out.

    Returns:
        [N, 3 + 6 n_freqs] encoding ([N, 0] for -1).
    """
    if n_freqs < 0:
        return d[:, :0]
    if n_freqs == 0:
        return d
    freqs = (2.0 ** torch.arange(n_freqs, dtype=d.dtype, device=d.device)) * math.pi
    arg = (d[:, None, :] * freqs[:, None]).reshape(d.shape[0], -1)  # [N, 3 n_freqs]
    return torch.cat([d, torch.sin(arg), torch.cos(arg)], dim=-1)


def fibonacci_directions(n: int) -> Tensor:
    """``n`` nearly uniform unit directions on the sphere (Fibonacci lattice), [n, 3]."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1).float()


class ColorField(nn.Module):
    """View-dependent colour of Gaussians from their centres: sigmoid(MLP_C(h_color(p), enc(d))).

    Args:
        grid_cfg: hash-grid sizes (see :meth:`HashGridConfig.for_scene`).
        center: [3] centre of the grid box.
        half_extent: [3] or scalar half-size of the grid box.
        hidden: width of the MLP's two hidden ReLU layers (DNGaussian: 64).
        n_freqs: frequencies of the view-direction encoding (NeRF: 4; 0: the direction alone; -1: no
            direction, a colour the same from every side).

    Example:
        >>> field = ColorField(HashGridConfig(n_levels=4, log2_table_size=12), torch.zeros(3), 1.0)
        >>> d = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
        >>> field(torch.rand(5, 3), d).shape
        torch.Size([5, 3])
    """

    def __init__(
        self,
        grid_cfg: HashGridConfig,
        center: Tensor,
        half_extent: Tensor | float,
        hidden: int = 64,
        n_freqs: int = 4,
    ) -> None:
        super().__init__()
        if hidden < 1 or n_freqs < -1:
            raise ValueError(f"need hidden >= 1 and n_freqs >= -1, got {hidden}, {n_freqs}")
        self.n_freqs = n_freqs
        self.grid = HashGrid(grid_cfg, center, half_extent)
        in_dim = self.grid.out_dim + (3 + 6 * n_freqs if n_freqs >= 0 else 0)
        self.mlp = nn.Sequential(
            nn.Linear(in_dim, hidden),
            nn.ReLU(),
            nn.Linear(hidden, hidden),
            nn.ReLU(),
            nn.Linear(hidden, 3),
        )

    def forward(
        self, means: Tensor, view_dirs: Tensor, corners: tuple[Tensor, Tensor] | None = None
    ) -> Tensor:
        """Colour of each Gaussian seen along ``view_dirs``.

        Args:
            means: [N, 3] Gaussian centres in world coordinates.
            view_dirs: [N, 3] unit directions from the camera to the Gaussians.
            corners: ``self.grid.corners(means)`` if the caller already has them (shared with the
                language grid, which has the same cell layout).

        Returns:
            [N, 3] RGB in (0, 1).
        """
        if means.shape != view_dirs.shape or means.dim() != 2 or means.shape[-1] != 3:
            raise ValueError(
                f"ColorField expects means and view_dirs of shape [N, 3], got {tuple(means.shape)} "
                f"and {tuple(view_dirs.shape)}"
            )
        h = self.grid.interpolate(*corners) if corners is not None else self.grid(means)
        return self.rgb(h, view_dirs)

    def rgb(self, h: Tensor, view_dirs: Tensor) -> Tensor:
        """RGB from grid features h [N, L F] (``self.grid`` read at the means) and unit directions [N, 3]."""
        x = torch.cat([h, frequency_encoding(view_dirs, self.n_freqs)], dim=-1)
        return torch.sigmoid(self.mlp(x))

    @torch.no_grad()
    def bake_dc(self, means: Tensor, n_dirs: int = _BAKE_DIRECTIONS, chunk: int = 8192) -> Tensor:
        """View-independent colour: the mean over ``n_dirs`` fixed, nearly uniform view directions.

        Used to write a standard 3DGS PLY, whose degree-0 SH coefficient holds this colour. No gradient.

        Args:
            means: [N, 3] Gaussian centres.
            n_dirs: number of directions averaged (a Fibonacci sphere, so deterministic).
            chunk: Gaussians evaluated at a time, to bound memory (chunk x n_dirs rows).

        Returns:
            [N, 3] RGB in (0, 1).
        """
        dirs = fibonacci_directions(n_dirs).to(means.device, means.dtype)  # [D, 3]
        out = []
        for start in range(0, means.shape[0], chunk):
            m = means[start : start + chunk]
            h = self.grid(m)  # the grid is evaluated once per Gaussian, the MLP once per direction
            hh = h[:, None, :].expand(-1, n_dirs, -1).reshape(-1, h.shape[-1])
            dd = dirs[None].expand(m.shape[0], -1, -1).reshape(-1, 3)
            out.append(self.rgb(hh, dd).view(m.shape[0], n_dirs, 3).mean(dim=1))
        return torch.cat(out) if out else means.new_zeros(0, 3)

    def mlp_parameters(self) -> Iterator[nn.Parameter]:
        """Parameters of MLP_C (DNGaussian's lr: 5e-4)."""
        return self.mlp.parameters()

    def grid_parameters(self) -> Iterator[nn.Parameter]:
        """The hash table (DNGaussian's lr: 5e-3)."""
        return self.grid.parameters()
