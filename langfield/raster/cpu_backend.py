"""The fast CPU rasterizer: numba kernels with a hand-written backward.

Same arithmetic as :mod:`langfield.raster.torch_backend` (the oracle), arranged for a 2-core CPU:

- tiles run in parallel (``prange`` over workers, each given tiles of about equal total work); inside
  a tile, one 16-pixel row is processed at a time, so the innermost loops run over 16 contiguous
  pixels and the compiler vectorises them;
- a Gaussian is skipped for a whole row of a tile when even the row segment's closest point to its
  centre gets alpha < 1/255 (for the conic [[a, b], [b, c]], q along the row is smallest at
  ``dx = -b dy / a``, clamped to the segment), which changes no pixel;
- ``exp`` is a polynomial: alpha only matters for ``q/2 <= ln 255 < 6``, where
  ``exp(x) = (p(x / 16))^16`` with a degree-7 Taylor ``p`` is accurate to ~1e-7 and needs no SVML;
- the backward walks each pixel's list front to back again and recomputes the transmittance, rather
  than dividing the final transmittance by (1 - alpha) from the back; what lies behind Gaussian i is
  ``C - prefix_i``, known from the forward output;
- gradients are written per (tile, Gaussian) intersection and then summed per Gaussian, one column
  per thread in a fixed order: no two threads write the same memory, so results are deterministic.

Projection and binning run in numba too (:mod:`langfield.raster.cpu_geometry`).

Choice of numba over a C++ extension: it needs no compiler at install time, caches its machine code
(``cache=True``), and keeps the kernels in Python beside the reference they are tested against.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from langfield.raster.binning import TILE_SIZE
from langfield.raster.cpu_geometry import configure_numba_threads

configure_numba_threads()

_F = np.float32
_ALPHA_MIN = _F(1.0 / 255.0)
_ALPHA_MAX = _F(0.99)
_T_MIN = _F(1e-4)
_HALF = _F(0.5)
_ONE = _F(1.0)
_ZERO = _F(0.0)
_EXP_FLOOR = _F(-6.0)  # exp(-6) < 1/255: below this the value only has to stay below ALPHA_MIN
_C = tuple(_F(1.0 / math.factorial(k)) for k in range(8))
_INV16 = _F(1.0 / 16.0)
_ROW_MARGIN = _F(1.001)


@njit(inline="always", fastmath=True)
def _exp_neg(x):
    """exp(x) for x <= 0, accurate where x >= -6 and small (< 1/255) below."""
    t = max(x, _EXP_FLOOR) * _INV16
    p = _C[0] + t * (_C[1] + t * (_C[2] + t * (_C[3] + t * (_C[4] + t * (_C[5] + t * (_C[6] + t * _C[7]))))))
    p = p * p
    p = p * p
    p = p * p
    return p * p


@njit(inline="always", fastmath=True)
def _row_misses(a, b, c, dy, lo, hi, q_bound):
    """Whether q = a dx^2 + 2 b dx dy + c dy^2 exceeds q_bound for every dx in [lo, hi].

    Along the row q is smallest at dx = -b dy / a (a > 0); compared as a dx = -b dy, without dividing.
    """
    t = -b * dy
    if t < a * lo:
        dx = lo
    elif t > a * hi:
        dx = hi
    else:  # the minimum lies inside the segment: q_min = dy^2 det / a
        return dy * dy * (a * c - b * b) > a * q_bound
    return a * dx * dx + _F(2.0) * b * dx * dy + c * dy * dy > q_bound


@njit(inline="always")
def _gather_tile(gids, start, m, means2d, conics, opac, q_max, colors):
    """The m Gaussians listed from `start`, gathered once into contiguous arrays: a tile's 16 rows
    each walk them again. q bounds carry the row test's margin."""
    n_ch = colors.shape[1]
    gx = np.empty(m, np.float32)
    gy = np.empty(m, np.float32)
    ga = np.empty(m, np.float32)
    gb = np.empty(m, np.float32)
    gc = np.empty(m, np.float32)
    go = np.empty(m, np.float32)
    gq = np.empty(m, np.float32)
    gcol = np.empty((m, n_ch), np.float32)
    for j in range(m):
        g = gids[start + j]
        gx[j], gy[j] = means2d[g, 0], means2d[g, 1]
        ga[j], gb[j], gc[j] = conics[g, 0], conics[g, 1], conics[g, 2]
        go[j], gq[j] = opac[g], q_max[g] * _ROW_MARGIN
        for ch in range(n_ch):
            gcol[j, ch] = colors[g, ch]
    return gx, gy, ga, gb, gc, go, gq, gcol


