"""The numba projection and binning against their PyTorch references: values and every gradient."""

from __future__ import annotations

import pytest
import torch
from conftest import random_gaussians

from langfield.camera import Camera
from langfield.raster.binning import bin_gaussians, opacity_aware_radii
from langfield.raster.cpu_geometry import bin_gaussians_cpu, project_gaussians_cpu
from langfield.raster.projection import project_gaussians


def project_both(params, cam: Camera, seed: int = 0):
    """Projects with both implementations and backpropagates the same random weights."""
    results = []
    for fn in (project_gaussians, project_gaussians_cpu):
        leaves = [p.detach().clone().requires_grad_(True) for p in params[:3]]
        proj = fn(*leaves, cam.world_to_camera(), cam.intrinsics(), cam.width, cam.height)
        g = torch.Generator().manual_seed(seed)
        loss = (proj.means2d * torch.randn(proj.means2d.shape, generator=g)).sum() + (
            proj.conics * torch.randn(proj.conics.shape, generator=g)
        ).sum()
        loss.backward()
        results.append((proj, [p.grad for p in leaves]))
    return results


def assert_projections_agree(params, cam: Camera) -> None:
    (ref, ref_grads), (fast, fast_grads) = project_both(params, cam)
    assert torch.equal(ref.radii, fast.radii)
    for name in ("means2d", "conics", "depths"):
        a, b = getattr(ref, name), getattr(fast, name)
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-5), name
    for name, a, b in zip(("means", "quats", "scales"), ref_grads, fast_grads, strict=True):
        assert torch.isfinite(b).all(), name
        scale = a.norm()
        if scale < 1e-8:
            assert b.norm() < 1e-6, name
            continue
        assert ((a - b).norm() / scale).item() <= 1e-4, name


@pytest.fixture
def cam() -> Camera:
    return Camera.look_at((0.0, -3.0, 0.5), (0.0, 0.0, 0.0), width=40, height=30, fov_x_deg=60)


@pytest.mark.parametrize("seed", [0, 1])
def test_projection_matches_reference(cam, seed):
    assert_projections_agree(random_gaussians(300, 1, seed=seed), cam)


def test_projection_matches_reference_off_screen_and_culled(cam):
    # Wide spread: many centres outside the frustum (the clamped tangent branch), behind the camera,
    # and straddling the near plane.
    params = random_gaussians(400, 1, seed=3)
    params[0] = params[0] * 6.0
    params[1][:5] = 0.0  # zero quaternions
    params[2][5:10] = 1e-8
    params[2][10:15] = 1e4
    assert_projections_agree(params, cam)


@pytest.mark.parametrize("seed", [0, 1])
def test_binning_matches_reference(cam, seed):
    means, quats, scales, opacities, _ = random_gaussians(500, 1, seed=seed, log_scale=-2.0)
    opacities[:20] = 0.001  # below 1/255: never binned
    proj = project_gaussians(means, quats, scales, cam.world_to_camera(), cam.intrinsics(), 40, 30)
    ref = bin_gaussians(
        proj.means2d, opacity_aware_radii(proj.radii, proj.conics, opacities), proj.depths, 40, 30
    )
    fast = bin_gaussians_cpu(proj.means2d, proj.radii, proj.conics, opacities, proj.depths, 40, 30)
    assert torch.equal(ref[0], fast[0]) and torch.equal(ref[1], fast[1])


def test_binning_of_nothing(cam):
    empty = torch.zeros(0)
    offsets, ids = bin_gaussians_cpu(
        torch.zeros(0, 2), torch.zeros(0, dtype=torch.int32), torch.zeros(0, 3), empty, empty, 40, 30
    )
    assert offsets.shape == (3 * 2 + 1,) and (offsets == 0).all() and ids.numel() == 0
