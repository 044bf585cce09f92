"""What training compares its renders with, read and checked before the first iteration.

:func:`check_inputs` reads every file of the scene that training will read; :func:`language_targets`
trains the scene's autoencoder (eq. 2) and encodes each training view's masks; :func:`depth_inputs` pairs
each view's depth prior with the LAD masks; :func:`empty_space` finds what each photo shows as empty;
:class:`ViewTargets` holds one view's targets at the size it renders (and :meth:`ViewTargets.half_size`
for the coarse start).
"""

from __future__ import annotations

import copy
import hashlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from encoders.autoencoder import AutoencoderConfig, LanguageAutoencoder, train_autoencoder
from encoders.cache import read_feature_cache
from encoders.text_table import TableTextEncoder
from langfield.camera import Camera
from langfield.io.scene import Scene
from langfield.model.language import N_LEVELS
from langfield.training.config import TrainConfig, flag_of
from langfield.training.lad import LADTarget
from langfield.training.regularisers import dark_backdrop


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
    masks, the bounds, the phrase table (it must hold the canonical phrases every query is compared
    with), and whether the training views agree on having language and depth targets.

    Raises:
        ValueError: the first problem, naming the file or setting (a SceneError, FeatureCacheError).
    """
    train_names = scene.names("train")
    if not train_names:
        raise ValueError(f"{scene.root}: no training views; choose them with views= or n_views=")
    bounds = scene_bounds(scene, cfg)
    behind = [c.name for c in scene.cameras("train") if not c.faces(bounds)]
    if cfg.bounds is not None and behind:
        raise ValueError(
            f"{flag_of('bounds')}: the box lies entirely behind training view(s) {', '.join(behind)}"
        )
    if scene.text_embeddings_path is not None:  # the field will answer queries with it: read it now
        TableTextEncoder(scene.text_embeddings_path)
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
        stereo: [H, W] the start's plane-sweep z-depth, NaN where unresolved (None: no sweep ran).
    """

    camera: Camera
    image: Tensor
    coverage: Tensor | None = None
    latents: Tensor | None = None
    language_weight: Tensor | None = None
    depth: LADTarget | None = None
    depth_input: tuple[Tensor, Tensor] | None = None
    stereo: Tensor | None = None

    def half_size(self) -> ViewTargets:
        """The view at half its width and height (DashGaussian's coarse-to-fine training, Chen et al.
        2025): photo and coverage area-averaged, the per-pixel targets (latents, masks, depth prior, stereo)
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
        stereo = None if self.stereo is None else self.stereo[rows][:, cols]
        return ViewTargets(cam, image, coverage, latents, weight, depth, depth_input, stereo)


def area_resize(images: list[Tensor], cam: Camera) -> list[Tensor]:
    """Each [H, W, C] image area-averaged to ``cam``'s size (differentiable)."""
    size = (cam.height, cam.width)
    return [
        torch.nn.functional.interpolate(x.permute(2, 0, 1)[None], size=size, mode="area")[0].permute(1, 2, 0)
        for x in images
    ]


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
