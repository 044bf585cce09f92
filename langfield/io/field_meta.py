"""What a field folder's ``field.json`` holds (:class:`FieldMeta`) and must hold to be loaded, checked
key by key (docs/format.md).

:func:`check_field_meta` runs before any tensor is read, and :func:`check_tensors` compares
``field.safetensors`` with the shapes the modules that ``field.json`` describes expect; each problem is
one :class:`FieldFileError` naming the file and the key, so an edited or damaged field folder gives one
clear line, not a traceback from deep inside the loader.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
from torch import Tensor

from langfield.kernels import BACKEND_ALIASES, BACKENDS
from langfield.model.hashgrid import HashGridConfig

__all__ = ["LANGUAGE_DECODES", "FieldFileError", "FieldMeta", "check_field_meta", "check_tensors"]

LANGUAGE_FEATURES = ("hashgrid", "per-gaussian")
# How a field reads its rendered latents (``language.decode``, ``--language-decode``): by vote among
# its codebook's entries, as the nearest entry, or decoded as they are (the paper's reading).
LANGUAGE_DECODES = ("vote", "codebook", "continuous")
TEXT_ENCODER_KINDS = ("table", "clip-onnx")


class FieldFileError(ValueError):
    """A field folder that cannot be loaded; the message names the file and the key."""


class FieldMeta(dict):
    """What ``field.json`` records: the JSON object itself (so it is written back key for key, and
    ``meta["config"]`` reads as before), with a typed property for each key the library reads.

    Library code reads the properties, never the keys: the defaults of an older or partial file are
    then decided here, once.
    """

    @property
    def backend(self) -> str:
        """The rasterizer backend the field was trained with ("auto" when not recorded; a field saved
        when the numba backend was called "cpu" reads "numba")."""
        backend = self.get("backend", "auto")
        return BACKEND_ALIASES.get(backend, backend)

    @property
    def background(self) -> list[float]:
        """The RGB behind the Gaussians (black when not recorded)."""
        return list(self.get("background") or (0.0, 0.0, 0.0))

    @property
    def bounds(self) -> np.ndarray:
        """``[2, 3]`` float64, the scene box (min, max) the hash grids cover."""
        return np.asarray(self["bounds"], dtype=np.float64)

    @property
    def centre(self) -> np.ndarray:
        """``[3]`` float64, the centre of the scene box: the colour grid's centre, which every field
        records (the bounds' centre; the bounds themselves are optional in field.json)."""
        return np.asarray(self["color_field"]["center"], dtype=np.float64)

    @property
    def scene(self) -> str | None:
        """The scene folder the field was trained on, if recorded."""
        return self.get("scene") or None

    @property
    def scene_args(self) -> dict[str, Any]:
        """How the scene was loaded for training (``load_scene``'s resolution and split arguments)."""
        return dict(self.get("scene_args") or {})

    @property
    def text_encoder(self) -> dict[str, Any] | None:
        """``{"kind": "table" | "clip-onnx", "path": ...}``, the encoder of the field's phrases."""
        return self.get("text_encoder")

    @property
    def color_field(self) -> dict[str, Any]:
        """The colour field's shape: its hash grid, box, MLP width and frequencies."""
        return self["color_field"]

    @property
    def language(self) -> dict[str, Any] | None:
        """The language part's shape (features, hidden width, grid, autoencoder, codebook), or None
        for a field without language."""
        return self.get("language") or None

    @property
    def language_decode(self) -> str | None:
        """How the field reads its rendered latents (:data:`LANGUAGE_DECODES`); None without language.
        Fields saved before the vote reading record none: with a codebook they read the nearest entry,
        without one they decode latents as they are."""
        spec = self.language
        if spec is None:
            return None
        return spec.get("decode") or ("codebook" if spec.get("codebook") is not None else "continuous")

    @property
    def train_seconds(self) -> float | None:
        """Wall-clock seconds of the training (None for a field that was not trained, e.g. aggregated)."""
        return self.get("train_seconds")

    @property
    def iterations(self) -> int | None:
        return self.get("iterations")

    @property
    def iterations_per_second(self) -> float | None:
        return self.get("iterations_per_second")

    @property
    def lop_removed(self) -> int:
        """Gaussians removed by the outlier pruning over the whole training (0 when none ran)."""
        return sum(int(r["removed"]) for r in self.get("lop") or [])

    @property
    def tensors_sha256(self) -> str | None:
        """The checksum of field.safetensors written beside it (None for a field never saved)."""
        return self.get("tensors_sha256")

    @property
    def text_table_sha256(self) -> str | None:
        """The checksum of the phrase table copied beside it, if one was."""
        return self.get("text_table_sha256")

    @property
    def depth(self) -> dict[str, Any] | None:
        """How the depth prior was used (``{"lad", "kind"}``), or None when training had none."""
        return self.get("depth")


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _is_whole(value: Any, low: int) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


class _Checker:
    def __init__(self, path: Path) -> None:
        self.path = path

    def fail(self, key: str, expected: str, value: Any) -> None:
        shown = repr(value)
        shown = shown if len(shown) <= 60 else shown[:57] + "..."
        raise FieldFileError(f"{self.path}: {key} must be {expected}, got {shown}")

    def mapping(self, meta: Mapping, key: str, optional: bool = False) -> Mapping | None:
        value = _get(meta, key)
        if value is None and optional:
            return None
        if not isinstance(value, Mapping):
            self.fail(key, "an object" + (" or null" if optional else ""), value)
        return value

    def numbers(self, meta: Mapping, key: str, count: int, optional: bool = False) -> None:
        value = _get(meta, key)
        if value is None and optional:
            return
        if not (isinstance(value, list) and len(value) == count and all(_is_number(v) for v in value)):
            self.fail(key, f"a list of {count} finite numbers" + (" or null" if optional else ""), value)

    def whole(self, meta: Mapping, key: str, low: int) -> None:
        value = _get(meta, key)
        if not _is_whole(value, low):
            self.fail(key, f"a whole number >= {low}", value)

    def choice(self, meta: Mapping, key: str, choices: tuple[str, ...], optional: bool = False) -> None:
        value = _get(meta, key)
        if value is None and optional:
            return
        if value not in choices:
            self.fail(key, " or ".join(repr(c) for c in choices) + (" or null" if optional else ""), value)

    def grid(self, meta: Mapping, key: str) -> None:
        spec = self.mapping(meta, key)
        known = {f.name for f in fields(HashGridConfig)}
        for name in spec:
            if name not in known:
                expected = f"one of the hash grid's settings ({', '.join(sorted(known))})"
                self.fail(f"{key}.{name}", expected, name)
        for name in known - {"init_scale"}:
            if name in spec:
                self.whole(meta, f"{key}.{name}", 1)
        try:
            HashGridConfig(**spec)
        except (TypeError, ValueError) as err:
            raise FieldFileError(f"{self.path}: {key}: {err}") from err


def _get(meta: Mapping, dotted: str) -> Any:
    value: Any = meta
    for part in dotted.split("."):
        value = value.get(part) if isinstance(value, Mapping) else None
    return value


def check_field_meta(meta: Any, path: Path, readable: tuple[int, ...]) -> dict[str, Any]:
    """Checks the keys of a parsed ``field.json`` that loading and rendering read.

    Args:
        meta: the parsed JSON.
        path: the file, for the messages.
        readable: the format versions this langfield reads (the last is the one it writes).

    Returns:
        ``meta`` itself, known to hold what :meth:`langfield.field.LanguageField.load` needs.

    Raises:
        FieldFileError: the first key that is missing or of the wrong kind, named with the file.
    """
    c = _Checker(path)
    if not isinstance(meta, dict):
        c.fail("the top level", "a JSON object", meta)
    version = meta.get("format_version")
    if not _is_whole(version, 0) or version not in readable:
        c.fail("format_version", " or ".join(str(v) for v in readable), version)
    for key in ("tensors_sha256", "text_table_sha256"):
        if meta.get(key) is not None and not isinstance(meta[key], str):
            c.fail(key, "a string", meta[key])
    c.grid(meta, "color_field.grid")
    c.numbers(meta, "color_field.center", 3)
    c.numbers(meta, "color_field.half_extent", 3)
    c.whole(meta, "color_field.hidden", 1)
    c.whole(meta, "color_field.n_freqs", -1)
    c.numbers(meta, "background", 3, optional=True)
    c.choice(meta, "backend", ("auto", *BACKENDS, *BACKEND_ALIASES), optional=True)
    bounds = meta.get("bounds")
    if bounds is not None and not (
        isinstance(bounds, list) and len(bounds) == 2 and all(isinstance(b, list) for b in bounds)
    ):
        c.fail("bounds", "[[xmin, ymin, zmin], [xmax, ymax, zmax]]", bounds)
    if bounds is not None:
        c.numbers({"b": bounds[0]}, "b", 3)
        c.numbers({"b": bounds[1]}, "b", 3)
    if meta.get("scene") is not None and not isinstance(meta["scene"], str):
        c.fail("scene", "a folder path (a string) or null", meta["scene"])
    if c.mapping(meta, "scene_args", optional=True) is not None:
        args = meta["scene_args"]
        unknown = set(args) - {"resolution", "views", "n_views"}
        if unknown:
            c.fail("scene_args", "an object of resolution, views and n_views", sorted(unknown))
    encoder = c.mapping(meta, "text_encoder", optional=True)
    if encoder is not None:
        c.choice(meta, "text_encoder.kind", TEXT_ENCODER_KINDS)
        if not isinstance(encoder.get("path"), str):
            c.fail("text_encoder.path", "a path (a string)", encoder.get("path"))
    language = c.mapping(meta, "language", optional=True)
    if language is not None:
        c.choice(meta, "language.features", LANGUAGE_FEATURES)
        c.mapping(meta, "language.autoencoder")
        if language["features"] == "hashgrid":
            c.grid(meta, "language.grid")
            c.whole(meta, "language.hidden", 1)
        sizes = language.get("codebook")
        if sizes is not None and not (
            isinstance(sizes, list) and len(sizes) == 3 and all(_is_whole(v, 0) for v in sizes)
        ):
            c.fail("language.codebook", "null or the entry counts of the three levels ([P0, P1, P2])", sizes)
        if not isinstance(language.get("registered", False), bool):
            c.fail("language.registered", "true or false", language.get("registered"))
        if language.get("registered") and sizes is None:
            c.fail("language.registered", "false for a field without a codebook", True)
        if "decode" in language:
            c.choice(meta, "language.decode", LANGUAGE_DECODES)
            if (language["decode"] == "continuous") != (sizes is None):
                c.fail(
                    "language.decode",
                    "'continuous' exactly when language.codebook is null",
                    language["decode"],
                )
    return meta


def check_tensors(
    tensors: Mapping[str, Tensor], expected: Mapping[str, tuple[int, ...]], path: Path, meta_path: Path
) -> None:
    """Checks that ``tensors`` holds exactly the ``expected`` keys with their shapes.

    Raises:
        FieldFileError: naming the first missing, unexpected or misshapen tensor and the file.
    """
    for key, shape in expected.items():
        if key not in tensors:
            raise FieldFileError(
                f"{path}: tensor {key!r} missing (the field {meta_path.name} describes needs it)"
            )
        if tuple(tensors[key].shape) != tuple(shape):
            raise FieldFileError(
                f"{path}: tensor {key!r} has shape {tuple(tensors[key].shape)} but {meta_path.name} "
                f"describes {tuple(shape)}"
            )
    for key in tensors:
        if key not in expected:
            raise FieldFileError(
                f"{path}: tensor {key!r} is not part of the field {meta_path.name} describes"
            )
