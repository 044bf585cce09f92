"""Export a DPT or Depth Anything model (transformers) to ONNX for OnnxDepthEstimator.

The model is read with ``transformers.AutoModelForDepthEstimation.from_pretrained`` from a local
folder (``config.json``, the weights and, for the preprocessing, ``preprocessor_config.json``: the
layout of e.g. ``depth-anything/Depth-Anything-V2-Small-hf``, ``LiheYoung/depth-anything-small-hf`` or
``Intel/dpt-hybrid-midas`` on the Hugging Face hub, downloaded once by the user) or from a hub id,
which transformers downloads at export time; the runtime never needs transformers or a hub.

The network is exported with ``torch.onnx.export`` (the ``torch.export`` based exporter, opset 18) at
one fixed input size with a dynamic batch axis: its ``predicted_depth`` output [B, H, W]. Input size,
mean and std come from ``preprocessor_config.json`` (``size``, ``image_mean``, ``image_std``: DPT
uses 0.5 / 0.5, Depth Anything ImageNet's) unless given. Relative DPT and Depth Anything heads predict
disparity (inverse depth up to scale and shift); a Depth Anything head with
``depth_estimation_type="metric"`` predicts depth. After export the ONNX file is run on the export
input and compared with PyTorch; the difference is recorded in the manifest (``check``).

Example:
    >>> export_depth("models/depth", checkpoint="Depth-Anything-V2-Small-hf")  # doctest: +SKIP
    PosixPath('models/depth/manifest.json')
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from encoders.manifest import write_manifest

__all__ = ["EXPORT_TOL", "OPSET", "export_depth"]

OPSET = 18
EXPORT_TOL = 1e-4  # max |ONNX - PyTorch| accepted, relative to max(1, max |PyTorch|)
_FILE = "depth.onnx"


def export_depth(
    out_dir: str | Path,
    checkpoint: str | Path | None = None,
    model: Any = None,
    *,
    model_id: str | None = None,
    input_size: int | Sequence[int] | None = None,
    mean: Sequence[float] | None = None,
    std: Sequence[float] | None = None,
) -> Path:
    """Export a DPT or Depth Anything model to ``out_dir`` (depth.onnx, manifest.json).

    Give exactly one of ``checkpoint``, ``model_id`` and ``model``.

    Args:
        out_dir: the model folder to write (created if needed).
        checkpoint: a local transformers model folder (config.json, weights, preprocessor_config.json).
        model: an already built ``DPTForDepthEstimation`` / ``DepthAnythingForDepthEstimation`` (tests
            pass tiny random ones); then ``input_size``, ``mean`` and ``std`` are required.
        model_id: a Hugging Face hub id that transformers downloads at export time.
        input_size: the network's input, H or (H, W); default: the preprocessor's ``size``. Depth
            Anything needs multiples of 14; an aspect ratio close to your images' avoids stretching.
        mean: per-channel normalisation mean (RGB, for images in [0, 1]); default: the preprocessor's.
        std: per-channel normalisation std; default: the preprocessor's.

    Returns:
        The manifest path.

    Raises:
        ImportError: transformers or torch's ONNX exporter is missing (the ``export`` extra).
        FileNotFoundError: ``checkpoint`` is not a folder.
        ValueError: an unsupported model type, missing preprocessing settings, or an export whose
            output differs from PyTorch's by more than EXPORT_TOL.
    """
    given = [x is not None for x in (checkpoint, model, model_id)]
    if sum(given) != 1:
        raise ValueError("export_depth: give exactly one of checkpoint (a folder), model_id or model")
    processor: dict[str, Any] = {}
    if model is None:
        model, processor, name = _load(checkpoint, model_id)
    else:
        name = f"{type(model).__name__} (given model)"
    model = model.eval()
    kind = _output_kind(model)
    size = _input_size(input_size, processor, name)
    mean_, std_ = _normalisation(mean, std, processor, name)

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "manifest.json").unlink(missing_ok=True)  # the folder is incomplete until the new manifest
    example = torch.from_numpy(np.random.default_rng(0).standard_normal((2, 3, *size), dtype=np.float32))
    err, scale = _export(_DepthHead(model), example, out / _FILE)
    if not err <= EXPORT_TOL * max(1.0, scale):
        raise ValueError(
            f"export_depth: {out / _FILE} differs from PyTorch by {err:.3g} (outputs up to {scale:.3g})"
        )
    return write_manifest(
        out,
        "depth",
        name,
        {"model": _FILE},
        input_size=list(size),
        mean=mean_,
        std=std_,
        output=kind,
        opset=OPSET,
        check={"max_abs_err": err, "max_abs_output": scale},
    )


def _load(checkpoint: str | Path | None, model_id: str | None) -> tuple[Any, dict, str]:
    """(model, preprocessor_config.json as a dict or {}, name) from a local folder or a hub id."""
    folder = None if checkpoint is None else Path(checkpoint)
    if folder is not None and not (folder / "config.json").is_file():
        raise FileNotFoundError(
            f"{folder / 'config.json'}: not found; --checkpoint must be a transformers model folder "
            f"(config.json, model.safetensors, preprocessor_config.json)"
        )
    try:
        from transformers import AutoModelForDepthEstimation
    except ImportError as exc:
        raise ImportError(
            f"langfield export depth needs transformers ({exc}); install the export extra: "
            f"pip install 'langfield[export]'"
        ) from exc
    if folder is not None:
        model = AutoModelForDepthEstimation.from_pretrained(folder, local_files_only=True)
        pre = folder / "preprocessor_config.json"
        processor = json.loads(pre.read_text()) if pre.is_file() else {}
        return model, processor, folder.resolve().name
    from huggingface_hub import hf_hub_download

    model = AutoModelForDepthEstimation.from_pretrained(model_id)
    processor = json.loads(Path(hf_hub_download(model_id, "preprocessor_config.json")).read_text())
    return model, processor, str(model_id)


def _output_kind(model: Any) -> str:
    config = getattr(model, "config", None)
    model_type = getattr(config, "model_type", None)
    if model_type == "dpt":
        return "disparity"
    if model_type == "depth_anything":
        return "depth" if config.depth_estimation_type == "metric" else "disparity"
    raise ValueError(
        f"export_depth: model type {model_type!r} is not supported; use a DPT or Depth Anything model "
        f"(model_type 'dpt' or 'depth_anything'), whose output kind is known"
    )


def _input_size(input_size: int | Sequence[int] | None, processor: dict, name: str) -> tuple[int, int]:
    if input_size is None:
        size = processor.get("size")
        if isinstance(size, dict) and {"height", "width"} <= set(size):
            input_size = (size["height"], size["width"])
        elif isinstance(size, dict) and "shortest_edge" in size:
            input_size = size["shortest_edge"]
        else:
            raise ValueError(f"export_depth: {name} has no preprocessor 'size'; give input_size (H, W)")
    hw = (input_size, input_size) if isinstance(input_size, int) else tuple(input_size)
    if len(hw) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in hw):
        raise ValueError(
            f"export_depth: input_size must be H or (H, W), positive integers, got {input_size!r}"
        )
    multiple = processor.get("ensure_multiple_of", 1)
    if hw[0] % multiple or hw[1] % multiple:
        raise ValueError(
            f"export_depth: {name} needs an input size that is a multiple of {multiple}, got {hw}"
        )
    return int(hw[0]), int(hw[1])


def _normalisation(
    mean: Sequence[float] | None, std: Sequence[float] | None, processor: dict, name: str
) -> tuple[list[float], list[float]]:
    if processor and not processor.get("do_rescale", True):
        raise ValueError(f"export_depth: {name}'s preprocessor does not rescale to [0, 1]; not supported")
    if processor and abs(processor.get("rescale_factor", 1 / 255) - 1 / 255) > 1e-9:
        raise ValueError(f"export_depth: {name}'s preprocessor rescales by {processor['rescale_factor']}")
    if mean is None or std is None:
        if processor and not processor.get("do_normalize", True):
            mean, std = mean or [0.0, 0.0, 0.0], std or [1.0, 1.0, 1.0]
        elif "image_mean" in processor and "image_std" in processor:
            mean, std = mean or processor["image_mean"], std or processor["image_std"]
        else:
            raise ValueError(
                f"export_depth: {name} has no preprocessor image_mean / image_std; give mean and std"
            )
    mean_, std_ = [float(v) for v in mean], [float(v) for v in std]
    if len(mean_) != 3 or len(std_) != 3 or min(std_) <= 0:
        raise ValueError(
            f"export_depth: mean and std must be 3 numbers each, std positive; got {mean_}, {std_}"
        )
    return mean_, std_


def _export(head: torch.nn.Module, example: torch.Tensor, path: Path) -> tuple[float, float]:
    """Export with a dynamic batch axis; returns (max |ONNX - torch|, max |torch|) on the example."""
    import onnxruntime as ort

    head = head.eval()
    with torch.no_grad():
        expected = head(example).numpy()
    batch = torch.export.Dim("batch", min=1, max=64)
    program = torch.onnx.export(
        head,
        (example,),
        input_names=["pixels"],
        output_names=["depth"],
        dynamic_shapes={"x": {0: batch}},
        opset_version=OPSET,
        dynamo=True,
        verbose=False,
    )
    program.save(str(path), external_data=False)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, {"pixels": example.numpy()})[0]
    if got.shape != expected.shape:
        raise ValueError(f"{path}: ONNX output has shape {got.shape}, PyTorch {expected.shape}")
    return float(np.abs(got - expected).max()), float(np.abs(expected).max())


class _DepthHead(torch.nn.Module):
    """pixels [B, 3, H, W] (normalised) -> predicted_depth [B, H, W]."""

    def __init__(self, model: Any) -> None:
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(pixel_values=x).predicted_depth
