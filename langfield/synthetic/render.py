"""Ray casting the room with Open3D: depth, primitive ids and a shaded, textured RGB, and the
distorted disparity prior a monocular model would give.
"""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d

from langfield.camera import Camera
from langfield.synthetic.room import Primitive

_SUPERSAMPLE = 2  # RGB is averaged over 2x2 rays per pixel; labels and depth use the pixel centre
_LIGHT_DIR = np.array([0.45, -0.7, 1.0]) / np.linalg.norm([0.45, -0.7, 1.0])
_AMBIENT, _DIFFUSE = 0.42, 0.58
_BACKGROUND_Z = 12.0  # metres (times scale): where the depth prior puts rays that hit nothing
_MISS = np.uint32(0xFFFFFFFF)  # Open3D's geometry id for a ray that hits nothing


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


def render_depth_ids(raycaster: o3d.t.geometry.RaycastingScene, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """True z-depth [H, W] float32 (0 = background) and primitive index [H, W] int16 (-1 = background)."""
    _, hits = _cast(raycaster, cam)
    miss = hits["geometry_ids"] == _MISS
    depth = np.where(miss, 0.0, hits["t_hit"]).astype(np.float32)
    ids = np.where(miss, -1, hits["geometry_ids"].astype(np.int64)).astype(np.int16)
    return depth, ids


def render_rgb(
    raycaster: o3d.t.geometry.RaycastingScene, cam: Camera, prims: list[Primitive], phases: np.ndarray
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


def depth_prior(depth: np.ndarray, rng: np.random.Generator, scale: float) -> np.ndarray:
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
