"""An image-to-image refiner run with onnxruntime: cleans a rendered pseudo view into a training target.

Sparse-view methods that distil a 2D prior into the splats render a virtual view, let an image-to-image
network remove the floaters, holes and blur of the under-constrained render, and train on the cleaned
image where the network is confident: Difix3D+ (Wu et al., CVPR 2025, arXiv:2503.01774) with a
single-step diffusion "fixer", Sp2360 (Paul et al., arXiv:2405.16517) with a cascade of inpainting and
artifact-removal models, GScenes (Paul et al., arXiv:2411.15966) with an image-to-image model and a
per-pixel confidence. This module is the runtime half of that loop and knows nothing of the network:
any model exported to a folder that follows the manifest works (:func:`encoders.export.refiner.
export_refiner` writes one from a ``torch.nn.Module``)::

    refiner/
      manifest.json    kind "refiner": input_size [H, W] or null (any size), mean, std, confidence
      model.onnx       pixels [B, 3, H, W] (normalised) -> [B, 3, H', W'] (normalised RGB)
                       or [B, 4, H', W'] (normalised RGB, then confidence logits)

:meth:`OnnxImageRefiner.refine` resizes the image to the network's input size when the manifest fixes
one, normalises it with the manifest's mean and std, runs the network, undoes the normalisation of the
RGB channels, turns the confidence logits into probabilities with a sigmoid (or gives confidence 1
everywhere when the network has no such channel) and resizes both back to the image's size. Resizing
uses OpenCV's area averaging when shrinking (antialiased) and bilinear interpolation when enlarging;
neither overshoots, so the result stays in [0, 1] (it is clipped anyway, as a network's RGB output is
not bounded).

Example:
    >>> refiner = OnnxImageRefiner("models/refiner")  # doctest: +SKIP
    >>> cleaned, confidence = refiner.refine(np.zeros((240, 320, 3), np.float32))  # doctest: +SKIP
    >>> cleaned.shape, confidence.shape  # doctest: +SKIP
    ((240, 320, 3), (240, 320))
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from encoders.manifest import MANIFEST, ManifestError, manifest_normalisation, onnx_session, read_manifest
from encoders.protocols import check_image

__all__ = ["OnnxImageRefiner"]


class OnnxImageRefiner:
    """An image-to-image network exported to ONNX that cleans rendered views.

    Args:
        folder: the model folder (``model.onnx`` or the file the manifest names, and ``manifest.json``).

    Attributes:
        folder: the model folder.
        model: the manifest's model name.
        input_size: (H, W) the network runs at, or None when it takes any size (the image's own).
        confidence: whether the network outputs a fourth, confidence channel (logits).

    Raises:
        ManifestError: a missing folder, a missing or malformed manifest, or the ONNX file missing; the
            message names the folder or file.
        ValueError: an ONNX file that cannot be loaded or whose input or output disagrees with the
            manifest.

    Example:
        >>> OnnxImageRefiner("models/refiner").input_size  # doctest: +SKIP
        (512, 512)
    """

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise ManifestError(f"{self.folder}: no such refiner model folder")
        manifest = read_manifest(self.folder, "refiner")
        where = self.folder / MANIFEST
        if "model" not in manifest["files"]:
            raise ManifestError(f"{where}: 'files' has no 'model' entry")
        self.model = str(manifest.get("model", ""))
        self.input_size = _input_size(manifest, where)
        confidence = manifest.get("confidence")
        if not isinstance(confidence, bool):
            raise ManifestError(f"{where}: 'confidence' must be true or false, got {confidence!r}")
        self.confidence = confidence
        self._mean, self._std = manifest_normalisation(manifest, where)
        self._path = manifest["files"]["model"]
        self._session = onnx_session(self._path)
        self._input = self._check_io(where)

    def refine(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Clean one rendered view.

        Args:
            image: [H, W, 3] float32 RGB in [0, 1] (uint8 is accepted); clamp a render before passing it.

        Returns:
            (cleaned, confidence): [H, W, 3] float32 RGB in [0, 1], and [H, W] float32 in [0, 1] (the
            sigmoid of the network's confidence channel, or all ones when it has none).

        Raises:
            ValueError: an image of the wrong shape, dtype or range, or with NaN / inf; a network output
                of the wrong shape or not finite. The message names the model folder or file.
        """
        img = check_image(image, f"OnnxImageRefiner({self.folder}).refine")
        h, w = img.shape[:2]
        net_hw = self.input_size or (h, w)
        x = _resize(img, net_hw)
        x = ((x - self._mean) / self._std).transpose(2, 0, 1)[None]
        out = np.asarray(self._session.run(None, {self._input: np.ascontiguousarray(x, np.float32)})[0])
        channels = 4 if self.confidence else 3
        if out.ndim != 4 or out.shape[:2] != (1, channels) or min(out.shape[2:]) < 1:
            raise ValueError(
                f"{self._path}: returned shape {out.shape}, expected [1, {channels}, H, W] "
                f"(confidence {str(self.confidence).lower()} in {self.folder / MANIFEST})"
            )
        out = out[0].astype(np.float32, copy=False)
        if not np.isfinite(out).all():
            raise ValueError(f"{self._path}: returned NaN or inf values")
        rgb = out[:3].transpose(1, 2, 0) * self._std + self._mean
        if self.confidence:
            # tanh form of the sigmoid: no overflow warning for large negative logits, exactly in [0, 1]
            conf = 0.5 + 0.5 * np.tanh(0.5 * out[3])
        else:
            conf = np.ones(out.shape[1:], np.float32)
        rgb, conf = _resize(rgb, (h, w)), _resize(conf, (h, w))
        return (
            np.ascontiguousarray(np.clip(rgb, 0.0, 1.0), dtype=np.float32),
            np.ascontiguousarray(np.clip(conf, 0.0, 1.0), dtype=np.float32),
        )

    def _check_io(self, where: Path) -> str:
        """The input's name, after checking the graph's input and output against the manifest."""
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        shape = list(inputs[0].shape) if len(inputs) == 1 else []
        # A dimension is dynamic when onnxruntime reports a name (str) or nothing (None) for it.
        dims = [d if isinstance(d, int) else None for d in shape]
        size = self.input_size
        if (
            len(inputs) != 1
            or len(dims) != 4
            or dims[0] not in (None, 1)  # refine runs one image
            or dims[1] != 3
            or (size is None and dims[2:] != [None, None])
            or (
                size is not None
                and any(d is not None and d != s for d, s in zip(dims[2:], size, strict=True))
            )
        ):
            want = (
                "[batch, 3, H, W] with dynamic H and W"
                if size is None
                else f"[batch, 3, {size[0]}, {size[1]}]"
            )
            raise ValueError(
                f"{self._path}: expected one input of shape {want} as {where} says, "
                f"got {[(i.name, i.shape) for i in inputs]}"
            )
        channels = 4 if self.confidence else 3
        out = list(outputs[0].shape) if outputs else []
        if not outputs or len(out) != 4 or (isinstance(out[1], int) and out[1] != channels):
            raise ValueError(
                f"{self._path}: expected an output of shape [batch, {channels}, H, W] "
                f"(confidence {str(self.confidence).lower()} in {where}), "
                f"got {[(o.name, o.shape) for o in outputs]}"
            )
        return inputs[0].name


def _input_size(manifest: dict, where: Path) -> tuple[int, int] | None:
    if "input_size" not in manifest:
        raise ManifestError(f"{where}: no 'input_size' ([H, W], or null for any size)")
    size = manifest["input_size"]
    if size is None:
        return None
    if (
        not isinstance(size, list)
        or len(size) != 2
        or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in size)
    ):
        raise ManifestError(
            f"{where}: 'input_size' must be [H, W], two positive integers, or null (any size), got {size!r}"
        )
    return size[0], size[1]


def _resize(array: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """[h, w] or [h, w, C] float32 resized to hw: area averaging to shrink, bilinear to enlarge."""
    if array.shape[:2] == hw:
        return array
    shrink = hw[0] * hw[1] < array.shape[0] * array.shape[1]
    interpolation = cv2.INTER_AREA if shrink else cv2.INTER_LINEAR
    return cv2.resize(np.ascontiguousarray(array), (hw[1], hw[0]), interpolation=interpolation)
