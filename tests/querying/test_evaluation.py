"""Tests of the query metrics and pictures (querying/evaluation.py, querying/visualize.py)."""

from __future__ import annotations

import matplotlib
import numpy as np
import pytest
import torch

from querying.evaluation import EMPTY_IOU, mask_iou, query_record, summarize_queries
from querying.relevancy import relevancy
from querying.visualize import LABEL_HEIGHT, SHEET_GAP, contact_sheet, heatmap_overlay, mask_overlay

WIDTH, HEIGHT = 160, 120


def _rect(top: int, left: int, height: int, width: int, shape=(HEIGHT, WIDTH)) -> torch.Tensor:
    mask = torch.zeros(shape, dtype=torch.bool)
    mask[top : top + height, left : left + width] = True
    return mask


# ---------------------------------------------------------------- IoU


def test_mask_iou_by_hand() -> None:
    pred = _rect(0, 0, 2, 3, shape=(4, 4))  # 6 pixels
    gt = _rect(1, 1, 2, 3, shape=(4, 4))  # 6 pixels, 2 shared with pred
    assert mask_iou(pred, gt) == pytest.approx(2 / 10)
    assert mask_iou(gt, pred) == pytest.approx(2 / 10)
    assert mask_iou(pred, pred) == 1.0


def test_mask_iou_of_empty_masks() -> None:
    empty = torch.zeros(4, 4, dtype=torch.bool)
    assert mask_iou(empty, empty) == EMPTY_IOU == 1.0
    assert mask_iou(empty, _rect(0, 0, 1, 1, shape=(4, 4))) == 0.0
    assert mask_iou(_rect(0, 0, 1, 1, shape=(4, 4)), empty) == 0.0


def test_mask_iou_accepts_0_1_masks_and_rejects_mismatched_shapes() -> None:
    assert mask_iou(torch.tensor([[1, 0], [1, 1]]), torch.tensor([[1.0, 1.0], [0.0, 1.0]])) == pytest.approx(
        2 / 4
    )
    with pytest.raises(ValueError, match="same shape"):
        mask_iou(torch.zeros(3, 4, dtype=torch.bool), torch.zeros(4, 3, dtype=torch.bool))


# ---------------------------------------------------------------- mIoU and mAcc


def test_summarize_queries_by_hand() -> None:
    records = [
        {"iou": 1.0, "hit": True},
        {"iou": 0.5, "hit": False},
        {"iou": 0.0, "hit": False},
        {"iou": 0.7, "hit": True},
    ]
    summary = summarize_queries(records)
    assert summary["mIoU"] == pytest.approx(2.2 / 4)
    assert summary["mAcc"] == pytest.approx(0.5)


def test_summarize_queries_weighs_every_pair_the_same() -> None:
    views = [
        {"name": "a", "queries": {"mug": {"iou": 1.0, "hit": True}}},
        {"name": "b", "queries": {"mug": {"iou": 0.0, "hit": False}, "sofa": {"iou": 0.5, "hit": True}}},
    ]
    summary = summarize_queries(q for v in views for q in v["queries"].values())
    assert summary == {"mIoU": pytest.approx(0.5), "mAcc": pytest.approx(2 / 3)}


def test_summarize_queries_without_labels_gives_none() -> None:
    assert summarize_queries([]) == {"mIoU": None, "mAcc": None}
    assert summarize_queries(iter(())) == {"mIoU": None, "mAcc": None}


def test_query_record_of_a_perfect_map() -> None:
    gt = _rect(40, 50, 30, 40)
    maps = torch.stack([gt.float() * 0.4, gt.float(), torch.full((HEIGHT, WIDTH), 0.5)])
    assert query_record(maps, gt) == {"iou": 1.0, "hit": True}


def test_query_record_of_a_map_pointing_elsewhere() -> None:
    gt = _rect(40, 50, 30, 40)
    record = query_record(_rect(80, 100, 30, 40).float()[None], gt)
    assert record == {"iou": 0.0, "hit": False}


