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
import zlib
from dataclasses import dataclass
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

__all__ = [
    "CANONICAL_PHRASES",
    "FEATURE_DIM",
    "LEVELS",
    "MIN_MASK_PIXELS",
    "SYNONYMS",
    "distance_to_surfaces",
    "distances_to_objects",
    "make_room",
    "room_layout",
]

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

_FOV_X_DEG = 60.0
_SUPERSAMPLE = 2  # RGB is averaged over 2x2 rays per pixel; labels and depth use the pixel centre
_LIGHT_DIR = np.array([0.45, -0.7, 1.0]) / np.linalg.norm([0.45, -0.7, 1.0])
_AMBIENT, _DIFFUSE = 0.42, 0.58
_BACKGROUND_Z = 12.0  # metres (times scale): where the depth prior puts rays that hit nothing
_MISS = np.uint32(0xFFFFFFFF)  # Open3D's geometry id for a ray that hits nothing
# Stub-embedding mixing weights: child = normalise(0.6 own + 0.8 parent), so cos(child, parent) ~ 0.8.
_OWN_WEIGHT, _PARENT_WEIGHT = 0.6, 0.8
_VIEW_NOISE, _SYNONYM_NOISE = 0.05, 0.2  # norms of the noise added to concept vectors

# Independent random streams, so adding draws to one never changes another.
_STREAM_LAYOUT, _STREAM_PRIOR, _STREAM_FEATURES, _STREAM_TEXT, _STREAM_ARRANGE = 1, 2, 3, 4, 5


