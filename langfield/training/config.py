"""Training settings: :class:`TrainConfig`, each setting declared once.

Every setting is one :func:`setting` call: its default, one line on what it does (the ``--help`` text),
the check its values must pass and, where ``langfield train`` has one, its flag. :func:`check_config`
and the command's flags (:func:`add_train_flags`) are generated from these declarations, so a setting
is never written twice. Settings are declared in groups (``GROUPS``: the start, the model, the losses,
the sparse-view terms, the schedule, the densification strategy and LOP); ``--help`` lists them so.
Attribute access stays flat (``cfg.lambda_depth``) so that field.json, sweep specs and ablation cases
written before the groups still read as they are.

Where a default is not the paper's, the comment above it says why; the figure behind it and the commit
are in docs/decisions.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from langfield.io.field_meta import LANGUAGE_DECODES, LANGUAGE_FEATURES
from langfield.kernels import BACKEND_ALIASES, BACKENDS
from langfield.training.lad import LAMBDA_SA
from langfield.training.lop import LOP_GAMMA, LOP_INTERVAL, LOP_TAU
from langfield.training.settings import (
    FLAG,
    TRI_STATE,
    Number,
    OneOf,
    Satisfies,
    Whole,
    add_flags,
    bounds_arg,
    check_fields,
    given_flags,
    is_box,
    refuse,
    setting,
)
from langfield.training.start import INIT_ALIGNS, INIT_METHODS, SWEEP_PLANES, SWEEP_VIEWS

GROUPS = {
    "run": "the run",
    "start": "where the Gaussians start",
    "model": "colour and language fields",
    "losses": "the loss terms",
    "sparse-view": "sparse-view regularisers",
    "schedule": "learning rates and schedule",
    "strategy": "edits of the Gaussian set",
    "lop": "language-guided outlier pruning",
}


def _in(group: str):
    return functools.partial(setting, group=group)


# A setting of each group: setting(default, help, check=..., flag=...) (langfield.training.settings).
in_run, in_start, in_model, in_losses = _in("run"), _in("start"), _in("model"), _in("losses")
in_sparse_view, in_schedule, in_strategy, in_lop = map(_in, ("sparse-view", "schedule", "strategy", "lop"))


@dataclass(frozen=True)
class TrainConfig:
    """Training settings; defaults from the paper, DNGaussian and 3DGS unless a comment says why not.

    ``None`` means "sized to the scene" (the run's length, the initial Gaussian count, the hash-table
    size) or "decided by the scene's files" (language, depth); the values used are in field.json.
    """

    # -- the run
    iterations: int | None = in_run(
        None,
        "training iterations (default: sized by the scene, 500 per training view in [1000, 6000])",
        check=Whole(0, optional=True),
        flag="--iterations",
        parse=int,
    )
    # 0.5 %: fern stops at 1300 of 1500 iterations 0.03 dB short of the whole run (1 %: 0.09 dB).
    stop_plateau: float = in_run(
        0.005,
        "end an unforced run once 200 iterations better the best fitting loss by under this fraction (0: no)",
        check=Number(0.0, 1.0),
        flag="--stop-plateau",
    )
    seed: int = in_run(0, "seed of the start and the view order", check=Whole(0), flag="--seed")
    backend: str = in_run(
        "auto",
        "rasterizer backend (cpu: numba's earlier name)",
        check=OneOf(("auto", *BACKENDS), aliases=tuple(BACKEND_ALIASES)),
        flag="--backend",
        choices=("auto", *BACKENDS, *BACKEND_ALIASES),
    )

    # -- the start (langfield.training.start)
    # "auto": the aligned depth prior (a point per pixel) where training uses one, else stereo (5-7 %).
    init: str = in_start(
        "auto",
        "where the Gaussians start: plane-sweep stereo on the training views, COLMAP's sparse SIFT "
        "points, the depth prior aligned to the stereo points, the scene's point cloud (sparse_pc.ply of "
        "langfield capture), or random in the bounds (default auto: depth when every training view has a "
        "depth prior, else dense)",
        check=OneOf(("auto", *INIT_METHODS)),
        flag="--init",
    )
    # Each step of the alignment makes the views agree more: "anchors" < "views" < "smooth" < "fused".
    init_align: str = in_start(
        "fused",
        "how the depth start aligns each view's prior: a line refined until the views agree with "
        "one another, a smooth correction from photo-consistency and the other views, then each pixel "
        "fused with the views that agree on it (fused, the default), the correction without the fusion "
        "(smooth), the line alone (views), or the line fitted to the view's own stereo (anchors)",
        check=OneOf(INIT_ALIGNS),
        flag="--init-align",
    )
    # DTU scan37 resolves 33 % more pixels with "best" (its views stand 35-71 degrees apart).
    init_sweep: str = in_start(
        "best", "sweep score of a depth: best view or mean", check=OneOf(SWEEP_VIEWS), flag="--init-sweep"
    )
    init_planes: str = in_start(
        "tilted",
        "sweep planes: also tilted 30 and 60 degrees, lower rows nearer, or fronto-parallel only",
        check=OneOf(tuple(SWEEP_PLANES)),
        flag="--init-planes",
    )
    init_fill: float = in_start(
        0.1, "random points added to the start, as a fraction of the photo points", check=Number(0.0, 10.0)
    )
    num_gaussians: int | None = in_start(
        None,
        "initial Gaussians (default: sized to the scene)",
        check=Whole(1, optional=True),
        flag="--num-gaussians",
        parse=int,
    )
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = in_start(
        None,
        "xmin,ymin,zmin,xmax,ymax,zmax to initialise in (default: the scene's estimate)",
        check=Satisfies(is_box, "((xmin, ymin, zmin), (xmax, ymax, zmax)) with max > min"),
        flag="--bounds",
        parse=bounds_arg,
    )

    # -- colour and language fields
    log2_table_size: int | None = in_model(
        None,
        "log2 of each hash table's size (default: sized to the scene)",
        check=Whole(8, 30, optional=True),
    )
    color_hidden: int = in_model(64, "hidden width of the colour MLP", check=Whole(1))
    # Three views show each point from three directions: frequencies fit them and extrapolate badly.
    color_freqs: int = in_model(
        0,
        "view-direction frequencies of the colour MLP (0: the direction alone, -1: none, NeRF: 4)",
        check=Whole(-1),
        flag="--color-freqs",
    )
    language: bool | None = in_model(
        None,
        "train the language field (default: when every training view has a feature cache)",
        check=TRI_STATE,
        flag="--no-language",
    )
    language_features: str = in_model(
        "hashgrid",
        "language latents from hash grids (SOVGaussian) or one per Gaussian (LangSplat baseline)",
        check=OneOf(LANGUAGE_FEATURES),
        flag="--language-features",
    )
    # The paper gives no width; the MLP maps 12 grid features to a 3-d latent, and 32 costs less than 64
    # at no loss of novel-view mIoU.
    language_hidden: int = in_model(32, "hidden width of MLP_L", check=Whole(1))
    # Language is constant over a part, and fine levels only hash-collide across objects; 1.0 gives the
    # colour layout.
    language_grid_scale: float = in_model(
        0.25,
        "language grid's finest resolution as a fraction of the colour grid's (1: the same)",
        check=Number(0.0, 1.0, open_low=True),
        flag="--language-grid-scale",
    )
    autoencoder_iterations: int = in_model(
        300, "training iterations of the scene's 512 -> 3 autoencoder", check=Whole(1)
    )
    # Eq. 2 alone packs a room's concepts 8-13 degrees apart on the 3-d sphere, and a rendered latent
    # 10 degrees off then decodes to a neighbour; the spread term pushes unlike concepts apart.
    autoencoder_spread: float = in_model(
        0.01,
        "weight of the autoencoder's term that spreads unlike concepts over the latent sphere "
        "(0: the paper's eq. 2 alone)",
        check=Number(0.0),
        flag="--autoencoder-spread",
    )
    # Rendered latents land about as far from their targets as a room's concepts lie apart; reading
    # them through the training masks' latents, by the vote of the Gaussians at the pixel, recovers the
    # concept. It changes no training step and can be changed after training.
    language_decode: str = in_model(
        "vote",
        "read rendered latents through the training masks' latents: by vote among the entries of "
        "the Gaussians at each pixel (vote), as the nearest entry (codebook), or decode them as they are "
        "(continuous, the paper)",
        check=OneOf(LANGUAGE_DECODES),
        flag="--language-decode",
    )

    # -- the loss terms (langfield.training.losses)
    lambda_dssim: float = in_losses(0.2, "D-SSIM's share of L_C (3DGS)", check=Number(0.0, 1.0))
    lambda_language: float = in_losses(1.0, "weight of L_LF", check=Number(0.0))
    # Under equal pixel weights a mug of 18 pixels is not rendered even in the views it is trained on.
    language_balance: float = in_losses(
        0.25,
        "L_LF weighs each pixel by its mask's area to the power minus this (0: every pixel alike, "
        "the paper's; 1: every mask alike)",
        check=Number(0.0, 1.0),
        flag="--language-balance",
    )
    depth: bool | None = in_losses(
        None,
        "train with the depth prior's L_D (default: when every training view has one, depths/)",
        check=TRI_STATE,
        flag="--no-depth",
    )
    lad: bool = in_losses(
        True,
        "per-mask (language-aware) normalisation of L_D (eq. 6, 9); off: the plain global term only",
        check=FLAG,
        flag="--no-lad",
    )
    # L_D's normalised terms are scale-invariant, so their gradient grows as 1 / the render's spread,
    # which is tiny at the start; at weight 1 they swamped L_C.
    lambda_depth: float = in_losses(0.01, "weight of L_D", check=Number(0.0))
    lambda_sa: float = in_losses(LAMBDA_SA, "weight of L_D's soft term (eq. 11)", check=Number(0.0))
    # 3DGS-MCMC's L1 on the opacities: three views leave most of the start in free space, and a
    # Gaussian the images do not need should fade until densification prunes it.
    lambda_opacity: float = in_losses(
        0.03,
        "weight of the L1 opacity penalty that fades unneeded Gaussians",
        check=Number(0.0),
        flag="--lambda-opacity",
    )
    # A surface as dark as a fixed black background would otherwise be left transparent. RGBA scenes
    # keep their own background.
    random_background: bool = in_losses(
        True,
        "a random background colour behind the Gaussians each iteration (scenes without alpha)",
        check=FLAG,
        flag="--random-background",
    )
    dark_backdrop: bool = in_losses(
        True,
        "treat a photo's black backdrop (tall dark regions at the border, DTU's) as empty space",
        check=FLAG,
        flag="--dark-backdrop",
    )
    lambda_empty: float = in_losses(
        1.0,
        "weight of the rendered alpha on the empty space the photos show (alpha, a black backdrop)",
        check=Number(0.0),
        flag="--lambda-empty",
    )

    # -- sparse-view regularisers (langfield.training.regularisers); 0 turns each off
    drop_gamma: float = in_sparse_view(
        0.2,
        "Gaussian dropout: a fraction gamma t / T left out at iteration t (DropGaussian; 0: off)",
        check=Number(0.0, 0.9),
        flag="--drop-gamma",
    )
    opacity_noise: float = in_sparse_view(
        0.0,
        "opacity noise: each opacity times 1 + e, e ~ N(0, s^2) clipped to +-s (Co-Adaptation; 0: off)",
        check=Number(0.0, 0.9),
        flag="--opacity-noise",
    )
    lambda_virtual: float = in_sparse_view(
        1.0,
        "weight of the virtual-view consistency term (Binocular-guided 3DGS; 0: off)",
        check=Number(0.0),
        flag="--lambda-virtual",
    )
    # DTU's wide baselines gain up to 0.2, fern loses there; 0.1 between.
    virtual_baseline: float = in_sparse_view(
        0.1,
        "sideways shift of the virtual camera as a fraction of the median rendered depth",
        check=Number(0.0, 1.0, open_low=True),
        flag="--virtual-baseline",
    )
    # Object scans' cameras stand 0.8-1.5 depths apart (DTU, Blender), LLFF's about 0.1: it keeps 0.1.
    virtual_spacing: float = in_sparse_view(
        0.4,
        "the virtual camera's shift as a share of the training cameras' mean spacing, where that is "
        "longer than --virtual-baseline's (0: off)",
        check=Number(0.0, 2.0),
        flag="--virtual-spacing",
    )
    virtual_occlusion: bool = in_sparse_view(
        False,
        "leave out of the virtual-view term the pixels the shifted view sees something in front of "
        "(the orbit always does)",
        check=FLAG,
        flag="--virtual-occlusion",
    )
    # Any direction checks vertical parallax too, which DTU's elevations need.
    virtual_directions: str = in_sparse_view(
        "any",
        "virtual cameras shifted left or right (a stereo pair), or in any direction of the image plane",
        check=OneOf(("horizontal", "any")),
        flag="--virtual-directions",
    )
    virtual_motion: str = in_sparse_view(
        "shift",
        "the virtual camera shifted in its image plane, orbiting the median depth ahead, or either at random",
        check=OneOf(("shift", "orbit", "both")),
        flag="--virtual-motion",
    )
    virtual_start: int = in_sparse_view(0, "first iteration of the virtual-view term", check=Whole(0))
    # It renders a second view; every second iteration fits fern better than every one.
    virtual_every: int = in_sparse_view(
        2, "the virtual-view term every n-th iteration", check=Whole(1), flag="--virtual-every"
    )
    virtual_resolution: float = in_sparse_view(
        1.0,
        "the virtual-view term's image size as a fraction of the training view's (0 < F <= 1)",
        check=Number(0.0, 1.0, open_low=True),
        flag="--virtual-resolution",
    )
    lambda_visibility: float = in_sparse_view(
        0.0,
        "weight of the free-space term: a view's surface may not lie in front of another view's",
        check=Number(0.0),
        flag="--lambda-visibility",
    )
    lambda_crossview: float = in_sparse_view(
        0.0,
        "weight of cross-view consistency: the rendered depth warps the other photos onto this one (0: off)",
        check=Number(0.0),
        flag="--lambda-crossview",
    )
    # The start's plane sweep resolves the textured surfaces the photos agree on (metric depth, no
    # scale to fit); real scenes without a depth prior have no other depth supervision.
    lambda_stereo: float = in_sparse_view(
        0.0, "weight of the sweep's depth on the render (0: off)", check=Number(0.0), flag="--lambda-stereo"
    )
    visibility_tolerance: float = in_sparse_view(
        0.02, "the free-space term's relative depth tolerance", check=Number(0.0, 1.0)
    )
    lambda_smooth: float = in_sparse_view(
        0.0, "weight of edge-aware depth smoothness (0: off)", check=Number(0.0), flag="--lambda-smooth"
    )
    # Mip-NeRF 360's distortion loss in squared form between the Gaussians' centres.
    lambda_spread: float = in_sparse_view(
        0.0,
        "weight of the depth spread: each pixel's blending weights gathered at one depth (0: off)",
        check=Number(0.0),
        flag="--lambda-spread",
    )
    spread_start: float = in_sparse_view(
        0.33, "the depth spread from this fraction of the run on", check=Number(0.0, 1.0)
    )
    lambda_anisotropy: float = in_sparse_view(
        0.0,
        "weight of the penalty on Gaussians longer than anisotropy_ratio times their width (0: off)",
        check=Number(0.0),
        flag="--lambda-anisotropy",
    )
    anisotropy_ratio: float = in_sparse_view(
        10.0, "the largest max/min scale the anisotropy penalty allows", check=Number(1.0)
    )
    refiner: str | None = in_sparse_view(
        None,
        "an ONNX image-refiner folder: its cleaned, confidence-weighted virtual views supervise training",
        check=Satisfies(lambda v: v is None or isinstance(v, str), "a model folder (a string) or None"),
        flag="--refiner",
        parse=str,
    )
    lambda_refiner: float = in_sparse_view(0.5, "weight of the refiner's pseudo views", check=Number(0.0))
    refiner_every: int = in_sparse_view(10, "a pseudo view every n-th iteration", check=Whole(1))
    refiner_start: int = in_sparse_view(500, "first iteration with pseudo views", check=Whole(0))
    co_train: bool = in_sparse_view(
        False, "co-train a second field; each checks the other (CoR-GS)", check=FLAG, flag="--co-train"
    )
    lambda_coreg: float = in_sparse_view(
        1.0, "weight of the co-trained fields' agreement", check=Number(0.0), flag="--lambda-coreg"
    )
    coprune_every: int = in_sparse_view(
        500, "iterations between co-pruning rounds (0: none)", check=Whole(0), flag="--coprune-every"
    )
    coprune_distance: float = in_sparse_view(
        0.01, "co-pruning's reach, a fraction of the start's median depth", check=Number(0.0, open_low=True)
    )

    # -- learning rates and schedule
    grid_lr: float = in_schedule(5e-3, "hash grids' learning rate", check=Number(0.0, open_low=True))
    mlp_lr: float = in_schedule(5e-4, "MLPs' learning rate", check=Number(0.0, open_low=True))
    per_gaussian_language_lr: float = in_schedule(
        2.5e-3, "per-Gaussian latents' learning rate (LangSplat's)", check=Number(0.0, open_low=True)
    )
    # DashGaussian's coarse to fine in one step: it buys time, not quality.
    half_resolution_until: float = in_schedule(
        0.33,
        "fraction of the run that renders the training views at half their width and height",
        check=Number(0.0, 1.0),
        flag="--half-resolution-until",
    )
    # The language pass is detached from the geometry: skipping the half-size start saves time, not quality.
    language_start: float = in_schedule(
        0.33, "fraction of the run before the language term", check=Number(0.0, 1.0), flag="--language-start"
    )

    # -- edits of the Gaussian set (langfield.training.strategy)
    densify: bool = in_strategy(
        True, "clone, split and prune Gaussians (off: keep the initial ones)", check=FLAG, flag="--no-densify"
    )
    max_gaussians: int | None = in_strategy(
        None, "most Gaussians densification may make (default: 4 x the start)", check=Whole(1, optional=True)
    )
    # 3DGS refines from 600; from 400 (half size still) the start's transparent Gaussians go sooner.
    refine_start: int = in_strategy(300, "first densification after this iteration", check=Whole(0))
    refine_every: int = in_strategy(100, "iterations between densifications", check=Whole(1))
    refine_stop: int | None = in_strategy(
        None, "last densification iteration (default: the run's end)", check=Whole(0, optional=True)
    )
    grad_threshold: float = in_strategy(
        0.0013, "screen-space gradient that clones or splits a Gaussian", check=Number(0.0, open_low=True)
    )
    prune_opacity: float = in_strategy(
        0.01, "opacity under which densification prunes a Gaussian", check=Number(0.0, 1.0)
    )
    # Binocular-guided 3DGS's decay (0.995): Gaussians the images keep asking for recover, the rest fade.
    opacity_decay: float = in_strategy(
        0.995,
        "every opacity times this factor each iteration from opacity_decay_start (1: off)",
        check=Number(0.0, 1.0, open_low=True),
        flag="--opacity-decay",
    )
    opacity_decay_start: int = in_strategy(500, "first iteration of the opacity decay", check=Whole(0))
    carve_free_space: bool = in_strategy(
        False, "remove Gaussians in front of the stereo's surfaces", check=FLAG, flag="--carve-free-space"
    )
    carve_tolerance: float = in_strategy(0.03, "carving's relative depth tolerance", check=Number(0.0, 1.0))

    # -- language-guided outlier pruning (langfield.training.lop)
    lop: bool = in_lop(
        True, "language-guided outlier pruning (eq. 14-16; needs language)", check=FLAG, flag="--no-lop"
    )
    lop_every: int = in_lop(LOP_INTERVAL, "iterations between LOP rounds (0: none)", check=Whole(0))
    lop_gamma: int = in_lop(LOP_GAMMA, "LOP's neighbours per Gaussian (eq. 15)", check=Whole(1))
    lop_tau: float = in_lop(
        LOP_TAU, "LOP's outlier threshold (eq. 16)", check=Number(0.0, 1.0, open_low=True)
    )

    def __post_init__(self) -> None:
        check_config(self)

    @classmethod
    def from_record(cls, record: Mapping[str, Any]) -> TrainConfig:
        """The config a field.json's ``config`` or a sweep run's settings record: JSON lists read as
        tuples, settings this version no longer has dropped, later ones at their defaults."""
        known = {f.name for f in dataclasses.fields(cls)}
        values = {k: v for k, v in record.items() if k in known}
        if values.get("bounds") is not None:
            values["bounds"] = tuple(tuple(float(x) for x in row) for row in values["bounds"])
        return cls(**values)


# Each setting's `langfield train` flag, named in check_config's messages.
CONFIG_FLAGS = {f.name: f.metadata["flag"] for f in dataclasses.fields(TrainConfig) if f.metadata["flag"]}

# Settings that rule one another out: (setting, test, what it must be).
_CROSS_CHECKS = (
    ("carve_free_space", lambda cfg: not cfg.carve_free_space or cfg.init in ("auto", "dense", "depth"),
     "False unless init is 'dense' or 'depth' (it carves with their stereo)"),
)  # fmt: skip


def check_config(cfg: TrainConfig) -> None:
    """Rejects a setting no training can use, before any work: one ValueError naming the setting and
    its ``langfield train`` flag."""
    check_fields(cfg, CONFIG_FLAGS)
    for name, ok, expected in _CROSS_CHECKS:
        if not ok(cfg):
            refuse(cfg, name, expected, CONFIG_FLAGS)


def flag_of(name: str) -> str:
    """The ``langfield train`` flag of setting ``name`` (for messages), or its TrainConfig name."""
    return CONFIG_FLAGS.get(name, f"TrainConfig.{name}")


def add_train_flags(parser: argparse.ArgumentParser, names: tuple[str, ...] | None = None) -> None:
    """The flags of TrainConfig's settings (those of ``names`` only, if given), grouped as declared."""
    add_flags(parser, TrainConfig, GROUPS, names)


def config_from_flags(args: argparse.Namespace, **fixed: Any) -> TrainConfig:
    """The TrainConfig the parsed flags give: each flag that was given, the rest at their defaults
    (checked: a bad value names its flag)."""
    return TrainConfig(**{**given_flags(args, CONFIG_FLAGS), **fixed})
