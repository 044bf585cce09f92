"""The fast CPU rasterizer: numba kernels with a hand-written backward.

Same arithmetic as :mod:`langfield.raster.composite` (the oracle), arranged for a 2-core CPU:

- tiles run in parallel (``prange`` over workers, each given tiles of about equal total work); inside
  a tile, one 16-pixel row is processed at a time, so the innermost loops run over 16 contiguous
  pixels (vector instructions where LLVM can tell the arrays apart, see ``_F_ROWS``);
- a Gaussian is skipped on the rows of a tile where even the row segment's closest point to its
  centre gets alpha < 1/255, which changes no pixel; those rows are found once per (tile, Gaussian)
  as an interval (:func:`_row_span`), not tested row by row;
- ``exp`` is a polynomial: alpha only matters for ``q/2 <= ln 255 < 6``, where
  ``exp(x) = (p(x / 16))^16`` with a degree-7 Taylor ``p`` is accurate to ~1e-7 and needs no SVML;
- the backward walks each pixel's list front to back again and recomputes the transmittance, rather
  than dividing the final transmittance by (1 - alpha) from the back; what lies behind Gaussian i is
  ``C - prefix_i``, known from the forward output, and the channels enter d alpha only through the
  dot product of their upstream gradient with the colour (:func:`_channels_row`);
- gradients are written per (tile, Gaussian) intersection and then summed per Gaussian, each thread
  owning a range of Gaussians and adding in list order: no two threads write the same memory, so
  results are deterministic.

Projection and binning run in numba too (:mod:`langfield.raster.projection_cpu`,
:mod:`langfield.raster.binning_cpu`).

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

from langfield.kernels import configure_numba
from langfield.raster.binning import TILE_SIZE

configure_numba()

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
# The forward's per-pixel state: rows of one [_F_ROWS + channels, 16] array per tile, the channels'
# sums last. In one array, LLVM can tell that a store to one row leaves the others alone (separate
# arrays might overlap, as far as it knows) and packs each row's 16 pixels into vector instructions
# (with SLP vectorisation on, langfield.kernels.configure_numba); fern's forward took 97 ms with
# separate arrays and 29 ms so (504x378, 24k Gaussians, 13 channels).
_TRANS, _LIVE, _WEIGHT, _LAST, _XS, _GAUSS, _TRANS_H, _LIVE_H, _LAST_H, _ACC_H, _F_ROWS = range(11)
# The backward's per-pixel state, likewise rows of one [_B_ROWS + channels, 16] array per tile: the
# first stream's (_B_), the second stream's (_H_), then the upstream gradient of each channel.
(_B_TRANS, _B_END, _B_GA, _B_WEIGHT, _B_DALPHA, _B_INV, _B_GAUSS, _B_HIT, _B_LAST, _B_XS, _B_QOK, _B_DOT,
 _B_SEEN, _B_BEHIND, _H_TRANS, _H_END, _H_GA, _H_GC, _H_TOTAL, _H_PREFIX, _H_LAST, _H_HIT, _H_WEIGHT,
 _H_INV, _H_DALPHA, _B_ROWS) = range(26)  # fmt: skip
_G_CH = 16  # channels a row of the backward's pixel-major upstream gradients holds


@njit(inline="always", fastmath=True)
def _exp_neg(x):
    """exp(x) for x <= 0, accurate where x >= -6 and small (< 1/255) below."""
    t = max(x, _EXP_FLOOR) * _INV16
    p = _C[0] + t * (_C[1] + t * (_C[2] + t * (_C[3] + t * (_C[4] + t * (_C[5] + t * (_C[6] + t * _C[7]))))))
    p = p * p
    p = p * p
    p = p * p
    return p * p


@njit(inline="always")
def _end_span(a, b, c, det, x, q_bound):
    """The dy where q at dx = x is at most q_bound: c dy^2 + 2 b x dy + a x^2 <= q_bound (a dy-interval,
    empty when the discriminant is negative)."""
    disc = c * q_bound - x * x * det
    if disc < 0.0:
        return False, 0.0, 0.0
    root = math.sqrt(disc)
    return True, (-b * x - root) / c, (-b * x + root) / c


@njit(inline="always")
def _row_span(a, b, c, lo, hi, q_bound, dy0):
    """The rows ``[r0, r1)`` of a tile (row r at ``dy = dy0 + r`` from the centre) where
    ``q = a dx^2 + 2 b dx dy + c dy^2`` can be at most ``q_bound`` for some dx in ``[lo, hi]``; at every
    other row alpha < 1/255 at each pixel, so the row is skipped. Once per (tile, Gaussian) instead of a
    test per row: the set of such dy is an interval (the ellipse q <= q_bound cut to the strip
    lo <= dx <= hi is convex), the union of where the row's smallest q lies inside the segment
    (dx = -b dy / a, q = dy^2 det / a) and where it lies at one of its ends. Widened by 0.1 % of its
    length and 1e-3 pixel, in float64: a row just outside is evaluated, never one inside skipped.
    Degenerate conics (det <= 0) get every row."""
    a, b, c = np.float64(a), np.float64(b), np.float64(c)
    lo, hi, q_bound, dy0 = np.float64(lo), np.float64(hi), np.float64(q_bound), np.float64(dy0)
    if q_bound < 0.0:
        return 0, 0
    det = a * c - b * b
    if not (a > 0.0 and c > 0.0 and det > 0.0):
        return 0, TILE_SIZE
    reach = math.sqrt(q_bound * a / det)
    found, y_lo, y_hi = False, 0.0, 0.0
    if b == 0.0:
        if lo <= 0.0 <= hi:
            found, y_lo, y_hi = True, -reach, reach
    else:
        t1, t2 = -a * lo / b, -a * hi / b
        y_lo, y_hi = max(-reach, min(t1, t2)), min(reach, max(t1, t2))
        found = y_lo <= y_hi
    for x in (lo, hi):
        ok, e_lo, e_hi = _end_span(a, b, c, det, x, q_bound)
        if ok:
            y_lo, y_hi = (min(y_lo, e_lo), max(y_hi, e_hi)) if found else (e_lo, e_hi)
            found = True
    if not found:
        return 0, 0
    pad = 1e-3 * (y_hi - y_lo) + 1e-3
    first, last = y_lo - pad - dy0, y_hi + pad - dy0  # in rows of the tile
    r0 = 0 if first <= 0.0 else (TILE_SIZE if first >= TILE_SIZE else int(math.ceil(first)))
    r1 = 0 if last < 0.0 else (TILE_SIZE if last >= TILE_SIZE - 1 else int(math.floor(last)) + 1)
    return r0, max(r0, r1)


@njit(inline="always")
def _add_row_grads(k, g_means2d, g_conics, g_opac, ca, cb, cc, dy, q0, q1, q2, gop):
    """Intersection k's gradients of its centre, conic and opacity from one tile row, added to a
    pass's arrays. On a row dy is one value, so with g_q = dL/dq at each pixel (q = a dx^2 + 2 b dx dy
    + c dy^2) the six sums the chain rule needs come from three: q0 = sum g_q, q1 = sum g_q dx and
    q2 = sum g_q dx^2 (dq/da = dx^2, dq/db = 2 dx dy, dq/dc = dy^2, dq/dmean = -dq/d(dx, dy))."""
    g_means2d[k, 0] -= _F(2.0) * (ca * q1 + cb * dy * q0)
    g_means2d[k, 1] -= _F(2.0) * (cb * q1 + cc * dy * q0)
    g_conics[k, 0] += q2
    g_conics[k, 1] += _F(2.0) * dy * q1
    g_conics[k, 2] += dy * dy * q0
    g_opac[k] += gop


@njit(inline="always")
def _zero_rows(lo, hi, g_means2d, g_conics, g_opac, g_values):
    """Intersections lo..hi-1's gradient rows set to zero. Each intersection belongs to one tile, so
    the tile's worker clears its own rows (in parallel, just before it adds to them), rather than the
    caller clearing all of them in one thread first (12 MB on fern, 2-3 ms)."""
    for k in range(lo, hi):
        g_means2d[k, 0] = _ZERO
        g_means2d[k, 1] = _ZERO
        for c in range(3):
            g_conics[k, c] = _ZERO
        g_opac[k] = _ZERO
        for c in range(g_values.shape[1]):
            g_values[k, c] = _ZERO


@njit(inline="always")
def _gather_tile(gids, start, m, means2d, conics, opac, q_max, colors, x_lo, x_hi, y0, spans, known):
    """The m Gaussians listed from `start`, gathered once into contiguous arrays: a tile's 16 rows
    each walk them again. The rows each Gaussian can reach in this tile (x from x_lo to x_hi, rows
    from y0; its q bound with the margin _ROW_MARGIN) are [span[j, 0], span[j, 1]): read from
    ``spans`` (per intersection) where ``known``, else found and, where ``spans`` has rows, kept there
    (the forward finds them, the backward reads them: 5 ms of float64 arithmetic on fern, once)."""
    n_ch = colors.shape[1]
    gx = np.empty(m, np.float32)
    gy = np.empty(m, np.float32)
    ga = np.empty(m, np.float32)
    gb = np.empty(m, np.float32)
    gc = np.empty(m, np.float32)
    go = np.empty(m, np.float32)
    gcol = np.empty((m, n_ch), np.float32)
    span = np.empty((m, 2), np.int64)
    for j in range(m):
        g = gids[start + j]
        gx[j], gy[j] = means2d[g, 0], means2d[g, 1]
        ga[j], gb[j], gc[j] = conics[g, 0], conics[g, 1], conics[g, 2]
        go[j] = opac[g]
        if known:
            span[j, 0], span[j, 1] = spans[start + j, 0], spans[start + j, 1]
        else:
            q_bound, dy0 = q_max[g] * _ROW_MARGIN, _F(y0) + _HALF - gy[j]
            span[j, 0], span[j, 1] = _row_span(ga[j], gb[j], gc[j], x_lo - gx[j], x_hi - gx[j], q_bound, dy0)
            if spans.shape[0] > 0:
                spans[start + j, 0], spans[start + j, 1] = span[j, 0], span[j, 1]
        for ch in range(n_ch):
            gcol[j, ch] = colors[g, ch]
    return gx, gy, ga, gb, gc, go, gcol, span


@njit(inline="always")
def _gather_pair(gids, start, m, opac_h, q_max_h, values_h):
    """The second stream's opacity, value and q bound per listed Gaussian (none without one); its
    reachable rows are left to :func:`_span_h`, marked not yet found (-1)."""
    k = m if opac_h.shape[0] > 0 else 0
    go = np.empty(k, np.float32)
    gv = np.empty(k, np.float32)
    gq = np.empty(k, np.float32)
    span = np.full((k, 2), -1, np.int64)
    for j in range(k):
        g = gids[start + j]
        go[j], gv[j], gq[j] = opac_h[g], values_h[g], q_max_h[g]
    return go, gv, gq, span


@njit(inline="always")
def _span_h(span, j, gq, gx, gy, ga, gb, gc, x_lo, x_hi, y0):
    """The rows of the tile the second stream's Gaussian j reaches (as :func:`_gather_tile`'s), found
    when first asked: the stream (the hard depth, every opacity 0.99) is spent at a pixel long before
    the first on faint Gaussians, so only the Gaussians it gets to need them."""
    if span[j, 0] < 0:
        span[j, 0], span[j, 1] = _row_span(
            ga[j], gb[j], gc[j], x_lo - gx[j], x_hi - gx[j], gq[j] * _ROW_MARGIN, _F(y0) + _HALF - gy[j]
        )
    return span[j, 0], span[j, 1]


@njit(inline="always")
def _tile(ti, tile_order, offsets, tiles_x, width):
    """The ti-th tile of the order: where its list starts, its length, its first pixel (x0, y0) and its
    first and last pixel centres in x."""
    tile = tile_order[ti]
    start = offsets[tile]
    x0 = (tile % tiles_x) * TILE_SIZE
    y0 = (tile // tiles_x) * TILE_SIZE
    x_last = _F(min(x0 + TILE_SIZE, width) - 1) + _HALF
    return start, offsets[tile + 1] - start, x0, y0, _F(x0) + _HALF, x_last


@njit(inline="always")
def _tile_rows(rows, x0):
    """Every per-pixel row of a tile in one array (see _F_ROWS), its pixel centres in x filled in."""
    s = np.empty((rows, TILE_SIZE), np.float32)
    for p in range(TILE_SIZE):
        s[_XS, p] = _F(x0 + p) + _HALF
    return s


@njit(inline="always")
def _start_row(s, x0, width):
    """A row's state before its first Gaussian: transmittance 1, no contributor yet, the pixels inside
    the image live."""
    for p in range(TILE_SIZE):
        s[_TRANS, p] = _ONE
        s[_LAST, p] = _ZERO
        s[_LIVE, p] = _ONE if x0 + p < width else _ZERO


@njit(inline="always", fastmath=True)
def _hit_row(s, mx, dy, ca, cb2, cc, o, kf):
    """One Gaussian over a tile row's 16 pixels (the row dy from its centre): each pixel's footprint
    (_GAUSS), weight (_WEIGHT, 0 where it is skipped) and the transmittance and liveness it leaves.
    Returns the pixels it reached and those still live after it."""
    n_hit = _ZERO
    n_live = _ZERO
    # Branch-free over the row's 16 pixels, so LLVM vectorises it.
    for p in range(TILE_SIZE):
        dx = s[_XS, p] - mx
        q = ca * dx * dx + cb2 * dx * dy + cc * dy * dy
        e = _exp_neg(-_HALF * q)
        s[_GAUSS, p] = e * _F(q >= _ZERO)
        alpha = min(_ALPHA_MAX, o * e)
        ok = _F((alpha >= _ALPHA_MIN) & (q >= _ZERO)) * s[_LIVE, p]
        test = s[_TRANS, p] * (_ONE - alpha)
        hit = ok * _F(test >= _T_MIN)
        s[_LIVE, p] = s[_LIVE, p] - ok + hit
        s[_WEIGHT, p] = hit * alpha * s[_TRANS, p]
        s[_TRANS, p] = s[_TRANS, p] + hit * (test - s[_TRANS, p])
        s[_LAST, p] = max(s[_LAST, p], hit * kf)
        n_hit += hit
        n_live += s[_LIVE, p]
    return n_hit, n_live


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
    opac_h,
    q_max_h,
    values_h,
    background_h,
    out_h,
    t_final_h,
    n_contrib_h,
    spans,
    n_ch_fixed,
):
    n_ch = colors.shape[1] if len(n_ch_fixed) == 0 else len(n_ch_fixed)  # see FIXED_CHANNELS
    pair = opac_h.shape[0] > 0  # a second, one-channel stream (see rasterize_pair_cpu)
    # Each worker takes a precomputed, balanced set of tiles (see _balance): prange splits its range
    # statically, and the tiles' work differs by 2x across an image.
    for w in prange(worker_starts.shape[0] - 1):
        for ti in range(worker_starts[w], worker_starts[w + 1]):
            start, m, x0, y0, x_lo, x_hi = _tile(ti, tile_order, offsets, tiles_x, width)
            s = _tile_rows(_F_ROWS + n_ch, x0)
            gx, gy, ga, gb, gc, go, gcol, span = _gather_tile(
                gids, start, m, means2d, conics, opac, q_max, colors, x_lo, x_hi, y0, spans, False
            )
            goh, gvh, gqh, span_h = _gather_pair(gids, start, m, opac_h, q_max_h, values_h)
            for r in range(TILE_SIZE):
                y = y0 + r
                if y >= height:
                    break
                _start_row(s, x0, width)
                for p in range(TILE_SIZE):
                    s[_TRANS_H, p] = _ONE
                    s[_LAST_H, p] = _ZERO
                    s[_LIVE_H, p] = s[_LIVE, p]
                    s[_ACC_H, p] = _ZERO
                s[_F_ROWS:, :] = _ZERO
                n_live = _ZERO  # each stream's live pixels, kept from the last Gaussian that reached it
                for p in range(TILE_SIZE):
                    n_live += s[_LIVE, p]
                n_live_h = n_live if pair else _ZERO
                py = _F(y) + _HALF
                for j in range(m):
                    ca, cb, cc = ga[j], gb[j], gc[j]
                    cb2 = _F(2.0) * cb
                    dy = py - gy[j]
                    miss = r < span[j, 0] or r >= span[j, 1]
                    # A spent second stream is skipped: the list holds every Gaussian at the second
                    # opacity's larger extent, so most of a row's list comes after that stream is spent.
                    miss_h = n_live_h == _ZERO
                    if not miss_h:
                        lo_h, hi_h = _span_h(span_h, j, gqh, gx, gy, ga, gb, gc, x_lo, x_hi, y0)
                        miss_h = r < lo_h or r >= hi_h
                    if miss and miss_h:
                        continue
                    o = go[j]
                    mx = gx[j]
                    kf = _F(j + 1)  # tile-local: exact in float32 for any list length that fits memory
                    if miss:  # only the second stream reaches this row: the footprint alone
                        for p in range(TILE_SIZE):
                            dx = s[_XS, p] - mx
                            q = ca * dx * dx + cb2 * dx * dy + cc * dy * dy
                            s[_GAUSS, p] = _exp_neg(-_HALF * q) * _F(q >= _ZERO)
                    else:
                        _, n_live = _hit_row(s, mx, dy, ca, cb2, cc, o, kf)
                        # Added whether or not a pixel was hit (a weight of 0 adds 0): a test of the
                        # row's hits before the 13 multiply-adds cost more than it saved (fern: 5 %).
                        for ch in range(n_ch):
                            col = gcol[j, ch]
                            for p in range(TILE_SIZE):
                                s[_F_ROWS + ch, p] += s[_WEIGHT, p] * col
                    if not miss_h:
                        # The same Gaussian's footprint (gauss) with the second stream's opacity.
                        oh = goh[j]
                        val = gvh[j]
                        n_live_h = _ZERO
                        for p in range(TILE_SIZE):
                            alpha = min(_ALPHA_MAX, oh * s[_GAUSS, p])
                            ok = _F(alpha >= _ALPHA_MIN) * s[_LIVE_H, p]
                            test = s[_TRANS_H, p] * (_ONE - alpha)
                            hit = ok * _F(test >= _T_MIN)
                            s[_LIVE_H, p] = s[_LIVE_H, p] - ok + hit
                            s[_ACC_H, p] += hit * alpha * s[_TRANS_H, p] * val
                            s[_TRANS_H, p] = s[_TRANS_H, p] + hit * (test - s[_TRANS_H, p])
                            s[_LAST_H, p] = max(s[_LAST_H, p], hit * kf)
                            n_live_h += s[_LIVE_H, p]
                    if n_live + n_live_h == _ZERO:
                        break
                for p in range(TILE_SIZE):
                    x = x0 + p
                    if x < width:
                        for ch in range(n_ch):
                            out[y, x, ch] = s[_F_ROWS + ch, p] + s[_TRANS, p] * background[ch]
                        t_final[y, x] = s[_TRANS, p]
                        n_contrib[y, x] = np.int32(start + np.int64(s[_LAST, p]))
                        if pair:
                            out_h[y, x, 0] = s[_ACC_H, p] + s[_TRANS_H, p] * background_h
                            t_final_h[y, x] = s[_TRANS_H, p]
                            n_contrib_h[y, x] = np.int32(start + np.int64(s[_LAST_H, p]))


@njit(parallel=True, fastmath=True, cache=True)
def _forward_slots(
    offsets, tile_order, worker_starts, gids, means2d, conics, opac, q_max, slots, width, height, tiles_x, out
):
    """:func:`_forward`'s first stream, each hit adding its weight to the Gaussian's own columns of
    ``out`` ([H, W, n_slots]; see rasterize_slots_cpu) instead of every channel's value."""
    n_ch = out.shape[2]
    k = slots.shape[1]
    none = np.empty((0, 0), np.float32)
    no_spans = np.empty((0, 2), np.int8)
    for w in prange(worker_starts.shape[0] - 1):
        for ti in range(worker_starts[w], worker_starts[w + 1]):
            start, m, x0, y0, x_lo, x_hi = _tile(ti, tile_order, offsets, tiles_x, width)
            s = _tile_rows(_F_ROWS + n_ch, x0)
            gx, gy, ga, gb, gc, go, _, span = _gather_tile(
                gids, start, m, means2d, conics, opac, q_max, none, x_lo, x_hi, y0, no_spans, False
            )
            for r in range(TILE_SIZE):
                y = y0 + r
                if y >= height:
                    break
                _start_row(s, x0, width)
                s[_F_ROWS:, :] = _ZERO
                py = _F(y) + _HALF
                for j in range(m):
                    if r < span[j, 0] or r >= span[j, 1]:
                        continue
                    dy = py - gy[j]
                    n_hit, n_live = _hit_row(s, gx[j], dy, ga[j], _F(2.0) * gb[j], gc[j], go[j], _F(j + 1))
                    if n_hit > _ZERO:
                        g = gids[start + j]
                        for c in range(k):
                            ch = slots[g, c]
                            if ch >= 0:
                                for p in range(TILE_SIZE):
                                    s[_F_ROWS + ch, p] += s[_WEIGHT, p]
                    if n_live == _ZERO:
                        break
                for p in range(TILE_SIZE):
                    x = x0 + p
                    if x < width:
                        for ch in range(n_ch):
                            out[y, x, ch] = s[_F_ROWS + ch, p]


