"""Text queries of a trained field: relevance maps, masks and 3D selections (docs/how-it-works.md).

``field.query("sofa")`` embeds the phrase (and the canonical phrases ``object``, ``things``, ``stuff``,
``texture``) once with the field's text encoder and returns a :class:`Query`, evaluated lazily per
camera. Per pixel, each level's rendered latent is decoded to CLIP space (through the field's codebook
when it has one) and scored by LERF's relevancy (:func:`querying.relevancy.relevancy`); masks follow
LangSplat's evaluation (:func:`querying.relevancy.relevancy_mask`). A 3D selection scores every
Gaussian's own latents the same way, so an object can be exported as a PLY or rendered alone.

Reading a latent. A field trained with a codebook (``--language-decode vote``, the default, or
``codebook``) reads each pixel as one of its level's training-mask latents: by vote among the entries of
the Gaussians that render it (:meth:`langfield.field.LanguageField.read_entries`), or as the nearest
entry of its rendered latent (:meth:`~langfield.field.LanguageField.decode_levels`). A query decodes
those few dozen entries once, scores them, and looks each pixel's relevancy up by its entry, which is
exact.

A field read continuously (``--language-decode continuous``, the paper's reading) decodes every latent.
Decoding a 160x120 view exactly (3 x 19,200 latents through the 3-16-...-512 decoder, about 240k
multiply-adds each, 28 GFLOP) takes over half a second on two cores. A query instead looks the pixels'
latents up in a lattice over the latent cube ``[-LATTICE_RADIUS, LATTICE_RADIUS]^3``:

- once per field (cached with its decoder), the lattice points are decoded up to the decoder's last
  hidden layer; their last-layer outputs ``u`` are kept as the hidden activations and ``|u|^2``;
- once per query, the projections ``e_k . u`` on the unit text embeddings follow by one small matrix
  product;
- per view, the projections and ``|u|^2`` are interpolated trilinearly at each pixel's latent
  (``grid_sample``) and give the cosines ``e_k . u / |u|``, hence the relevancy.

The decoder is a ReLU network, so ``u`` is piecewise linear in the latent and the projections are exact
inside a cell that one linear piece covers; elsewhere the error is measured against the exact decode
(``exact=True``, which the evaluation uses) in tests/test_query.py. Latents are read at unit length, as
``LanguageField.decode`` reads them, so every one lies inside the lattice's cube.

Per view, a query rasterizes only the nine latent channels, with every Gaussian's latents computed
once per query (they do not depend on the camera); a field read by vote then renders one channel per
codebook entry its Gaussians carry (:mod:`langfield.model.reading`).

Example:
    >>> field = langfield.LanguageField.load("out/")  # doctest: +SKIP
    >>> q = field.query("sofa")  # doctest: +SKIP
    >>> q.mask("test_000").shape, q.level("test_000")  # doctest: +SKIP
    (torch.Size([120, 160]), 2)
    >>> q.export_ply("sofa.ply")  # doctest: +SKIP
"""

from __future__ import annotations

import math
import weakref
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from encoders.protocols import TextEncoder, check_phrases
from encoders.text_table import TableTextEncoder
from langfield.camera import Camera
from langfield.constants import LATENT_NORM_EPS, TEXT_TABLE_FILE
from langfield.model import gaussians as G
from langfield.model.language import LANGUAGE_CHANNELS, LATENT_DIM, N_LEVELS
from langfield.raster import rasterize
from querying.relevancy import (
    CANONICAL_PHRASES,
    EMBEDDING_EPS,
    MASK_THRESHOLD,
    TEMPERATURE,
    normalize_map,
    relevancy,
    relevancy_mask,
)

if TYPE_CHECKING:
    from langfield.field import LanguageField, Render
    from langfield.io.scene import Scene

__all__ = [
    "DECODE_CHUNK",
    "EMPTY_ALPHA",
    "LATTICE_RADIUS",
    "LATTICE_SIZE",
    "MATCH_RELEVANCY",
    "EmptySelectionError",
    "Query",
    "QueryView",
    "Selection",
    "fill_empty",
    "make_query",
    "text_encoder_for",
]

