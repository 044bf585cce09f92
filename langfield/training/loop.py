"""The training loop: ``langfield.train(scene, TrainConfig(...))``.

One iteration: the strategy's pre-render edit (carving), the training view rendered
(:func:`render_step`: the position learning rate's decay, dropout, a random background), the named loss
terms (:func:`~langfield.training.losses.loss_terms`) summed and back-propagated, densification, the
optimizers' step, opacity decay and LOP (:class:`~langfield.training.strategy.TrainingStrategy`);
with ``co_train`` a second field takes each step beside the first (:mod:`langfield.training.cotrain`).
The run ends at its length, or earlier where its length was not forced and the fitting terms have
levelled off (:mod:`langfield.training.stopping`); field.json's ``stopped`` says which. Each
term's mean over every ``LOSS_LOG_EVERY`` iterations goes into field.json (``loss_terms``), and the
progress bar shows the largest. After the last iteration each Gaussian is registered to the training
masks it renders most (:func:`registered_entries`), timed apart from the loop.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from langfield.camera import Camera
from langfield.field import LanguageField
from langfield.io.scene import Scene
from langfield.kernels import reuse_freed_memory
from langfield.training.aggregate import register_entries
from langfield.training.config import TrainConfig
from langfield.training.cotrain import co_prune, coprune_due, coreg_due, coreg_terms
from langfield.training.losses import StepRender, loss_terms
from langfield.training.regularisers import drop_compensation, opacity_noise
from langfield.training.setup import Run, prepare
from langfield.training.stages import StageClock
from langfield.training.stopping import PlateauStop
from langfield.training.targets import LanguageTargets, backdrop_target
from querying.metrics import psnr

Callback = Callable[[int, float, LanguageField], None]

LOSS_LOG_EVERY = 50  # iterations per entry of field.json's loss_terms
SHOWN_TERMS = 3  # the largest terms in the progress bar


def train(
    scene: Scene,
    cfg: TrainConfig | None = None,
    *,
    progress: bool = True,
    callback: Callback | None = None,
    callback_every: int = 0,
    clock: StageClock | None = None,
) -> LanguageField:
    """Trains a field on ``scene``'s training views.

    Args:
        scene: a loaded scene with a "train" split.
        cfg: settings; ``TrainConfig()`` if None.
        progress: show a tqdm bar with the loss, its largest terms and the Gaussian count.
        callback: called as ``callback(step, train_seconds, field)`` every ``callback_every`` steps and
            at the end (with the iterations run); its own time is not counted as training time.
        clock: where given, the seconds of each stage of the iterations go there
            (:mod:`langfield.training.stages`).

    Returns:
        The trained :class:`LanguageField`; ``field.meta`` records timings, sizes and the loss terms.
    """
    reuse_freed_memory()
    run = prepare(scene, cfg or TrainConfig(), progress)
    if clock is not None:
        run.clock = clock
        if run.partner is not None:
            run.partner.clock = clock
    cfg, field, names = run.cfg, run.field, list(run.views)
    order: list[str] = []
    log = LossLog()
    train_seconds = 0.0
    stop = plateau_stop(run)
    steps_run = cfg.iterations
    bar = tqdm(total=cfg.iterations, disable=not progress, desc="train", dynamic_ncols=True, leave=False)
    for step in range(cfg.iterations):
        t0 = time.perf_counter()
        if not order:
            order = [names[i] for i in run.rng.permutation(len(names))]
        loss, terms, message = iterate(run, step, order.pop())
        if message:  # a LOP or co-pruning round ran: the set was edited
            bar.write(message)
            if stop is not None:
                stop.restart(step + 1)
        seconds = time.perf_counter() - t0
        train_seconds += seconds
        run.clock.add_iteration(seconds)
        log.add(step, loss, terms)
        bar.update(1)
        if stop is not None and (step + 1) % LOSS_LOG_EVERY == 0 and stop.levelled(log.closed()):
            steps_run = step + 1
            break
        if step % 10 == 0:
            bar.set_postfix(log.postfix(loss), gaussians=str(field.num_gaussians))
        if (
            callback is not None
            and callback_every
            and (step + 1) % callback_every == 0
            and step + 1 < cfg.iterations
        ):
            callback(step + 1, train_seconds, field)
    bar.close()
    _finish(run, train_seconds, log, steps_run, stop)
    if callback is not None:
        callback(steps_run, train_seconds, field)
    return field


def iterate(run: Run, step: int, name: str) -> tuple[torch.Tensor, dict[str, torch.Tensor], str | None]:
    """One iteration on training view ``name`` (of both fields when co-training): render, loss, backward,
    the strategy's edits and the optimizers' step. Returns the field's loss, its terms and a line on
    the pruning round that ran (LOP, co-pruning), if any."""
    runs = [run] if run.partner is None else [run, run.partner]
    stage = run.clock.stage
    with stage("strategy"):
        for r in runs:
            r.strategy.before_render(step)
    render = render_step(run, step, name)
    loss, terms = loss_terms(run, step, name, render)
    renders, joint = [render], loss
    if run.partner is not None:
        loss, terms, joint, partner_render = partner_step(run, step, name, render, loss, terms)
        renders.append(partner_render)
    with stage("backward"):
        joint.backward()
    with stage("strategy"):
        for r, rendered in zip(runs, renders, strict=True):
            r.strategy.after_backward(step, rendered.out, rendered.view.camera)
    with stage("optimizer"):
        for r in runs:
            for opt in r.optimizers.values():
                opt.step()
                opt.zero_grad(set_to_none=True)
    with stage("strategy"):
        message = run.strategy.after_optimizer_step(step)
        if run.partner is not None:
            run.partner.strategy.after_optimizer_step(step)
            if coprune_due(run, step + 1):
                run.co_pruned.append(co_prune(run, step + 1))
                line = "co-pruning at iteration {iteration}: removed {removed} (partner: {partner_removed})"
                line = line.format(**run.co_pruned[-1])
                message = line if message is None else f"{message}\n{line}"
    return loss, terms, message


def plateau_stop(run: Run) -> PlateauStop | None:
    """The run's early stop, or None where its length was forced or ``stop_plateau`` is 0."""
    if run.field.meta["training_length"]["forced"] or run.cfg.stop_plateau <= 0:
        return None
    return PlateauStop(run.cfg.stop_plateau, first_step=run.half_steps)


