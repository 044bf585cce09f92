"""The standard 3DGS PLY (as written by the reference 3DGS code and read by common 3DGS viewers).

Properties, all float32, little endian: ``x y z nx ny nz f_dc_0..2 f_rest_0..44 opacity scale_0..2
rot_0..3``. Colours go into the degree-0 spherical-harmonic coefficient (``f_dc = (rgb - 0.5) / C0``);
the higher-order ``f_rest`` are zero because our view dependence lives in the colour MLP. ``opacity``
holds logits, ``scale_*`` log scales and ``rot_*`` the quaternion (w, x, y, z), as 3DGS stores them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from langfield.atomic import atomic_path
from langfield.io.layout import SceneError

SH_C0 = 0.28209479177387814
N_REST = 45  # degree-3 SH: 15 coefficients x 3 colours


def _fields() -> list[str]:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(N_REST)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def read_points(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A point cloud PLY (x y z, optional red green blue), such as ``sparse_pc.ply``: ([P, 3] float32
    points, [P, 3] float32 colours in [0, 1], grey where the file has none); read with Open3D.

    Raises:
        SceneError: the file is missing, unreadable, empty or holds non-finite points.
    """
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: point cloud not found")
    cloud = o3d.io.read_point_cloud(str(path))
    points = np.asarray(cloud.points, dtype=np.float32)
    if len(points) == 0:
        raise SceneError(f"{path}: no points could be read (not a point cloud PLY, or empty)")
    if not np.isfinite(points).all():
        raise SceneError(f"{path}: has NaN or inf coordinates")
    colors = np.asarray(cloud.colors, dtype=np.float32) if cloud.has_colors() else np.full_like(points, 0.5)
    return points, colors


def write_gaussian_ply(
    path: str | Path,
    means: np.ndarray,
    rgb: np.ndarray,
    opacity_logits: np.ndarray,
    log_scales: np.ndarray,
    quats: np.ndarray,
) -> None:
    """Writes Gaussians as a binary 3DGS PLY, atomically.

    Args:
        means: [N, 3]; rgb: [N, 3] in [0, 1]; opacity_logits: [N] or [N, 1]; log_scales: [N, 3];
        quats: [N, 4] (w, x, y, z).
    """
    n = means.shape[0]
    names = _fields()
    data = np.zeros((n, len(names)), dtype="<f4")
    data[:, 0:3] = means
    data[:, 6:9] = (np.asarray(rgb) - 0.5) / SH_C0
    base = 9 + N_REST
    data[:, base] = np.asarray(opacity_logits).reshape(n)
    data[:, base + 1 : base + 4] = log_scales
    data[:, base + 4 : base + 8] = quats
    header = "ply\nformat binary_little_endian 1.0\n"
    header += f"element vertex {n}\n"
    header += "".join(f"property float {name}\n" for name in names)
    header += "end_header\n"
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(data.tobytes())


def read_gaussian_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Reads a binary little-endian 3DGS PLY into {property name: [N] float32 array}."""
    path = Path(path)
    with open(path, "rb") as f:
        raw = f.read()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file")
    header = raw[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError(f"{path}: only binary little-endian PLY is supported")
    n = next(int(line.split()[2]) for line in header if line.startswith("element vertex"))
    props = [line.split()[2] for line in header if line.startswith("property float")]
    body = np.frombuffer(raw[end + len(b"end_header\n") :], dtype="<f4")
    if body.size != n * len(props):
        raise ValueError(f"{path}: expected {n} vertices of {len(props)} floats, found {body.size} floats")
    table = body.reshape(n, len(props))
    return {name: table[:, i].copy() for i, name in enumerate(props)}
