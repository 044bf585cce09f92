"""The room's stub language: a feature vector per concept (with synonyms), per-view masks at three
levels with their features, the query labels and the phrase table.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import cv2
import numpy as np

from encoders.protocols import CANONICAL_PHRASES, LEVELS
from langfield.synthetic.room import STREAM_TEXT, Primitive

FEATURE_DIM = 512
# Synonym -> the label it means; its embedding is that label's plus a little noise.
SYNONYMS = {
    "couch": "sofa",
    "desk": "table",
    "cup": "mug",
    "lampshade": "lamp shade",
    "armchair": "chair",
    "bookshelf": "shelf",
    "carpet": "rug",
}
# Masks with fewer pixels than this in a view are dropped, as a mask generator drops specks.
MIN_MASK_PIXELS = 5
# Stub-embedding mixing weights: child = normalise(0.6 own + 0.8 parent), so cos(child, parent) ~ 0.8.
_OWN_WEIGHT, _PARENT_WEIGHT = 0.6, 0.8
_VIEW_NOISE, _SYNONYM_NOISE = 0.05, 0.2  # norms of the noise added to concept vectors


# -------------------------------------------------------------------------------- language features


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _random_unit(seed: int, text: str) -> np.ndarray:
    """A unit vector in R^512 fixed by the seed and the text (zlib.crc32 is stable across runs)."""
    rng = np.random.default_rng([seed, STREAM_TEXT, zlib.crc32(text.encode("utf-8"))])
    return _unit(rng.standard_normal(FEATURE_DIM))


def concept_vectors(prims: list[Primitive], seed: int) -> dict[str, np.ndarray]:
    """Stub CLIP-like embedding of every label: a whole's is random; a part's and a subpart's lean on
    their parent (normalise(0.6 own + 0.8 parent)), so "sofa cushion" is nearer "sofa" than "table"."""
    vectors: dict[str, np.ndarray] = {}
    for level in range(len(LEVELS) - 1, -1, -1):  # parents first
        for prim in prims:
            label = prim.labels[level]
            if label in vectors:
                continue  # a subpart named like its part (e.g. "lamp shade") shares its vector
            own = _random_unit(seed, label)
            parent = prim.labels[level + 1] if level + 1 < len(LEVELS) else None
            if parent is not None:
                own = _unit(_OWN_WEIGHT * own + _PARENT_WEIGHT * vectors[parent])
            vectors[label] = own
    return vectors


def _mask_keys(ids: np.ndarray, prims: list[Primitive], level: int) -> tuple[np.ndarray, list[str]]:
    """Mask key per pixel at `level` [H, W] (-1 = background) and the label of each key.

    At the subpart level each primitive is its own mask (four table legs are four masks, as a mask
    generator would see them); above, all primitives sharing a label form one mask.
    """
    if level == 0:
        return ids.astype(np.int64), [p.labels[0] for p in prims]
    labels = sorted({p.labels[level] for p in prims})
    key_of_prim = np.array([labels.index(p.labels[level]) for p in prims] + [-1])
    return key_of_prim[ids.astype(np.int64)], labels  # id -1 picks the trailing -1 for background


def mask_features(
    ids: np.ndarray, prims: list[Primitive], concepts: dict[str, np.ndarray], rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Segment maps [3, H, W] int32 and mask features [M, 512] float32 of one view.

    Each mask present with at least MIN_MASK_PIXELS pixels gets one row: its label's concept vector plus
    noise of norm 0.05, normalised, so views differ slightly as real CLIP crops do.
    """
    seg = np.full((len(LEVELS),) + ids.shape, -1, dtype=np.int32)
    rows: list[np.ndarray] = []
    for level in range(len(LEVELS)):
        keys, key_labels = _mask_keys(ids, prims, level)
        for key in np.unique(keys[keys >= 0]):
            inside = keys == key
            if inside.sum() < MIN_MASK_PIXELS:
                continue
            seg[level][inside] = len(rows)
            noise = _VIEW_NOISE * _unit(rng.standard_normal(FEATURE_DIM))
            rows.append(_unit(concepts[key_labels[key]] + noise))
    feats = np.stack(rows) if rows else np.zeros((0, FEATURE_DIM))
    return seg, feats.astype(np.float32)


# ------------------------------------------------------------------------------------------ writers


def write_segmentations(folder: Path, ids: np.ndarray, prims: list[Primitive]) -> None:
    """One binary PNG (0 / 255) per whole-level object with at least MIN_MASK_PIXELS pixels in view."""
    folder.mkdir(parents=True, exist_ok=True)
    wholes = np.array([p.labels[2] for p in prims] + [""])
    whole_map = wholes[ids.astype(np.int64)]
    for phrase in sorted(set(wholes[:-1])):
        mask = whole_map == phrase
        if mask.sum() >= MIN_MASK_PIXELS:
            cv2.imwrite(str(folder / f"{phrase}.png"), mask.astype(np.uint8) * 255)


def write_text_embeddings(path: Path, concepts: dict[str, np.ndarray], seed: int) -> None:
    """Every label, the synonyms (label + noise of norm 0.2) and the canonical phrases (random)."""
    table = {label: vec for label, vec in concepts.items()}
    for synonym, label in SYNONYMS.items():
        table[synonym] = _unit(concepts[label] + _SYNONYM_NOISE * _random_unit(seed, "synonym:" + synonym))
    for phrase in CANONICAL_PHRASES:
        table[phrase] = _random_unit(seed, phrase)
    np.savez(path, **{k: v.astype(np.float32) for k, v in sorted(table.items())})
