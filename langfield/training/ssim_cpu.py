"""The training loss's SSIM map as numba kernels, forward and backward.

The same formula, window and reflect padding as :func:`langfield.training.ssim._ssim_map_stacked` (the
PyTorch reference it is tested against, values and gradients; that one is kornia's), arranged for the
CPU:

- the five moments (x, y, x^2, y^2, xy of every channel) are planes ``[5 C, H, W]``; the Gaussian
  window filters along x and then along y, each a loop over contiguous pixels, so a 504 x 378 image
  takes a few milliseconds a pass where the padded depthwise convolutions and their backward took
  about 40 ms forward and back (fern's step renders 1.5 such images);
- a filter is a linear map ``out[i] = sum_j w_j in[refl(i + j - r)]``; inside ``[lo, hi)`` it is the
  plain window, at the borders a gather table (:func:`_filter_tables`). The backward applies the
  transposed map: for the symmetric Gaussian window the same plain window inside, its own table at the
  borders, where reflected taps land twice;
- the moments are kept from the forward; the backward turns the map's upstream gradient into the
  moments' gradients per pixel, filters them back (y, then x) and then meets the inputs (x^2's gradient
  is 2 x times its moment's, and so on).
"""

from __future__ import annotations

import functools

import kornia
import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from langfield.kernels import configure_numba

configure_numba()

_C1 = np.float32(0.01**2)
_C2 = np.float32(0.03**2)
_EPS = np.float32(1e-12)
_TWO = np.float32(2.0)