# Lattice points per axis, and the half-width of the latent cube they cover. Latents are read at unit
# length, as field.decode reads them, well inside the cube.
# 49 points (spacing 0.0625) cost about 75k decoded points, about a second, once per field.
LATTICE_SIZE = 49
LATTICE_RADIUS = 1.5
# Latents decoded per batch (bounds the [chunk, 512] intermediate to 64 MB).
DECODE_CHUNK = 1 << 15
# A phrase is *found* only where its relevancy beats the canonical phrases: relevancy 0.5 means "as
# similar as the closest of object / things / stuff / texture" (LERF), and 0.55 asks for a cosine
# margin of 0.02 over it (sigmoid(10 x 0.02)), beyond rounding. LangSplat's min-max normalised mask is
# never empty, so without this floor every phrase would "find" something.
MATCH_RELEVANCY = 0.55
# Pixels the field leaves nearly empty (rendered opacity below this) show the background, whose latent
# is 0; the decoder maps 0 to an arbitrary feature (its biases), often close to the scene's mean, which
# would light such pixels up for many phrases. :func:`fill_empty` takes them out of the maps.
EMPTY_ALPHA = 0.5

CameraKey = Camera | str | int


class QueryView(NamedTuple):
    """A query evaluated in one view. For a query of one phrase (``field.query("sofa")``) the phrase
    axis ``Q`` is absent; for a list of phrases it comes first.

    Attributes:
        relevance: ``[Q, H, W]`` relevancy in [0, 1] at the chosen level.
        mask: ``[Q, H, W]`` bool, LangSplat's mask (:func:`querying.relevancy.relevancy_mask`).
        level: ``[Q]`` long, the chosen level (0 subpart, 1 part, 2 whole).
        normalized: ``[Q, H, W]`` the chosen level's smoothed map stretched to [0, 1] (what the mask
            thresholds; the clearest heat map).
        maps: ``[Q, 3, H, W]`` relevancy of every level, empty pixels filled (:func:`fill_empty`).
        score: ``[Q]`` the highest relevancy at the chosen level.
        found: ``[Q]`` bool, ``score > MATCH_RELEVANCY`` and the mask is not empty.
    """

    relevance: Tensor
    mask: Tensor
    level: Tensor
    normalized: Tensor
    maps: Tensor
    score: Tensor
    found: Tensor


class Selection(NamedTuple):
    """The Gaussians that match one phrase (:meth:`Query.gaussians`).

    Attributes:
        indices: ``[K]`` long, ascending indices into the field's Gaussians; empty when nothing matches.
        scores: ``[K]`` relevancy of those Gaussians at the chosen level.
        level: the chosen level (0 subpart, 1 part, 2 whole).
        best: the highest relevancy of any Gaussian at that level.
    """

    indices: Tensor
    scores: Tensor
    level: int
    best: float


class EmptySelectionError(ValueError):
    """No Gaussian matches the phrase(s), so there is nothing to export or render."""


def fill_empty(maps: Tensor, alpha: Tensor, threshold: float = EMPTY_ALPHA) -> Tensor:
    """Gives the pixels the field leaves empty the lowest relevancy of the covered pixels of each map.

    They then never join a mask nor attract the localization point, and the min-max normalisation of
    LangSplat's mask pipeline runs over the covered pixels alone, as on a scene without background.

    Args:
        maps: ``[..., H, W]`` relevancy maps.
        alpha: ``[H, W]`` rendered opacity.
        threshold: pixels with ``alpha < threshold`` are empty (:data:`EMPTY_ALPHA`).

    Returns:
        ``[..., H, W]`` maps; unchanged where no pixel, or every pixel, is empty.
    """
    empty = alpha < threshold
    if not bool(empty.any()) or bool(empty.all()):
        return maps
    lowest = maps.masked_fill(empty, float("inf")).flatten(-2).amin(dim=-1)[..., None, None]
    return torch.where(empty, lowest, maps)


# ---------------------------------------------------------------- text encoder


