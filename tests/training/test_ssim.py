"""Tests of the training loss's SSIM (langfield/training/ssim.py, langfield/training/ssim_cpu.py) against
kornia's."""

from __future__ import annotations

import kornia
import numpy as np
import pytest
import torch

from langfield.training import ssim_cpu
from langfield.training.ssim import ssim_map


def _rand(*shape: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(*shape, generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize(
    "shape, window",
    [((48, 64, 3), 11), ((5, 5, 3), 5), ((4, 6, 3), 3), ((1, 1, 3), 1), ((2, 30, 3), 1)],
)
def test_ssim_window_shrinks_to_the_image(shape, window) -> None:
    a, b = _rand(*shape, seed=1), _rand(*shape, seed=2)
    m = ssim_map(a, b)
    assert m.shape == (1, shape[2], shape[0], shape[1])
    expected = kornia.metrics.ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None], window)
    torch.testing.assert_close(m, expected)


def _kornia_with_grads(a, b, weights):
    window = min(11, a.shape[0], a.shape[1])
    window = max(window if window % 2 else window - 1, 1)
    a_ref, b_ref = a.detach().clone().requires_grad_(True), b.detach().clone().requires_grad_(True)
    expected = kornia.metrics.ssim(a_ref.permute(2, 0, 1)[None], b_ref.permute(2, 0, 1)[None], window)
    (expected * weights).sum().backward()
    return expected, a_ref.grad, b_ref.grad


@pytest.mark.parametrize("backend", ["torch", "numba"])
@pytest.mark.parametrize(
    "shape",
    [(48, 64, 3), (64, 48, 3), (5, 7, 3), (12, 13, 1), (2, 30, 3), (30, 2, 3), (1, 1, 3), (11, 11, 5)],
)
def test_ssim_map_with_gradient_matches_kornia_values_and_gradients(backend, shape) -> None:
    # The torch path filters the five moments in one call; kornia filters them one by one; the numba
    # kernels filter planes along x, then y, with the reflected borders as gather tables.
    a = _rand(*shape, seed=6).requires_grad_(True)
    b = _rand(*shape, seed=7).requires_grad_(True)
    m = ssim_map(a, b, backend=backend)
    weights = torch.rand((1, shape[2], shape[0], shape[1]), generator=torch.Generator().manual_seed(8))
    expected, grad_a, grad_b = _kornia_with_grads(a, b, weights)
    torch.testing.assert_close(m, expected)
    (m * weights).sum().backward()
    # Float rounding only: tiny windows cancel (sigma^2 = E[x^2] - mu^2), so the bound scales with the
    # gradient's size.
    for grad, ref in ((a.grad, grad_a), (b.grad, grad_b)):
        torch.testing.assert_close(grad, ref, rtol=1e-3, atol=1e-4 * float(ref.abs().max()))


@pytest.mark.parametrize("backend", ["torch", "numba"])
def test_ssim_of_constant_and_equal_images_is_one_with_finite_gradients(backend) -> None:
    # Zero variance everywhere: only the constants c1, c2 keep the ratio defined.
    flat = torch.full((16, 20, 3), 0.5, requires_grad=True)
    m = ssim_map(flat, torch.full((16, 20, 3), 0.5), backend=backend)
    torch.testing.assert_close(m, torch.ones_like(m))
    m.mean().backward()
    assert torch.isfinite(flat.grad).all() and float(flat.grad.abs().max()) < 1e-6
    dark = torch.zeros(16, 20, 3, requires_grad=True)
    ssim_map(dark, torch.full((16, 20, 3), 1.0), backend=backend).mean().backward()
    assert torch.isfinite(dark.grad).all()


def test_numba_ssim_passes_a_gradient_only_where_asked() -> None:
    a, b = _rand(20, 24, 3, seed=1).requires_grad_(True), _rand(20, 24, 3, seed=2)
    ssim_map(a, b, backend="numba").mean().backward()
    assert a.grad is not None and b.grad is None
    a2, b2 = _rand(20, 24, 3, seed=1), _rand(20, 24, 3, seed=2).requires_grad_(True)
    ssim_map(a2, b2, backend="numba").mean().backward()
    a3 = a2.clone().requires_grad_(True)
    b3 = b2.detach().clone().requires_grad_(True)
    ssim_map(a3, b3, backend="torch").mean().backward()
    torch.testing.assert_close(b2.grad, b3.grad, rtol=1e-3, atol=1e-6)


@pytest.mark.parametrize("n, size", [(40, 11), (11, 11), (12, 11), (7, 5), (3, 3), (1, 1), (5, 1)])
def test_filter_tables_are_the_reflect_padded_window_and_its_transpose(n, size) -> None:
    # The filter as a matrix, from the kernels applied to the unit vectors, against the window slid over
    # a reflect-padded signal; its transpose's kernels against the matrix's transpose.
    w, (f_lo, f_hi, f_idx, f_wt), (t_lo, t_hi, t_idx, t_wt) = ssim_cpu._filter_tables(n, size)
    r = size // 2
    eye = np.eye(n, dtype=np.float32)
    forward, transpose = np.empty_like(eye), np.empty_like(eye)
    ssim_cpu._filter_x(eye, w, f_lo, f_hi, f_idx, f_wt, forward)
    ssim_cpu._filter_x(eye, w, t_lo, t_hi, t_idx, t_wt, transpose)
    padded = np.pad(eye, ((0, 0), (r, r)), mode="reflect")
    slid = np.stack([padded[:, i : i + size] @ w for i in range(n)], axis=1)
    np.testing.assert_allclose(forward, slid, atol=1e-7)
    np.testing.assert_allclose(transpose, forward.T, atol=1e-7)
    planes = eye[None].copy()
    along_y = np.empty_like(planes)
    ssim_cpu._filter_y(planes, w, f_lo, f_hi, f_idx, f_wt, along_y)
    np.testing.assert_allclose(along_y[0], slid.T, atol=1e-7)