@functools.lru_cache(maxsize=32)
def _filter_tables(n: int, size: int) -> tuple[np.ndarray, tuple, tuple]:
    """The 1-D Gaussian window (sigma 1.5, kornia's) on ``n`` samples with reflect padding, as
    ``(w, filter, transpose)``: the window and two linear maps, each ``(lo, hi, idx, wt)``. Rows
    ``[lo, hi)`` are the plain window centred on the row; every row's taps are also in the gather table
    ``idx, wt`` [n, m] (padded with zero weights), which the kernels use outside ``[lo, hi)``."""
    r = size // 2
    w = kornia.filters.get_gaussian_kernel1d(size, 1.5).reshape(-1).numpy().astype(np.float32)
    rows = np.repeat(np.arange(n), size)
    cols = (np.arange(n)[:, None] + np.arange(size)[None, :] - r).reshape(-1)
    cols = np.where(cols < 0, -cols, np.where(cols >= n, 2 * (n - 1) - cols, cols))
    weights = np.tile(w, n)

    def table(out_rows: np.ndarray, in_rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        order = np.argsort(out_rows, kind="stable")
        out_rows, in_rows, wts = out_rows[order], in_rows[order], weights[order]
        counts = np.bincount(out_rows, minlength=n)
        first = np.concatenate([[0], np.cumsum(counts)[:-1]])
        slot = np.arange(out_rows.size) - first[out_rows]
        idx = np.repeat(np.arange(n)[:, None], max(int(counts.max()), 1), axis=1)
        wt = np.zeros(idx.shape, np.float32)
        idx[out_rows, slot] = in_rows
        wt[out_rows, slot] = wts
        return idx.astype(np.int64), wt

    # The plain window holds where no tap is reflected: forward rows [r, n - r); in the transpose,
    # reflected taps land on rows 1..r and n - 1 - r..n - 2, so rows [r + 1, n - r - 1).
    f_lo, f_hi = r, max(r, n - r)
    t_lo, t_hi = min(r + 1, n), max(min(r + 1, n), n - r - 1)
    return w, (f_lo, f_hi, *table(rows, cols)), (t_lo, t_hi, *table(cols, rows))


@njit(parallel=True, fastmath=True, cache=True)
def _filter_x(src, w, lo, hi, idx, wt, out):  # pragma: no cover - numba
    """``out`` [R, W] = the window along each row of ``src`` [R, W]: plain on ``[lo, hi)``, by the
    table elsewhere. The plain part runs over slices (contiguous and with no negative index, which
    numba would otherwise test for wrap-around at every read, keeping the loop scalar)."""
    n_rows, width = out.shape
    r = w.shape[0] // 2
    n = hi - lo
    for i in prange(n_rows):
        o = out[i, lo:hi]
        for x in range(n):
            o[x] = 0.0
        for j in range(w.shape[0]):
            wj = w[j]
            s = src[i, lo + j - r : lo + j - r + n]
            for x in range(n):
                o[x] += wj * s[x]
        for b in range(width - n):  # the border columns
            x = b if b < lo else b + n
            acc = np.float32(0.0)
            for m in range(idx.shape[1]):
                acc += wt[x, m] * src[i, idx[x, m]]
            out[i, x] = acc


@njit(parallel=True, fastmath=True, cache=True)
def _filter_y(src, w, lo, hi, idx, wt, out):  # pragma: no cover - numba
    """``out`` [K, H, W] = the window along y of ``src`` [K, H, W]: a row is a weighted sum of whole
    rows (plain on ``[lo, hi)``, by the table elsewhere)."""
    planes, height, width = out.shape
    r = w.shape[0] // 2
    for q in prange(planes * height):
        k, y = q // height, q % height
        o = out[k, y]
        for x in range(width):
            o[x] = 0.0
        inside = lo <= y < hi
        for m in range(w.shape[0] if inside else idx.shape[1]):
            wm = w[m] if inside else wt[y, m]
            s = src[k, y + m - r] if inside else src[k, idx[y, m]]
            for x in range(width):
                o[x] += wm * s[x]


@njit(parallel=True, fastmath=True, cache=True)
def _moments(p, t, out):  # pragma: no cover - numba
    """The five moment planes [5 C, H, W] of images ``p``, ``t`` [H, W, C]: x, y, x^2, y^2, xy."""
    height, width, c = p.shape
    for y in prange(height):
        for ch in range(c):
            for x in range(width):
                a = p[y, x, ch]
                b = t[y, x, ch]
                out[ch, y, x] = a
                out[c + ch, y, x] = b
                out[2 * c + ch, y, x] = a * a
                out[3 * c + ch, y, x] = b * b
                out[4 * c + ch, y, x] = a * b


@njit(inline="always")
def _parts(mom, c, ch, y, x):  # pragma: no cover - numba
    """SSIM's factors at one pixel and channel from the filtered moments: luminance's numerator and
    denominator (a, cc), contrast-structure's (b, d), and mu_x, mu_y."""
    mu1 = mom[ch, y, x]
    mu2 = mom[c + ch, y, x]
    mu12 = mu1 * mu2
    a = _TWO * mu12 + _C1
    b = _TWO * (mom[4 * c + ch, y, x] - mu12) + _C2
    cc = mu1 * mu1 + mu2 * mu2 + _C1
    d = (mom[2 * c + ch, y, x] - mu1 * mu1) + (mom[3 * c + ch, y, x] - mu2 * mu2) + _C2
    return a, b, cc, d, mu1, mu2


@njit(parallel=True, cache=True)
def _ssim(mom, out):  # pragma: no cover - numba
    """The SSIM map [C, H, W] from the filtered moments [5 C, H, W] (kornia's eps in the denominator)."""
    c, height, width = out.shape
    for y in prange(height):
        for ch in range(c):
            for x in range(width):
                a, b, cc, d, _, _ = _parts(mom, c, ch, y, x)
                out[ch, y, x] = (a * b) / (cc * d + _EPS)


@njit(parallel=True, cache=True)
def _moment_grads(mom, grad, out):  # pragma: no cover - numba
    """The filtered moments' gradients [5 C, H, W] from the map's upstream gradient [C, H, W]."""
    c, height, width = grad.shape
    for y in prange(height):
        for ch in range(c):
            for x in range(width):
                a, b, cc, d, mu1, mu2 = _parts(mom, c, ch, y, x)
                inv = np.float32(1.0) / (cc * d + _EPS)
                g = grad[ch, y, x]
                ga = g * b * inv
                gb = g * a * inv
                s = g * a * b * inv * inv  # minus the gradient of the denominator's two factors, over them
                gc = -s * d
                gd = -s * cc
                out[ch, y, x] = _TWO * (mu2 * (ga - gb) + mu1 * (gc - gd))
                out[c + ch, y, x] = _TWO * (mu1 * (ga - gb) + mu2 * (gc - gd))
                out[2 * c + ch, y, x] = gd
                out[3 * c + ch, y, x] = gd
                out[4 * c + ch, y, x] = _TWO * gb


@njit(parallel=True, fastmath=True, cache=True)
def _input_grads(g_mom, p, t, gp, gt):  # pragma: no cover - numba
    """The inputs' gradients [H, W, C] from those of their (unfiltered) moment planes."""
    height, width, c = p.shape
    for y in prange(height):
        for ch in range(c):
            for x in range(width):
                a = p[y, x, ch]
                b = t[y, x, ch]
                g12 = g_mom[4 * c + ch, y, x]
                gp[y, x, ch] = g_mom[ch, y, x] + _TWO * a * g_mom[2 * c + ch, y, x] + b * g12
                gt[y, x, ch] = g_mom[c + ch, y, x] + _TWO * b * g_mom[3 * c + ch, y, x] + a * g12


def _filter(planes: np.ndarray, tables_y: tuple, tables_x: tuple, transpose: bool) -> np.ndarray:
    """The 2-D window over planes [K, H, W]: x then y, or for the transpose y then x."""
    k, height, width = planes.shape
    part = 2 if transpose else 1
    w_y, map_y = tables_y[0], tables_y[part]
    w_x, map_x = tables_x[0], tables_x[part]
    tmp = np.empty_like(planes)
    out = np.empty_like(planes)
    if transpose:
        _filter_y(planes, w_y, *map_y, tmp)
        _filter_x(tmp.reshape(k * height, width), w_x, *map_x, out.reshape(k * height, width))
    else:
        _filter_x(planes.reshape(k * height, width), w_x, *map_x, tmp.reshape(k * height, width))
        _filter_y(tmp, w_y, *map_y, out)
    return out


class SSIMMapNumba(torch.autograd.Function):
    """``kornia.metrics.ssim(p, t, size)`` of images [H, W, C] (as [1, C, H, W], max_val 1, "same"
    reflect padding) with its gradient to both images."""

    @staticmethod
    def forward(ctx, prediction: Tensor, target: Tensor, size: int) -> Tensor:  # type: ignore[override]
        p = prediction.detach().float().contiguous().numpy()
        t = target.detach().float().contiguous().numpy()
        height, width, c = p.shape
        tables_y, tables_x = _filter_tables(height, size), _filter_tables(width, size)
        raw = np.empty((5 * c, height, width), np.float32)
        _moments(p, t, raw)
        mom = _filter(raw, tables_y, tables_x, transpose=False)
        out = np.empty((c, height, width), np.float32)
        _ssim(mom, out)
        ctx.save_for_backward(torch.from_numpy(p), torch.from_numpy(t), torch.from_numpy(mom))
        ctx.tables = (tables_y, tables_x)
        return torch.from_numpy(out)[None]

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None, None]:  # type: ignore[override]
        p, t, mom = (x.numpy() for x in ctx.saved_tensors)
        g_mom = np.empty_like(mom)
        _moment_grads(mom, grad[0].float().contiguous().numpy(), g_mom)
        g_raw = _filter(g_mom, *ctx.tables, transpose=True)
        gp, gt = np.empty_like(p), np.empty_like(t)
        _input_grads(g_raw, p, t, gp, gt)
        want_p, want_t = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        return (torch.from_numpy(gp) if want_p else None, torch.from_numpy(gt) if want_t else None, None)