def text_encoder_for(
    field: LanguageField, text_encoder: TextEncoder | str | Path | None = None
) -> TextEncoder:
    """The text encoder that embeds phrases in the space of ``field``'s language features.

    In order: ``text_encoder`` if given (an encoder, a ``text_embeddings.npz`` file, or a CLIP model
    folder from ``langfield export clip``); else the reference in ``field.meta.text_encoder``:

    - ``{"kind": "table", "path": ...}``: the scene's phrase table. A saved field keeps a copy beside
      field.json (:data:`langfield.constants.TEXT_TABLE_FILE`), used first; else the recorded path.
    - ``{"kind": "clip-onnx", "path": ...}``: an ONNX CLIP model folder (``OnnxClipEncoder``).

    A field that records none falls back to the ``text_embeddings.npz`` of the scene it was trained on.

    Raises:
        ValueError: no encoder can be found; the message says how to give one.
    """
    if text_encoder is not None and not isinstance(text_encoder, (str, Path)):
        return text_encoder
    if text_encoder is not None:
        return _encoder_from_path(Path(text_encoder))
    ref = field.meta.text_encoder
    if ref is None:
        scene = field.meta.scene
        table = Path(scene) / TEXT_TABLE_FILE if scene else None
        if table is not None and table.is_file():
            return TableTextEncoder(table)
        raise ValueError(
            "the field records no text encoder and its scene has no text_embeddings.npz; give one "
            "(a text_embeddings.npz file or a CLIP model folder from `langfield export clip`)"
        )
    kind, path = ref.get("kind"), ref.get("path")
    if kind == "table":
        copy = field.folder / TEXT_TABLE_FILE if field.folder is not None else None
        return TableTextEncoder(copy if copy is not None and copy.is_file() else path)
    if kind == "clip-onnx":
        from encoders.onnx_clip import OnnxClipEncoder

        return OnnxClipEncoder(path)
    raise ValueError(f"field.json: unknown text encoder kind {kind!r} (expected 'table' or 'clip-onnx')")


def _encoder_from_path(path: Path) -> TextEncoder:
    if path.is_dir():
        from encoders.onnx_clip import OnnxClipEncoder

        return OnnxClipEncoder(path)
    return TableTextEncoder(path)


# ---------------------------------------------------------------- queries


def make_query(
    field: LanguageField,
    phrases: str | Sequence[str],
    text_encoder: TextEncoder | str | Path | None = None,
    *,
    scene: Scene | None = None,
) -> Query:
    """Embeds ``phrases`` and the canonical phrases once; see :meth:`LanguageField.query`.

    Args:
        field: a field with language features.
        phrases: one phrase (results without a phrase axis) or a list of phrases (phrase axis first).
        text_encoder: see :func:`text_encoder_for`; default the field's own.
        scene: resolves cameras given by view name or index; default the scene recorded in field.json,
            loaded when first needed.

    Raises:
        ValueError: the field has no language features, or no text encoder is found.
        encoders.text_table.UnknownPhraseError: a phrase the phrase table does not hold (the message
            names the phrase and the table's file).
    """
    if field.decoder is None or not field.has_language:
        raise ValueError("this field has no language features (trained without language); cannot query")
    single = isinstance(phrases, str)
    phrase_list = check_phrases([phrases] if single else phrases, "query")
    if not phrase_list:
        raise ValueError("query: no phrases given")
    encoder = text_encoder_for(field, text_encoder)
    embeddings = np.asarray(encoder.encode_text(phrase_list + list(CANONICAL_PHRASES)), dtype=np.float32)
    shared = _Shared(field, phrase_list, torch.from_numpy(embeddings), scene)
    return Query(shared, list(range(len(phrase_list))), single)


