"""Regularisers for training from three views, each a switch of
:class:`langfield.training.config.TrainConfig`.

- Gaussian dropout (DropGaussian, Park et al., CVPR 2025): each iteration a random fraction
  r_t = gamma t / T of the Gaussians is left out of the render and the opacities of the rest are
  scaled by 1 / (1 - r_t); every Gaussian renders at test time. Gaussians hidden behind others then
  get gradients and must explain the images too, which three views otherwise never ask of them.
- Virtual-view consistency (Binocular-guided 3DGS, Han et al., NeurIPS 2024, sec. 3.2): the training
  camera is shifted sideways by a baseline b, the shifted view is rendered, and warped back to the
  training view with the disparity f b / z of the training view's rendered depth; the warp must give
  the training image (L1 + D-SSIM). A wrong depth warps the wrong pixels, so the loss corrects the
  geometry between the views from the photos alone. Optionally the shift takes any direction in the
  image plane: object scans whose test views also differ in elevation need vertical parallax too.
  Or the camera orbits: it turns about the point at the median rendered depth ahead of it, so that it
  keeps the scene in view while it moves (the way DTU's and Blender's test views stand around an
  object), and the warp is a general reprojection that drops the pixels the virtual view sees occluded.
- Edge-aware depth smoothness (Godard et al., CVPR 2017, eq. 3, as monocular depth training uses it):
  the rendered depth, divided by its mean so the term does not depend on the scene's scale, should
  change little where the image does not; textureless surfaces (a white table) then take their depth
  from the textured edges around them instead of being explained by floaters anywhere on the ray.
- Depth spread (Mip-NeRF 360's distortion loss, Barron et al., CVPR 2022, eq. 15; 2D Gaussian
  splatting's, Huang et al., SIGGRAPH 2024, eq. 13, between Gaussians): the blending weights of a pixel
  should gather at one depth. Here in squared form, ``1/2 sum_ij w_i w_j (d_i - d_j)^2`` over the
  Gaussians' centres, which two rendered channels give in closed form (``alpha S - D^2``; the field
  renders it, :attr:`langfield.field.Render.depth_spread`) where the absolute form needs a sorted pass
  of its own. Three views leave an untextured wall free to be many faint layers spread along each ray:
  they fit the training images, but from a new angle, and in the 3D selection, they are off the wall.
- Anisotropy penalty: needle-thin Gaussians fit a training view with a streak that crosses every other
  view (the Blender lego far views); max scale / min scale above ``ratio`` is penalised
  (PhysGaussian's anisotropy regulariser, Xie et al., CVPR 2024, eq. 9).
- Empty space the photos show: where an image has alpha its background is no surface, and where a
  photo has a black backdrop (DTU's unlit studio) the backdrop is none either. Three views leave that
  backdrop free to be painted by opaque black Gaussians anywhere on its rays, and from a new angle they
  stand in front of the object. :func:`dark_backdrop` finds it from the image alone, with the rule
  DNGaussian (Li et al., CVPR 2024) and Binocular-guided 3DGS use on DTU: the brightest channel below
  30/255 over a vertical run of a sixth of the image height; here also only where the run's region
  touches the image border, so a dark object inside the frame stays a surface.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from langfield.camera import Camera

__all__ = [
    "anisotropy_loss",
    "dark_backdrop",
    "depth_smoothness",
    "drop_compensation",
    "opacity_noise",
    "orbit_camera",
    "reprojection_warp",
    "shifted_camera",
    "virtual_shift",
    "virtual_view_warp",
    "z_depth",
]


def dark_backdrop(image: np.ndarray, threshold: float = 30 / 255, run: float = 1 / 6) -> np.ndarray:
    """[H, W] bool: the pixels of a photo's black backdrop (module docstring).

    A pixel is backdrop when its brightest channel is below ``threshold`` and so is every pixel above
    it for ``run`` times the image height (or up to the top row), and its 4-connected region of such
    pixels touches the image border.

    Args:
        image: [H, W, 3] RGB in [0, 1].
        threshold: brightest-channel value below which a pixel is dark.
        run: length of the dark vertical run, as a fraction of the height (at least one pixel).
    """
    import cv2

    dark = np.asarray(image).max(axis=-1) < threshold
    height = dark.shape[0]
    need = max(1, round(run * height))
    length = np.zeros(dark.shape, np.int32)  # dark pixels ending at each row, counted from above
    length[0] = dark[0]
    for row in range(1, height):
        length[row] = np.where(dark[row], length[row - 1] + 1, 0)
    rows = np.arange(height)[:, None]
    backdrop = dark & (length >= np.minimum(need, rows + 1))
    if not backdrop.any():
        return backdrop
    count, labels = cv2.connectedComponents(backdrop.astype(np.uint8), connectivity=4)
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    touching = np.zeros(count, bool)
    touching[edge] = True
    touching[0] = False  # label 0: not backdrop
    return touching[labels]


def drop_compensation(n: int, rate: float, generator: torch.Generator) -> Tensor:
    """[n] opacity factors of Gaussian dropout: 0 for the dropped, 1 / (1 - rate) for the rest.

    Args:
        n: number of Gaussians.
        rate: fraction dropped, in [0, 1).
        generator: the random stream (seeded by the trainer).
    """
    if not 0.0 <= rate < 1.0:
        raise ValueError(f"drop rate must be in [0, 1), got {rate}")
    keep = torch.rand(n, generator=generator) >= rate
    return keep.float() / (1.0 - rate)


def opacity_noise(n: int, sigma: float, generator: torch.Generator) -> Tensor:
    """[n] opacity factors ``1 + e``, ``e ~ N(0, sigma^2)`` clipped to [-sigma, sigma]: the opacity noise
    of Chen et al. (NeurIPS 2025, arXiv:2508.12720), which keeps Gaussians from fitting the training
    views only together (co-adaptation). Drawn per Gaussian and iteration; the factors lie in
    [1 - sigma, 1 + sigma].

    Args:
        n: number of Gaussians.
        sigma: the noise's standard deviation, in [0, 1).
        generator: the random stream (seeded by the trainer).
    """
    if not 0.0 <= sigma < 1.0:
        raise ValueError(f"opacity noise must be in [0, 1), got {sigma}")
    noise = torch.randn(n, generator=generator) * sigma
    return 1.0 + noise.clamp(-sigma, sigma)


def shifted_camera(cam: Camera, right: float, up: float = 0.0) -> Camera:
    """The camera moved by ``right`` along its own x axis and ``up`` along its own y axis (OpenGL: up)."""
    c2w = cam.c2w.copy()
    c2w[:3, 3] = c2w[:3, 3] + right * c2w[:3, 0] + up * c2w[:3, 1]
    return replace(cam, name=f"{cam.name}+{right:.3g},{up:.3g}", c2w=c2w)


def orbit_camera(cam: Camera, right: float, up: float, pivot: float) -> Camera:
    """The camera turned about the point ``pivot`` ahead of it on its axis, by the angle
    ``hypot(right, up) / pivot``, towards its own x axis by ``right`` and y axis (OpenGL: up) by ``up``:
    for a small angle the centre moves as :func:`shifted_camera` moves it, and the pivot stays in
    the centre of the image."""
    length = math.hypot(right, up)
    if length == 0.0 or pivot <= 0.0:
        return replace(cam, name=f"{cam.name}~0")
    rotation, centre = cam.c2w[:3, :3], cam.c2w[:3, 3]
    forward = -rotation[:, 2]
    direction = (right * rotation[:, 0] + up * rotation[:, 1]) / length
    axis = np.cross(direction, forward)  # unit: direction is orthogonal to forward
    turn = _rotation(axis, length / pivot)
    target = centre + pivot * forward
    c2w = cam.c2w.copy()
    c2w[:3, :3] = turn @ rotation
    c2w[:3, 3] = target + turn @ (centre - target)
    return replace(cam, name=f"{cam.name}~{right:.3g},{up:.3g}", c2w=c2w)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """[3, 3] rotation by ``angle`` (radians) about the unit ``axis`` (Rodrigues' formula)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def reprojection_warp(
    other_image: Tensor,
    depth_z: Tensor,
    cam: Camera,
    other: Camera,
    other_depth: Tensor | None = None,
    tolerance: float = 0.05,
) -> tuple[Tensor, Tensor]:
    """Warps ``other``'s image onto ``cam`` through ``cam``'s z-depth: each pixel's surface point is
    projected into ``other`` and its image sampled there (bilinear, differentiable in the image and
    the depth). For a camera moved parallel to its image plane this is :func:`virtual_view_warp`.

    Args:
        other_image: [h, w, C] the image of ``other``.
        depth_z: [H, W] ``cam``'s z-depth (> 0 where valid).
        cam, other: the two cameras.
        other_depth: [h, w] ``other``'s own z-depth, if known: a point that lies more than
            ``tolerance`` (relative) behind it is hidden from ``other`` and left out.

    Returns:
        ``(warped [H, W, C], valid [H, W] bool)``: valid where the depth is positive, the point lies in
        front of ``other``, projects inside its image and (given ``other_depth``) is not hidden.
    """
    positive = depth_z > 1e-6
    safe = torch.where(positive, depth_z, torch.ones_like(depth_z))
    uv, z = other.project(cam.unproject(safe))
    u, v = uv[..., 0], uv[..., 1]
    warped, inside = _sample_at(other_image, u, v)
    valid = positive & (z > 1e-6) & inside
    if other_depth is not None:
        h, w = other_image.shape[:2]
        col = u.detach().floor().long().clamp(0, w - 1)
        row = v.detach().floor().long().clamp(0, h - 1)
        seen = other_depth.detach()[row, col]
        valid = valid & ((seen <= 1e-6) | (z.detach() <= seen * (1.0 + tolerance)))
    return warped, valid


