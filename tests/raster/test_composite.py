"""The fast CPU rasterizer against the PyTorch reference, on values and every gradient, and the hard cases."""

from __future__ import annotations

import contextlib

import pytest
import torch
from conftest import random_gaussians

from langfield.camera import Camera
from langfield.raster import composite_cpu, rasterize, rasterize_with_second_pass
from langfield.raster.composite_cpu import FIXED_CHANNELS
from langfield.raster.projection import project_gaussians, quat_to_rotmat

NAMES = ("means", "quats", "scales", "opacities", "features")


def render_and_grads(
    backend: str, params: list[torch.Tensor], camera: Camera, background=None, seed: int = 1
):
    leaves = [p.detach().clone().requires_grad_(True) for p in params]
    out = rasterize(*leaves, camera, background=background, backend=backend)
    g = torch.Generator().manual_seed(seed)
    w_img = torch.randn(out.image.shape, generator=g)
    w_alpha = torch.randn(out.alpha.shape, generator=g)
    ((out.image * w_img).sum() + (out.alpha * w_alpha).sum()).backward()
    return out, [p.grad for p in leaves]


def assert_finite(out, grads) -> None:
    assert torch.isfinite(out.image).all() and torch.isfinite(out.alpha).all()
    for name, grad in zip(NAMES, grads, strict=True):
        assert grad is not None and torch.isfinite(grad).all(), f"non-finite gradient for {name}"


def assert_backends_agree(params, camera, background=None) -> None:
    ref, ref_grads = render_and_grads("torch", params, camera, background)
    fast, fast_grads = render_and_grads("numba", params, camera, background)
    assert_finite(ref, ref_grads)
    assert_finite(fast, fast_grads)
    assert (ref.image - fast.image).abs().max() <= 1e-4
    assert (ref.alpha - fast.alpha).abs().max() <= 1e-4
    for name, a, b in zip(NAMES, ref_grads, fast_grads, strict=True):
        scale = a.norm()
        if scale < 1e-8:
            assert b.norm() < 1e-6, name
            continue
        rel = ((a - b).norm() / scale).item()
        assert rel <= 1e-3, f"{name}: relative gradient error {rel:.2e}"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_backends_agree_on_random_scenes(small_camera, seed):
    params = random_gaussians(200, 5, seed=seed)
    assert_backends_agree(params, small_camera, background=torch.rand(5))


@pytest.mark.parametrize("channels", [1, 16, 17, 40])
def test_backends_agree_for_any_channel_count(small_camera, channels):
    # The fast backward holds the upstream gradients 16 channels a row: one row, a full one, and more.
    params = random_gaussians(120, channels, seed=channels)
    assert_backends_agree(params, small_camera, background=torch.rand(channels))


def test_backends_agree_with_large_opaque_gaussians(small_camera):
    params = random_gaussians(60, 3, seed=3, log_scale=-1.5)
    params[3] = torch.full_like(params[3], 0.995)  # many alphas hit the 0.99 clamp and saturate pixels
    assert_backends_agree(params, small_camera)


def test_backends_agree_on_odd_image_size():
    cam = Camera.look_at((0.0, -3.0, 0.5), (0.0, 0.0, 0.0), width=37, height=21)
    assert_backends_agree(random_gaussians(150, 4, seed=4), cam)


def test_rendered_gaussian_lands_where_projected():
    cam = Camera.look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), width=41, height=31)
    means = torch.tensor([[0.3, 0.0, 0.2]])
    out = rasterize(
        means,
        torch.tensor([[1.0, 0, 0, 0]]),
        torch.full((1, 3), 0.03),
        torch.tensor([0.9]),
        torch.ones(1, 1),
        cam,
        backend="numba",
    )
    peak = torch.nonzero(out.image[..., 0] == out.image[..., 0].max())[0]
    v, u = peak.tolist()
    mx, my = out.means2d[0].tolist()
    assert abs(u + 0.5 - mx) <= 1 and abs(v + 0.5 - my) <= 1
    assert mx > cam.cx and my < cam.cy  # +x is right, +z (world up) is up in the image


