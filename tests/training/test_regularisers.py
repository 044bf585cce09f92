"""Sparse-view regularisers (langfield/training/regularisers.py) and their use in training."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import langfield as lf
from langfield.camera import Camera
from langfield.synthetic import make_room
from langfield.training.regularisers import (
    anisotropy_loss,
    dark_backdrop,
    depth_smoothness,
    depth_spread_loss,
    drop_compensation,
    opacity_noise,
    orbit_camera,
    reprojection_warp,
    shifted_camera,
    virtual_shift,
    virtual_view_warp,
    z_depth,
)


def test_dropout_drops_the_rate_and_keeps_the_expected_opacity() -> None:
    g = torch.Generator().manual_seed(0)
    factors = drop_compensation(100_000, 0.2, g)
    assert (factors == 0).float().mean() == pytest.approx(0.2, abs=0.005)
    assert torch.allclose(factors[factors > 0], torch.tensor(1.25))
    assert factors.mean() == pytest.approx(1.0, abs=0.01)
    assert torch.equal(drop_compensation(10, 0.0, g), torch.ones(10))
    with pytest.raises(ValueError, match="drop rate"):
        drop_compensation(10, 1.0, g)


def test_opacity_noise_is_clipped_gaussian_around_one() -> None:
    g = torch.Generator().manual_seed(0)
    factors = opacity_noise(100_000, 0.2, g)
    spread = (factors - 1.0).abs()
    assert float(spread.max()) <= 0.2 + 1e-6
    assert factors.mean() == pytest.approx(1.0, abs=0.005)
    # N(0, 0.2^2) clipped at one sigma: about 32 % of the draws sit on the bounds.
    on_bounds = (spread >= 0.2 - 1e-6).float().mean()
    assert on_bounds == pytest.approx(0.317, abs=0.01)
    assert torch.equal(opacity_noise(10, 0.0, g), torch.ones(10))
    with pytest.raises(ValueError, match="opacity noise"):
        opacity_noise(10, 1.0, g)


def test_shifted_camera_moves_along_its_own_x_and_y_axes() -> None:
    cam = Camera.look_at((0.0, -3.0, 1.0), (0.0, 0.0, 1.0), width=40, height=30)
    moved = shifted_camera(cam, 0.5)
    np.testing.assert_allclose(moved.center - cam.center, 0.5 * cam.c2w[:3, 0])
    np.testing.assert_allclose(moved.c2w[:3, :3], cam.c2w[:3, :3])
    lifted = shifted_camera(cam, 0.0, 0.25)
    np.testing.assert_allclose(lifted.center - cam.center, [0.0, 0.0, 0.25])  # the camera's up is world z


def test_virtual_shift_length_and_direction() -> None:
    depth, valid = torch.full((10, 10), 4.0), torch.ones(10, 10, dtype=torch.bool)
    rng = np.random.default_rng(0)
    stereo = [virtual_shift(depth, valid, 0.1, rng) for _ in range(200)]
    assert all(up == 0.0 and 0.2 <= abs(right) <= 0.4 for right, up in stereo)
    assert {np.sign(right) for right, _ in stereo} == {-1.0, 1.0}
    free = np.array([virtual_shift(depth, valid, 0.1, rng, any_direction=True) for _ in range(200)])
    lengths = np.linalg.norm(free, axis=1)
    assert lengths.min() >= 0.2 - 1e-9 and lengths.max() <= 0.4 + 1e-9
    assert (np.abs(free[:, 1]) > 0.1).mean() > 0.3  # vertical shifts occur
    assert virtual_shift(depth, torch.zeros_like(valid), 0.1, rng) == (0.0, 0.0)  # nothing covered


def test_virtual_shift_sized_by_the_cameras_spacing() -> None:
    depth, valid = torch.full((10, 10), 4.0), torch.ones(10, 10, dtype=torch.bool)

    def lengths(spacing: float) -> np.ndarray:
        rng = np.random.default_rng(0)
        shifts = [virtual_shift(depth, valid, 0.1, rng, True, spacing) for _ in range(50)]
        return np.linalg.norm(np.array(shifts), axis=1)

    # The spacing is shorter than 0.1 of the depth: the depth's shift, drawn exactly as without it.
    np.testing.assert_array_equal(lengths(0.3), lengths(0.0))
    wide = lengths(1.2)  # longer: the spacing's length, times the same draw in [0.5, 1]
    assert wide.min() >= 0.6 - 1e-9 and wide.max() <= 1.2 + 1e-9
    np.testing.assert_allclose(wide / lengths(0.0), 3.0)
    assert lengths(10.0).max() <= 4.0 + 1e-9  # never longer than the median depth


def test_z_depth_of_a_plane_is_constant() -> None:
    cam = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=40, height=30)
    v, u = torch.meshgrid(torch.arange(30) + 0.5, torch.arange(40) + 0.5, indexing="ij")
    ray = torch.sqrt(((u - cam.cx) / cam.fx) ** 2 + ((v - cam.cy) / cam.fy) ** 2 + 1)
    torch.testing.assert_close(z_depth(2.0 * ray, cam), torch.full((30, 40), 2.0))


def test_the_warp_with_the_true_depth_gives_back_the_training_image() -> None:
    """A fronto-parallel plane at z: the shifted view sees column u at u - fx b / z."""
    cam = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=64, height=16)
    z, b = 2.0, 0.1
    disparity = cam.fx * b / z
    u = torch.arange(64, dtype=torch.float32) + 0.5
    pattern = lambda x: torch.sin(x / 5.0)  # noqa: E731
    training = pattern(u).expand(16, 64)[..., None].repeat(1, 1, 3)
    shifted = pattern(u + disparity).expand(16, 64)[..., None].repeat(1, 1, 3)
    warped, valid = virtual_view_warp(shifted, torch.full((16, 64), z), cam, b)
    assert valid.sum() > 0.8 * valid.numel() and not valid[:, 0].any()  # the left edge comes from outside
    # Bilinear sampling of sin(x / 5) errs by at most h^2 / 8 * |f"| = 1 / 200.
    torch.testing.assert_close(warped[valid], training[valid], atol=5.1e-3, rtol=0)


def test_the_vertical_warp_with_the_true_depth_gives_back_the_training_image() -> None:
    """Camera moved up by b: a point at z seen at row v is at row v + fy b / z in the lifted view."""
    cam = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=16, height=64)
    z, b = 2.0, 0.1
    disparity = cam.fy * b / z
    v = torch.arange(64, dtype=torch.float32) + 0.5
    pattern = lambda x: torch.sin(x / 5.0)  # noqa: E731
    training = pattern(v)[:, None].expand(64, 16)[..., None].repeat(1, 1, 3)
    lifted = pattern(v - disparity)[:, None].expand(64, 16)[..., None].repeat(1, 1, 3)
    warped, valid = virtual_view_warp(lifted, torch.full((64, 16), z), cam, 0.0, b)
    assert valid.sum() > 0.8 * valid.numel() and not valid[-1].any()  # the bottom rows come from outside
    torch.testing.assert_close(warped[valid], training[valid], atol=5.1e-3, rtol=0)


def test_the_warp_matches_a_render_of_the_shifted_camera() -> None:
    """Against the rasterizer: a textured plane of small Gaussians rendered from the lifted camera and
    warped back with the plane's depth gives the training render (up to resampling)."""
    from langfield.model import gaussians as G
    from langfield.raster import rasterize

    cam = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=48, height=40)
    ys, xs = torch.meshgrid(torch.linspace(-1.6, 1.6, 90), torch.linspace(-1.6, 1.6, 90), indexing="ij")
    means = torch.stack([xs.flatten(), ys.flatten(), torch.full((8100,), -2.0)], dim=1)
    colors = (0.5 + 0.5 * torch.sin(3 * means[:, :1] + 5 * means[:, 1:2])).repeat(1, 3)
    splats = G.gaussians_at(means, init_opacity=0.99)

    def render(c: Camera) -> torch.Tensor:
        out = rasterize(splats["means"], splats["quats"], G.scales(splats), G.opacities(splats), colors, c)
        return out.image.detach()

    right, up = 0.06, -0.08
    lifted = render(shifted_camera(cam, right, up))
    warped, valid = virtual_view_warp(lifted, torch.full((40, 48), 2.0), cam, right, up)
    inner = valid.clone()
    inner[:3], inner[-3:], inner[:, :3], inner[:, -3:] = False, False, False, False
    assert inner.sum() > 0.6 * inner.numel()
    assert (warped - render(cam)).abs()[inner].mean() < 0.03


