"""The scene-specific language autoencoder (SOVGaussian eq. 2, after LangSplat).

CLIP features of masks are 512-d; rendering 512 channels per Gaussian is too costly, so each scene trains a
small autoencoder that squeezes its own features onto the unit sphere in R^3. The Gaussians carry and
render the 3-d latents; at query time the decoder lifts a rendered latent back to CLIP space.

Architecture (LangSplat, ``autoencoder/model.py`` and ``train.py`` defaults):

- encoder ``512-256-128-64-32-3``: Linear layers with ReLU between them, no activation after the last;
- decoder ``3-16-32-64-128-256-256-512``: the same pattern;
- both outputs L2-normalised, here with an epsilon so a zero latent (an empty pixel) decodes to zero
  instead of NaN.

Loss (eq. 2): ``MSE(x_hat, x) + w * (1 - cos(x_hat, x))``, the cosine taken over the feature dimension.

Deviations from LangSplat, on purpose:

- No BatchNorm in the encoder. LangSplat places ``BatchNorm1d`` before each inner ReLU of the encoder (the
  ones meant for its decoder land in a list that is never used, so its decoder has none). Our per-scene
  sets are a few hundred rows, mostly repeats of a few dozen concepts, and may be a single row: batch
  statistics are then degenerate (``BatchNorm1d`` refuses a batch of one in training mode) and the
  running statistics used in eval mode would differ from the training ones. Without it encode and decode
  are plain functions of their input, identical in training and inference.
- LangSplat's ``cos_loss`` takes ``F.cosine_similarity(..., dim=0)``, i.e. across the batch; the paper's
  eq. 2 means similarity between each feature and its reconstruction, so we use ``dim=-1``.
- Initialisation. With PyTorch's default Linear init the activations shrink layer by layer, so at the
  start every feature lands on nearly the same latent (spread ~0.01) and training sits on a plateau for
  hundreds of steps. We use He-normal weights with zero biases (the latents start spread over the
  sphere), set the first encoder bias so the encoder starts from mean-centred features (real CLIP
  features share a large common component), and start the decoder at the scene's mean feature (last
  layer scaled down, its bias the mean). On 40 random concepts this reaches a mean cosine of 0.99 in
  about 100 full-batch steps instead of about 1000.
- LangSplat trains 100 epochs of mini-batches of 64 at a constant Adam lr 1e-4 on all masks of a whole
  scene (hundreds of views). A 3-view scene has a few hundred features, so we take a fixed number of
  large-batch steps at lr 1e-3 with cosine decay, a few seconds on a CPU. See :class:`AutoencoderConfig`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from tqdm import tqdm


@dataclass(frozen=True)
class AutoencoderConfig:
    """Sizes and optimisation of the per-scene autoencoder.

    Attributes:
        feature_dim: width of the CLIP features (512 for ViT-B-16).
        encoder_dims: output widths of the encoder's Linear layers; the last is the latent width
            (LangSplat: 256, 128, 64, 32, 3).
        decoder_dims: output widths of the decoder's Linear layers; the last must equal ``feature_dim``
            (LangSplat: 16, 32, 64, 128, 256, 256, 512).
        iterations: Adam steps. LangSplat runs 100 epochs over all masks of a scene; here a fixed step
            count keeps the time independent of the number of features.
        lr: peak Adam learning rate, decayed by a cosine to ``lr * final_lr_fraction``. LangSplat uses a
            constant 1e-4, which needs thousands of steps; 1e-3 converges in a few hundred.
        final_lr_fraction: learning rate at the last step as a fraction of ``lr``.
        batch_size: rows per step, drawn without replacement each step; clamped to the number of features
            so a small scene trains full-batch. LangSplat: 64.
        cosine_weight: weight ``w`` of the cosine term of eq. 2 (LangSplat: 0.001).
        spread_weight: weight of :func:`spread_loss`, which pushes the latents of unlike features
            apart on the sphere (0: eq. 2 alone, as LangSplat).
        spread_temperature: ``t`` of :func:`spread_loss`.
        seed: seeds the initialisation and the batch sampling.
        eps: floor of the norm when normalising encoder and decoder outputs.
    """

    feature_dim: int = 512
    encoder_dims: tuple[int, ...] = (256, 128, 64, 32, 3)
    decoder_dims: tuple[int, ...] = (16, 32, 64, 128, 256, 256, 512)
    iterations: int = 300
    lr: float = 1e-3
    final_lr_fraction: float = 0.05
    batch_size: int = 512
    cosine_weight: float = 1e-3
    spread_weight: float = 0.0
    spread_temperature: float = 10.0
    seed: int = 0
    eps: float = 1e-8

    def __post_init__(self) -> None:
        if not self.encoder_dims or not self.decoder_dims or min(self.encoder_dims + self.decoder_dims) < 1:
            raise ValueError(f"encoder_dims and decoder_dims must be non-empty and positive, got {self}")
        if self.decoder_dims[-1] != self.feature_dim:
            raise ValueError(
                f"decoder_dims must end at feature_dim={self.feature_dim}, got {self.decoder_dims}"
            )
        if self.iterations < 1 or self.batch_size < 1:
            raise ValueError(
                f"iterations and batch_size must be >= 1, got {self.iterations}, {self.batch_size}"
            )
        if self.lr <= 0 or not 0 < self.final_lr_fraction <= 1:
            raise ValueError(
                f"need lr > 0 and 0 < final_lr_fraction <= 1, got {self.lr}, {self.final_lr_fraction}"
            )
        if self.spread_weight < 0 or self.spread_temperature <= 0:
            raise ValueError(
                f"need spread_weight >= 0 and spread_temperature > 0, got {self.spread_weight}, "
                f"{self.spread_temperature}"
            )
        if self.cosine_weight < 0 or self.eps <= 0:
            raise ValueError(f"need cosine_weight >= 0 and eps > 0, got {self.cosine_weight}, {self.eps}")

    @property
    def latent_dim(self) -> int:
        """Width of the latent the Gaussians render (3 in LangSplat)."""
        return self.encoder_dims[-1]


# The decoder's last layer starts this small so its output begins near its bias, the mean feature.
_DECODER_OUT_INIT_SCALE = 0.05


def _mlp(in_dim: int, dims: tuple[int, ...]) -> nn.Sequential:
    """Linear layers of the given output widths with ReLU between them and none after the last.

    He-normal weights keep the activation scale through the ReLUs (see the module docstring).
    """
    layers: list[nn.Module] = []
    for i, out_dim in enumerate(dims):
        if i > 0:
            layers.append(nn.ReLU())
        linear = nn.Linear(in_dim, out_dim)
        nn.init.kaiming_normal_(linear.weight, nonlinearity="relu")
        nn.init.zeros_(linear.bias)
        layers.append(linear)
        in_dim = out_dim
    return nn.Sequential(*layers)


def _check_last_dim(name: str, x: Tensor, dim: int) -> None:
    if x.ndim < 1 or x.shape[-1] != dim:
        raise ValueError(f"{name} must have shape [..., {dim}], got {tuple(x.shape)}")


def _decode(decoder: nn.Sequential, z: Tensor, eps: float) -> Tensor:
    """Shared by the full autoencoder and the decoder restored from a field."""
    return F.normalize(decoder(z), dim=-1, eps=eps)


class LanguageAutoencoder(nn.Module):
    """Encoder and decoder between CLIP space and the 3-d latent sphere (eq. 2, LangSplat).

    Attributes:
        encoder: ``nn.Sequential`` of Linear and ReLU, ``512 -> 3`` before normalisation.
        decoder: ``nn.Sequential`` of Linear and ReLU, ``3 -> 512`` before normalisation.

    Example:
        >>> ae = LanguageAutoencoder()
        >>> z, x_hat = ae(F.normalize(torch.randn(4, 512), dim=-1))
        >>> z.shape, x_hat.shape
        (torch.Size([4, 3]), torch.Size([4, 512]))
    """

    def __init__(self, cfg: AutoencoderConfig = AutoencoderConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = _mlp(cfg.feature_dim, cfg.encoder_dims)
        self.decoder = _mlp(cfg.latent_dim, cfg.decoder_dims)

    def encode(self, x: Tensor) -> Tensor:
        """Latents of CLIP features.

        Args:
            x: features ``[..., 512]``.

        Returns:
            unit latents ``[..., 3]`` (zero where the encoder output is zero).
        """
        _check_last_dim("features", x, self.cfg.feature_dim)
        return F.normalize(self.encoder(x), dim=-1, eps=self.cfg.eps)

    def decode(self, z: Tensor) -> Tensor:
        """CLIP-space features of latents, e.g. rendered latent maps ``[3, H, W, 3]``.

        Args:
            z: latents ``[..., 3]``; need not be unit (alpha blending shortens them), may be zero.

        Returns:
            unit features ``[..., 512]``, finite for any finite input.
        """
        _check_last_dim("latents", z, self.cfg.latent_dim)
        return _decode(self.decoder, z, self.cfg.eps)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Encode then decode.

        Args:
            x: features ``[..., 512]``.

        Returns:
            latents ``[..., 3]`` and reconstructions ``[..., 512]``.
        """
        z = self.encode(x)
        return z, self.decode(z)


