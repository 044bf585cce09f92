"""The small JSON manifest written beside every exported ONNX model, read by the runtime classes.

An exporter (``langfield export clip|sam|depth ... --out DIR``) writes ``DIR/manifest.json`` next to
the ONNX files. The runtime never guesses a model's preprocessing: input size, normalisation and
output kind come from here.

Example manifest::

    {"format_version": 1, "kind": "clip", "model": "ViT-B-16/laion2b_s34b_b88k",
     "files": {"image": "image.onnx", "text": "text.onnx", "vocab": "bpe_simple_vocab_16e6.txt.gz"},
     "input_size": 224, "mean": [...], "std": [...], "output": "unit", "dim": 512}
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

FORMAT_VERSION = 1
MANIFEST = "manifest.json"
KINDS = ("clip", "sam", "depth", "refiner")


class ManifestError(ValueError):
    """A model folder whose manifest is missing, malformed, of the wrong kind or names missing files."""


def write_manifest(folder: str | Path, kind: str, model: str, files: dict[str, str], **fields: Any) -> Path:
    """Writes ``folder/manifest.json`` atomically and returns its path.

    Args:
        folder: the model folder (created if needed).
        kind: one of KINDS.
        model: a human-readable model name (architecture and weights).
        files: role -> file name inside ``folder`` (e.g. {"image": "image.onnx"}).
        **fields: kind-specific settings (input_size, mean, std, output, ...); must be JSON-serialisable.
    """
    if kind not in KINDS:
        raise ValueError(f"manifest kind must be one of {KINDS}, got {kind!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    data = {"format_version": FORMAT_VERSION, "kind": kind, "model": model, "files": dict(files), **fields}
    path = folder / MANIFEST
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)
    return path


def read_manifest(folder: str | Path, kind: str) -> dict[str, Any]:
    """Reads and checks ``folder/manifest.json``; file entries come back as absolute paths.

    Raises:
        ManifestError: naming the file and what is wrong.
    """
    folder = Path(folder)
    path = folder / MANIFEST
    if not path.is_file():
        raise ManifestError(
            f"{path}: no model manifest (export the model with `langfield export {kind} ... --out {folder}`)"
        )
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ManifestError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise ManifestError(f"{path}: expected a JSON object")
    if data.get("format_version") != FORMAT_VERSION:
        raise ManifestError(
            f"{path}: format_version {data.get('format_version')!r}, this langfield reads {FORMAT_VERSION}"
        )
    if data.get("kind") != kind:
        raise ManifestError(f"{path}: holds a {data.get('kind')!r} model, expected {kind!r}")
    files = data.get("files")
    if not isinstance(files, dict) or not files:
        raise ManifestError(f"{path}: 'files' must map roles to file names")
    resolved = {}
    for role, name in files.items():
        f = folder / str(name)
        if not f.is_file():
            raise ManifestError(f"{path}: file {f} named for {role!r} does not exist")
        resolved[role] = f
    data["files"] = resolved
    return data


def manifest_triple(manifest: dict, key: str, where: Path) -> np.ndarray:
    """``manifest[key]`` as a float32 [3] array (per-channel mean or std), or a ManifestError."""
    value = manifest.get(key)
    try:
        arr = np.asarray(value, dtype=np.float32)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.shape != (3,) or not np.isfinite(arr).all():
        raise ManifestError(f"{where}: {key!r} must be three numbers (R, G, B), got {value!r}")
    return arr


def manifest_normalisation(manifest: dict, where: Path) -> tuple[np.ndarray, np.ndarray]:
    """The manifest's per-channel ``mean`` and ``std`` (std positive), or a ManifestError."""
    mean, std = manifest_triple(manifest, "mean", where), manifest_triple(manifest, "std", where)
    if (std <= 0).any():
        raise ManifestError(f"{where}: 'std' must be positive, got {std.tolist()}")
    return mean, std


def onnx_session(path: str | Path) -> Any:
    """An onnxruntime CPU session of one file, or a ValueError naming it."""
    import onnxruntime as ort

    try:
        return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types for unreadable models
        raise ValueError(f"{path}: cannot load ONNX model ({exc})") from exc