def test_the_warp_passes_gradient_to_the_depth() -> None:
    cam = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=32, height=8)
    u = torch.arange(32, dtype=torch.float32) + 0.5
    shifted = torch.sin(u / 3.0).expand(8, 32)[..., None].repeat(1, 1, 3)
    depth = torch.full((8, 32), 2.0, requires_grad=True)
    warped, valid = virtual_view_warp(shifted, depth, cam, 0.1)
    warped[valid].sum().backward()
    assert depth.grad is not None and depth.grad.abs().sum() > 0


def test_the_reprojection_warp_of_a_shifted_camera_is_the_binocular_warp() -> None:
    """The general warp against the closed-form one (values and the depth's gradient)."""
    cam = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=40, height=30)
    rng = torch.Generator().manual_seed(0)
    other_image = torch.rand(30, 40, 3, generator=rng)
    base = 2.0 + 0.5 * torch.rand(30, 40, generator=rng)
    right, up = 0.07, -0.05
    depth_a = base.clone().requires_grad_(True)
    depth_b = base.clone().requires_grad_(True)
    expected, expected_valid = virtual_view_warp(other_image, depth_a, cam, right, up)
    warped, valid = reprojection_warp(other_image, depth_b, cam, shifted_camera(cam, right, up))
    assert torch.equal(valid, expected_valid) and valid.sum() > 0.7 * valid.numel()
    torch.testing.assert_close(warped, expected, atol=1e-5, rtol=0)
    weights = torch.rand(30, 40, 3, generator=rng)
    (expected * weights)[expected_valid].sum().backward()
    (warped * weights)[valid].sum().backward()
    torch.testing.assert_close(depth_b.grad, depth_a.grad, atol=1e-4, rtol=1e-3)


def test_the_reprojection_warp_leaves_out_what_the_other_view_sees_occluded() -> None:
    cam = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=16, height=12)
    other = shifted_camera(cam, 0.05)
    image = torch.rand(12, 16, 3)
    depth = torch.full((12, 16), 2.0)
    _, free = reprojection_warp(image, depth, cam, other, torch.full((12, 16), 2.0))
    _, hidden = reprojection_warp(image, depth, cam, other, torch.full((12, 16), 1.5))
    _, empty = reprojection_warp(image, depth, cam, other, torch.zeros(12, 16))
    assert free.sum() > 0.7 * free.numel() and not hidden.any() and torch.equal(empty, free)


def _stripes(
    cam: Camera, depth: float, other: Camera, flip: bool = False, white_from: float = 9.0
) -> torch.Tensor:
    """[h, w, 3] what ``other`` sees of a plane at z-depth ``depth`` before ``cam`` (same axes), painted
    with sin(x / 0.15) along world x (1 - that with ``flip``), white from x = ``white_from`` on."""
    v, u = torch.meshgrid(torch.arange(other.height) + 0.5, torch.arange(other.width) + 0.5, indexing="ij")
    x = other.center[0] + (u - other.cx) / other.fx * depth  # the plane faces both cameras squarely
    paint = 0.5 + 0.5 * torch.sin(x / 0.15)
    paint = torch.where(x >= white_from, torch.ones_like(paint), 1.0 - paint if flip else paint)
    return paint[..., None].repeat(1, 1, 3).float()


def _crossview_setup() -> tuple[Camera, list[Camera], float]:
    cam = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=64, height=16)
    return cam, [shifted_camera(cam, 0.3), shifted_camera(cam, -0.3)], 2.0


