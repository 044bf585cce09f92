"""A monocular depth network run with onnxruntime: the real :class:`DepthEstimator` of the LAD prior.

A model folder is written by ``langfield export depth`` (:func:`encoders.export.depth.export_depth`)::

    depth/
      manifest.json    kind "depth": input_size [H, W], mean, std, output "disparity" | "depth"
      depth.onnx       pixels [B, 3, H, W] (normalised) -> [B, H, W]

:meth:`OnnxDepthEstimator.estimate` follows the Hugging Face DPT / Depth Anything pipeline
(``DPTImageProcessor`` then ``post_process_depth_estimation`` in transformers): resize the image to the
network's input size, normalise with the manifest's mean and std, run, and resize the prediction back
to the image's size. The ONNX graph has a fixed input size (DINOv2's position-embedding interpolation
does not export with dynamic height and width), so images of another aspect ratio are stretched to
it, as the common Depth Anything ONNX ports do; export with an input size close to your images'
aspect ratio to avoid that. Resizing uses OpenCV: area averaging when shrinking (PIL's bicubic resize
is antialiased too), bicubic when enlarging, and bilinear for the output (no overshoot).

Example:
    >>> est = OnnxDepthEstimator("models/depth")  # doctest: +SKIP
    >>> est.kind, est.estimate(np.zeros((240, 320, 3), np.float32)).shape  # doctest: +SKIP
    ('disparity', (240, 320))
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from encoders.manifest import ManifestError, manifest_normalisation, onnx_session, read_manifest
from encoders.protocols import DEPTH_KINDS, DepthKind, check_image

__all__ = ["OnnxDepthEstimator"]


class OnnxDepthEstimator:
    """DPT / MiDaS / Depth Anything exported to ONNX, behind the DepthEstimator protocol.

    Args:
        model_dir: the folder ``langfield export depth --out`` wrote.

    Attributes:
        kind: "disparity" (relative inverse depth: DPT, MiDaS, Depth Anything) or "depth" (larger is
            farther, e.g. a metric Depth Anything head), from the manifest's ``output``.
        input_size: (H, W) the network runs at.
        model: the manifest's model name.

    Raises:
        ManifestError: a missing or malformed manifest, or the ONNX file missing; the message names it.
        ValueError: an ONNX file whose input or output disagrees with the manifest.

    Example:
        >>> OnnxDepthEstimator("models/depth").input_size  # doctest: +SKIP
        (518, 518)
    """

    def __init__(self, model_dir: str | Path) -> None:
        self.model_dir = Path(model_dir)
        manifest = read_manifest(self.model_dir, "depth")
        where = self.model_dir / "manifest.json"
        if "model" not in manifest["files"]:
            raise ManifestError(f"{where}: 'files' has no 'model' entry")
        kind = manifest.get("output")
        if kind not in DEPTH_KINDS:
            raise ManifestError(f"{where}: 'output' must be one of {DEPTH_KINDS}, got {kind!r}")
        self.kind: DepthKind = kind
        self.model = str(manifest.get("model", ""))
        size = manifest.get("input_size")
        if (
            not isinstance(size, list)
            or len(size) != 2
            or any(isinstance(v, bool) or not isinstance(v, int) or v < 1 for v in size)
        ):
            raise ManifestError(f"{where}: 'input_size' must be [H, W], two positive integers, got {size!r}")
        self.input_size = (size[0], size[1])
        self._mean, self._std = manifest_normalisation(manifest, where)
        self._path = manifest["files"]["model"]
        self._session = onnx_session(self._path)
        inputs = self._session.get_inputs()
        shape = list(inputs[0].shape) if len(inputs) == 1 else []
        if len(inputs) != 1 or len(shape) != 4 or shape[1:] != [3, *self.input_size]:
            raise ValueError(
                f"{self._path}: expected one input of shape [batch, 3, {size[0]}, {size[1]}] as "
                f"{where} says, got {[(i.name, i.shape) for i in inputs]}"
            )

    def estimate(self, image: np.ndarray) -> np.ndarray:
        """Relative disparity (or depth) of one image.

        Args:
            image: [H, W, 3] float32 RGB in [0, 1] (uint8 is accepted).

        Returns:
            [H, W] float32, finite; its scale and shift mean nothing.
        """
        img = check_image(image, "OnnxDepthEstimator.estimate")
        h, w = img.shape[:2]
        net_h, net_w = self.input_size
        shrink = net_h * net_w < h * w
        x = cv2.resize(img, (net_w, net_h), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC)
        x = ((x - self._mean) / self._std).transpose(2, 0, 1)[None]
        out = np.asarray(
            self._session.run(None, {self._session.get_inputs()[0].name: x.astype(np.float32)})[0]
        )
        if out.ndim != 3 or out.shape[0] != 1:
            raise ValueError(f"{self._path}: returned shape {out.shape}, expected [1, H, W]")
        pred = out[0].astype(np.float32)
        if not np.isfinite(pred).all():
            raise ValueError(f"{self._path}: returned NaN or inf values")
        if pred.shape != (h, w):
            pred = cv2.resize(pred, (w, h), interpolation=cv2.INTER_LINEAR)
        return np.ascontiguousarray(pred, dtype=np.float32)
