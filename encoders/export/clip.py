"""Export an OpenCLIP model's image and text towers to ONNX for :class:`encoders.onnx_clip.OnnxClipEncoder`.

The towers are exported separately with ``torch.onnx.export`` (the ``torch.export`` based exporter,
opset 18) with a dynamic batch axis, each ending with L2 normalisation (``encode_image(x,
normalize=True)``, ``encode_text(t, normalize=True)`` in open_clip ``model.py``). The image tower takes
CLIP-normalised pixels; mean, std and input size come from the model's open_clip preprocessing config
(``open_clip.get_model_preprocess_cfg``) and go into the manifest. open_clip's BPE vocabulary file
(``open_clip.tokenizer.default_bpe()``) is copied beside the model, so the runtime tokenizes without
open_clip and without a hub. After export, both ONNX files are run on the export inputs and compared
with PyTorch; the largest absolute differences are recorded in the manifest (``check``), and an
export that differs by more than ``EXPORT_TOL`` is an error.

Example:
    >>> export_clip("models/clip", "ViT-B-16", pretrained="open_clip_pytorch_model.bin")  # doctest: +SKIP
    PosixPath('models/clip/manifest.json')
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch

from encoders.manifest import write_manifest

__all__ = ["EXPORT_TOL", "OPSET", "export_clip"]

OPSET = 18
EXPORT_TOL = 1e-4  # max |ONNX - PyTorch| accepted on the export inputs (unit rows)
_PROTOBUF_LIMIT = 1_900_000_000  # bytes; a larger tower keeps its weights in an external data file
_EXAMPLE_PHRASES = ("a photo of a sofa", "Hello, World! 42", "")


def export_clip(
    out_dir: str | Path,
    model_name: str = "ViT-B-16",
    pretrained: str | Path | None = None,
    model: Any = None,
) -> Path:
    """Export an OpenCLIP model to ``out_dir`` (image.onnx, text.onnx, BPE vocabulary, manifest.json).

    Args:
        out_dir: the model folder to write (created if needed).
        model_name: an open_clip architecture (``open_clip.list_models()``, e.g. "ViT-B-16"), or
            "local-dir:FOLDER" / "hf-hub:ORG/NAME" as open_clip accepts them.
        pretrained: a local checkpoint file, or an open_clip pretrained tag (e.g. "laion2b_s34b_b88k",
            which open_clip downloads at export time). Ignored when ``model`` is given.
        model: an already built open_clip CLIP model of architecture ``model_name`` (tests pass tiny
            random ones); its tokenizer is the one ``open_clip.get_tokenizer(model_name)`` gives.

    Returns:
        The manifest path.

    Raises:
        ImportError: open_clip or torch's ONNX exporter is missing (the ``export`` extra).
        FileNotFoundError: ``pretrained`` is neither a file nor a known tag.
        ValueError: a model whose tokenizer or preprocessing the runtime cannot reproduce, or an export
            whose outputs differ from PyTorch's by more than EXPORT_TOL.
    """
    open_clip = _import_open_clip()
    out = Path(out_dir)
    if model is None:
        model, weights = _load_model(open_clip, model_name, pretrained), pretrained
    else:
        weights = pretrained or "given model"
    model = model.eval()

    tokenizer = open_clip.get_tokenizer(model_name)
    _check_tokenizer(open_clip, tokenizer, model_name)
    size, mean, std = _preprocess(open_clip, model, model_name)
    context_length = int(model.context_length)
    if tokenizer.context_length != context_length:
        raise ValueError(
            f"export_clip: {model_name} has context length {context_length} but its tokenizer "
            f"{tokenizer.context_length}"
        )

    out.mkdir(parents=True, exist_ok=True)
    (out / "manifest.json").unlink(missing_ok=True)  # the folder is incomplete until the new manifest
    files, errors, dim = _export_towers(model, tokenizer, size, out)
    vocab = Path(open_clip.tokenizer.default_bpe())
    shutil.copyfile(vocab, out / vocab.name)
    files["vocab"] = vocab.name

    bad = {k: v for k, v in errors.items() if not v <= EXPORT_TOL}
    if bad:
        raise ValueError(
            f"export_clip: ONNX outputs in {out} differ from PyTorch by {bad} (> {EXPORT_TOL:g})"
        )
    return write_manifest(
        out,
        "clip",
        f"{model_name}/{Path(str(weights)).name if weights else 'untrained'}",
        files,
        input_size=size,
        mean=mean,
        std=std,
        context_length=context_length,
        vocab_size=int(tokenizer.vocab_size),
        dim=int(dim),
        output="unit",
        opset=OPSET,
        check=errors,
    )


def _export_towers(
    model: Any, tokenizer: Any, size: int, out: Path
) -> tuple[dict[str, str], dict[str, float], int]:
    """Exports the image and the text tower to ``out``; returns (the files by role, each tower's largest
    difference to PyTorch, the embedding dimension the towers share)."""
    pixels = torch.from_numpy(np.random.default_rng(0).standard_normal((2, 3, size, size), dtype=np.float32))
    tokens = tokenizer(list(_EXAMPLE_PHRASES))
    towers = {
        "image": (_ImageTower(model), pixels, "pixels"),
        "text": (_TextTower(model), tokens, "tokens"),
    }
    files: dict[str, str] = {}
    errors: dict[str, float] = {}
    dim = None
    for role, (tower, example, input_name) in towers.items():
        names, err, out_dim = _export_tower(tower, example, input_name, out / f"{role}.onnx")
        files.update({role if i == 0 else f"{role}_data": n for i, n in enumerate(names)})
        errors[f"{role}_max_abs_err"] = err
        dim = out_dim if dim is None else dim
        if out_dim != dim:
            raise ValueError(f"export_clip: image and text towers give dimensions {dim} and {out_dim}")
    return files, errors, dim


def _import_open_clip() -> Any:
    try:
        import open_clip
    except ImportError as exc:
        raise ImportError(
            f"langfield export clip needs open_clip_torch ({exc}); install the export extra: "
            f"pip install 'langfield[export]'"
        ) from exc
    return open_clip


def _load_model(open_clip: Any, model_name: str, pretrained: str | Path | None) -> Any:
    has_schema = model_name.startswith(("local-dir:", "hf-hub:"))
    if pretrained is None and not has_schema:
        raise ValueError(
            f"export_clip: give the weights of {model_name}: a checkpoint file or an open_clip pretrained "
            f"tag ({', '.join(open_clip.list_pretrained_tags_by_model(model_name)) or 'none known'})"
        )
    if model_name not in open_clip.list_models() and not has_schema:
        raise ValueError(
            f"export_clip: {model_name!r} is not an open_clip architecture (see open_clip.list_models())"
        )
    if pretrained is not None and not has_schema:
        tags = open_clip.list_pretrained_tags_by_model(model_name)
        if str(pretrained) not in tags and not os.path.isfile(pretrained):
            raise FileNotFoundError(
                f"{pretrained}: no such checkpoint file, and not a pretrained tag of {model_name} "
                f"(tags: {', '.join(tags) or 'none'})"
            )
    return open_clip.create_model(model_name, pretrained=None if has_schema else str(pretrained))


def _check_tokenizer(open_clip: Any, tokenizer: Any, model_name: str) -> None:
    """The runtime reproduces open_clip's SimpleTokenizer with lower-case cleaning and truncation only."""
    simple = open_clip.tokenizer.SimpleTokenizer
    if (
        not isinstance(tokenizer, simple)
        or tokenizer.clean_fn is not open_clip.tokenizer._clean_lower
        or tokenizer.reduction_fn is not None
    ):
        raise ValueError(
            f"export_clip: {model_name} uses a tokenizer other than open_clip's CLIP BPE tokenizer with "
            f"lower-case cleaning ({type(tokenizer).__name__}); OnnxClipEncoder cannot reproduce it"
        )


