"""The hash grid's trilinear interpolation as numba kernels, forward and backward.

Same arithmetic as :class:`langfield.model.hashgrid._InterpolateRows` (the PyTorch reference it is tested
against, values and gradients), arranged for the CPU:

- one pass per level (``prange`` over levels): each level owns its own block ``[l T, (l + 1) T)`` of
  table rows, so the backward's scatter-add into the table needs no atomics and no per-thread copies,
  and the result does not depend on the number of threads;
- inside a level the points run in order, so the corner rows ``[8, L, N]`` and the fractions
  ``[3, L, N]`` are read as 8 + 3 contiguous streams, and each corner's ``F`` features are one
  contiguous row of the point-major ``[L T, F]`` table;
- the 8 weights are recomputed in the backward rather than saved, and the table gradient and the
  gradient of the fractions come out of the same walk over the corners; the fractions' gradient is
  formed once per point from the 8 corner dot products (float accumulators of the table's dtype, no
  per-corner branches: 5x faster than a branch per corner and axis on the colour grid).

In PyTorch the same work is a gather, a broadcast product and a sum forward, and a product and an
``index_add_`` back, each through memory; the language grid (6 features per row) spent ~40 ms per
training step there for 14k Gaussians.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from langfield.kernels import configure_numba

configure_numba()


@njit(inline="always")
def _corner_weights(fx, fy, fz, w):  # pragma: no cover - numba
    """The 8 trilinear weights (:func:`_weights8`) into ``w``, corner ``c = 4 cx + 2 cy + cz``."""
    w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7] = _weights8(fx, fy, fz, np.float32(1.0))


@njit(parallel=True, fastmath=True, cache=True)
def _forward(table, rows, frac, rows_per_level, out, bad):  # pragma: no cover - numba
    n_groups = out.shape[0]
    n_feat = table.shape[1]
    per_group = n_feat // n_groups
    n_levels, n = rows.shape[1], rows.shape[2]
    for level in prange(n_levels):
        lo = level * rows_per_level
        hi = lo + rows_per_level
        col = level * per_group
        acc = np.empty(n_feat, dtype=table.dtype)
        w = np.empty(8, dtype=table.dtype)
        for i in range(n):
            _corner_weights(frac[0, level, i], frac[1, level, i], frac[2, level, i], w)
            for f in range(n_feat):
                acc[f] = 0.0
            for c in range(8):
                r = rows[c, level, i]
                if r < lo or r >= hi:
                    bad[level] = 1
                    continue
                wc = w[c]
                for f in range(n_feat):
                    acc[f] += wc * table[r, f]
            f = 0
            for g in range(n_groups):
                for k in range(per_group):
                    out[g, i, col + k] = acc[f]
                    f += 1


@njit(parallel=True, fastmath=True, cache=True)
def _backward(
    table, rows, frac, grad_out, rows_per_level, grad_table, grad_frac, bad
):  # pragma: no cover - numba
    n_groups = grad_out.shape[0]
    n_feat = table.shape[1]
    per_group = n_feat // n_groups
    n_levels, n = rows.shape[1], rows.shape[2]
    one = np.float32(1.0)
    for level in prange(n_levels):
        lo = level * rows_per_level
        hi = lo + rows_per_level
        col = level * per_group
        go = np.empty(n_feat, dtype=table.dtype)
        w = np.empty(8, dtype=table.dtype)
        d = np.empty(8, dtype=table.dtype)  # dL/dw_c: the output gradient dotted with corner c's row
        for i in range(n):
            fx, fy, fz = frac[0, level, i], frac[1, level, i], frac[2, level, i]
            _corner_weights(fx, fy, fz, w)
            f = 0
            for g in range(n_groups):
                for k in range(per_group):
                    go[f] = grad_out[g, i, col + k]
                    f += 1
            for c in range(8):
                r = rows[c, level, i]
                if r < lo or r >= hi:
                    bad[level] = 1
                    d[c] = 0.0
                    continue
                wc = w[c]
                acc = np.float32(0.0)  # unifies to float64 for a float64 table
                # Both gradients from one loop over the row (2.5x faster than a loop for each).
                for f in range(n_feat):
                    acc += go[f] * table[r, f]
                    grad_table[r, f] += wc * go[f]
                d[c] = acc
            grad_frac[0, level, i], grad_frac[1, level, i], grad_frac[2, level, i] = _frac_gradient(
                d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7], fx, fy, fz, one
            )


@njit(parallel=True, cache=True)
def _corners(  # pragma: no cover - numba
    x, center, two_half, res, max_corner, strides, level_offset, n_dense, primes, mask, consts, rows, frac,
    inside,
):  # fmt: skip
    """Each point's cell at every level: rows [8, L, N] and frac [3, L, N], as HashGrid.corners.

    No fastmath: the float arithmetic is the reference's, operation for operation, so the cells (the
    floor of a product) are the same. ``consts`` holds 0.5, 0 and 1 in the positions' dtype (a float
    literal would widen float32 arithmetic to float64). ``inside[a, i]`` records whether the clamp into
    the box left axis a alone, for the backward.
    """
    n_levels = res.shape[0]
    half, zero, one = consts[0], consts[1], consts[2]
    for i in prange(x.shape[0]):
        v0 = (x[i, 0] - center[0]) / two_half[0] + half
        v1 = (x[i, 1] - center[1]) / two_half[1] + half
        v2 = (x[i, 2] - center[2]) / two_half[2] + half
        inside[0, i] = (v0 >= zero) and (v0 <= one)
        inside[1, i] = (v1 >= zero) and (v1 <= one)
        inside[2, i] = (v2 >= zero) and (v2 <= one)
        u0, u1, u2 = min(max(v0, zero), one), min(max(v1, zero), one), min(max(v2, zero), one)
        for level in range(n_levels):
            p0, p1, p2 = u0 * res[level], u1 * res[level], u2 * res[level]
            top = max_corner[level]
            x0 = min(np.int64(np.floor(p0)), top)
            y0 = min(np.int64(np.floor(p1)), top)
            z0 = min(np.int64(np.floor(p2)), top)
            frac[0, level, i] = p0 - x0
            frac[1, level, i] = p1 - y0
            frac[2, level, i] = p2 - z0
            s1, s2 = strides[1, level], strides[2, level]
            r = _cell_rows(x0, y0, z0, level < n_dense, level_offset[level], s1, s2, primes, mask)
            for c in range(8):
                rows[c, level, i] = r[c]


@njit(parallel=True, fastmath=True, cache=True)
def _corners_backward(grad_frac, res, two_half, inside, grad_x):  # pragma: no cover - numba
    n_levels = res.shape[0]
    for i in prange(grad_x.shape[0]):
        for a in range(3):
            acc = grad_frac[a, 0, i] * res[0]
            for level in range(1, n_levels):
                acc += grad_frac[a, level, i] * res[level]
            grad_x[i, a] = acc / two_half[a] if inside[a, i] else 0.0


@njit(inline="always")
def _cell_rows(x0, y0, z0, dense, off, s1, s2, primes, mask):  # pragma: no cover - numba
    """The 8 corner rows of the cell with lower corner (x0, y0, z0) at one level, in the order of
    :meth:`HashGrid._corner_rows` (corner ``c = 4 cx + 2 cy + cz``); the same integers as :func:`_corners`
    writes. Each axis's two terms are made once and combined (a sum on dense levels, a XOR on hashed)."""
    if dense:
        hx0 = x0 + off
        hx1 = hx0 + 1
        hy0 = y0 * s1
        hy1 = hy0 + s1
        hz0 = z0 * s2
        hz1 = hz0 + s2
        return (hx0 + hy0 + hz0, hx0 + hy0 + hz1, hx0 + hy1 + hz0, hx0 + hy1 + hz1,
                hx1 + hy0 + hz0, hx1 + hy0 + hz1, hx1 + hy1 + hz0, hx1 + hy1 + hz1)  # fmt: skip
    hx0 = (x0 * primes[0]) & mask | off
    hx1 = ((x0 + 1) * primes[0]) & mask | off
    hy0 = (y0 * primes[1]) & mask
    hy1 = ((y0 + 1) * primes[1]) & mask
    hz0 = (z0 * primes[2]) & mask
    hz1 = ((z0 + 1) * primes[2]) & mask
    return (hx0 ^ hy0 ^ hz0, hx0 ^ hy0 ^ hz1, hx0 ^ hy1 ^ hz0, hx0 ^ hy1 ^ hz1,
            hx1 ^ hy0 ^ hz0, hx1 ^ hy0 ^ hz1, hx1 ^ hy1 ^ hz0, hx1 ^ hy1 ^ hz1)  # fmt: skip


