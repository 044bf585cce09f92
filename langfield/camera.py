"""Pinhole cameras.

A :class:`Camera` holds intrinsics in pixels and a camera-to-world pose in the OpenGL convention
(x right, y up, the camera looks down -z), as nerfstudio and the Blender NeRF data store it. The
rasterizer works in the OpenCV convention (x right, y down, z forward);
:meth:`Camera.world_to_camera` does the conversion.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import torch

_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


# A pose's rotation block may be off a rotation by float rounding of stored poses (float32 files: about
# 1e-7), not by more: a scaled or sheared block makes every projection wrong without an error.
ROTATION_TOLERANCE = 1e-4
# Focal lengths between 1/20 and 100 image sizes (fields of view of about 170 down to 0.6 degrees), the
# two within a factor 4 of each other, the principal point inside the image: outside these a value parsed
# but is not a camera's.
FOCAL_RANGE = (0.05, 100.0)
MAX_ASPECT = 4.0


def camera_spacing(centres: np.ndarray) -> float:
    """The mean pairwise distance of [C, 3] camera centres; 0 for fewer than two."""
    if len(centres) < 2:
        return 0.0
    i, j = np.triu_indices(len(centres), k=1)
    return float(np.linalg.norm(centres[i] - centres[j], axis=1).mean())


def box_corners(box: np.ndarray) -> np.ndarray:
    """[8, 3] the corners of the axis-aligned box [[xmin, ymin, zmin], [xmax, ymax, zmax]]."""
    return np.array([[box[i][0], box[j][1], box[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])


def _check_pose(name: str, c2w: np.ndarray) -> None:
    """Refuses a camera-to-world matrix that is not a rigid motion, with a hint at what it looks like."""
    if np.abs(c2w[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        raise ValueError(
            f"camera {name!r}: the pose's bottom row must be 0 0 0 1, got {np.round(c2w[3], 6).tolist()} "
            "(a transposed matrix?)"
        )
    r = c2w[:3, :3]
    gram = r.T @ r
    error = float(np.abs(gram - np.eye(3)).max())
    if error > ROTATION_TOLERANCE:
        scales = np.sqrt(np.diag(gram))
        off_diagonal = float(np.abs(gram - np.diag(np.diag(gram))).max())
        if off_diagonal <= ROTATION_TOLERANCE * scales.max() ** 2 and np.ptp(scales) <= 1e-3 * scales.max():
            hint = (
                f"it is a rotation scaled by {scales.mean():.6g}: a scene's scale belongs in the translation"
            )
        else:
            hint = "its columns are not orthonormal"
        raise ValueError(
            f"camera {name!r}: the pose's rotation block is not a rotation (R^T R differs from I by "
            f"{error:.2g}); {hint}"
        )
    if np.linalg.det(r) < 0:
        raise ValueError(
            f"camera {name!r}: the pose's rotation is a reflection (determinant -1): one axis is flipped; "
            "poses are camera-to-world with x right, y up, z back (OpenGL), not OpenCV's y down, z forward"
        )


def _check_intrinsics(name: str, width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> None:
    """Refuses intrinsics that parse but cannot belong to this image size (module constants)."""
    size = max(width, height)
    low, high = FOCAL_RANGE[0] * size, FOCAL_RANGE[1] * size
    for key, focal in (("fx", fx), ("fy", fy)):
        if not low <= focal <= high:
            raise ValueError(
                f"camera {name!r}: {key} {focal:g} pixels is outside [{low:g}, {high:g}] for a "
                f"{width}x{height} image (a focal length in millimetres, or for another image size?)"
            )
    if max(fx / fy, fy / fx) > MAX_ASPECT:
        raise ValueError(f"camera {name!r}: fx {fx:g} and fy {fy:g} differ by more than {MAX_ASPECT:g}x")
    if not (0.0 <= cx <= width and 0.0 <= cy <= height):
        raise ValueError(
            f"camera {name!r}: principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} image"
        )


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera.

    Attributes:
        name: the view's name (its image file name without extension), or "" for a free camera.
        width, height: image size in pixels.
        fx, fy, cx, cy: intrinsics in pixels.
        c2w: [4, 4] camera-to-world matrix, OpenGL convention, float64.

    Example:
        >>> cam = Camera.look_at(eye=(2, 0, 1), target=(0, 0, 0), width=160, height=120, fov_x_deg=60)
        >>> cam.world_to_camera().shape
        torch.Size([4, 4])
    """

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    c2w: np.ndarray = field(repr=False)

    def __post_init__(self) -> None:
        c2w = np.asarray(self.c2w, dtype=np.float64)
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
        if c2w.shape != (4, 4):
            raise ValueError(f"camera {self.name!r}: c2w must be 4x4 or 3x4, got shape {c2w.shape}")
        if not np.isfinite(c2w).all():
            raise ValueError(f"camera {self.name!r}: pose has NaN or inf entries")
        if not (self.width >= 1 and self.height >= 1):
            raise ValueError(
                f"camera {self.name!r}: image size must be positive, got {self.width}x{self.height}"
            )
        intr = np.array([self.fx, self.fy, self.cx, self.cy], dtype=np.float64)
        if not np.isfinite(intr).all() or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"camera {self.name!r}: focal lengths must be positive and finite")
        _check_pose(self.name, c2w)
        _check_intrinsics(self.name, self.width, self.height, self.fx, self.fy, self.cx, self.cy)
        object.__setattr__(self, "c2w", c2w)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def center(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        return self.c2w[:3, 3].copy()

    @property
    def forward(self) -> np.ndarray:
        """[3] unit viewing direction in world coordinates."""
        d = -self.c2w[:3, 2]
        return d / max(np.linalg.norm(d), 1e-12)

    def world_to_camera(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """[4, 4] world-to-camera matrix in the OpenCV convention (x right, y down, z forward)."""
        w2c = _GL_TO_CV @ np.linalg.inv(self.c2w)
        return torch.as_tensor(w2c, dtype=dtype)

    def intrinsics(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """[3, 3] pinhole matrix K."""
        k = [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]]
        return torch.tensor(k, dtype=dtype)

    def pose_cv(self) -> tuple[np.ndarray, np.ndarray]:
        """(R [3, 3], t [3]) world -> camera in the OpenCV convention, float64: the start works in
        metres across rooms, where float32 poses lose the millimetres its depth checks compare."""
        w2c = self.world_to_camera(dtype=torch.float64).numpy()
        return w2c[:3, :3], w2c[:3, 3]

    def pixel_rays(
        self, rows: np.ndarray | None = None, cols: np.ndarray | None = None, dtype: torch.dtype | None = None
    ) -> np.ndarray | torch.Tensor:
        """Camera-frame directions (x, y, 1) through pixel centres (OpenCV frame; pixel (r, c) spans
        [c, c + 1) x [r, r + 1), its centre at + 0.5): [H, W, 3] for every pixel, or [N, 3] for
        ``rows``, ``cols``. NumPy float64, or a tensor of ``dtype`` when one is given."""
        if dtype is not None:
            v, u = torch.meshgrid(
                torch.arange(self.height, dtype=dtype) + 0.5, torch.arange(self.width, dtype=dtype) + 0.5,
                indexing="ij",
            )  # fmt: skip
            x, y = (u - self.cx) / self.fx, (v - self.cy) / self.fy
            return torch.stack([x, y, torch.ones_like(x)], dim=-1)
        if rows is None or cols is None:
            rows, cols = np.mgrid[0 : self.height, 0 : self.width]
        x, y = (cols + 0.5 - self.cx) / self.fx, (rows + 0.5 - self.cy) / self.fy
        return np.stack([x, y, np.ones(np.shape(x))], axis=-1)

    def unproject(
        self, depth: np.ndarray | torch.Tensor, rows: np.ndarray | None = None, cols: np.ndarray | None = None
    ) -> np.ndarray | torch.Tensor:
        """World points at z-depth ``depth`` [H, W] (along the viewing axis) through pixel centres:
        [H, W, 3] for every pixel, or [N, 3] for ``rows``, ``cols``. A tensor gives a tensor of its
        dtype (differentiable in the depth); an array gives float64."""
        if isinstance(depth, torch.Tensor):
            rays = self.pixel_rays(dtype=depth.dtype)
            local = torch.stack([rays[..., 0] * depth, rays[..., 1] * depth, depth], dim=-1)
            w2c = self.world_to_camera(dtype=depth.dtype)
            return (local - w2c[:3, 3]) @ w2c[:3, :3]  # R^T (p - t)
        r, t = self.pose_cv()
        z = depth if rows is None else depth[rows, cols]
        rays = self.pixel_rays(rows, cols)
        return (rays * z[..., None] - t) @ r

    def project(
        self, points: np.ndarray | torch.Tensor
    ) -> tuple[np.ndarray, np.ndarray] | tuple[torch.Tensor, torch.Tensor]:
        """(pixel coordinates [..., 2], z-depths [...]) of world points [..., 3]; pixel (r, c)'s centre
        is at (c + 0.5, r + 0.5). Coordinates are meaningful where z > 0 only (at |z| < 1e-12 they are
        taken at that depth, so that they stay finite). A tensor gives tensors of its dtype; an array
        is projected in float64."""
        if isinstance(points, torch.Tensor):
            w2c = self.world_to_camera(dtype=points.dtype)
            p = points @ w2c[:3, :3].T + w2c[:3, 3]
            z = p[..., 2]
            safe = torch.where(z.abs() < 1e-12, torch.full_like(z, 1e-12), z)
            return torch.stack(
                [self.fx * p[..., 0] / safe + self.cx, self.fy * p[..., 1] / safe + self.cy], -1
            ), z
        r, t = self.pose_cv()
        p = points @ r.T + t
        z = p[..., 2]
        safe = np.where(np.abs(z) < 1e-12, 1e-12, z)
        return np.stack([self.fx * p[..., 0] / safe + self.cx, self.fy * p[..., 1] / safe + self.cy], -1), z

    def faces(self, box: np.ndarray) -> bool:
        """Whether any of the axis-aligned ``box`` [2, 3] lies in front of the camera (the box is
        convex: when all eight corners are behind, all of it is)."""
        return bool((self.project(box_corners(box))[1] > 0).any())

    def scaled(self, factor: float) -> Camera:
        """The same camera at an image `factor` times smaller (factor 2 halves width and height)."""
        if factor <= 0:
            raise ValueError(f"resolution factor must be positive, got {factor}")
        w = max(1, int(round(self.width / factor)))
        h = max(1, int(round(self.height / factor)))
        sx, sy = w / self.width, h / self.height
        return replace(
            self, width=w, height=h, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy
        )

    @classmethod
    def look_at(
        cls,
        eye,
        target,
        up=(0.0, 0.0, 1.0),
        *,
        width: int = 160,
        height: int = 120,
        fov_x_deg: float = 60.0,
        name: str = "",
    ) -> Camera:
        """A camera at `eye` looking at `target`, with `up` pointing up in the image."""
        eye = np.asarray(eye, dtype=np.float64)
        fwd = np.asarray(target, dtype=np.float64) - eye
        if np.linalg.norm(fwd) < 1e-12:
            raise ValueError("look_at: eye and target coincide")
        fwd /= np.linalg.norm(fwd)
        up = np.asarray(up, dtype=np.float64)
        right = np.cross(fwd, up)
        if np.linalg.norm(right) < 1e-9:  # looking along `up`: any perpendicular will do
            right = np.cross(fwd, [1.0, 0.0, 0.0] if abs(fwd[0]) < 0.9 else [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        true_up = np.cross(right, fwd)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -fwd, eye
        fx = 0.5 * width / np.tan(0.5 * np.deg2rad(fov_x_deg))
        return cls(name, width, height, fx, fx, width / 2.0, height / 2.0, c2w)