def test_latents_equal_to_the_ground_truth_give_miou_1() -> None:
    """Several views and phrases whose decoded features equal the ground truth score mIoU = mAcc = 1."""
    e = torch.eye(12)
    phrases, canonical = e[:3], e[8:12]
    views = []
    for offset in (0, 12, 25):
        objects = [_rect(10 + offset, 10, 30, 40), _rect(60, 70 + offset, 40, 35), _rect(15, 110, 20, 25)]
        feats = e[7].expand(3, HEIGHT, WIDTH, 12).clone()  # background concept at every level
        for k, gt in enumerate(objects):
            feats[2][gt] = e[k]  # whole level
            feats[1][gt] = (e[k] + e[4 + k]) / 2**0.5  # part level, cos 0.7 with the phrase
        maps = relevancy(feats, phrases, canonical)  # [Q, L, H, W]
        views.append({k: query_record(maps[k], gt) for k, gt in enumerate(objects)})
    summary = summarize_queries(r for view in views for r in view.values())
    assert summary == {"mIoU": 1.0, "mAcc": 1.0}


# ---------------------------------------------------------------- pictures


def _turbo(value: float) -> np.ndarray:
    return np.round(np.asarray(matplotlib.colormaps["turbo"](value)[:3]) * 255.0)


def test_heatmap_overlay_blends_turbo_over_the_image() -> None:
    rgb = torch.zeros(HEIGHT, WIDTH, 3)
    relevance = torch.zeros(HEIGHT, WIDTH)
    relevance[:, WIDTH // 2 :] = 1.0
    out = heatmap_overlay(rgb, relevance, alpha=1.0)
    assert out.dtype == np.uint8 and out.shape == (HEIGHT, WIDTH, 3)
    np.testing.assert_allclose(out[0, 0], _turbo(0.0), atol=1)
    np.testing.assert_allclose(out[0, -1], _turbo(1.0), atol=1)
    half = heatmap_overlay(np.ones((HEIGHT, WIDTH, 3), np.float32), relevance.numpy(), alpha=0.5)
    np.testing.assert_allclose(half[0, -1], (_turbo(1.0) + 255.0) / 2, atol=1)


def test_heatmap_overlay_clips_and_survives_nan() -> None:
    relevance = torch.tensor([[-1.0, 2.0, float("nan")]])
    out = heatmap_overlay(torch.zeros(1, 3, 3), relevance, alpha=1.0)
    np.testing.assert_allclose(out[0, 0], _turbo(0.0), atol=1)
    np.testing.assert_allclose(out[0, 1], _turbo(1.0), atol=1)


def test_mask_overlay_changes_only_the_mask() -> None:
    rgb = np.full((HEIGHT, WIDTH, 3), 0.5, np.float32)
    mask = _rect(40, 50, 30, 40)
    out = mask_overlay(rgb, mask, color=(255, 0, 0))
    outside = ~mask.numpy()
    assert (out[outside] == 128).all()
    assert (out[45, 60] != 128).any()
    assert out[45, 60, 0] > out[45, 60, 1]  # tinted red inside
    np.testing.assert_array_equal(out[40, 70], [255, 0, 0])  # outline on the mask's edge


def test_contact_sheet_layout_and_labels() -> None:
    tiles = [np.full((HEIGHT, WIDTH, 3), v, np.uint8) for v in (0, 100, 200)]
    sheet = contact_sheet(tiles, ["mug", "sofa", "table"], columns=2)
    rows_h = 2 * (HEIGHT + LABEL_HEIGHT) + 3 * SHEET_GAP
    assert sheet.shape == (rows_h, 2 * WIDTH + 3 * SHEET_GAP, 3) and sheet.dtype == np.uint8
    top, left = SHEET_GAP + HEIGHT + LABEL_HEIGHT + SHEET_GAP, SHEET_GAP
    assert (sheet[top : top + HEIGHT, left : left + WIDTH] == 200).all()  # third tile, second row
    label_strip = sheet[SHEET_GAP + HEIGHT : SHEET_GAP + HEIGHT + LABEL_HEIGHT, SHEET_GAP : SHEET_GAP + WIDTH]
    assert (label_strip < 128).any()  # text was drawn
    assert (sheet[top : top + HEIGHT, SHEET_GAP * 2 + WIDTH :] == 255).all()  # empty cell stays white


def test_contact_sheet_without_labels_and_mixed_sizes() -> None:
    tiles = [np.zeros((10, 20, 3), np.uint8), np.zeros((30, 15, 3), np.uint8)]
    sheet = contact_sheet(tiles, None, columns=3)
    assert sheet.shape == (30 + 2 * SHEET_GAP, 2 * 20 + 3 * SHEET_GAP, 3)
    with pytest.raises(ValueError, match="labels"):
        contact_sheet(tiles, ["one"], columns=2)