@njit(inline="always")
def _weights8(fx, fy, fz, one):  # pragma: no cover - numba
    """The 8 trilinear weights as a tuple, in :func:`_corner_weights`' order."""
    gx, gy, gz = one - fx, one - fy, one - fz
    w00, w01, w10, w11 = gx * gy, gx * fy, fx * gy, fx * fy
    return w00 * gz, w00 * fz, w01 * gz, w01 * fz, w10 * gz, w10 * fz, w11 * gz, w11 * fz


@njit(inline="always")
def _level(level, res, level_offset, n_dense, strides, per_group):  # pragma: no cover - numba
    """A level's cells per axis, block offset, whether it is dense, its dense row strides, and where
    its features go in the output: feature 0 at column ``col`` of group 0, feature 1 at column ``k1``
    of group ``g1`` (groups of ``per_group`` features)."""
    col = level * per_group
    return (
        res[level], level_offset[level], level < n_dense, strides[1, level], strides[2, level],
        col, 1 // per_group, col + 1 % per_group,
    )  # fmt: skip


@njit(inline="always")
def _cell(u, i, r_l, one, dense, off, s1, s2, primes, mask):  # pragma: no cover - numba
    """Point i's cell at the level of ``r_l`` cells per axis: its 8 corner rows (:func:`_cell_rows`)
    and its place in the cell (fx, fy, fz), by the operations of :func:`_corners` (so the same cells);
    the last cell's lower corner ``r_l - 1`` is in the positions' dtype, as the reference's."""
    top = r_l - one
    p0, p1, p2 = u[0, i] * r_l, u[1, i] * r_l, u[2, i] * r_l
    c0, c1, c2 = min(np.floor(p0), top), min(np.floor(p1), top), min(np.floor(p2), top)
    r = _cell_rows(np.int64(c0), np.int64(c1), np.int64(c2), dense, off, s1, s2, primes, mask)
    return r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], p0 - c0, p1 - c1, p2 - c2


