"""What a field folder's ``field.json`` must hold to be loaded, checked key by key (FORMAT.md).

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

from torch import Tensor

from langfield.hashgrid import HashGridConfig

__all__ = ["FieldFileError", "check_field_meta", "check_tensors"]

LANGUAGE_FEATURES = ("hashgrid", "per-gaussian")
TEXT_ENCODER_KINDS = ("table", "clip-onnx")
BACKEND_NAMES = ("auto", "torch", "cpu")


class FieldFileError(ValueError):
    """A field folder that cannot be loaded; the message names the file and the key."""


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
    c.whole(meta, "color_field.n_freqs", 0)
    c.numbers(meta, "background", 3, optional=True)
    c.choice(meta, "backend", BACKEND_NAMES, optional=True)
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