class LanguageDecoder(nn.Module):
    """The decoder half alone, as a field restores it (see :func:`load_decoder`).

    Attributes:
        decoder: the same ``nn.Sequential`` as :attr:`LanguageAutoencoder.decoder`.
    """

    def __init__(self, cfg: AutoencoderConfig = AutoencoderConfig()) -> None:
        super().__init__()
        self.cfg = cfg
        self.decoder = _mlp(cfg.latent_dim, cfg.decoder_dims)

    def decode(self, z: Tensor) -> Tensor:
        """Same as :meth:`LanguageAutoencoder.decode`: ``[..., 3] -> [..., 512]``, unit norm."""
        _check_last_dim("latents", z, self.cfg.latent_dim)
        return _decode(self.decoder, z, self.cfg.eps)

    def forward(self, z: Tensor) -> Tensor:
        return self.decode(z)


def autoencoder_loss(x: Tensor, x_hat: Tensor, cosine_weight: float = 1e-3) -> Tensor:
    """Reconstruction loss of eq. 2: ``MSE(x_hat, x) + w * mean(1 - cos(x_hat, x))``.

    The MSE is averaged over all elements and the cosine is taken per row over the feature dimension.
    For unit features the MSE alone is ``2 (1 - cos) / D``, so both terms pull the same way; the cosine
    term matters when the inputs are not normalised.

    Args:
        x: target features ``[..., D]``.
        x_hat: reconstructions ``[..., D]``.
        cosine_weight: ``w`` (LangSplat: 0.001).

    Returns:
        scalar loss.
    """
    if x.shape != x_hat.shape:
        raise ValueError(
            f"x and x_hat must have the same shape, got {tuple(x.shape)} and {tuple(x_hat.shape)}"
        )
    mse = (x_hat - x).square().mean()
    cos = F.cosine_similarity(x_hat, x, dim=-1).mean()
    return mse + cosine_weight * (1.0 - cos)