@dataclass(frozen=True)
class _Primitive:
    """One mesh of the room with its labels and its look."""

    mesh: o3d.geometry.TriangleMesh
    labels: tuple[str, str, str]  # (subpart, part, whole)
    color: tuple[float, float, float]  # base RGB in [0, 1]
    texture: str  # a kind known to _texture


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

    prims = _room_primitives(np.random.default_rng([seed, _STREAM_LAYOUT]), scale, layout)
    phases = np.random.default_rng([seed, _STREAM_LAYOUT, 1]).uniform(0, 2 * np.pi, (len(prims), 4))
    # Every label of every group, whether or not this layout holds it: a query for an absent object
    # is answered (by a low relevancy), not refused.
    concepts = _concept_vectors(_room_primitives(np.random.default_rng(0), scale), seed)
    cameras = _room_cameras(width, height, n_train, n_test, scale)
    raycaster = o3d.t.geometry.RaycastingScene()
    for prim in prims:  # geometry id i is primitive i
        raycaster.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(prim.mesh))

    for view, cam in enumerate(cameras):
        rgb = _render_rgb(raycaster, cam, prims, phases)
        depth, ids = _render_depth_ids(raycaster, cam)
        prior = _depth_prior(depth, np.random.default_rng([seed, _STREAM_PRIOR, view]), scale)
        feature_rng = np.random.default_rng([seed, _STREAM_FEATURES, view])
        seg, feats = _language_features(ids, prims, concepts, feature_rng)
        cv2.imwrite(str(out / IMAGES_DIR / f"{cam.name}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGBA2BGRA))
        np.save(out / DEPTHS_DIR / f"{cam.name}.npy", prior)
        features_path, segments_path = feature_cache_paths(out / FEATURES_DIR, cam.name)
        np.save(segments_path, seg)
        np.save(features_path, feats)
        np.save(out / "gt" / "depth" / f"{cam.name}.npy", depth)
        np.save(out / "gt" / "ids" / f"{cam.name}.npy", ids)
        _write_segmentations(out / SEGMENTATIONS_DIR / cam.name, ids, prims)

    _write_transforms(out / TRANSFORMS_FILE, cameras, n_train, prims, seed, scale, layout)
    _write_text_embeddings(out / TEXT_TABLE_FILE, concepts, seed)
    _write_ground_truth_mesh(out / "gt", prims)
    return out


def distance_to_surfaces(
    scene_dir: str | Path, points: np.ndarray, *, label: str | None = None, level: str | None = None
) -> np.ndarray:
    """Unsigned distance from each point to the nearest ground-truth surface of a synthetic scene.

    Args:
        scene_dir: a folder written by :func:`make_room`.
        points: [N, 3] world positions.
        label: if given, only the primitives carrying this label at any level (e.g. "sofa",
            "table legs", "lamp shade") count as surfaces.
        level: with ``label``, only that level's label counts (one of :data:`LEVELS`).

    Returns:
        [N] float32 distances, in scene units.

    Example:
        >>> scene = make_room("/tmp/room", width=64, height=48, n_test=0)
        >>> float(distance_to_surfaces(scene, np.array([[0.0, 0.0, 0.0]]))[0]) < 1e-6
        True
    """
    gt = Path(scene_dir) / "gt"
    pts = _check_points(points, "distance_to_surfaces")
    if level is not None and level not in LEVELS:
        raise ValueError(f"distance_to_surfaces: level must be one of {LEVELS}, got {level!r}")
    if not (gt / "mesh.ply").exists():
        raise FileNotFoundError(f"{gt / 'mesh.ply'}: missing; is {scene_dir} a make_room scene?")
    mesh = o3d.io.read_triangle_mesh(str(gt / "mesh.ply"))
    keep = None
    if label is not None:
        records = json.loads((gt / "primitives.json").read_text())
        ranges = [
            np.arange(*r["triangles"])
            for r in records
            if (r["labels"][level] == label if level else label in r["labels"].values())
        ]
        if not ranges:
            raise ValueError(f"distance_to_surfaces: no primitive of {gt / 'primitives.json'} is {label!r}")
        keep = np.concatenate(ranges)
    return _distances(mesh, keep, pts)


def distances_to_objects(
    scene_dir: str | Path, points: np.ndarray, level: str = "whole"
) -> tuple[list[str], np.ndarray]:
    """Unsigned distance from each point to each object's true surface, the objects being the labels
    of one level (e.g. every whole-level object: "sofa", "mug", ...).

    Returns:
        (the labels, sorted; [K, N] float32 distances, row k to the primitives labelled k).
    """
    gt = Path(scene_dir) / "gt"
    if level not in LEVELS:
        raise ValueError(f"distances_to_objects: level must be one of {LEVELS}, got {level!r}")
    pts = _check_points(points, "distances_to_objects")
    records = json.loads((gt / "primitives.json").read_text())
    mesh = o3d.io.read_triangle_mesh(str(gt / "mesh.ply"))
    labels = sorted({r["labels"][level] for r in records})
    rows = [
        _distances(
            mesh,
            np.concatenate([np.arange(*r["triangles"]) for r in records if r["labels"][level] == k]),
            pts,
        )
        for k in labels
    ]
    return labels, np.stack(rows) if rows else np.zeros((0, len(pts)), np.float32)


def _check_points(points: np.ndarray, who: str) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float32)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{who}: points must have shape [N, 3], got {pts.shape}")
    return pts


def _distances(mesh: o3d.geometry.TriangleMesh, triangles: np.ndarray | None, pts: np.ndarray) -> np.ndarray:
    """[N] float32 distance from ``pts`` to the ``triangles`` (indices; None: all) of ``mesh``."""
    if triangles is not None:
        chosen = o3d.utility.Vector3iVector(np.asarray(mesh.triangles)[triangles])
        mesh = o3d.geometry.TriangleMesh(mesh.vertices, chosen)
    raycaster = o3d.t.geometry.RaycastingScene()
    raycaster.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return raycaster.compute_distance(o3d.core.Tensor(pts)).numpy().astype(np.float32)


# ----------------------------------------------------------------------------------------- geometry


def _box(
    size: tuple[float, float, float], center: tuple[float, float, float], yaw_deg: float = 0.0
) -> o3d.geometry.TriangleMesh:
    """A box of `size` (x, y, z) centred at `center`, turned by `yaw_deg` about z."""
    mesh = o3d.geometry.TriangleMesh.create_box(*size)
    mesh.translate(-0.5 * np.asarray(size))
    if yaw_deg:
        mesh.rotate(mesh.get_rotation_matrix_from_xyz((0.0, 0.0, np.deg2rad(yaw_deg))), center=(0, 0, 0))
    return mesh.translate(center)


def _cylinder(radius: float, height: float, center: tuple[float, float, float]) -> o3d.geometry.TriangleMesh:
    """An upright closed cylinder centred at `center`."""
    return o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution=24).translate(center)


