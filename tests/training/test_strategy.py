"""Tests of the Gaussian parameters (gaussians.py) and of densification (strategy.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from langfield.model import gaussians as G
from langfield.raster.projection import quat_to_rotmat
from langfield.training.densify import DensifyStrategy, duplicate, remove, split

BOUNDS = np.array([[-1.0, -2.0, 0.0], [1.0, 2.0, 3.0]])
N = 40


def _setup(seed: int = 0, single_adam: bool = False, fused: bool = False):
    """Gaussians with an extra "lang" entry, optimizers that have taken one step, and strategy state.

    ``fused``: PyTorch's fused Adam (its step count is a tensor; its moments must follow the rows all
    the same)."""
    params = G.init_gaussians(BOUNDS, N, seed=seed)
    params["lang"] = nn.Parameter(torch.randn(N, 9, generator=torch.Generator().manual_seed(seed)))
    lrs = {**G.learning_rates(2.0), "lang": 1e-3}
    if single_adam:
        opt = torch.optim.Adam(
            [{"params": [p], "lr": lrs[k], "name": k} for k, p in params.items()], fused=fused
        )
        optimizers = {"gaussians": opt}
    else:
        optimizers = {
            k: torch.optim.Adam([{"params": [p], "lr": lrs[k], "name": k}], fused=fused)
            for k, p in params.items()
        }
    g = torch.Generator().manual_seed(seed + 1)
    for p in params.values():
        p.grad = torch.randn(p.shape, generator=g)
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    state = DensifyStrategy().initialize_state(params)
    state["grad2d"] += torch.rand(N, generator=g)
    state["count"] += 1
    return params, optimizers, state


def _adam_state(optimizers, p: nn.Parameter) -> dict:
    for opt in optimizers.values():
        if p in opt.state:
            return opt.state[p]
    raise AssertionError("parameter has no optimizer state")


def _snapshot(params, optimizers) -> dict[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
    return {
        k: (
            p.detach().clone(),
            _adam_state(optimizers, p)["exp_avg"].clone(),
            _adam_state(optimizers, p)["exp_avg_sq"].clone(),
        )
        for k, p in params.items()
    }


def _check_in_step(params, optimizers, n: int) -> None:
    """Every entry has n rows, is the object in its param group, and Adam can step."""
    for name, p in params.items():
        assert p.shape[0] == n, name
        groups = [g for opt in optimizers.values() for g in opt.param_groups if g.get("name") == name]
        assert len(groups) == 1 and groups[0]["params"][0] is p
        st = _adam_state(optimizers, p)
        assert st["exp_avg"].shape == p.shape and st["exp_avg_sq"].shape == p.shape
        p.grad = torch.ones_like(p)
    for opt in optimizers.values():
        opt.step()
    assert all(torch.isfinite(p).all() for p in params.values())


# ---------------------------------------------------------------- gaussians.py


def test_init_gaussians_shapes_bounds_and_defaults() -> None:
    p = G.init_gaussians(BOUNDS, 500, seed=3)
    assert {k: tuple(v.shape) for k, v in p.items()} == {
        "means": (500, 3),
        "log_scales": (500, 3),
        "quats": (500, 4),
        "opacity_logits": (500, 1),
    }
    means = p["means"].detach()
    assert (means >= torch.tensor(BOUNDS[0]).float()).all() and (
        means <= torch.tensor(BOUNDS[1]).float()
    ).all()
    assert torch.equal(p["quats"].detach(), torch.tensor([[1.0, 0, 0, 0]]).expand(500, 4))
    torch.testing.assert_close(G.opacities(p), torch.full((500, 1), 0.1))
    assert all(v.requires_grad and v.dtype == torch.float32 for v in p.values())


def test_init_gaussians_is_seeded() -> None:
    a, b, c = (G.init_gaussians(BOUNDS, 100, seed=s) for s in (7, 7, 8))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not torch.equal(a["means"], c["means"])


def test_init_scales_are_rms_distance_to_three_neighbours() -> None:
    p = G.init_gaussians(BOUNDS, 200, seed=0)
    means = p["means"].detach().double()
    d2 = torch.cdist(means, means).square()
    d2.fill_diagonal_(float("inf"))
    want = 0.5 * torch.log(d2.topk(3, largest=False).values.mean(dim=1))
    torch.testing.assert_close(p["log_scales"].detach()[:, 0].double(), want, atol=1e-4, rtol=1e-4)
    assert torch.equal(p["log_scales"][:, 0], p["log_scales"][:, 2])


def test_duplicate_points_get_finite_scales() -> None:
    pts = torch.tensor([[0.0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0]])
    log_scales = G.log_scales_from_neighbors(pts)
    assert torch.isfinite(log_scales).all()
    assert G.init_gaussians(BOUNDS, 1, seed=0)["log_scales"].isfinite().all()


def test_zero_quaternion_normalises_to_identity_with_finite_gradient() -> None:
    q = torch.tensor([[0.0, 0, 0, 0], [0, 2, 0, 0], [1, 1, 1, 1]], requires_grad=True)
    out = G.normalize_quats(q)
    torch.testing.assert_close(out, torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0.5, 0.5, 0.5, 0.5]]))
    out.sum().backward()
    assert torch.isfinite(q.grad).all()
    rot = quat_to_rotmat(out)
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3).expand(3, 3, 3), atol=1e-6, rtol=0)


def test_num_gaussians_for_scene() -> None:
    assert G.num_gaussians_for_scene(BOUNDS, 160 * 120, 3) == 8_640
    assert G.num_gaussians_for_scene(BOUNDS, 10, 3) == 2_000
    assert G.num_gaussians_for_scene(BOUNDS, 4000 * 3000, 3) == 50_000
    with pytest.raises(ValueError, match="bounds"):
        G.num_gaussians_for_scene(np.zeros((2, 3)), 100, 3)


def test_learning_rates_cover_the_parameters() -> None:
    lrs = G.learning_rates(3.0)
    assert set(lrs) == set(G.init_gaussians(BOUNDS, 5, seed=0))
    assert lrs["means"] == pytest.approx(1.6e-4 * 3.0)


# ---------------------------------------------------------------- duplicate / split / remove


@pytest.mark.parametrize("fused", [False, True])
@pytest.mark.parametrize("single_adam", [False, True])
def test_duplicate_keeps_optimizer_state(single_adam: bool, fused: bool) -> None:
    params, optimizers, state = _setup(single_adam=single_adam, fused=fused)
    before = _snapshot(params, optimizers)
    mask = torch.zeros(N, dtype=torch.bool)
    mask[[1, 5, 30]] = True
    duplicate(params, optimizers, state, mask)
    for name, p in params.items():
        old_p, old_m, old_v = before[name]
        st = _adam_state(optimizers, p)
        assert torch.equal(p[:N], old_p) and torch.equal(p[N:], old_p[mask])
        assert torch.equal(st["exp_avg"][:N], old_m) and torch.equal(st["exp_avg_sq"][:N], old_v)
        assert (st["exp_avg"][N:] == 0).all() and (st["exp_avg_sq"][N:] == 0).all()
    assert state["grad2d"].shape == (N + 3,) and (state["grad2d"][N:] == 0).all()
    _check_in_step(params, optimizers, N + 3)


@pytest.mark.parametrize("fused", [False, True])
@pytest.mark.parametrize("single_adam", [False, True])
def test_split_keeps_optimizer_state(single_adam: bool, fused: bool) -> None:
    params, optimizers, state = _setup(single_adam=single_adam, fused=fused)
    before = _snapshot(params, optimizers)
    mask = torch.zeros(N, dtype=torch.bool)
    mask[[0, 7]] = True
    split(params, optimizers, state, mask, generator=torch.Generator().manual_seed(0))
    n_rest = N - 2
    for name, p in params.items():
        old_p, old_m, old_v = before[name]
        st = _adam_state(optimizers, p)
        assert torch.equal(p[:n_rest], old_p[~mask])
        assert torch.equal(st["exp_avg"][:n_rest], old_m[~mask]) and torch.equal(
            st["exp_avg_sq"][:n_rest], old_v[~mask]
        )
        assert (st["exp_avg"][n_rest:] == 0).all() and (st["exp_avg_sq"][n_rest:] == 0).all()
    parents = before["log_scales"][0][mask]
    torch.testing.assert_close(params["log_scales"][n_rest:].detach(), (parents - math.log(1.6)).repeat(2, 1))
    assert torch.equal(params["lang"][n_rest:], before["lang"][0][mask].repeat(2, 1))
    # Children lie within a few parent standard deviations of the parent centre.
    offsets = params["means"][n_rest:].detach() - before["means"][0][mask].repeat(2, 1)
    assert (offsets.norm(dim=-1) < 6 * parents.exp().max(dim=-1).values.repeat(2)).all()
    _check_in_step(params, optimizers, N + 2)


@pytest.mark.parametrize("fused", [False, True])
@pytest.mark.parametrize("single_adam", [False, True])
def test_remove_keeps_survivor_state(single_adam: bool, fused: bool) -> None:
    params, optimizers, state = _setup(single_adam=single_adam, fused=fused)
    before = _snapshot(params, optimizers)
    grad2d = state["grad2d"].clone()
    mask = torch.zeros(N, dtype=torch.bool)
    mask[[2, 3, 39]] = True
    remove(params, optimizers, state, mask)
    for name, p in params.items():
        old_p, old_m, old_v = before[name]
        st = _adam_state(optimizers, p)
        assert torch.equal(p, old_p[~mask])
        assert torch.equal(st["exp_avg"], old_m[~mask]) and torch.equal(st["exp_avg_sq"], old_v[~mask])
    assert torch.equal(state["grad2d"], grad2d[~mask])
    _check_in_step(params, optimizers, N - 3)


def test_zero_quaternion_splits_without_nan() -> None:
    params, optimizers, state = _setup()
    with torch.no_grad():
        params["quats"][4] = 0.0
    mask = torch.zeros(N, dtype=torch.bool)
    mask[4] = True
    split(params, optimizers, state, mask, generator=torch.Generator().manual_seed(0))
    assert all(torch.isfinite(p).all() for p in params.values())
    assert torch.isfinite(G.quats_normalized(params)).all()


# ---------------------------------------------------------------- DensifyStrategy


def _info(params: nn.ParameterDict, grad_px: torch.Tensor, radii: torch.Tensor | None = None) -> dict:
    """A render's info whose means2d carries the given pixel-space gradient [N, 2]."""
    means2d = torch.zeros(params["means"].shape[0], 2, requires_grad=True)
    means2d.grad = grad_px
    if radii is None:
        radii = torch.full((grad_px.shape[0],), 3, dtype=torch.int32)
    return {"means2d": means2d, "radii": radii, "width": 160, "height": 120}


