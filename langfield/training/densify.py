"""Adaptive density control of the Gaussians (3DGS, with DNGaussian's sparse-view settings), gsplat style.

:class:`DensifyStrategy` accumulates each Gaussian's screen-space position gradient and, every
``refine_every`` steps, clones small Gaussians with a large gradient, splits large ones in two and prunes
transparent or oversized ones. The operations :func:`duplicate`, :func:`split` and :func:`remove` edit
every ``[N, ...]`` entry of the parameter dict alike (including ones added later, e.g. ``"lang"``) and keep
the optimizers in step: the new ``nn.Parameter`` replaces the old one in the dict and in the optimizer's
param group, Adam's moments follow the surviving rows and start at zero for new ones.

Optimizer layout: ``optimizers`` maps names to optimizers, one Adam per Gaussian parameter as in gsplat.
The helpers find each parameter by identity in every param group of every optimizer given, so a single
Adam with one group per key (passed under any name) and optimizers for other modules work too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from langfield.model.gaussians import normalize_quats
from langfield.raster.projection import quat_to_rotmat

Optimizers = dict[str, torch.optim.Optimizer]
# (name, old tensor) -> new tensor, applied to parameters, optimizer moments and strategy state.
_EditFn = Callable[[str, Tensor], Tensor]


@dataclass
class DensifyStrategy:
    """Clone / split / prune schedule (3DGS's adaptive density control, DNGaussian's sparse-view values).

    Defaults are DNGaussian's LLFF 3-view script (``scripts/run_llff.sh``, ``scene/gaussian_model.py``):
    refine every 100 steps after step 500 until the end of the 6000-step run, gradient threshold 0.0013
    (3DGS: 0.0002; DNGaussian's DTU script: 0.001), percent_dense 0.01, prune opacity below 0.01, densify
    only Gaussians more opaque than 0.1 (``split_opacity_thresh``), split into 2 with scales / 1.6, and
    no opacity reset.

    Attributes:
        refine_start: first refinement after this step (refines at steps > refine_start).
        refine_every: refinement interval in steps.
        refine_stop: no statistics and no refinement from this step on.
        grad_threshold: mean screen-space gradient norm (in NDC units, as 3DGS) above which a Gaussian grows.
        prune_opacity: Gaussians less opaque than this are removed.
        percent_dense: a Gaussian whose largest scale is <= percent_dense x scene extent is cloned,
            a larger one is split.
        grow_opacity_min: only Gaussians more opaque than this are cloned or split (DNGaussian).
        prune_scale3d: Gaussians whose largest scale exceeds this x scene extent are removed
            (3DGS / gsplat: 0.1); None keeps them, as DNGaussian does.
        split_scale_factor: children of a split get the parent's scales divided by this (3DGS: 0.8 x 2).
        max_gaussians: cap on the count; when growth would pass it, the Gaussians with the largest
            gradients grow first. A CPU budget, not from a paper.
        seed: seed of the samples that place split children.
    """

    refine_start: int = 500
    refine_every: int = 100
    refine_stop: int = 6000
    grad_threshold: float = 0.0013
    prune_opacity: float = 0.01
    percent_dense: float = 0.01
    grow_opacity_min: float = 0.1
    prune_scale3d: float | None = 0.1
    split_scale_factor: float = 1.6
    max_gaussians: int = 60_000
    seed: int = 0

    def initialize_state(self, params: nn.ParameterDict) -> dict[str, Any]:
        """Fresh running statistics for ``params``.

        Returns:
            {"grad2d": [N] summed gradient norms, "count": [N] times visible, "generator": torch.Generator
            for the split samples}.
        """
        n = params["means"].shape[0]
        device = params["means"].device
        return {
            "grad2d": torch.zeros(n, device=device),
            "count": torch.zeros(n, device=device),
            "generator": torch.Generator(device=device).manual_seed(self.seed),
        }

    def step_pre_backward(
        self, params: nn.ParameterDict, optimizers: Optimizers, state: dict[str, Any], step: int, info: dict
    ) -> None:
        """Ask autograd to keep ``info["means2d"].grad`` (needed when means2d is not a leaf)."""
        means2d = info.get("means2d")
        if means2d is not None and means2d.requires_grad and step < self.refine_stop:
            means2d.retain_grad()

    def step_post_backward(
        self,
        params: nn.ParameterDict,
        optimizers: Optimizers,
        state: dict[str, Any],
        step: int,
        info: dict,
        scene_extent: float,
    ) -> dict[str, int]:
        """Accumulate gradient statistics and, on refinement steps, clone, split and prune.

        Call after ``loss.backward()`` and before ``optimizer.step()``.

        Args:
            params: the Gaussians; edited in place on refinement steps.
            optimizers: optimizers holding the parameters (see the module docstring).
            state: from :meth:`initialize_state`; edited in place.
            step: current step, from 0.
            info: "means2d" [N, 2] or [C, N, 2] projected centres in pixels whose ``.grad`` is filled (a
                missing tensor or grad counts as not visible), "radii" [N] or [C, N] pixel radii (0 =
                culled; a trailing per-axis dim [..., 2] is accepted), "width", "height" in pixels.
            scene_extent: scene radius in world units.

        Returns:
            {"cloned", "split", "pruned"} numbers of Gaussians (zeros on other steps).
        """
        counts = {"cloned": 0, "split": 0, "pruned": 0}
        if step >= self.refine_stop:
            return counts
        self._update_state(params, state, info)
        if step > self.refine_start and step % self.refine_every == 0:
            counts = self._refine(params, optimizers, state, scene_extent)
            state["grad2d"].zero_()
            state["count"].zero_()
        return counts

    def _update_state(self, params: nn.ParameterDict, state: dict[str, Any], info: dict) -> None:
        """Add each visible Gaussian's screen-space gradient norm, normalised to NDC units as gsplat does."""
        means2d = info.get("means2d")
        grad = None if means2d is None else means2d.grad
        if grad is None:
            return
        n = params["means"].shape[0]
        if grad.shape[-2:] != (n, 2):
            raise ValueError(f"means2d grad must be [N, 2] or [C, N, 2] with N={n}, got {tuple(grad.shape)}")
        grad = grad.detach().reshape(-1, n, 2)  # [C, N, 2]
        n_cams = grad.shape[0]
        # Pixel gradients times half the image size are NDC gradients (3DGS's threshold units); with C
        # cameras the loss is a mean over them, so each camera's gradient is scaled back by C (gsplat).
        scale = grad.new_tensor([info["width"] / 2.0, info["height"] / 2.0]) * n_cams
        norms = (grad * scale).norm(dim=-1)  # [C, N]
        radii = torch.as_tensor(info["radii"], device=grad.device).reshape(n_cams, n, -1)
        visible = (radii > 0).all(dim=-1)  # [C, N]
        state["grad2d"] += torch.where(visible, norms, torch.zeros_like(norms)).sum(dim=0)
        state["count"] += visible.sum(dim=0).to(state["count"].dtype)

    @torch.no_grad()
    def _refine(
        self, params: nn.ParameterDict, optimizers: Optimizers, state: dict[str, Any], scene_extent: float
    ) -> dict[str, int]:
        """Clone, split and prune once; returns the counts."""
        n = params["means"].shape[0]
        grads = state["grad2d"] / state["count"].clamp_min(1.0)
        max_scale = params["log_scales"].exp().max(dim=-1).values
        opacity = torch.sigmoid(params["opacity_logits"]).reshape(n)
        grow = (grads > self.grad_threshold) & (opacity > self.grow_opacity_min)
        grow = _within_budget(grow, grads, self.max_gaussians - n)
        is_small = max_scale <= self.percent_dense * scene_extent
        is_dupli, is_split = grow & is_small, grow & ~is_small

        n_dupli = int(is_dupli.sum())
        if n_dupli:
            duplicate(params, optimizers, state, is_dupli)
        # Clones go to the end and are never split in the same round.
        is_split = torch.cat([is_split, is_split.new_zeros(n_dupli)])
        n_split = int(is_split.sum())
        if n_split:
            split(
                params,
                optimizers,
                state,
                is_split,
                generator=state.get("generator"),
                scale_factor=self.split_scale_factor,
            )

        opacity = torch.sigmoid(params["opacity_logits"]).reshape(-1)
        is_prune = opacity < self.prune_opacity
        if self.prune_scale3d is not None:
            is_prune |= params["log_scales"].exp().max(dim=-1).values > self.prune_scale3d * scene_extent
        n_prune = int(is_prune.sum())
        if n_prune:
            remove(params, optimizers, state, is_prune)
        return {"cloned": n_dupli, "split": n_split, "pruned": n_prune}


def _within_budget(grow: Tensor, grads: Tensor, budget: int) -> Tensor:
    """Keep at most ``budget`` of the ``grow`` mask [N], those with the largest gradients (stable order)."""
    n_grow = int(grow.sum())
    if n_grow <= max(budget, 0):
        return grow
    keep = torch.zeros_like(grow)
    if budget > 0:
        candidates = grow.nonzero().squeeze(1)
        order = torch.argsort(grads[candidates], descending=True, stable=True)
        keep[candidates[order[:budget]]] = True
    return keep


@torch.no_grad()
def duplicate(params: nn.ParameterDict, optimizers: Optimizers, state: dict[str, Any], mask: Tensor) -> None:
    """Clone the Gaussians in ``mask``: copies are appended; their optimizer moments and statistics are 0.

    Args:
        params: per-Gaussian parameters [N, ...]; replaced by [N + M, ...].
        optimizers: optimizers holding them.
        state: strategy state; [N] tensors become [N + M].
        mask: [N] bool, M of them True.
    """
    sel = mask.nonzero().squeeze(1)

    def param_fn(name: str, p: Tensor) -> Tensor:
        return torch.cat([p, p[sel]])

    def zeros_fn(name: str, v: Tensor) -> Tensor:
        return torch.cat([v, v.new_zeros(len(sel), *v.shape[1:])])

    _edit(params, optimizers, state, param_fn, zeros_fn)


@torch.no_grad()
def split(
    params: nn.ParameterDict,
    optimizers: Optimizers,
    state: dict[str, Any],
    mask: Tensor,
    *,
    generator: torch.Generator | None = None,
    scale_factor: float = 1.6,
) -> None:
    """Replace each Gaussian in ``mask`` by 2 children sampled from it (3DGS's densify_and_split).

    Children's means are drawn from the parent's Gaussian, their scales are the parent's / scale_factor,
    every other entry is copied. Children are appended after the untouched Gaussians; their optimizer
    moments and statistics are 0. A zero quaternion counts as the identity rotation (no NaN).

    Args:
        params: per-Gaussian parameters [N, ...] with "means", "log_scales", "quats"; replaced by
            [N + M, ...].
        optimizers: optimizers holding them.
        state: strategy state; [N] tensors become [N + M].
        mask: [N] bool, M of them True.
        generator: random generator of the samples (for reproducible runs).
        scale_factor: divisor of the children's scales.
    """
    sel = mask.nonzero().squeeze(1)
    rest = (~mask).nonzero().squeeze(1)
    scales = params["log_scales"][sel].exp()  # [M, 3]
    rotmats = quat_to_rotmat(normalize_quats(params["quats"][sel]))  # [M, 3, 3]
    noise = torch.randn(2, len(sel), 3, generator=generator, device=scales.device, dtype=scales.dtype)
    offsets = torch.einsum("nij,nj,bnj->bni", rotmats, scales, noise)  # [2, M, 3] in world coordinates

    def param_fn(name: str, p: Tensor) -> Tensor:
        if name == "means":
            children = (p[sel] + offsets).reshape(-1, 3)
        elif name == "log_scales":
            children = torch.log(scales / scale_factor).repeat(2, 1)
        else:
            children = p[sel].repeat(2, *[1] * (p.dim() - 1))
        return torch.cat([p[rest], children])

    def zeros_fn(name: str, v: Tensor) -> Tensor:
        return torch.cat([v[rest], v.new_zeros(2 * len(sel), *v.shape[1:])])

    _edit(params, optimizers, state, param_fn, zeros_fn)


@torch.no_grad()
def remove(params: nn.ParameterDict, optimizers: Optimizers, state: dict[str, Any], mask: Tensor) -> None:
    """Delete the Gaussians in ``mask`` from the parameters, the optimizer moments and the statistics.

    Args:
        params: per-Gaussian parameters [N, ...]; replaced by [N - M, ...].
        optimizers: optimizers holding them.
        state: strategy state; [N] tensors become [N - M].
        mask: [N] bool, M of them True.
    """
    keep = ~mask

    def keep_fn(name: str, v: Tensor) -> Tensor:
        return v[keep]

    _edit(params, optimizers, state, keep_fn, keep_fn)


def _edit(
    params: nn.ParameterDict,
    optimizers: Optimizers,
    state: dict[str, Any],
    param_fn: _EditFn,
    optimizer_fn: _EditFn,
) -> None:
    """Apply a change of the Gaussian count to every parameter, its optimizer moments, and the state.

    ``param_fn`` maps each parameter's data to the new data; ``optimizer_fn`` maps each per-Gaussian
    optimizer tensor (Adam's exp_avg, exp_avg_sq, ...) and each per-Gaussian state tensor alike.
    """
    n = params["means"].shape[0]
    opts = list({id(o): o for o in optimizers.values()}.values())
    for name in list(params.keys()):
        old = params[name]
        if old.shape[0] != n:
            raise ValueError(f"params[{name!r}] has {old.shape[0]} rows, params['means'] has {n}")
        new = nn.Parameter(param_fn(name, old.detach()), requires_grad=old.requires_grad)
        for opt in opts:
            _swap_in_optimizer(opt, old, new, lambda v, name=name: optimizer_fn(name, v))
        params[name] = new
    for key, value in state.items():
        if isinstance(value, Tensor) and value.dim() > 0 and value.shape[0] == n:
            state[key] = optimizer_fn(key, value)


def _swap_in_optimizer(
    opt: torch.optim.Optimizer, old: nn.Parameter, new: nn.Parameter, fn: Callable[[Tensor], Tensor]
) -> None:
    """Put ``new`` where ``old`` is in ``opt``'s param groups and carry its state over through ``fn``."""
    for group in opt.param_groups:
        for i, p in enumerate(group["params"]):
            if p is not old:
                continue
            group["params"][i] = new
            st = opt.state.pop(old, None)
            if st is not None:
                for key, value in st.items():
                    # Per-Gaussian moments have the parameter's shape; scalars such as Adam's step stay.
                    if isinstance(value, Tensor) and value.shape == old.shape:
                        st[key] = fn(value)
                opt.state[new] = st
