"""The synthetic room: the docs/format.md contract, determinism and the ground truth's consistency."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
import torch

from langfield.camera import Camera
from langfield.synthetic import (
    CANONICAL_PHRASES,
    FEATURE_DIM,
    LEVELS,
    SYNONYMS,
    distance_to_surfaces,
    distances_to_objects,
    make_room,
    room_layout,
)
from langfield.synthetic.ground_truth import (
    COVER_STEP,
    _subdivide,
    uncovered_triangles,
    write_ground_truth_mesh,
)
from langfield.synthetic.room import Primitive, _box, room_primitives

W, H = 64, 48
LAYOUT_0_DIGEST = "0d235cc9e5aa1df1"


@pytest.fixture(scope="module")
def scene(room_factory) -> Path:
    return room_factory(W, H)


def _frames(scene: Path) -> list[dict]:
    return json.loads((scene / "transforms.json").read_text())["frames"]


def _names(scene: Path) -> list[str]:
    return [Path(f["file_path"]).stem for f in _frames(scene)]


def _cameras(scene: Path) -> dict[str, Camera]:
    meta = json.loads((scene / "transforms.json").read_text())
    intrinsics = (meta["w"], meta["h"], meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"])
    cams = {}
    for f in meta["frames"]:
        name = Path(f["file_path"]).stem
        cams[name] = Camera(name, *intrinsics, np.array(f["transform_matrix"]))
    return cams


def _primitives(scene: Path) -> list[dict]:
    return json.loads((scene / "gt" / "primitives.json").read_text())


def _arrays(scene: Path, name: str) -> dict[str, np.ndarray]:
    return {
        "image": cv2.imread(str(scene / "images" / f"{name}.png"), cv2.IMREAD_UNCHANGED),
        "depth": np.load(scene / "depths" / f"{name}.npy"),
        "s": np.load(scene / "language_features" / f"{name}_s.npy"),
        "f": np.load(scene / "language_features" / f"{name}_f.npy"),
    }


def test_same_seed_is_byte_identical(scene: Path, tmp_path: Path) -> None:
    again = make_room(tmp_path / "again", seed=0, width=W, height=H)
    for name in _names(scene):
        a, b = _arrays(scene, name), _arrays(again, name)
        for key in a:
            assert a[key].dtype == b[key].dtype and a[key].tobytes() == b[key].tobytes(), (name, key)


def test_other_seed_gives_other_images(scene: Path, tmp_path: Path) -> None:
    other = make_room(tmp_path / "other", seed=1, width=W, height=H, n_test=0)
    a, b = _arrays(scene, "train_000"), _arrays(other, "train_000")
    assert not np.array_equal(a["image"], b["image"])
    assert not np.array_equal(a["f"], b["f"])


def test_format_files_have_right_shapes_and_dtypes(scene: Path) -> None:
    names = _names(scene)
    assert names == [f"train_{i:03d}" for i in range(3)] + [f"test_{i:03d}" for i in range(5)]
    for name in names:
        arr = _arrays(scene, name)
        assert arr["image"].shape == (H, W, 4) and arr["image"].dtype == np.uint8  # RGBA
        assert arr["depth"].shape == (H, W) and arr["depth"].dtype == np.float32
        assert np.isfinite(arr["depth"]).all()
        s, f = arr["s"], arr["f"]
        assert s.shape == (len(LEVELS), H, W) and np.issubdtype(s.dtype, np.integer)
        assert f.ndim == 2 and f.shape[1] == FEATURE_DIM and f.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, atol=1e-5)
        assert s.min() >= -1 and s.max() < len(f)
        assert set(np.unique(s[s >= 0])) == set(range(len(f))), "every row of _f is used by a mask"
        for level in range(len(LEVELS)):
            assert (s[level] >= 0).any(), (name, LEVELS[level])
        masks = list((scene / "segmentations" / name).glob("*.png"))
        assert {"sofa.png", "table.png"} <= {m.name for m in masks}
        for m in masks:
            assert set(np.unique(cv2.imread(str(m), cv2.IMREAD_GRAYSCALE))) <= {0, 255}
    assert (scene / "text_embeddings.npz").exists()


def test_levels_nest(scene: Path) -> None:
    for name in _names(scene):
        s = np.load(scene / "language_features" / f"{name}_s.npy")
        for finer, coarser in ((0, 1), (1, 2), (0, 2)):
            for row in np.unique(s[finer][s[finer] >= 0]):
                above = np.unique(s[coarser][s[finer] == row])
                assert len(above) == 1 and above[0] >= 0, (name, LEVELS[finer], row, above)


def test_intrinsics_match_images_and_poses_are_distinct(scene: Path) -> None:
    meta = json.loads((scene / "transforms.json").read_text())
    assert meta["camera_model"] == "PINHOLE" and meta["depth_kind"] == "disparity"
    assert (meta["w"], meta["h"]) == (W, H) and (meta["cx"], meta["cy"]) == (W / 2, H / 2)
    assert meta["fl_x"] == pytest.approx(0.5 * W / np.tan(np.deg2rad(30)))
    lo, hi = np.array(meta["aabb"])
    assert (hi - lo > 2.0).all()
    cams = _cameras(scene)
    train = [c.center for c in cams.values() if c.name.startswith("train")]
    test = [c.center for c in cams.values() if c.name.startswith("test")]
    assert [f["split"] for f in meta["frames"]] == ["train"] * 3 + ["test"] * 5
    dists = np.linalg.norm(np.array(train)[:, None] - np.array(test)[None], axis=-1)
    assert dists.min() > 0.1
    for c in cams.values():  # every camera stands inside the aabb and looks at the furniture
        assert (c.center > lo).all() and (c.center < hi).all()


def _ranks(x: np.ndarray) -> np.ndarray:
    r = np.empty(len(x))
    r[np.argsort(x, kind="stable")] = np.arange(len(x))
    return r


def test_depth_prior_is_monotone_but_distorted(scene: Path) -> None:
    for name in ("train_000", "test_002"):
        prior = np.load(scene / "depths" / f"{name}.npy").astype(np.float64)
        depth = np.load(scene / "gt" / "depth" / f"{name}.npy").astype(np.float64)
        fg = depth > 0
        prior, inv = prior[fg], 1.0 / depth[fg]
        spearman = np.corrcoef(_ranks(prior), _ranks(inv))[0, 1]
        assert spearman > 0.9
        a = np.stack([inv, np.ones_like(inv)], axis=1)
        coef, *_ = np.linalg.lstsq(a, prior, rcond=None)
        relative_residual = np.std(prior - a @ coef) / np.std(prior)
        assert relative_residual > 0.01, "the prior must not be an affine function of 1 / depth"


def test_background_is_white_with_zero_depth_and_no_mask(scene: Path) -> None:
    seen_background = False
    for name in _names(scene):
        ids = np.load(scene / "gt" / "ids" / f"{name}.npy")
        depth = np.load(scene / "gt" / "depth" / f"{name}.npy")
        s = np.load(scene / "language_features" / f"{name}_s.npy")
        assert ((depth == 0) == (ids < 0)).all()
        alpha = cv2.imread(str(scene / "images" / f"{name}.png"), cv2.IMREAD_UNCHANGED)[..., 3]
        assert (alpha[ids < 0] < 255).all() and (alpha[ids >= 0] > 0).all()
        assert (s[:, ids < 0] == -1).all()
        seen_background |= bool((ids < 0).any())
    assert seen_background, "the open side of the room shows background in some view"


def test_table_top_projects_onto_table_label(scene: Path) -> None:
    top = next(p for p in _primitives(scene) if p["labels"]["subpart"] == "table top")
    embeddings = np.load(scene / "text_embeddings.npz")
    wholes = sorted({p["labels"]["whole"] for p in _primitives(scene)})
    for name, cam in _cameras(scene).items():
        p_cam = cam.world_to_camera(torch.float64).numpy() @ np.append(top["center"], 1.0)
        u, v, _ = cam.intrinsics(torch.float64).numpy() @ (p_cam[:3] / p_cam[2])
        col, row = int(np.floor(u)), int(np.floor(v))
        assert 0 <= col < W and 0 <= row < H, name
        depth = np.load(scene / "gt" / "depth" / f"{name}.npy")[row, col]
        assert depth == pytest.approx(p_cam[2], abs=0.1), "ray caster and camera agree on depth"
        s = np.load(scene / "language_features" / f"{name}_s.npy")
        f = np.load(scene / "language_features" / f"{name}_f.npy")
        feature = f[s[2, row, col]]
        best = max(wholes, key=lambda w: float(feature @ embeddings[w]))
        assert best == "table", name
        table_mask = cv2.imread(str(scene / "segmentations" / name / "table.png"), cv2.IMREAD_GRAYSCALE)
        assert table_mask[row, col] == 255


def test_distance_to_surfaces(scene: Path) -> None:
    mesh = o3d.io.read_triangle_mesh(str(scene / "gt" / "mesh.ply"))
    vertices = np.asarray(mesh.vertices)[::97]
    assert np.abs(distance_to_surfaces(scene, vertices)).max() < 1e-5
    mid_air = np.array([[0.0, 0.0, 1.8]])
    assert distance_to_surfaces(scene, mid_air)[0] > 1.0
    top = next(p for p in _primitives(scene) if p["labels"]["subpart"] == "table top")["center"]
    assert distance_to_surfaces(scene, np.array([top]), label="table")[0] < 0.05
    assert distance_to_surfaces(scene, np.array([top]), label="lamp")[0] > 0.5
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        distance_to_surfaces(scene, np.zeros(3))
    # "mug" names the mug at the part and whole levels; "table top" is a subpart, not a whole object.
    mug = next(p for p in _primitives(scene) if p["labels"]["subpart"] == "mug body")["center"]
    assert distance_to_surfaces(scene, np.array([mug]), label="mug", level="whole")[0] < 0.05
    with pytest.raises(ValueError, match="no primitive"):
        distance_to_surfaces(scene, np.array([top]), label="table top", level="whole")
    with pytest.raises(ValueError, match="level must be one of"):
        distance_to_surfaces(scene, np.array([top]), label="table", level="room")


def test_distances_to_objects_equal_the_labelled_distances(scene: Path) -> None:
    points = np.random.default_rng(0).uniform([-2, -0.5, 0], [2, 2, 2], (50, 3))
    labels, dist = distances_to_objects(scene, points)
    assert {"sofa", "mug", "table", "wall", "floor"} <= set(labels) and dist.shape == (len(labels), 50)
    for k, label in enumerate(labels):
        np.testing.assert_allclose(dist[k], distance_to_surfaces(scene, points, label=label, level="whole"))
    np.testing.assert_allclose(dist.min(axis=0), distance_to_surfaces(scene, points), atol=1e-6)
    with pytest.raises(ValueError, match="level"):
        distances_to_objects(scene, points, level="room")


def _area(triangles: np.ndarray) -> float:
    cross = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    return float(np.linalg.norm(cross, axis=1).sum() / 2)


def test_subdividing_keeps_the_area_and_bounds_the_edges() -> None:
    tri = np.array(
        [[[0, 0, 0], [1.0, 0, 0], [0, 0.3, 0.2]], [[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]]], np.float32
    )
    pieces, parent = _subdivide(tri, 0.1)
    assert _area(pieces) == pytest.approx(_area(tri), rel=1e-5)
    edges = np.linalg.norm(pieces - np.roll(pieces, 1, axis=1), axis=2)
    assert edges.max() <= 0.1 + 1e-6
    assert (parent == 1).sum() == 1  # a small triangle stays one piece
    assert _area(pieces[parent == 0]) == pytest.approx(_area(tri[:1]), rel=1e-5)


def test_the_floor_under_the_rug_is_covered_and_a_point_in_the_rug_is_the_rugs(tmp_path) -> None:
    (tmp_path / "gt").mkdir()
    look = ((0.5, 0.5, 0.5), "plain")
    prims = [
        Primitive(_box((4.0, 4.0, 0.05), (0.0, 0.0, -0.025)), ("floor",) * 3, *look),
        Primitive(_box((2.0, 1.0, 0.01), (0.0, 0.0, 0.005)), ("rug",) * 3, *look),
    ]
    write_ground_truth_mesh(tmp_path / "gt", prims)
    floor, rug = uncovered_triangles(tmp_path)
    floor_area = 2 * 16 + 4 * 4 * 0.05
    assert _area(floor) == pytest.approx(floor_area - 2.0, abs=4 * COVER_STEP)  # less the rug's footprint
    rug_area = 2 * 2.0 + 2 * (2.0 + 1.0) * 0.01
    assert rug_area - 2.0 - 0.3 * 0.06 < _area(rug) < rug_area - 2.0  # no bottom, the sides' feet gone
    points = np.array([[0.3, 0.2, 0.004], [1.5, 0.0, 0.001]])  # inside the rug, 4 mm up; beside it
    labels, plain = distances_to_objects(tmp_path, points)
    _, seen = distances_to_objects(tmp_path, points, uncovered=True)
    assert labels == ["floor", "rug"]
    assert plain[:, 0].argmin() == 0  # nearest to the floor under the rug...
    assert seen[:, 0].argmin() == 1 and seen[1, 0] == pytest.approx(0.006, abs=1e-4)  # ...which is hidden
    assert seen[0, 0] == pytest.approx(0.054, abs=1e-4)  # the nearest uncovered floor: the slab's underside
    assert plain[:, 1].argmin() == seen[:, 1].argmin() == 0
    # Seen from above only, the slab's underside faces no camera: a point 3 cm into the slab, under the
    # rug, is then the rug's (4 cm below its top), no longer the underside's (2 cm).
    low = np.array([[0.3, 0.2, -0.03]])
    _, below = distances_to_objects(tmp_path, low, uncovered=True)
    _, above = distances_to_objects(tmp_path, low, uncovered=True, viewpoints=np.array([[0.0, 0.0, 2.0]]))
    assert below[:, 0].argmin() == 0 and below[0, 0] == pytest.approx(0.02, abs=1e-4)
    assert above[:, 0].argmin() == 1 and above[1, 0] == pytest.approx(0.04, abs=1e-4)
    floor_seen, rug_seen = uncovered_triangles(tmp_path, np.array([[0.0, 0.0, 2.0]]))
    assert _area(floor_seen) == pytest.approx(16 - 2.0, abs=4 * COVER_STEP)  # the top less the rug
    assert _area(rug_seen) == pytest.approx(2.0, abs=1e-4)  # the top: straight above, the sides face away


def test_text_embeddings_hold_labels_synonyms_and_canonical_phrases(scene: Path) -> None:
    emb = np.load(scene / "text_embeddings.npz")
    labels = {label for p in _primitives(scene) for label in p["labels"].values()}
    assert labels | set(SYNONYMS) | set(CANONICAL_PHRASES) <= set(emb.files)
    for key in emb.files:
        assert emb[key].shape == (FEATURE_DIM,) and emb[key].dtype == np.float32
        assert np.linalg.norm(emb[key]) == pytest.approx(1.0, abs=1e-5)
    for synonym, word in SYNONYMS.items():
        others = [w for w in labels if w != word]
        assert emb[synonym] @ emb[word] > max(emb[synonym] @ emb[w] for w in others), synonym
    assert emb["sofa cushion"] @ emb["sofa"] > emb["sofa cushion"] @ emb["table"]


def test_scale_scales_geometry_and_cameras(scene: Path, tmp_path: Path) -> None:
    big = make_room(tmp_path / "big", seed=0, width=W, height=H, n_test=0, scale=2.0)
    meta, big_meta = (json.loads((s / "transforms.json").read_text()) for s in (scene, big))
    np.testing.assert_allclose(np.array(big_meta["aabb"]), 2.0 * np.array(meta["aabb"]), atol=1e-9)
    depth, big_depth = (np.load(s / "gt" / "depth" / "train_001.npy") for s in (scene, big))
    np.testing.assert_allclose(big_depth, 2.0 * depth, rtol=1e-4)


def _primitives_digest(prims) -> str:
    h = hashlib.sha256()
    for p in prims:
        h.update((np.round(np.asarray(p.mesh.vertices), 5) + 0.0).tobytes())
        h.update(np.asarray(p.mesh.triangles).astype(np.int64).tobytes())
        h.update((np.round(np.asarray(p.color), 6) + 0.0).tobytes())
        h.update("|".join((*p.labels, p.texture)).encode())
    return h.hexdigest()[:16]


def test_layout_0_is_the_built_in_room_of_before_layouts() -> None:
    # The digest of every primitive (vertices, triangles, colours, labels) of seed 0, taken from the
    # generator before layouts existed (f2bd2d4): layout 0 must stay that room, figure for figure.
    prims = room_primitives(np.random.default_rng([0, 1]), 1.0, layout=0)
    assert _primitives_digest(prims) == LAYOUT_0_DIGEST


def test_layout_0_is_the_built_in_room_at_home() -> None:
    assert [(p.kind, p.size, p.dx, p.dy) for p in room_layout(0)] == [
        (kind, 1.0, 0.0, 0.0) for kind in ("sofa", "table", "lamp", "chair", "shelf")
    ]


def test_every_layout_places_three_or_more_groups() -> None:
    assert min(len(room_layout(k)) for k in range(1, 1201)) >= 3  # 317 once fitted only two


@pytest.mark.parametrize("layout", range(1, 13))
def test_random_layouts_place_three_or_more_groups_on_the_floor_apart(layout: int) -> None:
    placed = room_layout(layout)
    assert placed == room_layout(layout)  # a layout number is one room
    assert len(placed) >= 3 and {p.kind for p in placed} <= {"sofa", "table", "lamp", "chair", "shelf"}
    assert all(0.8 <= p.size <= 1.25 for p in placed)
    for i, a in enumerate(placed):
        lo, hi = a.footprint()
        assert lo[0] >= -1.95 - 1e-9 and hi[0] <= 1.95 + 1e-9 and lo[1] >= -1e-9 and hi[1] <= 1.97 + 1e-9
        for b in placed[i + 1 :]:
            blo, bhi = b.footprint()
            assert np.any(hi < blo) or np.any(bhi < lo), (a, b)  # footprints apart
    assert len({tuple((p.kind, p.dx) for p in room_layout(k)) for k in range(1, 13)}) == 12


def test_a_layout_moves_the_furniture_and_keeps_every_phrase(scene: Path, tmp_path: Path) -> None:
    default = make_room(tmp_path / "default", seed=0, width=W, height=H, n_test=0, layout=0)
    assert _arrays(default, "train_000")["image"].tobytes() == _arrays(scene, "train_000")["image"].tobytes()
    moved = make_room(tmp_path / "moved", seed=0, width=W, height=H, n_test=0, layout=2)
    assert not np.array_equal(_arrays(scene, "train_000")["image"], _arrays(moved, "train_000")["image"])
    kinds = {p.kind for p in room_layout(2)}
    wholes = {p["labels"]["whole"] for p in _primitives(moved)}
    assert wholes == kinds | {"floor", "wall", "rug", *(("mug", "book") if "table" in kinds else ())}
    assert {"sofa", "lamp", "shelf", "mug", "couch"} <= set(np.load(moved / "text_embeddings.npz").files)
    meta = json.loads((moved / "transforms.json").read_text())
    assert meta["generator"]["layout"] == 2
    for p in _primitives(moved):  # every piece of furniture stands on or above the floor, inside the walls
        lo, hi = np.asarray(p["aabb"])
        assert lo[2] >= -0.06 and lo[0] >= -2.06 and hi[1] <= 2.06, p["labels"]


def test_bad_arguments_are_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="image size"):
        make_room(tmp_path, width=4, height=48)
    with pytest.raises(ValueError, match="n_train"):
        make_room(tmp_path, n_train=0)
    with pytest.raises(ValueError, match="scale"):
        make_room(tmp_path, scale=0.0)
    with pytest.raises(ValueError, match="layout"):
        make_room(tmp_path, layout=-1)
