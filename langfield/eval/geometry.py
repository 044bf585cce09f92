"""Geometry figures for scenes that know their ground truth (the built-in synthetic scene).

- :func:`aligned_depth_error`: novel-view depth error after a per-view least-squares scale-and-shift fit
  to the true depth (monocular priors and sparse-view renders agree with the truth only up to those);
- :func:`count_floaters`: Gaussians whose centre lies farther than a tolerance from every true surface;
- :func:`observed_fraction`: how much of a test view shows surfaces some training view sees;
- :func:`depth_agreement` (any scene, no ground truth needed): whether the training views' rendered
  depths describe one surface, each view's surface reprojected into the others.

Both are used by ``langfield ablate`` to show what LAD and LOP change (issue: depth distillation and
outlier pruning). Scenes without ``gt/`` give ``None``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from encoders.protocols import TextEncoder
from langfield.camera import Camera
from langfield.field import LanguageField
from langfield.io.scene import Scene

FLOATER_TOLERANCE = 0.03  # x the scene bounds' diagonal: farther from every surface is a floater
# x the bounds' diagonal (about 6 cm in the built-in room): a Gaussian belongs to the object whose surface
# is nearest to its centre when that surface is within this distance (the mug is 9 cm across).
SELECTION_TOLERANCE = 0.01
MIN_ALPHA = 0.5  # pixels the render covers less than this are left out of the depth error


def ray_lengths(camera: Camera) -> np.ndarray:
    """[H, W] length of the camera-space ray through each pixel centre with z = 1."""
    u = (np.arange(camera.width) + 0.5 - camera.cx) / camera.fx
    v = (np.arange(camera.height) + 0.5 - camera.cy) / camera.fy
    return np.sqrt(1.0 + u[None, :] ** 2 + v[:, None] ** 2)


def aligned_depth_error(
    rendered: np.ndarray, alpha: np.ndarray, gt_distance: np.ndarray, min_alpha: float = MIN_ALPHA
) -> dict[str, float] | None:
    """Depth error after fitting ``a * rendered + b`` to the truth by least squares.

    Args:
        rendered: [H, W] soft depth (alpha-blended distance to the camera centre).
        alpha: [H, W] accumulated opacity; the depth is divided by it (the blend's weights sum to alpha).
        gt_distance: [H, W] true distance to the camera centre; 0 or non-finite where there is none.
        min_alpha: pixels with less coverage are skipped.

    Returns:
        {"abs_rel": mean |fit - gt| / gt, "mae": mean |fit - gt| (scene units), "pixels": count}, or
        None when fewer than 10 pixels qualify.
    """
    valid = np.isfinite(gt_distance) & (gt_distance > 0) & (alpha >= min_alpha) & np.isfinite(rendered)
    if valid.sum() < 10:
        return None
    d = (rendered[valid] / alpha[valid]).astype(np.float64)
    g = gt_distance[valid].astype(np.float64)
    design = np.stack([d, np.ones_like(d)], axis=1)
    (a, b), *_ = np.linalg.lstsq(design, g, rcond=None)
    err = np.abs(a * d + b - g)
    return {"abs_rel": float(np.mean(err / g)), "mae": float(np.mean(err)), "pixels": int(valid.sum())}


def _true_depth(path: Path, camera: Camera) -> np.ndarray:
    """[H, W] float64 ground-truth z-depth of a view, resized (nearest) to the camera's resolution."""
    z = np.load(path).astype(np.float64)
    if z.shape != (camera.height, camera.width):
        import cv2

        z = cv2.resize(z, (camera.width, camera.height), interpolation=cv2.INTER_NEAREST)
    return z


def depth_errors(field: LanguageField, scene: Scene, split: str = "test") -> dict | None:
    """Per-view and mean aligned depth error on ``split``; None without ``gt/depth/``."""
    folder = Path(scene.root) / "gt" / "depth"
    if not folder.is_dir():
        return None
    views = {}
    with torch.no_grad():
        for name in scene.names(split):
            path = folder / f"{name}.npy"
            if not path.is_file():
                continue
            cam = scene.camera(name)
            gt_z = _true_depth(path, cam).astype(np.float32)
            out = field.render(cam)
            err = aligned_depth_error(out.depth.numpy(), out.alpha.numpy(), gt_z * ray_lengths(cam))
            if err is not None:
                views[name] = err
    if not views:
        return None
    return {
        "abs_rel": float(np.mean([v["abs_rel"] for v in views.values()])),
        "mae": float(np.mean([v["mae"] for v in views.values()])),
        "views": views,
    }


def count_floaters(field: LanguageField, scene: Scene, tolerance: float = FLOATER_TOLERANCE) -> dict | None:
    """Gaussians farther than ``tolerance`` x the bounds' diagonal from every true surface.

    Returns:
        {"floaters": count, "fraction": of all Gaussians, "tolerance": in scene units}, or None when the
        scene has no ``gt/mesh.ply``.
    """
    if not (Path(scene.root) / "gt" / "mesh.ply").is_file():
        return None
    from langfield.synthetic import distance_to_surfaces

    bounds = field.meta.bounds
    tol = float(tolerance * np.linalg.norm(bounds[1] - bounds[0]))
    means = field.splats["means"].detach().numpy()
    dist = distance_to_surfaces(scene.root, means)
    count = int((dist > tol).sum())
    return {"floaters": count, "fraction": count / max(len(means), 1), "tolerance": tol}


def selection_scores(
    field: LanguageField,
    scene: Scene,
    tolerance: float = SELECTION_TOLERANCE,
    text_encoder: TextEncoder | str | Path | None = None,
) -> dict | None:
    """Precision and recall of the 3D text selection (``field.query(o).gaussians()``) of each object o.

    Each whole-level object of the scene's ``gt/primitives.json`` is queried by its name. The object's
    Gaussians are those whose centre's nearest true surface is one of the object's, within
    ``tolerance`` x the bounds' diagonal (OpenGaussian and Dr.Splat score 3D queries against the
    objects' geometry the same way). Only surfaces a camera could see count
    (:func:`langfield.synthetic.ground_truth.uncovered_triangles`): not those another primitive covers
    (the floor under the rug, 1 cm below its top: a Gaussian on the rug is the rug's), nor faces turned
    away from every camera of the scene (the floor slab's underside, 5 cm under the floor).

    Precision: the fraction of the selected Gaussians that are the object's (0 for an empty
    selection); recall: the fraction of the object's Gaussians selected. Surface precision: the same
    fraction of the selected Gaussians that lie on some surface, so that it scores the language alone;
    the Gaussians farther than the tolerance from every surface (a matter of geometry: no choice of
    latents puts them on an object) are counted apart, ``off_surface``.
    ``text_encoder`` embeds the object names (default the field's own; see ``LanguageField.query``).

    Returns:
        {"precision", "recall", "surface_precision" (means over the objects that have Gaussians),
        "off_surface" (the fraction of all Gaussians on no surface), "tolerance" (scene units),
        "objects": {name: {"precision", "recall", "surface_precision", "selected", "gaussians"}}};
        None when the scene has no ``gt/primitives.json`` or the field no language.
    """
    gt = Path(scene.root) / "gt"
    if not (gt / "primitives.json").is_file() or field.decoder is None or not field.has_language:
        return None
    from langfield.synthetic import distances_to_objects

    bounds = field.meta.bounds
    tol = float(tolerance * np.linalg.norm(bounds[1] - bounds[0]))
    means = field.splats["means"].detach().numpy()
    viewpoints = np.stack([cam.center for cam in scene.cameras("all")])
    objects, dist = distances_to_objects(
        scene.root, means, level="whole", uncovered=True, viewpoints=viewpoints
    )
    owner = np.where(dist.min(axis=0) <= tol, dist.argmin(axis=0), -1) if len(means) else np.zeros(0, int)
    selections = field.query(objects, text_encoder, scene=scene).gaussians()
    per_object: dict[str, dict[str, float | int | None]] = {}
    for k, (name, sel) in enumerate(zip(objects, selections, strict=True)):
        chosen = np.zeros(len(means), dtype=bool)
        chosen[sel.indices.numpy()] = True
        mine = owner == k
        hits = int((chosen & mine).sum())
        on_surface = int((chosen & (owner >= 0)).sum())
        per_object[name] = {
            "precision": hits / int(chosen.sum()) if chosen.any() else 0.0,
            "recall": hits / int(mine.sum()) if mine.any() else None,
            "surface_precision": hits / on_surface if on_surface else 0.0,
            "selected": int(chosen.sum()),
            "gaussians": int(mine.sum()),
        }
    scored = [v for v in per_object.values() if v["recall"] is not None]

    def mean(key: str) -> float | None:
        return float(np.mean([v[key] for v in scored])) if scored else None

    return {
        "precision": mean("precision"),
        "recall": mean("recall"),
        "surface_precision": mean("surface_precision"),
        "off_surface": float((owner < 0).mean()) if len(means) else 0.0,
        "tolerance": tol,
        "objects": per_object,
    }


def observed_fraction(scene: Scene, split: str = "test", tolerance: float = 0.02) -> dict | None:
    """How much of each ``split`` view shows a surface that some training view sees.

    Every pixel with a true depth is lifted to its surface point, projected into each training view,
    and counts as observed where it lands inside that image in front of the camera and within
    ``tolerance`` (relative) of the training view's own true depth there (not occluded). Separates
    "the test view shows what no training view saw" from "the reconstruction of what was seen is wrong".

    Returns:
        ``{"mean": fraction, "views": {name: fraction}}``, or None without ``gt/depth/``.
    """
    folder = Path(scene.root) / "gt" / "depth"
    train = scene.names("train")
    if not folder.is_dir() or not all((folder / f"{n}.npy").is_file() for n in train):
        return None
    # The witnesses: each training view's camera, world-to-camera matrix and true depth, read once.
    witnesses = []
    for other in train:
        oc = scene.camera(other)
        witnesses.append(
            (oc, oc.world_to_camera(torch.float64).numpy(), _true_depth(folder / f"{other}.npy", oc))
        )
    views = {}
    for name in scene.names(split):
        path = folder / f"{name}.npy"
        if not path.is_file():
            continue
        cam = scene.camera(name)
        z = _true_depth(path, cam)
        v, u = np.mgrid[0 : cam.height, 0 : cam.width] + 0.5
        valid = (np.isfinite(z) & (z > 0)).reshape(-1)
        cam_pts = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z, np.ones_like(z)], -1)
        world = cam_pts.reshape(-1, 4) @ np.linalg.inv(cam.world_to_camera(torch.float64).numpy()).T
        seen = np.zeros(len(world), dtype=bool)
        for oc, w2c, oz in witnesses:
            q = world @ w2c.T
            depth = q[:, 2]
            front = depth > 1e-6
            safe = np.where(front, depth, 1.0)
            col = np.floor(oc.fx * q[:, 0] / safe + oc.cx)
            row = np.floor(oc.fy * q[:, 1] / safe + oc.cy)
            inside = front & (col >= 0) & (col < oc.width) & (row >= 0) & (row < oc.height)
            ci = np.clip(col, 0, oc.width - 1).astype(np.int64)
            ri = np.clip(row, 0, oc.height - 1).astype(np.int64)
            seen |= inside & (np.abs(oz[ri, ci] - depth) <= tolerance * depth)
        if valid.any():
            views[name] = float(seen[valid].mean())
    if not views:
        return None
    return {"mean": float(np.mean(list(views.values()))), "views": views}


