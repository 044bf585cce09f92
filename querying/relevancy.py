"""Relevancy of text phrases to per-pixel language features, and LangSplat's mask pipeline.

A phrase q is scored against a feature f by its *relevancy* (LERF, Kerr et al. 2023, sec. 3.4; used
unchanged by LangSplat): with s the cosine similarity,

    rel_q(f) = min over canonical phrases c of exp(10 s_q) / (exp(10 s_q) + exp(10 s_c)),

where the canonical phrases are "object", "things", "stuff" and "texture" (LERF
``lerf/encoders/openclip_encoder.py``, ``negatives``; LangSplat ``eval/openclip_encoder.py``).

Masks follow LangSplat's evaluation (``eval/evaluate_iou_loc.py``, ``activate_stream``, and
``eval/utils.py``, ``smooth``), step by step, one function per step:

1. :func:`smooth_map`: per level, 0.5 * (30x30 box-filtered map) + 0.5 * map, the box being
   ``cv2.filter2D`` with its default anchor and border (:func:`box_filter`: window -15 .. +14, mirrored
   borders);
2. :func:`choose_level`: the level whose smoothed map has the highest maximum;
3. :func:`normalize_map`: that level's *smoothed* map, min-max stretched to [-1, 1] and clipped to [0, 1];
4. threshold at 0.4 (``--mask_thresh 0.4`` in LangSplat's ``eval/eval.sh``), i.e. 0.7 of the min-max range;
5. :func:`majority_filter`: 7x7 majority vote (LangSplat's ``smooth``: window of +-3 pixels cut off at
   the border, ties to 0, the last row and column not voting).

LangSplat uses these pixel sizes at whatever resolution it evaluates, which for LERF-OVS is the images'
own, 985 to 988 pixels wide. From :data:`REFERENCE_WIDTH` (985) on, the sizes here are LangSplat's and
the pipeline gives LangSplat's masks; on narrower images :func:`scaled_size` shrinks them with the
width (a 30-pixel box on a 160-pixel image would erase a mug).

Localization (LangSplat ``lerf_localization``): box-filter each level, take the level with the highest
maximum, and score a hit if that maximum's pixel lies inside the object (:func:`localization_hit`;
LangSplat tests it against the object's bounding boxes and accepts any tied maximum; here of tied
maxima the one deepest inside their plateau counts).

Small objects: at the map's minimum background, a band of width w pixels survives the threshold only
if w > 0.4 x the box size (0.5 + 0.5 w / box > 0.7); with the sizes of :func:`scaled_size` that is about
1.2 % of the image width, so at 160 pixels 1-pixel-thin structures (a table leg seen from afar) vanish
while anything 2 pixels wide survives. At LangSplat's own resolution the 7x7 majority vote also rounds
off the corners of masks, as it does in LangSplat.

Everything here works on tensors: ``[..., H, W]`` maps with any leading batch shape (phrases, levels),
so several phrases share one pass.

Example:
    >>> feats = torch.nn.functional.normalize(torch.randn(3, 120, 160, 512), dim=-1)
    >>> phrase, canon = torch.randn(1, 512), torch.randn(4, 512)
    >>> maps = relevancy(feats, phrase, canon)  # [1, 3, 120, 160]
    >>> result = relevancy_mask(maps)
    >>> result.mask.shape, result.level.shape
    (torch.Size([1, 120, 160]), torch.Size([1]))
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from encoders.protocols import CANONICAL_PHRASES

__all__ = [
    "CANONICAL_PHRASES",
    "EMBEDDING_EPS",
    "LOCALIZATION_BOX_AT_REFERENCE",
    "MAJORITY_SIZE_AT_REFERENCE",
    "MASK_THRESHOLD",
    "NORMALIZE_EPS",
    "REFERENCE_WIDTH",
    "SMOOTHING_BOX_AT_REFERENCE",
    "SMOOTHING_WEIGHT",
    "TEMPERATURE",
    "RelevancyMask",
    "box_filter",
    "choose_level",
    "cosine_similarity",
    "localization_hit",
    "localization_point",
    "majority_filter",
    "normalize_map",
    "relevancy",
    "relevancy_mask",
    "scaled_size",
    "smooth_map",
]

# Softmax temperature of the pairwise relevancy: softmax(10 * [s_q, s_c]) (LERF, LangSplat).
TEMPERATURE = 10.0
# Norm floor when normalising features, so zero vectors give similarity 0 (relevancy 0.5), not NaN.
EMBEDDING_EPS = 1e-8
# Image width (pixels) from which on LangSplat's filter sizes are used unscaled: the narrowest LERF-OVS
# image LangSplat evaluates on, at full resolution (waldo_kitchen 985x725, figurines 986x728, ramen and
# teatime 988x731; LangSplat's eval reads the size from each label's JSON).
REFERENCE_WIDTH = 985
# LangSplat activate_stream: `scale = 30`, a 30x30 mean filter, mixed half and half with the map.
SMOOTHING_BOX_AT_REFERENCE = 30
SMOOTHING_WEIGHT = 0.5
# LangSplat eval.sh: `--mask_thresh 0.4`, applied after stretching the map to [-1, 1] and clipping.
MASK_THRESHOLD = 0.4
# LangSplat activate_stream: `output / (torch.max(output) + 1e-9)`.
NORMALIZE_EPS = 1e-9
# LangSplat eval/utils.py smooth: `scale = 3`, a window of i-3 .. i+3, i.e. 7x7.
MAJORITY_SIZE_AT_REFERENCE = 7
# LangSplat lerf_localization: `scale = 30`, a 30x30 mean filter before the argmax.
LOCALIZATION_BOX_AT_REFERENCE = 30


class RelevancyMask(NamedTuple):
    """Output of :func:`relevancy_mask` for maps ``[..., L, H, W]``.

    Attributes:
        mask: ``[..., H, W]`` bool, the predicted object mask.
        level: ``[...]`` long, the chosen level (``int(result.level)`` for a single phrase).
        normalized: ``[..., H, W]`` float in [0, 1], the chosen level's normalised smoothed map that was
            thresholded (zero on the lower half of the map's range).
    """

    mask: Tensor
    level: Tensor
    normalized: Tensor


def _check_map(name: str, x: Tensor, min_dims: int) -> None:
    """The one input check of this module: a tensor with at least ``min_dims`` dimensions."""
    if not isinstance(x, Tensor) or x.dim() < min_dims or x.shape[-1] == 0 or x.shape[-2] == 0:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"{name}: expected a tensor with at least {min_dims} dimensions, got {shape}")


# ---------------------------------------------------------------- relevancy


def cosine_similarity(features: Tensor, embeddings: Tensor, eps: float = EMBEDDING_EPS) -> Tensor:
    """Cosine similarity of every feature with every embedding.

    The features are not copied to unit length (they can be millions of 512-d vectors): the dot
    products are divided by the feature norms, floored at ``eps`` so a zero feature scores 0.

    Args:
        features: ``[..., D]`` vectors of any length.
        embeddings: ``[K, D]`` vectors of any length.
        eps: norm floor.

    Returns:
        ``[..., K]`` float32 similarities in [-1, 1].
    """
    if embeddings.dim() != 2 or features.shape[-1] != embeddings.shape[-1]:
        raise ValueError(
            f"cosine_similarity: expected features [..., D] and embeddings [K, D], "
            f"got {tuple(features.shape)} and {tuple(embeddings.shape)}"
        )
    f = features.float()
    e = torch.nn.functional.normalize(embeddings.float(), dim=-1, eps=eps)
    norms = torch.linalg.vector_norm(f, dim=-1, keepdim=True).clamp_min(eps)
    return (f @ e.T) / norms


def relevancy(
    features: Tensor,
    phrase_embeddings: Tensor,
    canonical_embeddings: Tensor,
    temperature: float = TEMPERATURE,
) -> Tensor:
    """Relevancy of each phrase to each feature (LERF sec. 3.4; LangSplat ``get_relevancy``).

    rel_q = min_c exp(t s_q) / (exp(t s_q) + exp(t s_c)) = min_c sigmoid(t (s_q - s_c))
          = sigmoid(t (s_q - max_c s_c)),

    since the sigmoid is increasing; the sigmoid form never overflows. All phrases share one matrix
    product with the features.

    Args:
        features: ``[..., D]`` language features (e.g. decoded latents ``[L, H, W, 512]``); need not
            be unit vectors.
        phrase_embeddings: ``[Q, D]`` text embeddings of the queried phrases.
        canonical_embeddings: ``[C, D]`` text embeddings of :data:`CANONICAL_PHRASES`.
        temperature: the softmax temperature, 10 in LERF and LangSplat.

    Returns:
        ``[Q, ...]`` relevancy in [0, 1]; 0.5 means "as relevant as the most similar canonical phrase".

    Example:
        >>> e = torch.eye(3)
        >>> float(relevancy(e[0], e[:1], e[1:]))  # s_q = 1, s_c = 0: 1 / (1 + e^-10)
        0.9999545812606812
    """
    if phrase_embeddings.dim() != 2 or canonical_embeddings.dim() != 2 or canonical_embeddings.shape[0] == 0:
        raise ValueError(
            f"relevancy: expected phrase embeddings [Q, D] and canonical embeddings [C>0, D], "
            f"got {tuple(phrase_embeddings.shape)} and {tuple(canonical_embeddings.shape)}"
        )
    n_phrases = phrase_embeddings.shape[0]
    sims = cosine_similarity(features, torch.cat([phrase_embeddings, canonical_embeddings]))
    s_phrase, s_canonical = sims[..., :n_phrases], sims[..., n_phrases:]
    rel = torch.sigmoid(temperature * (s_phrase - s_canonical.amax(dim=-1, keepdim=True)))
    return rel.movedim(-1, 0)


# ---------------------------------------------------------------- image operations


def scaled_size(size_at_reference: int, width: int, reference_width: int = REFERENCE_WIDTH) -> int:
    """LangSplat's filter size for an image ``width`` pixels wide.

    At and above ``reference_width`` this is ``size_at_reference`` itself, so there the pipeline is
    LangSplat's, which uses the same 30 and 7 at every resolution. Below it the size shrinks with the
    width: the largest odd size not above ``size_at_reference * width / reference_width`` (at least 1).
    Odd, so the window is centred; rounded down, so relative to the image it is never wider than
    LangSplat's and never reaches further than LangSplat's longer side (15 pixels before a pixel for
    the 30 box, whose window is -15 .. +14; 3 either side for the vote).

    Args:
        size_at_reference: LangSplat's size in pixels (30 for the box, 7 for the vote).
        width: the image's width in pixels.
        reference_width: the width from which on LangSplat's size is used (:data:`REFERENCE_WIDTH`).

    Returns:
        A size >= 1, e.g. 30 -> 30 at 985 px and above, 29 at 980 px, 3 at 160 px; 7 -> 7 at 985 px,
        5 at 980 px, 1 at 160 px.
    """
    if size_at_reference < 1 or width < 1 or reference_width < 1:
        raise ValueError(f"scaled_size: sizes must be positive, got {size_at_reference}, {width}")
    if width >= reference_width:
        return size_at_reference
    scaled = size_at_reference * width / reference_width
    return max(1, 2 * int((scaled - 1) // 2) + 1)


def _as_batch(maps: Tensor) -> tuple[Tensor, torch.Size]:
    """``[..., H, W]`` -> ``[B, 1, H, W]`` float, and the leading shape to restore."""
    lead = maps.shape[:-2]
    return maps.reshape(-1, 1, *maps.shape[-2:]).float(), lead


def _reflect_101(n: int, before: int, after: int, device: torch.device) -> Tensor:
    """Indices of a length-``n`` axis padded by ``before`` and ``after`` with OpenCV's BORDER_REFLECT_101
    (``dcb|abcd|cba``), reflecting again as often as a pad longer than the axis needs."""
    index = torch.arange(-before, n + after, device=device)
    if n == 1:
        return torch.zeros_like(index)
    period = 2 * (n - 1)
    index = torch.remainder(index, period)
    return torch.where(index >= n, period - index, index)


def box_filter(maps: Tensor, size: int) -> Tensor:
    """``cv2.filter2D(map, -1, np.ones((size, size)) / size**2)``, OpenCV's defaults included (LangSplat
    ``eval/evaluate_iou_loc.py``, ``activate_stream`` and ``lerf_localization``, with size 30).

    The window of pixel i spans i - size // 2 .. i + (size - 1 - size // 2) in each axis, as
    ``filter2D``'s default anchor puts it: centred for an odd size, -15 .. +14 for LangSplat's 30.
    Pixels outside the image are mirrored without repeating the edge (BORDER_REFLECT_101, filter2D's
    default border), reflected again where the window is longer than the image.

    Args:
        maps: ``[..., H, W]`` float maps.
        size: window size in pixels, odd or even (see :func:`scaled_size`); 1 returns the maps unchanged.

    Returns:
        ``[..., H, W]`` float32 filtered maps.
    """
    _check_map("box_filter", maps, 2)
    if size < 1:
        raise ValueError(f"box_filter: size must be positive, got {size}")
    if size == 1:
        return maps.float().clone()
    h, w = maps.shape[-2:]
    batch, lead = _as_batch(maps)
    before, after = size // 2, size - 1 - size // 2
    padded = batch.index_select(-2, _reflect_101(h, before, after, batch.device))
    padded = padded.index_select(-1, _reflect_101(w, before, after, batch.device))
    # Separable mean: two passes of `size` additions per pixel instead of size**2.
    rows = torch.nn.functional.avg_pool2d(padded, (size, 1), stride=1)
    return torch.nn.functional.avg_pool2d(rows, (1, size), stride=1).reshape(*lead, h, w)


def _window_sums(batch: Tensor, size: int) -> Tensor:
    """Sums over centred ``size`` x ``size`` windows, zeros outside the image (exact for 0/1 images)."""
    r = size // 2
    rows = torch.nn.functional.avg_pool2d(batch, (size, 1), stride=1, padding=(r, 0), divisor_override=1)
    return torch.nn.functional.avg_pool2d(rows, (1, size), stride=1, padding=(0, r), divisor_override=1)


def majority_filter(mask: Tensor, size: int, last_line_votes: bool = False) -> Tensor:
    """Majority vote of a binary mask over a ``size`` x ``size`` window: LangSplat ``eval/utils.py``
    ``smooth`` (size 7: ``scale = 3``).

    A pixel is set if strictly more than half of the pixels that vote in its window are set; a tie
    goes to 0, as ``np.argmax(np.bincount(...))`` gives. The window is cut off at the image border. As
    in ``smooth``, whose slice of pixel i stops at ``min(i + scale + 1, h - 1)``, the last row and the
    last column never vote (they are still voted on); ``last_line_votes=True`` lets them vote too.
    A window without voters (an image one pixel high or wide) gives 0, where ``smooth`` would fail.

    Args:
        mask: ``[..., H, W]`` bool (or 0/1) masks.
        size: odd window size (see :func:`scaled_size`); 1 returns the mask unchanged.
        last_line_votes: whether the last row and column vote (False: LangSplat's ``smooth``).

    Returns:
        ``[..., H, W]`` bool masks.
    """
    _check_map("majority_filter", mask, 2)
    if size < 1 or size % 2 == 0:
        raise ValueError(f"majority_filter: size must be odd and positive, got {size}")
    if size == 1:
        return mask.bool().clone()
    batch, lead = _as_batch(mask.bool())
    voters = torch.ones_like(batch[:1])
    if not last_line_votes:
        voters[..., -1, :] = 0.0
        voters[..., :, -1] = 0.0
    ones = _window_sums(batch * voters, size)
    pixels = _window_sums(voters, size)
    return (2.0 * ones > pixels).reshape(*lead, *mask.shape[-2:])


# ---------------------------------------------------------------- LangSplat's mask pipeline


def smooth_map(maps: Tensor, box_size: int | None = None, weight: float = SMOOTHING_WEIGHT) -> Tensor:
    """``weight`` x box-filtered map + (1 - weight) x map (LangSplat ``activate_stream``:
    ``0.5 * (avg_filtered + valid_map)``, "suppresses noise and keeps the activation's edges sharp").

    Args:
        maps: ``[..., H, W]`` relevancy maps.
        box_size: box size (odd or even); default :data:`SMOOTHING_BOX_AT_REFERENCE` via
            :func:`scaled_size`.
        weight: weight of the box-filtered map (:data:`SMOOTHING_WEIGHT`).

    Returns:
        ``[..., H, W]`` float32 smoothed maps.
    """
    _check_map("smooth_map", maps, 2)
    size = scaled_size(SMOOTHING_BOX_AT_REFERENCE, maps.shape[-1]) if box_size is None else box_size
    return weight * box_filter(maps, size) + (1.0 - weight) * maps.float()


def choose_level(maps: Tensor, box_size: int | None = None) -> tuple[Tensor, Tensor]:
    """Pick, per phrase, the level whose smoothed map has the highest maximum (LangSplat
    ``activate_stream``: ``chosen_lvl = torch.argmax(score_lvl)`` with ``score = valid_map[i, k].max()``
    taken after smoothing). Ties go to the first level.

    Args:
        maps: ``[..., L, H, W]`` relevancy maps of L levels.
        box_size: box size for :func:`smooth_map`; default scaled to the width.

    Returns:
        ``(level [...] long, smoothed [..., L, H, W])``.
    """
    _check_map("choose_level", maps, 3)
    smoothed = smooth_map(maps, box_size)
    level = smoothed.flatten(-2).amax(dim=-1).argmax(dim=-1)
    return level, smoothed


def normalize_map(maps: Tensor, eps: float = NORMALIZE_EPS) -> Tensor:
    """LangSplat's stretch before thresholding (``activate_stream``, "truncate the heatmap into mask"):
    subtract the minimum, divide by the maximum (+ eps), map [0, 1] to [-1, 1] and clip to [0, 1].

    The map's lower half therefore becomes 0, and a threshold t on the result is a threshold of
    (1 + t) / 2 on the min-max normalised map (0.7 for LangSplat's 0.4). A constant map gives all
    zeros, not NaN.

    Args:
        maps: ``[..., H, W]`` maps.
        eps: added to the range, LangSplat's 1e-9.

    Returns:
        ``[..., H, W]`` float32 in [0, 1].
    """
    _check_map("normalize_map", maps, 2)
    flat = maps.float().flatten(-2)
    shifted = flat - flat.amin(dim=-1, keepdim=True)
    unit = shifted / (shifted.amax(dim=-1, keepdim=True) + eps)
    return (2.0 * unit - 1.0).clamp(0.0, 1.0).reshape(maps.shape)


def relevancy_mask(maps: Tensor, threshold: float = MASK_THRESHOLD) -> RelevancyMask:
    """LangSplat's evaluation mask from per-level relevancy maps: smooth, choose the level, normalise
    the chosen smoothed map, threshold (strictly above ``threshold``), majority-filter.

    Filter sizes come from :func:`scaled_size`: LangSplat's 30x30 box and 7x7 vote from
    :data:`REFERENCE_WIDTH` on; at 160 px a 3x3 box and no majority vote, so a map equal to an object's
    mask 2 or more pixels wide returns exactly that mask.

    Args:
        maps: ``[..., L, H, W]`` relevancy maps in [0, 1], e.g. :func:`relevancy`'s ``[Q, L, H, W]``.
        threshold: on the normalised map, LangSplat's ``--mask_thresh 0.4``.

    Returns:
        :class:`RelevancyMask` ``(mask [..., H, W], level [...], normalized [..., H, W])``.
    """
    level, smoothed = choose_level(maps)
    h, w = maps.shape[-2:]
    index = level[..., None, None, None].expand(*level.shape, 1, h, w)
    chosen = smoothed.gather(-3, index).squeeze(-3)
    normalized = normalize_map(chosen)
    mask = majority_filter(normalized > threshold, scaled_size(MAJORITY_SIZE_AT_REFERENCE, w))
    return RelevancyMask(mask, level, normalized)


# ---------------------------------------------------------------- localization


def localization_point(maps: Tensor, box_size: int | None = None) -> tuple[Tensor, Tensor]:
    """The pixel LangSplat's localization points at (``lerf_localization``): box-filter every level,
    keep the level with the highest maximum, return that maximum's pixel.

    Of maxima tied exactly (a plateau: a map read through a codebook is constant over each concept's
    pixels, and the relevancy saturates) the one deepest inside its tied region is taken, by
    chessboard distance to the nearest untied pixel or the image border; among equally deep ones the
    first level, then the first in row-major order. LangSplat accepts any tied pixel, so a flat map
    would hit everywhere; the first tied pixel in row-major order would be the plateau's top-left
    corner, which on a plateau that reaches past the object lies outside it.

    Args:
        maps: ``[..., H, W]`` or ``[..., L, H, W]`` relevancy maps; a 2-d map is one level.
        box_size: box size (odd or even); default :data:`LOCALIZATION_BOX_AT_REFERENCE` via
            :func:`scaled_size`.

    Returns:
        ``(level [...] long, yx [..., 2] long)``: the chosen level and (row, column) of the point.
    """
    _check_map("localization_point", maps, 2)
    if maps.dim() == 2:
        maps = maps[None]
    levels, h, w = maps.shape[-3:]
    lead = maps.shape[:-3]
    size = scaled_size(LOCALIZATION_BOX_AT_REFERENCE, w) if box_size is None else box_size
    filtered = box_filter(maps, size).reshape(-1, levels, h, w)  # [B, L, H, W]
    filtered = torch.nan_to_num(filtered, nan=-torch.inf)  # a NaN pixel is never the point
    top = filtered.flatten(1).amax(dim=1)  # [B]
    depth = _depth_inside(filtered == top[:, None, None, None])  # [B, L, H, W], 0 where not tied
    flat = depth.flatten(1).argmax(dim=1)  # first of the deepest: first level, then row-major
    level, pixel = flat // (h * w), flat % (h * w)
    yx = torch.stack([pixel // w, pixel % w], dim=-1)
    return level.reshape(lead), yx.reshape(*lead, 2)


def _depth_inside(region: Tensor) -> Tensor:
    """``[B, L, H, W]`` bool -> int32 chessboard distance of each region pixel to the nearest pixel
    outside the region or outside the image (1 on its rim), 0 outside (OpenCV's ``DIST_C`` transform,
    on the maps and levels that hold more than one region pixel)."""
    depth = region.to(torch.int32)
    counts = region.flatten(2).sum(dim=2)  # [B, L]
    if int(counts.sum()) <= 1:
        return depth
    import cv2

    for b, level in torch.nonzero(counts > 1).tolist():
        padded = np.pad(region[b, level].cpu().numpy().astype(np.uint8), 1)  # the border counts as outside
        distance = cv2.distanceTransform(padded, cv2.DIST_C, 3)[1:-1, 1:-1]
        depth[b, level] = torch.from_numpy(np.rint(distance).astype(np.int32)).to(depth.device)
    return depth


def localization_hit(maps: Tensor, gt_mask: Tensor) -> bool:
    """Whether the localization point (:func:`localization_point`) lies inside the object.

    LangSplat tests the point against the object's bounding boxes; here against its mask (docs/design.md).

    Args:
        maps: ``[H, W]`` or ``[L, H, W]`` relevancy maps of one phrase.
        gt_mask: ``[H, W]`` bool ground-truth mask.

    Returns:
        True if the point is inside ``gt_mask``.
    """
    if maps.dim() not in (2, 3) or tuple(gt_mask.shape) != tuple(maps.shape[-2:]):
        raise ValueError(
            f"localization_hit: expected maps [H, W] or [L, H, W] and a mask [H, W], "
            f"got {tuple(maps.shape)} and {tuple(gt_mask.shape)}"
        )
    _, yx = localization_point(maps)
    return bool(gt_mask.bool()[yx[0], yx[1]])