# The furniture groups: each one's home (the floor point it stands on in the built-in room, layout 0) and
# its floor footprint there (x, y lows and highs), which a layout moves, scales about the home and keeps
# from overlapping. "wall": stands against the back wall (y = 2) in every layout.
_GROUPS = {
    "sofa": {"home": (-0.3, 1.5), "footprint": ((-1.25, 1.1), (0.65, 1.9)), "wall": True},
    "table": {"home": (-0.3, 0.4), "footprint": ((-0.8, 0.125), (0.2, 0.675)), "wall": False},
    "lamp": {"home": (1.2, 1.6), "footprint": ((1.05, 1.45), (1.35, 1.75)), "wall": False},
    "chair": {"home": (1.1, 0.35), "footprint": ((0.875, 0.125), (1.325, 0.575)), "wall": False},
    "shelf": {"home": (-1.65, 1.8), "footprint": ((-1.95, 1.65), (-1.35, 1.95)), "wall": True},
}
# Where a layout may put furniture: the floor the training cameras see, inside the walls.
_FLOOR_LO, _FLOOR_HI = (-1.95, 0.0), (1.95, 1.97)
_LAYOUT_SIZES = (0.8, 1.25)  # each group's size factor in a random layout
_LAYOUT_TRIES = 200  # placements tried per group before it is left out


@dataclass(frozen=True)
class _Placement:
    """A furniture group scaled by ``size`` about its home and moved by (dx, dy) from it."""

    kind: str
    size: float = 1.0
    dx: float = 0.0
    dy: float = 0.0

    def footprint(self) -> tuple[np.ndarray, np.ndarray]:
        home = np.asarray(_GROUPS[self.kind]["home"])
        lo, hi = (np.asarray(v) for v in _GROUPS[self.kind]["footprint"])
        move = home + (self.dx, self.dy)
        return move + self.size * (lo - home), move + self.size * (hi - home)


def room_layout(layout: int) -> list[_Placement]:
    """The furniture of layout ``layout``: 0 is the built-in room (every group at home); any other
    number draws which groups stand in the room (at least three placed; a second chair sometimes),
    their sizes and their places on the floor, from its own random stream. Footprints are drawn 5 cm
    apart; make_room then shifts each group by up to 5 cm with the scene's seed, so two groups may
    touch and a group against the back wall may reach 2 cm into it."""
    if layout == 0:
        return [_Placement(kind) for kind in _GROUPS]
    rng = np.random.default_rng([layout, _STREAM_ARRANGE])
    placed: list[_Placement] = []
    while len(placed) < 3:  # a draw that fits fewer (a large sofa can leave no room for the shelf) is redrawn
        placed = _draw_layout(rng)
    return placed