def test_quat_to_rotmat_is_orthonormal_and_zero_quat_is_identity():
    r = quat_to_rotmat(torch.randn(10, 4))
    assert torch.allclose(r @ r.transpose(1, 2), torch.eye(3).expand(10, 3, 3), atol=1e-5)
    assert torch.allclose(quat_to_rotmat(torch.zeros(1, 4))[0], torch.eye(3))


def one_gaussian(mean, scale=0.1, opacity=0.8, quat=(1.0, 0.0, 0.0, 0.0), channels=3):
    return [
        torch.tensor([mean], dtype=torch.float32),
        torch.tensor([quat], dtype=torch.float32),
        torch.full((1, 3), float(scale)),
        torch.tensor([opacity], dtype=torch.float32),
        torch.ones(1, channels),
    ]


def with_backdrop(extra: list[torch.Tensor], seed: int = 5) -> list[torch.Tensor]:
    """The hard-case Gaussians in front of ordinary ones, so gradients are exercised around them."""
    base = random_gaussians(40, extra[4].shape[1], seed=seed)
    return [torch.cat([e, b]) for e, b in zip(extra, base, strict=True)]


@pytest.fixture
def cam() -> Camera:
    return Camera.look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), width=32, height=24)


def test_gaussian_at_camera_centre(cam):
    assert_backends_agree(with_backdrop(one_gaussian(cam.center.tolist())), cam)


def test_gaussian_behind_camera(cam):
    params = with_backdrop(one_gaussian((0.0, -4.0, 0.0), scale=0.5))
    out, grads = render_and_grads("numba", params, cam)
    assert out.radii[0] == 0
    assert_backends_agree(params, cam)


def test_gaussian_straddling_near_plane(cam):
    assert_backends_agree(with_backdrop(one_gaussian((0.0, -2.985, 0.0), scale=0.05)), cam)


@pytest.mark.parametrize("scale", [1e-8, 1e4])
def test_extreme_scales(cam, scale):
    assert_backends_agree(with_backdrop(one_gaussian((0.1, 0.0, 0.0), scale=scale)), cam)


def test_zero_quaternion(cam):
    assert_backends_agree(with_backdrop(one_gaussian((0.0, 0.0, 0.0), quat=(0.0, 0.0, 0.0, 0.0))), cam)


@pytest.mark.parametrize("logit", [1e4, -1e4])
def test_extreme_opacity_logits(cam, logit):
    params = one_gaussian((0.0, 0.0, 0.0), opacity=float(torch.sigmoid(torch.tensor(logit))))
    assert_backends_agree(with_backdrop(params), cam)


def test_near_degenerate_2d_covariance(cam):
    # A needle seen end-on and a flat disc seen edge-on: 3D covariance rank 1 and rank 2.
    needle = one_gaussian((0.0, 0.0, 0.0))
    needle[2] = torch.tensor([[1e-8, 1.0, 1e-8]])
    disc = one_gaussian((0.2, 0.0, 0.1))
    disc[2] = torch.tensor([[0.5, 1e-8, 0.5]])
    params = with_backdrop([torch.cat([a, b]) for a, b in zip(needle, disc, strict=True)])
    proj = project_gaussians(
        params[0], params[1], params[2], cam.world_to_camera(), cam.intrinsics(), cam.width, cam.height
    )
    assert torch.isfinite(proj.conics).all()
    assert_backends_agree(params, cam)


def test_gaussian_covering_whole_image(cam):
    params = with_backdrop(one_gaussian((0.0, 0.0, 0.0), scale=50.0, opacity=0.5))
    out, _ = render_and_grads("numba", params, cam)
    assert (out.alpha > 0.45).all()
    assert_backends_agree(params, cam)


