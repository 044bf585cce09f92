"""Co-training: two fields trained side by side from the same views, each the other's check (CoR-GS,
Zhang et al., ECCV 2024, arXiv:2405.12110).

Where the photos fix the scene, two fields trained on them agree; where they do not, the fields' own
random parts (here: the colour field's start, dropout's draws, the virtual cameras, the splits'
samples) make them differ. CoR-GS turns that difference into two edits:

- co-regularisation (:func:`coreg_terms`): in a virtual camera between the training cameras, each
  field's render is compared with the other's, held fixed (L1 + D-SSIM), so each is pulled to what
  both agree on;
- co-pruning (:func:`co_prune`): every ``coprune_every`` iterations each field loses the Gaussians
  with no Gaussian of the other within ``coprune_distance`` (times the start's median depth).

The first field is the run's result; the second (``run.partner``, built by
:func:`~langfield.training.setup.partner_run`) has no language and is dropped after the last
iteration. What was taken from CoR-GS's ``train.py`` (github.com/jiaw-z/CoR-GS): the two renders of
one pseudo camera each step, each loss against the other render detached, and the pruning of the
Gaussians without a correspondence within a distance (open3d), every 500 iterations after
densification begins. What differs: CoR-GS starts the pseudo views after 2,000 of 10,000 iterations
(DTU; 500 on LLFF); here they start with the full-size renders (a third of the run), and the
virtual camera is the one :func:`~langfield.training.virtual_views.sample_virtual_cameras` draws
between two training cameras.
CoR-GS's distance is 10 (DTU) or 5 (LLFF) of its scenes' units; here it is sized by the scene.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import open3d.core as o3c
import torch
from torch import Tensor

from langfield.field import GridFeatures
from langfield.training.densify import remove
from langfield.training.losses import color_loss
from langfield.training.virtual_views import sample_virtual_cameras

if TYPE_CHECKING:
    from langfield.training.setup import Run

__all__ = ["co_prune", "coprune_due", "coreg_due", "coreg_terms", "unmatched"]


def coreg_due(run: Run, step: int) -> bool:
    """Whether ``step`` compares the two fields: every step once the training views render at full
    size (CoR-GS compares every step from a fifth of its run on)."""
    return run.cfg.lambda_coreg > 0 and step >= run.half_steps


def coreg_terms(
    run: Run, grid: GridFeatures | None, partner_grid: GridFeatures | None
) -> tuple[Tensor, Tensor]:
    """Co-regularisation: both fields render one virtual camera at full size; returns ``(main's term,
    partner's term)``, each weighted by ``lambda_coreg``, each field's render against the other's
    detached. The loop calls it from the end of the half-size start on (:func:`coreg_due`)."""
    cfg, partner = run.cfg, run.partner
    cam = sample_virtual_cameras(list(run.cameras.values()), 1, run.rng)[0]
    with run.clock.stage("virtual view"):
        a = run.field.render(cam, backend=cfg.backend, language=False, grid=grid).rgb
        b = partner.field.render(cam, backend=cfg.backend, language=False, grid=partner_grid).rgb
        main = cfg.lambda_coreg * color_loss(a, b.detach(), cfg.lambda_dssim, cfg.backend)
        other = cfg.lambda_coreg * color_loss(b, a.detach(), cfg.lambda_dssim, cfg.backend)
    return main, other


def coprune_due(run: Run, iteration: int) -> bool:
    """Whether co-pruning runs after ``iteration`` iterations: every ``coprune_every`` once densification
    has begun, and not after the last."""
    every = run.cfg.coprune_every
    return (
        every > 0
        and iteration % every == 0
        and iteration > run.cfg.refine_start
        and iteration < run.cfg.iterations
    )


@torch.no_grad()
def co_prune(run: Run, iteration: int) -> dict[str, Any]:
    """One co-pruning round: each field loses its Gaussians that :func:`unmatched` finds, both decided
    before either is edited; a field that would lose all its Gaussians keeps them."""
    fields = (run, run.partner)
    means = [r.field.splats["means"].detach() for r in fields]
    drops = [
        unmatched(means[0], means[1], run.coprune_distance),
        unmatched(means[1], means[0], run.coprune_distance),
    ]
    removed = []
    for r, drop in zip(fields, drops, strict=True):
        count = int(drop.sum())
        if count == len(drop):
            count = 0
        elif count:
            remove(r.field.splats, r.optimizers, r.strategy.state, drop)
        removed.append(count)
    return {"iteration": iteration, "removed": removed[0], "partner_removed": removed[1]}


def unmatched(points: Tensor, others: Tensor, distance: float) -> Tensor:
    """``[N]`` bool: the ``points`` [N, 3] with none of ``others`` [M, 3] within ``distance`` (open3d's
    nearest-neighbour search; all of them when ``others`` is empty)."""
    if len(points) == 0 or len(others) == 0:
        return torch.ones(len(points), dtype=torch.bool)
    search = o3c.nns.NearestNeighborSearch(o3c.Tensor(np.ascontiguousarray(others.numpy(), dtype=np.float32)))
    search.knn_index()
    _, sq = search.knn_search(o3c.Tensor(np.ascontiguousarray(points.numpy(), dtype=np.float32)), 1)
    return torch.from_numpy(sq.numpy().reshape(-1) > distance * distance)
