"""Tests of the multi-resolution hash encoding."""

from __future__ import annotations

import itertools

import pytest
import torch

from langfield.model.hashgrid import HashGrid, HashGridConfig

# Tiny grid: levels of 2, 3 and 5 cells; with 2^6 rows the first two are dense, the last hashed.
TINY = HashGridConfig(
    n_levels=3, features_per_level=2, log2_table_size=6, base_resolution=2, finest_resolution=5
)


def _grid(cfg: HashGridConfig = TINY, seed: int = 0, dtype: torch.dtype = torch.float64) -> HashGrid:
    torch.manual_seed(seed)
    grid = HashGrid(cfg, torch.tensor([0.5, -1.0, 2.0]), torch.tensor([1.0, 2.0, 0.5])).to(dtype)
    with torch.no_grad():  # larger than the 1e-4 init so that interpolation errors are visible
        grid.table.uniform_(-1.0, 1.0)
    return grid


def _world(grid: HashGrid, u: torch.Tensor) -> torch.Tensor:
    """World positions of unit-cube positions u [N, 3]."""
    return grid.center + (2.0 * u - 1.0) * grid.half_extent


def _expected_row(vertex: tuple[int, int, int], res: int, table_size: int) -> int:
    """Instant-NGP's row of a vertex, written out independently of the module."""
    x, y, z = vertex
    if (res + 1) ** 3 <= table_size:
        return x + y * (res + 1) + z * (res + 1) ** 2
    return ((x * 1) ^ (y * 2654435761) ^ (z * 805459861)) % table_size


def test_resolutions_grow_from_base_to_finest() -> None:
    cfg = HashGridConfig()
    res = cfg.resolutions()
    assert res[0] == 16 and res[-1] == 512 and len(res) == 16
    assert all(a < b for a, b in zip(res, res[1:], strict=False))
    assert TINY.resolutions() == [2, 3, 5]


def test_output_shape_and_level_kinds() -> None:
    grid = _grid()
    assert grid.n_dense == 2
    assert grid.table.shape == (3, 64, 2)
    out = grid(_world(grid, torch.rand(7, 3, dtype=torch.float64)))
    assert out.shape == (7, 6)


