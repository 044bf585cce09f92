"""Export an image-to-image ``torch.nn.Module`` to ONNX for OnnxImageRefiner.

No refiner weights ship with langfield: the exporter takes any module that maps normalised pixels
[B, 3, H, W] to [B, 3, H', W'] (normalised RGB) or [B, 4, H', W'] (RGB, then confidence logits), e.g. a
single-step diffusion fixer wrapped so that its forward takes and returns tensors (Difix3D+, Wu et al.,
CVPR 2025, arXiv:2503.01774, runs at a fixed 512 x 512 after the VAE), or a small restoration CNN that
runs at any size. The folder it writes is read by :class:`encoders.onnx_refiner.OnnxImageRefiner`::

    refiner/
      manifest.json    kind "refiner": input_size [H, W] or null, mean, std, confidence, opset, check
      model.onnx       pixels [B, 3, H, W] -> refined [B, 3 | 4, H', W']

The module is exported as :mod:`encoders.export.depth` does it, with ``torch.onnx.export``'s
torch.export-based exporter (``dynamo=True``, which needs onnxscript; opset 18) and a dynamic batch
axis; with ``size=None`` the height and width are dynamic too (``torch.export.Dim.DYNAMIC``, which
lets torch.export infer the constraints the module puts on them, e.g. a multiple of 8 for a U-Net, and
fails the export rather than silently fixing them). The ONNX file is then run with onnxruntime on the
export input (and, for a dynamic model, on a second size) and compared with PyTorch; the largest
difference is recorded in the manifest (``check``).

Example:
    >>> net = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3, padding=1))  # doctest: +SKIP
    >>> export_refiner(net, "models/refiner", confidence=True)  # doctest: +SKIP
    PosixPath('models/refiner/manifest.json')
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from encoders.export.depth import EXPORT_TOL, OPSET
from encoders.manifest import MANIFEST, write_manifest

__all__ = ["export_refiner"]

_FILE = "model.onnx"
INPUT, OUTPUT = "pixels", "refined"
# Export inputs of a dynamic model: multiples of 16, not square, so that a U-Net's downsampling fits and
# a height/width mix-up shows; the second size checks that the graph did not keep the first one.
_DYNAMIC_SIZES = ((48, 64), (32, 80))


def export_refiner(
    module: torch.nn.Module,
    out_dir: str | Path,
    *,
    size: int | Sequence[int] | None = None,
    mean: Sequence[float] = (0.0, 0.0, 0.0),
    std: Sequence[float] = (1.0, 1.0, 1.0),
    confidence: bool,
    name: str | None = None,
) -> Path:
    """Export an image-to-image module to ``out_dir`` (model.onnx, manifest.json).

    Args:
        module: maps normalised pixels [B, 3, H, W] to [B, 3, H', W'] (normalised RGB) or, with
            ``confidence``, [B, 4, H', W'] (normalised RGB, then confidence logits); put into eval mode.
        out_dir: the model folder to write (created if needed).
        size: the fixed input, H or (H, W), the runtime resizes every image to; None: any size (the
            module must then run at any height and width).
        mean: per-channel normalisation mean (RGB, for images in [0, 1]); the runtime also uses it to
            undo the normalisation of the output's RGB channels.
        std: per-channel normalisation std, positive.
        confidence: whether the module outputs the fourth, confidence channel.
        name: the model name for the manifest; default: the module's class name.

    Returns:
        The manifest path.

    Raises:
        ImportError: torch's ONNX exporter or onnxscript is missing (the ``export`` extra).
        ValueError: a bad size, mean or std, a module whose output is not [B, 3 | 4, H', W'] as
            ``confidence`` says, or an export whose output differs from PyTorch's by more than
            EXPORT_TOL (relative to max(1, max |PyTorch|)).
    """
    if not isinstance(confidence, bool):
        raise ValueError(f"export_refiner: confidence must be True or False, got {confidence!r}")
    hw = _size(size)
    mean_, std_ = _normalisation(mean, std)
    module = module.eval()
    name = name or f"{type(module).__name__} (given module)"

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / MANIFEST).unlink(missing_ok=True)  # the folder is incomplete until the new manifest
    examples, expected = _run_examples(module, hw, confidence)
    path = out / _FILE
    _export(module, examples[0], path, dynamic_hw=hw is None)
    err, scale = _check(path, examples, [y.numpy() for y in expected])
    if not err <= EXPORT_TOL * max(1.0, scale):
        raise ValueError(
            f"export_refiner: {path} differs from PyTorch by {err:.3g} (outputs up to {scale:.3g})"
        )
    return write_manifest(
        out,
        "refiner",
        name,
        {"model": _FILE},
        input_size=None if hw is None else list(hw),
        mean=mean_,
        std=std_,
        confidence=confidence,
        opset=OPSET,
        check={"max_abs_err": err, "max_abs_output": scale},
    )


def _run_examples(
    module: torch.nn.Module, hw: tuple[int, int] | None, confidence: bool
) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Random inputs at the export's size (several sizes for a dynamic one) and the module's outputs,
    checked to be [B, 3 | 4, H', W'] as ``confidence`` says."""
    rng = np.random.default_rng(0)
    sizes = _DYNAMIC_SIZES if hw is None else (hw,)
    examples = [torch.from_numpy(rng.standard_normal((2, 3, *s), dtype=np.float32)) for s in sizes]
    channels = 4 if confidence else 3
    expected = []
    for x in examples:
        try:
            with torch.no_grad():
                expected.append(module(x))
        except RuntimeError as exc:  # e.g. a module that only runs at one size, exported with size=None
            hint = "; give size=(H, W) if it needs a fixed input size" if hw is None else ""
            raise ValueError(
                f"export_refiner: the module fails on input {tuple(x.shape)} ({exc}){hint}"
            ) from exc
    for x, y in zip(examples, expected, strict=True):
        if not isinstance(y, torch.Tensor) or y.ndim != 4 or y.shape[:2] != (x.shape[0], channels):
            got = tuple(y.shape) if isinstance(y, torch.Tensor) else type(y).__name__
            raise ValueError(
                f"export_refiner: the module must return [B, {channels}, H, W] for input {tuple(x.shape)} "
                f"(confidence={confidence}), got {got}"
            )
    return examples, expected


