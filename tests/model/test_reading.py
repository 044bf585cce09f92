"""Tests of the vote reading (langfield/model/reading.py): concept groups and the entry each pixel reads."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch import Tensor

from langfield.model.reading import VOTE_SHARE, concept_groups, vote_entries
from langfield.raster import one_hot_rows


def _unit(degrees: list[float]) -> Tensor:
    """Unit latents on a great circle at the given angles."""
    rad = torch.tensor([math.radians(d) for d in degrees])
    return torch.stack([torch.cos(rad), torch.sin(rad), torch.zeros_like(rad)], dim=1)


def test_concept_groups_link_chains_of_close_entries() -> None:
    # 0-1 and 1-2 are within 2 degrees, 0-2 is not: one concept by the chain. 3 stands alone.
    groups = concept_groups(_unit([0.0, 1.5, 3.0, 20.0, 20.5]))
    assert groups.tolist() == [0, 0, 0, 3, 3]
    assert concept_groups(_unit([0.0, 1.5]), angle_degrees=1.0).tolist() == [0, 1]
    assert concept_groups(torch.zeros(0, 3)).tolist() == []
    assert concept_groups(_unit([7.0])).tolist() == [0]
    dup = _unit([5.0, 5.0, 5.0])  # exact duplicates
    assert concept_groups(dup).tolist() == [0, 0, 0]


def _renderer(weights: Tensor):
    """A view of P pixels whose rendering weights are ``weights`` [P, N]: the render of the Gaussians'
    one-hot rows of columns [N, K] is ``weights @ rows`` (H = 1, W = P)."""
    return lambda columns, n: (weights @ one_hot_rows(columns, n))[None]


def _one_level(nearest: list[int], gaussians: list[int], weights: list[list[float]], groups: list[int], **kw):
    w = torch.tensor(weights)
    out = vote_entries(
        torch.tensor([nearest])[None],
        torch.tensor([gaussians]),
        [len(groups)],
        [torch.tensor(groups)],
        w.sum(dim=1)[None],
        _renderer(w),
        **kw,
    )
    return out[0, 0].tolist()


def test_a_blend_no_gaussian_carries_reads_the_mode() -> None:
    # Entries 0 (wall), 1 (lamp), 2 (table). Two Gaussians: wall and lamp.
    # Pixel 0: the blend's nearest is the table, which no Gaussian there carries -> the mode, wall.
    # Pixel 1: the blend's nearest is the lamp, which carries 0.3 >= 0.15 of the weight -> kept.
    # Pixel 2: the lamp carries 0.1 < 0.15 -> the mode, wall.
    got = _one_level(
        nearest=[2, 1, 1],
        gaussians=[0, 1],
        weights=[[0.6, 0.3], [0.6, 0.3], [0.8, 0.1]],
        groups=[0, 1, 2],
    )
    assert got == [0, 1, 0]
    assert _one_level([1], [0, 1], [[0.8, 0.1]], [0, 1, 2], share=0.1) == [1]  # at the share exactly


def test_the_share_counts_every_entry_of_the_concept() -> None:
    # Entries 0 and 1 are the same object seen in two views (one concept); entry 2 another object.
    # The blend reads entry 0; Gaussians on entries 0 and 1 carry 0.1 each: 0.2 of 1.0 together.
    got = _one_level(nearest=[0], gaussians=[0, 1, 2], weights=[[0.1, 0.1, 0.8]], groups=[0, 0, 2])
    assert got == [0]
    # As separate concepts neither carries 0.15: the mode, entry 2.
    assert _one_level([0], [0, 1, 2], [[0.1, 0.1, 0.8]], [0, 1, 2]) == [2]


def test_gaussians_without_an_entry_and_ties() -> None:
    # Gaussian 0 has no entry (-1: its latent is zero). It carries most: the pixel reads -1.
    assert _one_level(nearest=[1], gaussians=[-1, 0], weights=[[0.7, 0.2]], groups=[0, 1]) == [-1]
    # A blend read as -1 keeps it when the entry-less Gaussians carry enough.
    assert _one_level(nearest=[-1], gaussians=[-1, 0], weights=[[0.2, 0.7]], groups=[0, 1]) == [-1]
    # Two entries with equal weight: the lower one.
    assert _one_level(nearest=[2], gaussians=[1, 0], weights=[[0.4, 0.4]], groups=[0, 1, 2]) == [0]
    # Empty pixel (no weight): the blend's entry stays (0 >= 0.15 x 0).
    assert _one_level(nearest=[1], gaussians=[0], weights=[[0.0]], groups=[0, 1]) == [1]


def _reference(nearest, own, sizes, groups, weights_per_gaussian, share):
    """Pixel by pixel: the weight of each entry (slot P: none), the concept share, the rule."""
    levels, h, w = nearest.shape
    out = torch.empty_like(nearest)
    for lv in range(levels):
        p = sizes[lv]
        for y in range(h):
            for x in range(w):
                wg = weights_per_gaussian[y * w + x]  # [N]
                slot = torch.where(own[lv] < 0, p, own[lv])
                per_slot = torch.zeros(p + 1).index_add_(0, slot, wg)
                n = int(nearest[lv, y, x])
                concept = [*groups[lv].tolist(), -1]  # slot p: no entry
                ns = p if n < 0 else n
                carried = sum(float(per_slot[s]) for s in range(p + 1) if concept[s] == concept[ns])
                if carried >= share * float(wg.sum()):
                    out[lv, y, x] = n
                else:
                    best = int(torch.argmax(per_slot))  # first of equal maxima
                    out[lv, y, x] = -1 if best == p else best
    return out


@pytest.mark.parametrize("chunk_values", [12, 60, 1 << 20])
def test_vote_matches_a_pixel_by_pixel_reference(chunk_values: int) -> None:
    """Random views of three levels, read in chunks of one channel to all at once."""
    g = torch.Generator().manual_seed(0)
    h, w, n = 3, 4, 9
    sizes = [5, 3, 0]
    entries = [F.normalize(torch.randn(s, 3, generator=g), dim=-1) for s in sizes]
    entries[0][1] = entries[0][0]  # a duplicate: one concept
    groups = [concept_groups(e) for e in entries]

    def indices(shape: tuple[int, ...], size: int) -> Tensor:  # -1 (none) or an entry
        return torch.randint(-1, size, shape, generator=g) if size else torch.full(shape, -1)

    own = torch.stack([indices((n,), s) for s in sizes])
    nearest = torch.stack([indices((h, w), s) for s in sizes])
    weights = torch.rand(h * w, n, generator=g) * (torch.rand(h * w, n, generator=g) < 0.6)
    weights = weights / (weights.sum(dim=1, keepdim=True) + 0.3)  # alpha < 1
    alpha = weights.sum(dim=1).reshape(h, w)

    def render(columns: Tensor, c: int) -> Tensor:
        return (weights @ one_hot_rows(columns, c)).reshape(h, w, -1)

    got = vote_entries(nearest, own, sizes, groups, alpha, render, chunk_values=chunk_values)
    expected = _reference(nearest, own, sizes, groups, weights, VOTE_SHARE)
    assert torch.equal(got, expected)
    assert (got != nearest).any() and (got == nearest).any()  # both branches taken