def z_depth(distance: Tensor, cam: Camera) -> Tensor:
    """[H, W] z-depth (along the viewing axis) from the distance to the camera centre [H, W]."""
    rays = cam.pixel_rays(dtype=distance.dtype)
    x, y = rays[..., 0], rays[..., 1]
    return distance / torch.sqrt(x * x + y * y + 1.0)


def virtual_view_warp(
    shifted_image: Tensor, depth_z: Tensor, cam: Camera, right: float, up: float = 0.0
) -> tuple[Tensor, Tensor]:
    """Warps the render of :func:`shifted_camera` ``(cam, right, up)`` back onto ``cam``.

    The shift is parallel to the image plane, so a point at z-depth z seen at pixel (u, v) by ``cam``
    is at (u - fx right / z, v + fy up / z) in the shifted view (image rows run down, the camera's y
    axis up); the warp samples the shifted image there (bilinear, differentiable in both the image
    and the depth).

    Args:
        shifted_image: [H, W, C] render of the shifted camera.
        depth_z: [H, W] z-depth of ``cam``'s render (> 0 where valid).
        cam: the training camera.
        right, up: the shift used.

    Returns:
        ``(warped [H, W, C], valid [H, W] bool)``: valid where the depth is positive and the sample
        lands inside the shifted image.
    """
    h, w = depth_z.shape
    v, u = torch.meshgrid(
        torch.arange(h, dtype=depth_z.dtype) + 0.5, torch.arange(w, dtype=depth_z.dtype) + 0.5, indexing="ij"
    )
    positive = depth_z > 1e-6
    inverse = 1.0 / torch.where(positive, depth_z, torch.ones_like(depth_z))
    source_u = u - cam.fx * right * inverse
    source_v = v + cam.fy * up * inverse
    warped, inside = _sample_at(shifted_image, source_u, source_v)
    return warped, positive & inside


