"""Multi-resolution hash encoding (Instant-NGP, Müller et al. 2022), in pure PyTorch.

A point ``x`` in world space is mapped into the grid box ``center ± half_extent`` and normalised to
``u in [0, 1]^3``. Level ``l`` lays a grid of ``R_l`` cells (``R_l + 1`` vertices) per axis over the box;
each vertex owns a learnable ``F``-vector in row ``index_l(vertex)`` of that level's table. The encoding of
``x`` is the trilinear interpolation of its 8 surrounding vertex vectors, concatenated over the levels.

Resolutions grow geometrically, ``R_l = floor(R_min * b^l)`` with
``b = exp((ln R_max - ln R_min) / (L - 1))`` (Instant-NGP eq. 2-3). A coarse level whose
``(R_l + 1)^3`` vertices fit in the table is indexed densely (collision-free); finer levels use the
Instant-NGP spatial hash ``(x * 1 XOR y * 2654435761 XOR z * 805459861) mod T``. Because ``T`` is a power
of two, taking the low bits of the 64-bit products equals Instant-NGP's uint32 arithmetic exactly.

Unlike Instant-NGP's CUDA kernel, vertices sit on the cell corners (no half-cell offset), so the value at
a vertex is exactly its table row; this keeps the test of exactness simple and changes nothing else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from langfield.kernels import notice_once, resolve_backend
from langfield.model.hashgrid_cpu import CornersNumba, EncodeNumba, InterpolateRowsNumba

# Instant-NGP's spatial-hash primes (paper eq. 4); the first is 1 for cache coherence.
_PRIMES = (1, 2654435761, 805459861)


@dataclass(frozen=True)
class HashGridConfig:
    """Sizes of a multi-resolution hash grid.

    Defaults are DNGaussian's neural renderer (itself torch-ngp's): 16 levels x 2 features, base
    resolution 16, finest 512, table 2^19. Use :meth:`for_scene` to size a grid to a small scene.

    ``finest_resolution`` counts cells across the whole grid box at the finest level, so it is unit-free.
    DNGaussian passes ``desired_resolution = 512 * bound`` to torch-ngp together with inputs in
    ``[-bound, bound]``, i.e. 512 cells per two world units: its finest cell is ``1/256`` world units and
    depends on the scene's scale. We keep the count per box instead (512 for a box of half-size 1 matches
    DNGaussian), so a scene in millimetres and the same scene in metres get the same grid.

    Attributes:
        n_levels: number of resolution levels L.
        features_per_level: feature width F of each table row.
        log2_table_size: log2 of the rows per level T (a power of two, as in Instant-NGP).
        base_resolution: cells per axis at the coarsest level R_min.
        finest_resolution: cells per axis at the finest level R_max (see above).
        init_scale: table entries start uniform in ``[-init_scale, init_scale]`` (Instant-NGP: 1e-4).
    """

    n_levels: int = 16
    features_per_level: int = 2
    log2_table_size: int = 19
    base_resolution: int = 16
    finest_resolution: int = 512
    init_scale: float = 1e-4

    def __post_init__(self) -> None:
        if self.n_levels < 1 or self.features_per_level < 1:
            raise ValueError(f"n_levels and features_per_level must be >= 1, got {self}")
        if not 1 <= self.log2_table_size <= 30:
            raise ValueError(f"log2_table_size must be in [1, 30], got {self.log2_table_size}")
        if not 1 <= self.base_resolution <= self.finest_resolution:
            raise ValueError(
                f"need 1 <= base_resolution <= finest_resolution, got {self.base_resolution}, "
                f"{self.finest_resolution}"
            )

    @property
    def table_size(self) -> int:
        """Rows per level, ``T = 2^log2_table_size``."""
        return 1 << self.log2_table_size

    @property
    def out_dim(self) -> int:
        """Width of the encoding, ``L * F``."""
        return self.n_levels * self.features_per_level

    def resolutions(self) -> list[int]:
        """Cells per axis of every level, ``R_l = floor(R_min * b^l)`` (Instant-NGP eq. 2-3)."""
        if self.n_levels == 1:
            return [self.base_resolution]
        growth = math.exp(
            (math.log(self.finest_resolution) - math.log(self.base_resolution)) / (self.n_levels - 1)
        )
        # The small epsilon keeps R_{L-1} == R_max despite rounding in growth ** (L - 1).
        return [
            int(math.floor(self.base_resolution * growth**level + 1e-6)) for level in range(self.n_levels)
        ]

    @classmethod
    def for_scene(
        cls,
        num_points: int,
        image_pixels: int,
        *,
        features_per_level: int = 2,
        base_resolution: int = 16,
        max_growth: float = 1.3,
    ) -> HashGridConfig:
        """Size a grid to a scene of ``num_points`` Gaussians seen in images of ``image_pixels`` pixels.

        The rules (the grid is only queried at Gaussian centres, never along rays as in a NeRF):

        - Table: ``T = 2^ceil(log2(num_points))`` rows per level, clamped to ``[2^12, 2^19]``. At a fine
          level nearly every Gaussian falls in its own cell, so about one row per Gaussian is needed;
          more rows only add Adam work, and the coarse levels plus the MLP resolve the collisions that
          remain (Instant-NGP sec. 3). Pass the number of Gaussians expected after densification.
        - Finest resolution: twice the image's linear resolution ``sqrt(image_pixels)``, clamped to
          ``[base_resolution, 512]``: a colour or language detail smaller than about half a pixel in a
          training view cannot be supervised.
        - Levels: enough that consecutive levels grow by at most ``max_growth`` (Instant-NGP uses
          growth factors between 1.26 and 2), clamped to ``[4, 16]``.

        A 3-view 160x120 scene with 10-20k Gaussians gets ``T = 2^14-2^15``, finest 277, 12 levels.

        Args:
            num_points: number of Gaussians the grid will encode (> 0).
            image_pixels: pixels of one training image, ``width * height`` (> 0).
            features_per_level: feature width F.
            base_resolution: cells per axis at the coarsest level.
            max_growth: largest allowed ratio between the resolutions of consecutive levels (> 1).

        Returns:
            The sized config.

        Example:
            >>> HashGridConfig.for_scene(15_000, 160 * 120).log2_table_size
            14
        """
        if num_points < 1 or image_pixels < 1:
            raise ValueError(
                f"num_points and image_pixels must be positive, got {num_points}, {image_pixels}"
            )
        if max_growth <= 1.0:
            raise ValueError(f"max_growth must be > 1, got {max_growth}")
        log2_table = min(max(math.ceil(math.log2(num_points)), 12), 19)
        finest = min(max(int(round(2.0 * math.sqrt(image_pixels))), base_resolution), 512)
        n_levels = math.ceil(math.log(finest / base_resolution) / math.log(max_growth)) + 1
        n_levels = min(max(n_levels, 4), 16)
        return cls(
            n_levels=n_levels,
            features_per_level=features_per_level,
            log2_table_size=log2_table,
            base_resolution=base_resolution,
            finest_resolution=finest,
        )


class HashGrid(nn.Module):
    """Multi-resolution hash encoding of world positions.

    Args:
        cfg: grid sizes.
        center: [3] centre of the grid box in world coordinates.
        half_extent: [3] or scalar half-size of the box per axis (> 0). Training uses
            ``scene extent / 2 x 1.2`` around the scene centre; this class takes the box as given.

    Attributes:
        table: [L, T, F] the learnable feature table, one parameter so it can get its own learning rate.

    Example:
        >>> grid = HashGrid(HashGridConfig(n_levels=4, log2_table_size=12), torch.zeros(3), 1.0)
        >>> grid(torch.rand(10, 3)).shape
        torch.Size([10, 8])
    """

    def __init__(self, cfg: HashGridConfig, center: Tensor, half_extent: Tensor | float) -> None:
        super().__init__()
        self.cfg = cfg
        center = torch.as_tensor(center, dtype=torch.float32).reshape(3)
        half = torch.as_tensor(half_extent, dtype=torch.float32).expand(3).clone()
        if not (torch.isfinite(center).all() and torch.isfinite(half).all() and (half > 0).all()):
            raise ValueError(
                f"grid box needs a finite centre and a positive half extent, got {center}, {half}"
            )
        # Which cell look-up and interpolation run, named as the rasterizer's backends: "numba" (and
        # "auto", on CPU tensors) the numba kernels of :mod:`langfield.model.hashgrid_cpu`; "torch" the
        # PyTorch reference (corners' tensor code, ``_InterpolateRows``) the tests compare them against.
        self.backend = "auto"
        self.register_buffer("center", center)
        self.register_buffer("half_extent", half)

        res = cfg.resolutions()
        t = cfg.table_size
        # Levels whose vertices fit in the table are indexed densely; resolutions increase, so these form
        # a prefix of the levels.
        self.n_dense = sum(1 for r in res if (r + 1) ** 3 <= t)
        self.register_buffer("resolution", torch.tensor(res, dtype=torch.float32), persistent=False)
        self.register_buffer(
            "max_corner", torch.tensor(res, dtype=torch.int64)[:, None] - 1, persistent=False
        )
        verts = torch.tensor([r + 1 for r in res], dtype=torch.int64)
        # Row strides of the dense levels, [3, L]: row = x + y (R+1) + z (R+1)^2.
        self.register_buffer(
            "dense_strides", torch.stack([torch.ones_like(verts), verts, verts**2]), persistent=False
        )
        # Level l's rows start at l * T in the flat [L * T, F] view of the table.
        self.register_buffer(
            "level_offset", torch.arange(cfg.n_levels, dtype=torch.int64) * t, persistent=False
        )
        self.table = nn.Parameter(
            torch.empty(cfg.n_levels, t, cfg.features_per_level).uniform_(-cfg.init_scale, cfg.init_scale)
        )

    @property
    def out_dim(self) -> int:
        """Width of the encoding, ``L * F``."""
        return self.cfg.out_dim

    def normalize(self, x: Tensor) -> Tensor:
        """Map world positions into the unit cube of the grid box, clamping points outside it.

        Args:
            x: [N, 3] world positions.

        Returns:
            [N, 3] positions in ``[0, 1]^3``. Outside the box the gradient w.r.t. ``x`` is zero.
        """
        u = (x - self.center.to(x.dtype)) / (2.0 * self.half_extent.to(x.dtype)) + 0.5
        return u.clamp(0.0, 1.0)

    def forward(self, x: Tensor) -> Tensor:
        """Encode world positions.

        Differentiable w.r.t. the table and w.r.t. ``x`` (through the trilinear weights).

        Args:
            x: [N, 3] world positions.

        Returns:
            [N, L * F] features, level-major (level 0's F features first).
        """
        return self.encode(x)

    def encode(self, x: Tensor, groups: int = 1) -> Tensor:
        """Encode world positions, the features split into ``groups`` as :meth:`interpolate` splits them.

        Equal to ``interpolate(*corners(x), groups=groups)``, which the ``torch`` backend computes; the
        numba backend finds the cells and interpolates in one walk (:meth:`one_walk`), forward and
        back, with no rows in memory between them.

        Args:
            x: [N, 3] world positions (of the table's dtype for the one-walk kernels).
            groups: as in :meth:`interpolate`.

        Returns:
            [N, L * F] for ``groups == 1``, else [groups, N, L * F / groups].
        """
        if x.dim() != 2 or x.shape[-1] != 3:
            raise ValueError(f"HashGrid expects positions of shape [N, 3], got {tuple(x.shape)}")
        f = self.cfg.features_per_level
        if groups < 1 or f % groups:
            raise ValueError(f"groups must divide features_per_level={f}, got {groups}")
        if self.one_walk(x):
            notice_once()
            out = EncodeNumba.apply(x, self.table.view(-1, f), self._layout(), groups)
            return out[0] if groups == 1 else out
        return self.interpolate(*self.corners(x), groups=groups)

    def one_walk(self, x: Tensor) -> bool:
        """Whether :meth:`encode` reads positions ``x`` in one walk
        (:class:`~langfield.model.hashgrid_cpu.EncodeNumba`): the numba
        backend, CPU tensors, ``x`` of the table's dtype."""
        cpu = x.device.type == "cpu" and self.table.device.type == "cpu"
        return resolve_backend(self.backend) == "numba" and cpu and x.dtype == self.table.dtype

    def corners(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Find each point's cell at every level: the table rows of its 8 corners and its place in the cell.

        This is the part of the encoding that does not depend on the table, so grids with equal configs
        and boxes (the colour and language grids) can share it: ``g2.interpolate(*g1.corners(x))``.

        Args:
            x: [N, 3] world positions.

        Returns:
            rows: [8, L, N] int64 rows of the flat ``[L * T]`` table, corner ``c = 4 cx + 2 cy + cz``.
            frac: [3, L, N] position inside the cell per axis, in [0, 1]; carries the gradient to ``x``.
        """
        if x.dim() != 2 or x.shape[-1] != 3:
            raise ValueError(f"HashGrid expects positions of shape [N, 3], got {tuple(x.shape)}")
        if resolve_backend(self.backend) == "numba" and x.device.type == "cpu":
            # One kernel for both outputs; the tensor code below is its reference.
            notice_once()
            return CornersNumba.apply(x, self._layout())
        # Axis-major [3, L, N] layout keeps N innermost, so every broadcast over corners or levels below
        # runs over long contiguous rows (3-4x faster on the CPU than the point-major [N, L, 3]).
        pos = self.normalize(x).t()[:, None, :] * self.resolution.to(x.dtype)[None, :, None]
        # Clamping the lower corner to R - 1 keeps u == 1 inside the last cell (fraction 1) instead of
        # pointing at a corner R + 1 that does not exist.
        lo = torch.minimum(pos.detach().floor().to(torch.int64), self.max_corner)
        frac = pos - lo.to(x.dtype)
        return self._corner_rows(lo), frac

    def _layout(self) -> dict[str, Any]:
        """The grid's cell layout as numpy arrays, for :class:`CornersNumba`."""
        return {
            "center": self.center.detach().cpu().numpy(),
            "two_half": (2.0 * self.half_extent).detach().cpu().numpy(),
            "res": self.resolution.cpu().numpy(),
            "max_corner": self.max_corner[:, 0].cpu().numpy(),
            "strides": self.dense_strides.cpu().numpy(),  # [3, L]
            "level_offset": self.level_offset.cpu().numpy(),
            "n_dense": self.n_dense,
            "primes": np.array(_PRIMES, dtype=np.int64),
            "mask": self.cfg.table_size - 1,
        }

    def interpolate(self, rows: Tensor, frac: Tensor, groups: int = 1) -> Tensor:
        """Trilinearly interpolate the table at the corners found by :meth:`corners`.

        Args:
            rows: [8, L, N] int64 table rows.
            frac: [3, L, N] position inside the cell.
            groups: split each row's F features into this many groups of F / groups consecutive
                features and return one encoding per group (the language grid's three levels).

        Returns:
            [N, L * F] features for ``groups == 1``, else [groups, N, L * F / groups], each group
            level-major like the plain encoding.
        """
        f = self.cfg.features_per_level
        if groups < 1 or f % groups:
            raise ValueError(f"groups must divide features_per_level={f}, got {groups}")
        if resolve_backend(self.backend) == "numba" and self.table.device.type == "cpu":
            notice_once()
            out = InterpolateRowsNumba.apply(
                self.table.view(-1, f), rows, frac.to(self.table.dtype), self.cfg.table_size, groups
            )  # [G, N, L * F / G]
            return out[0] if groups == 1 else out
        # Feature-major [F, L * T] layout: a gather of single values is several times faster on the CPU
        # than a gather of F-wide rows, and so is the scatter-add of the backward pass.
        table_t = self.table.reshape(-1, f).t().contiguous()
        out = _InterpolateRows.apply(table_t, rows, frac.to(table_t.dtype))  # [F, L, N]
        n = rows.shape[-1]
        if groups == 1:
            return out.permute(2, 1, 0).reshape(n, self.cfg.out_dim)
        per = f // groups
        return out.reshape(groups, per, -1, n).permute(0, 3, 2, 1).reshape(groups, n, -1)

    def _corner_rows(self, lo: Tensor) -> Tensor:
        """Rows of the flat ``[L * T]`` table holding the 8 corners of each point's cell, per level.

        Args:
            lo: [3, L, N] int64 lower corner of the cell at every level.

        Returns:
            [8, L, N] int64 rows, corner ``c = 4 cx + 2 cy + cz``.
        """
        d, n_levels, n = self.n_dense, lo.shape[1], lo.shape[2]
        both = torch.stack([lo, lo + 1], dim=1)  # [3, 2, L, N]: the two corner coordinates per axis
        x, y, z = both[0, :, None, None], both[1, None, :, None], both[2, None, None, :]  # -> [2, 2, 2, L, N]
        rows = torch.empty(2, 2, 2, n_levels, n, dtype=torch.int64, device=lo.device)
        if d > 0:
            s = self.dense_strides[:, :d, None]  # [3, D, 1]
            # The level offset is folded into the x coordinates (2 values per point), so only the two
            # broadcasting adds touch all 8 corners.
            xd = x[..., :d, :] + self.level_offset[:d, None]
            torch.add(xd + y[..., :d, :] * s[1], z[..., :d, :] * s[2], out=rows[..., :d, :])
        if d < n_levels:
            mask = self.cfg.table_size - 1
            # Low bits of the XOR are the XOR of the low bits, so masking each axis's product first gives
            # the same hash; OR-ing the level offset (a multiple of T) into the x term then lands every
            # row in its level's block without another pass over all 8 corners.
            hx = (x[..., d:, :] * _PRIMES[0]) & mask | self.level_offset[d:, None]
            hy = (y[..., d:, :] * _PRIMES[1]) & mask
            hz = (z[..., d:, :] * _PRIMES[2]) & mask
            torch.bitwise_xor(hx ^ hy, hz, out=rows[..., d:, :])
        return rows.view(8, n_levels, n)


def _trilinear_weights(frac: Tensor) -> tuple[Tensor, Tensor]:
    """Trilinear weights of the 8 corners, in the order of :meth:`HashGrid._corner_rows`.

    Args:
        frac: [3, L, N] position inside the cell, in [0, 1].

    Returns:
        weights [8, L, N] that sum to 1, and the per-axis factors [3, 2, L, N] (``1 - f``, ``f``).
    """
    w = torch.stack([1.0 - frac, frac], dim=1)  # [3, 2, L, N]
    wxy = w[0, :, None] * w[1, None, :]  # [2, 2, L, N]
    return (wxy[:, :, None] * w[2, None, None, :]).view(8, *frac.shape[1:]), w


class _InterpolateRows(torch.autograd.Function):
    """Trilinear interpolation of gathered table entries, with a hand-written backward.

    Autograd's backward of a row gather (``embedding_dense_backward``) costs about 40x the forward on a
    2-core CPU, and its backward through the broadcast weight products about 3x; a scatter-add along the
    feature-major layout and the closed-form derivative of the weights cost about as much as the forward.
    """

    @staticmethod
    def forward(ctx, table_t: Tensor, rows: Tensor, frac: Tensor) -> Tensor:  # type: ignore[override]
        """table_t: [F, L * T] feature-major table; rows: [8, L, N]; frac: [3, L, N]. Returns [F, L, N]."""
        weight, axis_w = _trilinear_weights(frac)
        feats = table_t.index_select(1, rows.view(-1)).view(table_t.shape[0], *rows.shape)  # [F, 8, L, N]
        ctx.save_for_backward(rows, weight, axis_w, feats if ctx.needs_input_grad[2] else None)
        ctx.n_rows = table_t.shape[1]
        return (feats * weight).sum(dim=1)

    @staticmethod
    def backward(ctx, grad_out: Tensor) -> tuple[Tensor | None, None, Tensor | None]:  # type: ignore[override]
        """grad_out: [F, L, N]. Returns the gradients of table_t [F, L * T] and frac [3, L, N]."""
        rows, weight, axis_w, feats = ctx.saved_tensors
        # The incoming gradient is a permuted view of the [N, L * F] output's; making it contiguous here
        # (N * L * F values) keeps the [F, 8, L, N] products below contiguous, so no larger copy follows.
        grad_out = grad_out.contiguous()
        n_feat = grad_out.shape[0]
        grad_table = grad_frac = None
        if ctx.needs_input_grad[0]:
            values = (grad_out[:, None] * weight).reshape(n_feat, -1)
            grad_table = grad_out.new_zeros(n_feat, ctx.n_rows).index_add_(1, rows.view(-1), values)
        if ctx.needs_input_grad[2]:
            # dL/dw_c for every corner c, then dw_c/df_a = (+1 or -1) x the other two axes' factors.
            g = (grad_out[:, None] * feats).sum(dim=0).view(2, 2, 2, *grad_out.shape[1:])
            wx, wy, wz = axis_w[0], axis_w[1], axis_w[2]  # [2, L, N] each
            gx = ((g[1] - g[0]) * (wy[:, None] * wz[None, :])).sum(dim=(0, 1))
            gy = ((g[:, 1] - g[:, 0]) * (wx[:, None] * wz[None, :])).sum(dim=(0, 1))
            gz = ((g[:, :, 1] - g[:, :, 0]) * (wx[:, None] * wy[None, :])).sum(dim=(0, 1))
            grad_frac = torch.stack([gx, gy, gz])
        return grad_table, None, grad_frac