def depth_agreement(
    field: LanguageField, scene: Scene, split: str = "train", rel: float = 0.02, min_alpha: float = MIN_ALPHA
) -> dict | None:
    """Multi-view coherence of the rendered depth, with no ground truth: every pixel a view covers
    (alpha >= ``min_alpha``) is lifted to its rendered surface point (depth / alpha) and projected into
    every other view of ``split``; it agrees where it lands inside that image on a covered pixel whose
    rendered z-depth is within ``rel`` (relative) of the point's. Three views fitted with incoherent
    depth each agree with themselves only; one surface seen three times agrees up to occlusions.

    Returns:
        ``{"agreement": agreeing / landed, "landed": pixels that landed in a covered pixel of another
        view}``, or None with fewer than two views or nothing covered.
    """
    names = scene.names(split)
    if len(names) < 2:
        return None
    cams = [scene.camera(n) for n in names]
    z_maps, covered = [], []
    with torch.no_grad():
        for cam in cams:
            out = field.render(cam)
            alpha = out.alpha.numpy().astype(np.float64)
            distance = out.depth.numpy().astype(np.float64) / np.maximum(alpha, 1e-6)
            z_maps.append(distance / ray_lengths(cam))
            covered.append(alpha >= min_alpha)
    agree = landed = 0
    for i, cam in enumerate(cams):
        rows, cols = np.nonzero(covered[i])
        z = z_maps[i][rows, cols]
        # Pixel centres at z-depth z in OpenCV camera space, then world space.
        cam_points = np.stack(
            [(cols + 0.5 - cam.cx) / cam.fx * z, (rows + 0.5 - cam.cy) / cam.fy * z, z, np.ones_like(z)],
            axis=1,
        )
        world = cam_points @ np.linalg.inv(cam.world_to_camera(torch.float64).numpy()).T
        for j, other in enumerate(cams):
            if i == j:
                continue
            p = world @ other.world_to_camera(torch.float64).numpy().T
            depth = p[:, 2]
            front = depth > 1e-9
            u = np.floor(other.fx * p[front, 0] / depth[front] + other.cx).astype(np.int64)
            v = np.floor(other.fy * p[front, 1] / depth[front] + other.cy).astype(np.int64)
            depth = depth[front]
            inside = (u >= 0) & (v >= 0) & (u < other.width) & (v < other.height)
            u, v, depth = u[inside], v[inside], depth[inside]
            hit = covered[j][v, u]
            landed += int(hit.sum())
            agree += int((np.abs(z_maps[j][v, u][hit] - depth[hit]) <= rel * depth[hit]).sum())
    if landed == 0:
        return None
    return {"agreement": agree / landed, "landed": landed}