@njit(parallel=True, cache=True)
def _unit(x, center, two_half, consts, u, inside, nan):  # pragma: no cover - numba
    """Positions in the grid's unit cube, clamped, as :func:`_corners` makes them: ``u`` [3, N];
    ``inside[a, i]`` whether the clamp left axis a alone; ``nan[0]`` set where a coordinate is NaN
    (it has no cell: the kernels' rows would leave the table)."""
    half, zero, one = consts[0], consts[1], consts[2]
    for i in prange(x.shape[0]):
        for a in range(3):
            v = (x[i, a] - center[a]) / two_half[a] + half
            if v != v:
                nan[0] = 1
                v = zero
            inside[a, i] = (v >= zero) and (v <= one)
            u[a, i] = min(max(v, zero), one)


@njit(inline="always")
def _frac_gradient(d0, d1, d2, d3, d4, d5, d6, d7, fx, fy, fz, one):  # pragma: no cover - numba
    """dL/d(fx, fy, fz) from the corners' dL/dw_c (the output gradient dotted with corner c's row):
    dw_c / df_a is +-1 times the other two axes' factors."""
    gx, gy, gz = one - fx, one - fy, one - fz
    return (
        (d4 - d0) * gy * gz + (d5 - d1) * gy * fz + (d6 - d2) * fy * gz + (d7 - d3) * fy * fz,
        (d2 - d0) * gx * gz + (d3 - d1) * gx * fz + (d6 - d4) * fx * gz + (d7 - d5) * fx * fz,
        (d1 - d0) * gx * gy + (d3 - d2) * gx * fy + (d5 - d4) * fx * gy + (d7 - d6) * fx * fy,
    )