def test_the_cross_view_term_is_least_at_the_true_depth_and_pulls_towards_it() -> None:
    from langfield.training.losses import cross_view_loss

    cam, others, z = _crossview_setup()
    image = _stripes(cam, z, cam)
    photos = [(o, _stripes(cam, z, o)) for o in others]
    covered = torch.ones(16, 64, dtype=torch.bool)

    def loss_and_slope(depth: float) -> tuple[float, float]:
        d = torch.full((16, 64), depth, requires_grad=True)
        loss = cross_view_loss(d, covered, image, cam, photos)
        loss.backward()
        return float(loss.detach()), float(d.grad.sum())

    at_truth, _ = loss_and_slope(z)
    far, far_slope = loss_and_slope(z * 1.08)
    near, near_slope = loss_and_slope(z * 0.93)
    assert at_truth < 0.02 and far > 5 * at_truth and near > 5 * at_truth
    assert far_slope > 0 and near_slope < 0  # descent moves the depth back to the plane


def test_the_cross_view_term_takes_the_photo_that_agrees_per_pixel() -> None:
    """A second photo that disagrees everywhere (as one that sees the surface occluded) changes nothing;
    pixels no other photo sees and pixels the field does not cover are left out."""
    from langfield.training.losses import cross_view_loss

    cam, (left, right), z = _crossview_setup()
    image, depth = _stripes(cam, z, cam), torch.full((16, 64), z)
    good, bad = (left, _stripes(cam, z, left)), (right, torch.full((16, 64, 3), 2.0))
    covered = torch.ones(16, 64, dtype=torch.bool)
    _, seen = reprojection_warp(good[1], depth, cam, left)
    assert 0.8 * seen.numel() < seen.sum() < seen.numel()  # the left photo misses an edge
    alone = float(cross_view_loss(depth, seen, image, cam, [good]))
    assert 0 < alone < 0.02
    assert float(cross_view_loss(depth, covered, image, cam, [good])) == pytest.approx(alone, abs=1e-7)
    assert float(cross_view_loss(depth, seen, image, cam, [bad, good])) == pytest.approx(alone, abs=1e-7)
    assert float(cross_view_loss(depth, seen, image, cam, [bad])) > 20 * alone
    d = depth.clone().requires_grad_(True)
    nothing = torch.zeros(16, 64, dtype=torch.bool)
    for empty in (
        cross_view_loss(d, nothing, image, cam, [good]),
        cross_view_loss(d, covered, image, cam, []),
    ):
        assert float(empty.detach()) == 0.0
        empty.backward()  # still part of the graph
    assert float(d.grad.abs().sum()) == 0.0


def test_the_cross_view_term_leaves_out_what_has_no_texture() -> None:
    """A white wall matches white at any depth; what moves its surface there is only the stripes at its
    edge: it is left out, however wrong its depth."""
    from langfield.training.losses import cross_view_loss, textured

    cam, others, z = _crossview_setup()
    image = _stripes(cam, z, cam, white_from=0.3)
    photos = [(o, _stripes(cam, z, o, white_from=0.3)) for o in others]
    kept = textured(image, 0.02)
    assert kept[:, :39].all() and not kept[:, 40:].any()
    covered = torch.ones(16, 64, dtype=torch.bool)
    at_truth = float(cross_view_loss(torch.full((16, 64), z), covered, image, cam, photos))
    for min_std, moved in ((0.02, False), (-1.0, True)):
        depth = torch.full((16, 64), z)
        depth[:, 40:] = 0.6 * z  # the wall's depth far off
        depth.requires_grad_(True)
        loss = cross_view_loss(depth, covered, image, cam, photos, min_std=min_std)
        loss.backward()
        assert bool((depth.grad[:, 40:] != 0).any()) == moved
        if not moved:  # the kept pixels' SSIM windows reach the wall: a trace of it remains
            assert float(loss.detach()) == pytest.approx(at_truth, rel=0.01)


def test_an_orbiting_camera_keeps_its_pivot_in_the_image_centre() -> None:
    cam = Camera.look_at((0.3, -2.0, 0.5), (0.0, 0.0, 0.2), width=40, height=30)
    pivot = 1.5
    target = cam.center + pivot * cam.forward
    for right, up in ((0.4, 0.0), (0.0, -0.3), (0.2, 0.25)):
        turned = orbit_camera(cam, right, up, pivot)
        uv, z = turned.project(target[None])
        np.testing.assert_allclose(uv[0], (cam.cx, cam.cy), atol=1e-9)
        assert z[0] == pytest.approx(pivot)
        # The angle is the arc length over the radius; a small one moves the centre as the shift does.
        cosine = np.dot(cam.center - target, turned.center - target) / pivot**2
        assert math.acos(np.clip(cosine, -1, 1)) == pytest.approx(math.hypot(right, up) / pivot)
    small = orbit_camera(cam, 1e-4, -2e-4, pivot)
    np.testing.assert_allclose(small.center, shifted_camera(cam, 1e-4, -2e-4).center, atol=1e-7)
    assert np.array_equal(orbit_camera(cam, 0.0, 0.0, pivot).c2w, cam.c2w)


def test_anisotropy_penalises_needles_only() -> None:
    iso = torch.zeros(5, 3)
    needle = torch.log(torch.tensor([[1.0, 0.01, 0.01]])).requires_grad_(True)
    assert float(anisotropy_loss(iso, 10.0)) == 0.0
    loss = anisotropy_loss(needle, 10.0)
    assert float(loss) == pytest.approx(90.0, rel=1e-4)
    loss.backward()
    assert needle.grad[0, 0] > 0 and needle.grad[0, 1] < 0  # shrink the long axis, grow the short one
    assert float(anisotropy_loss(torch.zeros(0, 3), 10.0)) == 0.0


