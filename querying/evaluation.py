"""Open-vocabulary query metrics: mask IoU, localization hits, and their means over (view, phrase) pairs.

The metrics are LangSplat's (``eval/evaluate_iou_loc.py``): per (view, phrase) pair the IoU of the
mask of :func:`querying.relevancy.relevancy_mask` with the ground truth, and a localization hit
(:func:`querying.relevancy.localization_hit`); mIoU and mAcc are their means over all pairs, as
docs/format.md's evaluation report states.

Example:
    >>> records = [{"iou": 1.0, "hit": True}, {"iou": 0.5, "hit": False}]
    >>> summarize_queries(records)
    {'mIoU': 0.75, 'mAcc': 0.5}
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import torch
from torch import Tensor

from querying.relevancy import localization_hit, relevancy_mask

__all__ = ["EMPTY_IOU", "mask_iou", "query_record", "summarize_queries"]

# IoU of two empty masks: a prediction of "nothing" for an absent object is exact. (LangSplat divides
# by the union and would give NaN; its ground truth never has empty masks.)
EMPTY_IOU = 1.0


def mask_iou(prediction: Tensor, target: Tensor) -> float:
    """Intersection over union of two binary masks (LangSplat ``activate_stream``).

    Args:
        prediction: ``[H, W]`` bool (or 0/1) predicted mask.
        target: ``[H, W]`` bool (or 0/1) ground-truth mask.

    Returns:
        |prediction and target| / |prediction or target| in [0, 1]; :data:`EMPTY_IOU` (1.0) when both
        masks are empty.
    """
    if prediction.shape != target.shape:
        raise ValueError(
            f"mask_iou: masks must have the same shape, "
            f"got {tuple(prediction.shape)} and {tuple(target.shape)}"
        )
    p, t = prediction.bool(), target.bool()
    union = int(torch.count_nonzero(p | t))
    if union == 0:
        return EMPTY_IOU
    return int(torch.count_nonzero(p & t)) / union


def query_record(maps: Tensor, gt_mask: Tensor) -> dict[str, float | bool]:
    """Score one phrase in one view: the report's ``{"iou": .., "hit": ..}`` (docs/format.md).

    Args:
        maps: ``[L, H, W]`` relevancy maps of the phrase, one per level (:func:`relevancy`).
        gt_mask: ``[H, W]`` bool ground-truth mask of the phrase's object.

    Returns:
        ``{"iou": mask IoU of relevancy_mask(maps), "hit": localization_hit(maps, gt_mask)}``.
    """
    if maps.dim() != 3:
        raise ValueError(f"query_record: expected maps [L, H, W], got {tuple(maps.shape)}")
    return {
        "iou": mask_iou(relevancy_mask(maps).mask, gt_mask),
        "hit": localization_hit(maps, gt_mask),
    }


def summarize_queries(records: Iterable[Mapping[str, float | bool]]) -> dict[str, float | None]:
    """mIoU and mAcc over all (view, phrase) pairs (docs/format.md, "Evaluation report").

    For a report's ``views`` pass ``(q for v in views for q in v["queries"].values())``; every pair
    weighs the same, whatever its view.

    Args:
        records: one ``{"iou": float, "hit": bool}`` per (view, phrase) pair.

    Returns:
        ``{"mIoU": mean IoU, "mAcc": fraction of hits}``, both None when there are no records (a scene
        without labels).
    """
    records = list(records)
    if not records:
        return {"mIoU": None, "mAcc": None}
    return {
        "mIoU": sum(float(r["iou"]) for r in records) / len(records),
        "mAcc": sum(bool(r["hit"]) for r in records) / len(records),
    }