class _DecoderLattice:
    """The phrase-independent part of the lattice (module docstring): for the lattice points that a
    latent in the cube can be interpolated from, the decoder's last hidden activations and ``|u|^2``.

    The activations are kept in float16 (half the memory: about 40 MB for 75k points of 256; their
    relative rounding, 5e-4, is far below the interpolation error).
    """

    def __init__(self, decoder: nn.Sequential, size: int = LATTICE_SIZE, radius: float = LATTICE_RADIUS):
        self.size, self.radius = size, radius
        axis = torch.linspace(-radius, radius, size)
        zd, zh, zw = torch.meshgrid(axis, axis, axis, indexing="ij")
        points = torch.stack([zw, zh, zd], dim=-1)  # [d, h, w] holds latent (z0, z1, z2), as grid_sample
        # A latent of norm <= radius is read from corners within one cell diagonal of it; the cube's
        # corners beyond that are never read, so they are not decoded.
        self.needed = points.norm(dim=-1) <= radius * (1.0 + math.sqrt(3.0) * 2.0 / (size - 1))
        hidden, norm2 = [], []
        for chunk in points[self.needed].split(DECODE_CHUNK):
            h = decoder[:-1](chunk)
            u = decoder[-1](h)
            hidden.append(h.half())
            norm2.append((u * u).sum(-1))
        self.hidden = torch.cat(hidden)  # [M, hidden] float16
        self.norm2 = torch.cat(norm2)  # [M]

    def channels(self, last: nn.Linear, unit_embeddings: Tensor) -> Tensor:
        """``[1, K + 1, S, S, S]``: ``e_k . u`` for the K unit embeddings, then ``|u|^2``."""
        k, s = unit_embeddings.shape[0], self.size
        weights = last.weight.T @ unit_embeddings.T  # [hidden, K]
        projection = torch.cat([h.float() @ weights for h in self.hidden.split(DECODE_CHUNK)])
        projection += last.bias @ unit_embeddings.T
        channels = torch.zeros(k + 1, s, s, s)
        channels[:k, self.needed] = projection.T
        channels[k, self.needed] = self.norm2
        return channels[None]


# One lattice per decoder (a field's decoder is fixed after training), freed with the decoder.
_LATTICES: weakref.WeakKeyDictionary[nn.Module, _DecoderLattice] = weakref.WeakKeyDictionary()


def _decoder_lattice(field: LanguageField) -> _DecoderLattice:
    if field.decoder not in _LATTICES:
        with torch.no_grad():
            _LATTICES[field.decoder] = _DecoderLattice(field.decoder.decoder)
    return _LATTICES[field.decoder]


