"""Virtual cameras between and around the training cameras, for pseudo-view supervision.

Sparse-view Gaussian splatting overfits the few training views; rendering the splats from cameras that
no image was taken from, and supervising those renders with a prior, constrains the scene between
them. FSGS (Zhu et al., ECCV 2024, arXiv:2312.00451) synthesises such virtual views near the training
cameras for its depth prior; Difix3D+ (Wu et al., CVPR 2025, arXiv:2503.01774) renders views on the
way from the training cameras to novel ones and cleans them with a diffusion model before training on
them (:class:`encoders.onnx_refiner.OnnxImageRefiner` is that cleaning step here).

:func:`sample_virtual_cameras` picks two training cameras at random and interpolates between them at a
random fraction t: the centre linearly, the orientation along the shortest rotation between the two
(quaternion slerp, Shoemake, "Animating rotation with quaternion curves", SIGGRAPH 1985), so that the
virtual camera turns at constant angular speed and stays a rotation. The centre is then moved by
``jitter`` times the mean distance between the training centres in a uniformly random direction, so
that virtual views also leave the segments between the training cameras. Everything is drawn from the
given ``numpy.random.Generator``: the same generator state gives the same cameras.

Example:
    >>> a = Camera.look_at((1, -3, 1), (0, 0, 0), name="a")
    >>> b = Camera.look_at((-1, -3, 1), (0, 0, 0), name="b")
    >>> cams = sample_virtual_cameras([a, b], 4, np.random.default_rng(0))
    >>> [c.name for c in cams]
    ['virtual_0', 'virtual_1', 'virtual_2', 'virtual_3']
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from langfield.camera import Camera, camera_spacing

__all__ = ["interpolate_camera", "sample_virtual_cameras"]


def sample_virtual_cameras(
    cameras: list[Camera], n: int, rng: np.random.Generator, *, jitter: float = 0.1
) -> list[Camera]:
    """``n`` virtual cameras between and around the training cameras.

    Each one interpolates two distinct training cameras chosen at random (the same one twice when there
    is only one) at t uniform in [0, 1] (:func:`interpolate_camera`), then moves its centre by
    ``jitter * d`` in a uniformly random direction, where d is the mean distance between the training
    centres. With a single camera, or cameras that all share one centre, d is the mean distance of the
    centres from the world origin (the scene centre of normalised datasets such as nerfstudio's and
    Blender's), or 1 if that is 0 too.

    Args:
        cameras: the training cameras (at least one).
        n: how many virtual cameras, >= 0.
        rng: the random generator; the cameras depend on it alone.
        jitter: the centre's displacement as a fraction of d, >= 0 (0: on the segments between cameras).

    Returns:
        ``n`` cameras named ``virtual_0`` ... ``virtual_{n-1}``, with the intrinsics and image size of
        the first of their two training cameras and an orthonormal rotation (det +1).

    Raises:
        ValueError: no cameras, a negative or non-integer ``n``, or a negative or non-finite ``jitter``.
    """
    if len(cameras) < 1:
        raise ValueError("sample_virtual_cameras: needs at least one training camera, got none")
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
        raise ValueError(f"sample_virtual_cameras: n must be an integer >= 0, got {n!r}")
    if not (np.isfinite(jitter) and jitter >= 0):
        raise ValueError(f"sample_virtual_cameras: jitter must be finite and >= 0, got {jitter!r}")
    centres = np.stack([c.center for c in cameras])  # [C, 3]
    step = jitter * _spread(centres)
    out = []
    for i in range(int(n)):
        if len(cameras) == 1:
            a = b = 0
        else:
            a, b = (int(k) for k in rng.choice(len(cameras), size=2, replace=False))
        t = float(rng.uniform(0.0, 1.0))
        # Drawn even when jitter is 0, so that the pairs and fractions do not depend on it.
        direction = rng.standard_normal(3)
        direction /= max(float(np.linalg.norm(direction)), 1e-12)
        cam = interpolate_camera(cameras[a], cameras[b], t, name=f"virtual_{i}")
        c2w = cam.c2w.copy()
        c2w[:3, 3] += step * direction
        out.append(replace(cam, c2w=c2w))
    return out


def interpolate_camera(a: Camera, b: Camera, t: float, *, name: str = "") -> Camera:
    """The camera a fraction ``t`` of the way from ``a`` to ``b``.

    The centre is interpolated linearly, the rotation by slerp along the shortest arc; intrinsics and
    image size are ``a``'s. A rotation that is not quite orthonormal (rounding in a dataset's poses) is
    first replaced by the nearest rotation, so the result's rotation is orthonormal with det +1.

    Args:
        a: the camera at t = 0.
        b: the camera at t = 1.
        t: the fraction, in [0, 1] (values outside extrapolate).
        name: the new camera's name.

    Returns:
        The interpolated camera (``a`` itself, renamed, at t = 0 up to rounding; ``b``'s pose at t = 1).
    """
    q = _slerp(_quaternion(a.c2w[:3, :3]), _quaternion(b.c2w[:3, :3]), float(t))
    c2w = np.eye(4)
    c2w[:3, :3] = _rotation(q)
    c2w[:3, 3] = (1.0 - t) * a.center + t * b.center
    return replace(a, name=name, c2w=c2w)


def _spread(centres: np.ndarray) -> float:
    """The length jitter is a fraction of: mean pairwise distance of [C, 3] centres (see above)."""
    d = camera_spacing(centres)
    if d > 0:
        return d
    d = float(np.linalg.norm(centres, axis=1).mean())
    return d if d > 0 else 1.0


def _nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation (det +1) closest to [3, 3] ``m`` in the Frobenius norm, by SVD."""
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt)) or 1.0
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _quaternion(m: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of the rotation nearest [3, 3] ``m``.

    Shepperd's method: solve from the largest of 1 + trace and the diagonal-dominated alternatives, so
    the square root is never of a number near 0 (which loses precision near 180 degree rotations).
    """
    r = _nearest_rotation(m)
    tr = np.trace(r)
    k = int(np.argmax([tr, r[0, 0], r[1, 1], r[2, 2]]))
    if k == 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif k == 1:
        s = 2.0 * np.sqrt(1.0 + 2.0 * r[0, 0] - tr)
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif k == 2:
        s = 2.0 * np.sqrt(1.0 + 2.0 * r[1, 1] - tr)
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + 2.0 * r[2, 2] - tr)
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _rotation(q: np.ndarray) -> np.ndarray:
    """[3, 3] rotation of the quaternion (w, x, y, z), normalised first."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def _slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions along the shorter arc (q and -q are one
    rotation: flipping q1 when the dot product is negative turns by less than 180 degrees)."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    theta = np.arccos(min(dot, 1.0))
    if theta < 1e-6:  # nearly equal: sin(theta) ~ 0, and the normalised lerp is exact to O(theta^3)
        q = (1.0 - t) * q0 + t * q1
    else:
        q = (np.sin((1.0 - t) * theta) * q0 + np.sin(t * theta) * q1) / np.sin(theta)
    return q / np.linalg.norm(q)
