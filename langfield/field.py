"""LanguageField: trained Gaussians with their neural colour field; render, save, load.

On disk (docs/format.md): ``field.safetensors`` (every tensor, no pickle; from format 2 also the codebook,
``codebook.{level}``), ``field.json`` (config, format version, bounds, training views, text-encoder
reference, timings and the checksum of the tensors file), ``gaussians.ply`` (standard 3DGS) and,
when the text encoder is a scene's phrase table, a copy of it
(``text_embeddings.npz``) so that the folder answers text queries on its own. Files are first written
completely into a staging folder beside the output folder, then moved into place with ``field.json``
last; ``field.json`` names the SHA-256 of the tensors and of the table it belongs to, so a field
interrupted half-way through a save never loads silently mixed. Loading checks field.json key by key
and the tensors against it (:mod:`langfield.io.field_meta`).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import warnings
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import Tensor, nn

from encoders.autoencoder import AutoencoderConfig, LanguageDecoder, decoder_state, load_decoder
from langfield.camera import Camera
from langfield.constants import LATENT_NORM_EPS, TEXT_TABLE_FILE
from langfield.io.field_meta import (
    LANGUAGE_DECODES,
    FieldFileError,
    FieldMeta,
    check_field_meta,
    check_tensors,
)
from langfield.io.ply import write_gaussian_ply
from langfield.io.scene import Scene, load_scene
from langfield.model import gaussians as G
from langfield.model.colour import ColorField
from langfield.model.hashgrid import HashGridConfig
from langfield.model.language import LANGUAGE_CHANNELS, LATENT_DIM, N_LEVELS, LanguageHeads
from langfield.model.reading import concept_groups, vote_entries
from langfield.query import Query, make_query
from langfield.raster import Backend, rasterize, rasterize_slots, rasterize_with_second_pass

if TYPE_CHECKING:
    from collections.abc import Sequence

    from encoders.protocols import TextEncoder

# 2: a field may carry a codebook (``codebook.{level}`` tensors, ``language.codebook`` sizes); fields
# of version 1 have none and load as they were.
# 3: a field may carry its Gaussians' registered entries (``entries``, ``language.registered``).
FORMAT_VERSION = 3
READABLE_VERSIONS = (1, 2, 3)
HARD_DEPTH_OPACITY = 0.99  # mu in eq. 7 (the paper; DNGaussian uses 0.95)


class GridFeatures(NamedTuple):
    """The colour grid read at the Gaussians' centres, shared by every render of one set of means.

    Attributes:
        corners: the cell look-up ``(rows, frac)`` of :meth:`langfield.model.hashgrid.HashGrid.corners`,
            or None where the grid was read in one walk (the numba kernels), which needs none.
        features: [N, L F] interpolated grid features (the colour MLP's view-independent input).
    """

    corners: tuple[Tensor, Tensor] | None
    features: Tensor


class Render(NamedTuple):
    """One rendered view.

    Attributes:
        rgb: [H, W, 3] colour.
        depth: [H, W] soft depth, sum_j alpha_j T_j ||p_j - o|| (eq. 8).
        alpha: [H, W] accumulated opacity.
        means2d: [N, 2] projected centres (their ``.grad`` feeds densification).
        radii: [N] pixel radii, 0 where culled.
        depth_hard: [H, W] hard depth (eq. 7) when asked for, else None.
        latents: [3, H, W, 3] rendered language latents (level, row, column, latent) when the field has
            language, else None; :meth:`LanguageField.decode` maps them to CLIP space.
        depth_spread: [H, W] when asked for, else None: ``1/2 sum_ij w_i w_j (d_i - d_j)^2`` over the
            Gaussians blended at the pixel (weights ``w = alpha T``, ``d`` their centres' distances to
            the camera), i.e. alpha^2 times the variance of the blended distances. It is 0 where one
            Gaussian, or several at one depth, make the pixel.
    """

    rgb: Tensor
    depth: Tensor
    alpha: Tensor
    means2d: Tensor
    radii: Tensor
    depth_hard: Tensor | None = None
    latents: Tensor | None = None
    depth_spread: Tensor | None = None


def _second_moment(dist: Tensor) -> tuple[Tensor, Tensor]:
    """``([N, 1] (d - c)^2, c)`` with c the median distance: the moment about one distance per view, so
    that :func:`_spread` does not cancel ~(3 m)^2 against the ~(1 cm)^2 it measures."""
    ref = dist.detach().median() if len(dist) else dist.new_zeros(())
    return (dist - ref) ** 2, ref


def _spread(first: Tensor, second: Tensor, alpha: Tensor, ref: Tensor) -> Tensor:
    """:attr:`Render.depth_spread` from the rendered distance D, the rendered moment S about ``ref`` and
    alpha: ``alpha S - (D - alpha ref)^2`` (= 1/2 sum_ij w_i w_j (d_i - d_j)^2), clamped at 0 against
    rounding."""
    centred = first - alpha * ref
    return (alpha * second - centred * centred).clamp_min(0.0)


class LanguageField(nn.Module):
    """3D Gaussians whose colour and language latents are read from hash-grid fields at their centres.

    Args:
        splats: ParameterDict with "means" [N, 3], "log_scales" [N, 3], "quats" [N, 4],
            "opacity_logits" [N, 1], and "lang" [N, 9] for the per-Gaussian language baseline.
        color: the colour field.
        meta: what field.json records (config, bounds, training views, background, timings, language).
        language: the hash-grid language heads, if the field has hash-grid language features.
        decoder: the scene's autoencoder decoder (latent -> 512-d CLIP space), if the field has language.
        codebook: per level, the [P_l, 3] unit latents of the training views' masks at that level; with
            one, a rendered latent is read as its nearest entry (:meth:`decode_levels`). None: decoded
            as it is (the paper's reading).
        entries: [N, 3] long, each Gaussian's registered codebook entry per level (the training mask it
            carries the most rendering weight on, :func:`langfield.training.aggregate.register_entries`;
            -1: none), which the 3D selection reads (:meth:`gaussian_entries`); None: not registered.

    Attributes:
        folder: the folder the field was loaded from, else None.
    """

    def __init__(
        self,
        splats: nn.ParameterDict,
        color: ColorField,
        meta: dict[str, Any],
        language: LanguageHeads | None = None,
        decoder: LanguageDecoder | None = None,
        codebook: Sequence[Tensor] | None = None,
        entries: Tensor | None = None,
    ) -> None:
        super().__init__()
        self.splats = splats
        self.color = color
        self.meta = meta  # a FieldMeta (the setter wraps a plain dict)
        self.language = language
        self.decoder = decoder
        self.codebook = codebook  # checked by the setter
        self.entries = entries  # checked by the setter
        self.folder: Path | None = None
        # The language grid may reuse the colour grid's cell look-up when both share the layout.
        self._shared_cells = language is not None and _same_cells(color.grid, language.grid)

    @property
    def codebook(self) -> list[Tensor] | None:
        """Per level, the ``[P_l, 3]`` unit latents a rendered latent is read as (None: decoded as it is)."""
        return self._codebook

    @codebook.setter
    def codebook(self, entries: Sequence[Tensor] | None) -> None:
        if entries is None:
            self._codebook = None
            self._entries = None  # registered entries index the codebook
            return
        if self.decoder is None:
            raise ValueError("codebook: a field without a language decoder cannot read latents through one")
        if len(entries) != N_LEVELS:
            raise ValueError(f"codebook: need one entry tensor per level ({N_LEVELS}), got {len(entries)}")
        self._codebook = [check_codebook_level(c, level) for level, c in enumerate(entries)]

    @property
    def entries(self) -> Tensor | None:
        """``[N, 3]`` long: each Gaussian's registered codebook entry per level (-1: none), or None."""
        return self._entries

    @entries.setter
    def entries(self, value: Tensor | None) -> None:
        if value is None:
            self._entries = None
            return
        if self.codebook is None:
            raise ValueError("entries: a field without a codebook has no entries to register Gaussians to")
        if value.dtype != torch.long or tuple(value.shape) != (self.num_gaussians, N_LEVELS):
            raise ValueError(
                f"entries: expected long [{self.num_gaussians}, {N_LEVELS}], got {value.dtype} "
                f"{tuple(value.shape)}"
            )
        for level, c in enumerate(self.codebook):
            column = value[:, level]
            if bool((column < -1).any()) or bool((column >= len(c)).any()):
                raise ValueError(f"entries: level {level} holds indices outside -1 .. {len(c) - 1}")
        self._entries = value

    def gaussian_entries(self) -> Tensor:
        """``[3, N]`` long: the codebook entry each Gaussian is read as in 3D (:meth:`Query.gaussians`):
        its registered entry, else (unregistered, or a Gaussian no training view showed on a mask) the
        nearest entry of its own latent; -1 for a zero latent."""
        with torch.no_grad():
            own = self.codebook_indices(self.gaussian_latents().transpose(0, 1))
        if self._entries is None:
            return own
        registered = self._entries.T
        return torch.where(registered >= 0, registered, own)

    @property
    def language_decode(self) -> str | None:
        """How rendered latents are read (docs/how-it-works.md): ``"vote"`` (:meth:`read_entries`),
        ``"codebook"`` (the nearest entry) or ``"continuous"`` (decoded as they are); None without
        language. Settable between ``"vote"`` and ``"codebook"``: the reading changes nothing trained."""
        if self.meta.language is None:
            return None
        if self.codebook is None:
            return "continuous"
        return "vote" if self.meta.language_decode == "vote" else "codebook"

    @language_decode.setter
    def language_decode(self, value: str) -> None:
        if value not in LANGUAGE_DECODES:
            raise ValueError(f"language_decode must be one of {LANGUAGE_DECODES}, got {value!r}")
        if self.meta.language is None:
            raise ValueError("language_decode: this field has no language")
        if (value == "continuous") != (self.codebook is None):
            raise ValueError(
                f"language_decode {value!r}: 'vote' and 'codebook' read through a codebook, 'continuous' "
                f"without one; this field has {'none' if self.codebook is None else 'one'} "
                f"(set field.codebook = None to read it continuously)"
            )
        self.meta["language"] = dict(self.meta["language"], decode=value)

    @property
    def has_language(self) -> bool:
        return self.language is not None or "lang" in self.splats

    def gaussian_latents(self, corners: tuple[Tensor, Tensor] | None = None) -> Tensor | None:
        """[N, 3, 3] language latents of every Gaussian (level, latent), or None without language.

        The hash grid reads detached positions: L_LF must not move the Gaussians (docs/how-it-works.md).
        ``corners``: the colour grid's cell look-up of the means, reused when the grids share a layout.
        """
        if "lang" in self.splats:
            return self.splats["lang"].reshape(-1, N_LEVELS, LATENT_DIM)
        if self.language is not None:
            if corners is not None and self._shared_cells:
                rows, frac = corners
                return self.language(self.splats["means"], (rows, frac.detach()))
            return self.language(self.splats["means"].detach())
        return None

    def decode(self, latents: Tensor) -> Tensor:
        """Maps latents [..., 3] to unit 512-d CLIP features [..., 512] with the scene's decoder.

        Each latent is scaled to unit length first (a zero latent stays zero). The decoder was trained
        on the encoder's unit latents; a rendered latent is a blend of them and shorter (mean norm 0.96
        on the built-in scene), off the sphere the decoder knows. LangSplat decodes it as it is;
        projected, novel-view mIoU rose by 0.03 to 0.07 on five fields of three rooms
        (docs/history/figures.md).
        """
        if self.decoder is None:
            raise ValueError("this field has no language decoder (it was trained without language features)")
        return self.decoder.decode(nn.functional.normalize(latents, dim=-1, eps=LATENT_NORM_EPS))

    def codebook_indices(self, latents: Tensor) -> Tensor:
        """``[3, ...]`` long: each latent's nearest codebook entry at its level (largest cosine); -1 for a
        zero latent, which has no direction, and at a level without entries.

        Args:
            latents: ``[3, ..., 3]`` latents of the three levels (a render's ``latents``, or the
                Gaussians' own latents moved level-first).
        """
        self._need_codebook()
        _check_levels(latents)
        index = torch.full(latents.shape[:-1], -1, dtype=torch.long, device=latents.device)
        nonzero = latents.norm(dim=-1) > LATENT_NORM_EPS
        for level, entries in enumerate(self.codebook):
            if entries.shape[0]:
                # The entries are unit length, so the largest dot product is the largest cosine.
                nearest = (latents[level].to(entries.dtype) @ entries.T).argmax(dim=-1)
                index[level] = torch.where(nonzero[level], nearest, -1)
        return index

    def codebook_features(self, level: int) -> Tensor:
        """``[P_l + 1, 512]``: the decoded codebook entries of ``level``, then the decoded zero latent
        (row -1, what :meth:`codebook_indices` gives a zero latent)."""
        entries = self._need_codebook()[level]
        return self.decode(torch.cat([entries, entries.new_zeros(1, LATENT_DIM)]))

    def _need_codebook(self) -> list[Tensor]:
        if self._codebook is None:
            raise ValueError("this field has no codebook (it was trained with --language-decode continuous)")
        return self._codebook

    def vote_gaussians(self) -> tuple[Tensor, tuple[Tensor, ...]]:
        """What a vote reads of the Gaussians in every view: the nearest entry of each one's own latents
        ``[3, N]`` and their geometry (means, rotations, scales, opacities); no gradient."""
        with torch.no_grad():
            own = self.codebook_indices(self.gaussian_latents().transpose(0, 1))
            geometry = (
                self.splats["means"].detach(),
                self.splats["quats"].detach(),
                G.scales(self.splats),
                G.opacities(self.splats).reshape(-1),
            )
        return own, geometry

    def read_entries(
        self,
        camera: Camera,
        latents: Tensor,
        alpha: Tensor,
        gaussians: tuple[Tensor, tuple[Tensor, ...]] | None = None,
    ) -> Tensor:
        """``[3, H, W]`` long: the codebook entry each pixel of a view reads at each level (-1: none).

        ``"codebook"``: the nearest entry of the pixel's rendered latent. ``"vote"``: that entry where the
        Gaussians whose own latents are nearest to its concept carry at least
        :data:`~langfield.model.reading.VOTE_SHARE` of the pixel's weight, else the entry whose Gaussians
        carry the most (:func:`langfield.model.reading.vote_entries`; it renders the entries' weights in
        the view).

        Args:
            camera: the view.
            latents, alpha: its render's ``latents`` ``[3, H, W, 3]`` and ``alpha`` ``[H, W]``.
            gaussians: :meth:`vote_gaussians`, for a caller that reads many views of an unchanged field
                (computed here when None).
        """
        codebook = self._need_codebook()
        nearest = self.codebook_indices(latents)
        if self.language_decode != "vote":
            return nearest
        own, geometry = self.vote_gaussians() if gaussians is None else gaussians
        with torch.no_grad():

            def weights(columns: Tensor, n: int) -> Tensor:
                return rasterize_slots(*geometry, columns, n, camera, backend=self.meta.backend)

            sizes = [int(c.shape[0]) for c in codebook]
            groups = [concept_groups(c) for c in codebook]
            return vote_entries(nearest, own, sizes, groups, alpha, weights)

    def decode_entries(self, index: Tensor) -> Tensor:
        """``[3, ...]`` codebook entry indices (-1: none, read as the zero latent) -> ``[3, ..., 512]``
        their decoded CLIP features (no gradient)."""
        with torch.no_grad():
            rows = [self.codebook_features(level) for level in range(N_LEVELS)]
        return torch.stack([rows[level][index[level]] for level in range(N_LEVELS)])

    def decode_levels(self, latents: Tensor) -> Tensor:
        """``[3, ..., 3]`` latents of the three levels -> ``[3, ..., 512]`` CLIP features.

        With a codebook each latent is replaced by its nearest entry (:meth:`codebook_indices`) before
        it is decoded: the scene's concepts are the training masks' features, and a rendered latent a
        few degrees off decodes to a neighbouring concept on the 3-d sphere, where they lie 6-13
        degrees apart (docs/history/figures.md, "Language in novel views"); the nearest entry is still the
        right one. The choice of entry passes no gradient. Without a codebook, :meth:`decode`.
        """
        if self.codebook is None:
            return self.decode(latents)
        return self.decode_entries(self.codebook_indices(latents))

    @property
    def num_gaussians(self) -> int:
        return int(self.splats["means"].shape[0])

    @property
    def background(self) -> Tensor:
        """[3] colour behind the Gaussians (white for scenes whose images had alpha, else black)."""
        return torch.tensor(self.meta.background, dtype=torch.float32)

    def render(
        self,
        camera: Camera,
        *,
        backend: Backend | None = None,
        hard_depth: bool = False,
        language: bool = True,
        opacity_scale: Tensor | None = None,
        background: Tensor | None = None,
        grid: GridFeatures | None = None,
        depth_spread: bool = False,
    ) -> Render:
        """Renders colour, soft depth and alpha (and optionally hard depth) from ``camera``.

        Args:
            camera: any camera.
            backend: the rasterizer backend (default: the field's).
            hard_depth: also render the hard depth of eq. 7.
            language: render the latents too (when the field has language).
            opacity_scale: [N] factors on the opacities (Gaussian dropout during training).
            background: [3] colour behind the Gaussians instead of the field's (random backgrounds in
                training).
            grid: :meth:`grid_features` of the current means, when several views are rendered from the
                same Gaussians (a training step's virtual view): the grid is then read and
                differentiated once, not once per view.
            depth_spread: also render :attr:`Render.depth_spread` (one more channel, which passes
                gradient to the geometry).
        """
        backend = backend or self.meta.backend
        means = self.splats["means"]
        quats = self.splats["quats"]
        scales = G.scales(self.splats)
        opac = G.opacities(self.splats).reshape(-1)
        keep = None
        if opacity_scale is not None:
            opac = opac * opacity_scale
            keep = (opacity_scale > 0).to(opac.dtype)  # the hard depth drops the same Gaussians
        center = torch.as_tensor(camera.center, dtype=means.dtype)
        offset = means - center
        dist = torch.sqrt((offset * offset).sum(-1, keepdim=True) + 1e-12)
        grid = self.grid_features() if grid is None else grid
        rgb = self.color.rgb(grid.features, offset / dist)
        features = [rgb, dist]
        if depth_spread:
            second, ref = _second_moment(dist)
            features.append(second)
        n_geometry = len(features) + 2  # rgb is three channels
        latents = self.gaussian_latents(grid.corners) if language else None
        if latents is not None:
            features.append(latents.reshape(-1, LANGUAGE_CHANNELS))
        features = torch.cat(features, dim=-1)
        behind = self.background if background is None else background.to(features.dtype)
        background = torch.cat([behind, torch.zeros(features.shape[1] - 3)])
        # Channels past rgb + distance (+ its second moment) -- the latents -- pass no gradient to the
        # geometry: L_LF trains only the language features, in the same rasterization pass.
        gaussians = (means, quats, scales, opac, features, camera)
        options = {"background": background, "backend": backend, "geometry_channels": n_geometry}
        depth_hard = None
        if hard_depth:
            # Eq. 7: every opacity replaced by mu, scales and rotations detached, so the hard depth's
            # gradient moves only the means. One pass with the main render on the numba backend.
            mu = torch.full_like(opac, HARD_DEPTH_OPACITY) * (1.0 if keep is None else keep)
            out, hard = rasterize_with_second_pass(*gaussians, mu, dist, **options)
            depth_hard = hard[..., 0]
        else:
            out = rasterize(*gaussians, **options)
        rendered_latents = None
        if latents is not None:
            h, w = out.image.shape[:2]
            latent_channels = out.image[..., n_geometry:]
            rendered_latents = latent_channels.reshape(h, w, N_LEVELS, LATENT_DIM).permute(2, 0, 1, 3)
        spread = _spread(out.image[..., 3], out.image[..., 4], out.alpha, ref) if depth_spread else None
        rgb, depth = out.image[..., :3], out.image[..., 3]
        return Render(rgb, depth, out.alpha, out.means2d, out.radii, depth_hard, rendered_latents, spread)

    def grid_features(self) -> GridFeatures:
        """The colour grid at the current means (see :class:`GridFeatures`): in one walk where the grid
        has it (:meth:`~langfield.model.hashgrid.HashGrid.encode`), else through the cell look-up, which
        the language grid then reuses."""
        means, grid = self.splats["means"], self.color.grid
        if grid.one_walk(means):
            return GridFeatures(None, grid.encode(means))
        corners = grid.corners(means)
        return GridFeatures(corners, grid.interpolate(*corners))

    def query(
        self,
        phrases: str | Sequence[str],
        text_encoder: TextEncoder | str | Path | None = None,
        *,
        scene: Scene | None = None,
    ) -> Query:
        """Text query of the field: ``field.query("sofa")`` or ``field.query(["sofa", "lamp"])``.

        Phrases are embedded once by the field's text encoder, or by ``text_encoder`` (an encoder, a
        ``text_embeddings.npz`` or a CLIP model folder); the :class:`~langfield.query.Query` is
        evaluated lazily per camera (a Camera, or a view of ``scene`` by name or index). See
        :func:`langfield.query.make_query`.
        """
        return make_query(self, phrases, text_encoder, scene=scene)

    @property
    def meta(self) -> FieldMeta:
        """What field.json records (:class:`~langfield.io.field_meta.FieldMeta`)."""
        return self._meta

    @meta.setter
    def meta(self, value: dict[str, Any]) -> None:
        self._meta = value if isinstance(value, FieldMeta) else FieldMeta(value)

    def trained_scene(self, path: str | Path | None = None, remedy: str = "pass the scene folder") -> Scene:
        """The scene the field was trained on (``path`` if given, else the folder ``field.json``
        records), loaded as for training: with the resolution and split recorded in ``scene_args``.

        Raises:
            ValueError: no ``path`` and the field records none (the message ends with ``remedy``).
        """
        where = path or self.meta.scene
        if not where:
            source = f"{self.folder}/field.json" if self.folder is not None else "the field"
            raise ValueError(f"{source} names no scene; {remedy}")
        return load_scene(where, **self.meta.scene_args)

    def select(self, index: Tensor) -> LanguageField:
        """The field restricted to the Gaussians at ``index`` (``[K]`` long): the same colour and
        language fields, decoder and codebook, a copy of the meta; the selected splats are detached."""
        splats = nn.ParameterDict(
            {k: nn.Parameter(v.detach()[index], requires_grad=False) for k, v in self.splats.items()}
        )
        entries = None if self.entries is None else self.entries[index]
        return LanguageField(
            splats, self.color, dict(self.meta), self.language, self.decoder, self.codebook, entries
        )

    def export_ply(self, path: str | Path, index: Tensor | None = None) -> Path:
        """Writes the Gaussians (those at ``index``, default all) as a standard 3DGS PLY
        (:mod:`langfield.io.ply`), atomically; the colour field is baked into the degree-0 coefficient at
        each centre, clipped to [0, 1]. Missing parent folders are made."""
        splats = {k: v.detach() for k, v in self.splats.items()}
        if index is not None:
            splats = {k: v[index] for k, v in splats.items()}
        with torch.no_grad():
            rgb = self.color.bake_dc(splats["means"]).numpy()
            quats = G.quats_normalized(splats).numpy()
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_gaussian_ply(
            path,
            splats["means"].numpy(),
            np.clip(rgb, 0.0, 1.0),
            splats["opacity_logits"].numpy(),
            splats["log_scales"].numpy(),
            quats,
        )
        return path

    # ------------------------------------------------------------------ persistence

    def state_tensors(self) -> dict[str, Tensor]:
        tensors = {f"splats.{k}": v.detach().contiguous() for k, v in self.splats.items()}
        tensors.update({f"color.{k}": v.detach().contiguous() for k, v in self.color.state_dict().items()})
        if self.language is not None:
            tensors.update(
                {f"language.{k}": v.detach().contiguous() for k, v in self.language.state_dict().items()}
            )
        if self.decoder is not None:
            tensors.update({f"decoder.{k}": v for k, v in decoder_state(self.decoder).items()})
        for level, entries in enumerate(self.codebook or []):
            tensors[f"codebook.{level}"] = entries.contiguous()
        if self.entries is not None:
            tensors["entries"] = self.entries.contiguous()
        return tensors

    def save(self, out: str | Path, *, overwrite: bool = False) -> Path:
        """Writes field.safetensors, field.json and gaussians.ply (and the phrase table) into ``out``.

        Every file is first written completely into a staging folder beside ``out``: a new folder is
        then renamed into place whole, and an existing field is replaced file by file with field.json
        last, so an interrupted save leaves the old field loadable, or the new one.

        Args:
            out: the field folder.
            overwrite: replace a field already in ``out`` (``langfield train --force``); else that is
                an error and nothing is written.

        Raises:
            FileExistsError: ``out`` is a file, or holds a field and ``overwrite`` is False.
        """
        out = Path(out)
        check_output_folder(out, overwrite)
        out.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
        try:
            table = self._write_files(staging)
            if not out.exists():
                os.rename(staging, out)
                return out
            names = [p.name for p in staging.iterdir() if p.name != "field.json"]
            for name in names + ["field.json"]:
                os.replace(staging / name, out / name)
            if table is None and (out / TEXT_TABLE_FILE).exists():
                (out / TEXT_TABLE_FILE).unlink()  # an older field's table, which this field does not use
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        return out

    def _write_files(self, folder: Path) -> Path | None:
        """Writes the field's files into an empty ``folder``; returns the phrase table copied, if any."""
        save_file(self.state_tensors(), str(folder / "field.safetensors"))
        digest = _sha256(folder / "field.safetensors")
        self.export_ply(folder / "gaussians.ply")
        meta = dict(
            self.meta, format_version=FORMAT_VERSION, num_gaussians=self.num_gaussians, tensors_sha256=digest
        )
        meta.pop("text_table_sha256", None)
        if meta.get("language"):  # what the saved tensors hold, whatever the meta said before
            codebook = None if self.codebook is None else [int(c.shape[0]) for c in self.codebook]
            meta["language"] = dict(
                meta["language"],
                codebook=codebook,
                decode=self.language_decode,
                registered=self.entries is not None,
            )
        table = self._text_table()
        if table is not None:
            shutil.copyfile(table, folder / TEXT_TABLE_FILE)
            meta["text_table_sha256"] = _sha256(folder / TEXT_TABLE_FILE)
        (folder / "field.json").write_text(json.dumps(meta, indent=2, default=_json_default))
        return table

    def _text_table(self) -> Path | None:
        """The phrase table to copy beside field.json: this field's copy if it was loaded with one,
        else the table ``meta["text_encoder"]`` names; None if the encoder is not a table."""
        ref = self.meta.text_encoder
        if not ref or ref.get("kind") != "table":
            return None
        if self.folder is not None and (self.folder / TEXT_TABLE_FILE).is_file():
            return self.folder / TEXT_TABLE_FILE
        if Path(ref["path"]).is_file():
            return Path(ref["path"])
        warnings.warn(
            f"{ref['path']}: the field's phrase table is missing, so the saved field cannot answer text "
            f"queries without a text encoder given",
            stacklevel=3,
        )
        return None

    @classmethod
    def load(cls, out: str | Path) -> LanguageField:
        """Loads a field written by :meth:`save`.

        Raises:
            FileNotFoundError: ``out`` or one of its files is missing.
            FieldFileError: a file is damaged or disagrees with field.json; the message names the file
                and the key.
        """
        out = Path(out)
        meta_path, tensors_path = out / "field.json", out / "field.safetensors"
        if not out.is_dir():
            raise FileNotFoundError(f"{out}: not a field folder (no such folder)")
        for path in (meta_path, tensors_path):
            if not path.is_file():
                raise FileNotFoundError(f"{path}: missing; is {out} a folder written by `langfield train`?")
        try:
            meta = json.loads(meta_path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise FieldFileError(f"{meta_path}: not valid JSON ({err})") from err
        meta = FieldMeta(check_field_meta(meta, meta_path, READABLE_VERSIONS))
        if meta.tensors_sha256 and meta.tensors_sha256 != _sha256(tensors_path):
            raise FieldFileError(
                f"{tensors_path}: checksum differs from {meta_path}; the save was interrupted"
            )
        table_path = out / TEXT_TABLE_FILE
        if meta.text_table_sha256 and table_path.is_file():
            if meta.text_table_sha256 != _sha256(table_path):
                raise FieldFileError(
                    f"{table_path}: checksum differs from {meta_path}; the save was interrupted"
                )
        try:
            tensors = load_file(str(tensors_path))
        except Exception as err:  # safetensors raises its own error types for a damaged header
            raise FieldFileError(f"{tensors_path}: not a readable safetensors file ({err})") from err
        color = build_color_field(meta)
        language = decoder = None
        spec = meta.language
        if spec:
            language = build_language_heads(meta) if spec["features"] == "hashgrid" else None
            try:
                decoder = LanguageDecoder(autoencoder_config(spec))
            except (TypeError, ValueError) as err:
                raise FieldFileError(f"{meta_path}: language.autoencoder: {err}") from err
        sizes = (spec or {}).get("codebook")
        expected = _expected_shapes(tensors, color, language, decoder)
        expected.update({f"codebook.{level}": (size, LATENT_DIM) for level, size in enumerate(sizes or [])})
        registered = bool((spec or {}).get("registered"))
        if registered:
            expected["entries"] = (expected["splats.means"][0], N_LEVELS)
        check_tensors(tensors, expected, tensors_path, meta_path)
        splats = nn.ParameterDict(
            {k.split(".", 1)[1]: nn.Parameter(v) for k, v in tensors.items() if k.startswith("splats.")}
        )
        color.load_state_dict(_prefixed(tensors, "color"))
        if language is not None:
            language.load_state_dict(_prefixed(tensors, "language"))
        if decoder is not None:
            decoder = load_decoder(_prefixed(tensors, "decoder"), decoder.cfg)
        codebook = None if sizes is None else [tensors[f"codebook.{level}"] for level in range(len(sizes))]
        entries = tensors["entries"] if registered else None
        try:
            field = cls(splats, color, meta, language, decoder, codebook, entries)
        except ValueError as err:
            raise FieldFileError(f"{tensors_path}: {err}") from err
        field.folder = out
        # A loaded field is for rendering and querying: its renders carry no autograd graph (they are
        # plain tensors, `.numpy()` works). `field.requires_grad_(True)` makes it trainable again.
        return field.requires_grad_(False)

    def field_bytes(self) -> int:
        """Bytes of all tensors of the field."""
        return sum(t.numel() * t.element_size() for t in self.state_tensors().values())


# How far from unit length a codebook entry may be (entries are kept as given: normalising again would
# move some by a bit, and a saved field must read back exactly).
CODEBOOK_NORM_TOLERANCE = 1e-4


def check_codebook_level(entries: Tensor, level: int) -> Tensor:
    """One level's codebook as float32 ``[P, 3]`` unit latents (P may be 0: a level without masks)."""
    entries = torch.as_tensor(entries).detach().to(torch.float32)
    if entries.dim() != 2 or entries.shape[1] != LATENT_DIM:
        raise ValueError(f"codebook[{level}]: expected [P, {LATENT_DIM}] latents, got {tuple(entries.shape)}")
    norms = entries.norm(dim=-1)
    if not bool(torch.isfinite(entries).all()) or bool(((norms - 1).abs() > CODEBOOK_NORM_TOLERANCE).any()):
        raise ValueError(f"codebook[{level}]: entries must be finite unit latents (the encoder's output)")
    return entries


def _check_levels(latents: Tensor) -> None:
    if latents.dim() < 2 or latents.shape[0] != N_LEVELS or latents.shape[-1] != LATENT_DIM:
        raise ValueError(
            f"expected latents [{N_LEVELS}, ..., {LATENT_DIM}] (level first), got {tuple(latents.shape)}"
        )


def check_output_folder(out: Path, overwrite: bool) -> None:
    """Whether a field may be written to ``out``: a new folder, an existing folder without a field, or
    (``overwrite``) one with a field. Checked before training, so no work is spent on a field that
    cannot be saved.

    Raises:
        FileExistsError: ``out`` is a file, or holds a field and ``overwrite`` is False.
        NotADirectoryError: a parent of ``out`` is a file.
        PermissionError: the folder that would hold ``out`` cannot be written.
    """
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: is a file, not a folder for the field")
    if (out / "field.json").exists() and not overwrite:
        raise FileExistsError(f"{out}: holds a field already; pass --force (overwrite=True) to replace it")
    parent = next((p for p in [out, *out.parents] if p.exists()), Path("."))
    if not parent.is_dir():
        raise NotADirectoryError(f"{parent}: is a file, so the field folder {out} cannot be made")
    if not os.access(parent, os.W_OK):
        raise PermissionError(f"{parent}: cannot write there")


def _expected_shapes(
    tensors: dict[str, Tensor],
    color: ColorField,
    language: LanguageHeads | None,
    decoder: LanguageDecoder | None,
) -> dict[str, tuple[int, ...]]:
    """Every tensor the field described by field.json has, with its shape (N from the means)."""
    means = tensors.get("splats.means")
    n = int(means.shape[0]) if means is not None and means.dim() == 2 else 0
    shapes: dict[str, tuple[int, ...]] = {
        "splats.means": (n, 3),
        "splats.log_scales": (n, 3),
        "splats.quats": (n, 4),
        "splats.opacity_logits": (n, 1),
    }
    if decoder is not None and language is None:
        shapes["splats.lang"] = (n, LANGUAGE_CHANNELS)
    for prefix, module in (("color", color), ("language", language), ("decoder", decoder)):
        if module is not None:
            inner = module.decoder if prefix == "decoder" else module
            shapes.update({f"{prefix}.{k}": tuple(v.shape) for k, v in inner.state_dict().items()})
    return shapes


def build_color_field(meta: FieldMeta) -> ColorField:
    """A ColorField of the shape recorded in ``meta.color_field``."""
    spec = meta.color_field
    return ColorField(
        HashGridConfig(**spec["grid"]),
        torch.tensor(spec["center"], dtype=torch.float32),
        torch.tensor(spec["half_extent"], dtype=torch.float32),
        hidden=spec["hidden"],
        n_freqs=spec["n_freqs"],
    )


def _same_cells(a, b) -> bool:
    """Whether two hash grids find the same table rows for every point (configs may differ in features)."""
    return (
        a.cfg.n_levels == b.cfg.n_levels
        and a.cfg.log2_table_size == b.cfg.log2_table_size
        and torch.equal(a.resolution, b.resolution)
        and torch.equal(a.center, b.center)
        and torch.equal(a.half_extent, b.half_extent)
    )


def build_language_heads(meta: FieldMeta) -> LanguageHeads:
    """Hash-grid language heads of the shape recorded in ``meta`` (they share the colour grid's box)."""
    spec, box = meta.language, meta.color_field
    return LanguageHeads(
        HashGridConfig(**spec["grid"]),
        torch.tensor(box["center"], dtype=torch.float32),
        torch.tensor(box["half_extent"], dtype=torch.float32),
        hidden=spec["hidden"],
    )


def autoencoder_config(spec: dict[str, Any]) -> AutoencoderConfig:
    """The AutoencoderConfig recorded in field.json (JSON lists back to tuples)."""
    return AutoencoderConfig(
        **{k: tuple(v) if isinstance(v, list) else v for k, v in spec["autoencoder"].items()}
    )


def _prefixed(tensors: dict[str, Tensor], prefix: str) -> dict[str, Tensor]:
    return {k.split(".", 1)[1]: v for k, v in tensors.items() if k.startswith(prefix + ".")}


def color_field_spec(grid: HashGridConfig, center, half_extent, hidden: int, n_freqs: int) -> dict[str, Any]:
    return {
        "grid": asdict(grid),
        "center": [float(v) for v in np.asarray(center).reshape(3)],
        "half_extent": [float(v) for v in np.broadcast_to(np.asarray(half_extent, dtype=float), (3,))],
        "hidden": hidden,
        "n_freqs": n_freqs,
    }


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.ndarray, np.generic)):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to field.json")