def _draw_layout(rng: np.random.Generator) -> list[_Placement]:
    kinds = [k for k in _GROUPS if rng.random() < 0.75]
    while len(kinds) < 3:
        kinds = sorted({*kinds, str(rng.choice(list(_GROUPS)))}, key=list(_GROUPS).index)
    if "chair" in kinds and rng.random() < 0.4:
        kinds.append("chair")
    placed: list[_Placement] = []
    for kind in kinds:
        for _ in range(_LAYOUT_TRIES):
            size = float(rng.uniform(*_LAYOUT_SIZES))
            lo, hi = _Placement(kind, size).footprint()
            dx = float(rng.uniform(_FLOOR_LO[0] - lo[0], _FLOOR_HI[0] - hi[0]))
            if _GROUPS[kind]["wall"]:  # its back to the back wall, a few centimetres off
                dy = float(_FLOOR_HI[1] - hi[1] - rng.uniform(0.0, 0.05))
            else:
                dy = float(rng.uniform(_FLOOR_LO[1] - lo[1], _FLOOR_HI[1] - hi[1]))
            candidate = _Placement(kind, size, dx, dy)
            if all(not _overlap(candidate, other) for other in placed):
                placed.append(candidate)
                break
    return placed


def _overlap(a: _Placement, b: _Placement, gap: float = 0.05) -> bool:
    (alo, ahi), (blo, bhi) = a.footprint(), b.footprint()
    return bool(np.all(alo < bhi + gap) and np.all(blo < ahi + gap))


Color = tuple[float, float, float]


def _room_primitives(rng: np.random.Generator, scale: float, layout: int = 0) -> list[_Primitive]:
    """Every primitive of the room (furniture of :func:`room_layout`), in world coordinates x `scale`.

    Each furniture group is shifted by a few centimetres and each colour jittered by a few percent,
    both from `rng`, so that seeds give different (but equally valid) rooms.
    """
    prims: list[_Primitive] = []

    def adder(shift: tuple[float, float], place: _Placement | None = None):
        def add(
            mesh: o3d.geometry.TriangleMesh, subpart: str, part: str, whole: str, color: Color, texture: str
        ) -> None:
            dx = dy = 0.0
            if place is not None:
                if place.size != 1.0:
                    home = _GROUPS[place.kind]["home"]
                    mesh.scale(place.size, center=(home[0], home[1], 0.0))
                dx, dy = place.dx, place.dy
            mesh.translate((shift[0] + dx, shift[1] + dy, 0.0))
            jitter = np.clip(np.asarray(color) * (1 + rng.uniform(-0.06, 0.06, 3)), 0, 1)
            mesh.scale(scale, center=(0, 0, 0))
            prims.append(_Primitive(mesh, (subpart, part, whole), tuple(float(c) for c in jitter), texture))

        return add

    def shift() -> tuple[float, float]:
        return tuple(rng.uniform(-0.05, 0.05, 2))

    # Room shell: the floor's top face is z = 0; the front (camera) and right sides are open.
    fixed = adder((0.0, 0.0))
    fixed(_box((4.0, 4.0, 0.05), (0.0, 0.0, -0.025)), "floor", "floor", "floor", (0.74, 0.6, 0.44), "checker")
    fixed(_box((4.0, 0.05, 2.5), (0.0, 2.025, 1.25)), "wall", "wall", "wall", (0.86, 0.84, 0.78), "plaster")
    fixed(
        _box((0.05, 4.05, 2.5), (-2.025, 0.025, 1.25)), "wall", "wall", "wall", (0.8, 0.83, 0.86), "plaster"
    )
    adder(shift())(
        _box((2.0, 1.4, 0.01), (-0.3, 0.4, 0.005)), "rug", "rug", "rug", (0.6, 0.26, 0.22), "stripes"
    )
    for place in room_layout(layout):
        _BUILDERS[place.kind](adder(shift(), place))
    return prims