@njit(inline="always", fastmath=True)
def _footprint_row(s, j, mx, my, ca, cb, cc, o, py, miss):
    """Gaussian j's footprint on a tile row (rows _B_GAUSS, _B_QOK) and, unless the first stream
    misses the row, its alpha's hits, weights, 1 / (1 - alpha) and d alpha from the alpha output.
    Returns the first stream's number of hits."""
    dy = py - my
    kf = _F(j)
    n_hit = _ZERO
    if miss:  # only the second stream reaches this row: the footprint alone
        for p in range(TILE_SIZE):
            dx = s[_B_XS, p] - mx
            q = ca * dx * dx + _F(2.0) * cb * dx * dy + cc * dy * dy
            s[_B_GAUSS, p] = _exp_neg(-_HALF * q)
            s[_B_QOK, p] = _F(q >= _ZERO)
        return n_hit
    # Branch-free over the row's 16 pixels (as the forward), so LLVM vectorises it.
    for p in range(TILE_SIZE):
        dx = s[_B_XS, p] - mx
        q = ca * dx * dx + _F(2.0) * cb * dx * dy + cc * dy * dy
        gauss = _exp_neg(-_HALF * q)
        s[_B_GAUSS, p] = gauss
        s[_B_QOK, p] = _F(q >= _ZERO)
        alpha = min(_ALPHA_MAX, o * gauss)
        hit = _F((alpha >= _ALPHA_MIN) & (q >= _ZERO) & (kf < s[_B_LAST, p]))
        s[_B_HIT, p] = hit
        s[_B_WEIGHT, p] = hit * alpha * s[_B_TRANS, p]
        s[_B_INV, p] = _ONE / (_ONE - alpha)
        # d alpha_out / d alpha_i = T_final / (1 - alpha_i)
        s[_B_DALPHA, p] = hit * (s[_B_GA, p] * s[_B_END, p] * s[_B_INV, p])
        n_hit += hit
    return n_hit