def _sample_at(image: Tensor, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """``image`` [h, w, C] sampled bilinearly at pixel coordinates ``u``, ``v`` [H, W] (pixel centres at
    + 0.5; differentiable in the image and the coordinates): ``(samples [H, W, C], inside [H, W])``,
    inside where the coordinates lie between the outer pixel centres."""
    h, w = image.shape[:2]
    grid = torch.stack([2.0 * u / w - 1.0, 2.0 * v / h - 1.0], dim=-1)[None]
    sampled = torch.nn.functional.grid_sample(
        image.permute(2, 0, 1)[None], grid, mode="bilinear", padding_mode="border", align_corners=False
    )
    inside = (u >= 0.5) & (u <= w - 0.5) & (v >= 0.5) & (v <= h - 0.5)
    return sampled[0].permute(1, 2, 0), inside


def free_space_violation(
    points: Tensor, cam: Camera, depth_z: Tensor, covered: Tensor, tolerance: float
) -> tuple[Tensor, Tensor]:
    """How far ``points`` lie in the free space in front of the surface another view renders.

    A point X that one view renders as a surface, projected into ``cam`` at z-depth z, lies in front
    of what ``cam`` renders there (depth D) when z < D: ``cam`` looks through X. That contradicts X
    being opaque (COLMAP's fusion rejects such depths as free-space violations); behind D it is merely
    occluded, which is allowed.

    Args:
        points: [M, 3] world points.
        cam: the other view; ``depth_z`` [H, W] its rendered z-depth, ``covered`` [H, W] bool where it
            renders a surface.
        tolerance: relative depth margin not counted.

    Returns:
        ``(violation [M], valid [M] bool)``: relu(D (1 - tolerance) - z) / D, and where X projects
        into ``cam`` in front of it onto a covered pixel.
    """
    uv, z = cam.project(points)
    ahead = z > 1e-6
    u, v = uv[:, 0], uv[:, 1]
    inside = ahead & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    col = u.detach().floor().long().clamp(0, cam.width - 1)
    row = v.detach().floor().long().clamp(0, cam.height - 1)
    seen = depth_z[row, col]
    valid = inside & covered[row, col] & (seen > 1e-6)
    seen_safe = torch.where(valid, seen, torch.ones_like(seen))
    violation = torch.relu(seen_safe * (1.0 - tolerance) - z) / seen_safe
    return violation * valid, valid


def anisotropy_loss(log_scales: Tensor, ratio: float) -> Tensor:
    """mean over Gaussians of max(max scale / min scale, ratio) - ratio (PhysGaussian eq. 9).

    Args:
        log_scales: [N, 3] log standard deviations.
        ratio: the largest axis ratio left free.
    """
    if log_scales.shape[0] == 0:
        return log_scales.sum()
    spread = log_scales.max(dim=1).values - log_scales.min(dim=1).values
    return (torch.exp(spread).clamp_min(ratio) - ratio).mean()


def virtual_shift(
    depth_z: Tensor,
    valid: Tensor,
    fraction: float,
    rng: np.random.Generator,
    any_direction: bool = False,
    spacing: float = 0.0,
) -> tuple[float, float]:
    """A random ``(right, up)`` shift of the camera, ``fraction`` times the median rendered depth long,
    or ``spacing`` (scene units) where that is longer, but never longer than the median depth (times a
    uniform draw in [0.5, 1]): to the left or right (a stereo pair, as Binocular-guided 3DGS), or with
    ``any_direction`` at a uniform angle in the image plane (vertical parallax as well)."""
    depths = depth_z[valid]
    scale = float(depths.median()) if depths.numel() else 0.0
    draw = rng.uniform(0.5, 1.0)
    if fraction * scale >= spacing:
        length = float(draw * fraction * scale)
    else:
        length = float(draw * min(spacing, scale))
    if any_direction:
        angle = float(rng.uniform(0.0, 2.0 * math.pi))
        return length * math.cos(angle), length * math.sin(angle)
    return float(rng.choice([-1.0, 1.0])) * length, 0.0


def depth_spread_loss(spread: Tensor, depth: Tensor, alpha: Tensor) -> Tensor:
    """The mean depth spread of a render (module docstring) over the squared mean rendered depth.

    Args:
        spread: [H, W] :attr:`langfield.field.Render.depth_spread`.
        depth, alpha: [H, W] the same render's soft depth and alpha; their mean depth (held fixed) makes
            the term free of the scene's scale.
    """
    scale = (depth.sum() / alpha.sum().clamp_min(1e-8)).detach().clamp_min(1e-8)
    return spread.mean() / (scale * scale)


def depth_smoothness(depth: Tensor, image: Tensor, valid: Tensor, edge_weight: float = 10.0) -> Tensor:
    """Edge-aware depth smoothness: mean over valid neighbour pairs of |d_p - d_q| e^{-a |I_p - I_q|}.

    Args:
        depth: [H, W] rendered depth (> 0 where valid); divided by its valid mean, so scale-free.
        image: [H, W, 3] the training image (the edges that allow a depth change).
        valid: [H, W] bool pixels to use (covered by the field).
        edge_weight: a in the weight e^{-a |dI|} (image gradients per channel mean, values in [0, 1]).
    """
    if not bool(valid.any()):
        return depth.sum() * 0.0
    d = depth / depth[valid].mean().detach().clamp_min(1e-8)
    total, count = depth.new_zeros(()), 0
    for axis in (0, 1):
        dd = torch.diff(d, dim=axis).abs()
        di = torch.diff(image, dim=axis).abs().mean(-1)
        both = valid.narrow(axis, 0, valid.shape[axis] - 1) & valid.narrow(axis, 1, valid.shape[axis] - 1)
        total = total + (dd * torch.exp(-edge_weight * di))[both].sum()
        count += int(both.sum())
    return total / max(count, 1)