def test_depth_smoothness_is_scale_free_and_allows_steps_at_image_edges() -> None:
    image = torch.zeros(8, 8, 3)
    image[:, 4:] = 1.0  # an edge between columns 3 and 4
    valid = torch.ones(8, 8, dtype=torch.bool)
    flat = torch.full((8, 8), 2.0)
    step_at_edge = flat.clone()
    step_at_edge[:, 4:] = 4.0
    step_elsewhere = flat.clone()
    step_elsewhere[:, 2:] = 4.0
    assert float(depth_smoothness(flat, image, valid)) == 0.0
    assert float(depth_smoothness(step_at_edge, image, valid)) < 1e-4 * float(
        depth_smoothness(step_elsewhere, image, valid)
    )
    torch.testing.assert_close(
        depth_smoothness(10 * step_elsewhere, image, valid), depth_smoothness(step_elsewhere, image, valid)
    )
    assert float(depth_smoothness(step_elsewhere, image, torch.zeros(8, 8, dtype=torch.bool))) == 0.0


def test_depth_spread_loss_is_scale_free_and_empty_views_give_zero() -> None:
    spread = torch.rand(6, 8, generator=torch.Generator().manual_seed(0))
    alpha = torch.rand(6, 8, generator=torch.Generator().manual_seed(1))
    depth = alpha * 3.0
    loss = depth_spread_loss(spread, depth, alpha)
    assert float(loss) == pytest.approx(float(spread.mean()) / 9.0, rel=1e-6)
    torch.testing.assert_close(depth_spread_loss(100 * spread, 10 * depth, alpha), loss)
    nothing = depth_spread_loss(torch.zeros(6, 8), torch.zeros(6, 8), torch.zeros(6, 8))
    assert float(nothing) == 0.0


def test_the_spread_term_renders_from_its_start_on(scene, monkeypatch) -> None:
    from langfield.field import LanguageField

    asked = []
    real = LanguageField.render
    monkeypatch.setattr(
        LanguageField,
        "render",
        lambda self, cam, **k: asked.append(k.get("depth_spread", False)) or real(self, cam, **k),
    )
    cfg = lf.TrainConfig(
        iterations=6, num_gaussians=200, init="random", language=False, depth=False, lambda_virtual=0.0
    )
    lf.train(scene, dataclasses.replace(cfg, lambda_spread=1.0, spread_start=0.5), progress=False)
    assert asked[:6] == [False] * 3 + [True] * 3
    asked.clear()
    lf.train(scene, cfg, progress=False)  # off by default
    assert not any(asked)


@pytest.fixture(scope="module")
def scene(room_factory):
    return lf.load_scene(room_factory(48, 36, n_test=1))


@pytest.mark.slow
def test_training_with_every_regulariser_runs_each_term_and_records_it(scene) -> None:
    more = {"lambda_virtual": 1.0, "lambda_anisotropy": 0.1, "lambda_smooth": 0.1, "lambda_spread": 1.0,
            "lambda_visibility": 1.0, "spread_start": 0.0, "virtual_every": 2, "opacity_noise": 0.1,
            "virtual_motion": "orbit", "lambda_crossview": 1.0}  # fmt: skip
    cfg = lf.TrainConfig(iterations=6, num_gaussians=300, init="random", drop_gamma=0.2, **more)
    field = lf.train(scene, cfg, progress=False)
    assert all(torch.isfinite(p).all() for p in field.splats.values())
    (record,) = field.meta["loss_terms"]  # one stretch: fewer iterations than LOSS_LOG_EVERY
    assert record["iterations"] == [0, 5]
    # Each term ran where its schedule says: the virtual view every second step, the rest every step.
    steps = record["steps"]
    assert steps["virtual"] == 3
    for name in ("color", "anisotropy", "smooth", "spread", "visibility", "crossview", "opacity"):
        assert steps[name] == 6, name
    # The weighted terms add up to the total, and the penalties that cannot be negative are not.
    assert sum(record["terms"].values()) == pytest.approx(record["total"], rel=1e-6)
    assert all(record["terms"][n] >= 0 for n in ("anisotropy", "smooth", "spread", "visibility", "crossview"))
    assert record["terms"]["color"] > 0


def test_train_flags_set_every_regulariser(scene, tmp_path) -> None:
    import json

    from langfield.cli import main

    out = tmp_path / "out"
    flags = ["--drop-gamma", "0.3", "--lambda-virtual", "0.5", "--virtual-baseline", "0.25"]
    flags += ["--no-random-background", "--lambda-smooth", "0.01", "--lambda-anisotropy", "0.02"]
    flags += [
        "--no-dark-backdrop",
        "--lambda-empty",
        "0.5",
        "--opacity-decay",
        "0.99",
        "--virtual-every",
        "3",
        "--virtual-resolution",
        "0.5",
        "--half-resolution-until",
        "0.5",
        "--lambda-visibility",
        "0.1",
        "--lambda-spread",
        "0.05",
        "--opacity-noise",
        "0.1",
        "--virtual-motion",
        "orbit",
        "--lambda-crossview",
        "0.3",
        "--lambda-stereo",
        "0.4",
    ]
    argv = ["train", str(scene.root), "--out", str(out), "--iterations", "1", "--num-gaussians", "200"]
    assert main([*argv, "--init", "random", *flags]) == 0
    recorded = json.loads((out / "field.json").read_text())["config"]
    expected = {"drop_gamma": 0.3, "lambda_virtual": 0.5, "virtual_baseline": 0.25}
    expected.update(random_background=False, lambda_smooth=0.01, lambda_anisotropy=0.02)
    expected.update(dark_backdrop=False, lambda_empty=0.5, opacity_decay=0.99, virtual_every=3)
    expected.update(virtual_resolution=0.5, half_resolution_until=0.5, lambda_visibility=0.1)
    expected.update(lambda_spread=0.05, opacity_noise=0.1, virtual_motion="orbit", lambda_crossview=0.3)
    expected.update(lambda_stereo=0.4)
    assert {k: recorded[k] for k in expected} == expected
    assert main([*argv, "--force", "--random-background"]) == 0
    assert json.loads((out / "field.json").read_text())["config"]["random_background"] is True