@njit(inline="always", fastmath=True)
def _channels_row(s, g_px, gcol, j, k, n_geo, n_ch, n_chunk, g_colors):
    """Gaussian j's colour gradient on a tile row (to intersection k), and its channels' part of
    d alpha. Per pixel, with g the upstream gradient, c_i the colours, C the pixel's output:

        sum_ch g (c_i T_i - (C - prefix_i) / (1 - alpha_i))
            = (g . c_i) T_i - (g . C - sum_{j <= i} w_j (g . c_j)) / (1 - alpha_i),

    so the channels meet only in the dot g . c_i (_B_DOT), one multiply-add per channel and pixel; the
    running sum (_B_SEEN) and g . C (_B_BEHIND) are one row each. The colour gradient, the sum over
    the row's pixels of weight x g, runs over the channels in g_px (pixel-major) instead: one
    vector multiply-add per pixel, not a 16-pixel sum per channel."""
    for p in range(TILE_SIZE):
        s[_B_DOT, p] = _ZERO
    for ch in range(n_geo):  # channels from n_geo on pass no gradient to the geometry
        col = gcol[j, ch]
        for p in range(TILE_SIZE):
            s[_B_DOT, p] += s[_B_ROWS + ch, p] * col
    for p in range(TILE_SIZE):
        s[_B_SEEN, p] += s[_B_WEIGHT, p] * s[_B_DOT, p]
        d = s[_B_DOT, p] * s[_B_TRANS, p] - (s[_B_BEHIND, p] - s[_B_SEEN, p]) * s[_B_INV, p]
        s[_B_DALPHA, p] += s[_B_HIT, p] * d
    for c in range(n_chunk):
        b = c * (TILE_SIZE + 1)
        acc = b + TILE_SIZE
        for q in range(_G_CH):
            g_px[acc, q] = _ZERO
        for p in range(TILE_SIZE):
            w = s[_B_WEIGHT, p]
            for q in range(_G_CH):
                g_px[acc, q] += w * g_px[b + p, q]
        for q in range(min(_G_CH, n_ch - c * _G_CH)):
            g_colors[k, c * _G_CH + q] += g_px[acc, q]