def _sofa(add) -> None:
    """Against the back wall, facing -y."""
    fabric = (0.26, 0.36, 0.58)
    add(_box((1.6, 0.8, 0.35), (-0.3, 1.5, 0.175)), "sofa base", "sofa seat", "sofa", fabric, "fabric")
    for x in (-0.7, 0.1):
        add(
            _box((0.78, 0.6, 0.12), (x, 1.4, 0.41)),
            "sofa cushion",
            "sofa seat",
            "sofa",
            (0.36, 0.48, 0.72),
            "fabric",
        )
    add(_box((1.6, 0.2, 0.5), (-0.3, 1.8, 0.6)), "sofa back", "sofa back", "sofa", (0.3, 0.4, 0.62), "fabric")
    for x in (-1.175, 0.575):
        add(
            _box((0.15, 0.8, 0.6), (x, 1.5, 0.3)),
            "sofa armrest",
            "sofa armrests",
            "sofa",
            (0.22, 0.32, 0.52),
            "fabric",
        )


def _table(add) -> None:
    """A coffee table with a mug and a book on it."""
    add(
        _box((1.0, 0.55, 0.04), (-0.3, 0.4, 0.44)),
        "table top",
        "table top",
        "table",
        (0.56, 0.36, 0.2),
        "wood",
    )
    for dx in (-0.45, 0.45):
        for dy in (-0.22, 0.22):
            leg = _cylinder(0.025, 0.42, (-0.3 + dx, 0.4 + dy, 0.21))
            add(leg, "table leg", "table legs", "table", (0.3, 0.2, 0.12), "plain")
    red = (0.82, 0.16, 0.14)
    add(_cylinder(0.045, 0.1, (-0.05, 0.35, 0.51)), "mug body", "mug", "mug", red, "plain")
    add(_box((0.03, 0.015, 0.06), (0.01, 0.35, 0.51)), "mug handle", "mug", "mug", red, "plain")
    add(
        _box((0.22, 0.16, 0.04), (-0.58, 0.45, 0.48), yaw_deg=15),
        "book",
        "book",
        "book",
        (0.16, 0.46, 0.26),
        "plain",
    )


def _lamp(add) -> None:
    """A floor lamp."""
    metal = (0.22, 0.22, 0.24)
    add(_cylinder(0.15, 0.04, (1.2, 1.6, 0.02)), "lamp base", "lamp stand", "lamp", metal, "plain")
    add(_cylinder(0.02, 1.3, (1.2, 1.6, 0.69)), "lamp pole", "lamp stand", "lamp", metal, "plain")
    add(
        _cylinder(0.2, 0.28, (1.2, 1.6, 1.45)),
        "lamp shade",
        "lamp shade",
        "lamp",
        (0.96, 0.88, 0.64),
        "fabric",
    )


def _chair(add) -> None:
    """A chair facing -x."""
    wood = (0.66, 0.46, 0.26)
    add(_box((0.45, 0.45, 0.05), (1.1, 0.35, 0.45)), "chair seat", "chair seat", "chair", wood, "wood")
    add(_box((0.05, 0.45, 0.45), (1.3, 0.35, 0.7)), "chair back", "chair back", "chair", wood, "wood")
    for dx in (-0.19, 0.19):
        for dy in (-0.19, 0.19):
            leg = _cylinder(0.02, 0.425, (1.1 + dx, 0.35 + dy, 0.2125))
            add(leg, "chair leg", "chair legs", "chair", (0.4, 0.27, 0.15), "plain")


def _shelf(add) -> None:
    """An open shelf: two sides and four boards."""
    shelf = (0.52, 0.34, 0.2)
    for x in (-1.935, -1.365):
        add(_box((0.03, 0.3, 1.4), (x, 1.8, 0.7)), "shelf side", "shelf frame", "shelf", shelf, "wood")
    for z in (0.06, 0.5, 0.94, 1.39):
        add(_box((0.54, 0.3, 0.025), (-1.65, 1.8, z)), "shelf board", "shelf boards", "shelf", shelf, "wood")


_BUILDERS = {"sofa": _sofa, "table": _table, "lamp": _lamp, "chair": _chair, "shelf": _shelf}