@pytest.mark.parametrize(("every", "start", "steps"), [(1, 0, 7), (3, 0, 3), (2, 2, 3), (10, 0, 1)])
def test_virtual_term_runs_on_every_nth_iteration_from_its_start(
    scene, monkeypatch, every, start, steps
) -> None:
    cfg = lf.TrainConfig(
        iterations=7,
        num_gaussians=200,
        init="random",
        language=False,
        depth=False,
        virtual_every=every,
        virtual_start=start,
    )
    (record,) = lf.train(scene, cfg, progress=False).meta["loss_terms"]
    assert record["steps"]["virtual"] == steps
    assert record["steps"]["color"] == 7


def _spy_render_sizes(monkeypatch) -> list[tuple[int, int]]:
    """The (width, height) of every camera LanguageField.render is called with, from now on."""
    from langfield.field import LanguageField

    sizes = []
    real = LanguageField.render
    monkeypatch.setattr(
        LanguageField,
        "render",
        lambda self, cam, **k: sizes.append((cam.width, cam.height)) or real(self, cam, **k),
    )
    return sizes


def test_virtual_term_at_a_lower_resolution_renders_the_shifted_view_smaller(scene, monkeypatch) -> None:
    sizes = _spy_render_sizes(monkeypatch)
    cfg = lf.TrainConfig(
        iterations=3,
        num_gaussians=200,
        init="random",
        language=False,
        depth=False,
        virtual_resolution=0.5,
        virtual_every=1,
        half_resolution_until=0.0,
    )
    field = lf.train(scene, cfg, progress=False)
    assert sizes == [(48, 36), (24, 18)] * 3
    assert field.meta["config"]["virtual_resolution"] == 0.5
    assert all(torch.isfinite(p).all() for p in field.splats.values())


def test_the_orbiting_virtual_view_turns_about_the_rendered_depth(scene, monkeypatch) -> None:
    from langfield.training import losses

    turned = []

    def spy(cam, right, up, pivot):
        turned.append((cam, pivot, losses.shifted_camera(cam, right, up).center))
        return orbit_camera(cam, right, up, pivot)

    monkeypatch.setattr(losses, "orbit_camera", spy)
    cfg = lf.TrainConfig(iterations=4, num_gaussians=300, init="random", language=False, depth=False,
                         virtual_motion="orbit", virtual_every=1, half_resolution_until=0.0)  # fmt: skip
    field = lf.train(scene, cfg, progress=False)
    assert len(turned) == 4 and all(torch.isfinite(p).all() for p in field.splats.values())
    # Each pivot is a depth inside the room, and each turn moves the camera.
    for cam, pivot, shifted_centre in turned:
        assert 0.1 < pivot < 20.0
        assert np.linalg.norm(shifted_centre - cam.center) > 0


def test_both_motions_orbit_on_some_virtual_views_and_shift_on_others(scene, monkeypatch) -> None:
    from langfield.training import losses

    taken = []
    monkeypatch.setattr(losses, "orbit_camera", lambda *a: taken.append("orbit") or orbit_camera(*a))
    monkeypatch.setattr(losses, "shifted_camera", lambda *a: taken.append("shift") or shifted_camera(*a))
    cfg = lf.TrainConfig(iterations=12, num_gaussians=300, init="random", language=False, depth=False,
                         virtual_motion="both", virtual_every=1, half_resolution_until=0.0)  # fmt: skip
    lf.train(scene, cfg, progress=False)
    assert len(taken) == 12 and {"orbit", "shift"} <= set(taken)


def test_area_resize_averages_blocks_and_passes_gradient() -> None:
    from langfield.training.targets import area_resize

    x = torch.arange(4 * 6 * 2, dtype=torch.float32).reshape(4, 6, 2).requires_grad_(True)
    small = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=3, height=2)
    (y,) = area_resize([x], small)
    expected = x.detach().reshape(2, 2, 3, 2, 2).mean(dim=(1, 3))
    torch.testing.assert_close(y, expected)
    y.sum().backward()
    torch.testing.assert_close(x.grad, torch.full_like(x, 0.25))


def test_dropout_changes_training_and_rendering_uses_every_gaussian(scene) -> None:
    base = lf.TrainConfig(
        iterations=4, num_gaussians=300, init="random", language=False, depth=False, drop_gamma=0.0
    )
    plain = lf.train(scene, base, progress=False)
    dropped = lf.train(scene, lf.TrainConfig(**{**base.__dict__, "drop_gamma": 0.5}), progress=False)
    assert not torch.equal(plain.splats["means"], dropped.splats["means"])
    cam = scene.camera(scene.names("test")[0])
    with torch.no_grad():
        a, b = dropped.render(cam), dropped.render(cam)
    assert torch.equal(a.rgb, b.rgb)  # no dropout outside training


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("drop_gamma", 0.95),
        ("lambda_virtual", -1.0),
        ("anisotropy_ratio", 0.5),
        ("virtual_every", 0),
        ("virtual_resolution", 0.0),
        ("virtual_resolution", 1.5),
        ("half_resolution_until", 1.5),
        ("lambda_spread", -1.0),
        ("spread_start", 1.5),
    ],
)
def test_bad_regulariser_settings_are_refused(key, value) -> None:
    with pytest.raises(ValueError, match=key):
        lf.TrainConfig(**{key: value})


@pytest.mark.export
def test_training_with_a_tiny_onnx_refiner_runs_end_to_end(scene, tmp_path) -> None:
    pytest.importorskip("onnxscript", reason="needs the export extra (make test-export)")
    from encoders.export.refiner import export_refiner

    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3, padding=1))
    folder = tmp_path / "refiner"
    export_refiner(net, folder, confidence=True)
    base = dict(iterations=6, num_gaussians=300, init="random", language=False, depth=False)
    plain = lf.train(scene, lf.TrainConfig(**base), progress=False)
    refined = lf.train(
        scene,
        lf.TrainConfig(**base, refiner=str(folder), refiner_start=0, refiner_every=2, lambda_refiner=1.0),
        progress=False,
    )
    assert refined.meta["config"]["refiner"] == str(folder)
    assert all(torch.isfinite(p).all() for p in refined.splats.values())
    assert not torch.equal(plain.splats["means"], refined.splats["means"])  # the pseudo views trained it


