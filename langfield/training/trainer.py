"""Training a field from a scene's training views: ``langfield.train(scene, TrainConfig(...))``.

The loss is L = L_C + L_LF + L_D + L_O: L_C = 0.8 L1 + 0.2 D-SSIM with kornia's SSIM, L_LF the
language loss on the rendered latents (geometry detached), L_D the depth distillation of
:mod:`langfield.training.lad` (LAD, eq. 6-11) on the hard and soft rendered depth, and L_O an L1 penalty
on the opacities (3DGS-MCMC) that lets densification prune the Gaussians the images do not need. Gaussians are
initialised at random inside the scene bounds (COLMAP often fails on three views), sized to the scene,
densified by :class:`langfield.training.strategy.DensifyStrategy`, and pruned by language-guided outlier
pruning (:mod:`langfield.training.lop`, eq. 14-16) every ``lop_every`` iterations.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import math
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from encoders.autoencoder import (
    AutoencoderConfig,
    LanguageAutoencoder,
    decoder_state,
    load_decoder,
    train_autoencoder,
)
from encoders.cache import read_feature_cache
from encoders.protocols import LEVELS
from langfield.camera import Camera
from langfield.field import GridFeatures, LanguageField, Render, color_field_spec
from langfield.io.field_meta import LANGUAGE_DECODES, LANGUAGE_FEATURES
from langfield.io.layout import SceneError
from langfield.io.ply import read_points
from langfield.io.scene import Scene
from langfield.kernels import BACKEND_ALIASES, BACKENDS
from langfield.model import gaussians as G
from langfield.model.colour import ColorField
from langfield.model.hashgrid import HashGridConfig
from langfield.model.language import (
    LANGUAGE_CHANNELS,
    N_LEVELS,
    LanguageHeads,
    language_loss,
    mask_balance,
)
from langfield.raster import resolve_backend
from langfield.training.aggregate import register_entries
from langfield.training.initialisation import INIT_ALIGNS, INIT_METHODS, StartPoints, start_points
from langfield.training.lad import LAMBDA_SA, LADTarget, depth_loss
from langfield.training.lop import LOP_GAMMA, LOP_INTERVAL, LOP_TAU, lop_prune
from langfield.training.regularisers import (
    anisotropy_loss,
    backproject,
    dark_backdrop,
    depth_smoothness,
    depth_spread_loss,
    drop_compensation,
    free_space_violation,
    shifted_camera,
    virtual_shift,
    virtual_view_warp,
    z_depth,
)
from langfield.training.strategy import DensifyStrategy, remove
from langfield.training.virtual_views import sample_virtual_cameras
from querying.metrics import psnr, ssim_map


@dataclass(frozen=True)
class TrainConfig:
    """Training settings; defaults from the paper, DNGaussian and 3DGS (each setting's comment).

    ``None`` means "sized to the scene": the initial Gaussian count and the hash-table size follow
    the scene's bounds and training pixels; the values used are recorded in field.json.
    """

    iterations: int | None = None  # None: sized by the scene (training_length); N forces N
    seed: int = 0
    # Where the Gaussians start (langfield.training.initialisation): plane-sweep stereo on the training views,
    # COLMAP's sparse SIFT points, the depth prior aligned to the stereo depths, or random in the bounds.
    # "auto": "depth" when every training view has a depth prior that training uses, else "dense"
    # (init_method). Three views' plane sweep resolves 5-7 % of a room's pixels, a third of them off by
    # more than 2 %, and the start is topped up around them; the aligned prior gives every pixel a point.
    # Rooms of 3 layouts x 3 seeds: docs/figures.md, "A start from the depth prior".
    init: Literal["auto", "dense", "sfm", "depth", "points", "random"] = "auto"
    # The depth start's alignment: "views" refines each view's prior line, fitted to its own stereo, so
    # that the views agree with one another (langfield.training.prior_alignment); "smooth" then corrects
    # each view's prior by a smooth field from photo-consistency in a narrow band and the other views;
    # "fused" then moves each pixel to the mean of the views that agree on it, so that a surface starts
    # as one layer, not one per view (langfield.training.prior_correction); "anchors" keeps the per-view
    # fits. Rooms of 3 layouts x 3 seeds: docs/figures.md, "Aligning the priors to one another",
    # "Correcting the priors" and "One layer per surface".
    init_align: Literal["fused", "smooth", "views", "anchors"] = "fused"
    init_fill: float = 0.1  # random points added, as a fraction of the photo points
    backend: str = "auto"
    num_gaussians: int | None = None
    max_gaussians: int | None = None
    log2_table_size: int | None = None
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    lambda_dssim: float = 0.2
    densify: bool = True
    refine_start: int = 500
    refine_every: int = 100
    refine_stop: int | None = None  # None: refine until the last iteration (DNGaussian)
    grad_threshold: float = 0.0013
    prune_opacity: float = 0.01
    color_hidden: int = 64
    color_freqs: int = 4
    grid_lr: float = 5e-3
    mlp_lr: float = 5e-4
    language: bool | None = None  # None: when every training view has a feature cache
    language_features: Literal["hashgrid", "per-gaussian"] = "hashgrid"
    lambda_language: float = 1.0
    # MLP_L's hidden width; the paper gives none. 32 (against 64): the MLP maps 12 grid features to a
    # 3-d latent; its cost is ~5 ms per step less on 2 cores, novel-view mIoU no lower.
    language_hidden: int = 32
    # The language grid's finest resolution as a fraction of the colour grid's (levels halved): language
    # is constant over a part, and fine levels only hash-collide across objects; 1.0 gives the colour
    # layout. Built-in scene, 1500 it.: novel-view mIoU 0.153 -> 0.170 (seed 0) with 0.25 and hidden 32,
    # and the language field's cost per iteration drops by about half.
    language_grid_scale: float = 0.25
    per_gaussian_language_lr: float = 2.5e-3  # LangSplat's language_feature_lr
    # L_LF from this fraction of the run on: before it the latents are neither rendered nor trained (their
    # channels, the language grid and MLP_L are ~20 % of an iteration at 160x120). The language pass is
    # detached from the geometry, so colour and geometry train the same either way; the default skips
    # the half-size start, where the Gaussians move most. Built-in scene, 3 seeds: mIoU 0.531 against
    # 0.530 from iteration 0, training 10 % shorter (docs/figures.md).
    language_start: float = 0.33
    autoencoder_iterations: int = 300
    # L_LF's pixel weight: the area of the pixel's mask to this power, negated (langfield.model.language.
    # mask_balance); 0: every pixel alike, the paper's. Under it a mug of 18 pixels is not rendered even
    # in the views it is trained on. Rooms of 3 layouts x 3 seeds, 0.25 against 0: novel-view mIoU
    # 0.801 -> 0.817 (9 of 9 higher), 3D recall 0.836 -> 0.854, precision 0.629 -> 0.625; 0.5 gives
    # mIoU 0.821 at precision 0.612, 0.75 0.804 and 0.573 (docs/figures.md, "Small masks in L_LF").
    language_balance: float = 0.25
    # Weight of the autoencoder's spread term (encoders.autoencoder.spread_loss); 0: eq. 2 alone, the
    # paper's. Eq. 2 packs a room's concepts 8-13 degrees apart on the 3-d sphere, and a rendered latent
    # 10 degrees off decodes to a neighbour. Rooms of 3 layouts x 2 seeds: novel-view mIoU 0.585 -> 0.631
    # (5 of 6 higher), 3D recall 0.73 -> 0.81, PSNR unchanged (docs/figures.md, "Language in novel views").
    autoencoder_spread: float = 0.01
    # How a rendered latent is read: "codebook" as the nearest of the training masks' latents at its
    # level (LanguageField.decode_levels), "continuous" decoded as it is (the paper). Rendered latents
    # land ~12 degrees from their targets, about the spacing of a room's concepts on the 3-d sphere
    # (docs/figures.md, "Language in novel views"). "vote" reads the nearest entry only where the
    # Gaussians of its concept carry part of the pixel's weight, else the entry with the most weight
    # (langfield.model.reading): rooms 3x3, mIoU 0.817 -> 0.861 (docs/figures.md, "Reading by vote"). The
    # reading changes no training step: the field records it, and it can be changed after training.
    language_decode: str = "vote"
    depth: bool | None = None  # None: when every training view has a depth prior (depths/)
    lad: bool = True  # False: the plain global depth term only (the --no-lad ablation)
    # L_D's normalised terms are scale-invariant: their gradient grows as 1 / std of the render, which
    # is tiny at the random start (~1 % of the depth), and at weight 1 swamped L_C (PSNR 22 -> 11 dB on
    # the built-in scene). 0.01 against 0.001, rooms of 3 layouts x 3 seeds: PSNR 25.55 -> 26.00 dB,
    # mIoU 0.728 -> 0.747 (8 of 9 higher), 3D recall 0.77 -> 0.83 (docs/figures.md). Only scenes with
    # depth priors (depths/) train with it.
    lambda_depth: float = 0.01
    lambda_sa: float = LAMBDA_SA
    # L1 on the opacities, lambda * mean(sigmoid(o)) (3DGS-MCMC, Kheradmand et al. 2024, weight 0.01): a
    # Gaussian the images do not need fades below prune_opacity and densification removes it. Three
    # views leave most of the random start in free space, and those floaters carry wrong colours and
    # latents into new views; docs/figures.md has the sweep behind the default.
    lambda_opacity: float = 0.03
    # Sparse-view regularisers (langfield.training.regularisers); 0 turns each off. Defaults chosen by
    # 1000-iteration runs on LLFF fern, DTU scan37 and the built-in scene (docs/figures.md,
    # "Sparse-view geometry").
    drop_gamma: float = 0.2  # Gaussian dropout: rate gamma t / T (DropGaussian's 0.2)
    lambda_virtual: float = 1.0  # virtual-view consistency weight (Binocular-guided 3DGS)
    # Its sideways shift, as a fraction of the median rendered depth: DTU's wide baselines gain most
    # up to 0.2, fern loses 0.4 dB there; 0.1 between.
    virtual_baseline: float = 0.1
    # "horizontal": the shift to the left or right (a stereo pair, as the paper); "any": any direction
    # in the image plane, so vertical parallax is checked too. "any" at 1000 iterations: DTU scan37
    # 16.20 -> 17.50 dB masked, built-in scene 25.49 -> 26.06, fern 21.52 -> 21.45 (docs/figures.md).
    virtual_directions: Literal["horizontal", "any"] = "any"
    virtual_start: int = 0  # first iteration of the virtual-view term
    # The term on every n-th iteration (it renders a second view). Every second iteration fits fern
    # better (22.21 dB against 21.90 every iteration, 1500 iterations) at the built-in scene's cost
    # (mIoU 0.514 against 0.542): docs/figures.md, "Coarse start".
    virtual_every: int = 2
    # Coarse to fine (DashGaussian, Chen et al. CVPR 2025, schedules the resolution by the images'
    # spectra; here one step): this fraction of the run renders the views at half their width and height.
    # It buys time, not quality: fern 816 -> 626 s at 22.2 dB.
    half_resolution_until: float = 0.33
    # The term's image size as a fraction of the training view's: the shifted view is rendered, warped
    # and compared at this size (depth, image and coverage area-averaged down to it).
    virtual_resolution: float = 1.0
    # A random background colour each iteration (scenes without alpha): a surface as dark as the black
    # background would otherwise be left transparent, and the opacity penalty even asks for that. Where
    # a photo shows a black backdrop the target there is that colour too. RGBA scenes keep their white:
    # a random one there cost the built-in scene 2.1 dB and mIoU 0.05 (1500 iterations).
    random_background: bool = True
    # Empty space the photos show (langfield.training.regularisers.dark_backdrop): a black backdrop is
    # found by DNGaussian's DTU rule (no effect on photos without one: LLFF fern), and with the alpha of RGBA
    # images the rendered alpha there is penalised, lambda_empty * mean(alpha * (1 - coverage)).
    dark_backdrop: bool = True
    lambda_empty: float = 1.0
    # Binocular-guided 3DGS's opacity decay: every opacity times this factor each iteration after
    # refine_start (the paper's 0.995; 1: off); Gaussians the images keep asking for recover, the rest
    # fade. At 1000 iterations: DTU scan37 18.09 -> 18.55 dB masked, lego 15.61 -> 16.16, fern 21.45 -> 21.51.
    opacity_decay: float = 0.995
    # Free space between views: each training view's rendered surface, projected into the other
    # training views, may not lie in front of what they render (their last render, held fixed).
    lambda_visibility: float = 0.0
    visibility_tolerance: float = 0.02
    # Space carving with the start's stereo depth: every refine_every iterations, Gaussians whose centre
    # lies in front of a surface some training view's plane sweep resolved (by more than the tolerance,
    # relative) are removed: that view's rays pass through them.
    carve_free_space: bool = False
    carve_tolerance: float = 0.03
    lambda_smooth: float = 0.0  # edge-aware smoothness of the rendered depth
    # Depth spread (langfield.training.regularisers.depth_spread_loss): the blending weights of a pixel
    # gathered at one depth, Mip-NeRF 360's distortion loss in squared form between the Gaussians' centres.
    lambda_spread: float = 0.0
    spread_start: float = 0.33  # the term from this fraction of the run on
    lambda_anisotropy: float = 0.0  # penalty on max/min scale above anisotropy_ratio
    anisotropy_ratio: float = 10.0
    # Pseudo views: an ONNX image refiner folder (encoders.onnx_refiner) cleans renders of virtual cameras
    # between and around the training ones (langfield.training.virtual_views), used as
    # confidence-weighted targets.
    refiner: str | None = None
    lambda_refiner: float = 0.5
    refiner_every: int = 10
    refiner_start: int = 500
    lop: bool = True  # language-guided outlier pruning; needs the language field
    lop_every: int = LOP_INTERVAL
    lop_gamma: int = LOP_GAMMA
    lop_tau: float = LOP_TAU

    def __post_init__(self) -> None:
        check_config(self)


# The `langfield train` flag of each setting that has one, named in the messages of check_config (and
# checked against the parser by the tests).
CONFIG_FLAGS = {
    "iterations": "--iterations",
    "seed": "--seed",
    "backend": "--backend",
    "num_gaussians": "--num-gaussians",
    "init": "--init",
    "init_align": "--init-align",
    "bounds": "--bounds",
    "language_features": "--language-features",
    "language_grid_scale": "--language-grid-scale",
    "language_start": "--language-start",
    "autoencoder_spread": "--autoencoder-spread",
    "language_balance": "--language-balance",
    "language_decode": "--language-decode",
    "lambda_opacity": "--lambda-opacity",
    "drop_gamma": "--drop-gamma",
    "lambda_virtual": "--lambda-virtual",
    "virtual_baseline": "--virtual-baseline",
    "virtual_directions": "--virtual-directions",
    "virtual_every": "--virtual-every",
    "virtual_resolution": "--virtual-resolution",
    "half_resolution_until": "--half-resolution-until",
    "random_background": "--random-background",
    "dark_backdrop": "--dark-backdrop",
    "lambda_empty": "--lambda-empty",
    "opacity_decay": "--opacity-decay",
    "lambda_visibility": "--lambda-visibility",
    "carve_free_space": "--carve-free-space",
    "lambda_smooth": "--lambda-smooth",
    "lambda_spread": "--lambda-spread",
    "lambda_anisotropy": "--lambda-anisotropy",
    "refiner": "--refiner",
}


def check_config(cfg: TrainConfig) -> None:
    """Rejects a setting no training can use, before any work: one ValueError naming the setting
    (and its ``langfield train`` flag)."""
    c = _ConfigCheck(cfg)
    _check_start_and_model(c, cfg)
    _check_densification_and_language(c, cfg)
    _check_regularisers(c, cfg)


class _ConfigCheck:
    """The kinds of value a TrainConfig setting can be; each failure names the setting and its flag."""

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg

    def fail(self, name: str, expected: str) -> None:
        flag = f" ({CONFIG_FLAGS[name]})" if name in CONFIG_FLAGS else ""
        raise ValueError(f"TrainConfig.{name}{flag} must be {expected}, got {getattr(self.cfg, name)!r}")

    def whole(self, name: str, low: int, optional: bool = False) -> None:
        value = getattr(self.cfg, name)
        if optional and value is None:
            return
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
            self.fail(
                name, f"a whole number >= {low}" + (" (or None: sized to the scene)" if optional else "")
            )

    def number(self, name: str, low: float, high: float = math.inf, open_low: bool = False) -> None:
        value = getattr(self.cfg, name)
        ok = isinstance(value, (int, float, np.number)) and not isinstance(value, bool)
        ok = ok and math.isfinite(value)
        if not ok or value < low or (open_low and value == low) or value > high:
            lower = f"> {low}" if open_low else f">= {low}"
            self.fail(name, f"a finite number {lower}" + ("" if high == math.inf else f" and <= {high}"))


def _check_start_and_model(c: _ConfigCheck, cfg: TrainConfig) -> None:
    c.whole("iterations", 0, optional=True)
    c.whole("seed", 0)
    if cfg.backend not in ("auto", *BACKENDS, *BACKEND_ALIASES):
        c.fail("backend", "'auto', 'torch' or 'numba'")
    if cfg.init not in ("auto", *INIT_METHODS):
        c.fail("init", " or ".join(repr(m) for m in ("auto", *INIT_METHODS)))
    if cfg.init_align not in INIT_ALIGNS:
        c.fail("init_align", " or ".join(repr(m) for m in INIT_ALIGNS))
    c.number("init_fill", 0.0, 10.0)
    c.whole("num_gaussians", 1, optional=True)
    c.whole("max_gaussians", 1, optional=True)
    if cfg.log2_table_size is not None and not (
        isinstance(cfg.log2_table_size, int) and 8 <= cfg.log2_table_size <= 30
    ):
        c.fail("log2_table_size", "a whole number in [8, 30] (or None: sized to the scene)")
    if cfg.bounds is not None:
        try:
            box = np.asarray(cfg.bounds, dtype=np.float64)
        except (TypeError, ValueError):
            box = np.zeros(0)
        if box.shape != (2, 3) or not np.isfinite(box).all() or (box[1] <= box[0]).any():
            c.fail("bounds", "((xmin, ymin, zmin), (xmax, ymax, zmax)) with max > min")


def _check_densification_and_language(c: _ConfigCheck, cfg: TrainConfig) -> None:
    c.whole("refine_start", 0)
    c.whole("refine_every", 1)
    c.whole("refine_stop", 0, optional=True)
    c.number("grad_threshold", 0.0, open_low=True)
    c.number("prune_opacity", 0.0, 1.0)
    c.whole("color_hidden", 1)
    c.whole("color_freqs", 0)
    for name in ("grid_lr", "mlp_lr", "per_gaussian_language_lr"):
        c.number(name, 0.0, open_low=True)
    if cfg.language_features not in LANGUAGE_FEATURES:
        c.fail("language_features", " or ".join(map(repr, LANGUAGE_FEATURES)))
    c.whole("language_hidden", 1)
    c.number("language_grid_scale", 0.0, 1.0, open_low=True)
    c.whole("autoencoder_iterations", 1)
    c.number("lambda_dssim", 0.0, 1.0)
    for name in ("lambda_language", "lambda_depth", "lambda_sa", "lambda_opacity"):
        c.number(name, 0.0)
    for name in ("densify", "lad", "lop", "random_background", "dark_backdrop", "carve_free_space"):
        if not isinstance(getattr(cfg, name), bool):
            c.fail(name, "True or False")
    if cfg.carve_free_space and cfg.init not in ("auto", "dense", "depth"):
        c.fail("carve_free_space", "False unless init is 'dense' or 'depth' (it carves with their stereo)")


def _check_regularisers(c: _ConfigCheck, cfg: TrainConfig) -> None:
    c.number("drop_gamma", 0.0, 0.9)
    c.number("lambda_virtual", 0.0)
    c.number("virtual_baseline", 0.0, 1.0, open_low=True)
    if cfg.virtual_directions not in ("horizontal", "any"):
        c.fail("virtual_directions", "'horizontal' or 'any'")
    c.whole("virtual_start", 0)
    c.whole("virtual_every", 1)
    c.number("virtual_resolution", 0.0, 1.0, open_low=True)
    c.number("lambda_smooth", 0.0)
    c.number("lambda_spread", 0.0)
    c.number("spread_start", 0.0, 1.0)
    c.number("lambda_visibility", 0.0)
    c.number("visibility_tolerance", 0.0, 1.0)
    c.number("carve_tolerance", 0.0, 1.0)
    c.number("half_resolution_until", 0.0, 1.0)
    c.number("language_start", 0.0, 1.0, open_low=False)
    c.number("autoencoder_spread", 0.0, open_low=False)
    c.number("language_balance", 0.0, 1.0)
    if cfg.language_decode not in LANGUAGE_DECODES:
        c.fail("language_decode", " or ".join(repr(d) for d in LANGUAGE_DECODES))
    c.number("opacity_decay", 0.0, 1.0, open_low=True)
    c.number("lambda_empty", 0.0)
    c.number("lambda_anisotropy", 0.0)
    c.number("anisotropy_ratio", 1.0)
    if cfg.refiner is not None and not isinstance(cfg.refiner, str):
        c.fail("refiner", "a model folder (a string) or None")
    c.number("lambda_refiner", 0.0)
    c.whole("refiner_every", 1)
    c.whole("refiner_start", 0)
    c.whole("lop_every", 0)
    c.whole("lop_gamma", 1)
    c.number("lop_tau", 0.0, 1.0, open_low=True)


Callback = Callable[[int, float, LanguageField], None]


def color_loss(rendered: Tensor, target: Tensor, lambda_dssim: float = 0.2) -> Tensor:
    """L_C = (1 - lambda) L1 + lambda (1 - SSIM) on images [H, W, 3]."""
    l1 = (rendered - target).abs().mean()
    d_ssim = 1.0 - ssim_map(rendered, target).mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * d_ssim


def scene_bounds(scene: Scene, cfg: TrainConfig) -> np.ndarray:
    """[2, 3] region to initialise in: ``cfg.bounds`` if given, else the scene's own estimate."""
    bounds = np.asarray(cfg.bounds if cfg.bounds is not None else scene.bounds(), dtype=np.float64)
    if bounds.shape != (2, 3) or not np.isfinite(bounds).all() or (bounds[1] <= bounds[0]).any():
        raise ValueError(
            f"bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, got {bounds}"
        )
    return bounds


@dataclass
class LanguageTargets:
    """What L_LF compares with, per training view: autoencoded mask features at every pixel.

    Attributes:
        latents: view name -> [3, H, W, 3] latent of the mask covering each pixel at each level.
        valid: view name -> [3, H, W] bool, pixels that have a mask at that level.
        autoencoder: the scene's autoencoder (its decoder is saved with the field).
        stats: the autoencoder's training figures.
    """

    latents: dict[str, Tensor]
    valid: dict[str, Tensor]
    autoencoder: LanguageAutoencoder
    stats: dict[str, float]
    config: AutoencoderConfig
    segments: dict[str, Tensor]  # view name -> [3, H, W] mask ids, -1 = none (LAD's masks)
    prototypes: list[Tensor]  # per level, [P_l, 3] distinct latents of the masks used there (LOP)


def _all_or_none(names: list[str], have: list[str], wanted: bool | None, what: str, otherwise: str) -> None:
    """Refuses training views of which only some have an input (or none, where it is ``wanted``)."""
    missing = [n for n in names if n not in have]
    if missing and (wanted or have):
        raise ValueError(
            f"{what} for training views {missing}"
            + (f" (views {have} have one)" if have else "")
            + f"; run `langfield preprocess` or {otherwise}"
        )


def check_inputs(scene: Scene, cfg: TrainConfig, progress: bool = True) -> None:
    """Reads and checks every file training and the evaluation after it will read, before any work:
    each view's image (its size against its intrinsics), depth prior, feature cache and segmentation
    masks, the bounds, and whether the training views agree on having language and depth targets.

    Raises:
        ValueError: the first problem, naming the file or setting (a SceneError, FeatureCacheError).
    """
    train_names = scene.names("train")
    if not train_names:
        raise ValueError(f"{scene.root}: no training views; choose them with views= or n_views=")
    scene_bounds(scene, cfg)
    for name in tqdm(scene.names("all"), desc="check", disable=not progress, leave=False):
        scene.check_view(name)
    if cfg.language is not False:
        have = [n for n in train_names if scene.feature_paths(n) is not None]
        _all_or_none(train_names, have, cfg.language, f"{scene.root}/language_features: no feature cache",
                     "train without language (--no-language)")  # fmt: skip
    if cfg.depth is not False:
        have = [n for n in train_names if scene.depth_path(n) is not None]
        _all_or_none(train_names, have, cfg.depth, f"{scene.root}/depths: no depth prior",
                     "train without it (--no-depth)")  # fmt: skip
        if have and scene.depth_kind is None:
            raise ValueError(
                f"{scene.root}: depths/ needs depth_kind ('depth' or 'disparity') in transforms.json"
            )


# Autoencoders this process has trained, by (features, config): ablate, bench and sweeps train one
# scene many times, and the autoencoder (deterministic for its seed) was retrained for every run.
_AUTOENCODERS: OrderedDict[tuple[str, AutoencoderConfig], tuple[LanguageAutoencoder, dict[str, float]]] = (
    OrderedDict()
)
_AUTOENCODERS_KEPT = 4


def fit_autoencoder(
    features: np.ndarray, ae_cfg: AutoencoderConfig, progress: bool = True
) -> tuple[LanguageAutoencoder, dict[str, float]]:
    """:func:`train_autoencoder` on ``features``, or a copy of the one this process already trained on
    the same features with the same config (its stats then carry ``reused: 1.0``; ``seconds`` stays the
    time the training took)."""
    digest = hashlib.sha1(np.ascontiguousarray(features).tobytes())
    digest.update(str(features.shape).encode())
    key = (digest.hexdigest(), ae_cfg)
    if key in _AUTOENCODERS:
        _AUTOENCODERS.move_to_end(key)
        autoencoder, stats = _AUTOENCODERS[key]
        return copy.deepcopy(autoencoder), dict(stats, reused=1.0)
    autoencoder, stats = train_autoencoder(features, ae_cfg, progress=progress)
    _AUTOENCODERS[key] = (copy.deepcopy(autoencoder), dict(stats))
    while len(_AUTOENCODERS) > _AUTOENCODERS_KEPT:
        _AUTOENCODERS.popitem(last=False)
    return autoencoder, stats


def language_targets(scene: Scene, cfg: TrainConfig, progress: bool = True) -> LanguageTargets | None:
    """Reads the training views' feature caches, trains the autoencoder (eq. 2), encodes the targets.

    Returns None when language is off, or automatic and some training view has no cache.
    """
    names = scene.names("train")
    paths = {name: scene.feature_paths(name) for name in names}
    missing = [name for name, p in paths.items() if p is None]
    if cfg.language is False or (cfg.language is None and missing):
        return None
    if missing:
        raise ValueError(
            f"{scene.root}/language_features: no feature cache for training views {missing} "
            "(run `langfield preprocess` or train without language)"
        )
    caches = {}
    for name in names:
        cam = scene.camera(name)
        caches[name] = read_feature_cache(*paths[name], expected_hw=(cam.height, cam.width), dim=512)
    features = np.concatenate([c.features for c in caches.values()])
    if features.shape[0] == 0:
        raise ValueError(f"{scene.root}/language_features: the training views' caches hold no masks")
    ae_cfg = AutoencoderConfig(
        iterations=cfg.autoencoder_iterations, seed=cfg.seed, spread_weight=cfg.autoencoder_spread
    )
    autoencoder, stats = fit_autoencoder(features, ae_cfg, progress=progress)
    latents, valid, segments = {}, {}, {}
    per_level: list[list[Tensor]] = [[] for _ in range(N_LEVELS)]
    with torch.no_grad():
        for name, cache in caches.items():
            z = autoencoder.encode(torch.from_numpy(cache.features))  # [M, 3]
            seg = torch.from_numpy(cache.segments.astype(np.int64))  # [3, H, W]
            segments[name] = seg
            valid[name] = seg >= 0
            latents[name] = z[seg.clamp_min(0)] * valid[name][..., None]
            for level in range(N_LEVELS):
                ids = torch.unique(seg[level][seg[level] >= 0])
                per_level[level].append(z[ids])
    prototypes = [torch.unique(torch.cat(p), dim=0) for p in per_level]
    return LanguageTargets(latents, valid, autoencoder, stats, ae_cfg, segments, prototypes)


def depth_inputs(
    scene: Scene, cfg: TrainConfig, targets: LanguageTargets | None
) -> dict[str, tuple[Tensor, Tensor]] | None:
    """Each training view's LAD masks [3, H, W] and depth prior [H, W]; None when depth is off.

    The masks are the feature cache's (the language masks, as LAD asks); a view without a cache gets
    only the global term. Priors with NaN or inf pixels are rejected when the scene loads them; the
    background of images with alpha (alpha < 0.5) is left out of both terms.
    """
    if cfg.depth is False:
        return None
    priors = {name: scene.depth(name) for name in scene.names("train")}
    missing = [name for name, prior in priors.items() if prior is None]
    if cfg.depth is None and missing:
        return None
    if missing:
        raise ValueError(
            f"{scene.root}/depths: no depth prior for training views {missing} (or train with --no-depth)"
        )
    if scene.depth_kind is None:
        raise ValueError(
            f"{scene.root}: depths/ needs depth_kind ('depth' or 'disparity') in transforms.json"
        )
    out = {}
    for name, prior_np in priors.items():
        alpha = scene.alpha(name)
        if alpha is not None:  # the background of an RGBA image is no surface: not compared
            prior_np = np.where(alpha >= 0.5, prior_np, np.nan).astype(np.float32)
        prior = torch.from_numpy(prior_np)
        if targets is not None:
            seg = targets.segments[name]
        else:
            seg = torch.full((N_LEVELS, *prior.shape), -1, dtype=torch.int64)
        out[name] = (seg, prior)
    return out


@dataclass(frozen=True)
class ViewTargets:
    """What one training view supervises, at the size its camera renders.

    Attributes:
        camera: the view's camera (the scene's, or :meth:`half_size`'s).
        image: [H, W, 3] photo.
        coverage: [H, W] 1 on surfaces, 0 on the empty space the photo shows (None: no empty space).
        latents, language_weight: [3, H, W, 3] language latents and [3, H, W] L_LF's weight of each
            pixel (:func:`~langfield.model.language.mask_balance`; 0 where no mask gives a latent);
            None without language.
        depth: the L_D target (None without depth priors).
        depth_input: the masks [3, H, W] and prior [H, W] it was built from (to resample it).
    """

    camera: Camera
    image: Tensor
    coverage: Tensor | None = None
    latents: Tensor | None = None
    language_weight: Tensor | None = None
    depth: LADTarget | None = None
    depth_input: tuple[Tensor, Tensor] | None = None

    def half_size(self) -> ViewTargets:
        """The view at half its width and height (DashGaussian's coarse-to-fine training, Chen et al.
        2025): photo and coverage area-averaged, the per-pixel targets (latents, masks, depth prior)
        taken at the nearest pixel centre, and the L_D target rebuilt from those."""
        cam = self.camera.scaled(2.0)
        rows = ((torch.arange(cam.height) + 0.5) * self.camera.height / cam.height).long()
        cols = ((torch.arange(cam.width) + 0.5) * self.camera.width / cam.width).long()

        (image,) = area_resize([self.image], cam)
        coverage = None if self.coverage is None else area_resize([self.coverage[..., None]], cam)[0][..., 0]
        depth = depth_input = None
        if self.depth is not None and self.depth_input is not None:
            seg, prior = self.depth_input
            depth_input = (seg[:, rows][:, :, cols], prior[rows][:, cols])
            depth = LADTarget.from_view(*depth_input, self.depth.depth_kind)
        latents = None if self.latents is None else self.latents[:, rows][:, :, cols]
        weight = None if self.language_weight is None else self.language_weight[:, rows][:, :, cols]
        return ViewTargets(cam, image, coverage, latents, weight, depth, depth_input)


def init_method(scene: Scene, cfg: TrainConfig) -> str:
    """``cfg.init`` with "auto" resolved: "depth" when every training view has a depth prior and
    training uses it (``cfg.depth`` not False), else "dense"."""
    if cfg.init == "points" and scene.points_path is None:
        raise SceneError(
            f"--init points: {scene.root} has no point cloud (transforms.json's ply_file_path, as "
            "langfield capture writes it)"
        )
    if cfg.init != "auto":
        return cfg.init
    names = scene.names("train")
    priors = cfg.depth is not False and all(scene.depth_path(n) is not None for n in names)
    return "depth" if priors and scene.depth_kind is not None else "dense"


def scene_start(scene: Scene, cfg: TrainConfig) -> StartPoints:
    """Where the Gaussians start (:func:`~langfield.training.initialisation.start_points`, ``cfg.init``
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

    Adam's multi-tensor ("foreach") update: a few whole-tensor passes instead of a dozen element-wise
    ones per parameter (2.1x faster on the CPU for the built-in scene's parameters, equal to the loop
    bit for bit in a 20-step check).
    """
    lrs = dict(G.learning_rates(extent), lang=cfg.per_gaussian_language_lr)
    opts: dict[str, torch.optim.Optimizer] = {
        name: torch.optim.Adam([{"params": [p], "lr": lrs[name], "name": name}], eps=1e-15, foreach=True)
        for name, p in field.splats.items()
    }
    opts["color"] = torch.optim.Adam(
        [
            {"params": list(field.color.grid_parameters()), "lr": cfg.grid_lr},
            {"params": list(field.color.mlp_parameters()), "lr": cfg.mlp_lr},
        ],
        eps=1e-15,
        foreach=True,
    )
    if field.language is not None:
        opts["language"] = torch.optim.Adam(
            [
                {"params": list(field.language.grid_parameters()), "lr": cfg.grid_lr},
                {"params": list(field.language.mlp_parameters()), "lr": cfg.mlp_lr},
            ],
            eps=1e-15,
            foreach=True,
        )
    return opts


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


@dataclass
class _Run:
    """What one training run reads and updates: built from the scene once, every file read and checked,
    before the first iteration (:func:`_prepare`)."""

    cfg: TrainConfig  # with the run's length resolved
    scene: Scene
    field: LanguageField
    targets: LanguageTargets | None
    refiner: Any  # an OnnxImageRefiner, or None
    cameras: dict[str, Camera]
    views: dict[str, ViewTargets]
    half_views: dict[str, ViewTargets]  # the same at half size, for the first half_steps
    stereo: list  # the start's stereo surfaces, for carving free space
    optimizers: dict[str, torch.optim.Optimizer]
    strategy: DensifyStrategy
    state: dict[str, Any]
    extent: float
    means_lr0: float
    half_steps: int
    language_steps: int
    use_lop: bool
    rng: np.random.Generator
    drop_generator: torch.Generator
    carved: list[dict[str, int]] = dataclasses.field(default_factory=list)
    lop_rounds: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    rendered: dict[str, tuple[Camera, Tensor, Tensor]] = dataclasses.field(default_factory=dict)


def _prepare(scene: Scene, cfg: TrainConfig, progress: bool) -> _Run:
    """Checks the inputs, reads every target and builds the field, its optimizers and densification."""
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
    stereo = _stereo_surfaces(scene, start) if cfg.carve_free_space else []
    field.meta["depth"] = None if depth_in is None else {"lad": cfg.lad, "kind": scene.depth_kind}
    field.meta["training_length"] = length
    bounds = field.meta.bounds
    extent = float(np.linalg.norm(bounds[1] - bounds[0]) / 2)
    optimizers = make_optimizers(field, extent, cfg)
    strategy = DensifyStrategy(
        refine_start=cfg.refine_start,
        refine_every=cfg.refine_every,
        refine_stop=cfg.refine_stop if cfg.refine_stop is not None else cfg.iterations,  # DNGaussian
        grad_threshold=cfg.grad_threshold,
        prune_opacity=cfg.prune_opacity,
        max_gaussians=cfg.max_gaussians or 4 * field.num_gaussians,
        prune_scale3d=None,  # DNGaussian keeps large Gaussians; 3DGS prunes them only after opacity resets
    )
    cameras = {name: scene.camera(name) for name in train_names}
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
        )
        for name in train_names
    }
    # The first half_resolution_until of the run renders every view at half its width and height.
    half_steps = round(cfg.half_resolution_until * cfg.iterations)
    return _Run(
        cfg=cfg,
        scene=scene,
        field=field,
        targets=targets,
        refiner=refiner,
        cameras=cameras,
        views=views,
        half_views={name: v.half_size() for name, v in views.items()} if half_steps > 0 else {},
        stereo=stereo,
        optimizers=optimizers,
        strategy=strategy,
        state=strategy.initialize_state(field.splats),
        extent=extent,
        means_lr0=optimizers["means"].param_groups[0]["lr"],
        half_steps=half_steps,
        language_steps=round(cfg.language_start * cfg.iterations),
        use_lop=cfg.lop and targets is not None and cfg.lop_every > 0,
        rng=np.random.default_rng(cfg.seed),
        drop_generator=torch.Generator().manual_seed(cfg.seed),
    )


