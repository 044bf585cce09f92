"""A run's setup, before the first iteration: the run's length, where the Gaussians start, the field
built around them, its optimizers and every target (:func:`prepare` gives the :class:`Run` the loop
updates).
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from encoders.autoencoder import decoder_state, load_decoder
from encoders.protocols import LEVELS
from langfield.camera import Camera, camera_spacing
from langfield.field import LanguageField, color_field_spec
from langfield.io.layout import SceneError
from langfield.io.ply import read_points
from langfield.io.scene import Scene
from langfield.model import gaussians as G
from langfield.model.colour import ColorField
from langfield.model.hashgrid import HashGridConfig
from langfield.model.language import LANGUAGE_CHANNELS, N_LEVELS, LanguageHeads, mask_balance
from langfield.raster import resolve_backend
from langfield.training.config import TrainConfig, flag_of
from langfield.training.lad import LADTarget
from langfield.training.stages import StageClock
from langfield.training.start import SWEEP_PLANES, PlaneSweepConfig, StartPoints, start_points
from langfield.training.strategy import TrainingStrategy, field_extent, stereo_surfaces
from langfield.training.targets import (
    LanguageTargets,
    ViewTargets,
    check_inputs,
    depth_inputs,
    empty_space,
    language_targets,
    scene_bounds,
)

# The scene-sized run length (TrainConfig.iterations None). Each iteration fits one training view, so
# the length follows the views: ITERATIONS_PER_VIEW visits of each, within [MIN, MAX]. Three views give
# 1500 iterations, where the sparse-view defaults were chosen (docs/decisions.md).
ITERATIONS_PER_VIEW = 500


MIN_ITERATIONS = 1000


MAX_ITERATIONS = 6000  # SOVGaussian's and DNGaussian's length


def training_length(iterations: int | None, n_views: int) -> dict[str, Any]:
    """The run's length: ``iterations`` when given (forced), else sized by the ``n_views`` training
    views. Returns what field.json records: ``{"iterations", "forced", "rule"}``."""
    if iterations is not None:
        return {"iterations": int(iterations), "forced": True, "rule": flag_of("iterations")}
    n = min(max(ITERATIONS_PER_VIEW * max(n_views, 1), MIN_ITERATIONS), MAX_ITERATIONS)
    rule = f"{ITERATIONS_PER_VIEW} per training view x {n_views}, within [{MIN_ITERATIONS}, {MAX_ITERATIONS}]"
    return {"iterations": int(n), "forced": False, "rule": rule}


def init_method(scene: Scene, cfg: TrainConfig) -> str:
    """``cfg.init`` with "auto" resolved: "depth" when every training view has a depth prior and
    training uses it (``cfg.depth`` not False), else "dense"."""
    if cfg.init == "points" and scene.points_path is None:
        raise SceneError(
            f"{flag_of('init')} points: {scene.root} has no point cloud (transforms.json's ply_file_path, as "
            "langfield capture writes it)"
        )
    if cfg.init != "auto":
        return cfg.init
    names = scene.names("train")
    priors = cfg.depth is not False and all(scene.depth_path(n) is not None for n in names)
    return "depth" if priors and scene.depth_kind is not None else "dense"


def scene_start(scene: Scene, cfg: TrainConfig) -> StartPoints:
    """Where the Gaussians start (:func:`~langfield.training.start.start_points`, ``cfg.init``
    as :func:`init_method` resolves it)."""
    bounds = scene_bounds(scene, cfg)
    train_cams = scene.cameras("train")
    pixels = max(c.width * c.height for c in train_cams)  # of one image
    n = cfg.num_gaussians or G.num_gaussians_for_scene(bounds, pixels, len(train_cams))
    method = init_method(scene, cfg)
    return start_points(
        method,
        train_cams,
        [scene.image(c.name) for c in train_cams],
        bounds,
        n,
        seed=cfg.seed,
        fill=cfg.init_fill,
        priors=[scene.depth(c.name) for c in train_cams] if method == "depth" else None,
        depth_kind=scene.depth_kind,
        sweep=PlaneSweepConfig(views=cfg.init_sweep, tilts=SWEEP_PLANES[cfg.init_planes]),
        align=cfg.init_align,
        scene_points=read_points(scene.points_path) if method == "points" else None,
    )


def _language_parts(
    cfg: TrainConfig,
    targets: LanguageTargets | None,
    grid: HashGridConfig,
    center: np.ndarray,
    half_extent: float,
    splats: torch.nn.ParameterDict,
) -> tuple[LanguageHeads | None, Any, list[Tensor] | None, dict[str, Any] | None]:
    """The language part of a new field: its heads (a hash grid) or per-Gaussian latents (added to
    ``splats``), the frozen decoder, the codebook and what field.json records of them; all None
    without ``targets``."""
    if targets is None:
        return None, None, None, None
    language = codebook = None
    n = len(splats["means"])
    if cfg.language_features == "per-gaussian":
        splats["lang"] = torch.nn.Parameter(torch.zeros(n, LANGUAGE_CHANNELS))
    elif cfg.language_features == "hashgrid":
        lang_grid = grid
        if cfg.language_grid_scale != 1.0:
            finest = max(grid.base_resolution, round(grid.finest_resolution * cfg.language_grid_scale))
            levels = max(2, round(grid.n_levels * cfg.language_grid_scale**0.5))
            lang_grid = replace(grid, finest_resolution=finest, n_levels=levels)
        language = LanguageHeads(
            lang_grid,
            torch.tensor(center, dtype=torch.float32),
            float(half_extent),
            hidden=cfg.language_hidden,
        )
    else:
        raise ValueError(
            f"language_features must be 'hashgrid' or 'per-gaussian', got {cfg.language_features!r}"
        )
    decoder = load_decoder(decoder_state(targets.autoencoder), targets.config).requires_grad_(False)
    if cfg.language_decode != "continuous":
        codebook = [torch.nn.functional.normalize(p, dim=-1) for p in targets.prototypes]
    language_meta = {
        "features": cfg.language_features,
        "hidden": cfg.language_hidden,
        "grid": asdict(grid if language is None else language.grid.cfg),
        "levels": list(LEVELS[:N_LEVELS]),
        "autoencoder": asdict(targets.config),
        "autoencoder_stats": targets.stats,
        "codebook": None if codebook is None else [int(c.shape[0]) for c in codebook],
        "decode": cfg.language_decode,
        "registered": False,  # until training registers each Gaussian to its masks (train's end)
    }
    return language, decoder, codebook, language_meta


def build_field(
    scene: Scene,
    cfg: TrainConfig,
    targets: LanguageTargets | None = None,
    start: StartPoints | None = None,
) -> LanguageField:
    """An untrained field sized to ``scene``: Gaussians at ``start`` (default :func:`scene_start`),
    colour and language fields."""
    bounds = scene_bounds(scene, cfg)
    train_cams = scene.cameras("train")
    pixels = max(c.width * c.height for c in train_cams)  # of one image
    start = start or scene_start(scene, cfg)
    n = len(start.points)
    splats = G.gaussians_at(
        torch.from_numpy(start.points), lone_scale=0.01 * float(np.linalg.norm(bounds[1] - bounds[0]))
    )
    grid = HashGridConfig.for_scene(num_points=n, image_pixels=pixels)
    if cfg.log2_table_size is not None:
        grid = replace(grid, log2_table_size=cfg.log2_table_size)
    center = (bounds[0] + bounds[1]) / 2
    half_extent = (bounds[1] - bounds[0]).max() / 2 * 1.2  # scene extent / 2 x 1.2
    torch.manual_seed(cfg.seed)
    color = ColorField(
        grid,
        torch.tensor(center, dtype=torch.float32),
        float(half_extent),
        hidden=cfg.color_hidden,
        n_freqs=cfg.color_freqs,
    )
    language, decoder, codebook, language_meta = _language_parts(
        cfg, targets, grid, center, half_extent, splats
    )
    background = None if scene.background is None else [float(v) for v in scene.background]
    meta: dict[str, Any] = {
        "config": asdict(cfg),
        "backend": resolve_backend(cfg.backend),
        "bounds": bounds.tolist(),
        "scene": str(Path(scene.root).resolve()),
        "resolution": scene.resolution,
        "train_views": scene.names("train"),
        "test_views": scene.names("test"),
        "background": background,
        "num_gaussians_init": n,
        "init": start.stats,
        "color_field": color_field_spec(grid, center, half_extent, cfg.color_hidden, cfg.color_freqs),
        "language": language_meta,
    }
    # Text-encoder reference for queries (langfield.query): the scene's phrase table, if it has one.
    table = scene.text_embeddings_path
    meta["text_encoder"] = None if table is None else {"kind": "table", "path": str(Path(table).resolve())}
    return LanguageField(splats, color, meta, language, decoder, codebook)


def make_optimizers(
    field: LanguageField, extent: float, cfg: TrainConfig
) -> dict[str, torch.optim.Optimizer]:
    """One Adam per Gaussian parameter (so densification can edit each one) and one for the colour field.

    PyTorch's fused Adam: one pass over each parameter's elements, where the multi-tensor ("foreach")
    update makes a dozen whole-tensor passes (the same update up to rounding; docs/design.md,
    "Fused Adam").
    """
    lrs = dict(G.learning_rates(extent), lang=cfg.per_gaussian_language_lr)
    opts: dict[str, torch.optim.Optimizer] = {
        name: torch.optim.Adam([{"params": [p], "lr": lrs[name], "name": name}], eps=1e-15, fused=True)
        for name, p in field.splats.items()
    }
    opts["color"] = torch.optim.Adam(
        [
            {"params": list(field.color.grid_parameters()), "lr": cfg.grid_lr},
            {"params": list(field.color.mlp_parameters()), "lr": cfg.mlp_lr},
        ],
        eps=1e-15,
        fused=True,
    )
    if field.language is not None:
        opts["language"] = torch.optim.Adam(
            [
                {"params": list(field.language.grid_parameters()), "lr": cfg.grid_lr},
                {"params": list(field.language.mlp_parameters()), "lr": cfg.mlp_lr},
            ],
            eps=1e-15,
            fused=True,
        )
    return opts


@dataclass
class Run:
    """What one training run reads and updates, built from the scene once (every file read and checked)
    before the first iteration by :func:`prepare`."""

    cfg: TrainConfig  # with the run's length resolved
    scene: Scene
    field: LanguageField
    targets: LanguageTargets | None
    refiner: Any  # an OnnxImageRefiner, or None
    cameras: dict[str, Camera]
    views: dict[str, ViewTargets]
    half_views: dict[str, ViewTargets]  # the same at half size, for the first half_steps
    optimizers: dict[str, torch.optim.Optimizer]
    strategy: TrainingStrategy
    means_lr0: float
    half_steps: int
    language_steps: int
    rng: np.random.Generator
    drop_generator: torch.Generator
    # Each view's last rendered surface (camera, z-depth, covered), for the free-space term.
    rendered: dict[str, tuple[Camera, Tensor, Tensor]] = dataclasses.field(default_factory=dict)
    virtual_spacing: float = 0.0  # the virtual camera's shift from the cameras' spacing (scene units)
    clock: StageClock = dataclasses.field(default_factory=lambda: StageClock(enabled=False))
    # Co-training (cfg.co_train): the second field's run, and co-pruning's distance in scene units.
    partner: Run | None = None
    coprune_distance: float = 0.0
    co_pruned: list[dict[str, Any]] = dataclasses.field(default_factory=list)  # one record per round


def prepare(scene: Scene, cfg: TrainConfig, progress: bool = True) -> Run:
    """Checks the inputs, reads every target and builds the field, its optimizers and its strategy."""
    check_inputs(scene, cfg, progress=progress)
    length = training_length(cfg.iterations, len(scene.names("train")))
    cfg = replace(cfg, iterations=length["iterations"])
    refiner = None
    if cfg.refiner is not None:  # loaded before any work, so a bad model folder stops training at once
        from encoders.onnx_refiner import OnnxImageRefiner

        refiner = OnnxImageRefiner(cfg.refiner)
    train_names = scene.names("train")
    targets = language_targets(scene, cfg, progress=progress)
    depth_in = depth_inputs(scene, cfg, targets)
    start = scene_start(scene, cfg)
    field = build_field(scene, cfg, targets, start)
    field.meta["depth"] = None if depth_in is None else {"lad": cfg.lad, "kind": scene.depth_kind}
    field.meta["training_length"] = length
    optimizers = make_optimizers(field, field_extent(field), cfg)
    surfaces = stereo_surfaces(scene.cameras("train"), start) if cfg.carve_free_space else []
    strategy = TrainingStrategy(cfg, field, optimizers, targets, surfaces)
    cameras = {name: scene.camera(name) for name in train_names}
    stereo = {}
    if cfg.lambda_stereo > 0 and start.depths is not None:
        stereo = {name: torch.from_numpy(d) for name, d in zip(train_names, start.depths, strict=True)}
    coverage, source = empty_space(scene, cfg)
    field.meta["empty_space"] = {
        "source": source,
        "fraction": {name: round(float(1.0 - c.mean()), 4) for name, c in coverage.items()},
    }
    views = {
        name: ViewTargets(
            cameras[name],
            torch.from_numpy(scene.image(name)),
            coverage.get(name),
            None if targets is None else targets.latents[name],
            None if targets is None else mask_balance(targets.segments[name], cfg.language_balance),
            None if depth_in is None else LADTarget.from_view(*depth_in[name], scene.depth_kind),
            None if depth_in is None else depth_in[name],
            stereo.get(name),
        )
        for name in train_names
    }
    # The first half_resolution_until of the run renders every view at half its width and height.
    half_steps = round(cfg.half_resolution_until * cfg.iterations)
    run = Run(
        cfg=cfg,
        scene=scene,
        field=field,
        targets=targets,
        refiner=refiner,
        cameras=cameras,
        views=views,
        half_views={name: v.half_size() for name, v in views.items()} if half_steps > 0 else {},
        optimizers=optimizers,
        strategy=strategy,
        means_lr0=optimizers["means"].param_groups[0]["lr"],
        half_steps=half_steps,
        language_steps=round(cfg.language_start * cfg.iterations),
        rng=np.random.default_rng(cfg.seed),
        drop_generator=torch.Generator().manual_seed(cfg.seed),
        virtual_spacing=cfg.virtual_spacing * camera_spacing(np.stack([c.center for c in cameras.values()])),
    )
    if cfg.co_train:
        run.partner = partner_run(run, start, surfaces)
        run.coprune_distance = cfg.coprune_distance * median_depth(start.points, list(cameras.values()))
    return run


def partner_run(run: Run, start: StartPoints, surfaces: list) -> Run:
    """The second field of co-training (:mod:`langfield.training.cotrain`): the same start, views and
    targets, its own colour field, optimizers, strategy and random draws (seed + 1); no language, which
    co-training does not compare."""
    cfg = replace(run.cfg, seed=run.cfg.seed + 1, language=False)
    field = build_field(run.scene, cfg, None, start)
    field.meta.update(depth=run.field.meta["depth"], training_length=run.field.meta["training_length"])
    optimizers = make_optimizers(field, field_extent(field), cfg)
    strategy = TrainingStrategy(cfg, field, optimizers, None, surfaces, split_seed=cfg.seed)
    return replace(
        run,
        cfg=cfg,
        field=field,
        targets=None,
        optimizers=optimizers,
        strategy=strategy,
        means_lr0=optimizers["means"].param_groups[0]["lr"],
        rng=np.random.default_rng(cfg.seed),
        drop_generator=torch.Generator().manual_seed(cfg.seed),
        rendered={},
        partner=None,
        co_pruned=[],
    )


def median_depth(points: np.ndarray, cameras: list[Camera]) -> float:
    """The median z-depth of ``points`` [N, 3] in front of the cameras, over all of them (1 if none is)."""
    depth = np.concatenate([cam.project(points)[1] for cam in cameras]) if len(points) else np.zeros(0)
    depth = depth[depth > 0]
    return float(np.median(depth)) if depth.size else 1.0
