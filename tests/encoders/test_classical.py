"""GraphSegmenter: Felzenszwalb-Huttenlocher segmentation at three scales (OpenCV contrib)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

import encoders.classical as classical
from encoders.protocols import Segmenter

FERN = Path(__file__).resolve().parents[3] / "shared" / "data" / "llff_fern" / "images_8" / "image000.png"
needs_contrib = pytest.mark.skipif(
    not hasattr(cv2, "ximgproc"), reason="needs opencv-contrib-python-headless (cv2.ximgproc)"
)


@pytest.fixture(scope="module")
def fern() -> np.ndarray:
    if not FERN.is_file():
        pytest.skip(f"LLFF fern image not found at {FERN} (../shared/data beside the repo)")
    return cv2.cvtColor(cv2.imread(str(FERN)), cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


@needs_contrib
def test_fern_levels_are_partitions_from_fine_to_coarse(fern: np.ndarray) -> None:
    seg = classical.GraphSegmenter()
    assert isinstance(seg, Segmenter)
    levels = seg.segment(fern)
    h, w = fern.shape[:2]
    assert len(levels) == 3
    for masks in levels:
        assert masks.dtype == bool and masks.ndim == 3 and masks.shape[1:] == (h, w)
        np.testing.assert_array_equal(masks.sum(axis=0), 1)  # disjoint and covering
        areas = masks.sum(axis=(1, 2))
        assert (np.diff(areas) <= 0).all()  # largest first
    counts = [len(m) for m in levels]
    assert counts[0] > counts[1] > counts[2] > 1, counts
    min_sizes = [frac * h * w for _, _, frac in classical.DEFAULT_SCALES]
    for masks, min_size in zip(levels, min_sizes, strict=True):
        assert masks.sum(axis=(1, 2)).min() >= 0.5 * min_size


@needs_contrib
def test_two_flat_halves_give_the_two_halves() -> None:
    image = np.zeros((48, 64, 3), np.float32)
    image[:, 32:] = (0.9, 0.2, 0.1)
    unsmoothed = classical.GraphSegmenter(scales=((0.0, 200.0, 0.002),) * 3)
    for masks in unsmoothed.segment(image):
        assert masks.shape == (2, 48, 64)
        assert {masks[0, :, :32].all(), masks[1, :, :32].all()} == {True, False}
    # Smoothing blurs the step into a few one-column regions; the halves stay the two largest masks.
    for masks in classical.GraphSegmenter().segment(image):
        assert masks[:2, :, :29].all(axis=(1, 2)).any() and masks[:2, :, 35:].all(axis=(1, 2)).any()


@needs_contrib
def test_uint8_input_matches_float_input() -> None:
    rng = np.random.default_rng(0)
    image8 = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    seg = classical.GraphSegmenter()
    for a, b in zip(seg.segment(image8), seg.segment(image8.astype(np.float32) / 255.0), strict=True):
        np.testing.assert_array_equal(a, b)


@needs_contrib
def test_bad_scales_and_images_are_refused() -> None:
    with pytest.raises(ValueError, match="3 entries"):
        classical.GraphSegmenter(scales=((0.5, 100.0, 0.01),))
    with pytest.raises(ValueError, match="k > 0"):
        classical.GraphSegmenter(scales=((0.5, 0.0, 0.01),) * 3)
    with pytest.raises(ValueError, match="shape"):
        classical.GraphSegmenter().segment(np.zeros((8, 8), np.float32))


def test_missing_contrib_names_the_package(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delattr(classical.cv2, "ximgproc", raising=False)
    with pytest.raises(ImportError, match="opencv-contrib-python-headless"):
        classical.GraphSegmenter()