def _step_loss(run: _Run, step: int, name: str) -> tuple[Tensor, Render, Camera]:
    """Renders training view ``name`` at ``step`` and returns the step's loss, the render and its camera."""
    cfg, field = run.cfg, run.field
    view = run.half_views[name] if step < run.half_steps else run.views[name]
    cam = view.camera
    # 3DGS's exponential decay of the position learning rate to 1 % over the run.
    frac = step / max(cfg.iterations - 1, 1)
    run.optimizers["means"].param_groups[0]["lr"] = run.means_lr0 * math.exp(math.log(0.01) * frac)
    keep = None
    if cfg.drop_gamma > 0:
        rate = cfg.drop_gamma * step / max(cfg.iterations, 1)
        keep = drop_compensation(field.num_gaussians, rate, run.drop_generator)
    behind = None
    cover = view.coverage
    if cfg.random_background and run.scene.background is None:
        behind = torch.rand(3, generator=run.drop_generator)
    target = view.image
    if cover is not None and behind is not None:  # a photo's backdrop shows the random colour
        target = backdrop_target(view.image, cover, behind)
    grid = field.grid_features()  # read once, shared by this step's renders
    out = field.render(
        cam,
        backend=cfg.backend,
        hard_depth=view.depth is not None,
        language=step >= run.language_steps,
        opacity_scale=keep,
        background=behind,
        grid=grid,
        depth_spread=cfg.lambda_spread > 0 and step >= cfg.spread_start * cfg.iterations,
    )
    loss = color_loss(out.rgb, target, cfg.lambda_dssim)
    if cover is not None and cfg.lambda_empty > 0:
        loss = loss + cfg.lambda_empty * (out.alpha * (1.0 - cover)).mean()
    virtual_step = step >= cfg.virtual_start and (step - cfg.virtual_start) % cfg.virtual_every == 0
    if cfg.lambda_virtual > 0 and virtual_step:
        loss = loss + cfg.lambda_virtual * _virtual_view_loss(
            field, cam, target, out, keep, cfg, run.rng, grid
        )
    pseudo_step = step >= cfg.refiner_start and (step - cfg.refiner_start) % cfg.refiner_every == 0
    if run.refiner is not None and pseudo_step:
        pseudo = _pseudo_view_loss(field, run.refiner, list(run.cameras.values()), cfg, run.rng, grid)
        loss = loss + cfg.lambda_refiner * pseudo
    return loss + _geometry_and_language_loss(run, name, view, out), out, cam


