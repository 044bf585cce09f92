"""The small protocols every 2D foundation model of langfield sits behind.

SOVGaussian supervises its field with three 2D models:

- a :class:`Segmenter` gives masks at three levels (subpart, part, whole), as SAM's three multimask
  outputs per point prompt do in LangSplat;
- an :class:`ImageTextEncoder` maps mask crops (eq. 1) and phrases to unit vectors of one CLIP space;
  its text half alone is a :class:`TextEncoder`, which is all that querying needs;
- a :class:`DepthEstimator` gives a relative depth or disparity prior for LAD (eq. 6, 9).

The protocols are structural (``typing.Protocol``, runtime-checkable), so an ONNX model, a stub or a
user's own wrapper works without inheriting from anything. Images are ``[H, W, 3]`` float32 RGB in
[0, 1]; :func:`check_image` is the one boundary check that turns anything else into a clear error.

Example:
    >>> from encoders.stubs import StubSegmenter
    >>> isinstance(StubSegmenter(), Segmenter)
    True
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, Protocol, runtime_checkable

import numpy as np

__all__ = [
    "CANONICAL_PHRASES",
    "DEPTH_KINDS",
    "LEVELS",
    "DepthEstimator",
    "ImageTextEncoder",
    "Segmenter",
    "TextEncoder",
    "check_crops",
    "check_image",
    "check_phrases",
]

LEVELS = ("subpart", "part", "whole")
# LERF / LangSplat canonical ("negative") phrases that every query competes against.
CANONICAL_PHRASES = ("object", "things", "stuff", "texture")
DEPTH_KINDS = ("depth", "disparity")
DepthKind = Literal["depth", "disparity"]


@runtime_checkable
class Segmenter(Protocol):
    """Image -> masks at the three levels of LEVELS (LangSplat's SAM s / m / l outputs)."""

    def segment(self, image: np.ndarray) -> list[np.ndarray]:
        """Masks of one image at every level.

        Args:
            image: [H, W, 3] float32 RGB in [0, 1].

        Returns:
            A list of 3 bool arrays, one per level of LEVELS (subpart, part, whole), each [M_l, H, W];
            M_l may be 0. Masks of one level may overlap.
        """
        ...


@runtime_checkable
class TextEncoder(Protocol):
    """Phrases -> unit vectors in a CLIP space (the text half of :class:`ImageTextEncoder`)."""

    dim: int

    def encode_text(self, phrases: Sequence[str]) -> np.ndarray:
        """Embed phrases.

        Args:
            phrases: P phrases (a list, not a bare string).

        Returns:
            [P, dim] float32, unit rows.
        """
        ...


@runtime_checkable
class ImageTextEncoder(TextEncoder, Protocol):
    """Square image crops and phrases -> unit vectors in one CLIP space (OpenCLIP ViT-B-16: dim 512)."""

    image_size: int  # side S of the square crops encode_images takes (224 for CLIP)

    def encode_images(self, images: np.ndarray) -> np.ndarray:
        """Embed square crops.

        Args:
            images: [B, S, S, 3] float32 RGB in [0, 1], S = image_size.

        Returns:
            [B, dim] float32, unit rows.
        """
        ...


@runtime_checkable
class DepthEstimator(Protocol):
    """Image -> relative depth prior (scale and shift unknown), as DPT / MiDaS / Depth Anything give."""

    kind: DepthKind  # "depth": larger is farther; "disparity": larger is nearer

    def estimate(self, image: np.ndarray) -> np.ndarray:
        """Relative depth or disparity of one image.

        Args:
            image: [H, W, 3] float32 RGB in [0, 1].

        Returns:
            [H, W] float32, finite.
        """
        ...


def check_crops(images: np.ndarray, size: int, where: str) -> np.ndarray:
    """The crops an image encoder embeds, as an array, or a ValueError naming ``where``: [B, S, S, 3]
    floats, S = ``size`` (B may be 0)."""
    arr = np.asarray(images)
    if arr.ndim != 4 or arr.shape[1:] != (size, size, 3):
        raise ValueError(f"{where}: images must have shape [B, {size}, {size}, 3], got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.floating):
        raise ValueError(f"{where}: images must be float, got {arr.dtype}")
    return arr


def check_image(image: np.ndarray, where: str) -> np.ndarray:
    """The image as [H, W, 3] float32 in [0, 1], or a ValueError saying what is wrong.

    uint8 images are scaled by 1/255 (unambiguous); float images must already lie in [0, 1].

    Args:
        image: [H, W, 3] RGB, float in [0, 1] or uint8.
        where: who is checking, for the message (e.g. "StubSegmenter.segment").

    Returns:
        [H, W, 3] float32 (the input itself when it already is one).
    """
    arr = np.asarray(image)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise ValueError(f"{where}: image must have shape [H, W, 3] with H, W > 0, got {arr.shape}")
    if arr.dtype == np.uint8:
        return arr.astype(np.float32) / 255.0
    if not np.issubdtype(arr.dtype, np.floating):
        raise ValueError(f"{where}: image must be float in [0, 1] or uint8, got dtype {arr.dtype}")
    arr = arr.astype(np.float32, copy=False)
    if not np.isfinite(arr).all():
        raise ValueError(f"{where}: image has NaN or inf values")
    lo, hi = float(arr.min()), float(arr.max())
    if lo < 0.0 or hi > 1.0:
        raise ValueError(f"{where}: float image must lie in [0, 1], got values in [{lo:.4g}, {hi:.4g}]")
    return arr


def check_phrases(phrases: Sequence[str], where: str, allow_empty: bool = False) -> list[str]:
    """The phrases as a list of str; a bare string is refused rather than split into characters, and an
    empty or blank phrase is refused (CLIP would embed its start and end tokens alone, a vector that
    matches nothing in particular, and the query would report "no match" instead of the mistake).
    ``allow_empty`` is for the tokenizer, which gives an empty phrase its start and end tokens."""
    if isinstance(phrases, str):
        raise TypeError(f"{where}: pass a list of phrases, e.g. [{phrases!r}], not a bare string")
    out = list(phrases)
    for p in out:
        if not isinstance(p, str):
            raise TypeError(f"{where}: every phrase must be a str, got {type(p).__name__} {p!r}")
        if not allow_empty and not p.strip():
            raise ValueError(f"{where}: empty phrase {p!r}; give the words to look for")
    return out