def _preprocess(open_clip: Any, model: Any, model_name: str) -> tuple[int, list[float], list[float]]:
    cfg = open_clip.get_model_preprocess_cfg(model)
    if not {"size", "mean", "std"} <= set(cfg):
        raise ValueError(
            f"export_clip: the {model_name} model has no preprocessing config (size, mean, std); "
            f"build it with open_clip.create_model"
        )
    size = cfg["size"]
    side = (size, size) if isinstance(size, int) else tuple(size)
    if len(side) != 2 or side[0] != side[1]:
        raise ValueError(f"export_clip: {model_name} takes {size} images; only square inputs are supported")
    return int(side[0]), [float(v) for v in cfg["mean"]], [float(v) for v in cfg["std"]]


def _export_tower(
    tower: torch.nn.Module, example: torch.Tensor, input_name: str, path: Path
) -> tuple[list[str], float, int]:
    """Export one tower with a dynamic batch axis; returns (file names, max |ONNX - torch|, dim)."""
    import onnxruntime as ort

    tower = tower.eval()
    with torch.no_grad():
        expected = tower(example).numpy()
    external = sum(p.numel() * p.element_size() for p in tower.parameters()) > _PROTOBUF_LIMIT
    batch = torch.export.Dim("batch", min=1, max=4096)
    program = torch.onnx.export(
        tower,
        (example,),
        input_names=[input_name],
        output_names=["features"],
        dynamic_shapes={"x": {0: batch}},
        opset_version=OPSET,
        dynamo=True,
        verbose=False,
    )
    data = path.with_name(path.name + ".data")
    data.unlink(missing_ok=True)
    program.save(str(path), external_data=external)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, {input_name: example.numpy()})[0]
    if got.shape != expected.shape:
        raise ValueError(f"{path}: ONNX output has shape {got.shape}, PyTorch {expected.shape}")
    names = [path.name] + ([data.name] if data.is_file() else [])
    return names, float(np.abs(got - expected).max()), int(expected.shape[1])


class _ImageTower(torch.nn.Module):
    """pixels [B, 3, S, S] (CLIP-normalised) -> [B, D] unit rows."""

    def __init__(self, model: Any) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model.encode_image(x, normalize=True)


class _TextTower(torch.nn.Module):
    """tokens [B, context_length] int64 -> [B, D] unit rows."""

    def __init__(self, model: Any) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model.encode_text(x, normalize=True)
