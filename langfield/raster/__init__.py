"""Differentiable rasterization of 3D Gaussians with any number of channels.

:func:`rasterize` projects the Gaussians to screen-space ellipses, bins them into 16x16 tiles and
composites them with the chosen backend: ``"torch"`` (PyTorch throughout, written to be read: the
reference every test compares with) or ``"numba"`` (numba kernels for all three stages, hand-written
backward; ``"cpu"`` is its earlier name). ``"auto"`` picks ``"numba"``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from langfield.camera import Camera
from langfield.kernels import BACKENDS, resolve_backend
from langfield.raster.binning import bin_gaussians
from langfield.raster.composite import rasterize_torch
from langfield.raster.projection import NEAR_PLANE, Projected, project_gaussians, quat_to_rotmat

Backend = Literal["auto", "torch", "numba", "cpu"]  # "cpu": the numba backend's earlier name


class RasterOutput(NamedTuple):
    """What :func:`rasterize` returns.

    Attributes:
        image: [H, W, C] composited channels (background included).
        alpha: [H, W] accumulated opacity.
        means2d: [N, 2] projected centres; holds ``.grad`` after backward (for densification).
        radii: [N] int32 pixel radii, 0 where culled.
    """

    image: Tensor
    alpha: Tensor
    means2d: Tensor
    radii: Tensor


class Kernels(NamedTuple):
    """One backend's three stages, each the same function of the same arguments in every backend (the
    tests compare them pairwise: values and gradients).

    Attributes:
        project: :func:`~langfield.raster.projection.project_gaussians` or its numba twin.
        bin: :func:`~langfield.raster.binning.bin_gaussians` or its numba twin.
        composite: front-to-back compositing of the binned Gaussians.
        composite_pair: compositing of two passes over the same footprints in one walk, or None (the
            second pass is then a :func:`rasterize` of its own).
        composite_slots: compositing of one-hot channels given by index (:func:`rasterize_slots`), or
            None (the one-hot rows are then made and composited as any channels).
    """

    project: Callable
    bin: Callable
    composite: Callable
    composite_pair: Callable | None
    composite_slots: Callable | None


def kernels(backend: Backend) -> Kernels:
    """The kernels of ``backend``: the one table of what each backend runs. The ``numba`` kernels are
    imported, and the notice of their one-time compilation shown, when first asked for."""
    if resolve_backend(backend) == "torch":
        return Kernels(project_gaussians, bin_gaussians, rasterize_torch, None, None)
    from langfield.kernels import notice_once
    from langfield.raster.binning_cpu import bin_gaussians_cpu
    from langfield.raster.composite_cpu import rasterize_cpu, rasterize_pair_cpu, rasterize_slots_cpu
    from langfield.raster.projection_cpu import project_gaussians_cpu

    notice_once()
    return Kernels(
        project_gaussians_cpu, bin_gaussians_cpu, rasterize_cpu, rasterize_pair_cpu, rasterize_slots_cpu
    )


def _background(features: Tensor, background: Tensor | None) -> Tensor:
    """[C] background of ``features``' dtype (zeros if None)."""
    n_ch = features.shape[1]
    if background is None:
        return features.new_zeros(n_ch)
    return torch.as_tensor(background, dtype=features.dtype).reshape(n_ch)


def composite(
    projected: Projected,
    opacities: Tensor,
    features: Tensor,
    width: int,
    height: int,
    background: Tensor | None = None,
    backend: Backend = "auto",
    geometry_channels: int | None = None,
) -> tuple[Tensor, Tensor]:
    """Composites already projected Gaussians: returns image [H, W, C] and alpha [H, W]."""
    background = _background(features, background)
    opacities = opacities.reshape(-1)
    run = kernels(backend)
    offsets, ids = run.bin(
        projected.means2d, projected.radii, projected.conics, opacities, projected.depths, width, height
    )
    return run.composite(
        projected.means2d,
        projected.conics,
        opacities,
        features,
        offsets,
        ids,
        width,
        height,
        background,
        geometry_channels,
    )


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    camera: Camera,
    *,
    background: Tensor | None = None,
    backend: Backend = "auto",
    near: float = NEAR_PLANE,
    geometry_channels: int | None = None,
) -> RasterOutput:
    """Renders N Gaussians carrying C feature channels from ``camera``.

    Args:
        means: [N, 3] world positions.
        quats: [N, 4] rotations (w, x, y, z), normalised inside with an epsilon.
        scales: [N, 3] standard deviations (activated, not logs).
        opacities: [N] or [N, 1] in [0, 1].
        features: [N, C] channels to composite (colour, language latents, distance, ...).
        camera: the view.
        background: [C] value behind the Gaussians; zeros if None.
        backend: "auto", "torch" or "numba" ("cpu", its earlier name, still works).
        near: near plane; Gaussians closer than this (or behind the camera) are culled.
        geometry_channels: only the first this many channels pass gradient to the geometry (means,
            rotations, scales, opacities); the rest train only their own feature values, in the same
            pass. None: every channel does. The language loss uses this (L_LF detaches geometry).

    Returns:
        :class:`RasterOutput`.

    Example:
        >>> cam = Camera.look_at((0, 0, 3), (0, 0, 0), (0, 1, 0), width=32, height=24)
        >>> out = rasterize(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1),
        ...                 torch.tensor([0.8]), torch.ones(1, 3), cam)
        >>> out.image.shape
        torch.Size([24, 32, 3])
    """
    projected = kernels(backend).project(
        means, quats, scales, camera.world_to_camera(), camera.intrinsics(), camera.width, camera.height, near
    )
    if projected.means2d.requires_grad:
        projected.means2d.retain_grad()
    image, alpha = composite(
        projected,
        opacities,
        features,
        camera.width,
        camera.height,
        background=background,
        backend=backend,
        geometry_channels=geometry_channels,
    )
    return RasterOutput(image, alpha, projected.means2d, projected.radii)