def _geometry_and_language_loss(run: _Run, name: str, view: ViewTargets, out: Render) -> Tensor | float:
    """The step's terms on the rendered depth, the scales, the latents and the opacities."""
    cfg, field, cam = run.cfg, run.field, view.camera
    loss: Tensor | float = 0.0
    if cfg.lambda_visibility > 0 or cfg.lambda_smooth > 0:
        covered = out.alpha.detach() > 0.5
        depth_z = z_depth(out.depth / out.alpha.clamp_min(1e-4), cam)
    if cfg.lambda_visibility > 0:
        loss = loss + cfg.lambda_visibility * _visibility_loss(
            depth_z, covered, cam, name, run.rendered, cfg.visibility_tolerance
        )
        run.rendered[name] = (cam, depth_z.detach(), covered)
    if cfg.lambda_smooth > 0:
        loss = loss + cfg.lambda_smooth * depth_smoothness(depth_z, view.image, covered)
    if cfg.lambda_spread > 0 and out.depth_spread is not None:
        loss = loss + cfg.lambda_spread * depth_spread_loss(out.depth_spread, out.depth, out.alpha)
    if cfg.lambda_anisotropy > 0:
        loss = loss + cfg.lambda_anisotropy * anisotropy_loss(
            field.splats["log_scales"], cfg.anisotropy_ratio
        )
    if view.latents is not None and out.latents is not None:
        loss = loss + cfg.lambda_language * language_loss(out.latents, view.latents, view.language_weight)
    if view.depth is not None:
        loss = loss + cfg.lambda_depth * depth_loss(
            view.depth, out.depth_hard, out.depth, cfg.lambda_sa, lad=cfg.lad
        )
    if cfg.lambda_opacity > 0:
        loss = loss + cfg.lambda_opacity * G.opacities(field.splats).mean()
    return loss


