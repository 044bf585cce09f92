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