def test_gradcheck_table_and_positions() -> None:
    grid = _grid()
    g = torch.Generator().manual_seed(1)
    # Interior points far from cell faces, so finite differences do not cross a kink.
    x = _world(grid, 0.05 + 0.9 * torch.rand(6, 3, generator=g, dtype=torch.float64)).requires_grad_(True)

    # A functional call lets gradcheck perturb the table as an input.
    def functional(tab: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(grid, {"table": tab}, (pos,))

    tab = grid.table.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(functional, (tab, x), eps=1e-6, atol=1e-6)


def test_dense_levels_are_collision_free() -> None:
    cfg = HashGridConfig(n_levels=4, log2_table_size=12, base_resolution=4, finest_resolution=32)
    grid = _grid(cfg)
    res = cfg.resolutions()
    assert grid.n_dense >= 2
    for level in range(grid.n_dense):
        r = res[level]
        cells = torch.tensor(list(itertools.product(range(r), repeat=3)), dtype=torch.int64)  # [M, 3]
        lo = cells.t()[:, None, :].expand(3, cfg.n_levels, -1).contiguous()
        rows = grid._corner_rows(lo)[:, level]  # [8, M]
        corners = torch.tensor(list(itertools.product((0, 1), repeat=3)))  # order 4 cx + 2 cy + cz
        verts = cells[None] + corners[:, None]  # [8, M, 3]
        vid = verts[..., 0] + verts[..., 1] * (r + 1) + verts[..., 2] * (r + 1) ** 2
        pairs = torch.unique(torch.stack([vid.reshape(-1), rows.reshape(-1)], dim=1), dim=0)
        # A bijection between the (r + 1)^3 vertices and rows inside this level's block.
        assert len(pairs) == (r + 1) ** 3
        assert len(torch.unique(pairs[:, 1])) == (r + 1) ** 3
        assert pairs[:, 1].min() >= level * cfg.table_size
        assert pairs[:, 1].max() < (level + 1) * cfg.table_size


@pytest.mark.parametrize("level", [0, 1, 2])
def test_interpolation_is_exact_at_vertices(level: int) -> None:
    grid = _grid()
    r = TINY.resolutions()[level]
    verts = torch.tensor(list(itertools.product(range(r + 1), repeat=3)), dtype=torch.int64)
    out = grid(_world(grid, verts.double() / r)).detach()
    f = TINY.features_per_level
    got = out[:, level * f : (level + 1) * f]
    rows = [_expected_row(tuple(v), r, TINY.table_size) for v in verts.tolist()]
    want = grid.table.detach()[level, rows]
    torch.testing.assert_close(got, want, atol=1e-12, rtol=0)


def test_interpolation_is_trilinear_inside_a_cell() -> None:
    grid = _grid()
    u = torch.tensor([[0.3, 0.6, 0.9]], dtype=torch.float64)
    r = 2  # level 0: cell (0, 1, 1), fraction (0.6, 0.2, 0.8)
    lo, frac = [0, 1, 1], [0.6, 0.2, 0.8]
    want = torch.zeros(2, dtype=torch.float64)
    for c in itertools.product((0, 1), repeat=3):
        w = 1.0
        for a in range(3):
            w *= frac[a] if c[a] else 1.0 - frac[a]
        v = tuple(lo[a] + c[a] for a in range(3))
        want += w * grid.table.detach()[0, _expected_row(v, r, TINY.table_size)]
    torch.testing.assert_close(grid(_world(grid, u))[0, :2].detach(), want)


def test_points_outside_the_box_are_clamped_and_finite() -> None:
    grid = _grid(dtype=torch.float32)
    u = torch.tensor([[-3.0, 0.5, 0.5], [0.5, 7.0, 0.5], [1e6, -1e6, 2.0], [1.0, 1.0, 1.0]])
    x = _world(grid, u).requires_grad_(True)
    out = grid(x)
    assert torch.isfinite(out).all()
    torch.testing.assert_close(out, grid(_world(grid, u.clamp(0, 1))))
    out.sum().backward()
    assert torch.isfinite(x.grad).all()
    assert torch.isfinite(grid.table.grad).all()


def test_table_is_one_parameter_initialised_small() -> None:
    grid = HashGrid(HashGridConfig(n_levels=4, log2_table_size=10), torch.zeros(3), 1.0)
    assert [name for name, _ in grid.named_parameters()] == ["table"]
    assert grid.table.abs().max() <= 1e-4


def test_shared_corners_give_the_same_encoding() -> None:
    a, b = _grid(seed=0), _grid(seed=1)
    x = _world(a, torch.rand(5, 3, dtype=torch.float64))
    torch.testing.assert_close(b.interpolate(*a.corners(x)), b(x))


def test_for_scene_sizes_a_small_scene() -> None:
    cfg = HashGridConfig.for_scene(num_points=15_000, image_pixels=160 * 120)
    assert cfg.log2_table_size == 14
    assert 12 <= cfg.n_levels <= 16
    assert 256 <= cfg.finest_resolution <= 512
    res = cfg.resolutions()
    assert max(b / a for a, b in zip(res, res[1:], strict=False)) <= 1.35
    assert HashGridConfig.for_scene(20_000, 160 * 120).log2_table_size == 15
    assert HashGridConfig.for_scene(10, 16).log2_table_size == 12  # clamped below
    big = HashGridConfig.for_scene(10**7, 4000 * 3000)
    assert big.log2_table_size == 19 and big.finest_resolution == 512 and big.n_levels == 15


def test_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="half extent"):
        HashGrid(TINY, torch.zeros(3), 0.0)
    with pytest.raises(ValueError, match=r"\[N, 3\]"):
        _grid()(torch.zeros(4, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="base_resolution"):
        HashGridConfig(base_resolution=64, finest_resolution=32)


# ---------------------------------------------------------------- numba kernels against the reference

LANG = HashGridConfig(
    n_levels=4, features_per_level=6, log2_table_size=8, base_resolution=2, finest_resolution=12
)


def _both(grid: HashGrid, x: torch.Tensor, groups: int, upstream: torch.Tensor) -> list[list[torch.Tensor]]:
    """(output, table gradient, position gradient) from the numba kernels and the PyTorch reference."""
    results = []
    for backend in ("numba", "torch"):
        grid.backend = backend
        grid.table.grad = None
        xr = x.clone().requires_grad_(True)
        out = grid.interpolate(*grid.corners(xr), groups=groups)
        (out * upstream).sum().backward()
        results.append([out.detach(), grid.table.grad.clone(), xr.grad.clone()])
    grid.backend = "auto"
    return results


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("cfg,groups", [(TINY, 1), (LANG, 1), (LANG, 3), (LANG, 6)])
def test_numba_kernels_match_the_reference(cfg, groups, dtype) -> None:
    grid = _grid(cfg, dtype=dtype)
    torch.manual_seed(1)
    # Inside the box, on its faces, outside it (clamped), and many points in one cell (their table
    # gradients must add up, not overwrite each other).
    u = torch.cat([torch.rand(300, 3), torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.5, -0.2, 0.5]])])
    u = torch.cat([u, torch.full((40, 3), 0.31) + 1e-3 * torch.rand(40, 3)]).to(dtype)
    x = _world(grid, u)
    out_shape = (len(x), cfg.out_dim) if groups == 1 else (groups, len(x), cfg.out_dim // groups)
    upstream = torch.randn(out_shape, dtype=dtype)
    (fast, ref) = _both(grid, x, groups, upstream)
    tol = {"atol": 1e-5, "rtol": 1e-5} if dtype == torch.float32 else {"atol": 1e-12, "rtol": 1e-12}
    assert fast[0].shape == out_shape
    for a, b, what in zip(fast, ref, ("values", "table gradient", "position gradient"), strict=True):
        assert torch.isfinite(a).all(), what
        torch.testing.assert_close(a, b, **tol, msg=what)


@pytest.mark.parametrize("cfg,groups", [(TINY, 1), (LANG, 3)])
def test_one_walk_table_gradient_without_positions(cfg, groups) -> None:
    """Detached positions (the language grid's): the walk back leaves the positions' gradient out, and
    the table's is the reference's and, to the bit, the one computed beside the positions'."""
    grid = _grid(cfg, dtype=torch.float32)
    torch.manual_seed(2)
    u = torch.cat([torch.rand(300, 3), torch.full((40, 3), 0.31) + 1e-3 * torch.rand(40, 3)])
    x = _world(grid, u)
    out_shape = (len(x), cfg.out_dim) if groups == 1 else (groups, len(x), cfg.out_dim // groups)
    upstream = torch.randn(out_shape)
    grads = {}
    for backend, wanted in (("numba", False), ("numba", True), ("torch", False)):
        grid.backend = backend
        grid.table.grad = None
        xr = x.clone().requires_grad_(wanted)
        (grid.encode(xr, groups) * upstream).sum().backward()
        assert (xr.grad is not None) == wanted
        grads[backend, wanted] = grid.table.grad.clone()
    assert torch.equal(grads["numba", False], grads["numba", True])
    torch.testing.assert_close(grads["numba", False], grads["torch", False], atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "cfg,groups",
    [(TINY, 1), (TINY, 2), (LANG, 1), (LANG, 3), (HashGridConfig(n_levels=15, log2_table_size=12), 1)],
)
def test_one_walk_matches_the_reference(cfg, groups, dtype) -> None:
    """encode's one numba walk (cells found and interpolated together, forward and back) against the
    PyTorch reference's corners then interpolate: values, table and position gradients, inside the
    box, on its faces, outside it, and many points in one cell."""
    grid = _grid(cfg, dtype=dtype)
    torch.manual_seed(1)
    u = torch.cat([torch.rand(300, 3), torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.5, -0.2, 0.5]])])
    x = _world(grid, torch.cat([u, torch.full((40, 3), 0.31) + 1e-3 * torch.rand(40, 3)]).to(dtype))
    out_shape = (len(x), cfg.out_dim) if groups == 1 else (groups, len(x), cfg.out_dim // groups)
    upstream = torch.randn(out_shape, dtype=dtype)
    results = []
    for backend in ("numba", "torch"):
        grid.backend = backend
        assert grid.one_walk(x) == (backend == "numba")
        grid.table.grad = None
        xr = x.clone().requires_grad_(True)
        out = grid.encode(xr, groups)
        (out * upstream).sum().backward()
        results.append([out.detach(), grid.table.grad.clone(), xr.grad.clone()])
    fast, ref = results
    assert fast[0].shape == out_shape
    tol = {"atol": 1e-5, "rtol": 1e-5} if dtype == torch.float32 else {"atol": 1e-12, "rtol": 1e-12}
    # The position gradient sums one term per level, each up to |upstream| x the level's resolution.
    largest = (upstream.abs().amax() * max(cfg.resolutions()) * 2 * grid.table.abs().amax()).item()
    pos_atol = max(tol["atol"], 4e-7 * largest) if dtype == torch.float32 else tol["atol"]
    for a, b, what in zip(fast, ref, ("values", "table gradient", "position gradient"), strict=True):
        assert torch.isfinite(a).all(), what
        atol = pos_atol if what == "position gradient" else tol["atol"]
        torch.testing.assert_close(a, b, atol=atol, rtol=tol["rtol"], msg=what)
    assert (fast[2][-41, :2] == 0).all()  # the point outside the box: its clamped axes pass no gradient


def test_one_walk_refuses_nan_and_handles_no_points() -> None:
    grid = _grid(LANG, dtype=torch.float32)
    assert grid.encode(torch.zeros(0, 3)).shape == (0, LANG.out_dim)
    assert grid.encode(torch.zeros(0, 3), groups=3).shape == (3, 0, LANG.out_dim // 3)
    x = torch.rand(10, 3)
    x[4, 1] = float("inf")  # clamped onto the box's face, as the reference does
    assert torch.isfinite(grid.encode(x)).all()
    x[4, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN positions"):
        grid.encode(x)
    assert not grid.one_walk(x.double())  # another dtype than the table's: corners, then interpolate
    with pytest.raises(ValueError, match="groups must divide"):
        grid.encode(x, groups=4)


@pytest.mark.slow
def test_numba_kernels_pass_gradcheck() -> None:
    grid = _grid(LANG)
    x = _world(grid, torch.rand(12, 3, dtype=torch.float64)).requires_grad_(True)

    def encode(p, table):  # the table enters through the grid; gradcheck perturbs it in place
        return grid.interpolate(*grid.corners(p), groups=3)

    def one_walk(p, table):
        return grid.encode(p, groups=3)

    assert torch.autograd.gradcheck(encode, (x, grid.table))
    assert torch.autograd.gradcheck(one_walk, (x, grid.table))


def test_groups_split_the_plain_encoding() -> None:
    grid = _grid(LANG)
    x = _world(grid, torch.rand(20, 3, dtype=torch.float64))
    plain = grid(x).reshape(20, LANG.n_levels, 3, 2)  # per level: 3 groups of 2 features
    grouped = grid.interpolate(*grid.corners(x), groups=3)  # [3, N, L * 2]
    torch.testing.assert_close(grouped, plain.permute(2, 0, 1, 3).reshape(3, 20, -1))
    with pytest.raises(ValueError, match="groups must divide"):
        grid.interpolate(*grid.corners(x), groups=4)


def test_numba_kernels_handle_no_points_and_reject_foreign_rows() -> None:
    grid = _grid(LANG)
    empty = grid(torch.zeros(0, 3, dtype=torch.float64))
    assert empty.shape == (0, LANG.out_dim)
    rows, frac = grid.corners(torch.zeros(5, 3, dtype=torch.float64))
    rows = rows.clone()
    rows[0, 2, 1] = 0  # a level-0 row at level 2: not from this grid's layout
    with pytest.raises(ValueError, match="outside their level's block"):
        grid.interpolate(rows, frac)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "cfg", [TINY, LANG, HashGridConfig(n_levels=15, log2_table_size=12, finest_resolution=300)]
)
def test_numba_corners_match_the_reference(cfg, dtype) -> None:
    """The cells (rows exactly), the fractions and the positions' gradient through them, inside the box,
    on its faces and outside it, at dense and hashed levels."""
    grid = _grid(cfg, dtype=dtype)
    torch.manual_seed(2)
    u = torch.cat([torch.rand(500, 3), torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.5, -0.2, 0.5]])])
    x = _world(grid, u.to(dtype))
    upstream = torch.randn(3, cfg.n_levels, len(x), dtype=dtype)
    results = []
    for backend in ("numba", "torch"):
        grid.backend = backend
        xr = x.clone().requires_grad_(True)
        rows, frac = grid.corners(xr)
        (frac * upstream).sum().backward()
        results.append((rows, frac.detach(), xr.grad))
    grid.backend = "auto"
    (rows, frac, grad), (rows_ref, frac_ref, grad_ref) = results
    assert torch.equal(rows, rows_ref)
    tol = {"atol": 1e-5, "rtol": 1e-5} if dtype == torch.float32 else {"atol": 1e-12, "rtol": 1e-12}
    torch.testing.assert_close(frac, frac_ref, **tol)
    # The gradient sums one term per level, each up to |upstream| x the level's resolution (300 at the
    # finest), in an order of the compiler's choosing: float32 keeps a few ulps of the largest term.
    largest = (upstream.abs().amax() * max(cfg.resolutions())).item()
    atol = max(tol["atol"], 4e-7 * largest) if dtype == torch.float32 else tol["atol"]
    torch.testing.assert_close(grad, grad_ref, atol=atol, rtol=tol["rtol"])
    assert (grad[-1, :2] == 0).all()  # clamped axes pass no gradient
    rows, frac = grid.corners(torch.zeros(0, 3, dtype=dtype))
    assert rows.shape == (8, cfg.n_levels, 0) and frac.shape == (3, cfg.n_levels, 0)