@njit(parallel=True, cache=True)
def _encode_forward(
    u, res, strides, level_offset, n_dense, primes, mask, consts, table, out
):  # pragma: no cover - numba
    """The encoding at unit positions ``u`` [3, N] into ``out`` [G, N, L F / G]: :func:`_corners` and
    :func:`_forward` in one walk, with no [8, L, N] rows in memory. One level per task, as
    :func:`_forward`; the cells are computed with the same operations (no fastmath), so they are the
    same cells. Feature f of a row goes to group ``f // (F / G)``."""
    n_feat, n_levels, n, one = table.shape[1], res.shape[0], u.shape[1], consts[2]
    n_groups = out.shape[0]  # groups of per_group features
    per_group = n_feat // n_groups
    for level in prange(n_levels):
        r_l, off, dense, s1, s2, col, g1, k1 = _level(level, res, level_offset, n_dense, strides, per_group)
        for i in range(n):
            cell = _cell(u, i, r_l, one, dense, off, s1, s2, primes, mask)
            r0, r1, r2, r3, r4, r5, r6, r7, fx, fy, fz = cell
            w0, w1, w2, w3, w4, w5, w6, w7 = _weights8(fx, fy, fz, one)
            if n_feat == 2:  # the colour grid: straight-line code, 1.2-1.3x the speed of the loop
                a = w0 * table[r0, 0] + w1 * table[r1, 0] + w2 * table[r2, 0] + w3 * table[r3, 0]
                b = w0 * table[r0, 1] + w1 * table[r1, 1] + w2 * table[r2, 1] + w3 * table[r3, 1]
                a += w4 * table[r4, 0] + w5 * table[r5, 0] + w6 * table[r6, 0] + w7 * table[r7, 0]
                b += w4 * table[r4, 1] + w5 * table[r5, 1] + w6 * table[r6, 1] + w7 * table[r7, 1]
                out[0, i, col] = a
                out[g1, i, k1] = b
                continue
            f = 0
            for g in range(n_groups):
                for k in range(per_group):
                    v = w0 * table[r0, f] + w1 * table[r1, f] + w2 * table[r2, f] + w3 * table[r3, f]
                    v += w4 * table[r4, f] + w5 * table[r5, f] + w6 * table[r6, f] + w7 * table[r7, f]
                    out[g, i, col + k] = v
                    f += 1


@njit(parallel=True, fastmath=True, cache=True)
def _encode_backward(
    u, res, strides, level_offset, n_dense, primes, mask, consts, table, grad_out, grad_table,
    grad_frac, want_frac,
):  # fmt: skip  # pragma: no cover - numba
    """The table's gradient (added into ``grad_table``) and the fractions' ``grad_frac`` [3, L, N] of
    :func:`_encode_forward`, its cells recomputed; the arithmetic of :func:`_backward`. A row's reads
    come before its writes: LLVM cannot tell ``table`` from ``grad_table``, so a read after a write
    waits for it (the colour grid's two features, read first: 1.6x the speed of a loop over them).
    Without ``want_frac`` a grid of more than two features adds to the table only and leaves
    ``grad_frac`` unwritten: the language grid reads detached positions, and the corner rows' dot
    products with the upstream gradient, which only the positions' gradient needs, were 40 % of its walk
    back."""
    n_feat, n_levels, n, one = table.shape[1], res.shape[0], u.shape[1], consts[2]
    n_groups = grad_out.shape[0]  # groups of per_group features
    per_group = n_feat // n_groups
    for level in prange(n_levels):
        r_l, off, dense, s1, s2, col, g1, k1 = _level(level, res, level_offset, n_dense, strides, per_group)
        go = np.empty(n_feat, table.dtype)
        rows = np.empty(8, np.int64)
        w = np.empty(8, table.dtype)
        d = np.empty(8, table.dtype)
        for i in range(n):
            cell = _cell(u, i, r_l, one, dense, off, s1, s2, primes, mask)
            r0, r1, r2, r3, r4, r5, r6, r7, fx, fy, fz = cell
            w0, w1, w2, w3, w4, w5, w6, w7 = _weights8(fx, fy, fz, one)
            if n_feat == 2:
                ga, gb = grad_out[0, i, col], grad_out[g1, i, k1]
                d0 = ga * table[r0, 0] + gb * table[r0, 1]
                d1 = ga * table[r1, 0] + gb * table[r1, 1]
                d2 = ga * table[r2, 0] + gb * table[r2, 1]
                d3 = ga * table[r3, 0] + gb * table[r3, 1]
                d4 = ga * table[r4, 0] + gb * table[r4, 1]
                d5 = ga * table[r5, 0] + gb * table[r5, 1]
                d6 = ga * table[r6, 0] + gb * table[r6, 1]
                d7 = ga * table[r7, 0] + gb * table[r7, 1]
                for r, wc in ((r0, w0), (r1, w1), (r2, w2), (r3, w3), (r4, w4), (r5, w5), (r6, w6), (r7, w7)):
                    grad_table[r, 0] += wc * ga
                    grad_table[r, 1] += wc * gb
            else:
                f = 0
                for g in range(n_groups):
                    for k in range(per_group):
                        go[f] = grad_out[g, i, col + k]
                        f += 1
                # Corner by corner, each row's features contiguous (as :func:`_backward`).
                rows[0], rows[1], rows[2], rows[3] = r0, r1, r2, r3
                rows[4], rows[5], rows[6], rows[7] = r4, r5, r6, r7
                w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7] = w0, w1, w2, w3, w4, w5, w6, w7
                if not want_frac:
                    for c in range(8):
                        r, wc = rows[c], w[c]
                        for f in range(n_feat):
                            grad_table[r, f] += wc * go[f]
                    continue
                for c in range(8):
                    r, wc = rows[c], w[c]
                    acc = np.float32(0.0)  # unifies to float64 for a float64 table
                    for f in range(n_feat):
                        acc += go[f] * table[r, f]
                        grad_table[r, f] += wc * go[f]
                    d[c] = acc
                d0, d1, d2, d3, d4, d5, d6, d7 = d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7]
            grad_frac[0, level, i], grad_frac[1, level, i], grad_frac[2, level, i] = _frac_gradient(
                d0, d1, d2, d3, d4, d5, d6, d7, fx, fy, fz, one
            )


