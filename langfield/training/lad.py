"""Depth distillation: L_D = lambda L_SA + L_GL (eq. 11), language-aware (LAD) and global.

A monocular depth prior knows relative depth well inside one object and poorly across objects. LAD
(eq. 6, 9) therefore compares the rendered depth with the prior *inside each mask* of the view's
three-level segmentation, after min-max normalising both in that mask; the global term (eq. 10) compares
them over the whole image after mean / std normalisation, as DNGaussian's global depth loss does.
Both normalisations remove the prior's unknown scale and shift.

Per view, what does not change between iterations (which pixel belongs to which mask, the prior's
normalised values, which masks are usable) is computed once by :meth:`LADTarget.from_view`; each
iteration then costs one gather and two segment reductions (min, max) over all masks at once.

Prior pixels that are NaN or infinite are masked out of both terms (they belong to no mask and are not
part of the global statistics); the loader accepts such priors.

Example:
    >>> segments = torch.zeros(3, 8, 8, dtype=torch.long)  # one mask covering the view at every level
    >>> prior = torch.linspace(1.0, 2.0, 64).reshape(8, 8)
    >>> target = LADTarget.from_view(segments, prior, "depth")
    >>> depth = (prior * 3.0 + 1.0).requires_grad_()  # same shape up to scale and shift
    >>> depth_loss(target, depth, depth).item() < 1e-5
    True
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from encoders.protocols import DEPTH_KINDS, DepthKind

__all__ = [
    "GLOBAL_STD_RATIO",
    "LAMBDA_SA",
    "MIN_MASK_PIXELS",
    "PRIOR_MIN_RANGE",
    "RANGE_EPS",
    "RENDER_MIN_RANGE",
    "DepthKind",
    "LADTarget",
    "depth_loss",
    "global_depth_loss",
    "lad_loss",
]

LAMBDA_SA = 0.1  # eq. 11
MIN_MASK_PIXELS = 16  # masks with fewer valid pixels carry no usable depth structure
# A mask is skipped when the prior varies in it by less than this fraction of the prior's range over
# the image: relative, so the test does not depend on the prior's unknown scale.
PRIOR_MIN_RANGE = 1e-3
# Floor of the render's max - min in a mask, as a fraction of the render's range over the masked pixels
# (detached), so that a flat render at initialisation is never divided by zero and the loss stays
# invariant to the render's scale.
RENDER_MIN_RANGE = 1e-3
RANGE_EPS = 1e-6  # absolute floor under both relative floors (depth units), for constant images
GLOBAL_STD_RATIO = 0.01  # DNGaussian: (D - mean) / (std + 0.01 std)


@dataclass(frozen=True)
class LADTarget:
    """What the depth loss compares a view's rendered depth with; built once per view.

    An *entry* is one (mask, pixel) pair: a pixel covered at all three levels appears three times.
    Masks are the (level, id) pairs of ``segments``; the same id at two levels is two masks.

    Attributes:
        shape: (H, W) of the view.
        depth_kind: "depth" or "disparity", as the prior was given.
        pixel_index: [K] int64 flat pixel (y * W + x) of every entry of a usable mask.
        mask_index: [K] int64 mask of every entry, in 0..num_masks-1, ascending (entries of a mask
            are contiguous).
        mask_lengths: [M] int64 entries per mask.
        prior_local: [K] prior min-max normalised inside its mask (eq. 6), in [0, 1].
        num_masks: M, usable masks.
        num_skipped: masks dropped for having fewer than ``min_pixels`` valid pixels or a flat prior.
        valid_index: [V] int64 flat pixels with a finite prior (the global term's pixels); empty when
            the prior is constant (it then carries no depth information).
        prior_global: [V] prior normalised over the image (eq. 10).
    """

    shape: tuple[int, int]
    depth_kind: DepthKind
    pixel_index: Tensor
    mask_index: Tensor
    mask_lengths: Tensor
    prior_local: Tensor
    num_masks: int
    num_skipped: int
    valid_index: Tensor
    prior_global: Tensor

    @classmethod
    def from_view(
        cls,
        segments: Tensor,
        prior: Tensor,
        depth_kind: DepthKind,
        *,
        min_pixels: int = MIN_MASK_PIXELS,
        min_range: float = PRIOR_MIN_RANGE,
    ) -> LADTarget:
        """Precomputes a view's masks and normalised prior.

        Args:
            segments: [L, H, W] integer mask ids per level (L = 3: subpart, part, whole); -1 = no mask.
            prior: [H, W] float monocular depth or disparity, relative (unknown scale and shift); NaN
                and infinite pixels are ignored.
            depth_kind: "disparity" priors are negated so that larger means farther, like a depth.
            min_pixels: masks with fewer valid pixels are skipped.
            min_range: masks whose prior max - min is at most this fraction of the prior's range over
                the image are skipped.

        Returns:
            The view's :class:`LADTarget` (tensors on ``prior``'s device, float32).
        """
        _check_view_inputs(segments, prior, depth_kind, min_pixels)
        device = prior.device
        p = prior.detach().to(torch.float64).flatten()
        if depth_kind == "disparity":
            p = -p
        finite = torch.isfinite(p)
        valid_index = finite.nonzero().squeeze(1)
        pv = p[valid_index]
        image_range = float(pv.max() - pv.min()) if pv.numel() else 0.0

        # Entries: every (level, pixel) with a mask and a finite prior; key = level * (max id + 1) + id.
        seg = segments.to(device=device, dtype=torch.int64).flatten(1)  # [L, HW]
        covered = (seg >= 0) & finite[None]
        level, pixel = covered.nonzero(as_tuple=True)
        ids = seg[level, pixel]
        keys = level * (int(ids.max()) + 1 if ids.numel() else 1) + ids
        _, mask = torch.unique(keys, return_inverse=True)
        m_all = int(mask.max()) + 1 if mask.numel() else 0
        values = p[pixel]
        count = torch.bincount(mask, minlength=m_all)
        lo = _segment_reduce(values, mask, m_all, "amin")
        hi = _segment_reduce(values, mask, m_all, "amax")
        usable = (count >= min_pixels) & (hi - lo > max(min_range * image_range, RANGE_EPS))
        keep = usable[mask]
        compact = torch.cumsum(usable, 0) - 1  # old mask -> new mask
        mask, order = torch.sort(compact[mask[keep]], stable=True)  # contiguous masks for segment_reduce
        pixel, values = pixel[keep][order], values[keep][order]
        prior_local = (values - lo[usable][mask]) / (hi - lo)[usable][mask]
        num_masks = int(usable.sum())

        # Eq. 10 on the prior; population std (the render uses the same, so the convention cancels).
        std = float(pv.std(correction=0)) if pv.numel() else 0.0
        if std > RANGE_EPS:
            prior_global = (pv - pv.mean()) / ((1.0 + GLOBAL_STD_RATIO) * std)
        else:
            valid_index, prior_global = valid_index[:0], pv[:0]
        return cls(
            shape=(int(prior.shape[0]), int(prior.shape[1])),
            depth_kind=depth_kind,
            pixel_index=pixel,
            mask_index=mask,
            mask_lengths=torch.bincount(mask, minlength=num_masks),
            prior_local=prior_local.to(torch.float32),
            num_masks=num_masks,
            num_skipped=m_all - num_masks,
            valid_index=valid_index,
            prior_global=prior_global.to(torch.float32),
        )


def _check_view_inputs(segments: Tensor, prior: Tensor, depth_kind: str, min_pixels: int) -> None:
    if depth_kind not in DEPTH_KINDS:
        raise ValueError(f"depth_kind must be 'depth' or 'disparity', got {depth_kind!r}")
    if prior.ndim != 2 or not prior.is_floating_point():
        raise ValueError(f"prior must be a float [H, W] tensor, got {prior.dtype} {tuple(prior.shape)}")
    if segments.ndim != 3 or segments.shape[1:] != prior.shape or segments.is_floating_point():
        raise ValueError(
            f"segments must be an integer [L, H, W] tensor with (H, W) = {tuple(prior.shape)}, "
            f"got {segments.dtype} {tuple(segments.shape)}"
        )
    if min_pixels < 1:
        raise ValueError(f"min_pixels must be >= 1, got {min_pixels}")


def _segment_reduce(values: Tensor, segment: Tensor, num: int, reduce: Literal["amin", "amax"]) -> Tensor:
    """[num] min or max of ``values`` [K] per segment id [K] (every segment must be non-empty)."""
    return values.new_empty(num).scatter_reduce(0, segment, values, reduce, include_self=False)


def _check_depth(target: LADTarget, depth: Tensor) -> None:
    if depth.shape != target.shape or not depth.is_floating_point():
        raise ValueError(
            f"depth must be a float [H, W] tensor with (H, W) = {target.shape}, "
            f"got {depth.dtype} {tuple(depth.shape)}"
        )


def _zero(depth: Tensor) -> Tensor:
    """A zero scalar that is part of ``depth``'s graph (so ``backward`` works on it alone)."""
    return depth.flatten()[:0].sum()


