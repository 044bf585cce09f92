"""The depth losses (training/lad.py): LAD (eq. 6, 9), the global term (eq. 10) and L_D (eq. 11)."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from langfield.training.lad import (
    GLOBAL_STD_RATIO,
    LAMBDA_SA,
    MIN_MASK_PIXELS,
    PRIOR_MIN_RANGE,
    RANGE_EPS,
    RENDER_MIN_RANGE,
    LADTarget,
    depth_loss,
    global_depth_loss,
    lad_loss,
)

H, W = 24, 32


def _random_segments(seed: int = 0, ids: int = 6) -> Tensor:
    """[3, H, W] blocky masks; ids repeat across levels, some pixels have no mask."""
    g = torch.Generator().manual_seed(seed)
    levels = []
    for cells in (8, 4, 2):
        coarse = torch.randint(-1, ids, (cells, cells), generator=g)
        levels.append(
            coarse.repeat_interleave(H // cells + 1, 0)[:H].repeat_interleave(W // cells + 1, 1)[:, :W]
        )
    return torch.stack(levels)


def _reference_lad(segments: Tensor, prior: Tensor, depth: Tensor, kind: str) -> Tensor:
    """L_SA with a Python loop over (level, id) masks: the definition, written plainly."""
    p = -prior.double() if kind == "disparity" else prior.double()
    finite = torch.isfinite(p)
    image_range = (p[finite].max() - p[finite].min()).item()
    entries_d, entries_p = [], []
    for level in range(segments.shape[0]):
        for mask_id in segments[level].unique().tolist():
            if mask_id < 0:
                continue
            inside = (segments[level] == mask_id) & finite
            pm = p[inside]
            if inside.sum() < MIN_MASK_PIXELS or pm.max() - pm.min() <= max(
                PRIOR_MIN_RANGE * image_range, RANGE_EPS
            ):
                continue
            entries_p.append((pm - pm.min()) / (pm.max() - pm.min()))
            entries_d.append(depth[inside])
    all_d = torch.cat(entries_d)
    floor = max(RENDER_MIN_RANGE * (all_d.max() - all_d.min()).item(), RANGE_EPS)
    losses = [
        ((d - d.min()) / torch.clamp(d.max() - d.min(), min=floor) - pm.to(d.dtype)).abs()
        for d, pm in zip(entries_d, entries_p, strict=True)
    ]
    return torch.cat(losses).mean()


def _reference_global(prior: Tensor, depth: Tensor) -> Tensor:
    finite = torch.isfinite(prior)
    p, d = prior[finite].double(), depth[finite]
    pn = (p - p.mean()) / ((1 + GLOBAL_STD_RATIO) * p.std(correction=0))
    std = d.std(correction=0)
    dn = (d - d.mean()) / (std.detach() + GLOBAL_STD_RATIO * std)
    return (dn - pn.to(d.dtype)).abs().mean()


def _prior(seed: int = 1) -> Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(H, W, generator=g) * 5 + 1


def test_lad_matches_loop_reference_values_and_gradients():
    segments, prior = _random_segments(), _prior()
    depth = torch.rand(H, W, generator=torch.Generator().manual_seed(2)).requires_grad_()
    target = LADTarget.from_view(segments, prior, "depth")
    ours = lad_loss(target, depth)
    (g_ours,) = torch.autograd.grad(ours, depth)
    ref = _reference_lad(segments, prior, depth, "depth")
    (g_ref,) = torch.autograd.grad(ref, depth)
    assert target.num_masks > 5
    torch.testing.assert_close(ours, ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(g_ours, g_ref, rtol=1e-4, atol=1e-7)


def test_global_matches_reference_values_and_gradients():
    prior = _prior()
    depth = torch.rand(H, W, generator=torch.Generator().manual_seed(3)).requires_grad_()
    target = LADTarget.from_view(_random_segments(), prior, "depth")
    ours = global_depth_loss(target, depth)
    ref = _reference_global(prior, depth)
    torch.testing.assert_close(ours, ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(torch.autograd.grad(ours, depth)[0], torch.autograd.grad(ref, depth)[0])


def test_render_equal_to_prior_up_to_scale_and_shift_has_zero_loss():
    prior = _prior()
    target = LADTarget.from_view(_random_segments(), prior, "depth")
    depth = 0.3 * prior + 7.0
    assert lad_loss(target, depth).item() < 1e-6
    assert global_depth_loss(target, depth).item() < 1e-5
    assert lad_loss(target, torch.rand(H, W)).item() > 0.1


def test_lad_is_local_per_mask_affine_changes_cost_nothing():
    # One level of disjoint masks; a different scale and shift in each mask leaves L_SA at zero but not L_GL.
    segments = torch.full((3, H, W), -1)
    segments[0, :, : W // 2] = 0
    segments[0, :, W // 2 :] = 1
    prior = _prior()
    depth = torch.where(segments[0] == 0, 2.0 * prior + 1.0, 0.1 * prior - 4.0)
    target = LADTarget.from_view(segments, prior, "depth")
    assert target.num_masks == 2
    assert lad_loss(target, depth).item() < 1e-6
    assert global_depth_loss(target, depth).item() > 0.1


def test_loss_is_invariant_to_render_scale_and_shift():
    target = LADTarget.from_view(_random_segments(), _prior(), "depth")
    depth = torch.rand(H, W, generator=torch.Generator().manual_seed(4))
    base = depth_loss(target, depth, depth)
    torch.testing.assert_close(depth_loss(target, 4.0 * depth + 2.0, 4.0 * depth + 2.0), base)


def test_disparity_prior_is_negated():
    segments = _random_segments()
    z = _prior()
    disparity = 1.0 - 0.1 * z  # larger = nearer, affine in z
    as_disparity = LADTarget.from_view(segments, disparity, "disparity")
    as_depth = LADTarget.from_view(segments, z, "depth")
    torch.testing.assert_close(as_disparity.prior_local, as_depth.prior_local)
    torch.testing.assert_close(as_disparity.prior_global, as_depth.prior_global)
    assert depth_loss(as_disparity, z, z).item() < 1e-5
    # Read as a depth, the same disparity is inverted: the loss is large.
    wrong = LADTarget.from_view(segments, disparity, "depth")
    assert depth_loss(wrong, z, z).item() > 1.0


def test_masks_with_too_few_pixels_are_skipped():
    segments = torch.full((3, H, W), -1)
    segments[0].view(-1)[: MIN_MASK_PIXELS - 1] = 0
    segments[1].view(-1)[:MIN_MASK_PIXELS] = 0
    target = LADTarget.from_view(segments, _prior(), "depth")
    assert (target.num_masks, target.num_skipped) == (1, 1)
    assert target.pixel_index.numel() == MIN_MASK_PIXELS


def test_masks_with_flat_prior_are_skipped():
    segments = torch.full((3, H, W), -1)
    segments[0, : H // 2] = 0
    segments[0, H // 2 :] = 1
    prior = _prior()
    prior[: H // 2] = 3.0  # mask 0 sees a flat prior
    target = LADTarget.from_view(segments, prior, "depth")
    assert (target.num_masks, target.num_skipped) == (1, 1)
    assert set(target.pixel_index.tolist()) == set(range(H // 2 * W, H * W))


def test_same_id_at_two_levels_is_two_masks():
    segments = torch.full((3, H, W), -1)
    segments[0, :, : W // 2] = 5
    segments[1, : H // 2] = 5  # same id, other pixels
    prior = _prior()
    depth = torch.rand(H, W, generator=torch.Generator().manual_seed(5))
    target = LADTarget.from_view(segments, prior, "depth")
    assert target.num_masks == 2
    assert target.pixel_index.numel() == H * (W // 2) + (H // 2) * W
    torch.testing.assert_close(lad_loss(target, depth), _reference_lad(segments, prior, depth, "depth"))


def test_nan_and_inf_prior_pixels_are_masked_out_of_both_terms():
    segments, prior = _random_segments(), _prior()
    bad = torch.zeros(H, W, dtype=torch.bool)
    bad[2:6, 3:20] = True
    bad[10, 10] = True
    prior[bad] = float("nan")
    prior[0, 0] = float("inf")
    bad[0, 0] = True
    target = LADTarget.from_view(segments, prior, "depth")
    assert not bad.flatten()[target.pixel_index].any()
    assert not bad.flatten()[target.valid_index].any()
    depth = torch.rand(H, W, generator=torch.Generator().manual_seed(6)).requires_grad_()
    loss = depth_loss(target, depth, depth)
    (grad,) = torch.autograd.grad(loss, depth)
    assert torch.isfinite(loss) and torch.isfinite(grad).all()
    assert (grad[bad] == 0).all()
    # The render at those pixels does not matter, and the values match the references on the rest.
    changed = depth.detach().clone()
    changed[bad] = 100.0
    torch.testing.assert_close(depth_loss(target, changed, changed), loss.detach())
    torch.testing.assert_close(lad_loss(target, depth), _reference_lad(segments, prior, depth, "depth"))
    torch.testing.assert_close(global_depth_loss(target, depth), _reference_global(prior, depth))


def test_all_nan_prior_gives_zero_loss_that_backpropagates():
    target = LADTarget.from_view(_random_segments(), torch.full((H, W), float("nan")), "disparity")
    assert target.num_masks == 0 and target.valid_index.numel() == 0
    depth = torch.rand(H, W, requires_grad=True)
    loss = depth_loss(target, depth, depth)
    loss.backward()
    assert loss.item() == 0.0
    assert (depth.grad == 0).all()


def test_constant_prior_gives_zero_loss():
    target = LADTarget.from_view(_random_segments(), torch.full((H, W), 2.0), "depth")
    assert target.num_masks == 0 and target.valid_index.numel() == 0
    assert depth_loss(target, torch.rand(H, W), torch.rand(H, W)).item() == 0.0


@pytest.mark.parametrize("value", [0.0, 3.0])
def test_flat_render_has_finite_loss_and_gradient(value: float):
    target = LADTarget.from_view(_random_segments(), _prior(), "depth")
    hard = torch.full((H, W), value, requires_grad=True)
    soft = torch.full((H, W), value, requires_grad=True)
    loss = depth_loss(target, hard, soft)
    loss.backward()
    assert torch.isfinite(loss)
    assert torch.isfinite(hard.grad).all() and torch.isfinite(soft.grad).all()
    assert hard.grad.abs().sum() > 0


def test_render_flat_inside_one_mask_is_floored_not_divided_by_zero():
    segments = torch.full((3, H, W), -1)
    segments[0, :, : W // 2] = 0
    segments[0, :, W // 2 :] = 1
    depth = torch.rand(H, W, generator=torch.Generator().manual_seed(7))
    depth[:, : W // 2] = 2.0  # flat in mask 0 only
    depth.requires_grad_()
    target = LADTarget.from_view(segments, _prior(), "depth")
    loss = lad_loss(target, depth)
    (grad,) = torch.autograd.grad(loss, depth)
    assert torch.isfinite(loss) and torch.isfinite(grad).all()
    # In the flat mask the normalised render is 0; its gradient is bounded by 1 / (floor x entries).
    floor = RENDER_MIN_RANGE * (depth.max() - depth.min()).item()
    assert grad.abs().max() <= 2.0 / (floor * target.pixel_index.numel())


def test_prior_is_a_constant():
    prior = _prior().requires_grad_()
    target = LADTarget.from_view(_random_segments(), prior, "depth")
    assert not target.prior_local.requires_grad and not target.prior_global.requires_grad
    depth = torch.rand(H, W, requires_grad=True)
    depth_loss(target, depth, depth).backward()
    assert prior.grad is None
    assert depth.grad is not None and torch.isfinite(depth.grad).all()


def test_lad_gradient_only_reaches_pixels_in_usable_masks():
    segments = _random_segments()
    segments[:, :4] = -1  # no mask at any level
    target = LADTarget.from_view(segments, _prior(), "depth")
    depth = torch.rand(H, W, generator=torch.Generator().manual_seed(8)).requires_grad_()
    (grad,) = torch.autograd.grad(lad_loss(target, depth), depth)
    in_mask = torch.zeros(H * W, dtype=torch.bool)
    in_mask[target.pixel_index] = True
    assert (grad.flatten()[~in_mask] == 0).all()
    assert (~in_mask).any() and (grad.flatten()[in_mask] != 0).any()


def test_depth_loss_combines_terms_over_hard_and_soft_depth():
    target = LADTarget.from_view(_random_segments(), _prior(), "depth")
    g = torch.Generator().manual_seed(9)
    hard, soft = torch.rand(H, W, generator=g), torch.rand(H, W, generator=g)
    global_only = global_depth_loss(target, hard) + global_depth_loss(target, soft)
    lad = lad_loss(target, hard) + lad_loss(target, soft)
    torch.testing.assert_close(depth_loss(target, hard, soft, lad=False), global_only)
    torch.testing.assert_close(depth_loss(target, hard, soft), global_only + LAMBDA_SA * lad)
    torch.testing.assert_close(depth_loss(target, hard, soft, lambda_sa=1.0), global_only + lad)
    assert lad > 0


def test_gradient_descent_on_depth_reduces_loss():
    prior = _prior()
    target = LADTarget.from_view(_random_segments(), prior, "depth")
    depth = torch.rand(H, W, generator=torch.Generator().manual_seed(10)).requires_grad_()
    opt = torch.optim.Adam([depth], lr=0.02)
    first = depth_loss(target, depth, depth).item()
    for _ in range(100):
        opt.zero_grad()
        depth_loss(target, depth, depth).backward()
        opt.step()
    assert depth_loss(target, depth, depth).item() < 0.3 * first


def test_bad_inputs_raise():
    segments, prior = _random_segments(), _prior()
    with pytest.raises(ValueError, match="depth_kind"):
        LADTarget.from_view(segments, prior, "inverse")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="segments"):
        LADTarget.from_view(segments[:, :-1], prior, "depth")
    with pytest.raises(ValueError, match="segments"):
        LADTarget.from_view(segments.float(), prior, "depth")
    with pytest.raises(ValueError, match="prior"):
        LADTarget.from_view(segments, prior[None], "depth")
    target = LADTarget.from_view(segments, prior, "depth")
    with pytest.raises(ValueError, match="depth"):
        lad_loss(target, torch.rand(H, W + 1))
    with pytest.raises(ValueError, match="depth"):
        depth_loss(target, torch.rand(H, W), torch.rand(1, H, W))


def test_gradient_is_the_same_on_every_call_on_two_threads():
    # Past 32,768 (mask, pixel) entries PyTorch's indexing adds its gradient with atomics on 2+ threads,
    # in whatever order the threads meet; the losses must add in one order, or a seed would not repeat.
    h, w = 160, 240
    g = torch.Generator().manual_seed(11)
    # One mask over the whole view: both threads add into its entry all the time.
    segments = torch.full((3, h, w), -1)
    segments[0] = 0
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    target = LADTarget.from_view(segments, 1.0 + (xx + 2 * yy).float() / w, "depth")
    assert target.pixel_index.numel() > 32_768
    depth = torch.rand(h, w, generator=g)

    def gradient() -> Tensor:
        d = depth.clone().requires_grad_()
        depth_loss(target, d, d).backward()
        return d.grad

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        first = gradient()
        assert first.abs().sum() > 0
        for _ in range(30):
            assert torch.equal(gradient(), first)
    finally:
        torch.set_num_threads(before)