def _update(run: _Run, step: int, out: Render, cam: Camera, bar: tqdm) -> None:
    """After the backward pass: densification, the optimizer steps, opacity decay and LOP."""
    cfg, field = run.cfg, run.field
    if cfg.densify:
        info = {"means2d": out.means2d, "radii": out.radii, "width": cam.width, "height": cam.height}
        run.strategy.step_post_backward(field.splats, run.optimizers, run.state, step, info, run.extent)
    for opt in run.optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    if cfg.opacity_decay < 1.0 and step >= cfg.refine_start:
        with torch.no_grad():
            logits = field.splats["opacity_logits"]
            logits.copy_(torch.logit(torch.sigmoid(logits) * cfg.opacity_decay, eps=1e-6))
    if run.use_lop and (step + 1) % cfg.lop_every == 0:
        run.lop_rounds.append(_prune_outliers(field, run.targets, run.optimizers, run.state, cfg, step + 1))
        bar.write(
            f"LOP at iteration {step + 1}: removed {run.lop_rounds[-1]['removed']} of "
            f"{run.lop_rounds[-1]['before']} Gaussians"
        )


def registered_entries(
    field: LanguageField, cameras: dict[str, Camera], targets: LanguageTargets
) -> torch.Tensor:
    """``[N, 3]`` each Gaussian's codebook entry per level: the training mask it carries the most
    rendering weight on (:func:`~langfield.training.aggregate.register_entries`), which the 3D
    selection reads. Rooms, 3 layouts x 3 seeds: 3D precision 0.625 -> 0.733, recall 0.854 -> 0.877
    against each Gaussian's own latent (docs/figures.md, "Registered entries")."""
    entries = {}
    for name in cameras:
        nearest = field.codebook_indices(targets.latents[name])
        entries[name] = torch.where(targets.valid[name], nearest, -1)
    sizes = [len(c) for c in field.codebook]
    return register_entries(field, cameras, entries, sizes, backend=field.meta.backend)


