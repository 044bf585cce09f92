"""The built-in synthetic room: a scene folder with an independent ground truth.

:func:`make_room` builds a small furnished room from Open3D primitives (boxes, cylinders), renders it
by ray casting with Open3D's ``RaycastingScene`` (not with langfield's rasterizer, so the ground truth
does not share its bugs) and writes a scene folder in the layout of docs/format.md:

- ``images/``: textured, Lambert-shaded RGBA renders (2x2 supersampled); alpha 0 where rays miss,
  so the loader composites them on white;
- ``depths/``: a *distorted relative disparity prior*, as a monocular network gives: 1 / z, a monotone
  power, a per-view affine scale and shift, smooth multiplicative noise and a slight blur;
- ``language_features/``: 3-level segment maps (subpart, part, whole) and stub CLIP-like features;
- ``text_embeddings.npz``: phrase -> embedding in the same stub space, with synonyms and the canonical
  phrases; ``segmentations/``: one mask per (view, whole-level object).

Beside it, ``gt/`` holds what later checks compare against (not part of the docs/format.md contract):

- ``gt/depth/<name>.npy``: float32 [H, W] true z-depth (distance along the viewing axis); **0 where the
  ray hits nothing** (background);
- ``gt/ids/<name>.npy``: int16 [H, W] index of the primitive seen at each pixel centre, -1 = background;
- ``gt/mesh.ply``: every triangle of the room; ``gt/primitives.json``: per primitive its labels at the
  three levels, its triangle range in ``mesh.ply`` and its axis-aligned box.

World frame: z up, metres times ``scale``, the floor at z = 0, the room spanning [-2, 2] x [-2, 2] with a
back wall at y = 2 and a left wall at x = -2; the cameras stand inside the room and look towards +y.

Example:
    >>> scene = make_room("/tmp/room", width=64, height=48)
    >>> sorted(p.name for p in scene.iterdir())[:3]
    ['depths', 'gt', 'images']
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d

from encoders.cache import feature_cache_paths
from encoders.protocols import CANONICAL_PHRASES, LEVELS
from langfield.camera import Camera
from langfield.constants import (
    DEPTHS_DIR,
    FEATURES_DIR,
    IMAGES_DIR,
    SEGMENTATIONS_DIR,
    TEXT_TABLE_FILE,
    TRANSFORMS_FILE,
)
from langfield.synthetic.ground_truth import (
    distance_to_surfaces,
    distances_to_objects,
    write_ground_truth_mesh,
)
from langfield.synthetic.language import (
    FEATURE_DIM,
    MIN_MASK_PIXELS,
    SYNONYMS,
    concept_vectors,
    mask_features,
    write_segmentations,
    write_text_embeddings,
)
from langfield.synthetic.render import depth_prior, render_depth_ids, render_rgb
from langfield.synthetic.room import (
    STREAM_FEATURES,
    STREAM_LAYOUT,
    STREAM_PRIOR,
    Primitive,
    room_cameras,
    room_layout,
    room_primitives,
)

__all__ = [
    "CANONICAL_PHRASES",
    "FEATURE_DIM",
    "LEVELS",
    "MIN_MASK_PIXELS",
    "SYNONYMS",
    "distance_to_surfaces",
    "distances_to_objects",
    "make_room",
    "render_room",
    "room_layout",
]


def make_room(
    out_dir: str | Path,
    *,
    seed: int = 0,
    layout: int = 0,
    width: int = 160,
    height: int = 120,
    n_train: int = 3,
    n_test: int = 5,
    scale: float = 1.0,
) -> Path:
    """Write the synthetic room scene folder (docs/format.md layout plus ``gt/``).

    Args:
        out_dir: folder to write; created if missing, existing files are overwritten.
        seed: seeds colours, textures, small furniture offsets, the depth prior and the features;
            the same seed gives byte-identical arrays.
        layout: which furniture stands where (:func:`room_layout`): 0 is the built-in room; other
            numbers draw the groups, their sizes and places, independently of ``seed``.
        width, height: image size in pixels of every view (60 degree horizontal field of view).
        n_train: training views on an arc of 70 degrees at 1.5 m height.
        n_test: novel test views between and slightly off that arc.
        scale: the room's size factor (1 = metres).

    Returns:
        The scene folder's path.

    Example:
        >>> scene = make_room("/tmp/room", seed=1, width=64, height=48, n_test=2)
        >>> (scene / "images" / "train_000.png").exists()
        True
    """
    if width < 8 or height < 8:
        raise ValueError(f"make_room: image size must be at least 8x8, got {width}x{height}")
    if n_train < 1 or n_test < 0:
        raise ValueError(f"make_room: need n_train >= 1 and n_test >= 0, got {n_train}, {n_test}")
    if not (isinstance(layout, (int, np.integer)) and layout >= 0):
        raise ValueError(f"make_room: layout must be a whole number >= 0, got {layout!r}")
    if not (scale > 0 and np.isfinite(scale)):
        raise ValueError(f"make_room: scale must be positive and finite, got {scale}")
    out = Path(out_dir)
    for sub in (IMAGES_DIR, DEPTHS_DIR, FEATURES_DIR, SEGMENTATIONS_DIR, "gt/depth", "gt/ids"):
        (out / sub).mkdir(parents=True, exist_ok=True)

    prims, phases, raycaster = _room(seed, layout, scale)
    # Every label of every group, whether or not this layout holds it: a query for an absent object
    # is answered (by a low relevancy), not refused.
    concepts = concept_vectors(room_primitives(np.random.default_rng(0), scale), seed)
    cameras = room_cameras(width, height, n_train, n_test, scale)
    for view, cam in enumerate(cameras):
        rgb = render_rgb(raycaster, cam, prims, phases)
        depth, ids = render_depth_ids(raycaster, cam)
        prior = depth_prior(depth, np.random.default_rng([seed, STREAM_PRIOR, view]), scale)
        feature_rng = np.random.default_rng([seed, STREAM_FEATURES, view])
        seg, feats = mask_features(ids, prims, concepts, feature_rng)
        cv2.imwrite(str(out / IMAGES_DIR / f"{cam.name}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGBA2BGRA))
        np.save(out / DEPTHS_DIR / f"{cam.name}.npy", prior)
        features_path, segments_path = feature_cache_paths(out / FEATURES_DIR, cam.name)
        np.save(segments_path, seg)
        np.save(features_path, feats)
        np.save(out / "gt" / "depth" / f"{cam.name}.npy", depth)
        np.save(out / "gt" / "ids" / f"{cam.name}.npy", ids)
        write_segmentations(out / SEGMENTATIONS_DIR / cam.name, ids, prims)

    _write_transforms(out / TRANSFORMS_FILE, cameras, n_train, prims, seed, scale, layout)
    write_text_embeddings(out / TEXT_TABLE_FILE, concepts, seed)
    write_ground_truth_mesh(out / "gt", prims)
    return out


def _room(seed: int, layout: int, scale: float) -> tuple[list[Primitive], np.ndarray, object]:
    """The room's primitives, their texture phases and a ray caster holding them (geometry id i is
    primitive i)."""
    prims = room_primitives(np.random.default_rng([seed, STREAM_LAYOUT]), scale, layout)
    phases = np.random.default_rng([seed, STREAM_LAYOUT, 1]).uniform(0, 2 * np.pi, (len(prims), 4))
    raycaster = o3d.t.geometry.RaycastingScene()
    for prim in prims:
        raycaster.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(prim.mesh))
    return prims, phases, raycaster


def render_room(
    cameras: list[Camera], *, seed: int = 0, layout: int = 0, scale: float = 1.0
) -> list[np.ndarray]:
    """The room of :func:`make_room` (same ``seed``, ``layout``, ``scale``) seen from any cameras: one
    [H, W, 3] uint8 RGB image each, composited on white (for videos and photo sets of a known scene).

    Example:
        >>> cam = Camera.look_at(eye=(0.5, -1.5, 1.5), target=(0, 0.8, 0.55), width=32, height=24)
        >>> render_room([cam])[0].shape
        (24, 32, 3)
    """
    prims, phases, raycaster = _room(seed, layout, scale)
    images = []
    for cam in cameras:
        rgba = render_rgb(raycaster, cam, prims, phases).astype(np.float32) / 255.0
        rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
        images.append(np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8))
    return images


def _write_transforms(
    path: Path,
    cameras: list[Camera],
    n_train: int,
    prims: list[Primitive],
    seed: int,
    scale: float,
    layout: int = 0,
) -> None:
    """transforms.json: shared PINHOLE intrinsics, disparity priors, the room's aabb and every frame."""
    cam = cameras[0]
    lo = np.min([np.asarray(p.mesh.vertices).min(axis=0) for p in prims], axis=0) - 0.05 * scale
    hi = np.max([np.asarray(p.mesh.vertices).max(axis=0) for p in prims], axis=0) + 0.05 * scale
    frames = [
        {
            "file_path": f"images/{c.name}.png",
            "transform_matrix": c.c2w.tolist(),
            "split": "train" if i < n_train else "test",
        }
        for i, c in enumerate(cameras)
    ]
    meta = {
        "camera_model": "PINHOLE",
        "w": cam.width,
        "h": cam.height,
        "fl_x": cam.fx,
        "fl_y": cam.fy,
        "cx": cam.cx,
        "cy": cam.cy,
        "depth_kind": "disparity",
        "aabb": [lo.tolist(), hi.tolist()],
        "generator": {
            "name": "langfield.synthetic.make_room",
            "seed": seed,
            "layout": layout,
            "scale": scale,
        },
        "frames": frames,
    }
    path.write_text(json.dumps(meta, indent=2))
