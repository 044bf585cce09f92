"""Language features of the Gaussians: phi_j^l = MLP_L(h_lang^l(p_j)) for l in (subpart, part, whole).

Two ways to give each Gaussian its three 3-d latents (one per level):

- :class:`LanguageHeads` (SOVGaussian): three hash grids h_lang^l read at the Gaussian's centre and one
  shared MLP_L. The three grids share one table of 3 x 2 features per entry, so the hashing and the
  corner look-up are done once for all levels; mathematically these are three grids of 2 features with
  the same hash, which is how Instant-NGP-style grids of equal configuration behave anyway.
- the per-Gaussian baseline (LangSplat; the paper's ablation #4): a learnable [N, 9] parameter
  ``splats["lang"]``, edited with the other per-Gaussian parameters by densification.

The latents live in the autoencoder's 3-d space (eq. 2); the field decodes rendered latents to CLIP
space with the scene's decoder.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import torch
from torch import Tensor, nn

from encoders.protocols import LEVELS
from langfield.model.hashgrid import HashGrid, HashGridConfig

N_LEVELS = len(LEVELS)  # subpart, part, whole
LATENT_DIM = 3
LANGUAGE_CHANNELS = N_LEVELS * LATENT_DIM
FEATURES_PER_LEVEL = 2  # of each level's grid, as the colour grid (DNGaussian: 16 levels x 2)


class LanguageHeads(nn.Module):
    """Hash-grid language field: [N, 3] positions -> [N, 3 levels, 3] latents.

    Args:
        grid_cfg: the grid sizes (``features_per_level`` is replaced by 2 per language level x 3 levels).
        center: [3] centre of the grid box.
        half_extent: [3] or scalar half-size of the grid box.
        hidden: width of MLP_L's hidden layer.
    """

    def __init__(
        self, grid_cfg: HashGridConfig, center: Tensor, half_extent: Tensor | float, hidden: int = 64
    ):
        super().__init__()
        cfg = replace(grid_cfg, features_per_level=FEATURES_PER_LEVEL * N_LEVELS)
        self.grid = HashGrid(cfg, center, half_extent)
        self.n_grid_levels = cfg.n_levels
        in_dim = cfg.n_levels * FEATURES_PER_LEVEL
        self.mlp = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, LATENT_DIM))

    def forward(self, means: Tensor, corners: tuple[Tensor, Tensor] | None = None) -> Tensor:
        """Latents [N, 3, 3] (Gaussian, language level, latent) at positions ``means`` [N, 3].

        ``corners`` may come from another grid with the same cell layout (the colour grid), which spares
        the hashing; the caller detaches what should pass no gradient.
        """
        # Each table row holds, per grid level, subpart (2), part (2), whole (2); read back as three
        # encodings [3, N, L * 2], one per language level, which MLP_L maps in one batch.
        if corners is None:
            h = self.grid.encode(means, groups=N_LEVELS)
        else:
            h = self.grid.interpolate(*corners, groups=N_LEVELS)
        return self.mlp(h).permute(1, 0, 2)

    def grid_parameters(self) -> Iterator[nn.Parameter]:
        yield from self.grid.parameters()

    def mlp_parameters(self) -> Iterator[nn.Parameter]:
        yield from self.mlp.parameters()


def language_loss(rendered: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """L_LF = sum_l weighted mean over the pixels with a mask at level l of ||E_i^l - Phi_i^l||_1.

    With ``weight`` the masks' presence (bool) every such pixel counts alike, the paper's L_LF; with
    :func:`mask_balance` weights small masks count more.

    Args:
        rendered: [3, H, W, 3] rendered latents per level.
        target: [3, H, W, 3] autoencoded mask features per level.
        weight: [3, H, W] bool (pixels that have a mask at that level) or float (each pixel's weight, 0
            where there is no mask).

    Returns:
        Scalar; levels with no mask contribute 0 (no division by zero).
    """
    err = (rendered - target).abs().sum(-1)  # [3, H, W]
    w = weight.to(err.dtype)
    per_level = (err * w).flatten(1).sum(1) / w.flatten(1).sum(1).clamp_min(1e-12)
    return per_level.sum()


def mask_balance(segments: Tensor, power: float) -> Tensor:
    """L_LF's pixel weights: the area of the pixel's mask at that level to the power ``-power``.

    Under the paper's L_LF (``power`` 0) a mask weighs as its area: a mug of 18 pixels weighs 1/300 of
    a wall, and a Gaussian that straddles the mug and the table takes the table's latent (an L1 fit
    follows the majority of its pixels), so the mug is not rendered even in the views it was trained
    on. ``power`` 1 weighs every mask alike (then every few-pixel fragment weighs as a wall); between
    the two, small masks gain without the large ones losing their fit.

    Args:
        segments: [3, H, W] integer mask ids per level, -1 where no mask.
        power: in [0, 1]; 0 gives the masks' presence (the paper's weighting).

    Returns:
        [3, H, W] float32, 0 where no mask.
    """
    valid = segments >= 0
    if power == 0:
        return valid.float()
    weight = torch.zeros(segments.shape, dtype=torch.float32)
    for level in range(segments.shape[0]):
        _, inverse, counts = torch.unique(segments[level], return_inverse=True, return_counts=True)
        weight[level] = counts.float()[inverse] ** -power
    return weight * valid
