"""Every edit of the Gaussian set during training, in one object: :class:`TrainingStrategy`.

gsplat's habit: the strategy owns each change to the set of Gaussians together with the optimizer state
that follows it, and the loop calls it at fixed points of an iteration:

- :meth:`~TrainingStrategy.before_render`: space carving with the start's stereo (optional);
- :meth:`~TrainingStrategy.after_backward`: densification's clone / split / prune
  (:class:`~langfield.training.densify.DensifyStrategy`), which reads this step's gradients;
- :meth:`~TrainingStrategy.after_optimizer_step`: Binocular-guided 3DGS's opacity decay and, every
  ``lop_every`` iterations, a round of language-guided outlier pruning (:mod:`langfield.training.lop`),
  except where fewer than half an interval of the run would follow it (:meth:`lop_due`).

:meth:`~TrainingStrategy.record` is what field.json keeps of the edits.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from langfield.camera import Camera
from langfield.field import LanguageField, Render
from langfield.training.config import TrainConfig
from langfield.training.densify import DensifyStrategy, remove
from langfield.training.lop import lop_prune
from langfield.training.regularisers import free_space_violation
from langfield.training.start import StartPoints
from langfield.training.targets import LanguageTargets

Surface = tuple[Camera, Tensor, Tensor]  # camera, z-depth [H, W], resolved [H, W] bool


class TrainingStrategy:
    """The edits of one run's Gaussian set; ``optimizers`` follow every edit (Adam's moments kept in step).

    Args:
        cfg: the run's settings (``iterations`` resolved).
        field: the field whose ``splats`` are edited.
        optimizers: one per Gaussian parameter (:func:`~langfield.training.setup.make_optimizers`).
        targets: the language targets (LOP's prototypes); None without language, which turns LOP off.
        stereo: the start's stereo surfaces, for carving (:func:`stereo_surfaces`); empty: no carving.
        split_seed: seed of the samples that place split children (co-training's second field: its own).
    """

    def __init__(
        self,
        cfg: TrainConfig,
        field: LanguageField,
        optimizers: dict[str, torch.optim.Optimizer],
        targets: LanguageTargets | None,
        stereo: list[Surface],
        split_seed: int = 0,
    ) -> None:
        self.cfg, self.field, self.optimizers, self.targets, self.stereo = (
            cfg,
            field,
            optimizers,
            targets,
            stereo,
        )
        self.densify = DensifyStrategy(
            refine_start=cfg.refine_start,
            refine_every=cfg.refine_every,
            refine_stop=cfg.refine_stop if cfg.refine_stop is not None else cfg.iterations,  # DNGaussian
            grad_threshold=cfg.grad_threshold,
            prune_opacity=cfg.prune_opacity,
            max_gaussians=cfg.max_gaussians or 4 * field.num_gaussians,
            # DNGaussian keeps large Gaussians; 3DGS prunes them only after opacity resets.
            prune_scale3d=None,
            seed=split_seed,
        )
        self.state = self.densify.initialize_state(field.splats)
        self.extent = field_extent(field)
        self.use_lop = cfg.lop and targets is not None and cfg.lop_every > 0
        self.carved: list[dict[str, int]] = []
        self.lop_rounds: list[dict[str, Any]] = []

    def before_render(self, step: int) -> None:
        """Space carving every ``refine_every`` iterations, when the run carves."""
        if self.stereo and step % self.cfg.refine_every == 0:
            self.carved.append(self._carve(step))

    def after_backward(self, step: int, out: Render, cam: Camera) -> None:
        """Densification, from this step's screen-space gradients (before the optimizers step)."""
        if self.cfg.densify:
            info = {"means2d": out.means2d, "radii": out.radii, "width": cam.width, "height": cam.height}
            self.densify.step_post_backward(
                self.field.splats, self.optimizers, self.state, step, info, self.extent
            )

    def after_optimizer_step(self, step: int) -> str | None:
        """Opacity decay from ``opacity_decay_start``, and a LOP round every ``lop_every`` iterations;
        returns a line on the round, if one ran."""
        cfg = self.cfg
        if cfg.opacity_decay < 1.0 and step >= cfg.opacity_decay_start:
            with torch.no_grad():
                logits = self.field.splats["opacity_logits"]
                logits.copy_(torch.logit(torch.sigmoid(logits) * cfg.opacity_decay, eps=1e-6))
        if self.lop_due(step + 1):
            self.lop_rounds.append(self._prune_outliers(step + 1))
            last = self.lop_rounds[-1]
            return f"LOP at iteration {step + 1}: removed {last['removed']} of {last['before']} Gaussians"
        return None

    def lop_due(self, iteration: int) -> bool:
        """Whether a LOP round runs after ``iteration`` iterations: every ``lop_every``, where at least
        half an interval of the run follows. A round removes up to tau of the Gaussians and leaves holes
        that the training after it fills; at the run's last step nothing would (docs/decisions.md,
        ``lop_every``)."""
        every = self.cfg.lop_every
        return self.use_lop and iteration % every == 0 and 2 * (self.cfg.iterations - iteration) >= every

    def record(self) -> dict[str, Any]:
        """field.json's ``carved`` (None when the run does not carve) and ``lop`` (None without LOP)."""
        carved = {"removed": sum(c["removed"] for c in self.carved), "rounds": len(self.carved)}
        return {"carved": carved if self.stereo else None, "lop": self.lop_rounds if self.use_lop else None}

    def _carve(self, step: int) -> dict[str, int]:
        removed = carve_free_space(
            self.field.splats, self.stereo, self.optimizers, self.state, self.cfg.carve_tolerance
        )
        return {"iteration": step, "removed": removed}

    @torch.no_grad()
    def _prune_outliers(self, step: int) -> dict[str, Any]:
        """One LOP round (eq. 14-16): removes the language-group outliers."""
        cfg, field = self.cfg, self.field
        before = field.num_gaussians
        result = lop_prune(
            field.splats["means"].detach(),
            field.gaussian_latents(),
            self.targets.prototypes,
            gamma=cfg.lop_gamma,
            tau=cfg.lop_tau,
        )
        if result.num_pruned:
            remove(field.splats, self.optimizers, self.state, result.prune)
        return {
            "iteration": step,
            "before": before,
            "removed": result.num_pruned,
            "removed_by_level": list(result.pruned_by_level),
        }


@torch.no_grad()
def carve_free_space(
    splats: torch.nn.ParameterDict,
    stereo: list[Surface],
    optimizers: dict[str, torch.optim.Optimizer],
    state: dict[str, Any],
    tolerance: float,
) -> int:
    """Removes the Gaussians whose centre lies in front of a surface a training view's stereo resolved
    (in the free space its rays cross: space carving, Kutulakos and Seitz 2000); returns how many."""
    means = splats["means"].detach()
    free = torch.zeros(means.shape[0], dtype=torch.bool)
    for cam, depth, resolved in stereo:
        violation, _ = free_space_violation(means, cam, depth, resolved, tolerance)
        free |= violation > 0
    removed = int(free.sum())
    if removed == means.shape[0]:  # the stereo disagrees with every Gaussian: keep them rather than none
        return 0
    if removed:
        remove(splats, optimizers, state, free)
    return removed


def field_extent(field: LanguageField) -> float:
    """Half the diagonal of the field's bounds: densification's scene scale."""
    bounds = field.meta.bounds
    return float(np.linalg.norm(bounds[1] - bounds[0]) / 2)


def stereo_surfaces(cameras: list[Camera], start: StartPoints) -> list[Surface]:
    """The training views' stereo depth maps as (camera, z-depth [H, W], resolved [H, W] bool)."""
    if start.depths is None:
        return []
    surfaces = []
    for cam, depth in zip(cameras, start.depths, strict=True):
        resolved = np.isfinite(depth)
        surfaces.append((cam, torch.from_numpy(np.where(resolved, depth, 0.0)), torch.from_numpy(resolved)))
    return surfaces
