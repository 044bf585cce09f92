"""Pictures of queries: relevancy heatmaps over the image, mask overlays, and labelled contact sheets.

All functions return ``uint8 [H, W, 3]`` RGB arrays (convert with ``cv2.cvtColor(.., cv2.COLOR_RGB2BGR)``
before ``cv2.imwrite``). Inputs may be numpy arrays or tensors.

Example:
    >>> rgb = np.zeros((30, 40, 3), np.float32)
    >>> heat = heatmap_overlay(rgb, np.linspace(0, 1, 40)[None].repeat(30, 0))
    >>> sheet = contact_sheet([heat, heat, heat], ["a", "b", "c"], columns=2)
    >>> heat.dtype, sheet.shape[2]
    (dtype('uint8'), 3)
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import matplotlib
import numpy as np
import torch

__all__ = [
    "COLORMAP",
    "HEATMAP_ALPHA",
    "MASK_ALPHA",
    "MASK_COLOR",
    "contact_sheet",
    "heatmap_overlay",
    "mask_overlay",
]

# LangSplat and LERF draw relevancy with turbo (``colormaps.ColormapOptions("turbo")``).
COLORMAP = "turbo"
HEATMAP_ALPHA = 0.6  # weight of the colour map over the image
MASK_ALPHA = 0.45  # weight of the mask colour inside the mask
MASK_COLOR = (255, 64, 32)
# Contact sheet layout, in pixels; Hershey simplex at 0.4 is legible on 160-pixel-wide tiles.
SHEET_GAP = 4
LABEL_HEIGHT = 16
FONT = cv2.FONT_HERSHEY_SIMPLEX
FONT_SCALE = 0.4
BACKGROUND = 255


def _numpy(x: np.ndarray | torch.Tensor) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def _rgb_uint8(rgb: np.ndarray | torch.Tensor) -> np.ndarray:
    """``[H, W, 3]`` float in [0, 1] (or uint8) -> uint8."""
    image = _numpy(rgb)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an RGB image [H, W, 3], got {image.shape}")
    if image.dtype == np.uint8:
        return image
    return (np.clip(image.astype(np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def _colormap_lut(name: str) -> np.ndarray:
    """``[256, 3]`` uint8 lookup table of a matplotlib colormap."""
    colors = matplotlib.colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3]
    return (colors * 255.0 + 0.5).astype(np.uint8)


def heatmap_overlay(
    rgb: np.ndarray | torch.Tensor, relevance: np.ndarray | torch.Tensor, alpha: float = HEATMAP_ALPHA
) -> np.ndarray:
    """The relevance map in the turbo colormap, blended over the image.

    Values are clipped to [0, 1] and not rescaled: pass :func:`relevancy_mask`'s normalised map for
    the most contrast, or a raw relevancy map to compare phrases on one scale.

    Args:
        rgb: ``[H, W, 3]`` image, float in [0, 1] or uint8.
        relevance: ``[H, W]`` relevance in [0, 1].
        alpha: weight of the colour map (:data:`HEATMAP_ALPHA`).

    Returns:
        ``uint8 [H, W, 3]`` RGB.
    """
    image = _rgb_uint8(rgb)
    rel = _numpy(relevance).astype(np.float32)
    if rel.shape != image.shape[:2]:
        raise ValueError(f"heatmap_overlay: relevance {rel.shape} does not match the image {image.shape[:2]}")
    index = (np.nan_to_num(np.clip(rel, 0.0, 1.0)) * 255.0 + 0.5).astype(np.uint8)
    heat = _colormap_lut(COLORMAP)[index]
    return cv2.addWeighted(heat, alpha, image, 1.0 - alpha, 0.0)


def mask_overlay(
    rgb: np.ndarray | torch.Tensor,
    mask: np.ndarray | torch.Tensor,
    color: tuple[int, int, int] = MASK_COLOR,
    alpha: float = MASK_ALPHA,
) -> np.ndarray:
    """The image tinted with ``color`` inside the mask, the mask's outline drawn in ``color``.

    Args:
        rgb: ``[H, W, 3]`` image, float in [0, 1] or uint8.
        mask: ``[H, W]`` bool mask.
        color: RGB colour, 0..255.
        alpha: weight of the colour inside the mask (:data:`MASK_ALPHA`).

    Returns:
        ``uint8 [H, W, 3]`` RGB.
    """
    image = _rgb_uint8(rgb)
    m = _numpy(mask).astype(bool)
    if m.shape != image.shape[:2]:
        raise ValueError(f"mask_overlay: mask {m.shape} does not match the image {image.shape[:2]}")
    out = image.copy()
    tint = np.array(color, np.float32)
    out[m] = (alpha * tint + (1.0 - alpha) * image[m].astype(np.float32) + 0.5).astype(np.uint8)
    contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, tuple(int(c) for c in color), 1)
    return out


def contact_sheet(
    images: Sequence[np.ndarray | torch.Tensor], labels: Sequence[str] | None = None, columns: int = 4
) -> np.ndarray:
    """Tiles in a grid, each with its label written beneath it (``cv2.putText``).

    Tiles may differ in size; each cell is as large as the largest tile, tiles sit at its top left.

    Args:
        images: ``uint8 [H, W, 3]`` RGB tiles.
        labels: one label per tile, or None for no label strip.
        columns: tiles per row.

    Returns:
        ``uint8 [rows * (H + label) + gaps, columns * W + gaps, 3]`` RGB on a white background.
    """
    if not images:
        raise ValueError("contact_sheet: no images")
    if labels is not None and len(labels) != len(images):
        raise ValueError(f"contact_sheet: {len(labels)} labels for {len(images)} images")
    if columns < 1:
        raise ValueError(f"contact_sheet: columns must be positive, got {columns}")
    tiles = [_rgb_uint8(image) for image in images]
    cell_h = max(t.shape[0] for t in tiles) + (LABEL_HEIGHT if labels is not None else 0)
    cell_w = max(t.shape[1] for t in tiles)
    columns = min(columns, len(tiles))
    rows = -(-len(tiles) // columns)
    sheet = np.full(
        (rows * cell_h + (rows + 1) * SHEET_GAP, columns * cell_w + (columns + 1) * SHEET_GAP, 3),
        BACKGROUND,
        np.uint8,
    )
    for i, tile in enumerate(tiles):
        top = SHEET_GAP + (i // columns) * (cell_h + SHEET_GAP)
        left = SHEET_GAP + (i % columns) * (cell_w + SHEET_GAP)
        sheet[top : top + tile.shape[0], left : left + tile.shape[1]] = tile
        if labels is not None:
            baseline = top + tile.shape[0] + LABEL_HEIGHT - 4
            cv2.putText(sheet, str(labels[i]), (left, baseline), FONT, FONT_SCALE, (0, 0, 0), 1, cv2.LINE_AA)
    return sheet