def spread_loss(z: Tensor, x: Tensor, temperature: float = 10.0) -> Tensor:
    """Uniformity of the latents on the sphere (Wang and Isola, ICML 2020), each pair weighted by how
    unlike its features are: ``log(sum_ij w_ij exp(-t |z_i - z_j|^2) / sum_ij w_ij)`` with
    ``w_ij = max(0, 1 - cos(x_i, x_j))`` off the diagonal.

    A 3-d latent holds a scene's few dozen concepts; eq. 2 alone packs them a few degrees apart, and a
    rendered latent a few degrees off then decodes to a neighbour's feature. Repeats of one concept
    (cosine near 1) weigh nothing, so they stay together.

    Args:
        z: latents ``[M, d]``.
        x: their features ``[M, D]`` (unit rows).
        temperature: ``t``; larger pushes only near neighbours.

    Returns:
        scalar, 0 or below; 0 when no pair differs.
    """
    xn = F.normalize(x, dim=-1)
    w = (1.0 - xn @ xn.T).clamp_min(0.0)
    w = w * (1.0 - torch.eye(len(x), dtype=w.dtype))
    if float(w.sum()) <= 0.0:
        return z.sum() * 0.0
    d2 = torch.cdist(z, z).square()
    return torch.log((w * torch.exp(-temperature * d2)).sum() / w.sum())


@torch.no_grad()
def _init_from_features(ae: LanguageAutoencoder, x: Tensor) -> None:
    """Data-dependent start: the encoder sees centred features, the decoder outputs the mean feature.

    Args:
        ae: a freshly built autoencoder, changed in place.
        x: the scene's features ``[M, 512]``.
    """
    mean = x.mean(dim=0)
    first, last = ae.encoder[0], ae.decoder[-1]
    first.bias.copy_(-first.weight @ mean)
    last.weight.mul_(_DECODER_OUT_INIT_SCALE)
    last.bias.copy_(mean)