def _size(size: int | Sequence[int] | None) -> tuple[int, int] | None:
    if size is None:
        return None
    hw = (size, size) if isinstance(size, int) else tuple(size)
    if len(hw) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in hw):
        raise ValueError(f"export_refiner: size must be None, H or (H, W), positive integers, got {size!r}")
    return int(hw[0]), int(hw[1])


def _normalisation(mean: Sequence[float], std: Sequence[float]) -> tuple[list[float], list[float]]:
    mean_, std_ = [float(v) for v in mean], [float(v) for v in std]
    if len(mean_) != 3 or len(std_) != 3 or not np.isfinite(mean_ + std_).all() or min(std_) <= 0:
        raise ValueError(
            f"export_refiner: mean and std must be 3 finite numbers each, std positive; got {mean_}, {std_}"
        )
    return mean_, std_


def _export(module: torch.nn.Module, example: torch.Tensor, path: Path, *, dynamic_hw: bool) -> None:
    """torch.onnx.export with a dynamic batch axis, and dynamic height and width when asked."""
    axes: dict[int, object] = {0: torch.export.Dim("batch", min=1, max=64)}
    if dynamic_hw:
        axes[2] = axes[3] = torch.export.Dim.DYNAMIC
    program = torch.onnx.export(
        module,
        (example,),
        input_names=[INPUT],
        output_names=[OUTPUT],
        dynamic_shapes=(axes,),  # positional: the module's forward argument may have any name
        opset_version=OPSET,
        dynamo=True,
        verbose=False,
    )
    program.save(str(path), external_data=False)


def _check(path: Path, examples: list[torch.Tensor], expected: list[np.ndarray]) -> tuple[float, float]:
    """(max |ONNX - torch|, max |torch|) over the examples, run with onnxruntime."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    err = scale = 0.0
    for x, want in zip(examples, expected, strict=True):
        got = session.run(None, {INPUT: x.numpy()})[0]
        if got.shape != want.shape:
            raise ValueError(
                f"{path}: ONNX output has shape {got.shape} for input {tuple(x.shape)}, PyTorch {want.shape}"
            )
        err = max(err, float(np.abs(got - want).max()))
        scale = max(scale, float(np.abs(want).max()))
    return err, scale
