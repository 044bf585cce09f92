"""The room's ground truth (``gt/``): the mesh with each triangle's primitive, and distances from
points to the surfaces of objects.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import open3d as o3d

from encoders.protocols import LEVELS
from langfield.synthetic.room import Primitive


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
        >>> from langfield.synthetic import make_room
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
    scene_dir: str | Path,
    points: np.ndarray,
    level: str = "whole",
    uncovered: bool = False,
    viewpoints: np.ndarray | None = None,
) -> tuple[list[str], np.ndarray]:
    """Unsigned distance from each point to each object's true surface, the objects being the labels
    of one level (e.g. every whole-level object: "sofa", "mug", ...).

    With ``uncovered`` only the surface no other primitive covers counts (:func:`uncovered_triangles`):
    a point on the rug, 1 cm above the floor, is then nearest to the rug, not to the floor under it;
    with ``viewpoints`` too, only the faces that face one of them.

    Returns:
        (the labels, sorted; [K, N] float32 distances, row k to the primitives labelled k).
    """
    gt = Path(scene_dir) / "gt"
    if level not in LEVELS:
        raise ValueError(f"distances_to_objects: level must be one of {LEVELS}, got {level!r}")
    pts = _check_points(points, "distances_to_objects")
    records = json.loads((gt / "primitives.json").read_text())
    labels = sorted({r["labels"][level] for r in records})
    surfaces = uncovered_triangles(scene_dir, viewpoints) if uncovered else _primitive_triangles(gt, records)
    rows = [
        _soup_distances(
            np.concatenate([t for t, r in zip(surfaces, records, strict=True) if r["labels"][level] == k]),
            pts,
        )
        for k in labels
    ]
    return labels, np.stack(rows) if rows else np.zeros((0, len(pts)), np.float32)


# A surface point this close to another primitive's surface is covered by it: a contact face (the floor
# under the rug or the sofa, a table top under a book, a box face inside a wall) that no camera sees.
COVER_DISTANCE = 0.002
# The longest edge of the pieces each triangle is cut into to find its covered part (scene units).
COVER_STEP = 0.025


def uncovered_triangles(scene_dir: str | Path, viewpoints: np.ndarray | None = None) -> list[np.ndarray]:
    """Per primitive of ``gt/primitives.json``, ``[M, 3, 3]`` float32: its surface less the part within
    :data:`COVER_DISTANCE` of another primitive's surface (covered, see there). A triangle that comes
    near another primitive is first cut into pieces of edges up to :data:`COVER_STEP`, and each piece is
    kept or dropped by its centre. With ``viewpoints`` ``[V, 3]`` (the scene's camera centres), pieces
    that face away from every one are dropped too: the floor slab's underside, a wall's outer face
    (the primitives' triangles wind outwards)."""
    gt = Path(scene_dir) / "gt"
    records = json.loads((gt / "primitives.json").read_text())
    triangles = _primitive_triangles(gt, records)
    lows = np.array([r["aabb"][0] for r in records]) - COVER_DISTANCE
    highs = np.array([r["aabb"][1] for r in records]) + COVER_DISTANCE
    out = []
    for i, tris in enumerate(triangles):
        # [T_i, P]: the triangle's box meets another primitive's (grown by COVER_DISTANCE).
        near = (tris.min(axis=1)[:, None] <= highs[None]).all(-1) & (
            tris.max(axis=1)[:, None] >= lows[None]
        ).all(-1)
        near[:, i] = False
        touching = near.any(axis=1)
        cut, parent = _subdivide(tris[touching], COVER_STEP)
        centres = cut.mean(axis=1)
        covered = np.zeros(len(cut), dtype=bool)
        for j in np.flatnonzero(near.any(axis=0)):
            inside = np.flatnonzero(((centres >= lows[j]) & (centres <= highs[j])).all(axis=1))
            if len(inside):  # only centres inside the other primitive's box can lie that close to it
                gap = _soup_distances(triangles[j], centres[inside])
                covered[inside[gap <= COVER_DISTANCE]] = True
        hit = np.zeros(int(touching.sum()), dtype=bool)  # a triangle none of whose pieces is covered
        hit[parent[covered]] = True  # stays whole
        kept = np.concatenate([tris[~touching], tris[touching][~hit], cut[~covered & hit[parent]]])
        if viewpoints is not None and len(kept):
            normal = np.cross(kept[:, 1] - kept[:, 0], kept[:, 2] - kept[:, 0])
            towards = np.asarray(viewpoints, np.float32)[None] - kept.mean(axis=1)[:, None]  # [M, V, 3]
            kept = kept[((towards * normal[:, None]).sum(-1) > 0).any(axis=1)]
        out.append(kept)
    return out


def _primitive_triangles(gt: Path, records: list[dict]) -> list[np.ndarray]:
    """Per primitive of ``records``, ``[T, 3, 3]`` float32: its triangles' corners in ``gt/mesh.ply``."""
    mesh = o3d.io.read_triangle_mesh(str(gt / "mesh.ply"))
    corners = np.asarray(mesh.vertices, dtype=np.float32)[np.asarray(mesh.triangles)]
    return [corners[slice(*r["triangles"])] for r in records]


def _subdivide(triangles: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """``[T, 3, 3]`` triangles -> ``[M, 3, 3]`` pieces and ``[M]`` the index of each piece's triangle:
    each cut into n x n similar triangles, n the smallest count that makes every edge at most
    ``step``."""
    pieces, parents = [], []
    for k, (a, b, c) in enumerate(triangles):
        longest = max(np.linalg.norm(b - a), np.linalg.norm(c - a), np.linalg.norm(c - b))
        n = max(1, int(np.ceil(longest / step)))
        steps = np.arange(n + 1)
        grid = (
            a + steps[:, None, None] * ((b - a) / n) + steps[None, :, None] * ((c - a) / n)
        )  # [n+1, n+1, 3]
        i, j = (g.ravel() for g in np.meshgrid(np.arange(n), np.arange(n), indexing="ij"))
        up = i + j <= n - 1  # corners (i, j), (i + 1, j), (i, j + 1)
        down = i + j <= n - 2  # corners (i + 1, j), (i + 1, j + 1), (i, j + 1)
        iu, ju, id_, jd = i[up], j[up], i[down], j[down]
        pieces.append(np.stack([grid[iu, ju], grid[iu + 1, ju], grid[iu, ju + 1]], axis=1))
        pieces.append(np.stack([grid[id_ + 1, jd], grid[id_ + 1, jd + 1], grid[id_, jd + 1]], axis=1))
        parents.append(np.full(int(up.sum() + down.sum()), k))
    if not pieces:
        return np.zeros((0, 3, 3), np.float32), np.zeros(0, np.int64)
    return np.concatenate(pieces).astype(np.float32), np.concatenate(parents)


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


def _soup_distances(triangles: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """[N] float32 distance from ``pts`` to ``triangles`` ``[T, 3, 3]`` (inf when there are none)."""
    if len(triangles) == 0:
        return np.full(len(pts), np.inf, np.float32)
    raycaster = o3d.t.geometry.RaycastingScene()
    vertices = o3d.core.Tensor(triangles.reshape(-1, 3).astype(np.float32))
    indices = o3d.core.Tensor(np.arange(3 * len(triangles), dtype=np.uint32).reshape(-1, 3))
    raycaster.add_triangles(vertices, indices)
    return raycaster.compute_distance(o3d.core.Tensor(pts)).numpy().astype(np.float32)


def write_ground_truth_mesh(gt: Path, prims: list[Primitive]) -> None:
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