def test_accumulates_ndc_gradient_of_visible_gaussians() -> None:
    params, optimizers, _ = _setup()
    strategy = DensifyStrategy()
    state = strategy.initialize_state(params)
    grad = torch.zeros(N, 2)
    grad[0] = torch.tensor([1e-4, 0.0])
    grad[1] = torch.tensor([0.0, 2e-4])
    radii = torch.full((N,), 2, dtype=torch.int32)
    radii[1] = 0
    strategy.step_post_backward(params, optimizers, state, 10, _info(params, grad, radii), 2.0)
    assert state["grad2d"][0].item() == pytest.approx(1e-4 * 80)
    assert state["grad2d"][1].item() == 0.0 and state["count"][1].item() == 0.0
    assert state["count"][0].item() == 1.0
    info = _info(params, grad)
    info["means2d"].grad = None  # nothing visible
    strategy.step_post_backward(params, optimizers, state, 11, info, 2.0)
    assert state["count"][0].item() == 1.0


def _high_grad(n: int, idx: list[int]) -> torch.Tensor:
    grad = torch.zeros(n, 2)
    grad[idx] = 1.0  # far above any threshold once scaled to NDC
    return grad


def test_refine_clones_small_and_splits_large() -> None:
    params, optimizers, _ = _setup()
    strategy = DensifyStrategy(prune_scale3d=None)
    state = strategy.initialize_state(params)
    extent = 2.0
    with torch.no_grad():
        params["log_scales"][:] = math.log(0.001)  # small: <= 0.01 x extent
        params["log_scales"][[3, 4]] = math.log(0.5)  # large
        params["opacity_logits"][:] = 2.0
    counts = strategy.step_post_backward(
        params, optimizers, state, 600, _info(params, _high_grad(N, [0, 1, 3, 4])), extent
    )
    assert counts == {"cloned": 2, "split": 2, "pruned": 0}
    _check_in_step(params, optimizers, N + 4)
    assert (state["grad2d"] == 0).all() and (state["count"] == 0).all()