def train(
    scene: Scene,
    cfg: TrainConfig | None = None,
    *,
    progress: bool = True,
    callback: Callback | None = None,
    callback_every: int = 0,
) -> LanguageField:
    """Trains a field on ``scene``'s training views.

    Args:
        scene: a loaded scene with a "train" split.
        cfg: settings; ``TrainConfig()`` if None.
        progress: show a tqdm bar with the loss and the Gaussian count.
        callback: called as ``callback(step, train_seconds, field)`` every ``callback_every`` steps and
            at the end; its own time is not counted as training time.

    Returns:
        The trained :class:`LanguageField`; ``field.meta`` records timings and sizes.
    """
    run = _prepare(scene, cfg or TrainConfig(), progress)
    cfg, field, names = run.cfg, run.field, list(run.views)
    order: list[str] = []
    train_seconds = 0.0
    bar = tqdm(total=cfg.iterations, disable=not progress, desc="train", dynamic_ncols=True, leave=False)
    for step in range(cfg.iterations):
        t0 = time.perf_counter()
        if run.stereo and step % cfg.refine_every == 0:
            run.carved.append(
                _carve_free_space(field, run.stereo, run.optimizers, run.state, cfg.carve_tolerance, step)
            )
        if not order:
            order = [names[i] for i in run.rng.permutation(len(names))]
        loss, out, cam = _step_loss(run, step, order.pop())
        loss.backward()
        _update(run, step, out, cam, bar)
        train_seconds += time.perf_counter() - t0
        bar.update(1)
        if step % 10 == 0:
            bar.set_postfix(loss=f"{loss.item():.4f}", gaussians=str(field.num_gaussians))
        if (
            callback is not None
            and callback_every
            and (step + 1) % callback_every == 0
            and step + 1 < cfg.iterations
        ):
            callback(step + 1, train_seconds, field)
    bar.close()
    if field.codebook is not None and run.targets is not None:
        # After the iterations and timed apart: train_seconds and iterations_per_second stay the loop's.
        t0 = time.perf_counter()
        field.entries = registered_entries(field, run.cameras, run.targets)
        seconds = round(time.perf_counter() - t0, 3)
        field.meta["language"] = dict(field.meta["language"], registered=True, register_seconds=seconds)
    field.meta.update(
        carved={"removed": sum(c["removed"] for c in run.carved), "rounds": len(run.carved)}
        if run.stereo
        else None,
        lop=run.lop_rounds if run.use_lop else None,
        train_seconds=train_seconds,
        iterations=cfg.iterations,
        iterations_per_second=cfg.iterations / train_seconds if train_seconds > 0 else None,
        num_gaussians=field.num_gaussians,
    )
    if callback is not None:
        callback(cfg.iterations, train_seconds, field)
    return field


