"""The numba projection and binning against their PyTorch references (values and every gradient), and the
clamp of the EWA Jacobian of both backends against gsplat's limits."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import random_gaussians

from langfield.camera import Camera
from langfield.raster.binning import TILE_SIZE, bin_gaussians
from langfield.raster.binning_cpu import _order_by_depth, bin_gaussians_cpu
from langfield.raster.projection import Projected, project_gaussians
from langfield.raster.projection_cpu import project_gaussians_cpu


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
    ref = bin_gaussians(proj.means2d, proj.radii, proj.conics, opacities, proj.depths, 40, 30)
    fast = bin_gaussians_cpu(proj.means2d, proj.radii, proj.conics, opacities, proj.depths, 40, 30)
    assert torch.equal(ref[0], fast[0]) and torch.equal(ref[1], fast[1])


def test_binning_keeps_the_index_order_of_equal_depths(cam):
    """Duplicated Gaussians (equal depths in every copy): each tile lists the copies by index, as the
    reference's stable sort does."""
    means, quats, scales, opacities, _ = random_gaussians(100, 1, seed=3, log_scale=-2.0)
    means, quats, scales, opacities = (torch.cat([t, t, t]) for t in (means, quats, scales, opacities))
    proj = project_gaussians(means, quats, scales, cam.world_to_camera(), cam.intrinsics(), 40, 30)
    ref = bin_gaussians(proj.means2d, proj.radii, proj.conics, opacities, proj.depths, 40, 30)
    fast = bin_gaussians_cpu(proj.means2d, proj.radii, proj.conics, opacities, proj.depths, 40, 30)
    assert torch.equal(ref[0], fast[0]) and torch.equal(ref[1], fast[1])


def test_depth_order_is_a_stable_sort_of_the_floats():
    """The radix sort of the depths' bits orders as a stable comparison sort does: ties (copies, 0.0
    and -0.0) in the candidates' order, negative depths and infinities in their place."""
    rng = np.random.default_rng(0)
    depths = rng.normal(size=3000).astype(np.float32)
    depths[::7] = depths[3]
    depths[::11] = 0.0
    depths[1::13] = -0.0
    depths[5], depths[6] = np.inf, -np.inf
    depths[100:200] = rng.uniform(1.0, 1.0001, 100)  # differing in the last bits only
    cand = np.sort(rng.choice(3000, 2500, replace=False)).astype(np.int64)
    expected = cand[np.argsort(depths[cand], kind="stable")]
    assert np.array_equal(_order_by_depth(cand, depths), expected)
    assert _order_by_depth(cand[:0], depths).shape == (0,)


def _needles(n: int, seed: int) -> list[torch.Tensor]:
    """Elongated Gaussians (one axis 30x the others): their boxes hold many tiles the ellipse misses."""
    params = random_gaussians(n, 3, seed=seed, log_scale=-3.0)
    params[2][:, 0] *= 30.0
    return params


