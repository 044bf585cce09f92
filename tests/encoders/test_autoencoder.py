"""Tests of the per-scene language autoencoder (eq. 2, LangSplat architecture)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from safetensors.torch import load_file, save_file
from torch import nn

from encoders.autoencoder import (
    AutoencoderConfig,
    LanguageAutoencoder,
    LanguageDecoder,
    autoencoder_loss,
    decoder_state,
    encoder_state,
    load_decoder,
    spread_loss,
    train_autoencoder,
)

# Few steps where only stability or determinism is checked, to keep the suite fast.
QUICK = AutoencoderConfig(iterations=20)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def clustered_features(
    n_concepts: int = 40, repeats: int = 8, noise: float = 0.05, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Like the synthetic scene's masks: random unit concepts, each seen several times plus noise.

    Returns:
        features [n_concepts * repeats, 512] and concepts [n_concepts, 512], float32 and unit norm.
    """
    rng = np.random.default_rng(seed)
    concepts = _unit(rng.standard_normal((n_concepts, 512)))
    rows = np.repeat(concepts, repeats, axis=0)
    features = _unit(rows + noise * _unit(rng.standard_normal(rows.shape)))
    return features.astype(np.float32), concepts.astype(np.float32)


@pytest.fixture(scope="module", autouse=True)
def one_thread() -> Iterator[None]:
    """On a shared, busy 2-core machine two OpenMP threads run these small matmuls several times slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def trained(one_thread: None) -> tuple[LanguageAutoencoder, dict[str, float], np.ndarray, np.ndarray]:
    """The default config on 40 concepts x 4 views, trained once for the module."""
    features, concepts = clustered_features(repeats=4)
    ae, stats = train_autoencoder(features, progress=False)
    return ae, stats, features, concepts


def _linear_chain(seq: nn.Sequential) -> list[tuple[int, int]]:
    return [(m.in_features, m.out_features) for m in seq if isinstance(m, nn.Linear)]


def test_architecture_matches_langsplat() -> None:
    ae = LanguageAutoencoder()
    assert _linear_chain(ae.encoder) == [(512, 256), (256, 128), (128, 64), (64, 32), (32, 3)]
    assert _linear_chain(ae.decoder) == [
        (3, 16),
        (16, 32),
        (32, 64),
        (64, 128),
        (128, 256),
        (256, 256),
        (256, 512),
    ]
    for seq in (ae.encoder, ae.decoder):
        kinds = [type(m) for m in seq]
        # Linear, then (ReLU, Linear) pairs: no activation after the last layer, no BatchNorm.
        assert kinds[0] is nn.Linear and kinds[-1] is nn.Linear
        assert all(k is nn.ReLU for k in kinds[1::2]) and all(k is nn.Linear for k in kinds[0::2])


def test_outputs_are_unit_norm() -> None:
    ae = LanguageAutoencoder()
    x = F.normalize(torch.randn(16, 512, generator=torch.Generator().manual_seed(0)), dim=-1)
    z, x_hat = ae(x)
    assert z.shape == (16, 3) and x_hat.shape == (16, 512)
    torch.testing.assert_close(z.norm(dim=-1), torch.ones(16))
    torch.testing.assert_close(x_hat.norm(dim=-1), torch.ones(16))


def test_decode_of_zero_latent_is_finite() -> None:
    ae = LanguageAutoencoder()
    z = torch.zeros(4, 3, requires_grad=True)
    out = ae.decode(z)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(z.grad).all()


def test_decode_is_finite_when_the_decoder_outputs_zero() -> None:
    ae = LanguageAutoencoder()
    with torch.no_grad():
        for p in ae.decoder.parameters():
            p.zero_()
    out = ae.decode(torch.randn(2, 3))
    assert torch.equal(out, torch.zeros(2, 512))


def test_decode_accepts_rendered_latent_maps() -> None:
    ae = LanguageAutoencoder()
    maps = torch.randn(3, 5, 7, 3, generator=torch.Generator().manual_seed(1))
    out = ae.decode(maps)
    assert out.shape == (3, 5, 7, 512)
    torch.testing.assert_close(out.reshape(-1, 512), ae.decode(maps.reshape(-1, 3)))


def test_bad_shapes_raise() -> None:
    ae = LanguageAutoencoder()
    with pytest.raises(ValueError, match=r"\[\.\.\., 3\]"):
        ae.decode(torch.zeros(2, 4))
    with pytest.raises(ValueError, match=r"\[\.\.\., 512\]"):
        ae.encode(torch.zeros(2, 256))
    with pytest.raises(ValueError, match="M >= 1"):
        train_autoencoder(np.zeros((0, 512), np.float32), QUICK, progress=False)
    with pytest.raises(ValueError, match="decoder_dims"):
        AutoencoderConfig(decoder_dims=(16, 256))


def test_loss_is_zero_for_perfect_reconstruction() -> None:
    x = F.normalize(torch.randn(8, 512), dim=-1)
    assert autoencoder_loss(x, x.clone(), cosine_weight=0.001).item() == pytest.approx(0.0, abs=1e-6)


def test_loss_cosine_is_over_the_feature_dimension() -> None:
    x = F.normalize(torch.randn(8, 512), dim=-1)
    # x_hat = -x: every row has cosine -1, so the cosine term is 2 w; the MSE is |2x|^2 / 512 per row.
    loss = autoencoder_loss(x, -x, cosine_weight=0.5)
    assert loss.item() == pytest.approx(4.0 / 512 + 0.5 * 2.0, rel=1e-5)


def test_training_decreases_the_loss(trained: tuple) -> None:
    _, stats, _, _ = trained
    assert stats["loss"] < 0.1 * stats["initial_loss"]


def test_training_reconstructs_clustered_concepts(trained: tuple) -> None:
    ae, stats, features, concepts = trained
    assert stats["mean_cosine"] >= 0.95
    assert stats["n_features"] == len(features)
    with torch.no_grad():
        c = torch.from_numpy(concepts)
        recon = ae.decode(ae.encode(c))
    assert F.cosine_similarity(recon, c, dim=-1).mean().item() >= 0.95


def test_spread_loss_by_hand_and_its_degenerate_cases() -> None:
    x = torch.eye(3)[:2]  # two unlike features (cosine 0): weight 1 each way
    z = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # |z0 - z1|^2 = 2
    assert spread_loss(z, x, temperature=3.0).item() == pytest.approx(-6.0)
    assert spread_loss(torch.zeros(2, 3), x).item() == pytest.approx(0.0)  # together: log 1
    same = torch.ones(4, 3) / 3**0.5  # repeats of one feature weigh nothing, wherever their latents lie
    loss = spread_loss(torch.randn(4, 3, requires_grad=True), same)
    assert loss.item() == 0.0 and loss.requires_grad
    assert torch.isfinite(spread_loss(torch.zeros(1, 3), torch.ones(1, 3))).all()  # one row


def _nearest_concept_angles(ae: LanguageAutoencoder, concepts: np.ndarray) -> torch.Tensor:
    with torch.no_grad():
        z = ae.encode(torch.from_numpy(concepts))
    angles = torch.rad2deg(torch.acos((z @ z.T).clamp(-1, 1)))
    return angles.fill_diagonal_(360.0).amin(dim=1)


@pytest.mark.slow
def test_the_spread_term_moves_unlike_concepts_apart_and_keeps_the_reconstruction() -> None:
    features, concepts = clustered_features(n_concepts=30, repeats=3)
    plain, _ = train_autoencoder(features, progress=False)
    spread, stats = train_autoencoder(features, AutoencoderConfig(spread_weight=1e-3), progress=False)
    before, after = _nearest_concept_angles(plain, concepts), _nearest_concept_angles(spread, concepts)
    assert after.median() > 1.5 * before.median() and after.min() > before.min()
    assert stats["mean_cosine"] >= 0.98
    with torch.no_grad():  # a concept's repeats still share its latent
        z = spread.encode(torch.from_numpy(features)).reshape(30, 3, 3)
    assert F.cosine_similarity(z, z.mean(1, keepdim=True), dim=-1).min() > 0.99
    with pytest.raises(ValueError, match="spread_weight"):
        AutoencoderConfig(spread_weight=-1.0)


def test_training_is_deterministic_with_the_seed() -> None:
    features, _ = clustered_features(n_concepts=5, repeats=3)
    small = replace(QUICK, batch_size=8)  # mini-batches, so the sampling order is exercised too
    a, _ = train_autoencoder(features, small, progress=False)
    b, _ = train_autoencoder(features, small, progress=False)
    c, _ = train_autoencoder(features, replace(small, seed=1), progress=False)
    for key, value in a.state_dict().items():
        assert torch.equal(value, b.state_dict()[key])
    assert not all(torch.equal(v, c.state_dict()[k]) for k, v in a.state_dict().items())


def test_training_leaves_the_global_rng_alone() -> None:
    features, _ = clustered_features(n_concepts=3, repeats=2)
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    train_autoencoder(features, replace(QUICK, iterations=2), progress=False)
    assert torch.equal(torch.rand(3), expected)


@pytest.mark.parametrize("rows", [1, 2, 5])
def test_tiny_feature_sets_train_without_nan(rows: int) -> None:
    features, _ = clustered_features(n_concepts=rows, repeats=1, seed=rows)
    ae, stats = train_autoencoder(features, QUICK, progress=False)
    assert all(np.isfinite(v) for v in stats.values())
    assert all(torch.isfinite(p).all() for p in ae.parameters())


def test_duplicate_rows_train_without_nan() -> None:
    features = np.repeat(clustered_features(n_concepts=1, repeats=1)[0], 2, axis=0)
    ae, stats = train_autoencoder(torch.from_numpy(features), QUICK, progress=False)
    assert np.isfinite(stats["loss"]) and stats["mean_cosine"] > 0.99
    assert torch.isfinite(ae.encode(torch.from_numpy(features))).all()


def test_decoder_state_round_trip(trained: tuple, tmp_path: Path) -> None:
    ae, _, _, _ = trained
    state = decoder_state(ae)
    assert state and all(isinstance(v, torch.Tensor) for v in state.values())
    path = tmp_path / "decoder.safetensors"
    save_file(state, str(path))
    save_file(encoder_state(ae), str(tmp_path / "encoder.safetensors"))
    decoder = load_decoder(load_file(str(path)), ae.cfg)
    assert isinstance(decoder, LanguageDecoder)
    z = torch.randn(3, 4, 5, 3, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        assert torch.equal(decoder.decode(z), ae.decode(z))
        assert torch.equal(decoder(z), ae.decode(z))