def test_refine_skips_transparent_and_off_schedule() -> None:
    params, optimizers, _ = _setup()
    strategy = DensifyStrategy(prune_opacity=0.0, prune_scale3d=None)
    state = strategy.initialize_state(params)
    with torch.no_grad():
        params["opacity_logits"][:] = -1.0  # opacity 0.27 > 0.1
        params["opacity_logits"][0] = -3.0  # opacity 0.05: DNGaussian does not grow it
    info = _info(params, _high_grad(N, [0, 1]))
    assert (
        strategy.step_post_backward(params, optimizers, state, 550, info, 2.0)["cloned"] == 0
    )  # not a refine step
    assert (
        strategy.step_post_backward(params, optimizers, state, 500, info, 2.0)["cloned"] == 0
    )  # refines after 500
    counts = strategy.step_post_backward(params, optimizers, state, 600, info, 2.0)
    assert counts["cloned"] + counts["split"] == 1
    n = params["means"].shape[0]
    assert strategy.step_post_backward(
        params, optimizers, state, 6000, _info(params, _high_grad(n, [1])), 2.0
    ) == {"cloned": 0, "split": 0, "pruned": 0}


def test_prune_removes_exactly_the_transparent() -> None:
    params, optimizers, _ = _setup()
    strategy = DensifyStrategy()
    state = strategy.initialize_state(params)
    low = [2, 11, 25]
    with torch.no_grad():
        params["log_scales"][:] = math.log(0.01)
        params["opacity_logits"][:] = 0.0
        params["opacity_logits"][low] = -6.0  # opacity 0.0025 < 0.01
    keep_means = params["means"].detach()[[i for i in range(N) if i not in low]].clone()
    counts = strategy.step_post_backward(
        params, optimizers, state, 600, _info(params, torch.zeros(N, 2)), 10.0
    )
    assert counts == {"cloned": 0, "split": 0, "pruned": 3}
    assert torch.equal(params["means"].detach(), keep_means)
    _check_in_step(params, optimizers, N - 3)