def test_a_bad_refiner_folder_stops_training_before_work(scene, tmp_path) -> None:
    from encoders.manifest import ManifestError

    with pytest.raises(ManifestError, match="missing"):
        lf.train(scene, lf.TrainConfig(iterations=2, refiner=str(tmp_path / "missing")), progress=False)


def test_dark_backdrop_is_a_tall_dark_region_at_the_border() -> None:
    image = np.full((60, 80, 3), 0.8, np.float32)
    image[:20] = 0.02  # a black backdrop along the top: a run of 20 rows, a third of the height
    image[30:55, 30:50] = 0.0  # a black object inside the frame: tall enough, but not at the border
    image[50:53, :10] = 0.0  # a dark strip at the border, 3 rows: too short a run
    backdrop = dark_backdrop(image)
    assert backdrop[:20].all() and backdrop[20:].sum() == 0
    assert not dark_backdrop(np.full((60, 80, 3), 0.5, np.float32)).any()
    assert dark_backdrop(np.zeros((60, 80, 3), np.float32)).all()  # all black: all backdrop
    assert dark_backdrop(np.zeros((1, 1, 3), np.float32)).all()  # one pixel
    brighter = image.copy()
    brighter[:20, :, 1] = 0.2  # one channel above 30/255: not dark
    assert not dark_backdrop(brighter).any()


def test_empty_space_comes_from_alpha_or_a_dark_backdrop(tmp_path) -> None:
    import cv2

    from langfield.training.targets import empty_space

    root = make_room(tmp_path / "room", seed=0, width=40, height=30, n_test=1)
    with_alpha = lf.load_scene(root)
    coverage, source = empty_space(with_alpha, lf.TrainConfig())
    assert source == "alpha" and set(coverage) == set(with_alpha.names("train"))
    for name, c in coverage.items():
        np.testing.assert_array_equal(c.numpy(), with_alpha.alpha(name))
    for path in (root / "images").glob("*.png"):
        opaque = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if path.stem == "train_000":
            opaque[:10] = 0  # a black backdrop along the top of one view
        cv2.imwrite(str(path), opaque)
    photos = lf.load_scene(root)
    coverage, source = empty_space(photos, lf.TrainConfig())
    assert source == "dark backdrop" and list(coverage) == ["train_000"]
    assert (coverage["train_000"][:10] == 0).all() and coverage["train_000"][10:].mean() > 0.9
    assert empty_space(photos, lf.TrainConfig(dark_backdrop=False)) == ({}, None)


def test_backdrop_target_replaces_only_the_empty_part() -> None:
    from langfield.training.targets import backdrop_target

    colour = torch.tensor([0.2, 0.5, 0.9])
    rgb = torch.rand(6, 5, 3)
    backdrop = torch.zeros(6, 5, dtype=torch.bool)
    backdrop[:2] = True  # the top two rows are the backdrop
    coverage = (~backdrop).float()
    target = backdrop_target(rgb, coverage, colour)
    torch.testing.assert_close(target[:2], colour.expand(2, 5, 3))
    torch.testing.assert_close(target[2:], rgb[2:])
    surface = torch.ones(6, 5)
    torch.testing.assert_close(backdrop_target(rgb, surface, colour), rgb)  # nothing empty: unchanged


def test_random_background_only_without_alpha_and_the_empty_space_term_change_training(tmp_path) -> None:
    import cv2

    root = make_room(tmp_path / "room", seed=0, width=40, height=30, n_test=1)
    base = dict(iterations=3, num_gaussians=200, init="random", language=False, depth=False)
    with_alpha = lf.load_scene(root)
    a = lf.train(with_alpha, lf.TrainConfig(**base, random_background=False), progress=False)
    b = lf.train(with_alpha, lf.TrainConfig(**base, random_background=True), progress=False)
    assert torch.equal(a.splats["means"], b.splats["means"])  # RGBA scenes keep their white background
    e = lf.train(
        with_alpha, lf.TrainConfig(**base, random_background=False, lambda_empty=0.0), progress=False
    )
    assert not torch.equal(a.splats["means"], e.splats["means"])
    assert a.meta["empty_space"]["source"] == "alpha"
    for path in (root / "images").glob("*.png"):
        cv2.imwrite(str(path), cv2.imread(str(path), cv2.IMREAD_COLOR))  # drop the alpha channel
    opaque = lf.load_scene(root)
    assert opaque.background is None
    c = lf.train(opaque, lf.TrainConfig(**base, random_background=False), progress=False)
    d = lf.train(opaque, lf.TrainConfig(**base, random_background=True), progress=False)
    assert not torch.equal(c.splats["means"], d.splats["means"])
    assert c.meta["empty_space"] == {"source": None, "fraction": {}}


def test_opacity_decay_fades_the_gaussians_from_its_start(scene) -> None:
    base = dict(
        iterations=4, num_gaussians=300, init="random", language=False, depth=False, densify=False,
        lambda_opacity=0.0, opacity_decay_start=1,
    )  # fmt: skip
    plain = lf.train(scene, lf.TrainConfig(**base, opacity_decay=1.0), progress=False)
    decayed = lf.train(scene, lf.TrainConfig(**base, opacity_decay=0.5), progress=False)
    opacities = lf.model.gaussians.opacities
    ratio = float(opacities(decayed.splats).mean() / opacities(plain.splats).mean())
    # Three decayed iterations (1, 2, 3) halve every opacity three times; Adam moves a logit by ~lr.
    assert 0.125 * 0.7 < ratio < 0.125 * 1.4
    # From iteration 3: one halving.
    later_cfg = lf.TrainConfig(**dict(base, opacity_decay_start=3), opacity_decay=0.5)
    later = lf.train(scene, later_cfg, progress=False)
    ratio = float(opacities(later.splats).mean() / opacities(plain.splats).mean())
    assert 0.5 * 0.7 < ratio < 0.5 * 1.4
    with pytest.raises(ValueError, match="opacity_decay"):
        lf.TrainConfig(opacity_decay=0.0)