def lad_loss(target: LADTarget, depth: Tensor) -> Tensor:
    """L_SA, language-aware depth distillation (eq. 6, 9).

    Inside every usable mask m, the rendered depth is min-max normalised, (D - min_m D) /
    max(max_m D - min_m D, floor), and compared by L1 with the prior normalised the same way (eq. 6).
    The floor is ``RENDER_MIN_RANGE`` x the render's range over all masked pixels (detached), at least
    ``RANGE_EPS``: a mask in which the render is still flat gives values in [0, 1] and finite gradients.
    The loss is the mean over all entries (mask, pixel) of all levels, so a pixel counts once per level
    that covers it and large masks weigh in proportion to their area.

    Args:
        target: the view's :class:`LADTarget`.
        depth: [H, W] rendered depth (hard or soft; differentiable).

    Returns:
        Scalar L_SA; 0 (still in ``depth``'s graph) when the view has no usable mask.
    """
    _check_depth(target, depth)
    if target.num_masks == 0:
        return _zero(depth)
    # index_select, not indexing: indexing's backward (index_put_ with accumulate) adds with atomics on
    # two or more threads past 32,768 entries, so two runs of one seed would differ; index_add_ adds
    # in order.
    d = depth.flatten().index_select(0, target.pixel_index)
    lo = torch.segment_reduce(d, "min", lengths=target.mask_lengths)
    hi = torch.segment_reduce(d, "max", lengths=target.mask_lengths)
    floor = (RENDER_MIN_RANGE * (d.amax() - d.amin())).detach().clamp_min(RANGE_EPS)
    scale = torch.maximum(hi - lo, floor)
    local = (d - lo.index_select(0, target.mask_index)) / scale.index_select(0, target.mask_index)
    return (local - target.prior_local.to(depth.dtype)).abs().mean()


