"""Training-free language: each Gaussian's latents as the rendering-weighted mean of the training views'
mask latents (Occam's LGS, Cheng et al. 2024, and Dr.Splat aggregate features onto Gaussians this way).

A rendered channel is ``L(p) = sum_i w_i(p) c_i`` over the Gaussians i at pixel p, so the gradient of
``sum_p <L(p), t(p)>`` with respect to ``c_i`` is ``sum_p w_i(p) t(p)``: one forward and backward pass
of the rasterizer per view gives every Gaussian's weighted sum of the targets ``t``, and with the
targets' valid masks as ``t`` the sum of its weights. The rasterizer is the tested one (values and
gradients against the torch reference), so nothing here re-implements blending.

Example:
    >>> # field trained (or geometry-only), targets = langfield.training.trainer.language_targets(scene, cfg)
    >>> # latents, weight = aggregate_latents(field, cameras, targets.latents, targets.valid)
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor, nn

from langfield.camera import Camera
from langfield.field import LANGUAGE_CHANNELS, LanguageField

__all__ = ["aggregate_latents", "with_latents"]


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
