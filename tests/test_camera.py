"""Camera.project / unproject / pixel_rays: the pixel geometry every caller shares (langfield/camera.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from langfield.camera import Camera, camera_spacing


def _camera() -> Camera:
    cam = Camera.look_at((0.4, -1.5, 0.7), (0.1, 0.2, 0.0), width=64, height=48, fov_x_deg=55)
    return Camera(cam.name, cam.width, cam.height, cam.fx, cam.fy * 1.1, cam.cx + 2.5, cam.cy - 1.0, cam.c2w)


def test_unproject_then_project_returns_the_pixel_centres_in_float64() -> None:
    cam = _camera()
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.5, 4.0, (cam.height, cam.width))
    points = cam.unproject(depth)
    assert points.shape == (48, 64, 3) and points.dtype == np.float64
    uv, z = cam.project(points)
    rows, cols = np.mgrid[0:48, 0:64]
    np.testing.assert_allclose(uv[..., 0], cols + 0.5, atol=1e-9)
    np.testing.assert_allclose(uv[..., 1], rows + 0.5, atol=1e-9)
    np.testing.assert_allclose(z, depth, rtol=1e-12)
    # Chosen pixels give the same points as the whole image.
    r, c = np.array([0, 47, 20]), np.array([63, 0, 31])
    np.testing.assert_array_equal(cam.unproject(depth, r, c), points[r, c])


def test_the_tensor_path_agrees_with_float64_and_is_differentiable() -> None:
    cam = _camera()
    depth = torch.rand(48, 64, dtype=torch.float64) * 3 + 0.5
    depth.requires_grad_(True)
    points = cam.unproject(depth)
    np.testing.assert_allclose(points.detach().numpy(), cam.unproject(depth.detach().numpy()), atol=1e-12)
    uv, z = cam.project(points)
    torch.testing.assert_close(z, depth)
    # d z / d depth is the identity through unproject then project: a wrong frame would not give it.
    (grad,) = torch.autograd.grad(z.sum(), depth)
    torch.testing.assert_close(grad, torch.ones_like(grad))


def test_pixel_rays_have_unit_z_and_point_through_the_pixel_centres() -> None:
    cam = _camera()
    rays = cam.pixel_rays()
    assert rays.shape == (48, 64, 3)
    np.testing.assert_array_equal(rays[..., 2], 1.0)
    torch_rays = cam.pixel_rays(dtype=torch.float32)
    np.testing.assert_allclose(torch_rays.numpy(), rays, atol=1e-6)
    # The principal point's ray is the optical axis.
    axis = cam.pixel_rays(np.array([cam.cy - 0.5]), np.array([cam.cx - 0.5]))
    np.testing.assert_allclose(axis, [[0.0, 0.0, 1.0]], atol=1e-12)


@pytest.mark.parametrize("z", [-1.0, 0.0, 1e-14])
def test_points_behind_or_at_the_camera_project_to_finite_coordinates_with_their_depth(z) -> None:
    cam = Camera.look_at((0, 0, 0), (0, 0, -1), (0, 1, 0), width=8, height=6)
    world = np.array([[0.3, 0.2, -z]])  # the camera looks down -z: camera-frame depth z
    uv, depth = cam.project(world)
    assert np.isfinite(uv).all()
    np.testing.assert_allclose(depth, [z], atol=1e-15)
    uv_t, depth_t = cam.project(torch.tensor(world))
    assert torch.isfinite(uv_t).all() and float(depth_t[0]) == pytest.approx(z, abs=1e-15)


def _posed(c2w=None, **intrinsics) -> Camera:
    base = Camera.look_at((0.4, -1.5, 0.7), (0.1, 0.2, 0.0), width=64, height=48)
    values = {"fx": base.fx, "fy": base.fy, "cx": base.cx, "cy": base.cy, **intrinsics}
    return Camera("v", 64, 48, values["fx"], values["fy"], values["cx"], values["cy"],
                  base.c2w if c2w is None else c2w)  # fmt: skip


def test_a_pose_rounded_to_float32_is_a_camera() -> None:
    pose = _posed().c2w.astype(np.float32).astype(np.float64)
    assert _posed(pose).c2w.shape == (4, 4)


@pytest.mark.parametrize(
    ("change", "said"),
    [
        (lambda m: m[:3, :3].__imul__(1.5), "rotation scaled by 1.5"),
        (lambda m: m[:3, 0].__iadd__(0.1 * m[:3, 1]), "not orthonormal"),
        (lambda m: m[:3, 2].__imul__(-1.0), "reflection"),
        (lambda m: m.__setitem__((3, 0), 0.5), "bottom row"),
    ],
    ids=["scaled", "sheared", "mirrored", "bottom-row"],
)
def test_a_pose_that_is_not_a_rigid_motion_is_refused_with_a_hint(change, said) -> None:
    pose = _posed().c2w.copy()
    change(pose)
    with pytest.raises(ValueError, match=said):
        _posed(pose)


@pytest.mark.parametrize(
    ("intrinsics", "said"),
    [
        ({"fx": 2.0, "fy": 2.0}, "fx 2 pixels is outside"),
        ({"fx": 9000.0, "fy": 9000.0}, "outside"),
        ({"fy": 300.0}, "differ by more than"),
        ({"cx": 70.0}, "principal point"),
        ({"cy": -1.0}, "principal point"),
    ],
)
def test_intrinsics_that_cannot_belong_to_the_image_are_refused(intrinsics, said) -> None:
    with pytest.raises(ValueError, match=said):
        _posed(**intrinsics)


def test_camera_spacing_is_the_mean_pairwise_distance() -> None:
    centres = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0], [0.0, 4.0, 0.0]])
    assert camera_spacing(centres) == pytest.approx((3.0 + 4.0 + 5.0) / 3)
    assert camera_spacing(centres[:1]) == 0.0  # one camera has no spacing
    assert camera_spacing(np.zeros((3, 3))) == 0.0  # duplicate cameras