def global_depth_loss(target: LADTarget, depth: Tensor) -> Tensor:
    """L_GL, global depth normalisation (eq. 10), DNGaussian's global term with an L1.

    Over the pixels with a finite prior, the render becomes (D - mean D) / (sg(std D) + 0.01 std D) with
    sg the stop-gradient (DNGaussian, ``patch_norm_mse_loss_global``), std floored at ``RANGE_EPS``;
    the prior was normalised as (P - mean P) / (1.01 std P) in :meth:`LADTarget.from_view`.

    Args:
        target: the view's :class:`LADTarget`.
        depth: [H, W] rendered depth (hard or soft; differentiable).

    Returns:
        Scalar L_GL; 0 (still in ``depth``'s graph) when the prior has no finite pixel or is constant.
    """
    _check_depth(target, depth)
    if target.valid_index.numel() == 0:
        return _zero(depth)
    d = depth.flatten().index_select(0, target.valid_index)
    mean = d.mean()
    # sqrt of a clamped variance: finite gradient for a constant render.
    std = ((d - mean).square().mean()).clamp_min(RANGE_EPS**2).sqrt()
    normalised = (d - mean) / (std.detach() + GLOBAL_STD_RATIO * std)
    return (normalised - target.prior_global.to(depth.dtype)).abs().mean()


def depth_loss(
    target: LADTarget,
    hard_depth: Tensor,
    soft_depth: Tensor,
    lambda_sa: float = LAMBDA_SA,
    lad: bool = True,
) -> Tensor:
    """L_D = lambda L_SA + L_GL (eq. 11), summed over the hard (eq. 7) and soft (eq. 8) rendered depth.

    Args:
        target: the view's :class:`LADTarget`.
        hard_depth: [H, W] depth rendered with every opacity set to mu (eq. 7).
        soft_depth: [H, W] depth rendered with the Gaussians' opacities (eq. 8).
        lambda_sa: weight of L_SA.
        lad: False drops L_SA, leaving the plain global depth loss (the ``--no-lad`` ablation).

    Returns:
        Scalar L_D.
    """
    total = _zero(soft_depth)
    for depth in (hard_depth, soft_depth):
        total = total + global_depth_loss(target, depth)
        if lad:
            total = total + lambda_sa * lad_loss(target, depth)
    return total