# The scene-sized run length (TrainConfig.iterations None). Each iteration fits one training view, so
# the length follows the views: ITERATIONS_PER_VIEW visits of each, within [MIN, MAX]. Three views give
# 1500 iterations (the sparse-view defaults were chosen at 1000-1500, docs/figures.md); fern's curve is
# within 0.3 dB of its 1000-iteration point from 500 iterations on ("Time to quality").
ITERATIONS_PER_VIEW = 500
MIN_ITERATIONS = 1000
MAX_ITERATIONS = 6000  # SOVGaussian's and DNGaussian's length


def training_length(iterations: int | None, n_views: int) -> dict[str, Any]:
    """The run's length: ``iterations`` when given (forced), else sized by the ``n_views`` training
    views. Returns what field.json records: ``{"iterations", "forced", "rule"}``."""
    if iterations is not None:
        return {"iterations": int(iterations), "forced": True, "rule": "--iterations"}
    n = min(max(ITERATIONS_PER_VIEW * max(n_views, 1), MIN_ITERATIONS), MAX_ITERATIONS)
    rule = f"{ITERATIONS_PER_VIEW} per training view x {n_views}, within [{MIN_ITERATIONS}, {MAX_ITERATIONS}]"
    return {"iterations": int(n), "forced": False, "rule": rule}