def _room_cameras(width: int, height: int, n_train: int, n_test: int, scale: float) -> list[Camera]:
    """Training views on a 70 degree arc at 1.5 m, test views between and slightly off the arc.

    Test views sit at 0.88 or 0.94 of the arc's radius and 0.12 m above or below it, so none coincides
    with a training view even where their angles agree.
    """
    target = np.array([0.0, 0.8, 0.55])
    radius, eye_z, span = 2.7, 1.5, 70.0

    def camera(angle_deg: float, r: float, z: float, name: str) -> Camera:
        a = np.deg2rad(angle_deg)
        eye = np.array([target[0] + r * np.sin(a), target[1] - r * np.cos(a), z])
        return Camera.look_at(
            eye * scale, target * scale, width=width, height=height, fov_x_deg=_FOV_X_DEG, name=name
        )

    train_angles = np.linspace(-span / 2, span / 2, n_train) if n_train > 1 else np.zeros(1)
    cams = [camera(a, radius, eye_z, f"train_{i:03d}") for i, a in enumerate(train_angles)]
    for i in range(n_test):
        angle = -span / 2 + span * (i + 0.5) / n_test
        r = radius * (0.88 if i % 2 == 0 else 0.94)
        z = eye_z + (0.12 if i % 2 == 0 else -0.12)
        cams.append(camera(angle, r, z, f"test_{i:03d}"))
    return cams


# ---------------------------------------------------------------------------------------- rendering


def _camera_rays(cam: Camera) -> np.ndarray:
    """[H, W, 6] world rays (origin, direction) through the pixel centres of `cam`.

    Directions have camera-space z = -1 (OpenGL: the camera looks down -z), so the ray parameter of a
    hit is its z-depth.
    """
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    dirs_cam = np.stack([(u - cam.cx) / cam.fx, -(v - cam.cy) / cam.fy, -np.ones_like(u)], axis=-1)
    dirs = dirs_cam @ cam.c2w[:3, :3].T
    origins = np.broadcast_to(cam.c2w[:3, 3], dirs.shape)
    return np.concatenate([origins, dirs], axis=-1).astype(np.float32)


def _cast(raycaster: o3d.t.geometry.RaycastingScene, cam: Camera) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Cast the rays of `cam`; returns the rays [H, W, 6] and Open3D's hit arrays."""
    rays = _camera_rays(cam)
    hits = raycaster.cast_rays(o3d.core.Tensor(rays))
    return rays, {k: v.numpy() for k, v in hits.items()}


def _render_depth_ids(
    raycaster: o3d.t.geometry.RaycastingScene, cam: Camera
) -> tuple[np.ndarray, np.ndarray]:
    """True z-depth [H, W] float32 (0 = background) and primitive index [H, W] int16 (-1 = background)."""
    _, hits = _cast(raycaster, cam)
    miss = hits["geometry_ids"] == _MISS
    depth = np.where(miss, 0.0, hits["t_hit"]).astype(np.float32)
    ids = np.where(miss, -1, hits["geometry_ids"].astype(np.int64)).astype(np.int16)
    return depth, ids


