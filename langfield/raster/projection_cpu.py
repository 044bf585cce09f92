"""The fast CPU backend's projection: numba kernels with a hand-written backward.

Same arithmetic as :func:`langfield.raster.projection.project_gaussians` (the PyTorch reference it is
tested against, values and gradients), one Gaussian per loop iteration in float64. In PyTorch the
projection is ~60 small batched ops whose autograd graph costs more than the arithmetic; here it is
one pass forward and one pass back.

The backward of the EWA projection, per Gaussian, chains (each line's gradient feeds the one above):

- conic = inverse of the 2D covariance [[a, b], [b, c]] (a, c include the 0.3 px low-pass);
- cov2d = J Sigma_cam J^T, J the Jacobian of the perspective projection at the centre, its tangent
  clamped to :func:`langfield.raster.projection.tangent_limits` (gsplat's limits); outside them the
  clamped coordinate is z times the limit, so its gradient goes to z only, as autograd of the
  reference's ``z * clamp(x / z)`` gives;
- Sigma_cam = W Sigma W^T, W the world-to-camera rotation;
- Sigma = M M^T with M = R(q / |q|) diag(s);
- means2d = (fx x / z + cx, fy y / z + cy) with (x, y, z) = W p + t.

Culled Gaussians (behind the near plane, non-finite or degenerate covariance) get zero gradients, as
the reference's ``torch.where`` gives them.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from langfield.kernels import configure_numba
from langfield.raster.projection import EPS_2D, NEAR_PLANE, QUAT_NORM2_MIN, Projected, tangent_limits

configure_numba()


@njit(inline="always")
def _rotmat(w, x, y, z):
    return (
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    )


@njit(parallel=True, cache=True)
def _project_forward(
    means, quats, scales, rot, trans, fx, fy, cx, cy, width, height, near, eps2d, lims,
    out_means2d, out_conics, out_depths, out_radii, out_valid, out_sigma, out_norm,
):  # fmt: skip
    n = means.shape[0]
    lim_xn, lim_xp, lim_yn, lim_yp = lims[0], lims[1], lims[2], lims[3]  # projection.tangent_limits
    for i in prange(n):
        px, py, pz = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
        x = rot[0, 0] * px + rot[0, 1] * py + rot[0, 2] * pz + trans[0]
        y = rot[1, 0] * px + rot[1, 1] * py + rot[1, 2] * pz + trans[1]
        z = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz + trans[2]
        out_depths[i] = z
        out_valid[i] = False
        out_radii[i] = 0
        out_means2d[i, 0] = 0.0
        out_means2d[i, 1] = 0.0
        out_conics[i, 0] = 1.0
        out_conics[i, 1] = 0.0
        out_conics[i, 2] = 1.0
        # Sigma_cam (also needed by the backward), computed for every Gaussian.
        qw, qx, qy, qz = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
        norm = math.sqrt(max(qw * qw + qx * qx + qy * qy + qz * qz, QUAT_NORM2_MIN))
        out_norm[i] = norm
        r = _rotmat(qw / norm, qx / norm, qy / norm, qz / norm)
        s0, s1, s2 = float(scales[i, 0]), float(scales[i, 1]), float(scales[i, 2])
        wm = np.empty((3, 3))
        for a in range(3):
            wm[a, 0] = (rot[a, 0] * r[0] + rot[a, 1] * r[3] + rot[a, 2] * r[6]) * s0
            wm[a, 1] = (rot[a, 0] * r[1] + rot[a, 1] * r[4] + rot[a, 2] * r[7]) * s1
            wm[a, 2] = (rot[a, 0] * r[2] + rot[a, 1] * r[5] + rot[a, 2] * r[8]) * s2
        for a in range(3):
            for b in range(3):
                out_sigma[i, a, b] = wm[a, 0] * wm[b, 0] + wm[a, 1] * wm[b, 1] + wm[a, 2] * wm[b, 2]
        if not z > near:
            continue
        tx = z * min(max(x / z, -lim_xn), lim_xp)
        ty = z * min(max(y / z, -lim_yn), lim_yp)
        j00, j02 = fx / z, -fx * tx / (z * z)
        j11, j12 = fy / z, -fy * ty / (z * z)
        s = out_sigma[i]
        # cov2d = J S J^T with J = [[j00, 0, j02], [0, j11, j12]]
        a = j00 * (j00 * s[0, 0] + j02 * s[2, 0]) + j02 * (j00 * s[0, 2] + j02 * s[2, 2]) + eps2d
        b = j11 * (j00 * s[0, 1] + j02 * s[2, 1]) + j12 * (j00 * s[0, 2] + j02 * s[2, 2])
        c = j11 * (j11 * s[1, 1] + j12 * s[2, 1]) + j12 * (j11 * s[1, 2] + j12 * s[2, 2]) + eps2d
        det = a * c - b * b
        if not (math.isfinite(det) and math.isfinite(a) and math.isfinite(c) and det > 0):
            continue
        out_valid[i] = True
        out_conics[i, 0] = c / det
        out_conics[i, 1] = -b / det
        out_conics[i, 2] = a / det
        mx = fx * x / z + cx
        my = fy * y / z + cy
        out_means2d[i, 0] = mx
        out_means2d[i, 1] = my
        mid = 0.5 * (a + c)
        lam_max = mid + math.sqrt(max(mid * mid - det, 0.1))
        radius = math.ceil(3.0 * math.sqrt(lam_max))
        if not math.isfinite(radius):
            radius = 1e7 if radius > 0 else 0.0
        radius = min(radius, 1e7)
        if mx + radius > 0 and mx - radius < width and my + radius > 0 and my - radius < height:
            out_radii[i] = np.int32(radius)


@njit(parallel=True, cache=True)
def _project_backward(
    means, quats, scales, rot, trans, fx, fy, eps2d, lims,
    valid, sigma, norms, g_means2d, g_conics, out_g_means, out_g_quats, out_g_scales,
):  # fmt: skip
    n = means.shape[0]
    lim_xn, lim_xp, lim_yn, lim_yp = lims[0], lims[1], lims[2], lims[3]  # the forward's limits
    for i in prange(n):
        for k in range(3):
            out_g_means[i, k] = 0.0
            out_g_scales[i, k] = 0.0
        for k in range(4):
            out_g_quats[i, k] = 0.0
        if not valid[i]:
            continue
        px, py, pz = float(means[i, 0]), float(means[i, 1]), float(means[i, 2])
        x = rot[0, 0] * px + rot[0, 1] * py + rot[0, 2] * pz + trans[0]
        y = rot[1, 0] * px + rot[1, 1] * py + rot[1, 2] * pz + trans[1]
        z = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz + trans[2]
        ux, uy = x / z, y / z
        in_x = -lim_xn <= ux <= lim_xp
        in_y = -lim_yn <= uy <= lim_yp
        tx = z * min(max(ux, -lim_xn), lim_xp)
        ty = z * min(max(uy, -lim_yn), lim_yp)
        z2 = z * z
        j00, j02 = fx / z, -fx * tx / z2
        j11, j12 = fy / z, -fy * ty / z2
        s = sigma[i]
        a = j00 * (j00 * s[0, 0] + j02 * s[2, 0]) + j02 * (j00 * s[0, 2] + j02 * s[2, 2]) + eps2d
        b = j11 * (j00 * s[0, 1] + j02 * s[2, 1]) + j12 * (j00 * s[0, 2] + j02 * s[2, 2])
        c = j11 * (j11 * s[1, 1] + j12 * s[2, 1]) + j12 * (j11 * s[1, 2] + j12 * s[2, 2]) + eps2d
        det = a * c - b * b
        inv = 1.0 / det
        inv2 = inv * inv
        # conic (c, -b, a) / det -> a, b, c
        g0, g1, g2 = float(g_conics[i, 0]), float(g_conics[i, 1]), float(g_conics[i, 2])
        ga = -g0 * c * c * inv2 + g1 * b * c * inv2 + g2 * (inv - a * c * inv2)
        gb = 2.0 * g0 * b * c * inv2 + g1 * (-inv - 2.0 * b * b * inv2) + 2.0 * g2 * a * b * inv2
        gc = g0 * (inv - a * c * inv2) + g1 * a * b * inv2 - g2 * a * a * inv2
        # cov2d = J S J^T: symmetric upstream gradient Gs = [[ga, gb/2], [gb/2, gc]]
        hb = 0.5 * gb
        jm = np.zeros((2, 3))
        jm[0, 0], jm[0, 2], jm[1, 1], jm[1, 2] = j00, j02, j11, j12
        gs = np.empty((2, 2))
        gs[0, 0], gs[0, 1], gs[1, 0], gs[1, 1] = ga, hb, hb, gc
        # dL/dSigma_cam = J^T Gs J
        gj_t = np.empty((2, 3))  # Gs J
        for r in range(2):
            for col in range(3):
                gj_t[r, col] = gs[r, 0] * jm[0, col] + gs[r, 1] * jm[1, col]
        g_sc = np.empty((3, 3))
        for r in range(3):
            for col in range(3):
                g_sc[r, col] = jm[0, r] * gj_t[0, col] + jm[1, r] * gj_t[1, col]
        # dL/dJ = 2 Gs J Sigma_cam
        gjm = np.empty((2, 3))
        for r in range(2):
            for col in range(3):
                gjm[r, col] = 2.0 * (gj_t[r, 0] * s[0, col] + gj_t[r, 1] * s[1, col] + gj_t[r, 2] * s[2, col])
        g_z = -gjm[0, 0] * fx / z2 - gjm[1, 1] * fy / z2
        g_z += gjm[0, 2] * 2.0 * fx * tx / (z2 * z) + gjm[1, 2] * 2.0 * fy * ty / (z2 * z)
        g_tx = -gjm[0, 2] * fx / z2
        g_ty = -gjm[1, 2] * fy / z2
        g_x = 0.0
        g_y = 0.0
        if in_x:
            g_x += g_tx
        else:
            g_z += g_tx * (tx / z)
        if in_y:
            g_y += g_ty
        else:
            g_z += g_ty * (ty / z)
        # means2d
        gmx, gmy = float(g_means2d[i, 0]), float(g_means2d[i, 1])
        g_x += gmx * fx / z
        g_y += gmy * fy / z
        g_z -= gmx * fx * x / z2 + gmy * fy * y / z2
        for k in range(3):
            out_g_means[i, k] = rot[0, k] * g_x + rot[1, k] * g_y + rot[2, k] * g_z
        # Sigma_cam = W Sigma W^T -> dL/dSigma = W^T G W
        g_sw = np.empty((3, 3))
        tmp = np.empty((3, 3))
        for r in range(3):
            for col in range(3):
                tmp[r, col] = g_sc[r, 0] * rot[0, col] + g_sc[r, 1] * rot[1, col] + g_sc[r, 2] * rot[2, col]
        for r in range(3):
            for col in range(3):
                g_sw[r, col] = rot[0, r] * tmp[0, col] + rot[1, r] * tmp[1, col] + rot[2, r] * tmp[2, col]
        # Sigma = M M^T, M = R diag(s): dL/dM = (G + G^T) M
        norm = norms[i]
        qw, qx, qy, qz = quats[i, 0] / norm, quats[i, 1] / norm, quats[i, 2] / norm, quats[i, 3] / norm
        rq = _rotmat(qw, qx, qy, qz)
        sc = (float(scales[i, 0]), float(scales[i, 1]), float(scales[i, 2]))
        g_r = np.empty(9)
        for r in range(3):
            for col in range(3):
                gm = 0.0
                for k in range(3):
                    gm += (g_sw[r, k] + g_sw[k, r]) * rq[3 * k + col] * sc[col]
                out_g_scales[i, col] += gm * rq[3 * r + col]
                g_r[3 * r + col] = gm * sc[col]
        # R(q) -> normalised q
        gw = 2.0 * (-g_r[1] * qz + g_r[2] * qy + g_r[3] * qz - g_r[5] * qx - g_r[6] * qy + g_r[7] * qx)
        gx = 2.0 * (
            g_r[1] * qy + g_r[2] * qz + g_r[3] * qy - 2.0 * g_r[4] * qx
            - g_r[5] * qw + g_r[6] * qz + g_r[7] * qw - 2.0 * g_r[8] * qx
        )  # fmt: skip
        gy = 2.0 * (
            -2.0 * g_r[0] * qy + g_r[1] * qx + g_r[2] * qw + g_r[3] * qx
            + g_r[5] * qz - g_r[6] * qw + g_r[7] * qz - 2.0 * g_r[8] * qy
        )  # fmt: skip
        gz = 2.0 * (
            -2.0 * g_r[0] * qz - g_r[1] * qw + g_r[2] * qx + g_r[3] * qw
            - 2.0 * g_r[4] * qz + g_r[5] * qy + g_r[6] * qx + g_r[7] * qy
        )  # fmt: skip
        # q / max(|q|, 1e-12): the clamp passes no gradient to the norm
        q2 = quats[i, 0] ** 2 + quats[i, 1] ** 2 + quats[i, 2] ** 2 + quats[i, 3] ** 2
        dot = gw * qw + gx * qx + gy * qy + gz * qz if q2 > QUAT_NORM2_MIN else 0.0
        out_g_quats[i, 0] = (gw - qw * dot) / norm
        out_g_quats[i, 1] = (gx - qx * dot) / norm
        out_g_quats[i, 2] = (gy - qy * dot) / norm
        out_g_quats[i, 3] = (gz - qz * dot) / norm


class _ProjectCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, w2c, intrinsics, width, height, near, eps2d):
        # numpy, not torch, for the conversions: a torch op right after a numba kernel waits for its
        # threads to wake (see configure_numba).
        m = means.detach().numpy().astype(np.float64)
        q = quats.detach().numpy().astype(np.float64)
        s = scales.detach().numpy().astype(np.float64)
        w2c = w2c.detach().numpy().astype(np.float64)
        rot, trans = np.ascontiguousarray(w2c[:3, :3]), np.ascontiguousarray(w2c[:3, 3])
        k = intrinsics.detach().numpy().astype(np.float64)
        fx, fy, cx, cy = float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
        n = m.shape[0]
        means2d = np.empty((n, 2))
        conics = np.empty((n, 3))
        depths = np.empty(n)
        radii = np.empty(n, np.int32)
        valid = np.empty(n, np.bool_)
        sigma = np.empty((n, 3, 3))
        norms = np.empty(n)
        # Both backends clamp with the same limits, computed once by the reference's function.
        lims = np.array(tangent_limits(float(width), float(height), fx, fy, cx, cy), np.float64)
        _project_forward(
            m, q, s, rot, trans, fx, fy, cx, cy, float(width), float(height), float(near), float(eps2d), lims,
            means2d, conics, depths, radii, valid, sigma, norms,
        )  # fmt: skip
        ctx.saved = (m, q, s, rot, trans, fx, fy, float(eps2d), lims)
        ctx.state = (valid, sigma, norms)
        out_radii = torch.from_numpy(radii)
        ctx.mark_non_differentiable(out_radii)
        return (
            torch.from_numpy(means2d.astype(np.float32)),
            torch.from_numpy(conics.astype(np.float32)),
            torch.from_numpy(depths.astype(np.float32)),
            out_radii,
        )

    @staticmethod
    def backward(ctx, g_means2d, g_conics, _g_depths, _g_radii):
        m, q, s, rot, trans, fx, fy, eps2d, lims = ctx.saved
        valid, sigma, norms = ctx.state
        n = m.shape[0]
        gm2 = np.zeros((n, 2)) if g_means2d is None else g_means2d.numpy().astype(np.float64)
        gcn = np.zeros((n, 3)) if g_conics is None else g_conics.numpy().astype(np.float64)
        g_means, g_quats, g_scales = np.empty((n, 3)), np.empty((n, 4)), np.empty((n, 3))
        _project_backward(
            m, q, s, rot, trans, fx, fy, eps2d, lims,
            valid, sigma, norms, gm2, gcn, g_means, g_quats, g_scales,
        )  # fmt: skip
        as32 = lambda a: torch.from_numpy(a.astype(np.float32))  # noqa: E731
        return as32(g_means), as32(g_quats), as32(g_scales), None, None, None, None, None, None


def project_gaussians_cpu(
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
    """:func:`langfield.raster.projection.project_gaussians` on numba kernels (same contract)."""
    means2d, conics, depths, radii = _ProjectCPU.apply(
        means, quats, scales, world_to_camera, intrinsics, width, height, near, eps2d
    )
    return Projected(means2d, conics, depths, radii)
