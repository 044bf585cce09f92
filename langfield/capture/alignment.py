"""How far recovered camera poses are from known ones, once a similarity transform (scale, rotation,
translation) takes the recovered frame onto the known one: structure from motion fixes poses only up
to such a transform.

The transform is Umeyama's least-squares fit (Umeyama 1991, "Least-squares estimation of
transformation parameters between two point patterns") of each camera's centre and the tips of its
three axes, drawn at the cameras' rms distance from their mean (each pose set at its own scale).
Fitting the centres alone, as COLMAP's ``model_aligner`` does, leaves the rotation to the centres'
spread: for cameras on a nearly planar arc (a walk around a room at one height) a centimetre of centre
error tilts it by degrees (1.7 degrees on a video of the built-in room whose relative rotations were
right to 0.5 degrees); the axes pin it to the orientations as well.

Example:
    >>> import numpy as np
    >>> c2w = np.stack([np.eye(4)] * 3); c2w[:, :3, 3] = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    >>> moved = c2w.copy(); moved[:, :3, 3] = 2 * moved[:, :3, 3] + 5
    >>> errors = pose_errors(moved, c2w)
    >>> print(f'{errors["rotation_deg"].max():.6f} {errors["centre"].max():.6f}')
    0.000000 0.000000
"""

from __future__ import annotations

import numpy as np

__all__ = ["align_poses", "pose_errors", "umeyama"]


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation [3, 3], translation [3]) minimising sum |scale R source + t - target|^2.

    Args:
        source, target: [N, 3] corresponding points, N >= 3 and not all on one line.
    """
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3 or len(source) < 3:
        raise ValueError(f"umeyama: need two [N, 3] arrays with N >= 3, got {source.shape}, {target.shape}")
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    s, t = source - mu_s, target - mu_t
    u, d, vt = np.linalg.svd(t.T @ s / len(source))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rotation = u @ sign @ vt
    variance = (s**2).sum() / len(source)
    if variance <= 0:
        raise ValueError("umeyama: the source points coincide")
    scale = float(np.trace(np.diag(d) @ sign) / variance)
    return scale, rotation, mu_t - scale * rotation @ mu_s


def _frame_points(c2w: np.ndarray) -> np.ndarray:
    """[4N, 3]: each camera's centre and its axes' tips at the centres' rms spread (1 if they coincide)."""
    centres = c2w[:, :3, 3]
    spread = float(np.sqrt(((centres - centres.mean(axis=0)) ** 2).sum(axis=1).mean())) or 1.0
    tips = centres[:, None, :] + spread * np.swapaxes(c2w[:, :3, :3], 1, 2)  # row k: axis k
    return np.concatenate([centres, tips.reshape(-1, 3)])


def align_poses(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation [3, 3], translation [3]) taking the cameras ``source`` [N, 4, 4] onto the same
    cameras ``target`` [N, 4, 4] (camera-to-world, one axes convention): Umeyama on their centres and
    axis tips (the module docstring)."""
    return umeyama(
        _frame_points(np.asarray(source, np.float64)), _frame_points(np.asarray(target, np.float64))
    )


def pose_errors(estimated: np.ndarray, reference: np.ndarray) -> dict[str, np.ndarray | float]:
    """Per-camera errors of ``estimated`` against ``reference`` after the similarity alignment.

    Args:
        estimated, reference: [N, 4, 4] camera-to-world matrices of the same cameras, same axes
            convention (both OpenGL or both OpenCV).

    Returns:
        {"rotation_deg": [N] angle between the aligned and reference rotations, "centre": [N] distance
        between the aligned and reference centres, "scale": the alignment's scale, "size": the
        reference centres' largest distance from their mean (to express "centre" relative to the
        scene's size)}.
    """
    estimated, reference = np.asarray(estimated, np.float64), np.asarray(reference, np.float64)
    scale, rotation, translation = align_poses(estimated, reference)
    centres = scale * estimated[:, :3, 3] @ rotation.T + translation
    aligned = np.einsum("ij,njk->nik", rotation, estimated[:, :3, :3])
    relative = np.einsum("nji,njk->nik", aligned, reference[:, :3, :3])
    cos = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    size = float(np.linalg.norm(reference[:, :3, 3] - reference[:, :3, 3].mean(axis=0), axis=1).max())
    return {
        "rotation_deg": np.degrees(np.arccos(cos)),
        "centre": np.linalg.norm(centres - reference[:, :3, 3], axis=1),
        "scale": scale,
        "size": size,
    }
