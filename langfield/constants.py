"""Names and numbers that more than one module must agree on, kept in one place.

A leaf module: it imports nothing from langfield, so any module may use it.
"""

from __future__ import annotations

__all__ = [
    "DEPTHS_DIR",
    "FEATURES_DIR",
    "IMAGES_DIR",
    "LATENT_NORM_EPS",
    "MASKS_DIR",
    "POINTS_FILE",
    "SEGMENTATIONS_DIR",
    "TEXT_TABLE_FILE",
    "TRANSFORMS_FILE",
]

# A scene folder's parts (docs/format.md).
TRANSFORMS_FILE = "transforms.json"
IMAGES_DIR = "images"
DEPTHS_DIR = "depths"
FEATURES_DIR = "language_features"
SEGMENTATIONS_DIR = "segmentations"
MASKS_DIR = "masks"
# The sparse points of a scene that `langfield capture` posed (nerfstudio's name; transforms.json's
# `ply_file_path` names it).
POINTS_FILE = "sparse_pc.ply"

# The copy of the scene's phrase table a saved field keeps beside field.json (text-encoder "table"), and
# the name of that table in a scene folder.
TEXT_TABLE_FILE = "text_embeddings.npz"

# A latent is divided by max(|z|, this) before decoding: a zero latent (an empty pixel, a level without
# masks) stays zero, and only latents shorter than this are not brought to unit length.
LATENT_NORM_EPS = 1e-6
