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