def test_large_gaussians_centred_off_screen_at_the_clamp_limits(cam):
    # Centres 2 % inside and outside 3DGS's 1.3 tan(fov / 2) on all four sides, wide enough to reach the
    # image: the clamped Jacobian shapes what is rendered, and both backends must clamp alike.
    depth = 2.0  # camera-space z of the centres (the camera sits at y = -3 looking along +y)
    lim_x = 1.3 * 0.5 * cam.width / cam.fx
    lim_y = 1.3 * 0.5 * cam.height / cam.fy
    centres = []
    for factor in (0.98, 1.02):
        for sign in (1.0, -1.0):
            centres.append((sign * lim_x * factor * depth, depth - 3.0, 0.1))
            centres.append((0.1, depth - 3.0, sign * lim_y * factor * depth))
    parts = [one_gaussian(c, scale=0.6, opacity=0.7, quat=(0.9, 0.3, -0.2, 0.1)) for c in centres]
    params = with_backdrop([torch.cat(p) for p in zip(*parts, strict=True)])
    out, _ = render_and_grads("numba", params, cam)
    assert (out.radii[: len(centres)] > 0).all()
    assert_backends_agree(params, cam)


def test_empty_scene_all_culled(cam):
    params = random_gaussians(20, 3)
    params[0] = params[0] - torch.tensor([0.0, 10.0, 0.0])  # all behind the camera
    for backend in ("torch", "numba"):
        out = rasterize(*params, cam, background=torch.tensor([0.2, 0.3, 0.4]), backend=backend)
        assert (out.radii == 0).all()
        assert torch.allclose(out.image, torch.tensor([0.2, 0.3, 0.4]).expand_as(out.image))
        assert (out.alpha == 0).all()
    assert_backends_agree(params, cam)


def test_one_pixel_image():
    cam = Camera.look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), width=1, height=1)
    assert_backends_agree(random_gaussians(30, 3, seed=6, log_scale=-1.0), cam)


def test_tile_with_more_gaussians_than_typical_cap(cam):
    # 3000 overlapping Gaussians in one tile: far beyond the 256-per-batch cap of CUDA rasterizers.
    g = torch.Generator().manual_seed(7)
    n = 3000
    params = [
        torch.randn(n, 3, generator=g) * 0.01,
        torch.randn(n, 4, generator=g),
        torch.full((n, 3), 0.02),
        torch.full((n,), 0.02),
        torch.rand(n, 3, generator=g),
    ]
    assert_backends_agree(params, cam)


def test_backends_agree_with_geometry_detached_for_later_channels(small_camera):
    params = random_gaussians(200, 6, seed=8)
    results = {}
    for backend in ("torch", "numba"):
        leaves = [p.detach().clone().requires_grad_(True) for p in params]
        out = rasterize(*leaves, small_camera, backend=backend, geometry_channels=2)
        g = torch.Generator().manual_seed(2)
        (out.image * torch.randn(out.image.shape, generator=g)).sum().backward()
        results[backend] = [p.grad for p in leaves]
    for name, a, b in zip(NAMES, results["torch"], results["numba"], strict=True):
        assert ((a - b).norm() / a.norm()).item() <= 1e-3, name


@pytest.mark.parametrize("channels, geometry", FIXED_CHANNELS)
def test_kernels_compiled_for_a_channel_count_match_the_reference_and_the_general_kernel(
    small_camera, channels, geometry
):
    """The compositing kernels built for a known channel count (training's and the bench's) against
    the PyTorch reference, and to the bit against the kernels that read the count at run time."""
    params = random_gaussians(200, channels, seed=channels + geometry)
    results = {}
    for backend in ("torch", "numba", "general"):
        leaves = [p.detach().clone().requires_grad_(True) for p in params]
        with _general_kernels(backend == "general"):
            out = rasterize(
                *leaves, small_camera, backend=backend.replace("general", "numba"), geometry_channels=geometry
            )
        g = torch.Generator().manual_seed(3)
        (out.image * torch.randn(out.image.shape, generator=g)).sum().backward()
        results[backend] = (out.image.detach(), [p.grad for p in leaves])
    assert (results["torch"][0] - results["numba"][0]).abs().max() <= 1e-4
    for name, a, b in zip(NAMES, results["torch"][1], results["numba"][1], strict=True):
        assert ((a - b).norm() / a.norm()).item() <= 1e-3, name
    assert torch.equal(results["numba"][0], results["general"][0])
    for name, a, b in zip(NAMES, results["numba"][1], results["general"][1], strict=True):
        assert torch.equal(a, b), name