class _Shared:
    """What the phrases of one ``field.query`` call share: embeddings, the Gaussians' latents, the
    lattice channels, the last view's latents, the scene and the Gaussians' relevancy."""

    def __init__(self, field: LanguageField, phrases: list[str], embeddings: Tensor, scene: Scene | None):
        self.field = field
        self.phrases = phrases
        self.embeddings = embeddings  # [Q + C, D]: the phrases, then the canonical phrases
        self.scene = scene
        self.gaussians: tuple[Tensor, ...] | None = None
        self.channels: Tensor | None = None
        self.last_render: tuple[Camera, Tensor, Tensor] | None = None
        self.last_entries: tuple[Camera, Tensor] | None = None
        self.voters: tuple[Tensor, tuple[Tensor, ...]] | None = None  # LanguageField.vote_gaussians
        self.gaussian_rel: Tensor | None = None
        self.code_tables: list[Tensor] | None = None

    @property
    def n_phrases(self) -> int:
        return len(self.phrases)

    def camera(self, key: CameraKey) -> Camera:
        if isinstance(key, Camera):
            return key
        if self.scene is None:
            if not self.field.meta.scene:
                raise ValueError(f"camera {key!r}: the field records no scene; pass a Camera or scene=")
            self.scene = self.field.trained_scene()
        return self.scene.camera(key)

    def gaussian_relevancy(self) -> Tensor:
        """``[Q, 3, N]`` every phrase's relevancy at each Gaussian, per level: with a codebook, of the entry
        it is read as (:meth:`LanguageField.gaussian_entries`: its registered entry, else its latent's
        nearest), else of its latents decoded exactly; computed once."""
        if self.gaussian_rel is None:
            with torch.no_grad():
                if self.field.codebook is not None:
                    self.gaussian_rel = self.entry_relevancy(self.field.gaussian_entries())
                else:
                    latents = self.field.gaussian_latents()  # [N, 3, 3]
                    self.gaussian_rel = self.exact_relevancy(latents.transpose(0, 1))
        return self.gaussian_rel

    def gaussian_inputs(self) -> tuple[Tensor, ...]:
        """Means, rotations, scales, opacities and ``[N, 9]`` latents of the Gaussians, computed once:
        none depends on the camera."""
        if self.gaussians is None:
            splats = self.field.splats
            with torch.no_grad():
                latents = self.field.gaussian_latents().reshape(-1, LANGUAGE_CHANNELS)
                self.gaussians = (
                    splats["means"].detach(),
                    splats["quats"].detach(),
                    G.scales(splats),
                    G.opacities(splats).reshape(-1),
                    latents,
                )
        return self.gaussians

    def lattice_channels(self) -> tuple[_DecoderLattice, Tensor]:
        """The field's lattice and this query's ``[1, K + 1, S, S, S]`` channels (built when first asked)."""
        lattice = _decoder_lattice(self.field)
        if self.channels is None:
            with torch.no_grad():
                unit = F.normalize(self.embeddings, dim=-1, eps=EMBEDDING_EPS)
                self.channels = lattice.channels(self.field.decoder.decoder[-1], unit)
        return lattice, self.channels

    def render(self, camera: Camera) -> tuple[Tensor, Tensor]:
        """``[3, H, W, 3]`` rendered latents and ``[H, W]`` opacity, as ``field.render(camera)`` gives
        them; only the latent channels are rasterized, and the last view is kept for the phrases."""
        if self.last_render is not None and self.last_render[0] is camera:
            return self.last_render[1:]
        with torch.no_grad():
            backend = self.field.meta.backend
            out = rasterize(*self.gaussian_inputs(), camera, backend=backend)  # background 0, as render()
        rendered = out.image.reshape(*out.image.shape[:2], N_LEVELS, LATENT_DIM).permute(2, 0, 1, 3)
        self.last_render = (camera, rendered, out.alpha)
        return rendered, out.alpha

    def entries(self, camera: Camera) -> Tensor:
        """``[3, H, W]`` the codebook entries the view's pixels read (:meth:`LanguageField.read_entries`);
        the last view's are kept."""
        if self.last_entries is not None and self.last_entries[0] is camera:
            return self.last_entries[1]
        latents, alpha = self.render(camera)
        if self.voters is None and self.field.language_decode == "vote":
            self.voters = self.field.vote_gaussians()
        with torch.no_grad():
            index = self.field.read_entries(camera, latents, alpha, self.voters)
        self.last_entries = (camera, index)
        return index

    def entry_relevancy(self, index: Tensor) -> Tensor:
        """``[3, ...]`` codebook entry indices (level first; -1 the zero latent) -> ``[Q, 3, ...]`` the
        relevancy of the decoded entries, looked up."""
        tables = self.codebook_tables()
        return torch.stack([tables[level][:, index[level]] for level in range(N_LEVELS)], dim=1)

    def codebook_tables(self) -> list[Tensor]:
        """Per level, ``[Q, P_l + 1]`` relevancy of the decoded codebook entries, then of the zero latent
        (:meth:`LanguageField.codebook_features`); computed once per query."""
        if self.code_tables is None:
            q = self.n_phrases
            with torch.no_grad():
                self.code_tables = [
                    relevancy(self.field.codebook_features(level), self.embeddings[:q], self.embeddings[q:])
                    for level in range(N_LEVELS)
                ]
        return self.code_tables

    def exact_relevancy(self, latents: Tensor) -> Tensor:
        """``[3, ..., 3]`` latents (level first) -> ``[Q, 3, ...]`` relevancy of the decoded latents: with
        a codebook each latent's nearest entry, whose relevancy is looked up (the same values as
        decoding it), else every latent decoded (in chunks)."""
        if self.field.codebook is not None:
            return self.entry_relevancy(self.field.codebook_indices(latents))
        flat = latents.reshape(-1, latents.shape[-1])
        q = self.n_phrases
        out = torch.empty(q, flat.shape[0])
        with torch.no_grad():
            for start in range(0, flat.shape[0], DECODE_CHUNK):
                decoded = self.field.decode(flat[start : start + DECODE_CHUNK])
                out[:, start : start + DECODE_CHUNK] = relevancy(
                    decoded, self.embeddings[:q], self.embeddings[q:]
                )
        return out.reshape(q, *latents.shape[:-1])

    def lattice_relevancy(self, latents: Tensor) -> Tensor:
        """``[L, H, W, 3]`` latents -> ``[Q, L, H, W]`` relevancy by the lattice (module docstring); a
        field with a codebook needs no lattice: its look-up is exact and as fast."""
        if self.field.codebook is not None:
            return self.exact_relevancy(latents)
        lattice, channels = self.lattice_channels()
        with torch.no_grad():
            latents = F.normalize(latents, dim=-1, eps=LATENT_NORM_EPS)  # as field.decode reads them
            grid = (latents / lattice.radius).clamp(-1.0, 1.0)[None]
            values = F.grid_sample(channels, grid, mode="bilinear", align_corners=True)[0]
            cosines = values[:-1] / values[-1:].clamp_min(EMBEDDING_EPS**2).sqrt()
            # relevancy = min_c sigmoid(t (s_q - s_c)) = sigmoid(t (s_q - max_c s_c)), LERF sec. 3.4
            q = self.n_phrases
            rel = torch.sigmoid(TEMPERATURE * (cosines[:q] - cosines[q:].amax(dim=0, keepdim=True)))
        return rel


