"""``make install``'s warm-up: every CPU kernel compiled (or loaded) once, ahead of the first run
(:mod:`langfield.kernels` says why)."""

from __future__ import annotations

import os
import time

import torch

from langfield.camera import Camera
from langfield.kernels import COMPILE_HERE, notice_once, uncompiled_kernels
from langfield.model.colour import ColorField
from langfield.model.hashgrid import HashGridConfig
from langfield.raster import rasterize, rasterize_slots
from langfield.raster.composite_cpu import FIXED_CHANNELS
from langfield.training.ssim import ssim_map

__all__ = ["main", "warm_up"]


def warm_up() -> float:
    """Compiles (or loads) every kernel by rendering a few Gaussians forward and backward with the
    ``numba`` backend and a hash-grid colour field, as training does (with the loss's SSIM), and their
    weights per codebook entry, as a query does. Returns the seconds it took."""
    t0 = time.perf_counter()
    notice_once()
    generator = torch.Generator().manual_seed(0)
    n = 64
    means = (torch.rand(n, 3, generator=generator) - 0.5).requires_grad_(True)
    quats = torch.randn(n, 4, generator=generator).requires_grad_(True)
    scales = torch.full((n, 3), 0.05).requires_grad_(True)
    opacities = torch.full((n,), 0.5).requires_grad_(True)
    color = ColorField(HashGridConfig(n_levels=2, log2_table_size=8), torch.zeros(3), 1.0)
    features = color(means, torch.nn.functional.normalize(means, dim=-1))
    # The grid's two-kernel path (cell look-up, then interpolation): positions of another dtype than the
    # table's take it, and the one walk's tests compare with it.
    grid = color.grid
    grid.interpolate(*grid.corners(means.detach().requires_grad_(True))).sum().backward()
    camera = Camera.look_at(eye=(0, -2, 0.5), target=(0, 0, 0), width=32, height=24)
    out = rasterize(means, quats, scales, opacities, features, camera, backend="numba")
    (out.image.sum() + out.alpha.sum()).backward()
    for n_ch, n_geo in FIXED_CHANNELS:  # the compositing kernels compiled for these counts too
        channels = torch.rand(n, n_ch, generator=generator).requires_grad_(True)
        fixed = rasterize(
            means, quats, scales, opacities, channels, camera, backend="numba", geometry_channels=n_geo
        )
        fixed.image.sum().backward()
    slots = torch.randint(0, 4, (n, 1), generator=generator)  # a vote's weights per codebook entry
    rasterize_slots(means.detach(), quats.detach(), scales.detach(), opacities.detach(), slots, 4, camera)
    ssim_map(out.image.detach().requires_grad_(True), out.image.detach(), backend="numba").sum().backward()
    return time.perf_counter() - t0


def main() -> None:
    """``make install``'s warm-up: compiles what is not cached, in this process, and says how long it
    took."""
    os.environ[COMPILE_HERE] = "1"
    todo = len(uncompiled_kernels())
    seconds = warm_up()
    left = uncompiled_kernels()
    state = "all cached" if not left else f"still not cached: {', '.join(left)}"
    print(f"langfield kernels: {todo} compiled, {seconds:.1f} s; {state}")
