"""SAM's automatic mask generator on two ONNX sessions, with the three multimask outputs as three levels.

LangSplat (``preprocess.py`` and its fork ``segment-anything-langsplat``, whose
``SamAutomaticMaskGenerator._process_batch`` splits ``masks[:, 0]``, ``[:, 1]``, ``[:, 2]`` into
``data_s``, ``data_m``, ``data_l``) runs SAM's automatic mask generator (AMG) and keeps the three
multimask outputs of every point prompt apart: output 0 -> small (subpart), 1 -> medium (part),
2 -> large (whole). These are SAM's mask tokens 1-3 (token 0 is the single-mask output); SAM's paper
motivates three outputs by "nested masks are often at most three deep: whole, part, and subpart".
Each level is then filtered on its own:

1. a ``points_per_side`` x ``points_per_side`` grid of single-point prompts (SAM ``build_point_grid``),
   decoded ``points_per_batch`` at a time against one image embedding;
2. predicted IoU > ``pred_iou_thresh`` (0.7 in LangSplat; SAM's default is 0.88);
3. stability score >= ``stability_score_thresh`` (0.85; SAM 0.95): the IoU of the mask thresholded at
   logit +1 and at logit -1 (SAM ``calculate_stability_score``, offset 1.0), on the full-size logits;
4. greedy box NMS at ``box_nms_thresh`` (0.7), scored by the predicted IoU (SAM ``_process_crop``);
5. holes and islands smaller than ``min_mask_area`` pixels removed (SAM ``remove_small_regions``; 100
   in LangSplat);
6. LangSplat's mask NMS (``mask_nms`` with iou_thr 0.8, score_thr 0.7, inner_thr 0.5), scored by
   predicted IoU x stability: drop a mask that overlaps a better one by mask IoU > 0.8, a mask whose
   score is <= 0.7, and a mask lying >= 85 % inside a mask of its level that it covers < 50 % of.

Every pairwise step is vectorised: box NMS is a full IoU matrix with the Cluster-NMS iteration (a
matrix-vector product per pass, exactly greedy NMS, so no torchvision), and the mask NMS is one matrix
product of the flattened low-resolution masks, where LangSplat's ``mask_nms`` visits every pair of
full-size masks in a Python loop.

LangSplat also runs one extra layer of image crops (``crop_n_layers=1``); this runtime does not, as
The design asks for the 32 x 32 grid on the whole image only.

The two ONNX models (written by :func:`encoders.export.sam.export_sam`) are SAM's image encoder
(normalised, longest-side resized, zero-padded [1, 3, S, S] image -> [1, C, S/16, S/16] embedding;
S = 1024) and its prompt encoder + mask decoder (embedding, points [B, N, 2] in the resized frame,
labels [B, N] -> IoU predictions [B, 3] and low-resolution mask logits [B, 3, S/4, S/4]). The
preprocessing and the upsampling of the logits happen here, in numpy and OpenCV, as
``SamPredictor.set_image`` and ``Sam.postprocess_masks`` do them in PyTorch.

Cost: the decoder repeats its image-side work for every prompt, so the 1024 prompts dominate. With
ViT-B on two CPU cores the encoder takes about 10 s and the decoder about 100 s per image; the
filters and NMS take a second or two. ``points_per_side=16`` quarters the decoder's share.

Example:
    >>> seg = OnnxSamSegmenter("models/sam")  # doctest: +SKIP
    >>> subpart, part, whole = seg.segment(image)  # doctest: +SKIP
    >>> subpart.dtype, subpart.shape[1:] == image.shape[:2]  # doctest: +SKIP
    (dtype('bool'), True)
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from encoders.manifest import onnx_session, read_manifest
from encoders.protocols import LEVELS, check_image

__all__ = [
    "ENCODER_INPUT",
    "EMBEDDINGS",
    "IOU_PREDICTIONS",
    "LOW_RES_MASKS",
    "POINT_COORDS",
    "POINT_LABELS",
    "STABILITY_OFFSET",
    "OnnxSamSegmenter",
    "box_iou",
    "box_nms",
    "mask_nms",
    "masks_to_boxes",
    "point_grid",
    "preprocess_image",
    "remove_small_regions",
    "resize_logits",
    "resized_shape",
    "stability_score",
]

# Input and output names of the two ONNX graphs (shared with encoders/export/sam.py).
ENCODER_INPUT = "image"
EMBEDDINGS = "image_embeddings"
POINT_COORDS = "point_coords"
POINT_LABELS = "point_labels"
IOU_PREDICTIONS = "iou_predictions"
LOW_RES_MASKS = "low_res_masks"

STABILITY_OFFSET = 1.0  # SAM's stability_score_offset
_FOREGROUND, _PADDING = 1.0, -1.0  # SAM point labels: a positive click, and the "not a point" pad
_RESIZE_BUDGET = 1 << 24  # at most this many full-size logits (floats) are held at once
_RESIZE_CHANNELS = 8  # masks resized together by OpenCV (more is slower: the S x S step outgrows caches)


class OnnxSamSegmenter:
    """SAM automatic masks at three levels (subpart, part, whole) from an exported ONNX SAM.

    Args:
        model_dir: folder with ``manifest.json`` (kind "sam") and the two ONNX files.
        points_per_side: the prompt grid has points_per_side^2 points (32 as LangSplat).
        points_per_batch: prompts decoded per decoder call.
        pred_iou_thresh: keep a mask whose predicted IoU is above this.
        stability_score_thresh: keep a mask whose stability score is at least this.
        box_nms_thresh: box IoU above which the lower-scored box of a level is suppressed.
        min_mask_area: holes and islands smaller than this many pixels are removed (0 = off).
        dedup_iou_thresh: LangSplat mask NMS: mask IoU above which the lower-scored mask is dropped.
        dedup_score_thresh: LangSplat mask NMS: predicted IoU x stability must exceed this.
        dedup_inner_thresh: LangSplat mask NMS: a mask >= 85 % inside a bigger one of its level (which
            it covers < 50 % of) is dropped when the product of the two coverages is below this.

    Example:
        >>> seg = OnnxSamSegmenter("models/sam", points_per_side=16)  # doctest: +SKIP
        >>> subpart, part, whole = seg.segment(image)  # doctest: +SKIP
    """

    def __init__(
        self,
        model_dir: str | Path,
        points_per_side: int = 32,
        points_per_batch: int = 64,
        pred_iou_thresh: float = 0.7,
        stability_score_thresh: float = 0.85,
        box_nms_thresh: float = 0.7,
        min_mask_area: int = 100,
        dedup_iou_thresh: float = 0.8,
        dedup_score_thresh: float = 0.7,
        dedup_inner_thresh: float = 0.5,
    ) -> None:
        if points_per_side < 1 or points_per_batch < 1 or min_mask_area < 0:
            raise ValueError(
                f"OnnxSamSegmenter: need points_per_side >= 1, points_per_batch >= 1, min_mask_area >= 0, "
                f"got {points_per_side}, {points_per_batch}, {min_mask_area}"
            )
        manifest = read_manifest(model_dir, "sam")
        self.model = str(manifest["model"])
        self.input_size = int(manifest["input_size"])
        self.mean = np.asarray(manifest["mean"], dtype=np.float32)
        self.std = np.asarray(manifest["std"], dtype=np.float32)
        self.mask_threshold = float(manifest["mask_threshold"])
        self.points_per_side = int(points_per_side)
        self.points_per_batch = int(points_per_batch)
        self.pred_iou_thresh = float(pred_iou_thresh)
        self.stability_score_thresh = float(stability_score_thresh)
        self.box_nms_thresh = float(box_nms_thresh)
        self.min_mask_area = int(min_mask_area)
        self.dedup_iou_thresh = float(dedup_iou_thresh)
        self.dedup_score_thresh = float(dedup_score_thresh)
        self.dedup_inner_thresh = float(dedup_inner_thresh)
        files = manifest["files"]
        self._encoder = onnx_session(files["image_encoder"])
        self._decoder = onnx_session(files["decoder"])

    def embed(self, image: np.ndarray) -> tuple[np.ndarray, tuple[int, int]]:
        """SAM's image embedding of one image (``SamPredictor.set_image``).

        Args:
            image: [H, W, 3] float32 RGB in [0, 1].

        Returns:
            The embedding [1, C, S/16, S/16] float32 and the resized (h, w) inside the S x S input.
        """
        img = check_image(image, "OnnxSamSegmenter.embed")
        x = preprocess_image(img, self.input_size, self.mean, self.std)
        (embedding,) = self._encoder.run([EMBEDDINGS], {ENCODER_INPUT: x})
        return embedding, resized_shape(img.shape[0], img.shape[1], self.input_size)

    def decode(
        self, embedding: np.ndarray, points: np.ndarray, image_size: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Three masks per single-point prompt (SAM ``predict_torch`` with ``multimask_output=True``).

        Args:
            embedding: [1, C, S/16, S/16] from :meth:`embed`.
            points: [B, 2] float (x, y) pixel coordinates in the original image.
            image_size: (H, W) of the original image.

        Returns:
            IoU predictions [B, 3] and low-resolution mask logits [B, 3, S/4, S/4], float32, outputs in
            the order (subpart, part, whole).
        """
        h, w = image_size
        rh, rw = resized_shape(h, w, self.input_size)
        b = len(points)
        coords = np.zeros((b, 2, 2), dtype=np.float32)  # second point: SAM's padding point at (0, 0)
        coords[:, 0] = np.asarray(points, dtype=np.float64) * (rw / w, rh / h)  # ResizeLongestSide
        labels = np.tile(np.array([_FOREGROUND, _PADDING], dtype=np.float32), (b, 1))
        iou, logits = self._decoder.run(
            [IOU_PREDICTIONS, LOW_RES_MASKS],
            {EMBEDDINGS: embedding, POINT_COORDS: coords, POINT_LABELS: labels},
        )
        return iou, logits

    def segment(self, image: np.ndarray) -> list[np.ndarray]:
        """Masks of one image at the three levels.

        Args:
            image: [H, W, 3] float32 RGB in [0, 1] (uint8 is accepted).

        Returns:
            3 bool arrays [M_l, H, W] for (subpart, part, whole), best-scored (predicted IoU x
            stability) first.
        """
        img = check_image(image, "OnnxSamSegmenter.segment")
        h, w = img.shape[:2]
        embedding, resized = self.embed(img)
        points = point_grid(self.points_per_side) * (w, h)
        candidates = [_Candidates() for _ in LEVELS]
        for start in range(0, len(points), self.points_per_batch):
            iou, logits = self.decode(embedding, points[start : start + self.points_per_batch], (h, w))
            for level, cand in enumerate(candidates):
                self._filter_batch(iou[:, level], logits[:, level], resized, (h, w), cand)
        return [self._select(cand, (h, w)) for cand in candidates]

    def _filter_batch(
        self,
        iou: np.ndarray,
        logits: np.ndarray,
        resized: tuple[int, int],
        image_size: tuple[int, int],
        out: _Candidates,
    ) -> None:
        """Steps 2-3 on one batch of one level: predicted-IoU and stability filters; keeps the survivors.

        Args:
            iou: [B] predicted IoUs; logits: [B, h, w] low-resolution logits of one level.
        """
        keep = np.flatnonzero(iou > self.pred_iou_thresh)
        h, w = image_size
        lh, lw = logits.shape[-2:]
        # The low-resolution window that covers the image (the rest is padding).
        wh = -(-resized[0] * lh // self.input_size)
        ww = -(-resized[1] * lw // self.input_size)
        chunk = max(1, _RESIZE_BUDGET // (h * w))
        for s in range(0, len(keep), chunk):
            idx = keep[s : s + chunk]
            full = resize_logits(logits[idx], self.input_size, resized, image_size)
            stability = stability_score(full, self.mask_threshold, STABILITY_OFFSET)
            masks = full > self.mask_threshold
            ok = (stability >= self.stability_score_thresh) & masks.any(axis=(1, 2))
            if not ok.any():
                continue
            masks = masks[ok]
            out.add(
                packed=np.packbits(masks.reshape(len(masks), -1), axis=1),
                boxes=masks_to_boxes(masks),
                iou=iou[idx[ok]],
                stability=stability[ok],
                small=(logits[idx[ok], :wh, :ww] > self.mask_threshold).reshape(int(ok.sum()), -1),
            )

    def _select(self, cand: _Candidates, image_size: tuple[int, int]) -> np.ndarray:
        """Steps 4-6 on one level's survivors: box NMS, small-region cleaning, LangSplat's mask NMS."""
        h, w = image_size
        if cand.count == 0:
            return np.zeros((0, h, w), dtype=bool)
        boxes, iou, stability, packed, small = cand.arrays()
        keep = box_nms(boxes, iou, self.box_nms_thresh)
        masks = np.unpackbits(packed[keep], axis=1, count=h * w).reshape(len(keep), h, w).astype(bool)
        if self.min_mask_area > 0:
            masks = np.stack([remove_small_regions(m, self.min_mask_area) for m in masks])
        chosen = mask_nms(
            small[keep],
            iou[keep] * stability[keep],
            iou_thresh=self.dedup_iou_thresh,
            score_thresh=self.dedup_score_thresh,
            inner_thresh=self.dedup_inner_thresh,
        )
        return masks[chosen]


class _Candidates:
    """One level's masks that passed the per-batch filters, gathered over the batches."""

    def __init__(self) -> None:
        self._parts: list[tuple[np.ndarray, ...]] = []
        self.count = 0

    def add(
        self,
        packed: np.ndarray,
        boxes: np.ndarray,
        iou: np.ndarray,
        stability: np.ndarray,
        small: np.ndarray,
    ) -> None:
        self._parts.append((boxes, iou, stability, packed, small))
        self.count += len(boxes)

    def arrays(self) -> tuple[np.ndarray, ...]:
        """boxes [N, 4], iou [N], stability [N], bit-packed masks [N, ceil(HW / 8)], low-res masks [N, P]."""
        return tuple(np.concatenate(col) for col in zip(*self._parts, strict=True))


def point_grid(points_per_side: int) -> np.ndarray:
    """SAM's prompt grid (``build_point_grid``): cell centres of an n x n grid over [0, 1]^2.

    Args:
        points_per_side: n.

    Returns:
        [n * n, 2] float64 (x, y), row by row.

    Example:
        >>> point_grid(2)
        array([[0.25, 0.25],
               [0.75, 0.25],
               [0.25, 0.75],
               [0.75, 0.75]])
    """
    side = (np.arange(points_per_side) + 0.5) / points_per_side
    x, y = np.meshgrid(side, side)
    return np.stack([x.ravel(), y.ravel()], axis=1)


def resized_shape(h: int, w: int, long_side: int) -> tuple[int, int]:
    """(h, w) scaled so the longer side is ``long_side``, rounded (SAM ``get_preprocess_shape``)."""
    scale = long_side / max(h, w)
    return int(h * scale + 0.5), int(w * scale + 0.5)


def preprocess_image(image: np.ndarray, input_size: int, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    """The image encoder's input: longest side resized to S, normalised, zero-padded to S x S.

    As ``SamPredictor.set_image`` + ``Sam.preprocess``, except that the resize runs on the float image
    with OpenCV (area averaging when shrinking, bilinear when enlarging) instead of PIL on uint8.

    Args:
        image: [H, W, 3] float32 RGB in [0, 1].
        input_size: S (1024 for SAM).
        mean, std: [3] per-channel normalisation for values in [0, 1] (SAM: ImageNet's).

    Returns:
        [1, 3, S, S] float32; the padding (bottom and right) is 0 after normalisation, as in SAM.
    """
    h, w = image.shape[:2]
    rh, rw = resized_shape(h, w, input_size)
    shrink = rh < h or rw < w
    resized = cv2.resize(image, (rw, rh), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    out = np.zeros((1, 3, input_size, input_size), dtype=np.float32)
    out[0, :, :rh, :rw] = ((resized - mean) / std).transpose(2, 0, 1)
    return out


def resize_logits(
    logits: np.ndarray, input_size: int, resized: tuple[int, int], image_size: tuple[int, int]
) -> np.ndarray:
    """Low-resolution mask logits at the image's size, as ``Sam.postprocess_masks``.

    SAM resamples bilinearly (half-pixel centres) to S x S, crops the resized image's (h, w) and
    resamples bilinearly to (H, W). OpenCV's INTER_LINEAR is the same filter; it runs on a few masks at
    a time as the channels of one image, and the first step upsamples only the rows and columns that
    survive the crop (plus one, so that the border pixels see the same neighbours).

    Args:
        logits: [K, h_lr, w_lr] float32, S a multiple of h_lr and w_lr (S/4 square for SAM).
        input_size: S.
        resized: (h, w) of the resized image inside the S x S input.
        image_size: (H, W) of the original image.

    Returns:
        [K, H, W] float32.
    """
    k, lh, lw = logits.shape
    if input_size % lh or input_size % lw:
        raise ValueError(
            f"resize_logits: input size {input_size} is not a multiple of the logits' {lh} x {lw}"
        )
    fy, fx = input_size // lh, input_size // lw
    (rh, rw), (h, w) = resized, image_size
    ch, cw = min(lh, -(-rh // fy) + 1), min(lw, -(-rw // fx) + 1)
    out = np.empty((k, h, w), dtype=np.float32)
    for s in range(0, k, _RESIZE_CHANNELS):
        x = np.ascontiguousarray(logits[s : s + _RESIZE_CHANNELS, :ch, :cw].transpose(1, 2, 0))
        up = cv2.resize(x, (cw * fx, ch * fy), interpolation=cv2.INTER_LINEAR).reshape(ch * fy, cw * fx, -1)
        full = cv2.resize(up[:rh, :rw], (w, h), interpolation=cv2.INTER_LINEAR).reshape(h, w, -1)
        out[s : s + _RESIZE_CHANNELS] = full.transpose(2, 0, 1)
    return out


def stability_score(logits: np.ndarray, threshold: float, offset: float) -> np.ndarray:
    """SAM's stability score: |logits > t + o| / |logits > t - o| per mask (0 for an empty mask).

    Args:
        logits: [K, H, W].
        threshold: the mask threshold t (0.0 for SAM).
        offset: o (1.0 in SAM's automatic mask generator).

    Returns:
        [K] float32 in [0, 1].
    """
    flat = logits.reshape(len(logits), -1)
    inner = (flat > threshold + offset).sum(axis=1)
    outer = (flat > threshold - offset).sum(axis=1)
    return (inner / np.maximum(outer, 1)).astype(np.float32)


def masks_to_boxes(masks: np.ndarray) -> np.ndarray:
    """Bounding boxes of bool masks as [x0, y0, x1, y1) with exclusive ends (a 1-pixel mask has area 1).

    SAM's ``batched_mask_to_box`` returns inclusive ends; exclusive ends keep thin masks' boxes from
    having zero area in the NMS. An empty mask gets [0, 0, 0, 0].

    Args:
        masks: [K, H, W] bool.

    Returns:
        [K, 4] float32.
    """
    k, h, w = masks.shape
    rows, cols = masks.any(axis=2), masks.any(axis=1)
    y0, y1 = rows.argmax(axis=1), h - rows[:, ::-1].argmax(axis=1)
    x0, x1 = cols.argmax(axis=1), w - cols[:, ::-1].argmax(axis=1)
    boxes = np.stack([x0, y0, x1, y1], axis=1).astype(np.float32)
    boxes[~rows.any(axis=1)] = 0.0
    return boxes


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of every box of ``a`` [N, 4] with every box of ``b`` [M, 4] (xyxy); [N, M], 0 where empty."""
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    lo = np.maximum(a[:, None, :2], b[None, :, :2])
    hi = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(hi - lo, 0, None).prod(axis=2)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def box_nms(boxes: np.ndarray, scores: np.ndarray, iou_thresh: float) -> np.ndarray:
    """Greedy non-maximum suppression, vectorised (as ``torchvision.ops.nms``).

    Greedy NMS keeps box j iff no kept box with a higher score overlaps it by IoU > ``iou_thresh``.
    Cluster-NMS (Zheng et al. 2020, "Enhancing Geometric Factors in Model Learning and Inference for
    Object Detection and Instance Segmentation", eq. 8-9) finds that fixed point by iterating
    ``keep = no (keep & overlap) above`` from "keep all": one matrix-vector product per pass, exact
    after at most N passes and in practice after a few.

    Args:
        boxes: [N, 4] xyxy.
        scores: [N]; ties keep the input order.
        iou_thresh: a box overlapping a kept better one by more than this is suppressed.

    Returns:
        Indices of the kept boxes [K] int64, by decreasing score.
    """
    order = np.argsort(-np.asarray(scores), kind="stable")
    b = np.asarray(boxes, dtype=np.float64)[order]
    overlap = np.triu(box_iou(b, b) > iou_thresh, k=1).astype(np.float32)  # [i, j]: better i hits j
    keep = np.ones(len(order), dtype=bool)
    for _ in range(len(order)):
        new = (keep.astype(np.float32) @ overlap) == 0
        if np.array_equal(new, keep):
            break
        keep = new
    return order[keep]


def mask_nms(
    masks: np.ndarray,
    scores: np.ndarray,
    iou_thresh: float = 0.8,
    score_thresh: float = 0.7,
    inner_thresh: float = 0.5,
) -> np.ndarray:
    """LangSplat's per-level mask de-duplication (``preprocess.py: mask_nms``), vectorised.

    With masks sorted by decreasing score, mask j is dropped if

    - some better mask i has mask IoU(i, j) > ``iou_thresh`` (not greedy: i counts even if itself
      dropped, as in LangSplat);
    - its score <= ``score_thresh``;
    - it lies inside another mask b of the level: |j & b| / |j| >= 0.85 and |j & b| / |b| < 0.5, and
      the product of the two ratios is below ``inner_thresh`` (whichever of j, b scores higher).

    If a rule would drop every mask, it drops none of the 3 best instead (LangSplat's intent).
    Intersections are one matrix product of the flattened masks.

    Args:
        masks: [N, P] bool, flattened (low-resolution masks suffice).
        scores: [N] (LangSplat: predicted IoU x stability).
        iou_thresh, score_thresh, inner_thresh: LangSplat's iou_thr 0.8, score_thr 0.7, inner_thr 0.5.

    Returns:
        Indices of the kept masks, int64, by decreasing score.
    """
    scores = np.asarray(scores, dtype=np.float64)
    order = np.argsort(-scores, kind="stable")
    m = np.asarray(masks)[order].reshape(len(order), -1).astype(np.float32)
    s = scores[order]
    area = m.sum(axis=1).astype(np.float64)
    inter = (m @ m.T).astype(np.float64)
    union = area[:, None] + area[None, :] - inter
    iou = np.where(union > 0, inter / np.maximum(union, 1), 0.0)
    duplicate = np.triu(iou > iou_thresh, k=1).any(axis=0)
    # cover[a, b] = |a & b| / |a|: how much of a lies inside b.
    cover = inter / np.maximum(area, 1)[:, None]
    inside = (cover >= 0.85) & (cover.T < 0.5) & (cover * cover.T < inner_thresh)
    np.fill_diagonal(inside, False)
    rules = [~duplicate, s > score_thresh, ~inside.any(axis=1)]
    keep = np.ones(len(order), dtype=bool)
    for ok in rules:
        if not ok.any():
            ok = np.zeros_like(ok)
            ok[:3] = True
        keep &= ok
    return order[keep]


def remove_small_regions(mask: np.ndarray, min_area: int) -> np.ndarray:
    """Fills holes, then removes islands, smaller than ``min_area`` pixels (SAM ``remove_small_regions``).

    Regions are 8-connected. If every island is small the largest one stays, so a mask never empties.

    Args:
        mask: [H, W] bool.
        min_area: in pixels.

    Returns:
        [H, W] bool.
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats((~mask).astype(np.uint8), connectivity=8)
    fill = stats[:, cv2.CC_STAT_AREA] < min_area
    fill[0] = True  # label 0 = the mask itself
    mask = fill[labels]
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return mask
    sizes = stats[1:, cv2.CC_STAT_AREA]
    stay = np.zeros(n, dtype=bool)
    stay[1:] = sizes >= min_area
    if not stay.any():
        stay[1 + int(sizes.argmax())] = True
    return stay[labels]