@contextlib.contextmanager
def _general_kernels(on: bool):
    """The run-time-count kernels for every call while on (composite_cpu._fixed answering none)."""
    if not on:
        yield
        return
    original = composite_cpu._fixed
    composite_cpu._fixed = lambda n_ch, n_geo: ((), ())
    try:
        yield
    finally:
        composite_cpu._fixed = original


def test_detached_channels_pass_no_gradient_to_geometry(small_camera):
    # A loss on channels 2.. only (the language latents) must leave the Gaussians' geometry untouched.
    params = random_gaussians(200, 6, seed=9)
    for backend in ("torch", "numba"):
        leaves = [p.detach().clone().requires_grad_(True) for p in params]
        out = rasterize(*leaves, small_camera, backend=backend, geometry_channels=2)
        out.image[..., 2:].square().sum().backward()
        for name, grad in zip(NAMES[:4], leaves[:4], strict=True):
            assert grad.grad is None or torch.count_nonzero(grad.grad) == 0, f"{backend}: {name}"
        assert torch.count_nonzero(leaves[4].grad[:, 2:]) > 0
        assert torch.count_nonzero(leaves[4].grad[:, :2]) == 0


def test_row_span_holds_every_row_a_dense_scan_reaches():
    # The CPU kernels evaluate a Gaussian on a tile's rows [r0, r1) only: a dense scan of each row's
    # segment must find q above the bound on every row outside, and the span must not run more than a
    # row past the rows the scan reaches (it is widened by rounding margins only).
    import numpy as np

    from langfield.raster.binning import TILE_SIZE
    from langfield.raster.composite_cpu import _row_span

    rng = np.random.default_rng(0)
    f = np.float32
    checked = extra = 0
    for _ in range(3000):
        a, c = rng.uniform(0.001, 2.0, 2)
        b = rng.uniform(-0.999, 0.999) * np.sqrt(a * c) if rng.random() > 0.1 else 0.0  # positive definite
        a, b, c = f(a), f(b), f(c)
        lo = f(rng.uniform(-30, 30))
        hi, dy0, bound = lo + f(15.0), f(rng.uniform(-40, 25)), f(rng.uniform(0.5, 12.0))
        r0, r1 = _row_span(a, b, c, lo, hi, bound, dy0)
        assert 0 <= r0 <= r1 <= TILE_SIZE
        xs = np.linspace(lo, hi, 4001, dtype=np.float64)
        for r in range(TILE_SIZE):
            dy = float(dy0) + r
            q_min = (float(a) * xs * xs + 2 * float(b) * xs * dy + float(c) * dy * dy).min()
            if q_min <= bound:
                assert r0 <= r < r1, (a, b, c, lo, dy0, bound, r, r0, r1)
                checked += 1
            elif r0 <= r < r1:
                extra += 1
    assert checked > 1500
    assert extra < 0.05 * checked  # the span is the reached rows plus rounding, not the whole tile


@pytest.mark.parametrize(
    "conic, bound, expected",
    [
        ((1.0, 0.0, 1.0), -1.0, (0, 0)),  # a Gaussian too faint to reach 1/255 anywhere
        ((1.0, 1.0, 1.0), 9.0, (0, 16)),  # degenerate (det 0): every row is evaluated
        ((1.0, 0.0, 0.0), 9.0, (0, 16)),  # no extent in y
        ((1e-8, 0.0, 1e-8), 9.0, (0, 16)),  # huge: reaches every row
        ((1e8, 0.0, 1e8), 9.0, (4, 5)),  # a point on row 4 (dy0 = -4.0)
    ],
)
def test_row_span_edge_cases(conic, bound, expected):
    from langfield.raster.composite_cpu import _row_span

    a, b, c = conic
    assert _row_span(a, b, c, -2.0, 13.0, bound, -4.0) == expected