def _check(bad: np.ndarray, rows_per_level: int) -> None:
    if bad.any():
        levels = np.flatnonzero(bad).tolist()
        raise ValueError(
            f"hash-grid corner rows outside their level's block of {rows_per_level} rows at levels {levels}: "
            "the rows must come from corners() of a grid with the same configuration"
        )


class InterpolateRowsNumba(torch.autograd.Function):
    """Trilinear interpolation of table rows: the numba counterpart of ``_InterpolateRows``.

    ``table``: [L * T, F] point-major table (the parameter's own memory, no copy); ``rows``: [8, L, N]
    int64 from :meth:`HashGrid.corners`; ``frac``: [3, L, N]. Returns [G, N, L * F / G]: the features
    split into ``groups`` G of F / G consecutive features, each group level-major (G = 1 is the plain
    [N, L * F] encoding). The language grid stores its three levels' features side by side in one row
    and reads them back as three encodings, with no permuted copy forward or back.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx, table: Tensor, rows: Tensor, frac: Tensor, rows_per_level: int, groups: int = 1
    ) -> Tensor:
        table_c = table.detach().contiguous()
        rows_c = rows.contiguous()
        frac_c = frac.detach().contiguous()
        n_levels, n = rows.shape[1], rows.shape[2]
        out = torch.empty(groups, n, n_levels * (table.shape[1] // groups), dtype=table.dtype)
        bad = np.zeros(n_levels, dtype=np.uint8)
        _forward(table_c.numpy(), rows_c.numpy(), frac_c.numpy(), rows_per_level, out.numpy(), bad)
        _check(bad, rows_per_level)
        ctx.save_for_backward(table_c, rows_c, frac_c)
        ctx.rows_per_level = rows_per_level
        return out

    @staticmethod
    def backward(ctx, grad_out: Tensor) -> tuple[Tensor | None, None, Tensor | None, None, None]:  # type: ignore[override]
        table, rows, frac = ctx.saved_tensors
        want_table, want_frac = ctx.needs_input_grad[0], ctx.needs_input_grad[2]
        if not (want_table or want_frac):
            return None, None, None, None, None
        grad_out = grad_out.to(table.dtype).contiguous()
        # The kernel always writes both gradients (one branch-free walk); an unwanted one is dropped.
        grad_table = torch.zeros_like(table)
        grad_frac = torch.empty_like(frac)
        bad = np.zeros(rows.shape[1], dtype=np.uint8)
        _backward(
            table.numpy(),
            rows.numpy(),
            frac.numpy(),
            grad_out.numpy(),
            ctx.rows_per_level,
            grad_table.numpy(),
            grad_frac.numpy(),
            bad,
        )
        _check(bad, ctx.rows_per_level)
        return (grad_table if want_table else None), None, (grad_frac if want_frac else None), None, None


class CornersNumba(torch.autograd.Function):
    """:meth:`HashGrid.corners <langfield.model.hashgrid.HashGrid.corners>` in one numba pass: rows
    [8, L, N] int64 and frac [3, L, N] of positions ``x`` [N, 3], the gradient flowing to ``x`` through
    frac. The reference builds the same rows from broadcast tensors of all 8 corners (about 50 ms for
    50k Gaussians at 15 levels on 2 cores; this pass writes each row once).

    ``grid``: a dict of the grid's layout as numpy arrays (:meth:`HashGrid._layout`).
    """

    @staticmethod
    def forward(ctx, x: Tensor, grid: dict) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        xc = x.detach().contiguous()
        dt = xc.numpy().dtype
        n, n_levels = xc.shape[0], grid["res"].shape[0]
        rows = torch.empty(8, n_levels, n, dtype=torch.int64)
        frac = torch.empty(3, n_levels, n, dtype=xc.dtype)
        inside = np.empty((3, n), dtype=np.bool_)
        res, two_half = grid["res"].astype(dt), grid["two_half"].astype(dt)
        _corners(
            xc.numpy(), grid["center"].astype(dt), two_half, res, grid["max_corner"], grid["strides"],
            grid["level_offset"], grid["n_dense"], grid["primes"], grid["mask"],
            np.array([0.5, 0.0, 1.0], dtype=dt), rows.numpy(), frac.numpy(), inside,
        )  # fmt: skip
        ctx.mark_non_differentiable(rows)
        ctx.set_materialize_grads(False)  # else autograd hands backward a zero [8, L, N] for the rows
        ctx.saved = (res, two_half, inside)
        return rows, frac

    @staticmethod
    def backward(ctx, grad_rows: Tensor | None, grad_frac: Tensor | None) -> tuple[Tensor | None, None]:  # type: ignore[override]
        if grad_frac is None:
            return None, None
        res, two_half, inside = ctx.saved
        g = grad_frac.contiguous().numpy()
        grad_x = torch.empty(g.shape[2], 3, dtype=grad_frac.dtype)
        _corners_backward(g, res.astype(g.dtype), two_half.astype(g.dtype), inside, grad_x.numpy())
        return grad_x, None


class EncodeNumba(torch.autograd.Function):
    """:meth:`HashGrid.encode <langfield.model.hashgrid.HashGrid.encode>` in one numba walk per
    direction: positions ``x`` [N, 3] to the features [G, N, L * F / G] of the point-major table
    ``table`` [L * T, F], as :class:`CornersNumba` then :class:`InterpolateRowsNumba` give them, without
    the [8, L, N] int64 rows between them (on fern's 50,000 Gaussians at 15 levels, 48 MB written and
    read twice a step); the backward finds the cells again. ``x`` and ``table`` share one dtype.
    """

    @staticmethod
    def forward(ctx, x: Tensor, table: Tensor, grid: dict, groups: int = 1) -> Tensor:  # type: ignore[override]
        xc = x.detach().contiguous()
        table_c = table.detach().contiguous()
        dt = xc.numpy().dtype
        n, n_levels = xc.shape[0], grid["res"].shape[0]
        consts = np.array([0.5, 0.0, 1.0], dtype=dt)
        two_half, res = grid["two_half"].astype(dt), grid["res"].astype(dt)
        u = np.empty((3, n), dtype=dt)
        inside = np.empty((3, n), dtype=np.bool_)
        nan = np.zeros(1, dtype=np.uint8)
        _unit(xc.numpy(), grid["center"].astype(dt), two_half, consts, u, inside, nan)
        if nan[0]:
            raise ValueError("hash grid: NaN positions have no cell (the Gaussians' means went NaN)")
        cells = (grid["strides"], grid["level_offset"], grid["n_dense"], grid["primes"], grid["mask"])
        layout = (res, *cells, consts)
        out = torch.empty(groups, n, n_levels * (table.shape[1] // groups), dtype=table.dtype)
        _encode_forward(u, *layout, table_c.numpy(), out.numpy())
        ctx.save_for_backward(table_c)
        ctx.saved = (u, inside, two_half, layout)
        return out

    @staticmethod
    def backward(ctx, grad_out: Tensor) -> tuple[Tensor | None, Tensor | None, None, None]:  # type: ignore[override]
        (table,) = ctx.saved_tensors
        want_x, want_table = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        if not (want_x or want_table):
            return None, None, None, None
        u, inside, two_half, layout = ctx.saved
        grad_out = grad_out.to(table.dtype).contiguous()
        # The table's gradient is always made; the positions' only where they want one (a grid of two
        # features, the colour grid's, makes both in one branch-free walk).
        grad_table = torch.zeros_like(table)
        grad_frac = np.empty((3, layout[0].shape[0], u.shape[1]), dtype=u.dtype)
        _encode_backward(u, *layout, table.numpy(), grad_out.numpy(), grad_table.numpy(), grad_frac, want_x)
        grad_x = None
        if want_x:
            grad_x = torch.empty(u.shape[1], 3, dtype=table.dtype)
            _corners_backward(grad_frac, layout[0], two_half, inside, grad_x.numpy())
        return grad_x, (grad_table if want_table else None), None, None
