"""Which codebook entry a pixel reads: the nearest entry of its blended latent, checked against the
entries of the Gaussians that render it (``--language-decode vote``, docs/how-it-works.md).

A rendered latent is a blend, ``L(p) = sum_i w_i(p) c_i``. Where Gaussians of two concepts share a pixel
(an object's edge, a thin lamp post in front of a wall), the blend lies between their latents on the
3-d sphere, and its nearest entry can be a third concept that no Gaussian there carries: a table along
a lamp post, a mug on a table's leg. The vote reads the blend's nearest entry only where Gaussians whose
own latents are nearest to that concept's entries carry at least :data:`VOTE_SHARE` of the pixel's
rendering weight; elsewhere the pixel reads the entry whose Gaussians carry the most weight there (the
mode of the Gaussians' entries instead of the entry of their mean).

The weights per entry come from the tested rasterizer itself: every Gaussian carries a one-hot row of
its entry, so channel e of the render is ``sum_i w_i(p) [entry_i = e]``; the rows are given by index
(:func:`langfield.raster.rasterize_slots`), so a hit costs a Gaussian's three entries, not every entry.
Entries are rendered in chunks of channels, so memory stays bounded for a codebook of thousands of
training masks.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

__all__ = ["CONCEPT_ANGLE_DEGREES", "VOTE_SHARE", "concept_groups", "vote_entries"]

# A pixel keeps its blend's nearest entry when the Gaussians of that entry's concept carry at least this
# share of its opacity. Nine rooms, novel-view mIoU of one training run each (docs/history/figures.md,
# "Reading by vote"): share 0.1 0.861, 0.15 0.861, 0.25 0.859; 1 (the mode alone) 0.845; the blend
# alone 0.817.
VOTE_SHARE = 0.15
# Entries closer than this are one concept (single linkage). The entries are the training views' masks;
# one object's masks in different views lie 0-1 degree apart in the rooms, different objects 6 or more.
# 2 and 5 degrees read the nine rooms alike; 0 (each entry its own concept) gives 0.847.
CONCEPT_ANGLE_DEGREES = 2.0
# Floats of one chunk's [H, W, C] weights (64 MiB).
CHUNK_VALUES = 1 << 24


def concept_groups(entries: Tensor, angle_degrees: float = CONCEPT_ANGLE_DEGREES) -> Tensor:
    """``[P]`` long: a concept id per entry of ``entries`` ``[P, 3]`` (unit rows): entries linked by a
    chain of pairs closer than ``angle_degrees`` share the smallest index among them."""
    n = entries.shape[0]
    labels = torch.arange(n)
    if n == 0:
        return labels
    close = entries @ entries.T >= math.cos(math.radians(angle_degrees))
    close |= torch.eye(n, dtype=torch.bool)
    while True:  # propagate the smallest label along links; at most P rounds
        spread = torch.where(close, labels[None, :], n).amin(dim=1)
        if torch.equal(spread, labels):
            return labels
        labels = spread


def vote_entries(
    nearest: Tensor,
    gaussian_entries: Tensor,
    sizes: list[int],
    groups: list[Tensor],
    alpha: Tensor,
    render: Callable[[Tensor, int], Tensor],
    share: float = VOTE_SHARE,
    chunk_values: int = CHUNK_VALUES,
) -> Tensor:
    """The entry each pixel reads at each level.

    Args:
        nearest: ``[L, H, W]`` long, the nearest entry of each pixel's blended latent (-1: none).
        gaussian_entries: ``[L, N]`` long, the nearest entry of each Gaussian's own latent (-1: none).
        sizes: the number of entries of each level.
        groups: per level, ``[P_l]`` long concept ids (:func:`concept_groups`).
        alpha: ``[H, W]`` the pixels' accumulated opacity (the sum of their rendering weights).
        render: ``(columns [N, K] long, C)`` -> ``[H, W, C]``: channel c the rendering weight of the
            Gaussians that list c among their columns (-1: none), as
            :func:`langfield.raster.rasterize_slots` gives it.
        share: :data:`VOTE_SHARE`.
        chunk_values: most floats of one render's output.

    Returns:
        ``[L, H, W]`` long: ``nearest`` where its concept's Gaussians carry at least ``share`` of
        ``alpha``, else the entry with the most weight (-1 where Gaussians without an entry carry most;
        ties go to the lower entry).
    """
    h, w = alpha.shape
    levels = range(len(sizes))
    # Slots per level: its entries, then "no entry" (a concept of its own, -1).
    slot_of = [torch.where(e < 0, sizes[lv], e) for lv, e in enumerate(gaussian_entries)]
    # Concept ids per slot in [0, P]: a group's smallest entry, P for "no entry".
    concepts = [torch.cat([g, g.new_tensor([sizes[lv]])]) for lv, g in enumerate(groups)]
    nearest_slot = torch.stack([torch.where(nearest[lv] < 0, sizes[lv], nearest[lv]) for lv in levels])
    nearest_concept = torch.stack([concepts[lv][nearest_slot[lv]] for lv in levels])
    # Per level, each pixel's slots of its blend's concept: [H * W, G] (-1: padding).
    members = [_members(concepts[lv])[nearest_concept[lv].reshape(-1)] for lv in levels]
    best_weight = torch.full((len(sizes), h, w), -1.0)
    best_slot = torch.zeros((len(sizes), h, w), dtype=torch.long)
    concept_weight = torch.zeros(len(sizes), h, w)
    # A slot no Gaussian carries weighs 0 everywhere: it wins nowhere a pixel has weight, so it is not
    # rendered.
    slots = [(lv, int(s)) for lv in levels for s in torch.unique(slot_of[lv])]
    step = max(1, chunk_values // max(1, h * w))
    for start in range(0, len(slots), step):
        chunk = slots[start : start + step]
        # Each Gaussian's column in this chunk at each level (-1: its slot lies in another chunk).
        column_of = [torch.full((sizes[lv] + 1,), -1, dtype=torch.long) for lv in levels]
        for c, (lv, s) in enumerate(chunk):
            column_of[lv][s] = c
        columns = torch.stack([column_of[lv][slot_of[lv]] for lv in levels], dim=1)  # [N, L]
        weights = render(columns, len(chunk))  # [H, W, C]
        for lv in levels:
            cols = [c for c, (level, _) in enumerate(chunk) if level == lv]
            if not cols:
                continue
            ids = torch.tensor([chunk[c][1] for c in cols])
            part = weights[..., cols[0] : cols[-1] + 1]  # a chunk lists its slots level by level
            top, arg = part.max(dim=-1)  # the first of equal maxima: the lower slot
            better = top > best_weight[lv]  # strictly: an earlier chunk's lower slot keeps a tie
            best_weight[lv] = torch.where(better, top, best_weight[lv])
            best_slot[lv] = torch.where(better, ids[arg], best_slot[lv])
            # The weight of the pixel's concept: its member slots' columns here (-1: not in this chunk).
            member_cols = torch.where(members[lv] >= 0, column_of[lv][members[lv]], -1) - cols[0]
            inside = member_cols >= 0
            carried = part.reshape(h * w, -1).gather(1, member_cols.clamp_min(0)) * inside
            concept_weight[lv] += carried.sum(dim=1).reshape(h, w)
    chosen = torch.where(concept_weight >= share * alpha, nearest_slot, best_slot)
    return torch.stack([torch.where(chosen[lv] == sizes[lv], -1, chosen[lv]) for lv in levels])


def _members(concepts: Tensor) -> Tensor:
    """``[K, G]`` long: row k lists the slots whose concept is k (``concepts`` ``[S]``, ids in [0, K)),
    padded with -1 to the largest concept's size G."""
    k = int(concepts.max()) + 1
    order = torch.argsort(concepts, stable=True)
    counts = torch.bincount(concepts, minlength=k)
    rank = torch.arange(len(concepts)) - torch.repeat_interleave(torch.cumsum(counts, 0) - counts, counts)
    out = torch.full((k, int(counts.max())), -1, dtype=torch.long)
    out[concepts[order], rank] = order
    return out