@njit(parallel=True, fastmath=True, cache=True)
def _forward(
    offsets,
    tile_order,
    worker_starts,
    gids,
    means2d,
    conics,
    opac,
    q_max,
    colors,
    background,
    width,
    height,
    tiles_x,
    out,
    t_final,
    n_contrib,
):
    n_ch = colors.shape[1]
    # Each worker takes a precomputed, balanced set of tiles (see _balance): prange splits its range
    # statically, and the tiles' work differs by 2x across an image.
    for w in prange(worker_starts.shape[0] - 1):
        for ti in range(worker_starts[w], worker_starts[w + 1]):
            tile = tile_order[ti]
            start, end = offsets[tile], offsets[tile + 1]
            x0 = (tile % tiles_x) * TILE_SIZE
            y0 = (tile // tiles_x) * TILE_SIZE
            x_lo = _F(x0) + _HALF  # the tile's first and last pixel centres in x
            x_hi = _F(min(x0 + TILE_SIZE, width) - 1) + _HALF
            trans = np.empty(TILE_SIZE, np.float32)
            live = np.empty(TILE_SIZE, np.float32)
            weight = np.empty(TILE_SIZE, np.float32)
            last = np.empty(TILE_SIZE, np.float32)
            xs = np.empty(TILE_SIZE, np.float32)
            acc = np.empty((n_ch, TILE_SIZE), np.float32)
            m = end - start
            gx, gy, ga, gb, gc, go, gq, gcol = _gather_tile(
                gids, start, m, means2d, conics, opac, q_max, colors
            )
            for p in range(TILE_SIZE):
                xs[p] = _F(x0 + p) + _HALF
            for r in range(TILE_SIZE):
                y = y0 + r
                if y >= height:
                    break
                for p in range(TILE_SIZE):
                    trans[p] = _ONE
                    last[p] = _ZERO
                    live[p] = _ONE if x0 + p < width else _ZERO
                acc[:, :] = _ZERO
                py = _F(y) + _HALF
                for j in range(m):
                    ca, cb, cc = ga[j], gb[j], gc[j]
                    cb2 = _F(2.0) * cb
                    dy = py - gy[j]
                    if _row_misses(ca, cb, cc, dy, x_lo - gx[j], x_hi - gx[j], gq[j]):
                        continue
                    o = go[j]
                    mx = gx[j]
                    kf = _F(j + 1)  # tile-local: exact in float32 for any list length that fits memory
                    n_hit = _ZERO
                    n_live = _ZERO
                    # Branch-free over the row's 16 pixels, so LLVM vectorises it.
                    for p in range(TILE_SIZE):
                        dx = xs[p] - mx
                        q = ca * dx * dx + cb2 * dx * dy + cc * dy * dy
                        alpha = min(_ALPHA_MAX, o * _exp_neg(-_HALF * q))
                        ok = _F((alpha >= _ALPHA_MIN) & (q >= _ZERO)) * live[p]
                        test = trans[p] * (_ONE - alpha)
                        hit = ok * _F(test >= _T_MIN)
                        live[p] = live[p] - ok + hit
                        weight[p] = hit * alpha * trans[p]
                        trans[p] = trans[p] + hit * (test - trans[p])
                        last[p] = max(last[p], hit * kf)
                        n_hit += hit
                        n_live += live[p]
                    if n_hit > _ZERO:
                        for ch in range(n_ch):
                            col = gcol[j, ch]
                            for p in range(TILE_SIZE):
                                acc[ch, p] += weight[p] * col
                    if n_live == _ZERO:
                        break
                for p in range(TILE_SIZE):
                    x = x0 + p
                    if x < width:
                        for ch in range(n_ch):
                            out[y, x, ch] = acc[ch, p] + trans[p] * background[ch]
                        t_final[y, x] = trans[p]
                        n_contrib[y, x] = np.int32(start + np.int64(last[p]))


@njit(parallel=True, fastmath=True, cache=True)
def _backward(
    offsets,
    tile_order,
    worker_starts,
    gids,
    means2d,
    conics,
    opac,
    q_max,
    colors,
    width,
    height,
    tiles_x,
    out,
    t_final,
    n_contrib,
    grad_out,
    grad_alpha,
    g_means2d,
    g_conics,
    g_opac,
    g_colors,
    n_geo,
):
    n_ch = colors.shape[1]
    # Each worker takes a precomputed, balanced set of tiles (see _balance): prange splits its range
    # statically, and the tiles' work differs by 2x across an image.
    for w in prange(worker_starts.shape[0] - 1):
        for ti in range(worker_starts[w], worker_starts[w + 1]):
            tile = tile_order[ti]
            start = offsets[tile]  # the row loop stops at the last contributing Gaussian, before the end
            x0 = (tile % tiles_x) * TILE_SIZE
            y0 = (tile // tiles_x) * TILE_SIZE
            x_lo = _F(x0) + _HALF  # the tile's first and last pixel centres in x
            x_hi = _F(min(x0 + TILE_SIZE, width) - 1) + _HALF
            trans = np.empty(TILE_SIZE, np.float32)
            t_end = np.empty(TILE_SIZE, np.float32)
            g_a = np.empty(TILE_SIZE, np.float32)
            last = np.empty(TILE_SIZE, np.int32)
            weight = np.empty(TILE_SIZE, np.float32)
            d_alpha = np.empty(TILE_SIZE, np.float32)
            inv_1m = np.empty(TILE_SIZE, np.float32)
            gauss_px = np.empty(TILE_SIZE, np.float32)
            prefix = np.empty((n_ch, TILE_SIZE), np.float32)
            total = np.empty((n_ch, TILE_SIZE), np.float32)
            g_c = np.empty((n_ch, TILE_SIZE), np.float32)
            hits = np.empty(TILE_SIZE, np.float32)
            lastf = np.empty(TILE_SIZE, np.float32)
            xs = np.empty(TILE_SIZE, np.float32)
            for p in range(TILE_SIZE):
                xs[p] = _F(x0 + p) + _HALF
            # The tile's Gaussians up to its last contributor.
            tile_last = start
            for r in range(min(TILE_SIZE, height - y0)):
                for p in range(min(TILE_SIZE, width - x0)):
                    tile_last = max(tile_last, n_contrib[y0 + r, x0 + p])
            m = tile_last - start
            gx, gy, ga, gb, gc, go, gq, gcol = _gather_tile(
                gids, start, m, means2d, conics, opac, q_max, colors
            )
            for r in range(TILE_SIZE):
                y = y0 + r
                if y >= height:
                    break
                row_last = 0
                for p in range(TILE_SIZE):
                    x = x0 + p
                    if x < width:
                        last[p] = n_contrib[y, x]
                        t_end[p] = t_final[y, x]
                        g_a[p] = grad_alpha[y, x]
                        for ch in range(n_ch):
                            total[ch, p] = out[y, x, ch]
                            g_c[ch, p] = grad_out[y, x, ch]
                    else:
                        last[p] = 0
                        t_end[p] = _ONE
                        g_a[p] = _ZERO
                        for ch in range(n_ch):
                            total[ch, p] = _ZERO
                            g_c[ch, p] = _ZERO
                    row_last = max(row_last, last[p])
                    lastf[p] = _F(max(last[p] - start, 0))
                    trans[p] = _ONE
                prefix[:, :] = _ZERO
                py = _F(y) + _HALF
                for k in range(start, row_last):
                    j = k - start
                    ca, cb, cc = ga[j], gb[j], gc[j]
                    mx, my = gx[j], gy[j]
                    dy = py - my
                    if _row_misses(ca, cb, cc, dy, x_lo - mx, x_hi - mx, gq[j]):
                        continue
                    o = go[j]
                    n_hit = _ZERO
                    kf = _F(j)
                    # Branch-free over the row's 16 pixels (as the forward), so LLVM vectorises it.
                    for p in range(TILE_SIZE):
                        dx = xs[p] - mx
                        q = ca * dx * dx + _F(2.0) * cb * dx * dy + cc * dy * dy
                        gauss = _exp_neg(-_HALF * q)
                        raw = o * gauss
                        gauss_px[p] = gauss
                        alpha = min(_ALPHA_MAX, raw)
                        hit = _F((alpha >= _ALPHA_MIN) & (q >= _ZERO) & (kf < lastf[p]))
                        hits[p] = hit
                        weight[p] = hit * alpha * trans[p]
                        inv_1m[p] = _ONE / (_ONE - alpha)
                        # d alpha_out / d alpha_i = T_final / (1 - alpha_i)
                        d_alpha[p] = hit * (g_a[p] * t_end[p] * inv_1m[p])
                        n_hit += hit
                    if n_hit == _ZERO:
                        continue
                    for ch in range(n_geo):
                        col = gcol[j, ch]
                        s = _ZERO
                        for p in range(TILE_SIZE):
                            w = weight[p]
                            s += w * g_c[ch, p]
                            prefix[ch, p] += w * col
                            # dC/d alpha_i = c_i T_i - (C - prefix_i) / (1 - alpha_i)
                            d = col * trans[p] - (total[ch, p] - prefix[ch, p]) * inv_1m[p]
                            d_alpha[p] += hits[p] * (g_c[ch, p] * d)
                        g_colors[k, ch] += s
                    # Channels from n_geo on pass no gradient to the geometry: only their own values'.
                    for ch in range(n_geo, n_ch):
                        s = _ZERO
                        for p in range(TILE_SIZE):
                            s += weight[p] * g_c[ch, p]
                        g_colors[k, ch] += s
                    gm_x = _ZERO
                    gm_y = _ZERO
                    gca = _ZERO
                    gcb = _ZERO
                    gcc = _ZERO
                    gop = _ZERO
                    for p in range(TILE_SIZE):
                        hit = hits[p]
                        dx = xs[p] - mx
                        gauss = gauss_px[p]
                        raw = o * gauss
                        trans[p] = trans[p] * (_ONE - hit * min(_ALPHA_MAX, raw))
                        # a clamped alpha passes no gradient
                        da = d_alpha[p] * _F(raw < _ALPHA_MAX)
                        gop += da * gauss
                        g_q = -_HALF * raw * da
                        gca += g_q * dx * dx
                        gcb += g_q * _F(2.0) * dx * dy
                        gcc += g_q * dy * dy
                        gm_x -= g_q * (_F(2.0) * ca * dx + _F(2.0) * cb * dy)
                        gm_y -= g_q * (_F(2.0) * cb * dx + _F(2.0) * cc * dy)
                    g_means2d[k, 0] += gm_x
                    g_means2d[k, 1] += gm_y
                    g_conics[k, 0] += gca
                    g_conics[k, 1] += gcb
                    g_conics[k, 2] += gcc
                    g_opac[k] += gop


@njit(cache=True)
def _balance(offsets, n_workers):
    """Tiles grouped per worker so every worker gets about the same number of intersections.

    Longest-processing-time-first: tiles by decreasing count, each to the least loaded worker.
    Returns (tile_order, worker_starts): worker w runs tile_order[worker_starts[w]:worker_starts[w + 1]].
    """
    n_tiles = offsets.shape[0] - 1
    cost = offsets[1:] - offsets[:-1] + 1
    owner = np.empty(n_tiles, np.int64)
    load = np.zeros(n_workers, np.int64)
    for t in np.argsort(-cost, kind="mergesort"):
        w = np.argmin(load)
        owner[t] = w
        load[w] += cost[t]
    counts = np.zeros(n_workers + 1, np.int64)
    for t in range(n_tiles):
        counts[owner[t] + 1] += 1
    starts = np.cumsum(counts)
    cursor = starts[:-1].copy()
    order = np.empty(n_tiles, np.int64)
    for t in range(n_tiles):
        order[cursor[owner[t]]] = t
        cursor[owner[t]] += 1
    return order, starts


@njit(parallel=True, cache=True)
def _scatter_sum(ids, g_m, g_cn, g_op, g_col, s_m, s_cn, s_op, s_col):
    """Per-intersection gradients summed per Gaussian: one column per thread, in intersection order.

    Each column has one writer and a fixed summation order, so the result is deterministic.
    """
    n_ch = g_col.shape[1]
    for j in prange(6 + n_ch):
        for k in range(ids.shape[0]):
            g = ids[k]
            if j < 2:
                s_m[g, j] += g_m[k, j]
            elif j < 5:
                s_cn[g, j - 2] += g_cn[k, j - 2]
            elif j == 5:
                s_op[g] += g_op[k]
            else:
                s_col[g, j - 6] += g_col[k, j - 6]


def _q_max(opacities: np.ndarray) -> np.ndarray:
    """Largest q at which ``o exp(-q/2)`` still reaches 1/255; negative if never."""
    with np.errstate(divide="ignore"):
        q = 2.0 * np.log(np.maximum(opacities.astype(np.float64), 1e-30) * 255.0)
    return np.maximum(q, -1.0).astype(np.float32)


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx, means2d, conics, opacities, colors, background, tile_offsets, gaussian_ids, width, height, n_geo
    ):
        m = means2d.detach().float().contiguous().numpy()
        cn = conics.detach().float().contiguous().numpy()
        op = opacities.detach().float().contiguous().numpy()
        col = colors.detach().float().contiguous().numpy()
        bg = background.detach().float().contiguous().numpy()
        offs = tile_offsets.contiguous().numpy()
        ids = gaussian_ids.contiguous().numpy()
        qm = _q_max(op)
        n_ch = col.shape[1]
        out = np.empty((height, width, n_ch), np.float32)
        t_final = np.empty((height, width), np.float32)
        n_contrib = np.empty((height, width), np.int32)
        tiles_x = math.ceil(width / TILE_SIZE)
        order, starts = _balance(offs, max(1, numba.get_num_threads()))
        _forward(
            offs, order, starts, ids, m, cn, op, qm, col, bg, width, height, tiles_x, out, t_final, n_contrib
        )
        ctx.arrays = (offs, order, starts, ids, m, cn, op, qm, col, out, t_final, n_contrib)
        ctx.size = (width, height, tiles_x)
        ctx.n = means2d.shape[0]
        ctx.n_geo = n_geo
        return torch.from_numpy(out), torch.from_numpy(1.0 - t_final)

    @staticmethod
    def backward(ctx, grad_image, grad_alpha):
        offs, order, starts, ids, m, cn, op, qm, col, out, t_final, n_contrib = ctx.arrays
        width, height, tiles_x = ctx.size
        n_isect, n_ch = ids.shape[0], col.shape[1]
        g_m = np.zeros((n_isect, 2), np.float32)
        g_cn = np.zeros((n_isect, 3), np.float32)
        g_op = np.zeros(n_isect, np.float32)
        g_col = np.zeros((n_isect, n_ch), np.float32)
        go = (
            np.ascontiguousarray(grad_image.float().numpy()) if grad_image is not None else np.zeros_like(out)
        )
        ga = (
            np.ascontiguousarray(grad_alpha.float().numpy())
            if grad_alpha is not None
            else np.zeros_like(t_final)
        )
        _backward(
            offs,
            order,
            starts,
            ids,
            m,
            cn,
            op,
            qm,
            col,
            width,
            height,
            tiles_x,
            out,
            t_final,
            n_contrib,
            go,
            ga,
            g_m,
            g_cn,
            g_op,
            g_col,
            ctx.n_geo,
        )
        n = ctx.n
        s_m, s_cn, s_op, s_col = (np.zeros((n, 2), np.float32), np.zeros((n, 3), np.float32),
                                  np.zeros(n, np.float32), np.zeros((n, n_ch), np.float32))  # fmt: skip
        _scatter_sum(ids, g_m, g_cn, g_op, g_col, s_m, s_cn, s_op, s_col)
        return (
            torch.from_numpy(s_m),
            torch.from_numpy(s_cn),
            torch.from_numpy(s_op),
            torch.from_numpy(s_col),
            None,
            None,
            None,
            None,
            None,
            None,
        )


def rasterize_cpu(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    tile_offsets: Tensor,
    gaussian_ids: Tensor,
    width: int,
    height: int,
    background: Tensor,
    geometry_channels: int | None = None,
) -> tuple[Tensor, Tensor]:
    """Same contract as :func:`langfield.raster.torch_backend.rasterize_torch`, on numba kernels."""
    n_geo = colors.shape[1] if geometry_channels is None else int(geometry_channels)
    return _RasterizeCPU.apply(
        means2d, conics, opacities, colors, background, tile_offsets, gaussian_ids, width, height, n_geo
    )