@contextmanager
def _one_thread(enabled: bool = True) -> Iterator[None]:
    """Runs PyTorch on one thread. A view's tensors are small (3 x H x W x a few channels): there,
    OpenMP's fork-join costs more than it saves, and on a busy machine every parallel region waits for
    a time slice for its second thread (a 160x120 view measured 4 ms on one thread, 100 ms on two while
    another process ran). The rasterizer's compiled kernels keep their own threads."""
    before = torch.get_num_threads()
    if enabled:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


class Query:
    """Phrases embedded once, evaluated lazily per camera (``field.query(...)``; docs/api.md).

    Cameras are a :class:`~langfield.camera.Camera` (a scene's own or ``Camera.look_at(...)``) or a view
    of the field's scene by name or index. A query of one phrase returns results without a phrase axis;
    a query of a list returns the phrase axis first, and all its phrases share one rasterization and
    one look-up per view (codebook entries, or the lattice for a continuous field). The last view is
    kept, so ``q.relevance(cam)`` then ``q.mask(cam)`` compute it once. A query reflects the field when
    it was made: query again after changing the field.

    Example:
        >>> q = field.query(["sofa", "lamp"])  # doctest: +SKIP
        >>> q.mask("test_000").shape, q["lamp"].mask("test_000").shape  # doctest: +SKIP
        (torch.Size([2, 120, 160]), torch.Size([120, 160]))
    """

    def __init__(self, shared: _Shared, rows: list[int], single: bool) -> None:
        self._shared = shared
        self._rows = rows
        self._single = single
        self._last: tuple[Camera, bool, QueryView] | None = None

    @property
    def phrases(self) -> list[str]:
        return [self._shared.phrases[i] for i in self._rows]

    @property
    def phrase_embeddings(self) -> Tensor:
        """``[Q, D]`` the phrases' text embeddings."""
        return self._shared.embeddings[self._rows]

    @property
    def canonical_embeddings(self) -> Tensor:
        """``[C, D]`` the embeddings of the canonical phrases every phrase is compared against."""
        return self._shared.embeddings[self._shared.n_phrases :]

    def __len__(self) -> int:
        return len(self._rows)

    def __getitem__(self, key: int | str) -> Query:
        """The query of one of the phrases (by position or text); it shares the work of this one."""
        phrases = self.phrases
        if isinstance(key, str):
            if key not in phrases:
                raise KeyError(f"{key!r} is not one of this query's phrases {phrases}")
            key = phrases.index(key)
        return Query(self._shared, [self._rows[key]], True)

    def __repr__(self) -> str:
        return f"Query({self.phrases[0]!r})" if self._single else f"Query({self.phrases!r})"

    # -------------------------------------------------------- 2D

    def relevancy_maps(self, latents: Tensor, exact: bool = False) -> Tensor:
        """Relevancy of every level from rendered latents.

        Args:
            latents: ``[3, H, W, 3]`` rendered latents (``field.render(cam).latents``).
            exact: decode every pixel instead of interpolating the lattice (a field with a codebook
                looks every pixel's entry up either way: that is exact).

        Returns:
            ``[Q, 3, H, W]`` relevancy in [0, 1] (``[3, H, W]`` for a query of one phrase), before
            :func:`fill_empty` (which needs the opacity; :meth:`view` applies it).
        """
        if latents.dim() != 4 or latents.shape[0] != N_LEVELS or latents.shape[-1] != LATENT_DIM:
            raise ValueError(f"relevancy_maps: expected latents [3, H, W, 3], got {tuple(latents.shape)}")
        shared = self._shared
        maps = shared.exact_relevancy(latents) if exact else shared.lattice_relevancy(latents)
        return self._shape(maps[self._rows])

    def entry_maps(self, index: Tensor) -> Tensor:
        """Relevancy of every level from the codebook entries a view reads (a field with a codebook).

        Args:
            index: ``[3, H, W]`` long, :meth:`LanguageField.read_entries` (-1: the zero latent).

        Returns:
            ``[Q, 3, H, W]`` relevancy in [0, 1] (``[3, H, W]`` for a query of one phrase), before
            :func:`fill_empty`.
        """
        if self._shared.field.codebook is None:
            raise ValueError("entry_maps: this field has no codebook; use relevancy_maps on its latents")
        if index.dim() != 3 or index.shape[0] != N_LEVELS:
            raise ValueError(f"entry_maps: expected entry indices [3, H, W], got {tuple(index.shape)}")
        return self._shape(self._shared.entry_relevancy(index)[self._rows])

    def view(self, camera: CameraKey, exact: bool = False) -> QueryView:
        """Everything the query gives in one view (relevance, mask, level, ...); see :class:`QueryView`.

        Args:
            camera: a Camera, or a view of the field's scene by name or index.
            exact: decode every pixel (slow; the evaluation's path) instead of the lattice; the same
                for a field with a codebook, whose look-up is exact.
        """
        cam = self._shared.camera(camera)
        if self._last is not None and self._last[0] is cam and self._last[1] == exact:
            return self._last[2]
        if not exact and self._shared.field.codebook is None:
            self._shared.lattice_channels()  # built once, on every thread: products worth parallelising
        with _one_thread(not exact), torch.no_grad():
            latents, alpha = self._shared.render(cam)
            if self._shared.field.codebook is not None:
                maps = self.entry_maps(self._shared.entries(cam))
            else:
                maps = self.relevancy_maps(latents, exact)
            maps = fill_empty(maps[None] if self._single else maps, alpha)  # [Q, 3, H, W]
            result = relevancy_mask(maps)
            h, w = maps.shape[-2:]
            relevance = maps.gather(1, result.level[:, None, None, None].expand(-1, 1, h, w)).squeeze(1)
            score = relevance.flatten(1).amax(dim=1)
            found = (score > MATCH_RELEVANCY) & result.mask.flatten(1).any(dim=1)
        parts = (relevance, result.mask, result.level, result.normalized, maps, score, found)
        out = QueryView(*(self._shape(t) for t in parts))
        self._last = (cam, exact, out)
        return out

    def relevance(self, camera: CameraKey, exact: bool = False) -> Tensor:
        """``[H, W]`` (``[Q, H, W]``) relevancy in [0, 1] at the level the mask pipeline chose."""
        return self.view(camera, exact).relevance

    def mask(self, camera: CameraKey, exact: bool = False) -> Tensor:
        """``[H, W]`` (``[Q, H, W]``) bool mask, LangSplat's pipeline (querying.relevancy_mask)."""
        return self.view(camera, exact).mask

    def level(self, camera: CameraKey, exact: bool = False) -> int | Tensor:
        """The level chosen in that view: an int (0 subpart, 1 part, 2 whole), or ``[Q]`` long."""
        level = self.view(camera, exact).level
        return int(level) if self._single else level

    # -------------------------------------------------------- 3D

    def gaussians(
        self, level: int | None = None, threshold: float = MASK_THRESHOLD
    ) -> Selection | list[Selection]:
        """The Gaussians that match: each Gaussian's three latents decoded exactly and scored; with a
        codebook, each Gaussian reads as its registered entry (the training mask it carries the most
        weight on, when training registered it) or its latent's nearest entry.

        As the 2D mask: the level with the highest relevancy is chosen (or ``level``), the relevancy at
        that level is min-max stretched over the Gaussians (:func:`querying.relevancy.normalize_map`)
        and thresholded at ``threshold``. When no Gaussian's relevancy at that level exceeds
        :data:`MATCH_RELEVANCY` the selection is empty. The Gaussians' relevancy is computed once per
        query; other levels and thresholds reuse it.

        Args:
            level: 0 subpart, 1 part, 2 whole; default the level where the phrase scores highest.
            threshold: on the stretched relevancy, in [0, 1] (LangSplat's mask threshold by default).

        Returns:
            A :class:`Selection` (a list of them, one per phrase, for a query of several phrases).
        """
        if level is not None and level not in range(N_LEVELS):
            raise ValueError(f"level must be 0 (subpart), 1 (part) or 2 (whole), got {level!r}")
        if not 0.0 <= threshold <= 1.0:
            raise ValueError(f"threshold must be in [0, 1], got {threshold!r}")
        rel = self._shared.gaussian_relevancy()[self._rows]  # [Q, 3, N]
        n = rel.shape[-1]
        if level is not None:
            levels = torch.full((rel.shape[0],), level, dtype=torch.long)
        elif n == 0:
            levels = torch.zeros(rel.shape[0], dtype=torch.long)
        else:
            levels = rel.amax(dim=-1).argmax(dim=-1)
        chosen = rel.gather(1, levels[:, None, None].expand(-1, 1, n))  # [Q, 1, N]: a 1 x N map
        selected = (normalize_map(chosen) > threshold)[:, 0] if n else chosen[:, 0].bool()
        selections = []
        for q in range(rel.shape[0]):
            best = float(chosen[q].max()) if n else 0.0
            idx = torch.nonzero(selected[q] & (best > MATCH_RELEVANCY)).flatten()
            selections.append(Selection(idx, chosen[q, 0, idx], int(levels[q]), best))
        return selections[0] if self._single else selections

    def selected_indices(self) -> Tensor:
        """``[K]`` long, the union of the phrases' selections, ascending."""
        selections = self.gaussians()
        selections = [selections] if isinstance(selections, Selection) else selections
        return torch.unique(torch.cat([s.indices for s in selections]))

    def subfield(self) -> LanguageField:
        """The field restricted to the selected Gaussians (same colour and language fields).

        Raises:
            EmptySelectionError: nothing matches.
        """
        return self._shared.field.select(self._nonempty_selection())

    def render(self, camera: CameraKey) -> Render:
        """Renders the selected Gaussians alone (:meth:`subfield`) from ``camera``.

        Raises:
            EmptySelectionError: nothing matches.
        """
        with torch.no_grad():
            return self.subfield().render(self._shared.camera(camera))

    def export_ply(self, path: str | Path) -> Path:
        """Writes the selected Gaussians as a standard 3DGS PLY, colours baked as ``field.save`` does.

        Raises:
            EmptySelectionError: nothing matches.
        """
        return self._shared.field.export_ply(path, self._nonempty_selection())

    # -------------------------------------------------------- helpers

    def _nonempty_selection(self) -> Tensor:
        idx = self.selected_indices()
        if idx.numel() == 0:
            names = ", ".join(repr(p) for p in self.phrases)
            raise EmptySelectionError(
                f"no Gaussian matches {names}: none has a relevancy above {MATCH_RELEVANCY} "
                f"(it is no closer to the phrase than to the canonical phrases)"
            )
        return idx

    def _shape(self, t: Tensor) -> Tensor:
        return t[0] if self._single else t