def backdrop_target(image: Tensor, coverage: Tensor, colour: Tensor) -> Tensor:
    """The training target [H, W, 3] with ``colour`` [3] behind a photo's empty space: ``image`` where
    ``coverage`` [H, W] is 1, ``colour`` where it is 0 (the backdrop's own near-black replaced)."""
    cover = coverage[..., None]
    return image * cover + (1.0 - cover) * colour


def empty_space(scene: Scene, cfg: TrainConfig) -> tuple[dict[str, Tensor], str | None]:
    """Where each training view shows empty space: ``({name: [H, W] coverage in [0, 1]}, source)``.

    Coverage is 1 on surfaces and 0 on empty space: the alpha channel of RGBA images, else (with
    ``cfg.dark_backdrop``) 0 on a black backdrop (:func:`~langfield.training.regularisers.dark_backdrop`);
    views with neither are left out. ``source`` is "alpha", "dark backdrop" or None (the report's record).
    """
    coverage: dict[str, Tensor] = {}
    sources = set()
    for name in scene.names("train"):
        alpha = scene.alpha(name)
        if alpha is not None:
            sources.add("alpha")
        elif cfg.dark_backdrop:
            backdrop = dark_backdrop(scene.image(name))
            if backdrop.any():
                alpha = (~backdrop).astype(np.float32)
                sources.add("dark backdrop")
        if alpha is not None:
            coverage[name] = torch.from_numpy(np.ascontiguousarray(alpha, dtype=np.float32))
    return coverage, " and ".join(sorted(sources)) or None