def rasterize_with_second_pass(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    features: Tensor,
    camera: Camera,
    second_opacities: Tensor,
    second_values: Tensor,
    *,
    background: Tensor | None = None,
    backend: Backend = "auto",
    near: float = NEAR_PLANE,
    geometry_channels: int | None = None,
) -> tuple[RasterOutput, Tensor]:
    """:func:`rasterize`, and a second pass of the same Gaussians with rotations and scales detached,
    other opacities and one value channel on a zero background: the hard depth of eq. 7.

    Equal to two :func:`rasterize` calls, ``rasterize(means, quats.detach(), scales.detach(),
    second_opacities, second_values, camera)`` being the second (the ``torch`` backend makes exactly
    those). The ``numba`` backend composites both in one walk over the tiles: the footprints are equal, so
    each pixel's Gaussian weight is computed once for both (the hard depth then costs ~1/3 of its own
    pass), and each pass's gradients still go to its own inputs.

    Returns:
        The first pass's :class:`RasterOutput` and the second pass's image [H, W, 1].
    """
    second_opacities = second_opacities.reshape(-1)
    second_values = second_values.reshape(-1, 1)
    run = kernels(backend)
    if run.composite_pair is None:
        out = rasterize(
            means, quats, scales, opacities, features, camera,
            background=background, backend=backend, near=near, geometry_channels=geometry_channels,
        )  # fmt: skip
        second = rasterize(
            means, quats.detach(), scales.detach(), second_opacities, second_values, camera,
            backend=backend, near=near,
        )  # fmt: skip
        return out, second.image
    view = (camera.world_to_camera(), camera.intrinsics(), camera.width, camera.height, near)
    projected = run.project(means, quats, scales, *view)
    detached = run.project(means, quats.detach(), scales.detach(), *view)
    if projected.means2d.requires_grad:
        projected.means2d.retain_grad()
    background = _background(features, background)
    opacities = opacities.reshape(-1)
    # Either pass's Gaussians: a list binned by the larger opacity holds every one that reaches a tile.
    reach = torch.maximum(opacities.detach(), second_opacities.detach())
    p, w, h = projected, camera.width, camera.height
    offsets, ids = run.bin(p.means2d, p.radii, p.conics, reach, p.depths, w, h)
    image, alpha, second, _ = run.composite_pair(
        projected.means2d, projected.conics, opacities, features,
        detached.means2d, detached.conics, second_opacities, second_values,
        offsets, ids, camera.width, camera.height, background, geometry_channels,
    )  # fmt: skip
    return RasterOutput(image, alpha, projected.means2d, projected.radii), second


def one_hot_rows(slots: Tensor, n_slots: int) -> Tensor:
    """``[N, n_slots]`` float rows with a 1 at each of a row's ``slots`` (``[N, K]`` long, -1: none)."""
    rows = torch.zeros(slots.shape[0], n_slots + 1)
    rows.scatter_(1, torch.where(slots < 0, n_slots, slots), 1.0)
    return rows[:, :n_slots]


def rasterize_slots(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    slots: Tensor,
    n_slots: int,
    camera: Camera,
    *,
    backend: Backend = "auto",
    near: float = NEAR_PLANE,
) -> Tensor:
    """Each column's rendering weight: ``[H, W, n_slots]``, channel c the sum of the weights of the
    Gaussians that list c in their ``slots`` row (``[N, K]`` long, distinct columns, -1: none). No
    gradient.

    Equal to ``rasterize(means, quats, scales, opacities, one_hot_rows(slots, n_slots), camera).image``,
    which the ``torch`` backend computes; the ``numba`` backend adds each hit to a Gaussian's K columns
    only (:func:`~langfield.raster.composite_cpu.rasterize_slots_cpu`).
    """
    run = kernels(backend)
    with torch.no_grad():
        if run.composite_slots is None:
            rows = one_hot_rows(slots, n_slots)
            return rasterize(means, quats, scales, opacities, rows, camera, backend=backend, near=near).image
        w, h = camera.width, camera.height
        p = run.project(means, quats, scales, camera.world_to_camera(), camera.intrinsics(), w, h, near)
        opacities = opacities.reshape(-1)
        offsets, ids = run.bin(p.means2d, p.radii, p.conics, opacities, p.depths, w, h)
        return run.composite_slots(p.means2d, p.conics, opacities, slots, n_slots, offsets, ids, w, h)


__all__ = [
    "BACKENDS",
    "Kernels",
    "RasterOutput",
    "composite",
    "kernels",
    "one_hot_rows",
    "project_gaussians",
    "quat_to_rotmat",
    "rasterize",
    "rasterize_slots",
    "rasterize_with_second_pass",
    "resolve_backend",
]