def _plane_views() -> tuple[Camera, Camera, torch.Tensor, torch.Tensor]:
    """Two cameras 0.3 apart facing the plane z = -2, and the z-depth each sees of it."""
    a = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=40, height=30)
    b = Camera.look_at((0.3, 0.0, 0.0), (0.3, 0.0, -1.0), (0.0, 1.0, 0.0), width=40, height=30)
    return a, b, torch.full((30, 40), 2.0), torch.full((30, 40), 2.0)


def test_unproject_inverts_the_projection() -> None:
    a, _, depth, _ = _plane_views()
    points = a.unproject(depth)
    torch.testing.assert_close(points[..., 2], torch.full((30, 40), -2.0), atol=1e-5, rtol=0)
    w2c = a.world_to_camera()
    local = points.reshape(-1, 3) @ w2c[:3, :3].T + w2c[:3, 3]
    u = a.fx * local[:, 0] / local[:, 2] + a.cx
    torch.testing.assert_close(u.reshape(30, 40)[0], torch.arange(40, dtype=torch.float32) + 0.5)


def test_free_space_violation_counts_points_in_front_of_the_other_view_only() -> None:
    from langfield.training.regularisers import free_space_violation

    a, b, depth_a, depth_b = _plane_views()
    covered = torch.ones(30, 40, dtype=torch.bool)
    on_surface, valid = free_space_violation(a.unproject(depth_a).reshape(-1, 3), b, depth_b, covered, 0.02)
    assert valid.float().mean() > 0.5 and float(on_surface.abs().max()) < 1e-5
    near = a.unproject(depth_a * 0.5).reshape(-1, 3)  # halfway to a: b looks through these
    violation, valid = free_space_violation(near, b, depth_b, covered, 0.02)
    assert valid.any() and torch.allclose(violation[valid], torch.tensor((2.0 * 0.98 - 1.0) / 2.0), atol=1e-4)
    behind = a.unproject(depth_a * 1.5).reshape(-1, 3)  # occluded from b: allowed
    assert float(free_space_violation(behind, b, depth_b, covered, 0.02)[0].abs().max()) == 0.0
    nothing = torch.zeros(30, 40, dtype=torch.bool)  # b renders no surface there: no claim
    violation, valid = free_space_violation(near, b, depth_b, nothing, 0.02)
    assert not valid.any() and float(violation.abs().max()) == 0.0


def test_the_free_space_term_pulls_a_near_surface_back() -> None:
    from langfield.training.regularisers import free_space_violation

    a, b, depth_a, depth_b = _plane_views()
    near = (depth_a * 0.5).requires_grad_(True)
    violation, valid = free_space_violation(
        a.unproject(near).reshape(-1, 3), b, depth_b, torch.ones(30, 40, dtype=torch.bool), 0.02
    )
    violation.sum().backward()
    assert float(near.grad[valid.reshape(30, 40)].max()) < 0  # descent makes the depth larger


def test_training_with_the_free_space_term_runs(scene, monkeypatch) -> None:
    from langfield.training import losses

    calls = []
    real = losses.visibility_loss
    monkeypatch.setattr(losses, "visibility_loss", lambda *a, **k: calls.append(len(a[4])) or real(*a, **k))
    cfg = lf.TrainConfig(
        iterations=5, num_gaussians=200, init="random", language=False, lambda_visibility=1.0
    )
    field = lf.train(scene, cfg, progress=False)
    assert calls == [0, 1, 2, 3, 3]  # the views rendered before each step; each view once per round
    assert all(torch.isfinite(p).all() for p in field.splats.values())


def test_carving_removes_the_gaussians_in_front_of_a_resolved_surface_only() -> None:
    from langfield.model import gaussians as G
    from langfield.training.densify import DensifyStrategy
    from langfield.training.strategy import carve_free_space

    a, b, depth, _ = _plane_views()
    resolved = torch.ones(30, 40, dtype=torch.bool)
    resolved[:, 20:] = False  # a's right half unresolved: nothing known in front of it
    # On the plane (z = -2), halfway to a in front of its resolved left half, the same in front of the
    # unresolved right half, and behind the plane.
    points = torch.tensor([[-0.2, 0.0, -2.0], [-0.2, 0.0, -1.0], [0.2, 0.0, -1.0], [-0.2, 0.0, -3.0]])
    splats = G.gaussians_at(points)
    optimizers = {k: torch.optim.Adam([p]) for k, p in splats.items()}
    state = DensifyStrategy().initialize_state(splats)
    assert carve_free_space(splats, [(a, depth, resolved)], optimizers, state, 0.03) == 1
    kept = splats["means"].detach()
    torch.testing.assert_close(kept, points[[0, 2, 3]])
    assert optimizers["means"].param_groups[0]["params"][0] is splats["means"]
    assert state["grad2d"].shape == (3,)


def test_carving_that_would_remove_every_gaussian_removes_none() -> None:
    from langfield.model import gaussians as G
    from langfield.training.densify import DensifyStrategy
    from langfield.training.strategy import carve_free_space

    a, _, depth, _ = _plane_views()
    points = torch.tensor([[-0.2, 0.0, -1.0], [0.1, 0.0, -1.5]])  # both in front of the plane
    splats = G.gaussians_at(points)
    optimizers = {k: torch.optim.Adam([p]) for k, p in splats.items()}
    state = DensifyStrategy().initialize_state(splats)
    stereo = [(a, depth, torch.ones(30, 40, dtype=torch.bool))]
    assert carve_free_space(splats, stereo, optimizers, state, 0.03) == 0
    torch.testing.assert_close(splats["means"].detach(), points)


