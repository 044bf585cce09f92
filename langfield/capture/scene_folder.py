"""Writing one posed model as an ordinary scene folder (docs/format.md): ``images/``,
``transforms.json`` in the nerfstudio convention and the sparse points as ``sparse_pc.ply``.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from langfield.capture.poses import PoseModel
from langfield.capture.views import Normalisation
from langfield.constants import IMAGES_DIR, POINTS_FILE, TRANSFORMS_FILE

__all__ = ["write_points", "write_scene"]

_DISTORTION = ("k1", "k2", "p1", "p2")


def _intrinsics(camera: dict) -> dict:
    """transforms.json's keys of one OPENCV camera (fx fy cx cy k1 k2 p1 p2)."""
    fx, fy, cx, cy, *dist = camera["params"]
    keys = {"w": camera["width"], "h": camera["height"], "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy}
    keys.update(zip(_DISTORTION, dist, strict=True))
    return keys


def write_points(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    """The sparse points as a binary PLY (x y z float, red green blue uchar), as nerfstudio's
    ``sparse_pc.ply``; written with Open3D."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.asarray(points, np.float64).reshape(-1, 3))
    cloud.colors = o3d.utility.Vector3dVector(np.asarray(colors, np.float64).reshape(-1, 3) / 255.0)
    if not o3d.io.write_point_cloud(str(path), cloud, write_ascii=False):
        raise OSError(f"{path}: Open3D could not write the point cloud")


def write_scene(
    folder: Path,
    model: PoseModel,
    normalisation: Normalisation,
    train: Sequence[str],
    frames_dir: Path,
    stems: dict[str, str],
) -> dict:
    """Writes ``model`` as a scene in ``folder`` (new); ``train`` are file names of training views,
    every other registered frame is a test view. ``stems`` maps file names to frame names.

    Returns:
        What the report records: {"train", "test", "points", "shared_camera"}.
    """
    (folder / IMAGES_DIR).mkdir(parents=True)
    shared = len({json.dumps(c) for c in model.cameras.values()}) == 1
    meta: dict = {"camera_model": "OPENCV"}
    if shared:
        meta.update(_intrinsics(next(iter(model.cameras.values()))))
    fallback = _overall_range(model)
    frames = []
    for name in model.names:
        shutil.copyfile(frames_dir / name, folder / IMAGES_DIR / name)
        near, far = model.depth_range.get(name, fallback)
        frame = {
            "file_path": f"{IMAGES_DIR}/{name}",
            "transform_matrix": normalisation.camera_to_world(model.cam_from_world[name]).tolist(),
            "split": "train" if name in train else "test",
            # The LLFF near and far of the frame (its points' depths), in the scene's units.
            "near": near * normalisation.scale,
            "far": far * normalisation.scale,
        }
        if not shared:
            frame.update(_intrinsics(model.cameras[name]))
        frames.append(frame)
    meta["ply_file_path"] = POINTS_FILE
    meta["frames"] = frames
    (folder / TRANSFORMS_FILE).write_text(json.dumps(meta, indent=2))
    write_points(folder / POINTS_FILE, normalisation.points(model.points), model.colors)
    return {
        "train": [stems[n] for n in model.names if n in train],
        "test": [stems[n] for n in model.names if n not in train],
        "points": len(model.points),
        "shared_camera": shared,
    }


def _overall_range(model: PoseModel) -> tuple[float, float]:
    """(nearest near, farthest far) over the frames, for a frame that observes no point."""
    if model.depth_range:
        ranges = np.array(list(model.depth_range.values()))
        return float(ranges[:, 0].min()), float(ranges[:, 1].max())
    return 0.1, 100.0
