"""SAM on ONNX: exporter against PyTorch, the automatic mask generator's steps against reference loops.

The helpers (NMS, mask NMS, logit upsampling, stability, boxes) need only numpy and torch. The export
tests (marked ``export``) need segment-anything and build a tiny, randomly initialised SAM of the real
architecture; they are skipped where segment-anything is not installed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from conftest import tiny_sam

from encoders.manifest import ManifestError, read_manifest
from encoders.onnx_sam import (
    OnnxSamSegmenter,
    box_iou,
    box_nms,
    mask_nms,
    masks_to_boxes,
    point_grid,
    preprocess_image,
    remove_small_regions,
    resize_logits,
    resized_shape,
    stability_score,
)
from encoders.protocols import Segmenter

TINY_SIZE = 128  # tiny SAM input side: 8 x 8 embedding, 32 x 32 low-resolution masks


# ---------------------------------------------------------------- reference loops, written for the tests


def greedy_nms_loop(boxes: np.ndarray, scores: np.ndarray, thresh: float) -> list[int]:
    """Textbook greedy NMS: visit boxes by score, keep one unless a kept box overlaps it by > thresh."""
    kept: list[int] = []
    for i in sorted(range(len(boxes)), key=lambda k: -scores[k]):
        if all(box_iou(boxes[i : i + 1], boxes[k : k + 1])[0, 0] <= thresh for k in kept):
            kept.append(i)
    return kept


def langsplat_mask_nms_loop(
    masks: np.ndarray, scores: np.ndarray, iou_thr: float, score_thr: float, inner_thr: float
) -> list[int]:
    """LangSplat preprocess.py mask_nms, pair by pair (without its all-dropped fallback)."""
    order = sorted(range(len(masks)), key=lambda k: -scores[k])
    m = [masks[k] for k in order]
    area = [float(x.sum()) for x in m]
    n = len(m)
    iou_max, inner_lower, inner_upper = [0.0] * n, [0.0] * n, [0.0] * n
    for i in range(n):
        for j in range(i + 1, n):
            inter = float((m[i] & m[j]).sum())
            union = float((m[i] | m[j]).sum())
            iou_max[j] = max(iou_max[j], inter / union)
            if inter / area[i] < 0.5 and inter / area[j] >= 0.85:
                inner_upper[j] = max(inner_upper[j], 1 - inter / area[j] * inter / area[i])
            if inter / area[i] >= 0.85 and inter / area[j] < 0.5:
                inner_lower[i] = max(inner_lower[i], 1 - inter / area[j] * inter / area[i])
    return [
        order[k]
        for k in range(n)
        if iou_max[k] <= iou_thr
        and scores[order[k]] > score_thr
        and inner_upper[k] <= 1 - inner_thr
        and inner_lower[k] <= 1 - inner_thr
    ]


def random_boxes(rng: np.random.Generator, n: int) -> np.ndarray:
    """n boxes crowded in a 100 x 100 field, so that many overlap."""
    xy = rng.uniform(0, 80, (n, 2))
    wh = rng.uniform(5, 40, (n, 2))
    return np.concatenate([xy, xy + wh], axis=1)


def random_masks(rng: np.random.Generator, n: int, h: int = 24, w: int = 32) -> np.ndarray:
    """n rectangles, some of them copies shrunk or grown by a pixel and some nested in others."""
    masks = np.zeros((n, h, w), dtype=bool)
    for k in range(n):
        if k >= 2 and rng.random() < 0.4:  # near-copy or nested piece of an earlier mask
            ys, xs = np.nonzero(masks[rng.integers(k)])
            y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
            if rng.random() < 0.5:  # drop the first row or column, if there is another
                y0, x0 = (
                    y0 + int(y1 - y0 > 1) * rng.integers(0, 2),
                    x0 + int(x1 - x0 > 1) * rng.integers(0, 2),
                )
            else:
                y1, x1 = y0 + max(1, (y1 - y0) // 3), x0 + max(1, (x1 - x0) // 3)
        else:
            y0, x0 = rng.integers(0, h - 2), rng.integers(0, w - 2)
            y1, x1 = rng.integers(y0 + 1, h + 1), rng.integers(x0 + 1, w + 1)
        masks[k, y0:y1, x0:x1] = True
    return masks


def torch_postprocess(
    logits: np.ndarray, input_size: int, resized: tuple[int, int], image_size: tuple[int, int]
) -> np.ndarray:
    """Sam.postprocess_masks: bilinear to S x S, crop the resized image, bilinear to (H, W)."""
    x = F.interpolate(
        torch.from_numpy(logits)[:, None], (input_size, input_size), mode="bilinear", align_corners=False
    )
    x = x[..., : resized[0], : resized[1]]
    return F.interpolate(x, image_size, mode="bilinear", align_corners=False)[:, 0].numpy()


# ---------------------------------------------------------------- vectorised helpers


@pytest.mark.parametrize("thresh", [0.3, 0.5, 0.7])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_box_nms_matches_greedy_loop(seed: int, thresh: float) -> None:
    rng = np.random.default_rng(seed)
    boxes, scores = random_boxes(rng, 150), rng.random(150)
    keep = box_nms(boxes, scores, thresh)
    assert keep.tolist() == greedy_nms_loop(boxes, scores, thresh)
    assert 1 < len(keep) < 150


def test_box_nms_long_suppression_chain() -> None:
    # Each box overlaps only its neighbours: greedy keeps every other one, the worst case for the
    # Cluster-NMS iteration (one pass per link of the chain).
    x = np.arange(40, dtype=np.float64) * 2.0
    boxes = np.stack([x, np.zeros(40), x + 10.0, np.full(40, 10.0)], axis=1)
    scores = np.linspace(1.0, 0.5, 40)
    assert box_nms(boxes, scores, 0.7).tolist() == greedy_nms_loop(boxes, scores, 0.7)


def test_box_nms_matches_torchvision() -> None:
    ops = pytest.importorskip("torchvision.ops")
    rng = np.random.default_rng(3)
    boxes, scores = random_boxes(rng, 300), rng.random(300)
    expected = ops.nms(torch.from_numpy(boxes), torch.from_numpy(scores), 0.7).numpy()
    np.testing.assert_array_equal(box_nms(boxes, scores, 0.7), expected)


def test_box_nms_empty_and_degenerate_boxes() -> None:
    assert box_nms(np.zeros((0, 4)), np.zeros(0), 0.7).tolist() == []
    boxes = np.array([[0, 0, 0, 0], [0, 0, 0, 0], [1, 1, 5, 5]], dtype=np.float64)
    assert sorted(box_nms(boxes, np.array([0.9, 0.8, 0.7]), 0.5).tolist()) == [0, 1, 2]


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_mask_nms_matches_langsplat_loop(seed: int) -> None:
    rng = np.random.default_rng(seed)
    masks = random_masks(rng, 40)
    scores = rng.uniform(0.5, 1.0, 40)
    keep = mask_nms(masks.reshape(40, -1), scores, 0.8, 0.7, 0.5)
    assert keep.tolist() == langsplat_mask_nms_loop(masks, scores, 0.8, 0.7, 0.5)
    assert 0 < len(keep) < 40


def test_mask_nms_drops_a_piece_inside_a_bigger_mask_whatever_its_score() -> None:
    big = np.zeros((20, 20), dtype=bool)
    big[2:18, 2:18] = True
    piece = np.zeros_like(big)
    piece[4:8, 4:8] = True
    masks = np.stack([piece, big]).reshape(2, -1)
    assert mask_nms(masks, np.array([0.99, 0.8])).tolist() == [1]
    assert mask_nms(masks, np.array([0.8, 0.99])).tolist() == [1]


def test_mask_nms_keeps_three_best_when_every_score_is_low() -> None:
    masks = np.eye(5, dtype=bool).repeat(4, axis=1)  # 5 disjoint masks
    assert mask_nms(masks, np.array([0.1, 0.5, 0.3, 0.2, 0.4])).tolist() == [1, 4, 2]


@pytest.mark.parametrize(
    ("input_size", "low_res", "image_size"),
    [
        (128, 32, (48, 64)),
        (128, 32, (64, 48)),
        (128, 32, (150, 200)),
        (1024, 256, (378, 504)),
        (1024, 256, (384, 512)),
        (1024, 256, (1, 9)),
        (64, 16, (1000, 750)),
    ],
)
def test_resize_logits_matches_sam_postprocess(
    input_size: int, low_res: int, image_size: tuple[int, int]
) -> None:
    logits = np.random.default_rng(0).normal(0, 4, (2, low_res, low_res)).astype(np.float32)
    resized = resized_shape(*image_size, input_size)
    got = resize_logits(logits, input_size, resized, image_size)
    # OpenCV's float bilinear weights agree with PyTorch's to a few 1e-5 of the logits' range.
    expected = torch_postprocess(logits, input_size, resized, image_size)
    np.testing.assert_allclose(got, expected, atol=5e-5 * np.abs(logits).max())


def test_stability_score_counts_pixels_above_both_cutoffs() -> None:
    logits = np.array([[[-2.0, -0.5, 0.5, 2.0]], [[-3.0, -3.0, -3.0, -3.0]]], dtype=np.float32)
    np.testing.assert_allclose(stability_score(logits, 0.0, 1.0), [1 / 3, 0.0])


def test_masks_to_boxes_exclusive_ends() -> None:
    masks = np.zeros((3, 6, 8), dtype=bool)
    masks[0, 2, 3] = True
    masks[1, 1:4, 2:7] = True
    np.testing.assert_array_equal(masks_to_boxes(masks), [[3, 2, 4, 3], [2, 1, 7, 4], [0, 0, 0, 0]])


def test_remove_small_regions_fills_holes_and_drops_islands() -> None:
    mask = np.zeros((20, 20), dtype=bool)
    mask[2:12, 2:12] = True
    mask[5, 5] = False  # a 1-pixel hole
    mask[16:18, 16:18] = True  # a 4-pixel island
    out = remove_small_regions(mask, 10)
    expected = np.zeros_like(mask)
    expected[2:12, 2:12] = True
    np.testing.assert_array_equal(out, expected)
    specks = np.zeros((20, 20), dtype=bool)
    specks[1, 1] = True
    specks[5:7, 5:7] = True
    np.testing.assert_array_equal(
        remove_small_regions(specks, 10), np.pad(np.ones((2, 2), bool), [(5, 13)] * 2)
    )


def test_point_grid_is_sams_cell_centres() -> None:
    grid = point_grid(4)
    side = np.linspace(1 / 8, 1 - 1 / 8, 4)  # SAM build_point_grid
    np.testing.assert_allclose(grid[:4, 0], side)
    np.testing.assert_allclose(grid[::4, 1], side)
    assert grid.shape == (16, 2)


def test_preprocess_pads_with_zero_and_normalises() -> None:
    mean, std = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])
    image = np.full((48, 64, 3), 0.5, np.float32)
    x = preprocess_image(image, 128, mean, std)
    assert x.shape == (1, 3, 128, 128) and x.dtype == np.float32
    np.testing.assert_allclose(
        x[0, :, :96, :].reshape(3, -1), ((0.5 - mean) / std)[:, None].repeat(96 * 128, 1), rtol=1e-6
    )
    assert not x[0, :, 96:, :].any()


def test_missing_model_folder_is_a_manifest_error(tmp_path: Path) -> None:
    with pytest.raises(ManifestError, match="langfield export sam"):
        OnnxSamSegmenter(tmp_path)


# ---------------------------------------------------------------- export (needs segment-anything)


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> tuple[Any, Path]:
    """(tiny SAM, its exported folder), exported once per module."""
    sam = tiny_sam(TINY_SIZE, 4, 0)
    from encoders.export.sam import export_sam

    folder = export_sam(tmp_path_factory.mktemp("sam"), model=sam)
    return sam, folder


@pytest.fixture
def image() -> np.ndarray:
    rng = np.random.default_rng(0)
    img = np.zeros((48, 64, 3), np.float32)
    img[:, :30] = (0.8, 0.3, 0.2)
    img[10:40, 36:60] = (0.1, 0.4, 0.9)
    return np.clip(img + rng.normal(0, 0.02, img.shape), 0, 1).astype(np.float32)


@pytest.mark.export
def test_manifest_describes_the_export(exported: tuple[Any, Path]) -> None:
    _, folder = exported
    m = read_manifest(folder, "sam")
    assert set(m["files"]) == {"image_encoder", "decoder"}
    assert m["input_size"] == TINY_SIZE and m["mask_threshold"] == 0.0
    np.testing.assert_allclose(m["mean"], [0.485, 0.456, 0.406])
    np.testing.assert_allclose(m["std"], [0.229, 0.224, 0.225])
    assert m["levels"] == ["subpart", "part", "whole"]


@pytest.mark.export
def test_image_encoder_matches_pytorch(exported: tuple[Any, Path], image: np.ndarray) -> None:
    sam, folder = exported
    seg = OnnxSamSegmenter(folder)
    embedding, resized = seg.embed(image)
    assert resized == (96, 128)
    x = preprocess_image(image, TINY_SIZE, seg.mean, seg.std)
    with torch.no_grad():
        expected = sam.image_encoder(torch.from_numpy(x)).numpy()
    assert embedding.shape == expected.shape == (1, 32, 8, 8)
    assert np.abs(embedding - expected).max() <= 1e-4


@pytest.mark.export
def test_preprocess_matches_sam_on_a_flat_image(exported: tuple[Any, Path]) -> None:
    # A flat image resizes exactly with any filter, so SAM's PIL resize and OpenCV's agree.
    transforms = pytest.importorskip("segment_anything.utils.transforms")
    sam, folder = exported
    seg = OnnxSamSegmenter(folder)
    image8 = np.full((48, 64, 3), (200, 90, 30), np.uint8)
    resized = transforms.ResizeLongestSide(TINY_SIZE).apply_image(image8)
    with torch.no_grad():
        expected = sam.preprocess(torch.from_numpy(resized).permute(2, 0, 1)[None].float()).numpy()
    got = preprocess_image(image8.astype(np.float32) / 255.0, TINY_SIZE, seg.mean, seg.std)
    np.testing.assert_allclose(got, expected, atol=1e-5)


@pytest.mark.export
@pytest.mark.parametrize("batch", [1, 7])
def test_decoder_matches_pytorch(exported: tuple[Any, Path], image: np.ndarray, batch: int) -> None:
    transforms = pytest.importorskip("segment_anything.utils.transforms")
    sam, folder = exported
    seg = OnnxSamSegmenter(folder)
    embedding, _ = seg.embed(image)
    points = np.random.default_rng(batch).uniform(0, 1, (batch, 2)) * (64, 48)
    iou, logits = seg.decode(embedding, points, (48, 64))
    # SamPredictor.predict_torch on the same points, one single-point prompt per row.
    coords = transforms.ResizeLongestSide(TINY_SIZE).apply_coords(points, (48, 64))
    with torch.no_grad():
        sparse, dense = sam.prompt_encoder(
            points=(torch.tensor(coords, dtype=torch.float32)[:, None], torch.ones(batch, 1)),
            boxes=None,
            masks=None,
        )
        low_res, iou_pred = sam.mask_decoder(
            image_embeddings=torch.from_numpy(embedding),
            image_pe=sam.prompt_encoder.get_dense_pe(),
            sparse_prompt_embeddings=sparse,
            dense_prompt_embeddings=dense,
            multimask_output=True,
        )
    assert iou.shape == (batch, 3) and logits.shape == (batch, 3, 32, 32)
    assert np.abs(iou - iou_pred.numpy()).max() <= 1e-4
    assert np.abs(logits - low_res.numpy()).max() <= 1e-4


@pytest.mark.export
def test_upsampled_masks_match_sam_postprocess(exported: tuple[Any, Path], image: np.ndarray) -> None:
    sam, folder = exported
    seg = OnnxSamSegmenter(folder)
    embedding, resized = seg.embed(image)
    _, logits = seg.decode(embedding, np.array([[20.0, 20.0], [50.0, 30.0]]), (48, 64))
    with torch.no_grad():
        expected = sam.postprocess_masks(torch.from_numpy(logits), resized, (48, 64)).numpy()
    got = resize_logits(logits.reshape(-1, 32, 32), TINY_SIZE, resized, (48, 64)).reshape(expected.shape)
    assert np.abs(got - expected).max() <= 5e-5 * np.abs(logits).max()


@pytest.mark.export
def test_automatic_masks_have_the_protocol_shapes(exported: tuple[Any, Path], image: np.ndarray) -> None:
    _, folder = exported
    # A random SAM predicts low IoUs: open the score filters so that every step sees masks.
    seg = OnnxSamSegmenter(
        folder,
        points_per_side=6,
        points_per_batch=16,
        pred_iou_thresh=-np.inf,
        stability_score_thresh=0.0,
        min_mask_area=8,
        dedup_score_thresh=-np.inf,
    )
    assert isinstance(seg, Segmenter)
    levels = seg.segment(image)
    assert len(levels) == 3
    assert all(m.dtype == bool and m.ndim == 3 and m.shape[1:] == (48, 64) for m in levels)
    assert sum(len(m) for m in levels) > 0
    assert all(m.any(axis=(1, 2)).all() for m in levels)  # no empty mask
    for again, first in zip(seg.segment(image), levels, strict=True):  # deterministic
        np.testing.assert_array_equal(again, first)
    default = OnnxSamSegmenter(folder, points_per_side=4).segment(image)
    assert [m.shape[1:] for m in default] == [(48, 64)] * 3


@pytest.mark.export
def test_export_refuses_no_weights(tmp_path: Path) -> None:
    pytest.importorskip("segment_anything")
    from encoders.export.sam import export_sam

    with pytest.raises(ValueError, match="checkpoint"):
        export_sam(tmp_path)