def train_autoencoder(
    features: np.ndarray | Tensor, cfg: AutoencoderConfig = AutoencoderConfig(), *, progress: bool = True
) -> tuple[LanguageAutoencoder, dict[str, float]]:
    """Fit the autoencoder to one scene's mask features (eq. 2) with Adam.

    Deterministic for a given seed on the CPU: the initialisation uses a forked global generator (the
    caller's random state is left untouched) and the batches a private one. If all rows are equal the
    centred encoder starts at, and keeps, a zero latent, which decodes exactly to that feature.

    Args:
        features: CLIP features ``[M, 512]``, M >= 1; repeated rows are fine.
        cfg: sizes and optimisation.
        progress: show a tqdm bar with the loss.

    Returns:
        the trained autoencoder in eval mode, and stats: ``initial_loss`` (eq. 2 on the first batch,
        before any step), ``loss`` (eq. 2 on all features at the end),
        ``mean_cosine`` between features and reconstructions, ``seconds``, ``iterations``, ``n_features``.
    """
    x = torch.as_tensor(features).detach().to(dtype=torch.float32, device="cpu")
    if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] != cfg.feature_dim:
        raise ValueError(f"features must have shape [M >= 1, {cfg.feature_dim}], got {tuple(x.shape)}")
    if not torch.isfinite(x).all():
        raise ValueError("features contain NaN or inf")
    start = time.perf_counter()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(cfg.seed)
        ae = LanguageAutoencoder(cfg)
    _init_from_features(ae, x)
    gen = torch.Generator().manual_seed(cfg.seed)
    m = x.shape[0]
    batch = min(cfg.batch_size, m)
    optimizer = torch.optim.Adam(ae.parameters(), lr=cfg.lr)
    # Cosine decay: Adam at 1e-3 occasionally spikes late in training; a small final rate settles the
    # weights so the result does not depend on where the last step landed.
    floor = cfg.final_lr_fraction
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * s / cfg.iterations))
    )
    ae.train()
    initial = math.nan
    bar = tqdm(
        range(cfg.iterations), disable=not progress, desc="autoencoder", dynamic_ncols=True, leave=False
    )
    for step in bar:
        xb = x if batch == m else x[torch.randperm(m, generator=gen)[:batch]]
        z, x_hat = ae(xb)
        loss = autoencoder_loss(xb, x_hat, cfg.cosine_weight)
        if step == 0:
            initial = loss.item()
        if cfg.spread_weight > 0:
            loss = loss + cfg.spread_weight * spread_loss(z, xb, cfg.spread_temperature)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()
        if step % 50 == 0 or step == cfg.iterations - 1:
            bar.set_postfix(loss=f"{loss.item():.2e}")
    bar.close()
    ae.eval()
    with torch.no_grad():
        _, x_hat = ae(x)
        final = autoencoder_loss(x, x_hat, cfg.cosine_weight).item()
        mean_cos = F.cosine_similarity(x_hat, x, dim=-1).mean().item()
    stats = {
        "initial_loss": initial,
        "loss": final,
        "mean_cosine": mean_cos,
        "seconds": time.perf_counter() - start,
        "iterations": float(cfg.iterations),
        "n_features": float(m),
    }
    return ae, stats


def decoder_state(ae: LanguageAutoencoder | LanguageDecoder) -> dict[str, Tensor]:
    """The decoder's weights as a flat dict of contiguous CPU tensors (safetensors-ready, no pickle).

    Keys are those of the decoder's ``nn.Sequential`` (``"0.weight"``, ``"0.bias"``, ``"2.weight"``, ...);
    a field adds its own prefix when saving.
    """
    return {k: v.detach().to("cpu").clone().contiguous() for k, v in ae.decoder.state_dict().items()}


def encoder_state(ae: LanguageAutoencoder) -> dict[str, Tensor]:
    """The encoder's weights, as :func:`decoder_state` gives the decoder's."""
    return {k: v.detach().to("cpu").clone().contiguous() for k, v in ae.encoder.state_dict().items()}


def load_decoder(state: dict[str, Tensor], cfg: AutoencoderConfig = AutoencoderConfig()) -> LanguageDecoder:
    """Rebuild the decoder from :func:`decoder_state`; ``cfg`` must give the same sizes it was trained with.

    Returns:
        a :class:`LanguageDecoder` in eval mode whose ``decode`` equals the trained autoencoder's.
    """
    dec = LanguageDecoder(cfg)
    dec.decoder.load_state_dict(state, strict=True)
    return dec.eval()