def _finish(run: Run, train_seconds: float, log: LossLog, steps: int, stop: PlateauStop | None) -> None:
    """Registers each Gaussian to its training masks and records the run in field.meta."""
    cfg, field = run.cfg, run.field
    if field.codebook is not None and run.targets is not None:
        # After the iterations and timed apart: train_seconds and iterations_per_second stay the loop's.
        t0 = time.perf_counter()
        field.entries = registered_entries(field, run.cameras, run.targets)
        seconds = round(time.perf_counter() - t0, 3)
        field.meta["language"] = dict(field.meta["language"], registered=True, register_seconds=seconds)
    reason = "forced" if field.meta["training_length"]["forced"] else "length"
    stopped = {"reason": reason, "iteration": steps, "length": cfg.iterations}
    if steps < cfg.iterations and stop is not None:
        stopped.update(reason="plateau", tolerance=stop.tolerance, terms=stop.evidence)
    field.meta.update(
        **run.strategy.record(),
        train_seconds=train_seconds,
        iterations=steps,
        stopped=stopped,
        iterations_per_second=steps / train_seconds if train_seconds > 0 else None,
        num_gaussians=field.num_gaussians,
        loss_terms=log.entries(),
    )
    if run.partner is not None:
        field.meta["co_training"] = {
            "partner_gaussians": run.partner.field.num_gaussians,
            "coprune_distance": run.coprune_distance,
            "co_pruned": run.co_pruned,
        }


def partner_step(
    run: Run, step: int, name: str, render: StepRender, loss: torch.Tensor, terms: dict[str, torch.Tensor]
) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor, StepRender]:
    """Co-training's share of a step (:mod:`langfield.training.cotrain`): the partner field renders the
    same training view with its own loss, and, where due, both fields render a virtual camera and each
    is compared with the other. Returns the main field's loss and terms (``coreg`` among them where it
    ran), the sum of both fields' losses to back-propagate, and the partner's render."""
    partner = run.partner
    other = render_step(partner, step, name)
    other_loss, _ = loss_terms(partner, step, name, other)
    if coreg_due(run, step):
        mine, theirs = coreg_terms(run, render.grid, other.grid)
        terms = {**terms, "coreg": mine}
        loss, other_loss = loss + mine, other_loss + theirs
    return loss, terms, loss + other_loss, other


def render_step(run: Run, step: int, name: str) -> StepRender:
    """Renders training view ``name`` at ``step`` (at half size in the coarse start), with dropout, opacity
    noise and a random background; sets the position learning rate for the step."""
    cfg, field = run.cfg, run.field
    view = run.half_views[name] if step < run.half_steps else run.views[name]
    # 3DGS's exponential decay of the position learning rate to 1 % over the run.
    frac = step / max(cfg.iterations - 1, 1)
    run.optimizers["means"].param_groups[0]["lr"] = run.means_lr0 * math.exp(math.log(0.01) * frac)
    keep = None
    if cfg.drop_gamma > 0:
        rate = cfg.drop_gamma * step / max(cfg.iterations, 1)
        keep = drop_compensation(field.num_gaussians, rate, run.drop_generator)
    if cfg.opacity_noise > 0:
        noise = opacity_noise(field.num_gaussians, cfg.opacity_noise, run.drop_generator)
        keep = noise if keep is None else keep * noise
    behind = None
    if cfg.random_background and run.scene.background is None:
        behind = torch.rand(3, generator=run.drop_generator)
    target = view.image
    if view.coverage is not None and behind is not None:  # a photo's backdrop shows the random colour
        target = backdrop_target(view.image, view.coverage, behind)
    with run.clock.stage("hash grids"):
        grid = field.grid_features()  # read once, shared by this step's renders
    with run.clock.stage("render"):
        out = field.render(
            view.camera,
            backend=cfg.backend,
            hard_depth=view.depth is not None,
            language=step >= run.language_steps,
            opacity_scale=keep,
            background=behind,
            grid=grid,
            depth_spread=cfg.lambda_spread > 0 and step >= cfg.spread_start * cfg.iterations,
        )
    return StepRender(view, out, target, keep, grid)


