"""Where the Gaussians start, from the training photos themselves (``--init``; no network).

:func:`start_points` runs one method (:mod:`~langfield.training.start.points` says what each does):

- ``dense``: plane-sweep stereo on the training views (:mod:`~langfield.training.start.stereo`).
- ``depth``: the stereo first, then each view's depth prior fitted to it, the fits aligned so that the
  views agree, each prior corrected and the views fused (:mod:`~langfield.training.start.depth_prior`,
  which calls :mod:`~langfield.training.start.alignment` and :mod:`~langfield.training.start.correction`
  in that order).
- ``sfm``: COLMAP's sparse SIFT points triangulated with the known poses (:mod:`~langfield.training.
  start.sfm`).
- ``points``: the scene's own point cloud; ``random``: uniform in the bounds.

Every method is topped up near its surfaces to the Gaussian count asked for, plus a sparse random fill
(:mod:`~langfield.training.start.points`). Patch matching lives in :mod:`~langfield.training.start.
matching`; pixel geometry is :class:`~langfield.camera.Camera`'s (``project``, ``unproject``).
"""

from langfield.training.start.depth_prior import INIT_ALIGNS, depth_prior_points
from langfield.training.start.points import INIT_METHODS, MIN_POINTS, StartPoints, random_points, start_points
from langfield.training.start.stereo import (
    SWEEP_PLANES,
    SWEEP_VIEWS,
    PlaneSweepConfig,
    dense_points,
    plane_sweep,
    stereo_depths,
)

__all__ = [
    "INIT_ALIGNS",
    "INIT_METHODS",
    "MIN_POINTS",
    "SWEEP_PLANES",
    "SWEEP_VIEWS",
    "PlaneSweepConfig",
    "StartPoints",
    "dense_points",
    "depth_prior_points",
    "plane_sweep",
    "random_points",
    "start_points",
    "stereo_depths",
]