def _render_rgb(
    raycaster: o3d.t.geometry.RaycastingScene, cam: Camera, prims: list[_Primitive], phases: np.ndarray
) -> np.ndarray:
    """[H, W, 4] uint8 RGBA image: textured Lambert shading, 2x2 supersampled.

    Alpha is the fraction of a pixel's rays that hit geometry; colour is straight (not premultiplied),
    so compositing on white, as the scene loader does, gives the white-background picture. Alpha tells
    the trainer the background colour, as in the Blender NeRF data.
    """
    rays, hits = _cast(raycaster, cam.scaled(1.0 / _SUPERSAMPLE))
    h, w = hits["t_hit"].shape
    rays, ids = rays.reshape(-1, 6), hits["geometry_ids"].reshape(-1)
    normals, t = hits["primitive_normals"].reshape(-1, 3), hits["t_hit"].reshape(-1)
    rgb = np.ones((h * w, 3))
    for gid, prim in enumerate(prims):
        sel = ids == gid
        if not sel.any():
            continue
        dirs = rays[sel, 3:].astype(np.float64)
        points = rays[sel, :3] + t[sel, None] * dirs
        n = normals[sel].astype(np.float64)
        n *= -np.sign(np.sum(n * dirs, axis=1, keepdims=True) + 1e-12)  # face the viewer
        light = _AMBIENT + _DIFFUSE * np.clip(n @ _LIGHT_DIR, 0.0, None)
        tex = _texture(prim.texture, points, phases[gid])
        rgb[sel] = np.asarray(prim.color) * (tex * light)[:, None]
    rgb = rgb.reshape(h, w, 3)
    s = _SUPERSAMPLE
    composite = rgb.reshape(h // s, s, w // s, s, 3).mean(axis=(1, 3))  # on white
    alpha = (ids != _MISS).reshape(h // s, s, w // s, s).mean(axis=(1, 3))[..., None]
    straight = np.where(alpha > 0, (composite - (1.0 - alpha)) / np.maximum(alpha, 1e-6), 1.0)
    rgba = np.concatenate([straight, alpha], axis=-1)
    return np.clip(np.round(rgba * 255.0), 0, 255).astype(np.uint8)


def _texture(kind: str, points: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """[N] brightness factor of a procedural texture at world `points` [N, 3]; `phase` [4] is seeded."""
    x, y, z = points.T
    if kind == "checker":  # 0.5 m floor tiles
        return np.where((np.floor(x / 0.5 + phase[0] / 7) + np.floor(y / 0.5)) % 2 == 0, 1.0, 0.8)
    if kind == "stripes":  # rug stripes 8 cm wide
        return np.where(np.sin(2 * np.pi * x / 0.16 + phase[0]) > 0, 1.0, 0.74)
    if kind == "plaster":  # subtle low-frequency mottling
        return 1.0 + 0.04 * np.sin(3.1 * x + 1.7 * z + phase[0]) * np.sin(2.3 * y - 2.9 * z + phase[1])
    if kind == "fabric":  # fine weave plus soft mottling
        weave = np.sin(2 * np.pi * (x + y) / 0.04 + phase[0]) * np.sin(2 * np.pi * (z - x) / 0.04 + phase[1])
        return 1.0 + 0.06 * weave + 0.05 * np.sin(5.0 * x + 3.0 * y + 4.0 * z + phase[2])
    if kind == "wood":  # grain along x with a slow wobble
        wobble = 2.0 * np.sin(3.0 * x + phase[1])
        return 1.0 + 0.1 * np.sin(2 * np.pi * (y + 0.3 * z) / 0.05 + wobble + phase[0])
    if kind == "plain":
        return np.ones(len(points))
    raise ValueError(f"unknown texture {kind!r}")


# -------------------------------------------------------------------------------------- depth prior


def _depth_prior(depth: np.ndarray, rng: np.random.Generator, scale: float) -> np.ndarray:
    """A distorted relative disparity [H, W] float32 from true z-depth (0 = background).

    Steps, each what a monocular network gets wrong: a monotone power of 1 / z, a slight blur across
    object edges, smooth multiplicative noise of about 3 %, and an unknown positive scale and shift.
    """
    h, w = depth.shape
    z = np.where(depth > 0, depth, _BACKGROUND_Z * scale).astype(np.float64)
    disparity = (1.0 / z) ** rng.uniform(0.7, 0.9)
    sigma = 0.6 * max(w / 160.0, 0.5)
    disparity = cv2.GaussianBlur(disparity, (0, 0), sigmaX=sigma, borderType=cv2.BORDER_REFLECT)
    coarse = rng.standard_normal((4, 5))
    noise = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    disparity *= 1.0 + 0.03 * noise
    prior = rng.uniform(0.5, 2.0) * disparity + rng.uniform(0.0, 0.3)
    return prior.astype(np.float32)


# -------------------------------------------------------------------------------- language features


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _random_unit(seed: int, text: str) -> np.ndarray:
    """A unit vector in R^512 fixed by the seed and the text (zlib.crc32 is stable across runs)."""
    rng = np.random.default_rng([seed, _STREAM_TEXT, zlib.crc32(text.encode("utf-8"))])
    return _unit(rng.standard_normal(FEATURE_DIM))


def _concept_vectors(prims: list[_Primitive], seed: int) -> dict[str, np.ndarray]:
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


def _mask_keys(ids: np.ndarray, prims: list[_Primitive], level: int) -> tuple[np.ndarray, list[str]]:
    """Mask key per pixel at `level` [H, W] (-1 = background) and the label of each key.

    At the subpart level each primitive is its own mask (four table legs are four masks, as a mask
    generator would see them); above, all primitives sharing a label form one mask.
    """
    if level == 0:
        return ids.astype(np.int64), [p.labels[0] for p in prims]
    labels = sorted({p.labels[level] for p in prims})
    key_of_prim = np.array([labels.index(p.labels[level]) for p in prims] + [-1])
    return key_of_prim[ids.astype(np.int64)], labels  # id -1 picks the trailing -1 for background


def _language_features(
    ids: np.ndarray, prims: list[_Primitive], concepts: dict[str, np.ndarray], rng: np.random.Generator
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


def _write_segmentations(folder: Path, ids: np.ndarray, prims: list[_Primitive]) -> None:
    """One binary PNG (0 / 255) per whole-level object with at least MIN_MASK_PIXELS pixels in view."""
    folder.mkdir(parents=True, exist_ok=True)
    wholes = np.array([p.labels[2] for p in prims] + [""])
    whole_map = wholes[ids.astype(np.int64)]
    for phrase in sorted(set(wholes[:-1])):
        mask = whole_map == phrase
        if mask.sum() >= MIN_MASK_PIXELS:
            cv2.imwrite(str(folder / f"{phrase}.png"), mask.astype(np.uint8) * 255)


def _write_transforms(
    path: Path,
    cameras: list[Camera],
    n_train: int,
    prims: list[_Primitive],
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


def _write_text_embeddings(path: Path, concepts: dict[str, np.ndarray], seed: int) -> None:
    """Every label, the synonyms (label + noise of norm 0.2) and the canonical phrases (random)."""
    table = {label: vec for label, vec in concepts.items()}
    for synonym, label in SYNONYMS.items():
        table[synonym] = _unit(concepts[label] + _SYNONYM_NOISE * _random_unit(seed, "synonym:" + synonym))
    for phrase in CANONICAL_PHRASES:
        table[phrase] = _random_unit(seed, phrase)
    np.savez(path, **{k: v.astype(np.float32) for k, v in sorted(table.items())})


def _write_ground_truth_mesh(gt: Path, prims: list[_Primitive]) -> None:
    """gt/mesh.ply with every triangle, and gt/primitives.json mapping triangle ranges to labels."""
    merged = o3d.geometry.TriangleMesh()
    records, start = [], 0
    for i, prim in enumerate(prims):
        merged += prim.mesh
        n = len(prim.mesh.triangles)
        lo, hi = np.asarray(prim.mesh.vertices).min(axis=0), np.asarray(prim.mesh.vertices).max(axis=0)
        records.append(
            {
                "index": i,
                "labels": dict(zip(LEVELS, prim.labels, strict=True)),
                "triangles": [start, start + n],
                "aabb": [lo.tolist(), hi.tolist()],
                "center": ((lo + hi) / 2).tolist(),
            }
        )
        start += n
    o3d.io.write_triangle_mesh(str(gt / "mesh.ply"), merged, write_ascii=False)
    (gt / "primitives.json").write_text(json.dumps(records, indent=2))
