"""A segmenter without weights: Felzenszwalb-Huttenlocher graph segmentation at three scales.

langfield keeps a classical fallback beside SAM, so a scene can be
preprocessed with no model download at all. Felzenszwalb and Huttenlocher's "Efficient Graph-Based
Image Segmentation" (IJCV 2004) merges 8-connected pixels along edges of increasing colour
difference while the difference stays below each region's internal difference plus k / |region|;
a larger k gives larger regions, ``sigma`` smooths the image first and regions smaller than
``min_size`` are merged into a neighbour. OpenCV contrib implements it
(``cv2.ximgproc.segmentation.createGraphSegmentation``), which needs the package
``opencv-contrib-python-headless`` instead of ``opencv-python-headless``.

One partition per level, from fine to coarse, each region one mask:

=========  =====  ======  =======================
level      sigma  k       min_size (of the image)
=========  =====  ======  =======================
subpart    0.5    200     0.2 %
part       0.8    500     1 %
whole      1.0    1000    1.5 %
=========  =====  ======  =======================

k is in units of 8-bit colour difference (the image is segmented as uint8 RGB), as in the paper's
examples (k = 300 on images of about 320 x 240). ``min_size`` is a fraction of the image area, so a
level gives about as many masks at any resolution; on the 504 x 378 LLFF fern views the three levels
give about 110, 20 and 10 masks. Unlike SAM's levels these partitions do not overlap
within a level, and region boundaries follow colour, not objects.

Example:
    >>> import numpy as np
    >>> image = np.zeros((48, 64, 3), np.float32); image[:, 32:] = 1.0
    >>> [m.shape for m in GraphSegmenter().segment(image)]  # doctest: +SKIP
    [(2, 48, 64), (2, 48, 64), (2, 48, 64)]
"""

from __future__ import annotations

import cv2
import numpy as np

from encoders.protocols import LEVELS, check_image

__all__ = ["DEFAULT_SCALES", "GraphSegmenter"]

# (sigma, k, min_size as a fraction of the image area) for subpart, part, whole.
DEFAULT_SCALES: tuple[tuple[float, float, float], ...] = (
    (0.5, 200.0, 0.002),
    (0.8, 500.0, 0.01),
    (1.0, 1000.0, 0.015),
)


class GraphSegmenter:
    """Felzenszwalb-Huttenlocher graph segmentation at three scales, one partition per level.

    Args:
        scales: (sigma, k, min_size fraction of the image area) per level (subpart, part, whole),
            finest first; see the module docstring for the defaults.

    Raises:
        ImportError: if OpenCV lacks the contrib module ``ximgproc`` (install
            opencv-contrib-python-headless in place of opencv-python-headless).

    Example:
        >>> seg = GraphSegmenter()  # doctest: +SKIP
        >>> subpart, part, whole = seg.segment(image)  # doctest: +SKIP
    """

    def __init__(self, scales: tuple[tuple[float, float, float], ...] = DEFAULT_SCALES) -> None:
        if not hasattr(cv2, "ximgproc"):
            raise ImportError(
                "GraphSegmenter needs OpenCV's contrib modules (cv2.ximgproc), which this OpenCV "
                f"({cv2.__version__}) lacks: pip uninstall -y opencv-python-headless && "
                "pip install opencv-contrib-python-headless"
            )
        if len(scales) != len(LEVELS):
            raise ValueError(f"GraphSegmenter: scales must have {len(LEVELS)} entries, got {len(scales)}")
        for sigma, k, frac in scales:
            if sigma < 0 or k <= 0 or not 0 <= frac < 1:
                raise ValueError(
                    "GraphSegmenter: need sigma >= 0, k > 0, 0 <= min_size fraction < 1, "
                    f"got {(sigma, k, frac)}"
                )
        self.scales = tuple((float(s), float(k), float(f)) for s, k, f in scales)

    def segment(self, image: np.ndarray) -> list[np.ndarray]:
        """Masks of one image at the three levels.

        Args:
            image: [H, W, 3] float32 RGB in [0, 1] (uint8 is accepted).

        Returns:
            3 bool arrays [M_l, H, W] for (subpart, part, whole); the masks of a level are disjoint
            and cover the image; largest first.
        """
        img = check_image(image, "GraphSegmenter.segment")
        h, w = img.shape[:2]
        rgb8 = np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8)
        out = []
        for sigma, k, frac in self.scales:
            min_size = max(1, int(round(frac * h * w)))
            graph = cv2.ximgproc.segmentation.createGraphSegmentation(sigma, k, min_size)
            labels = graph.processImage(rgb8)
            out.append(_label_masks(labels))
        return out


def _label_masks(labels: np.ndarray) -> np.ndarray:
    """[M, H, W] bool, one mask per label of an [H, W] label image, largest first."""
    ids, flat, counts = np.unique(labels, return_inverse=True, return_counts=True)
    order = np.argsort(-counts, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(ids))
    return rank[flat.reshape(labels.shape)][None] == np.arange(len(ids))[:, None, None]