def _virtual_view_loss(
    field: LanguageField,
    cam: Camera,
    image: Tensor,
    out: Render,
    keep: Tensor | None,
    cfg: TrainConfig,
    rng: np.random.Generator,
    grid: GridFeatures | None = None,
) -> Tensor:
    """Binocular consistency (Han et al. 2024): the training view's depth must warp a sideways-shifted
    render onto the training image. L1 + D-SSIM over the pixels the field covers and the warp reaches."""
    covered = out.alpha.detach() > 0.5
    depth = z_depth(out.depth / out.alpha.clamp_min(1e-4), cam)
    right, up = virtual_shift(
        depth.detach(), covered, cfg.virtual_baseline, rng, any_direction=cfg.virtual_directions == "any"
    )
    if right == 0.0 and up == 0.0:
        return out.rgb.sum() * 0.0
    if cfg.virtual_resolution < 1.0:
        cam = cam.scaled(1.0 / cfg.virtual_resolution)
        depth, image, cover = area_resize([depth[..., None], image, covered[..., None].float()], cam)
        depth, covered = depth[..., 0], cover[..., 0] > 0.5
    shifted = field.render(
        shifted_camera(cam, right, up), backend=cfg.backend, language=False, opacity_scale=keep, grid=grid
    )
    warped, valid = virtual_view_warp(shifted.rgb, depth, cam, right, up)
    mask = (valid & covered).float()
    if float(mask.sum()) < 1:
        return out.rgb.sum() * 0.0
    l1 = ((warped - image).abs().mean(-1) * mask).sum() / mask.sum()
    d_ssim = ((1.0 - ssim_map(warped, image)[0].mean(0)) * mask).sum() / mask.sum()
    return (1.0 - cfg.lambda_dssim) * l1 + cfg.lambda_dssim * d_ssim


def area_resize(images: list[Tensor], cam: Camera) -> list[Tensor]:
    """Each [H, W, C] image area-averaged to ``cam``'s size (differentiable)."""
    size = (cam.height, cam.width)
    return [
        torch.nn.functional.interpolate(x.permute(2, 0, 1)[None], size=size, mode="area")[0].permute(1, 2, 0)
        for x in images
    ]


def _visibility_loss(
    depth_z: Tensor,
    seen: Tensor,
    cam: Camera,
    name: str,
    rendered: dict[str, tuple[Camera, Tensor, Tensor]],
    tolerance: float,
) -> Tensor:
    """Mean free-space violation (:func:`langfield.training.regularisers.free_space_violation`) of this view's
    rendered surface [H, W] in every other training view's last render."""
    points = backproject(depth_z, cam)[seen]
    total = depth_z.sum() * 0.0
    count = 0
    for other, (other_cam, other_depth, other_seen) in rendered.items():
        if other == name:
            continue
        violation, valid = free_space_violation(points, other_cam, other_depth, other_seen, tolerance)
        total = total + violation.sum()
        count += int(valid.sum())
    return total / max(count, 1)


def _stereo_surfaces(scene: Scene, start: StartPoints) -> list[tuple[Camera, Tensor, Tensor]]:
    """The training views' stereo depth maps as (camera, z-depth [H, W], resolved [H, W] bool)."""
    if start.depths is None:
        return []
    surfaces = []
    for cam, depth in zip(scene.cameras("train"), start.depths, strict=True):
        resolved = np.isfinite(depth)
        surfaces.append((cam, torch.from_numpy(np.where(resolved, depth, 0.0)), torch.from_numpy(resolved)))
    return surfaces


@torch.no_grad()
def _carve_free_space(
    field: LanguageField,
    stereo: list[tuple[Camera, Tensor, Tensor]],
    optimizers: dict[str, torch.optim.Optimizer],
    state: dict[str, Any],
    tolerance: float,
    step: int,
) -> dict[str, int]:
    """Removes the Gaussians whose centre lies in front of a surface a training view's stereo resolved
    (in the free space its rays cross: space carving, Kutulakos and Seitz 2000)."""
    means = field.splats["means"].detach()
    free = torch.zeros(means.shape[0], dtype=torch.bool)
    for cam, depth, resolved in stereo:
        violation, _ = free_space_violation(means, cam, depth, resolved, tolerance)
        free |= violation > 0
    removed = int(free.sum())
    if removed == means.shape[0]:  # the stereo disagrees with every Gaussian: keep them rather than none
        removed = 0
    if removed:
        remove(field.splats, optimizers, state, free)
    return {"iteration": step, "removed": removed}


def _pseudo_view_loss(
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


@torch.no_grad()
def _prune_outliers(
    field: LanguageField,
    targets: LanguageTargets,
    optimizers: dict[str, torch.optim.Optimizer],
    state: dict[str, Any],
    cfg: TrainConfig,
    step: int,
) -> dict[str, Any]:
    """One LOP round (eq. 14-16): removes the language-group outliers, optimizer state kept in step."""
    before = field.num_gaussians
    latents = field.gaussian_latents()
    result = lop_prune(
        field.splats["means"].detach(), latents, targets.prototypes, gamma=cfg.lop_gamma, tau=cfg.lop_tau
    )
    if result.num_pruned:
        remove(field.splats, optimizers, state, result.prune)
    return {"iteration": step, "before": before, "removed": result.num_pruned,
            "removed_by_level": list(result.pruned_by_level)}  # fmt: skip


def summary_line(field: LanguageField, test_psnr: float | None) -> str:
    """The one-line summary printed at the end of training."""
    m = field.meta
    ips = m.iterations_per_second
    parts = [
        f"trained {m.iterations or 0} iterations in {m.train_seconds or 0.0:.1f} s",
        f"{ips:.1f} it/s" if ips else "",
        f"{field.num_gaussians} Gaussians",
        f"backend {m.backend}",
        f"novel-view PSNR {test_psnr:.2f} dB" if test_psnr is not None else "no test views",
    ]
    return ", ".join(p for p in parts if p)