def test_the_stereo_term_is_the_mean_relative_depth_error_where_the_sweep_resolved() -> None:
    from langfield.training.losses import stereo_depth_loss

    stereo = torch.tensor([[2.0, math.nan, 4.0], [1.0, 1.0, math.nan]])
    covered = torch.tensor([[True, True, True], [True, False, True]])
    depth = torch.tensor([[2.5, 9.0, 3.0], [1.0, 7.0, 0.1]], requires_grad=True)
    loss = stereo_depth_loss(depth, covered, stereo)
    assert float(loss.detach()) == pytest.approx((0.5 / 2 + 1.0 / 4 + 0.0) / 3)
    loss.backward()
    expected = torch.tensor([[1 / 2, 0.0, -1 / 4], [0.0, 0.0, 0.0]]) / 3  # sign(z - s) / s / count
    torch.testing.assert_close(depth.grad, expected)
    # Nothing resolved where the field covers: zero, still in the graph.
    d = depth.detach().clone().requires_grad_(True)
    none = stereo_depth_loss(d, torch.zeros_like(covered), stereo)
    none.backward()
    assert float(none.detach()) == 0.0 and float(d.grad.abs().sum()) == 0.0


def test_training_with_the_stereo_term_supervises_the_views_the_sweep_resolved(scene) -> None:
    cfg = lf.TrainConfig(iterations=4, num_gaussians=300, init="dense", language=False, depth=False,
                         lambda_stereo=1.0)  # fmt: skip
    field = lf.train(scene, cfg, progress=False)
    (record,) = field.meta["loss_terms"]
    assert record["steps"]["stereo"] == 4 and record["terms"]["stereo"] > 0
    assert field.meta["init"]["dense"]["points"] > 0
    off = lf.train(scene, dataclasses.replace(cfg, lambda_stereo=0.0), progress=False)
    assert "stereo" not in off.meta["loss_terms"][0]["steps"]
    # A random start runs no sweep: the term has nothing to compare with and is absent.
    bare = lf.train(scene, dataclasses.replace(cfg, init="random"), progress=False)
    assert "stereo" not in bare.meta["loss_terms"][0]["steps"]


def test_training_with_carving_records_what_it_removed(scene) -> None:
    cfg = lf.TrainConfig(iterations=3, num_gaussians=300, language=False, depth=False, carve_free_space=True)
    field = lf.train(scene, dataclasses.replace(cfg, refine_every=2), progress=False)
    carved = field.meta["carved"]
    assert carved["rounds"] == 2
    assert 0 < carved["removed"] == 300 - field.meta["num_gaussians"]


def test_a_view_at_half_size_averages_the_photo_and_samples_the_targets() -> None:
    from langfield.training.lad import LADTarget
    from langfield.training.targets import ViewTargets

    cam = Camera.look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), width=8, height=6)
    image = torch.rand(6, 8, 3)
    coverage = torch.ones(6, 8)
    coverage[:, :2] = 0.0
    seg = torch.arange(6 * 8).reshape(1, 6, 8).repeat(3, 1, 1) // 4  # masks of 4 pixels along a row
    latents = torch.rand(3, 6, 8, 3)
    prior = torch.linspace(1.0, 2.0, 48).reshape(6, 8)
    view = ViewTargets(
        cam, image, coverage, latents, seg >= 0, LADTarget.from_view(seg, prior, "depth"), (seg, prior)
    )
    half = view.half_size()
    assert (half.camera.width, half.camera.height) == (4, 3) and half.camera.fx == pytest.approx(cam.fx / 2)
    torch.testing.assert_close(half.image, image.reshape(3, 2, 4, 2, 3).mean(dim=(1, 3)))
    torch.testing.assert_close(half.coverage[:, 0], torch.zeros(3))  # pixels 0-1 of each row: empty
    torch.testing.assert_close(half.latents, latents[:, 1::2][:, :, 1::2])  # the nearest pixel centres
    assert half.language_weight.shape == (3, 3, 4) and half.depth.shape == (3, 4)
    torch.testing.assert_close(half.depth_input[1], prior[1::2, 1::2])
    bare = ViewTargets(cam, image).half_size()
    assert bare.coverage is None and bare.latents is None and bare.depth is None and bare.stereo is None
    stereo = torch.full((6, 8), math.nan)
    stereo[1, 1], stereo[3, 5] = 2.0, 3.0
    torch.testing.assert_close(ViewTargets(cam, image, stereo=stereo).half_size().stereo, stereo[1::2, 1::2],
                               equal_nan=True)  # fmt: skip


def test_language_trains_only_from_its_start_and_leaves_the_geometry_as_it_was(scene, monkeypatch) -> None:
    from langfield.field import LanguageField

    calls = []
    real = LanguageField.render
    spy = lambda self, cam, **k: calls.append(k.get("language", True)) or real(self, cam, **k)  # noqa: E731
    monkeypatch.setattr(LanguageField, "render", spy)
    base = dict(iterations=4, num_gaussians=200, init="random", lambda_virtual=0.0, lop=False, densify=False)
    late = lf.train(scene, lf.TrainConfig(**base, language_start=0.5), progress=False)
    assert calls == [False, False, True, True]
    early = lf.train(scene, lf.TrainConfig(**base), progress=False)
    # L_LF reads detached positions and passes no gradient to the geometry: the same Gaussians.
    for key in ("means", "log_scales", "quats", "opacity_logits"):
        torch.testing.assert_close(late.splats[key], early.splats[key])
    assert late.meta["config"]["language_start"] == 0.5
    # Two language steps moved the language grid less far from its start than four.
    fresh = lf.train(scene, lf.TrainConfig(**dict(base, iterations=0)), progress=False)
    moved = [(f.language.grid.table - fresh.language.grid.table).abs().sum() for f in (late, early)]
    assert 0 < moved[0] < moved[1]


def test_half_resolution_renders_the_first_part_of_the_run_smaller(scene, monkeypatch) -> None:
    sizes = _spy_render_sizes(monkeypatch)
    cfg = lf.TrainConfig(
        iterations=4, num_gaussians=200, init="random", lambda_virtual=0.0, half_resolution_until=0.5
    )
    field = lf.train(scene, cfg, progress=False)  # the room has language and depth targets
    assert sizes == [(24, 18), (24, 18), (48, 36), (48, 36)]
    assert field.meta["config"]["half_resolution_until"] == 0.5
    assert all(torch.isfinite(p).all() for p in field.splats.values())
