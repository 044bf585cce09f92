"""Projection of 3D Gaussians to screen-space ellipses (EWA splatting), shared by every backend.

The projection is O(N) work, written in PyTorch so autograd differentiates it; the backends only
differ in how they composite the projected ellipses into pixels. The 2D covariance, its inverse and
the radii are computed in float64: with scales from 1e-8 to 1e4 the determinant of a float32 2D
covariance loses every digit to cancellation.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

EPS_2D = 0.3  # low-pass filter added to the 2D covariance, in pixels^2 (3DGS, gsplat)
NEAR_PLANE = 0.01


class Projected(NamedTuple):
    """Screen-space Gaussians. Culled Gaussians have ``radii == 0`` and safe, unused values elsewhere.

    Attributes:
        means2d: [N, 2] pixel coordinates of the centres (pixel centres at integer + 0.5).
        conics: [N, 3] the inverse 2D covariance (a, b, c) = [[a, b], [b, c]].
        depths: [N] camera-space z.
        radii: [N] int32 3-sigma radius in pixels, 0 for culled Gaussians.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor


# The rasterizer's floor under |q|^2 (|q| >= 1e-12): only a guard against 0 / 0, so that a zero
# quaternion renders as the identity without NaN. It is not langfield.model.gaussians.QUAT_EPS (1e-8),
# below which the parameters' own normalisation snaps a quaternion to the identity: the renderer must
# draw whatever it is given, and the two paths round differently between 1e-12 and 1e-8.
QUAT_NORM2_MIN = 1e-24


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [N, 3, 3] from quaternions [N, 4] (w, x, y, z), normalised with an epsilon.

    A zero quaternion gives the identity (every term of the matrix vanishes but the diagonal's 1).
    """
    norm = torch.sqrt(torch.clamp((quats * quats).sum(-1, keepdim=True), min=QUAT_NORM2_MIN))
    w, x, y, z = (quats / norm).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """Sigma = R S S^T R^T, [N, 3, 3], from quaternions [N, 4] and scales [N, 3]."""
    m = quat_to_rotmat(quats) * scales[:, None, :]
    return m @ m.transpose(1, 2)


def tangent_limits(
    width: float, height: float, fx: float, fy: float, cx: float, cy: float
) -> tuple[float, float, float, float]:
    """How far off-screen the centre's tangents x/z, y/z may go before the EWA Jacobian is clamped.

    gsplat's limits (``gsplat/cuda/_torch_impl.py``, ``_persp_proj``; ``persp_proj`` in
    ``gsplat/cuda/csrc/utils.cuh``): the image edges as seen from the principal point, plus a margin of
    0.3 tan(fov / 2), where tan(fov_x / 2) = 0.5 width / fx and tan(fov_y / 2) = 0.5 height / fy. With
    the principal point at the image centre this is 3DGS's ``limx = 1.3f * tan_fovx``
    (diff-gaussian-rasterization ``cuda_rasterizer/forward.cu``, ``computeCov2D``).

    Returns:
        ``(x_neg, x_pos, y_neg, y_pos)``: x/z is clamped to [-x_neg, x_pos], y/z to [-y_neg, y_pos].
    """
    margin_x = 0.3 * (0.5 * width / fx)
    margin_y = 0.3 * (0.5 * height / fy)
    return (
        cx / fx + margin_x,
        (width - cx) / fx + margin_x,
        cy / fy + margin_y,
        (height - cy) / fy + margin_y,
    )


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    world_to_camera: Tensor,
    intrinsics: Tensor,
    width: int,
    height: int,
    near: float = NEAR_PLANE,
    eps2d: float = EPS_2D,
) -> Projected:
    """Projects Gaussians with the local affine (EWA) approximation of the perspective projection.

    Args:
        means: [N, 3] world positions.
        quats: [N, 4] rotations (w, x, y, z); need not be normalised.
        scales: [N, 3] standard deviations along the rotated axes (not logs).
        world_to_camera: [4, 4] OpenCV convention (x right, y down, z forward).
        intrinsics: [3, 3] pinhole matrix.
        width, height: image size in pixels.
        near: Gaussians with camera z below this are culled (at or behind the camera).
        eps2d: low-pass added to the 2D covariance diagonal.

    Returns:
        :class:`Projected`, float32 tensors except ``radii`` (int32).
    """
    dt = torch.float64
    w2c = world_to_camera.to(dt)
    fx, fy = float(intrinsics[0, 0]), float(intrinsics[1, 1])
    cx, cy = float(intrinsics[0, 2]), float(intrinsics[1, 2])
    rot, trans = w2c[:3, :3], w2c[:3, 3]

    p_cam = means.to(dt) @ rot.T + trans
    x, y, z = p_cam.unbind(-1)
    in_front = z > near
    z_safe = torch.where(in_front, z, torch.ones_like(z))

    # The Jacobian is taken at the centre's tangent clamped to a margin around the frustum
    # (tangent_limits): far outside it the affine approximation would blow up the covariance. The
    # projected mean itself is not clamped.
    lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos = tangent_limits(width, height, fx, fy, cx, cy)
    tx = z_safe * torch.clamp(x / z_safe, -lim_x_neg, lim_x_pos)
    ty = z_safe * torch.clamp(y / z_safe, -lim_y_neg, lim_y_pos)
    zeros = torch.zeros_like(z_safe)
    jac = torch.stack(
        [fx / z_safe, zeros, -fx * tx / z_safe**2, zeros, fy / z_safe, -fy * ty / z_safe**2], dim=-1
    ).reshape(-1, 2, 3)

    cov_cam = rot @ covariance_3d(quats.to(dt), scales.to(dt)) @ rot.T
    cov2d = jac @ cov_cam @ jac.transpose(1, 2)
    a = cov2d[:, 0, 0] + eps2d
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + eps2d
    det = a * c - b * b
    finite = torch.isfinite(det) & torch.isfinite(a) & torch.isfinite(c)
    valid = in_front & finite & (det > 0)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    a = torch.where(valid, a, torch.ones_like(a))
    c = torch.where(valid, c, torch.ones_like(c))
    b = torch.where(valid, b, torch.zeros_like(b))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)

    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], dim=-1)
    means2d = torch.where(valid[:, None], means2d, torch.zeros_like(means2d))

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam_max = mid + torch.sqrt(torch.clamp(mid * mid - det_safe, min=0.1))
        radius = torch.ceil(3.0 * torch.sqrt(lam_max))
        radius = torch.clamp(torch.nan_to_num(radius, nan=0.0, posinf=1e7), max=1e7)
        mx, my = means2d[:, 0], means2d[:, 1]
        on_screen = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        radii = torch.where(valid & on_screen, radius, torch.zeros_like(radius)).to(torch.int32)

    return Projected(means2d.float(), conics.float(), z.float().detach(), radii)