def _box_binning(proj, opacities, width: int, height: int):
    """Every Gaussian in every tile of its 3-sigma square, nearest first: the uncut lists."""
    tiles_x, tiles_y = -(-width // TILE_SIZE), -(-height // TILE_SIZE)
    lists = [[] for _ in range(tiles_x * tiles_y)]
    for i in torch.argsort(proj.depths, stable=True).tolist():
        r = int(proj.radii[i])
        if r <= 0 or opacities[i] < 1.0 / 255.0:
            continue
        mx, my = proj.means2d[i].tolist()
        for ty in range(max(0, int((my - r) // TILE_SIZE)), min(tiles_y, int((my + r) // TILE_SIZE) + 1)):
            for tx in range(max(0, int((mx - r) // TILE_SIZE)), min(tiles_x, int((mx + r) // TILE_SIZE) + 1)):
                lists[ty * tiles_x + tx].append(i)
    offsets = torch.tensor([0] + [len(x) for x in lists]).cumsum(0)
    return offsets, torch.tensor([i for x in lists for i in x], dtype=torch.int64)


@pytest.mark.parametrize("seed", [0, 1])
def test_binning_lists_exactly_the_tiles_a_gaussian_reaches(cam, seed):
    # Brute force: a tile is listed iff some pixel centre in it gets alpha >= 1/255 (up to the margin).
    means, quats, scales, opacities, _ = _needles(60, seed)
    proj = project_gaussians(means, quats, scales, cam.world_to_camera(), cam.intrinsics(), 40, 30)
    offsets, ids = bin_gaussians(proj.means2d, proj.radii, proj.conics, opacities, proj.depths, 40, 30)
    ys, xs = torch.meshgrid(torch.arange(30.0) + 0.5, torch.arange(40.0) + 0.5, indexing="ij")
    n_box = 0
    for i in torch.nonzero(proj.radii > 0).squeeze(1).tolist():
        a, b, c = proj.conics[i].double().tolist()
        dx, dy = xs.double() - float(proj.means2d[i, 0]), ys.double() - float(proj.means2d[i, 1])
        q = a * dx * dx + 2 * b * dx * dy + c * dy * dy
        q_max = 2 * np.log(max(float(opacities[i]) * 255.0, 1.0))
        for t in range(6):  # 3 x 2 tiles
            tx, ty = t % 3, t // 3
            block = q[ty * 16 : ty * 16 + 16, tx * 16 : tx * 16 + 16]
            listed = bool((ids[offsets[t] : offsets[t + 1]] == i).any())
            if block.min() <= q_max:
                assert listed, (i, t)
            elif block.min() > 1.001 * q_max:
                assert not listed, (i, t)
        n_box += int(proj.radii[i] > 0)
    assert n_box > 30
    # The cut matters for needles: fewer pairs than the 3-sigma squares list.
    assert ids.numel() < 0.8 * _box_binning(proj, opacities, 40, 30)[1].numel()


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_cut_tiles_change_no_pixel_and_no_gradient(cam, backend):
    from langfield.raster import composite
    from langfield.raster.composite import rasterize_torch
    from langfield.raster.composite_cpu import rasterize_cpu

    means, quats, scales, opacities, colors = _needles(80, 2)
    proj = project_gaussians(means, quats, scales, cam.world_to_camera(), cam.intrinsics(), 40, 30)
    fn = rasterize_torch if backend == "torch" else rasterize_cpu
    results = []
    for lists in ("cut", "box"):
        m2d = proj.means2d.detach().clone().requires_grad_(True)
        cn = proj.conics.detach().clone().requires_grad_(True)
        op = opacities.clone().requires_grad_(True)
        col = colors.clone().requires_grad_(True)
        bg = torch.zeros(3)
        if lists == "cut":
            p2 = Projected(m2d, cn, proj.depths, proj.radii)
            image, alpha = composite(p2, op, col, 40, 30, background=bg, backend=backend)
        else:
            offsets, ids = _box_binning(proj, opacities, 40, 30)
            image, alpha = fn(m2d, cn, op, col, offsets, ids, 40, 30, bg)
        g = torch.Generator().manual_seed(0)
        ((image * torch.randn(image.shape, generator=g)).sum() + alpha.sum()).backward()
        results.append([image.detach(), alpha.detach(), m2d.grad, cn.grad, op.grad, col.grad])
    for a, b in zip(*results, strict=True):
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-6)


def test_binning_of_nothing(cam):
    empty = torch.zeros(0)
    offsets, ids = bin_gaussians_cpu(
        torch.zeros(0, 2), torch.zeros(0, dtype=torch.int32), torch.zeros(0, 3), empty, empty, 40, 30
    )
    assert offsets.shape == (3 * 2 + 1,) and (offsets == 0).all() and ids.numel() == 0


# ---------------------------------------------------------------- off-screen clamp of the Jacobian

# Camera space = world space: the OpenGL pose diag(1, -1, -1) flips y and z back to OpenCV's.
_IDENTITY_POSE = np.diag([1.0, -1.0, -1.0, 1.0])


def _clamp_camera(cx: float, cy: float) -> Camera:
    return Camera("", 64, 48, 50.0, 40.0, cx, cy, _IDENTITY_POSE)


def _rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _expected_conics(means, quats, scales, cam: Camera, lims) -> np.ndarray:
    """The EWA conic of each Gaussian in float64, J taken at the tangent clipped to ``lims``."""
    x_neg, x_pos, y_neg, y_pos = lims
    out = []
    for mean, q, s in zip(means, quats, scales, strict=True):
        x, y, z = mean
        tx = z * np.clip(x / z, -x_neg, x_pos)
        ty = z * np.clip(y / z, -y_neg, y_pos)
        jac = np.array([[cam.fx / z, 0.0, -cam.fx * tx / z**2], [0.0, cam.fy / z, -cam.fy * ty / z**2]])
        m = _rotmat(q) * s[None, :]
        cov = jac @ (m @ m.T) @ jac.T + 0.3 * np.eye(2)
        inv = np.linalg.inv(cov)
        out.append([inv[0, 0], inv[0, 1], inv[1, 1]])
    return np.array(out)


def _gaussians_at_the_limits(lims, z: float = 2.0, seed: int = 0):
    """Centres 2 % inside and 2 % outside each of the four limits, plus one far outside each."""
    x_neg, x_pos, y_neg, y_pos = lims
    tangents = []
    for factor in (0.98, 1.02, 3.0):
        tangents += [(x_pos * factor, 0.1), (-x_neg * factor, -0.1)]
        tangents += [(0.1, y_pos * factor), (-0.1, -y_neg * factor)]
    means = np.array([[u * z, v * z, z] for u, v in tangents])
    rng = np.random.default_rng(seed)
    quats = rng.normal(size=(len(means), 4))
    scales = np.tile([0.05, 0.1, 0.4], (len(means), 1))  # long in z: J's third column matters
    return means, quats, scales


@pytest.mark.parametrize(
    ("cx", "cy", "lims"),
    [
        # Centred principal point: 3DGS's 1.3 tan(fov / 2) on every side, tan = 0.5 * 64 / 50, 0.5 * 48 / 40.
        (32.0, 24.0, (1.3 * 0.64, 1.3 * 0.64, 1.3 * 0.6, 1.3 * 0.6)),
        # Off-centre: gsplat's (edge - c) / f + 0.3 tan(fov / 2) per side, worked out by hand.
        (20.0, 30.0, (20 / 50 + 0.192, 44 / 50 + 0.192, 30 / 40 + 0.18, 18 / 40 + 0.18)),
    ],
    ids=["centred", "off-centre"],
)
@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_jacobian_is_clamped_at_gsplats_limits(backend, cx, cy, lims):
    cam = _clamp_camera(cx, cy)
    means, quats, scales = _gaussians_at_the_limits(lims)
    fn = project_gaussians if backend == "torch" else project_gaussians_cpu
    proj = fn(
        torch.tensor(means, dtype=torch.float32),
        torch.tensor(quats, dtype=torch.float32),
        torch.tensor(scales, dtype=torch.float32),
        cam.world_to_camera(),
        cam.intrinsics(),
        cam.width,
        cam.height,
    )
    # The inputs as the backends see them (float32), so only the clamp can make a difference.
    m32, q32, s32 = (np.float32(a).astype(np.float64) for a in (means, quats, scales))
    expected = _expected_conics(m32, q32, s32, cam, lims)
    np.testing.assert_allclose(proj.conics.numpy(), expected, rtol=2e-5, atol=0)
    # The clamp matters here: without it the centres just outside would give other conics.
    unclamped = _expected_conics(m32, q32, s32, cam, (np.inf,) * 4)
    outside = np.arange(len(means)) % 12 >= 4
    assert (np.abs(unclamped - expected).max(axis=1)[outside] > 1e-3 * np.abs(expected).max()).all()
    assert np.allclose(unclamped[~outside], expected[~outside])
    # The projected mean is never clamped.
    mean2d = np.stack([cam.fx * m32[:, 0] / m32[:, 2] + cx, cam.fy * m32[:, 1] / m32[:, 2] + cy], -1)
    np.testing.assert_allclose(proj.means2d.numpy(), mean2d, rtol=1e-6, atol=1e-4)


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_clamped_tangent_passes_no_gradient_to_its_coordinate(backend):
    lims = (20 / 50 + 0.192, 44 / 50 + 0.192, 30 / 40 + 0.18, 18 / 40 + 0.18)
    cam = _clamp_camera(20.0, 30.0)
    means, quats, scales = (torch.tensor(a, dtype=torch.float32) for a in _gaussians_at_the_limits(lims))
    means.requires_grad_(True)
    fn = project_gaussians if backend == "torch" else project_gaussians_cpu
    proj = fn(means, quats, scales, cam.world_to_camera(), cam.intrinsics(), cam.width, cam.height)
    weights = torch.randn(proj.conics.shape, generator=torch.Generator().manual_seed(0))
    (proj.conics * weights).sum().backward()
    # Order per factor: +x, -x limit (x tested), +y, -y limit (y tested); factors 0.98, 1.02, 3.
    kind = np.arange(len(means)) % 4
    outside = np.arange(len(means)) % 12 >= 4
    tested = np.where(kind < 2, 0, 1)
    g = means.grad.numpy()[np.arange(len(means)), tested]
    assert (g[outside] == 0).all()
    assert (np.abs(g[~outside]) > 1e-6).all()
    assert (means.grad[:, 2] != 0).all()  # z still moves the clamped Jacobian


def test_projection_matches_reference_at_the_clamp_limits():
    lims = (20 / 50 + 0.192, 44 / 50 + 0.192, 30 / 40 + 0.18, 18 / 40 + 0.18)
    params = [torch.tensor(a, dtype=torch.float32) for a in _gaussians_at_the_limits(lims, seed=1)]
    assert_projections_agree(params, _clamp_camera(20.0, 30.0))