@njit(inline="always", fastmath=True)
def _geometry_row(s, k, mx, my, ca, cb, cc, o, py, g_means2d, g_conics, g_opac):
    """The first stream's gradients of intersection k's centre, conic and opacity from a tile row's
    d alpha; then the row's transmittance moves past the Gaussian."""
    gop = _ZERO
    q0 = _ZERO
    q1 = _ZERO
    q2 = _ZERO
    for p in range(TILE_SIZE):
        hit = s[_B_HIT, p]
        dx = s[_B_XS, p] - mx
        gauss = s[_B_GAUSS, p]
        raw = o * gauss
        s[_B_TRANS, p] = s[_B_TRANS, p] * (_ONE - hit * min(_ALPHA_MAX, raw))
        # a clamped alpha passes no gradient
        da = s[_B_DALPHA, p] * _F(raw < _ALPHA_MAX)
        gop += da * gauss
        g_q = -_HALF * raw * da
        q0 += g_q
        q1 += g_q * dx
        q2 += g_q * dx * dx
    _add_row_grads(k, g_means2d, g_conics, g_opac, ca, cb, cc, py - my, q0, q1, q2, gop)


@njit(inline="always", fastmath=True)
def _second_stream_row(s, k, j, mx, my, ca, cb, cc, oh, val, py, g_means2d, g_conics, g_opac, g_values):
    """The second stream on a tile row: same footprint (_B_GAUSS, from _footprint_row), its own
    opacity, one channel, every gradient its own (to intersection k of the _h arrays)."""
    kf = _F(j)
    n_hit_h = _ZERO
    for p in range(TILE_SIZE):
        alpha = min(_ALPHA_MAX, oh * s[_B_GAUSS, p])
        hit = _F((alpha >= _ALPHA_MIN) & (kf < s[_H_LAST, p])) * s[_B_QOK, p]
        s[_H_HIT, p] = hit
        s[_H_WEIGHT, p] = hit * alpha * s[_H_TRANS, p]
        s[_H_INV, p] = _ONE / (_ONE - alpha)
        s[_H_DALPHA, p] = hit * (s[_H_GA, p] * s[_H_END, p] * s[_H_INV, p])
        n_hit_h += hit
    if n_hit_h == _ZERO:
        return
    g_val = _ZERO
    gop = _ZERO
    q0 = _ZERO
    q1 = _ZERO
    q2 = _ZERO
    for p in range(TILE_SIZE):
        w = s[_H_WEIGHT, p]
        g_val += w * s[_H_GC, p]
        s[_H_PREFIX, p] += w * val
        d = val * s[_H_TRANS, p] - (s[_H_TOTAL, p] - s[_H_PREFIX, p]) * s[_H_INV, p]
        hit = s[_H_HIT, p]
        raw = oh * s[_B_GAUSS, p]
        da = (s[_H_DALPHA, p] + hit * (s[_H_GC, p] * d)) * _F(raw < _ALPHA_MAX)
        s[_H_TRANS, p] = s[_H_TRANS, p] * (_ONE - hit * min(_ALPHA_MAX, raw))
        dx = s[_B_XS, p] - mx
        gop += da * s[_B_GAUSS, p]
        g_q = -_HALF * raw * da
        q0 += g_q
        q1 += g_q * dx
        q2 += g_q * dx * dx
    g_values[k, 0] += g_val
    _add_row_grads(k, g_means2d, g_conics, g_opac, ca, cb, cc, py - my, q0, q1, q2, gop)


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
    geo,
    opac_h,
    q_max_h,
    values_h,
    out_h,
    t_final_h,
    n_contrib_h,
    grad_out_h,
    grad_alpha_h,
    g_means2d_h,
    g_conics_h,
    g_opac_h,
    g_values_h,
    spans,
    n_ch_fixed,
    n_geo_fixed,
):
    n_ch = colors.shape[1] if len(n_ch_fixed) == 0 else len(n_ch_fixed)  # see FIXED_CHANNELS
    n_geo = geo if len(n_geo_fixed) == 0 else len(n_geo_fixed)
    n_chunk = (n_ch + _G_CH - 1) // _G_CH
    pair = opac_h.shape[0] > 0
    # Each worker takes a precomputed, balanced set of tiles (see _balance): prange splits its range
    # statically, and the tiles' work differs by 2x across an image.
    for w in prange(worker_starts.shape[0] - 1):
        for ti in range(worker_starts[w], worker_starts[w + 1]):
            tile = tile_order[ti]
            start = offsets[tile]  # the row loop stops at the last contributing Gaussian, before the end
            _zero_rows(start, offsets[tile + 1], g_means2d, g_conics, g_opac, g_colors)
            if pair:
                _zero_rows(start, offsets[tile + 1], g_means2d_h, g_conics_h, g_opac_h, g_values_h)
            x0 = (tile % tiles_x) * TILE_SIZE
            y0 = (tile // tiles_x) * TILE_SIZE
            x_lo = _F(x0) + _HALF  # the tile's first and last pixel centres in x
            x_hi = _F(min(x0 + TILE_SIZE, width) - 1) + _HALF
            s = np.empty((_B_ROWS + n_ch, TILE_SIZE), np.float32)
            # The upstream gradients pixel-major, _G_CH channels a row, then the colour gradient's sums.
            g_px = np.zeros((n_chunk * (TILE_SIZE + 1), _G_CH), np.float32)
            last = np.empty(TILE_SIZE, np.int32)
            for p in range(TILE_SIZE):
                s[_B_XS, p] = _F(x0 + p) + _HALF
            # The tile's Gaussians up to its last contributor (of either stream).
            tile_last = start
            for r in range(min(TILE_SIZE, height - y0)):
                for p in range(min(TILE_SIZE, width - x0)):
                    tile_last = max(tile_last, n_contrib[y0 + r, x0 + p])
                    if pair:
                        tile_last = max(tile_last, n_contrib_h[y0 + r, x0 + p])
            m = tile_last - start
            gx, gy, ga, gb, gc, go, gcol, span = _gather_tile(
                gids, start, m, means2d, conics, opac, q_max, colors, x_lo, x_hi, y0, spans, True
            )
            goh, gvh, gqh, span_h = _gather_pair(gids, start, m, opac_h, q_max_h, values_h)
            for r in range(TILE_SIZE):
                y = y0 + r
                if y >= height:
                    break
                row_last = 0
                row_last_h = 0  # past it, no pixel of the row has a second-stream contributor
                for p in range(TILE_SIZE):
                    x = x0 + p
                    inside = x < width
                    last[p] = n_contrib[y, x] if inside else 0
                    s[_B_END, p] = t_final[y, x] if inside else _ONE
                    s[_B_GA, p] = grad_alpha[y, x] if inside else _ZERO
                    behind = _ZERO
                    for ch in range(n_ch):
                        g = grad_out[y, x, ch] if inside else _ZERO
                        s[_B_ROWS + ch, p] = g
                        g_px[(ch // _G_CH) * (TILE_SIZE + 1) + p, ch % _G_CH] = g
                        if ch < n_geo and inside:
                            behind += g * out[y, x, ch]
                    s[_B_BEHIND, p] = behind
                    s[_B_SEEN, p] = _ZERO
                    row_last = max(row_last, last[p])
                    s[_B_LAST, p] = _F(max(last[p] - start, 0))
                    s[_B_TRANS, p] = _ONE
                    s[_H_TRANS, p] = _ONE
                    s[_H_PREFIX, p] = _ZERO
                    s[_H_LAST, p] = _ZERO
                    if pair and inside:
                        last_h = n_contrib_h[y, x]
                        row_last_h = max(row_last_h, last_h)
                        s[_H_LAST, p] = _F(max(last_h - start, 0))
                    s[_H_END, p] = t_final_h[y, x] if pair and inside else _ONE
                    s[_H_GA, p] = grad_alpha_h[y, x] if pair and inside else _ZERO
                    s[_H_TOTAL, p] = out_h[y, x, 0] if pair and inside else _ZERO
                    s[_H_GC, p] = grad_out_h[y, x, 0] if pair and inside else _ZERO
                py = _F(y) + _HALF
                for k in range(start, max(row_last, row_last_h)):
                    j = k - start
                    # Each stream only up to its own last contributor in the row.
                    miss = k >= row_last or r < span[j, 0] or r >= span[j, 1]
                    miss_h = k >= row_last_h
                    if not miss_h:
                        lo_h, hi_h = _span_h(span_h, j, gqh, gx, gy, ga, gb, gc, x_lo, x_hi, y0)
                        miss_h = r < lo_h or r >= hi_h
                    if miss and miss_h:
                        continue
                    n_hit = _footprint_row(s, j, gx[j], gy[j], ga[j], gb[j], gc[j], go[j], py, miss)
                    if not miss_h:
                        _second_stream_row(
                            s, k, j, gx[j], gy[j], ga[j], gb[j], gc[j], goh[j], gvh[j], py,
                            g_means2d_h, g_conics_h, g_opac_h, g_values_h,
                        )  # fmt: skip
                    if n_hit == _ZERO:
                        continue
                    _channels_row(s, g_px, gcol, j, k, n_geo, n_ch, n_chunk, g_colors)
                    _geometry_row(
                        s, k, gx[j], gy[j], ga[j], gb[j], gc[j], go[j], py, g_means2d, g_conics, g_opac
                    )


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
def _scatter_sum(ids, g_m, g_cn, g_op, g_col, s_m, s_cn, s_op, s_col, n_parts):
    """Per-intersection gradients summed per Gaussian. Part w of ``n_parts`` (one per thread) owns a
    contiguous range of Gaussians and walks every intersection, adding those of its own ones.

    Each Gaussian has one writer and its intersections are added in list order whatever the number of
    parts, so the result is deterministic. (One column per thread instead re-read the list 19 times
    and wrote scattered single floats: 3-6 ms against about 1 ms on fern.)
    """
    n = s_op.shape[0]
    n_ch = g_col.shape[1]
    for w in prange(n_parts):
        lo = n * w // n_parts
        hi = n * (w + 1) // n_parts
        for k in range(ids.shape[0]):
            g = ids[k]
            if g < lo or g >= hi:
                continue
            s_m[g, 0] += g_m[k, 0]
            s_m[g, 1] += g_m[k, 1]
            for c in range(3):
                s_cn[g, c] += g_cn[k, c]
            s_op[g] += g_op[k]
            for c in range(n_ch):
                s_col[g, c] += g_col[k, c]


def _q_max(opacities: np.ndarray) -> np.ndarray:
    """Largest q at which ``o exp(-q/2)`` still reaches 1/255; negative if never."""
    with np.errstate(divide="ignore"):
        q = 2.0 * np.log(np.maximum(opacities.astype(np.float64), 1e-30) * 255.0)
    return np.maximum(q, -1.0).astype(np.float32)


# Channel counts the compositing kernels are also compiled for as constants, beside the kernel for any
# count: training renders 4 channels (colour and depth, all 4 moving the geometry) and 13 with the
# language latents (4 moving the geometry), the bench 13 (all 13). With the count known, LLVM unrolls
# the loops over the channels whole: fern's view, 13 channels, forward 23.0 -> 19.9 ms, backward 38.9
# -> 36.7 ms. A count travels as the length of a tuple of zeros, which is part of the tuple's type (so
# each length has its machine code) and is read at dispatch as fast as any argument; an integer marked
# `numba.literally` did the same but went through the compiler's typing on every call (about 1 s).
FIXED_CHANNELS = ((4, 4), (13, 4), (13, 13))


def _fixed(n_ch: int, n_geo: int) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The channel and geometry-channel counts of a call as tuples of that many zeros where the pair
    is one of FIXED_CHANNELS, else empty tuples (the counts read at run time)."""
    if (n_ch, n_geo) not in FIXED_CHANNELS:
        return (), ()
    return (0,) * n_ch, (0,) * n_geo


_NO_PAIR = (
    np.zeros(0, np.float32),  # opacities
    np.zeros(0, np.float32),  # q bounds
    np.zeros(0, np.float32),  # values
)


def _pair_outputs(height: int, width: int, pair: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The second stream's image [H, W, 1], final transmittance and last contributors (1x1 stand-ins
    without one)."""
    h, w = (height, width) if pair else (1, 1)
    return np.zeros((h, w, 1), np.float32), np.ones((h, w), np.float32), np.zeros((h, w), np.int32)


def _as_np(t: Tensor) -> np.ndarray:
    return t.detach().float().contiguous().numpy()


class _RasterizeCPU(torch.autograd.Function):
    """One stream (colour + features) or, with ``pair``, also a second one-channel stream that shares
    the first one's footprints (means2d, conics: equal values) but has its own opacities and values and
    passes its gradients to its own inputs (``means2d_h``, ``conics_h``, ...)."""

    @staticmethod
    def forward(
        ctx,
        means2d,
        conics,
        opacities,
        colors,
        background,
        tile_offsets,
        gaussian_ids,
        width,
        height,
        n_geo,
        means2d_h=None,
        conics_h=None,
        opacities_h=None,
        values_h=None,
    ):
        pair = opacities_h is not None
        m, cn, op, col, bg = (_as_np(t) for t in (means2d, conics, opacities, colors, background))
        offs = tile_offsets.contiguous().numpy()
        ids = gaussian_ids.contiguous().numpy()
        qm = _q_max(op)
        stream_h = _NO_PAIR
        if pair:
            op_h = _as_np(opacities_h.reshape(-1))
            stream_h = (op_h, _q_max(op_h), _as_np(values_h.reshape(-1)))
        n_ch = col.shape[1]
        out = np.empty((height, width, n_ch), np.float32)
        t_final = np.empty((height, width), np.float32)
        n_contrib = np.empty((height, width), np.int32)
        out_h, t_final_h, n_contrib_h = _pair_outputs(height, width, pair)
        tiles_x = math.ceil(width / TILE_SIZE)
        order, starts = _balance(offs, max(1, numba.get_num_threads()))
        spans = np.empty((ids.shape[0], 2), np.int8)  # each intersection's rows in its tile (0..16)
        _forward(
            offs, order, starts, ids, m, cn, op, qm, col, bg, width, height, tiles_x, out, t_final, n_contrib,
            *stream_h, _F(0.0), out_h, t_final_h, n_contrib_h, spans, _fixed(n_ch, n_geo)[0],
        )  # fmt: skip
        ctx.arrays = (offs, order, starts, ids, m, cn, op, qm, col, out, t_final, n_contrib, spans)
        ctx.pair = (stream_h, out_h, t_final_h, n_contrib_h)
        ctx.size = (width, height, tiles_x)
        ctx.n = means2d.shape[0]
        ctx.n_geo = n_geo
        image, alpha = torch.from_numpy(out), torch.from_numpy(1.0 - t_final)
        if not pair:
            return image, alpha
        return image, alpha, torch.from_numpy(out_h), torch.from_numpy(1.0 - t_final_h)

    @staticmethod
    def backward(ctx, grad_image, grad_alpha, grad_image_h=None, grad_alpha_h=None):
        offs, order, starts, ids, m, cn, op, qm, col, out, t_final, n_contrib, spans = ctx.arrays
        stream_h, out_h, t_final_h, n_contrib_h = ctx.pair
        pair = stream_h[0].shape[0] > 0
        width, height, tiles_x = ctx.size
        n_isect, n_ch = ids.shape[0], col.shape[1]

        def upstream(grad, like):
            return np.ascontiguousarray(grad.float().numpy()) if grad is not None else np.zeros_like(like)

        go, ga = upstream(grad_image, out), upstream(grad_alpha, t_final)
        go_h, ga_h = upstream(grad_image_h, out_h), upstream(grad_alpha_h, t_final_h)
        k = n_isect if pair else 0
        # Not cleared here: each tile's worker clears its own intersections' rows (_zero_rows).
        g_m, g_cn = np.empty((n_isect, 2), np.float32), np.empty((n_isect, 3), np.float32)
        g_op, g_col = np.empty(n_isect, np.float32), np.empty((n_isect, n_ch), np.float32)
        g_m_h, g_cn_h = np.empty((k, 2), np.float32), np.empty((k, 3), np.float32)
        g_op_h, g_val_h = np.empty(k, np.float32), np.empty((k, 1), np.float32)
        _backward(
            offs, order, starts, ids, m, cn, op, qm, col, width, height, tiles_x, out, t_final, n_contrib,
            go, ga, g_m, g_cn, g_op, g_col, ctx.n_geo,
            *stream_h, out_h, t_final_h, n_contrib_h, go_h, ga_h, g_m_h, g_cn_h, g_op_h, g_val_h, spans,
            *_fixed(n_ch, ctx.n_geo),
        )  # fmt: skip
        grads = [*_summed(ids, ctx.n, g_m, g_cn, g_op, g_col), None, None, None, None, None, None]
        if pair:
            grads += _summed(ids, ctx.n, g_m_h, g_cn_h, g_op_h, g_val_h)
        return tuple(grads)


def _summed(ids, n, g_m, g_cn, g_op, g_col) -> list[Tensor]:
    """Per-intersection gradients summed per Gaussian (deterministically, see _scatter_sum)."""
    s_m, s_cn, s_op, s_col = (np.zeros((n, 2), np.float32), np.zeros((n, 3), np.float32),
                              np.zeros(n, np.float32), np.zeros((n, g_col.shape[1]), np.float32))  # fmt: skip
    _scatter_sum(ids, g_m, g_cn, g_op, g_col, s_m, s_cn, s_op, s_col, max(1, numba.get_num_threads()))
    return [torch.from_numpy(a) for a in (s_m, s_cn, s_op, s_col)]


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
    """Same contract as :func:`langfield.raster.composite.rasterize_torch`, on numba kernels."""
    n_geo = colors.shape[1] if geometry_channels is None else int(geometry_channels)
    return _RasterizeCPU.apply(
        means2d, conics, opacities, colors, background, tile_offsets, gaussian_ids, width, height, n_geo
    )


def rasterize_pair_cpu(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    means2d_h: Tensor,
    conics_h: Tensor,
    opacities_h: Tensor,
    values_h: Tensor,
    tile_offsets: Tensor,
    gaussian_ids: Tensor,
    width: int,
    height: int,
    background: Tensor,
    geometry_channels: int | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Two rasterizations of the same footprints in one walk over the tiles: :func:`rasterize_cpu` of
    (means2d, conics, opacities, colors) and of (means2d_h, conics_h, opacities_h, values_h [N, 1]) on a
    zero background. The footprints must be equal in value (a second projection of the same Gaussians,
    for instance with rotations and scales detached); each stream's gradients go to its own inputs.
    The lists must hold every Gaussian either stream reaches (binned with the larger opacity).

    Returns (image [H, W, C], alpha [H, W], image_h [H, W, 1], alpha_h [H, W]).
    """
    if not (
        torch.equal(means2d.detach(), means2d_h.detach()) and torch.equal(conics.detach(), conics_h.detach())
    ):
        raise ValueError("rasterize_pair_cpu: the two streams' footprints (means2d, conics) differ")
    n_geo = colors.shape[1] if geometry_channels is None else int(geometry_channels)
    return _RasterizeCPU.apply(
        means2d, conics, opacities, colors, background, tile_offsets, gaussian_ids, width, height, n_geo,
        means2d_h, conics_h, opacities_h, values_h,
    )  # fmt: skip


def rasterize_slots_cpu(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    slots: Tensor,
    n_slots: int,
    tile_offsets: Tensor,
    gaussian_ids: Tensor,
    width: int,
    height: int,
) -> Tensor:
    """The render of one-hot rows without making them: ``[H, W, n_slots]`` whose channel c is
    ``sum_i w_i(p) [c in slots[i]]``, the rendering weights of the Gaussians that list column c.

    Equal to :func:`rasterize_cpu` of the ``[N, n_slots]`` rows with a 1 at each of a Gaussian's
    ``slots`` (``[N, K]`` long, -1: none; a Gaussian's columns distinct) on a zero background, with the
    same transmittance; a hit adds to K columns instead of all n_slots. Reading a codebook by vote
    (:mod:`langfield.model.reading`) renders one column per entry: on a 160x120 view of the built-in
    scene (4,952 Gaussians), 175 one-hot channels took 46 ms, 13 colour and latent channels 15 ms, and
    the 175 columns given by index 12 ms. No gradient.
    """
    k = slots.shape[1] if slots.dim() == 2 else -1
    if k < 1 or slots.shape[0] != means2d.shape[0]:
        raise ValueError(f"rasterize_slots_cpu: slots must be [N, K >= 1], got {tuple(slots.shape)}")
    if n_slots < 1 or int(slots.max()) >= n_slots:
        raise ValueError(f"rasterize_slots_cpu: columns must lie below n_slots={n_slots}")
    m, cn, op = (_as_np(t) for t in (means2d, conics, opacities))
    offs = tile_offsets.contiguous().numpy()
    out = np.empty((height, width, n_slots), np.float32)
    order, starts = _balance(offs, max(1, numba.get_num_threads()))
    cols = slots.detach().to(torch.int64).contiguous().numpy()
    _forward_slots(
        offs, order, starts, gaussian_ids.contiguous().numpy(), m, cn, op, _q_max(op), cols, width, height,
        math.ceil(width / TILE_SIZE), out,
    )  # fmt: skip
    return torch.from_numpy(out)
