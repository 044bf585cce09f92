"""Deterministic STUBS of the encoder protocols, for tests and the synthetic demo only.

None of these is a model: they need no weights, run in milliseconds and give the same output for the
same input on every machine, so tests can check the plumbing (eq. 1 crops, caches, LAD, querying)
without SAM, CLIP or a depth network. Their outputs are shaped and normalised like the real ones and
are loosely tied to the image so that a pipeline built on them still behaves sensibly:

- :class:`StubSegmenter`: colour quantisation plus connected components at three granularities;
  finer levels are exactly nested inside coarser ones.
- :class:`StubImageTextEncoder`: a crop's colour histogram through a fixed random projection (similar
  colours -> similar vectors); a phrase's vector is random, seeded by a stable hash of its text, and
  has no relation to images (use a scene's ``text_embeddings.npz`` for meaningful text).
- :class:`StubDepthEstimator`: a disparity that grows towards the bottom of the image and with
  brightness, the way a floor comes nearer towards the camera.

Example:
    >>> import numpy as np
    >>> image = np.zeros((24, 32, 3), np.float32); image[:, 16:] = 1.0
    >>> [m.shape for m in StubSegmenter(blur_sigma=0).segment(image)]
    [(2, 24, 32), (2, 24, 32), (2, 24, 32)]
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence

import cv2
import numpy as np

from encoders.protocols import DEPTH_KINDS, LEVELS, DepthKind, check_crops, check_image, check_phrases

__all__ = ["StubDepthEstimator", "StubImageTextEncoder", "StubSegmenter"]

# Independent random streams, so that the image projection and the text vectors never share draws.
_STREAM_IMAGE, _STREAM_TEXT = 0x1A6E, 0x7E47
_BLACK = 0.5 / 255.0  # a pixel at or below this in every channel counts as eq. 1's black-out
_HIST_BIAS = 0.25  # constant input beside the histogram, so an all-black crop still has a direction


class StubSegmenter:
    """STUB segmenter: colour quantisation + connected components at three granularities.

    The image is blurred slightly, each channel is quantised into ``bins[l]`` equal steps, and every
    4-connected region of one quantised colour with at least ``min_area`` pixels is a mask of level l.
    Because each entry of ``bins`` is a multiple of the next, every finer cell lies inside one coarser
    cell, so every subpart mask lies inside one part mask and every part mask inside one whole mask.

    Args:
        bins: quantisation steps per channel for (subpart, part, whole); each a multiple of the next.
        min_area: smallest mask kept, in pixels (a mask generator drops specks too).
        max_masks: at most this many masks per level, the largest ones (bounds memory on noisy images).
        blur_sigma: Gaussian blur before quantising, in pixels (0 = none).

    Example:
        >>> import numpy as np
        >>> masks = StubSegmenter().segment(np.full((24, 32, 3), 0.3, np.float32))
        >>> [m.shape[0] for m in masks]
        [1, 1, 1]
    """

    def __init__(
        self,
        bins: tuple[int, int, int] = (8, 4, 2),
        min_area: int = 4,
        max_masks: int = 64,
        blur_sigma: float = 0.8,
    ) -> None:
        if len(bins) != len(LEVELS) or any(int(b) < 1 for b in bins):
            raise ValueError(f"StubSegmenter: bins must be 3 positive integers, got {bins}")
        if any(bins[i] % bins[i + 1] for i in range(len(bins) - 1)):
            raise ValueError(f"StubSegmenter: each of bins must be a multiple of the next, got {bins}")
        if min_area < 1 or max_masks < 1 or blur_sigma < 0:
            raise ValueError(
                f"StubSegmenter: need min_area >= 1, max_masks >= 1, blur_sigma >= 0, "
                f"got {min_area}, {max_masks}, {blur_sigma}"
            )
        self.bins = tuple(int(b) for b in bins)
        self.min_area = int(min_area)
        self.max_masks = int(max_masks)
        self.blur_sigma = float(blur_sigma)

    def segment(self, image: np.ndarray) -> list[np.ndarray]:
        """Masks of one image at the three levels.

        Args:
            image: [H, W, 3] float32 RGB in [0, 1] (uint8 is accepted).

        Returns:
            3 bool arrays [M_l, H, W] for (subpart, part, whole), largest mask first.
        """
        img = check_image(image, "StubSegmenter.segment")
        if self.blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.blur_sigma, borderType=cv2.BORDER_REFLECT)
        return [self._level_masks(img, q) for q in self.bins]

    def _level_masks(self, img: np.ndarray, q: int) -> np.ndarray:
        """[M, H, W] bool: the connected regions of one quantised colour, largest first."""
        h, w, _ = img.shape
        # Scaling by q and flooring is exact for power-of-two q, so nesting across levels is exact.
        cells = np.minimum(np.floor(img * q), q - 1).astype(np.int32)
        codes = (cells[..., 0] * q + cells[..., 1]) * q + cells[..., 2]
        masks: list[np.ndarray] = []
        for code in np.unique(codes):
            n, labels = cv2.connectedComponents((codes == code).astype(np.uint8), connectivity=4)
            for k in range(1, n):
                region = labels == k
                if region.sum() >= self.min_area:
                    masks.append(region)
        areas = np.array([m.sum() for m in masks], dtype=np.int64)
        order = np.argsort(-areas, kind="stable")[: self.max_masks]
        return np.stack([masks[i] for i in order]) if masks else np.zeros((0, h, w), dtype=bool)


class StubImageTextEncoder:
    """STUB image-text encoder: colour histograms and hashed phrases, projected into R^dim.

    An image's vector is its normalised ``bins^3`` colour histogram over non-black pixels (eq. 1 blacks
    out everything outside the mask, so black is "not the object"), plus a small constant, times a
    fixed Gaussian matrix seeded by ``seed``; a random projection roughly keeps inner products, so
    crops of the same colours get nearly the same vector and crops of different colours nearly
    orthogonal ones. A phrase's vector is a Gaussian draw seeded by ``seed`` and zlib.crc32 of its UTF-8
    text (stable across runs, unlike Python's salted ``hash``).

    Args:
        dim: embedding dimension (512 like OpenCLIP ViT-B-16).
        seed: seeds the projection and the phrase vectors.
        image_size: side of the square crops :meth:`encode_images` takes (224 like CLIP; tests use
            less to stay fast).
        bins: histogram steps per colour channel.

    Example:
        >>> enc = StubImageTextEncoder(dim=8, image_size=4)
        >>> enc.encode_text(["sofa"]).shape, enc.encode_images(np.ones((2, 4, 4, 3), np.float32)).shape
        ((1, 8), (2, 8))
    """

    def __init__(self, dim: int = 512, seed: int = 0, image_size: int = 224, bins: int = 4) -> None:
        if dim < 1 or image_size < 1 or bins < 1:
            raise ValueError(
                f"StubImageTextEncoder: dim, image_size and bins must be >= 1, "
                f"got {dim}, {image_size}, {bins}"
            )
        self.dim = int(dim)
        self.seed = int(seed)
        self.image_size = int(image_size)
        self.bins = int(bins)
        rng = np.random.default_rng([self.seed, _STREAM_IMAGE])
        self._projection = rng.standard_normal((self.bins**3 + 1, self.dim)).astype(np.float32)

    def encode_images(self, images: np.ndarray) -> np.ndarray:
        """Embed square crops.

        Args:
            images: [B, S, S, 3] float32 RGB in [0, 1], S = image_size.

        Returns:
            [B, dim] float32 unit rows.
        """
        arr = check_crops(images, self.image_size, "StubImageTextEncoder.encode_images")
        b = arr.shape[0]
        pixels = arr.reshape(b, -1, 3).astype(np.float32)
        cells = np.clip(np.floor(pixels * self.bins), 0, self.bins - 1).astype(np.int64)
        codes = (cells[..., 0] * self.bins + cells[..., 1]) * self.bins + cells[..., 2]
        weight = (pixels.max(axis=2) > _BLACK).astype(np.float32)
        n_codes = self.bins**3
        flat = (np.arange(b)[:, None] * n_codes + codes).ravel()
        hist = np.bincount(flat, weights=weight.ravel(), minlength=b * n_codes).reshape(b, n_codes)
        hist /= np.maximum(np.linalg.norm(hist, axis=1, keepdims=True), 1e-12)
        x = np.concatenate([hist, np.full((b, 1), _HIST_BIAS)], axis=1).astype(np.float32)
        return _unit_rows(x @ self._projection)

    def encode_text(self, phrases: Sequence[str]) -> np.ndarray:
        """Embed phrases as seeded random unit vectors.

        Args:
            phrases: P phrases.

        Returns:
            [P, dim] float32 unit rows; the same phrase always gives the same row.
        """
        phrases = check_phrases(phrases, "StubImageTextEncoder.encode_text")
        rows = np.zeros((len(phrases), self.dim), dtype=np.float32)
        for i, phrase in enumerate(phrases):
            rng = np.random.default_rng([self.seed, _STREAM_TEXT, zlib.crc32(phrase.encode("utf-8"))])
            rows[i] = rng.standard_normal(self.dim)
        return _unit_rows(rows)


class StubDepthEstimator:
    """STUB depth prior: nearer towards the bottom of the image and where it is brighter.

    disparity = 0.2 + 0.6 v + 0.2 luminance, with v in [0, 1] from the top row to the bottom row; it is
    positive, so ``kind="depth"`` returns its reciprocal. Like a monocular network's output it is only
    relative (its scale and shift mean nothing).

    Args:
        kind: "disparity" (larger is nearer, like DPT / MiDaS) or "depth" (larger is farther).

    Example:
        >>> StubDepthEstimator().estimate(np.zeros((24, 32, 3), np.float32)).shape
        (24, 32)
    """

    def __init__(self, kind: DepthKind = "disparity") -> None:
        if kind not in DEPTH_KINDS:
            raise ValueError(f"StubDepthEstimator: kind must be one of {DEPTH_KINDS}, got {kind!r}")
        self.kind: DepthKind = kind

    def estimate(self, image: np.ndarray) -> np.ndarray:
        """Relative disparity (or depth) of one image.

        Args:
            image: [H, W, 3] float32 RGB in [0, 1].

        Returns:
            [H, W] float32, positive and finite.
        """
        img = check_image(image, "StubDepthEstimator.estimate")
        h = img.shape[0]
        v = np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None] if h > 1 else np.zeros((1, 1), np.float32)
        luminance = img @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
        disparity = 0.2 + 0.6 * v + 0.2 * luminance
        out = disparity if self.kind == "disparity" else 1.0 / disparity
        return out.astype(np.float32)


def _unit_rows(x: np.ndarray) -> np.ndarray:
    """Rows of x scaled to unit L2 norm, float32 (inputs here never have a zero row)."""
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)