def test_prune_removes_oversized() -> None:
    params, optimizers, _ = _setup()
    strategy = DensifyStrategy()
    state = strategy.initialize_state(params)
    with torch.no_grad():
        params["opacity_logits"][:] = 0.0
        params["log_scales"][:] = math.log(0.01)
        params["log_scales"][7] = math.log(0.5)  # > 0.1 x extent 2
    counts = strategy.step_post_backward(
        params, optimizers, state, 600, _info(params, torch.zeros(N, 2)), 2.0
    )
    assert counts["pruned"] == 1 and params["means"].shape[0] == N - 1


def test_growth_respects_max_gaussians() -> None:
    params, optimizers, _ = _setup()
    strategy = DensifyStrategy(max_gaussians=N + 2, prune_scale3d=None)
    state = strategy.initialize_state(params)
    with torch.no_grad():
        params["opacity_logits"][:] = 2.0
        params["log_scales"][:] = math.log(0.001)
    grad = torch.zeros(N, 2)
    grad[[0, 1, 2, 3], 0] = torch.tensor([1.0, 4.0, 3.0, 2.0])
    before = params["means"].detach().clone()
    counts = strategy.step_post_backward(params, optimizers, state, 600, _info(params, grad), 2.0)
    assert counts["cloned"] == 2 and params["means"].shape[0] == N + 2
    assert torch.equal(params["means"][N:].detach(), before[[1, 2]])  # the two largest gradients


def test_refinement_is_deterministic() -> None:
    def run() -> dict[str, torch.Tensor]:
        params, optimizers, _ = _setup(seed=5)
        strategy = DensifyStrategy(seed=3)
        state = strategy.initialize_state(params)
        with torch.no_grad():
            params["opacity_logits"][:] = 2.0
            params["log_scales"][::2] = math.log(0.5)
        grad = torch.rand(N, 2, generator=torch.Generator().manual_seed(0))
        strategy.step_post_backward(params, optimizers, state, 600, _info(params, grad), 20.0)
        return {k: v.detach().clone() for k, v in params.items()}

    a, b = run(), run()
    assert a["means"].shape[0] > N
    assert all(torch.equal(a[k], b[k]) for k in a)
