"""SAM (segment-anything) to two ONNX models: the image encoder, and the prompt encoder + mask decoder.

The folder this writes is read by :class:`encoders.onnx_sam.OnnxSamSegmenter`::

    sam/
      manifest.json             kind "sam": input_size, mean, std, mask_threshold, levels
      image_encoder.onnx        image [1, 3, S, S] -> image_embeddings [1, C, S/16, S/16]
      image_encoder.onnx.data   its weights, only beyond protobuf's 2 GB limit (ViT-H)
      decoder.onnx              image_embeddings, point_coords [B, N, 2], point_labels [B, N]
                                -> iou_predictions [B, 3], low_res_masks [B, 3, S/4, S/4]

The image encoder takes the image already resized so its longer side is S (1024), normalised with
``mean`` / ``std`` (ImageNet's, for pixel values in [0, 1]; SAM stores them x 255) and zero-padded at
the bottom and right, as ``SamPredictor.set_image`` prepares it; the runtime does that in numpy.

The decoder follows segment-anything's ``SamOnnxModel`` (``utils/onnx.py``) and
``scripts/export_onnx_model.py``: point coordinates are in the resized S x S frame, labels are 1
(foreground), 0 (background), 2 / 3 (box corners) or -1 (padding; SAM adds one padding point at
(0, 0) when there is no box). It differs in three ways, all for the automatic mask generator: the
batch axis of the prompts is dynamic (one single-point prompt per row, decoded against one
embedding, as ``MaskDecoder.predict_masks`` repeats the embedding per prompt); it returns only the
three multimask outputs (tokens 1-3, as ``MaskDecoder.forward`` with ``multimask_output=True``),
not the single-mask token 0; and it has no mask input and no upsampling (the runtime upsamples only
the masks that pass the IoU filter).

Export runs torch.onnx's torch.export-based exporter (``dynamo=True``, which needs onnxscript); ViT-B
takes about a minute and a half on a 2-core CPU, then each model is run once with onnxruntime against
PyTorch.

Weights: https://github.com/facebookresearch/segment-anything#model-checkpoints
(``sam_vit_b_01ec64.pth``, ``sam_vit_l_0b3195.pth``, ``sam_vit_h_4b8939.pth``).

Example:
    >>> export_sam("models/sam", checkpoint="sam_vit_b_01ec64.pth", model_type="vit_b")  # doctest: +SKIP
    PosixPath('models/sam')
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from encoders.manifest import MANIFEST, write_manifest
from encoders.onnx_sam import (
    EMBEDDINGS,
    ENCODER_INPUT,
    IOU_PREDICTIONS,
    LOW_RES_MASKS,
    POINT_COORDS,
    POINT_LABELS,
)
from encoders.protocols import LEVELS

__all__ = ["export_sam"]

ENCODER_FILE = "image_encoder.onnx"
DECODER_FILE = "decoder.onnx"
_CHECK_TOL = 1e-3  # exporter self-check: max |ONNX - PyTorch| relative to the output's scale


def export_sam(
    out_dir: str | Path,
    checkpoint: str | Path | None = None,
    model_type: str = "vit_b",
    model: Any = None,
) -> Path:
    """Exports SAM's image encoder and mask decoder to ONNX and writes the manifest.

    Each model is checked once against PyTorch with onnxruntime before the manifest is written.

    Args:
        out_dir: the model folder (created if needed).
        checkpoint: a segment-anything checkpoint (``.pth``), loaded with
            ``segment_anything.sam_model_registry[model_type]``.
        model_type: "vit_b", "vit_l" or "vit_h" (with ``checkpoint``).
        model: a ``segment_anything.modeling.Sam`` to export instead of a checkpoint (tests pass a
            tiny, randomly initialised one).

    Returns:
        ``out_dir`` as a Path, ready for ``OnnxSamSegmenter(out_dir)``.
    """
    if model is None:
        if checkpoint is None:
            raise ValueError(
                "export_sam: pass checkpoint= (e.g. sam_vit_b_01ec64.pth from "
                "https://github.com/facebookresearch/segment-anything#model-checkpoints) or model="
            )
        try:
            from segment_anything import sam_model_registry
        except ImportError as exc:
            raise ImportError(
                "export_sam needs segment-anything: pip install 'langfield[export]' "
                "(or pip install segment-anything)"
            ) from exc
        if model_type not in ("vit_b", "vit_l", "vit_h"):
            raise ValueError(f"export_sam: model_type must be vit_b, vit_l or vit_h, got {model_type!r}")
        model = sam_model_registry[model_type](checkpoint=str(checkpoint))
        name = f"sam_{model_type} ({Path(checkpoint).name})"
    else:
        enc = model.image_encoder
        width = enc.patch_embed.proj.out_channels
        name = f"sam (in-memory model: ViT embed_dim {width}, {len(enc.blocks)} blocks)"
    model = model.eval().float().cpu()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / MANIFEST).unlink(missing_ok=True)  # until the new one is written, the folder is unfinished
    size = int(model.image_encoder.img_size)

    image = torch.randn(1, 3, size, size, generator=torch.Generator().manual_seed(0))
    encoder_files = _export_encoder(model, image, out)
    with torch.no_grad():
        embedding = model.image_encoder(image)
    decoder = _MultimaskDecoder(model).eval()
    coords, labels = _example_prompts(size, batch=3)
    _export_decoder(decoder, (embedding, coords, labels), out / DECODER_FILE)

    _check(out / ENCODER_FILE, {ENCODER_INPUT: image}, [embedding], "image encoder")
    coords, labels = _example_prompts(size, batch=5)  # another batch size than the traced one
    inputs = {EMBEDDINGS: embedding, POINT_COORDS: coords, POINT_LABELS: labels}
    _check(out / DECODER_FILE, inputs, list(decoder(embedding, coords, labels)), "decoder")

    mean = [round(float(v) / 255.0, 6) for v in model.pixel_mean.flatten()]
    std = [round(float(v) / 255.0, 6) for v in model.pixel_std.flatten()]
    write_manifest(
        out,
        "sam",
        name,
        {"image_encoder": ENCODER_FILE, "decoder": DECODER_FILE, **encoder_files},
        input_size=size,
        mean=mean,
        std=std,
        mask_threshold=float(model.mask_threshold),
        levels=list(LEVELS),
    )
    return out


class _MultimaskDecoder(torch.nn.Module):
    """Prompt encoder + mask decoder for point prompts: the three multimask outputs, low resolution.

    Reuses ``SamOnnxModel._embed_points`` (segment-anything's traceable point embedding); the dense
    prompt is SAM's "no mask" embedding, as ``PromptEncoder.forward`` gives without a mask input.
    """

    def __init__(self, sam: Any) -> None:
        super().__init__()
        from segment_anything.utils.onnx import SamOnnxModel

        self.onnx_model = SamOnnxModel(sam, return_single_mask=False)

    @torch.no_grad()
    def forward(
        self, image_embeddings: torch.Tensor, point_coords: torch.Tensor, point_labels: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        sparse = self.onnx_model._embed_points(point_coords, point_labels)
        sam = self.onnx_model.model
        prompt = sam.prompt_encoder
        dense = prompt.no_mask_embed.weight.reshape(1, -1, 1, 1).expand(1, -1, *image_embeddings.shape[-2:])
        masks, iou = sam.mask_decoder.predict_masks(
            image_embeddings=image_embeddings,
            image_pe=prompt.get_dense_pe(),
            sparse_prompt_embeddings=sparse,
            dense_prompt_embeddings=dense,
        )
        return iou[:, 1:], masks[:, 1:]  # token 0 is the single-mask output


def _example_prompts(size: int, batch: int) -> tuple[torch.Tensor, torch.Tensor]:
    """[batch, 2, 2] coordinates and [batch, 2] labels: one foreground point plus SAM's padding point."""
    g = torch.Generator().manual_seed(batch)
    coords = torch.zeros(batch, 2, 2)
    coords[:, 0] = torch.rand(batch, 2, generator=g) * size
    labels = torch.tensor([[1.0, -1.0]]).repeat(batch, 1)
    return coords, labels


def _export_encoder(model: Any, image: torch.Tensor, out: Path) -> dict[str, str]:
    """Writes image_encoder.onnx; returns extra manifest files (the external weights of ViT-H).

    The exporter moves the weights to ``image_encoder.onnx.data`` by itself when they pass protobuf's
    2 GB limit (ViT-H); ViT-B and ViT-L stay in one file.
    """
    path = out / ENCODER_FILE
    weights = path.with_name(path.name + ".data")
    weights.unlink(missing_ok=True)  # a stale one from an earlier export would be listed otherwise
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model.image_encoder,
            (image,),
            str(path),
            input_names=[ENCODER_INPUT],
            output_names=[EMBEDDINGS],
            dynamo=True,
            external_data=False,
            verbose=False,
        )
    return {"image_encoder_weights": weights.name} if weights.exists() else {}


