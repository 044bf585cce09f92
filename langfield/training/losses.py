"""The loss terms of one training step, by name: :func:`loss_terms`.

L = L_C + L_LF + L_D + L_O (the paper) plus the sparse-view terms: L_C = (1 - lambda) L1 + lambda D-SSIM
(3DGS), L_LF the language loss on the rendered latents (geometry detached), L_D the depth distillation
of :mod:`langfield.training.lad` (LAD, eq. 6-11) on the hard and soft rendered depth, L_O an L1 penalty
on the opacities (3DGS-MCMC). Each term is returned weighted and under its name, so that the loop can
record and show it; a term that is off or does not apply this step is absent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from langfield.camera import Camera
from langfield.field import GridFeatures, LanguageField, Render
from langfield.model import gaussians as G
from langfield.model.language import language_loss
from langfield.training.config import TrainConfig
from langfield.training.lad import depth_loss
from langfield.training.regularisers import (
    anisotropy_loss,
    depth_smoothness,
    depth_spread_loss,
    free_space_violation,
    orbit_camera,
    reprojection_warp,
    shifted_camera,
    virtual_shift,
    virtual_view_warp,
    z_depth,
)
from langfield.training.ssim import ssim_map
from langfield.training.targets import ViewTargets, area_resize
from langfield.training.virtual_views import sample_virtual_cameras

if TYPE_CHECKING:
    from langfield.training.setup import Run


@dataclass(frozen=True)
class StepRender:
    """One step's render of its training view and what it is compared with.

    Attributes:
        view: the view's targets at the size rendered.
        out: the render.
        target: [H, W, 3] the photo (with this step's background behind its empty space).
        keep: [N] dropout's per-Gaussian opacity scale, or None.
        grid: the hash-grid features read once for this step's renders.
    """

    view: ViewTargets
    out: Render
    target: Tensor
    keep: Tensor | None
    grid: GridFeatures | None


class Terms(dict):
    """Weighted loss terms by name, and their ``total``, summed as each term is added."""

    total: Tensor | None = None

    def add(self, name: str, value: Tensor) -> None:
        self[name] = value
        self.total = value if self.total is None else self.total + value


def loss_terms(run: Run, step: int, name: str, render: StepRender) -> tuple[Tensor, dict[str, Tensor]]:
    """The loss of training view ``name`` at ``step``: ``(total, weighted terms by name)``; ``color``
    is always among them.

    The terms on the rendered image are summed as they are made, the others likewise apart, then the two
    sums are added: the order of a float sum, and of autograd's accumulation, is part of what makes a
    run repeat bit for bit.
    """
    cfg, field, view, out = run.cfg, run.field, render.view, render.out
    cam = view.camera
    stage = run.clock.stage
    image = Terms()
    with stage("colour loss"):
        image.add("color", color_loss(out.rgb, render.target, cfg.lambda_dssim, cfg.backend))
        if view.coverage is not None and cfg.lambda_empty > 0:
            image.add("empty", cfg.lambda_empty * (out.alpha * (1.0 - view.coverage)).mean())
    virtual_step = step >= cfg.virtual_start and (step - cfg.virtual_start) % cfg.virtual_every == 0
    if cfg.lambda_virtual > 0 and virtual_step:
        with stage("virtual view"):
            virtual = virtual_view_loss(
                field, cam, render.target, out, render.keep, cfg, run.rng, render.grid, run.virtual_spacing
            )
            image.add("virtual", cfg.lambda_virtual * virtual)
    pseudo_step = step >= cfg.refiner_start and (step - cfg.refiner_start) % cfg.refiner_every == 0
    if run.refiner is not None and pseudo_step:
        cameras = list(run.cameras.values())
        with stage("virtual view"):
            pseudo = pseudo_view_loss(field, run.refiner, cameras, cfg, run.rng, render.grid)
            image.add("pseudo", cfg.lambda_refiner * pseudo)
    with stage("other terms"):
        others = _geometry_and_language_terms(run, name, view, out)
    total = image.total if others.total is None else image.total + others.total
    return total, {**image, **others}


def _geometry_and_language_terms(run: Run, name: str, view: ViewTargets, out: Render) -> Terms:
    """The step's terms on the rendered depth, the scales, the latents and the opacities."""
    cfg, field, cam = run.cfg, run.field, view.camera
    terms = Terms()
    use_stereo = cfg.lambda_stereo > 0 and view.stereo is not None
    if cfg.lambda_visibility > 0 or cfg.lambda_smooth > 0 or cfg.lambda_crossview > 0 or use_stereo:
        covered = out.alpha.detach() > 0.5
        depth_z = z_depth(out.depth / out.alpha.clamp_min(1e-4), cam)
    if cfg.lambda_visibility > 0:
        violation = visibility_loss(depth_z, covered, cam, name, run.rendered, cfg.visibility_tolerance)
        terms.add("visibility", cfg.lambda_visibility * violation)
        run.rendered[name] = (cam, depth_z.detach(), covered)
    if cfg.lambda_crossview > 0:
        others = [(v.camera, v.image) for other, v in run.views.items() if other != name]
        crossview = cross_view_loss(
            depth_z, covered, view.image, cam, others, cfg.lambda_dssim, backend=cfg.backend
        )
        terms.add("crossview", cfg.lambda_crossview * crossview)
    if use_stereo:
        terms.add("stereo", cfg.lambda_stereo * stereo_depth_loss(depth_z, covered, view.stereo))
    if cfg.lambda_smooth > 0:
        terms.add("smooth", cfg.lambda_smooth * depth_smoothness(depth_z, view.image, covered))
    if cfg.lambda_spread > 0 and out.depth_spread is not None:
        terms.add("spread", cfg.lambda_spread * depth_spread_loss(out.depth_spread, out.depth, out.alpha))
    if cfg.lambda_anisotropy > 0:
        terms.add(
            "anisotropy",
            cfg.lambda_anisotropy * anisotropy_loss(field.splats["log_scales"], cfg.anisotropy_ratio),
        )
    if view.latents is not None and out.latents is not None:
        terms.add(
            "language", cfg.lambda_language * language_loss(out.latents, view.latents, view.language_weight)
        )
    if view.depth is not None:
        lad = depth_loss(view.depth, out.depth_hard, out.depth, cfg.lambda_sa, lad=cfg.lad)
        terms.add("depth", cfg.lambda_depth * lad)
    if cfg.lambda_opacity > 0:
        terms.add("opacity", cfg.lambda_opacity * G.opacities(field.splats).mean())
    return terms


def color_loss(rendered: Tensor, target: Tensor, lambda_dssim: float = 0.2, backend: str = "auto") -> Tensor:
    """L_C = (1 - lambda) L1 + lambda (1 - SSIM) on images [H, W, 3] (SSIM by ``backend``, see
    :func:`~langfield.training.ssim.ssim_map`)."""
    l1 = (rendered - target).abs().mean()
    d_ssim = 1.0 - ssim_map(rendered, target, backend=backend).mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * d_ssim


def virtual_view_loss(
    field: LanguageField,
    cam: Camera,
    image: Tensor,
    out: Render,
    keep: Tensor | None,
    cfg: TrainConfig,
    rng: np.random.Generator,
    grid: GridFeatures | None = None,
    spacing: float = 0.0,
) -> Tensor:
    """Binocular consistency (Han et al. 2024): the training view's depth must warp a sideways-shifted
    render onto the training image. L1 + D-SSIM over the pixels the field covers and the warp reaches.
    The shift is ``cfg.virtual_baseline`` times the median rendered depth, or ``spacing`` (scene units)
    where that is longer (:func:`langfield.training.regularisers.virtual_shift`).
    With ``virtual_motion="orbit"`` the virtual camera turns about the median depth instead ("both":
    one or the other, at random); then, or with ``virtual_occlusion``, the pixels the virtual view sees
    occluded are left out."""
    covered = out.alpha.detach() > 0.5
    depth = z_depth(out.depth / out.alpha.clamp_min(1e-4), cam)
    right, up = virtual_shift(
        depth.detach(),
        covered,
        cfg.virtual_baseline,
        rng,
        any_direction=cfg.virtual_directions == "any",
        spacing=spacing,
    )
    if right == 0.0 and up == 0.0:
        return out.rgb.sum() * 0.0
    if cfg.virtual_resolution < 1.0:
        cam = cam.scaled(1.0 / cfg.virtual_resolution)
        depth, image, cover = area_resize([depth[..., None], image, covered[..., None].float()], cam)
        depth, covered = depth[..., 0], cover[..., 0] > 0.5
    if not bool(covered.any()):
        return out.rgb.sum() * 0.0
    orbit = cfg.virtual_motion == "orbit" or (cfg.virtual_motion == "both" and rng.random() < 0.5)
    if orbit:
        virtual = orbit_camera(cam, right, up, float(depth.detach()[covered].median()))
    else:
        virtual = shifted_camera(cam, right, up)
    seen = field.render(virtual, backend=cfg.backend, language=False, opacity_scale=keep, grid=grid)
    if orbit or cfg.virtual_occlusion:
        seen_depth = z_depth(seen.depth / seen.alpha.clamp_min(1e-4), virtual)
        warped, valid = reprojection_warp(seen.rgb, depth, cam, virtual, seen_depth)
    else:
        warped, valid = virtual_view_warp(seen.rgb, depth, cam, right, up)
    mask = (valid & covered).float()
    if float(mask.sum()) < 1:
        return out.rgb.sum() * 0.0
    l1 = ((warped - image).abs().mean(-1) * mask).sum() / mask.sum()
    d_ssim = ((1.0 - ssim_map(warped, image, backend=cfg.backend)[0].mean(0)) * mask).sum() / mask.sum()
    return (1.0 - cfg.lambda_dssim) * l1 + cfg.lambda_dssim * d_ssim


def cross_view_loss(
    depth_z: Tensor,
    covered: Tensor,
    image: Tensor,
    cam: Camera,
    others: list[tuple[Camera, Tensor]],
    lambda_dssim: float = 0.2,
    min_std: float = 0.02,
    backend: str = "auto",
) -> Tensor:
    """Multi-view photometric consistency between the training photos: this view's rendered z-depth
    [H, W] warps each other photo onto ``image`` [H, W, 3] (:func:`reprojection_warp`), and where the
    field covers a pixel the warp must give the photo (L1 + D-SSIM). Per pixel the better of the other
    photos counts (Monodepth2's minimum reprojection error, Godard et al., ICCV 2019): a surface one
    photo sees occluded or outside its frame is then judged by the one that sees it. The photos are
    fixed targets, so the gradient reaches the depth alone, through the image gradients where the warp
    lands; unlike the virtual-view term, nothing the field renders elsewhere can agree with a wrong depth.

    Args:
        others: ``(camera, photo [h, w, 3])`` of the other training views, at any size.
        min_std: pixels whose 7 x 7 neighbourhood in ``image`` varies less (standard deviation of the
            grey level) are left out: a white table or a saturated highlight matches its like at any
            depth, and there the term would only move the surface at random.
        backend: SSIM's (:func:`~langfield.training.ssim.ssim_map`).
    """
    best = None
    for other_cam, other_image in others:
        warped, valid = reprojection_warp(other_image, depth_z, cam, other_cam)
        error = (1.0 - lambda_dssim) * (warped - image).abs().mean(-1)
        error = error + lambda_dssim * (1.0 - ssim_map(warped, image, backend=backend)[0].mean(0))
        error = torch.where(valid, error, torch.full_like(error, math.inf))
        best = error if best is None else torch.minimum(best, error)
    if best is None:
        return depth_z.sum() * 0.0
    mask = covered & torch.isfinite(best) & textured(image, min_std)
    if not bool(mask.any()):
        return depth_z.sum() * 0.0
    return torch.where(mask, best, torch.zeros_like(best)).sum() / mask.sum()


def stereo_depth_loss(depth_z: Tensor, covered: Tensor, stereo: Tensor) -> Tensor:
    """Mean relative error ``|z - s| / s`` of the rendered z-depth [H, W] against the start's plane-sweep
    depth ``stereo`` [H, W] (NaN where unresolved), over the pixels the sweep resolved and the field
    covers. The sweep keeps a depth only where its window matched, was textured and another view's
    depth agreed (:func:`~langfield.training.start.stereo.stereo_depths`): metric depth the photos
    themselves fix, as DS-NeRF (Deng et al., CVPR 2022) supervises with SfM's sparse depth."""
    resolved = torch.isfinite(stereo) & covered
    if not bool(resolved.any()):
        return depth_z.sum() * 0.0
    target = torch.where(resolved, stereo, torch.ones_like(stereo))
    error = (depth_z - target).abs() / target
    return torch.where(resolved, error, torch.zeros_like(error)).sum() / resolved.sum()


def textured(image: Tensor, min_std: float, size: int = 7) -> Tensor:
    """[H, W] bool: where the grey level of ``image`` [H, W, 3] varies by more than ``min_std`` (standard
    deviation) over a ``size`` x ``size`` neighbourhood."""
    grey = image.detach().mean(-1)[None, None]

    def mean(x: Tensor) -> Tensor:
        return torch.nn.functional.avg_pool2d(x, size, 1, size // 2, count_include_pad=False)

    variance = (mean(grey * grey) - mean(grey) ** 2).clamp_min(0.0)
    return variance[0, 0].sqrt() > min_std


def visibility_loss(
    depth_z: Tensor,
    seen: Tensor,
    cam: Camera,
    name: str,
    rendered: dict[str, tuple[Camera, Tensor, Tensor]],
    tolerance: float,
) -> Tensor:
    """Mean free-space violation (:func:`langfield.training.regularisers.free_space_violation`) of this view's
    rendered surface [H, W] in every other training view's last render."""
    points = cam.unproject(depth_z)[seen]
    total = depth_z.sum() * 0.0
    count = 0
    for other, (other_cam, other_depth, other_seen) in rendered.items():
        if other == name:
            continue
        violation, valid = free_space_violation(points, other_cam, other_depth, other_seen, tolerance)
        total = total + violation.sum()
        count += int(valid.sum())
    return total / max(count, 1)


def pseudo_view_loss(
    field: LanguageField,
    refiner: Any,
    cameras: list[Camera],
    cfg: TrainConfig,
    rng: np.random.Generator,
    grid: GridFeatures | None = None,
) -> Tensor:
    """Renders a virtual camera, lets the refiner clean the render, and returns the confidence-weighted
    L1 to the cleaned image (a fixed target: no gradient flows through the refiner)."""
    cam = sample_virtual_cameras(cameras, 1, rng)[0]
    out = field.render(cam, backend=cfg.backend, language=False, grid=grid)
    cleaned, confidence = refiner.refine(out.rgb.detach().clamp(0, 1).numpy())
    target = torch.from_numpy(np.ascontiguousarray(cleaned))
    weight = torch.from_numpy(np.ascontiguousarray(confidence))[..., None]
    return (weight * (out.rgb - target).abs()).mean()