def _two_passes(backend: str, params, camera, second_opacities, seed: int = 2):
    """rasterize_with_second_pass on fresh leaves: outputs and every leaf's gradient under random weights."""
    leaves = [p.detach().clone().requires_grad_(True) for p in params]
    means, quats, scales, opacities, features = leaves
    second_values = means.norm(dim=-1, keepdim=True)  # a distance, as the hard depth renders
    out, second = rasterize_with_second_pass(
        means, quats, scales, opacities, features, camera, second_opacities, second_values,
        background=torch.full((features.shape[1],), 0.3), backend=backend, geometry_channels=2,
    )  # fmt: skip
    g = torch.Generator().manual_seed(seed)
    loss = sum((t * torch.randn(t.shape, generator=g)).sum() for t in (out.image, out.alpha, second))
    loss.backward()
    return (out.image, out.alpha, second), [p.grad for p in leaves], out.means2d.grad


@pytest.mark.parametrize("seed", [0, 1])
def test_second_pass_in_one_walk_equals_two_passes(small_camera, seed):
    # The numba backend composites both passes in one walk over the tiles; the torch backend makes two
    # separate rasterize calls (the reference). Some opacities above the second pass's 0.99, some
    # Gaussians dropped from it (opacity 0), as dropout leaves them.
    params = random_gaussians(150, 4, seed=seed, log_scale=-2.0)
    params[3][:10] = 0.995
    second = torch.full((150,), 0.99)
    second[10:40] = 0.0
    ref, ref_grads, ref_m2d = _two_passes("torch", params, small_camera, second)
    fast, fast_grads, fast_m2d = _two_passes("numba", params, small_camera, second)
    for a, b in zip(ref, fast, strict=True):
        assert (a - b).abs().max() <= 1e-4
    # The main pass's screen-space gradient (densification's statistic) leaves the second pass out.
    for name, a, b in zip(NAMES, ref_grads, fast_grads, strict=True):
        rel = ((a - b).norm() / a.norm().clamp_min(1e-12)).item()
        assert rel <= 1e-3, f"{name}: relative gradient error {rel:.2e}"
    assert ((ref_m2d - fast_m2d).norm() / ref_m2d.norm()).item() <= 1e-3


@pytest.mark.parametrize("seed", [0, 1])
def test_second_pass_spent_early_still_equals_two_passes(small_camera, seed):
    # Fern's case: faint Gaussians (opacities 0.01-0.05) behind one another, the second pass at 0.99.
    # The second pass is spent within a few Gaussians of each pixel while the first goes on, so the
    # numba walk skips it for the rest of each row (forward and backward); nothing may change.
    params = random_gaussians(400, 4, seed=seed, log_scale=-1.0)
    params[3] = 0.01 + 0.04 * torch.rand(400, generator=torch.Generator().manual_seed(seed))
    second = torch.full((400,), 0.99)
    ref, ref_grads, _ = _two_passes("torch", params, small_camera, second)
    fast, fast_grads, _ = _two_passes("numba", params, small_camera, second)
    # The second pass's alpha (its value 1): spent (T under 1 %) at most pixels; the first is not.
    ones = torch.ones(400, 1)
    _, alpha_h = rasterize_with_second_pass(*params, small_camera, second, ones, backend="numba")
    assert float((alpha_h > 0.99).float().mean()) > 0.9 and float(ref[1].mean()) < 0.7
    for a, b in zip(ref, fast, strict=True):
        assert (a - b).abs().max() <= 1e-4
    for name, a, b in zip(NAMES, ref_grads, fast_grads, strict=True):
        rel = ((a - b).norm() / a.norm().clamp_min(1e-12)).item()
        assert rel <= 1e-3, f"{name}: relative gradient error {rel:.2e}"


def test_second_pass_moves_only_what_it_renders_with(small_camera):
    # The second pass alone: rotations and scales detached, the first pass's features untouched.
    params = random_gaussians(80, 3, seed=4, log_scale=-2.0)
    leaves = [p.detach().clone().requires_grad_(True) for p in params]
    means, quats, scales, opacities, features = leaves
    out, second = rasterize_with_second_pass(
        means, quats, scales, opacities, features, small_camera, torch.full((80,), 0.99), means[:, 2:3]
    )
    second.sum().backward()
    assert means.grad.abs().sum() > 0
    for other in (quats, scales, opacities, features, out.means2d):
        assert other.grad is None or other.grad.abs().sum() == 0