class LossLog:
    """Each loss term's mean over every ``LOSS_LOG_EVERY`` iterations (and over the last, shorter
    stretch): field.json's ``loss_terms``, a list of ``{"iterations": [first, last], "total": mean,
    "terms": {name: mean}, "steps": {name: iterations it ran}}``; a term that skipped an iteration
    counts 0 there, so the terms add up to the total."""

    def __init__(self) -> None:
        self._entries: list[dict[str, Any]] = []
        self._sums: dict[str, float] = {}
        self._counts: dict[str, int] = {}
        self._first = 0
        self._last: dict[str, float] = {}

    def add(self, step: int, loss: torch.Tensor, terms: dict[str, torch.Tensor]) -> None:
        values = {"total": float(loss.detach())}
        values.update((name, float(t.detach())) for name, t in terms.items())
        for name, value in values.items():
            self._sums[name] = self._sums.get(name, 0.0) + value
            self._counts[name] = self._counts.get(name, 0) + 1
        self._last = values
        if (step + 1) % LOSS_LOG_EVERY == 0:
            self._close(step)

    def _close(self, step: int) -> None:
        if not self._counts:
            return
        length = self._counts.pop("total")
        means = {name: self._sums[name] / length for name in self._sums}
        total = means.pop("total")
        self._entries.append(
            {"iterations": [self._first, step], "total": total, "terms": means, "steps": self._counts}
        )
        self._sums, self._counts, self._first = {}, {}, step + 1

    def closed(self) -> list[dict[str, Any]]:
        """The stretches closed so far (the one under way left out)."""
        return self._entries

    def entries(self) -> list[dict[str, Any]]:
        """Every stretch, the last one closed at the last iteration added."""
        if self._counts:
            self._close(self._first + self._counts["total"] - 1)
        return self._entries

    def postfix(self, loss: torch.Tensor) -> dict[str, str]:
        """The progress bar's loss and its ``SHOWN_TERMS`` largest terms at the last step."""
        terms = {k: v for k, v in self._last.items() if k != "total"}
        largest = sorted(terms, key=lambda k: -abs(terms[k]))[:SHOWN_TERMS]
        return {"loss": f"{float(loss.detach()):.4f}", **{k: f"{terms[k]:.4f}" for k in largest}}


def registered_entries(
    field: LanguageField, cameras: dict[str, Camera], targets: LanguageTargets
) -> torch.Tensor:
    """``[N, 3]`` each Gaussian's codebook entry per level: the training mask it carries the most
    rendering weight on (:func:`~langfield.training.aggregate.register_entries`), which the 3D
    selection reads. Rooms, 3 layouts x 3 seeds: 3D precision 0.625 -> 0.733, recall 0.854 -> 0.877
    against each Gaussian's own latent (docs/history/figures.md, "Registered entries")."""
    entries = {}
    for name in cameras:
        nearest = field.codebook_indices(targets.latents[name])
        entries[name] = torch.where(targets.valid[name], nearest, -1)
    sizes = [len(c) for c in field.codebook]
    return register_entries(field, cameras, entries, sizes, backend=field.meta.backend)


def evaluate_psnr(field: LanguageField, scene: Scene, split: str = "test") -> float | None:
    """Mean PSNR over a split's views, or None if it has none."""
    names = scene.names(split)
    if not names:
        return None
    values = []
    with torch.no_grad():
        for name in names:
            out = field.render(scene.camera(name))
            values.append(psnr(out.rgb, torch.from_numpy(scene.image(name))))
    return float(np.mean(values))


def summary_line(field: LanguageField, test_psnr: float | None) -> str:
    """The one-line summary printed at the end of training."""
    m = field.meta
    ips = m.iterations_per_second
    stop = m.get("stopped") or {}
    done = f"{m.iterations or 0} iterations"
    if stop.get("reason") == "plateau":
        done = f"{m.iterations} of {stop['length']} iterations (the fit levelled off)"
    parts = [
        f"trained {done} in {m.train_seconds or 0.0:.1f} s",
        f"{ips:.1f} it/s" if ips else "",
        f"{field.num_gaussians} Gaussians",
        f"backend {m.backend}",
        f"novel-view PSNR {test_psnr:.2f} dB" if test_psnr is not None else "no test views",
    ]
    return ", ".join(p for p in parts if p)