def _export_decoder(decoder: torch.nn.Module, inputs: tuple[torch.Tensor, ...], path: Path) -> None:
    """Writes decoder.onnx with dynamic prompt batch and point count."""
    batch, points = torch.export.Dim("batch"), torch.export.Dim("num_points")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            decoder,
            inputs,
            str(path),
            input_names=[EMBEDDINGS, POINT_COORDS, POINT_LABELS],
            output_names=[IOU_PREDICTIONS, LOW_RES_MASKS],
            dynamic_shapes={
                "image_embeddings": None,
                "point_coords": {0: batch, 1: points},
                "point_labels": {0: batch, 1: points},
            },
            dynamo=True,
            external_data=False,
            verbose=False,
        )


def _check(path: Path, inputs: dict[str, torch.Tensor], expected: list[torch.Tensor], what: str) -> None:
    """Runs the ONNX model with onnxruntime and raises if it disagrees with PyTorch."""
    import onnxruntime as ort

    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, {k: v.numpy() for k, v in inputs.items()})
    for g, e in zip(got, expected, strict=True):
        e = e.detach().numpy()
        err = float(np.abs(g - e).max())
        if g.shape != e.shape or err > _CHECK_TOL * (1.0 + float(np.abs(e).max())):
            raise RuntimeError(
                f"export_sam: the exported {what} ({path}) disagrees with PyTorch: shapes {g.shape} vs "
                f"{e.shape}, max abs error {err:.3g}"
            )