def test_second_pass_rejects_footprints_that_differ(small_camera):
    from langfield.raster.composite_cpu import rasterize_pair_cpu

    m, c = torch.zeros(2, 2), torch.ones(2, 3)
    with pytest.raises(ValueError, match="footprints"):
        rasterize_pair_cpu(
            m, c, torch.ones(2), torch.ones(2, 1), m + 1, c, torch.ones(2), torch.ones(2, 1),
            torch.zeros(2, dtype=torch.int64), torch.zeros(0, dtype=torch.int64), 16, 16, torch.zeros(1),
        )  # fmt: skip


def _slots(n: int, sizes: list[int], seed: int) -> torch.Tensor:
    """[n, len(sizes)] columns: level l's in its own range of sizes[l] after the ones before, -1 for some."""
    g = torch.Generator().manual_seed(seed)
    cols, base = [], 0
    for size in sizes:
        c = torch.randint(0, size, (n,), generator=g) + base
        cols.append(torch.where(torch.rand(n, generator=g) < 0.2, -1, c))
        base += size
    return torch.stack(cols, dim=1)


@pytest.mark.parametrize("seed", [0, 1])
def test_slot_render_equals_the_render_of_one_hot_rows(small_camera, seed):
    # The vote's weights per codebook entry: numba adds each hit to a Gaussian's own columns only; the
    # reference makes the one-hot rows and composites them as any channels, in either backend.
    from langfield.raster import one_hot_rows, rasterize_slots

    means, quats, scales, opacities, _ = random_gaussians(150, 1, seed=seed, log_scale=-2.0)
    opacities[:10] = 0.995  # saturated pixels end early in both
    sizes = [7, 30, 4]
    slots = _slots(150, sizes, seed)
    geometry = (means, quats, scales, opacities)
    rows = one_hot_rows(slots, sum(sizes))
    assert rows.sum(dim=1).tolist() == (slots >= 0).sum(dim=1).tolist()
    for backend in ("torch", "numba"):
        reference = rasterize(*geometry, rows, small_camera, backend=backend).image
        got = rasterize_slots(*geometry, slots, sum(sizes), small_camera, backend=backend)
        assert got.shape == (small_camera.height, small_camera.width, sum(sizes))
        assert (got - reference).abs().max() <= 1e-5, backend
    assert got.amax() > 0.5  # the columns carry real weight


def test_slot_render_refuses_columns_it_has_no_channel_for(small_camera):
    from langfield.raster.composite_cpu import rasterize_slots_cpu

    m, c, o = torch.zeros(2, 2), torch.ones(2, 3), torch.ones(2)
    lists = (torch.zeros(2, dtype=torch.int64), torch.zeros(0, dtype=torch.int64), 16, 16)
    with pytest.raises(ValueError, match="below n_slots=3"):
        rasterize_slots_cpu(m, c, o, torch.tensor([[0], [3]]), 3, *lists)
    with pytest.raises(ValueError, match=r"\[N, K >= 1\]"):
        rasterize_slots_cpu(m, c, o, torch.zeros(2, 0, dtype=torch.long), 3, *lists)


def test_cpu_is_the_numba_backends_earlier_name(capsys) -> None:
    """``cpu`` still selects the numba kernels, said once; a field saved with it reads ``numba``."""
    import langfield.kernels as kernels_module
    from langfield.io.field_meta import FieldMeta
    from langfield.raster import kernels, resolve_backend

    kernels_module._aliases_noticed.clear()
    assert resolve_backend("cpu") == resolve_backend("auto") == "numba"
    assert kernels("cpu") == kernels("numba") != kernels("torch")
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["langfield: backend 'cpu' is now called 'numba'"]
    assert FieldMeta({"backend": "cpu"}).backend == "numba"
    with pytest.raises(ValueError, match="choose from auto, torch, numba"):
        resolve_backend("gpu")
