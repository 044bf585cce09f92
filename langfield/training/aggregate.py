"""Training-free language: each Gaussian's latents as the rendering-weighted mean of the training views'
mask latents (Occam's LGS, Cheng et al. 2024, and Dr.Splat aggregate features onto Gaussians this way),
and each Gaussian's registered entry, the training mask it carries the most weight on
(:func:`register_entries`, which the trainer runs at its end for the 3D selection).

A rendered channel is ``L(p) = sum_i w_i(p) c_i`` over the Gaussians i at pixel p, so the gradient of
``sum_p <L(p), t(p)>`` with respect to ``c_i`` is ``sum_p w_i(p) t(p)``: one forward and backward pass
of the rasterizer per view gives every Gaussian's weighted sum of the targets ``t``, and with the
targets' valid masks as ``t`` the sum of its weights. The rasterizer is the tested one (values and
gradients against the torch reference), so nothing here re-implements blending.

Example:
    >>> # field trained (or geometry-only), targets = langfield.training.targets.language_targets(scene, cfg)
    >>> # latents, weight = aggregate_latents(field, cameras, targets.latents, targets.valid)
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor, nn

from langfield.camera import Camera
from langfield.field import LANGUAGE_CHANNELS, LanguageField
from langfield.model import gaussians as G
from langfield.raster import rasterize

__all__ = ["MIN_REGISTER_WEIGHT", "aggregate_latents", "register_entries", "with_latents"]

# A Gaussian whose rendering weight on a level's masked training pixels sums to less than this (a
# thousandth of one pixel) is left unregistered at that level (-1).
MIN_REGISTER_WEIGHT = 1e-3
# Floats of one pass's [H, W, C] weights and [N, C] gradient in register_entries (64 MiB).
REGISTER_CHUNK_VALUES = 1 << 24


def with_latents(field: LanguageField, latents: Tensor) -> LanguageField:
    """A field sharing ``field``'s Gaussians, colour field, decoder and codebook whose language is the
    per-Gaussian ``latents`` [N, 3, 3] (the hash grid, if any, left out)."""
    splats = nn.ParameterDict(dict(field.splats))
    splats["lang"] = nn.Parameter(latents.reshape(len(latents), LANGUAGE_CHANNELS).detach().clone())
    meta = dict(field.meta)
    if field.meta.language:  # field.json then says what the latents are
        meta["language"] = {**field.meta.language, "features": "per-gaussian"}
    return LanguageField(splats, field.color, meta, None, field.decoder, field.codebook)


def aggregate_latents(
    field: LanguageField,
    cameras: Mapping[str, Camera],
    latents: Mapping[str, Tensor],
    valid: Mapping[str, Tensor],
    backend: str = "auto",
) -> tuple[Tensor, Tensor]:
    """Every Gaussian's rendering-weighted mean of the views' target latents, per level.

    Args:
        field: the Gaussians (their language, if any, is not used).
        cameras: view name -> camera.
        latents: view name -> [3, H, W, 3] latent of the mask at each pixel and level.
        valid: view name -> [3, H, W] bool, pixels with a mask at that level.

    Returns:
        ``(latents [N, 3, 3], weight [N, 3])``: the weighted mean latent, scaled to unit length (zero
        where a Gaussian has no weight at that level), and the summed weight behind it.
    """
    missing = [name for name in cameras if name not in latents or name not in valid]
    if missing:
        raise ValueError(f"aggregate_latents: no target latents for views {missing}")
    n = field.num_gaussians
    total = torch.zeros(n, LANGUAGE_CHANNELS)
    weight = torch.zeros(n, LANGUAGE_CHANNELS)
    if n == 0:
        return total.reshape(0, 3, 3), weight.reshape(0, 3, 3)[..., 0]
    probe = with_latents(field, torch.zeros(n, 3, 3))
    leaf = probe.splats["lang"]  # the only tensor that asks for a gradient
    for key in [k for k in probe.splats if k != "lang"]:  # the probe's own dict: the field keeps its own
        probe.splats[key] = nn.Parameter(probe.splats[key].detach(), requires_grad=False)
    for name, cam in cameras.items():
        mask = valid[name].float()  # [3, H, W]
        target = latents[name] * mask[..., None]  # [3, H, W, 3]
        ones = mask[..., None].expand_as(target)
        out = probe.render(cam, backend=backend, hard_depth=False)
        for goal, acc, last in ((target, total, False), (ones, weight, True)):
            (grad,) = torch.autograd.grad(
                out.latents, [leaf], grad_outputs=goal, retain_graph=not last, allow_unused=True
            )
            if grad is not None:  # None: no Gaussian reaches the view
                acc += grad
    weight = weight.reshape(n, 3, 3)[..., 0]
    mean = total.reshape(n, 3, 3)
    norm = mean.norm(dim=-1, keepdim=True)
    return torch.where(norm > 0, mean / norm.clamp_min(1e-12), torch.zeros_like(mean)), weight


def register_entries(
    field: LanguageField,
    cameras: Mapping[str, Camera],
    entries: Mapping[str, Tensor],
    sizes: list[int],
    backend: str = "auto",
    min_weight: float = MIN_REGISTER_WEIGHT,
    chunk_values: int = REGISTER_CHUNK_VALUES,
) -> Tensor:
    """Every Gaussian's entry at each level: the training mask it carries the most rendering weight on.

    The mode of the masks under a Gaussian, not their mean: a Gaussian on the edge between a lamp post
    and a wall is the lamp's or the wall's, where the mean of their latents can be nearest to a third
    concept (the same reason as the vote of :mod:`langfield.model.reading`). Per level, the weight a Gaussian
    carries on the pixels of entry e is the gradient of ``sum_p <render(p), [entry(p) = e]>`` with
    respect to a one-hot channel of that Gaussian (module docstring); entries go in chunks of channels.

    Args:
        field: the Gaussians (their language is not used).
        cameras: view name -> camera.
        entries: view name -> ``[L, H, W]`` long, the codebook entry of each pixel's mask at each level
            (-1: no mask).
        sizes: the number of entries of each level.
        min_weight: a Gaussian with less weight than this on a level's masked pixels gets -1 there.

    Returns:
        ``[N, L]`` long: per Gaussian and level the entry with the most weight (ties: the lower entry),
        or -1.
    """
    missing = [name for name in cameras if name not in entries]
    if missing:
        raise ValueError(f"register_entries: no mask entries for views {missing}")
    n, levels = field.num_gaussians, len(sizes)
    best_weight = torch.zeros(n, levels)
    best = torch.full((n, levels), -1, dtype=torch.long)
    total = torch.zeros(n, levels)
    splats = field.splats
    with torch.no_grad():
        geometry = (
            splats["means"].detach(),
            splats["quats"].detach(),
            G.scales(splats).detach(),
            G.opacities(splats).reshape(-1).detach(),
        )
    slots = [(level, e) for level in range(levels) for e in range(sizes[level])]
    pixels = max([c.width * c.height for c in cameras.values()] + [1])
    step = max(1, chunk_values // max(n, pixels))
    for start in range(0, len(slots) if n else 0, step):
        chunk = slots[start : start + step]
        weight = torch.zeros(n, len(chunk))
        for name, cam in cameras.items():
            goal = torch.stack([(entries[name][level] == e).float() for level, e in chunk], dim=-1)
            if not bool(goal.any()):
                continue
            probe = torch.zeros(n, len(chunk), requires_grad=True)
            image = rasterize(*geometry, probe, cam, backend=backend).image
            (grad,) = torch.autograd.grad(image, [probe], grad_outputs=goal)
            weight += grad
        for c, (level, e) in enumerate(chunk):
            better = weight[:, c] > best_weight[:, level]  # strictly: a tie keeps the lower entry
            best_weight[:, level] = torch.where(better, weight[:, c], best_weight[:, level])
            best[:, level] = torch.where(better, e, best[:, level])
            total[:, level] += weight[:, c]
    return torch.where(total >= min_weight, best, -1)
