"""Encoder protocols, their deterministic stubs, and the phrase-table text encoder."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from encoders.protocols import (
    LEVELS,
    DepthEstimator,
    ImageTextEncoder,
    Segmenter,
    TextEncoder,
    check_image,
)
from encoders.stubs import StubDepthEstimator, StubImageTextEncoder, StubSegmenter
from encoders.text_table import CANONICAL_PHRASES, TableTextEncoder, TextTableError, UnknownPhraseError


def _blocks(h: int = 24, w: int = 32) -> np.ndarray:
    """[H, W, 3] image of four flat colour blocks with a two-tone stripe inside the red one."""
    img = np.zeros((h, w, 3), np.float32)
    img[: h // 2, : w // 2] = (0.9, 0.1, 0.1)
    img[: h // 2, w // 2 :] = (0.1, 0.2, 0.9)
    img[h // 2 :, : w // 2] = (0.1, 0.8, 0.2)
    img[h // 2 :, w // 2 :] = (0.95, 0.95, 0.9)
    img[2:6, 2:10] = (0.7, 0.1, 0.1)  # a darker red patch: a subpart of the red block
    return img


def _crop(color: tuple[float, float, float], size: int = 16, fill: float = 1.0) -> np.ndarray:
    """[S, S, 3] crop: a centred square of `color` covering `fill` of the side, black around it."""
    crop = np.zeros((size, size, 3), np.float32)
    n = max(1, int(size * fill))
    o = (size - n) // 2
    crop[o : o + n, o : o + n] = color
    return crop


# ------------------------------------------------------------------------------------------ protocols


def test_stubs_satisfy_protocols() -> None:
    assert isinstance(StubSegmenter(), Segmenter)
    assert isinstance(StubImageTextEncoder(dim=8, image_size=8), ImageTextEncoder)
    assert isinstance(StubImageTextEncoder(dim=8, image_size=8), TextEncoder)
    assert isinstance(StubDepthEstimator(), DepthEstimator)
    assert not isinstance(StubSegmenter(), ImageTextEncoder)
    assert LEVELS == ("subpart", "part", "whole")


def test_check_image_converts_uint8_and_rejects_bad_images() -> None:
    assert check_image(np.full((2, 3, 3), 255, np.uint8), "t").dtype == np.float32
    assert check_image(np.full((2, 3, 3), 255, np.uint8), "t").max() == 1.0
    with pytest.raises(ValueError, match=r"t: image must have shape \[H, W, 3\]"):
        check_image(np.zeros((4, 4)), "t")
    with pytest.raises(ValueError, match=r"lie in \[0, 1\]"):
        check_image(np.full((2, 2, 3), 2.0, np.float32), "t")
    with pytest.raises(ValueError, match="NaN"):
        check_image(np.full((2, 2, 3), np.nan, np.float32), "t")


# ------------------------------------------------------------------------------------------- segmenter


def test_stub_segmenter_gives_three_levels_of_bool_masks() -> None:
    levels = StubSegmenter().segment(_blocks())
    assert len(levels) == 3
    for masks in levels:
        assert masks.dtype == bool and masks.ndim == 3 and masks.shape[1:] == (24, 32)
        assert masks.shape[0] >= 1 and (masks.reshape(len(masks), -1).sum(axis=1) >= 4).all()
    # The dark patch is its own subpart but shares the red block's whole-level mask.
    assert levels[0].shape[0] > levels[2].shape[0]


def test_stub_segmenter_is_deterministic() -> None:
    a, b = StubSegmenter().segment(_blocks()), StubSegmenter().segment(_blocks())
    for ma, mb in zip(a, b, strict=True):
        np.testing.assert_array_equal(ma, mb)


def test_stub_segmenter_levels_are_nested() -> None:
    rng = np.random.default_rng(3)
    image = np.clip(_blocks() + rng.normal(0, 0.05, (24, 32, 3)), 0, 1).astype(np.float32)
    levels = StubSegmenter().segment(image)
    for fine, coarse in ((levels[0], levels[1]), (levels[1], levels[2])):
        for mask in fine:  # inside exactly one coarser mask
            inside = [(mask & ~c).sum() == 0 for c in coarse]
            assert sum(inside) == 1


def test_stub_segmenter_flat_image_and_bad_bins() -> None:
    levels = StubSegmenter().segment(np.full((12, 16, 3), 0.4, np.float32))
    assert [m.shape[0] for m in levels] == [1, 1, 1] and all(m.all() for m in levels)
    with pytest.raises(ValueError, match="multiple of the next"):
        StubSegmenter(bins=(6, 4, 2))


# ----------------------------------------------------------------------------------------- image-text


def test_stub_image_encoder_unit_rows_and_colour_sensitive() -> None:
    enc = StubImageTextEncoder(dim=64, image_size=16)
    crops = np.stack(
        [
            _crop((0.9, 0.1, 0.1)),
            _crop((0.9, 0.1, 0.1), fill=0.5),
            _crop((0.1, 0.2, 0.9)),
            np.zeros((16, 16, 3)),
        ]
    ).astype(np.float32)
    out = enc.encode_images(crops)
    assert out.shape == (4, 64) and out.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-5)
    assert out[0] @ out[1] > 0.99  # same colour, other size: the black padding does not count
    assert out[0] @ out[2] < 0.5
    assert np.isfinite(out[3]).all()  # an all-black crop still has a direction


def test_stub_image_encoder_is_deterministic_and_checks_size() -> None:
    crops = np.stack([_crop((0.5, 0.3, 0.2)), _crop((0.2, 0.9, 0.4))])
    a = StubImageTextEncoder(dim=32, image_size=16).encode_images(crops)
    np.testing.assert_array_equal(a, StubImageTextEncoder(dim=32, image_size=16).encode_images(crops))
    assert not np.allclose(a, StubImageTextEncoder(dim=32, image_size=16, seed=1).encode_images(crops))
    with pytest.raises(ValueError, match=r"\[B, 8, 8, 3\]"):
        StubImageTextEncoder(dim=32, image_size=8).encode_images(crops)


def test_stub_text_encoder_is_stable_and_refuses_a_bare_string() -> None:
    enc = StubImageTextEncoder(dim=32, image_size=8)
    rows = enc.encode_text(["sofa", "table", "sofa"])
    assert rows.shape == (3, 32) and rows.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(rows, axis=1), 1.0, atol=1e-5)
    np.testing.assert_array_equal(rows[0], rows[2])
    np.testing.assert_array_equal(
        rows, StubImageTextEncoder(dim=32, image_size=8).encode_text(["sofa", "table", "sofa"])
    )
    assert abs(rows[0] @ rows[1]) < 0.9
    assert enc.encode_text([]).shape == (0, 32)
    with pytest.raises(TypeError, match="list of phrases"):
        enc.encode_text("sofa")


# ---------------------------------------------------------------------------------------------- depth


def test_stub_depth_estimator_disparity_and_depth() -> None:
    image = _blocks()
    disparity = StubDepthEstimator().estimate(image)
    assert StubDepthEstimator().kind == "disparity"
    assert disparity.shape == (24, 32) and disparity.dtype == np.float32
    assert np.isfinite(disparity).all() and (disparity > 0).all()
    np.testing.assert_array_equal(disparity, StubDepthEstimator().estimate(image))
    flat = StubDepthEstimator().estimate(np.full((24, 32, 3), 0.5, np.float32))
    assert flat[-1, 0] > flat[0, 0]  # the bottom of the image is nearer
    depth = StubDepthEstimator(kind="depth").estimate(image)
    np.testing.assert_allclose(depth, 1.0 / disparity, rtol=1e-5)
    with pytest.raises(ValueError, match="kind"):
        StubDepthEstimator(kind="metric")  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------- phrase table


def _table(tmp_path: Path, dim: int = 8, **entries: np.ndarray) -> Path:
    """A text_embeddings.npz with the canonical phrases, "sofa", "table", and `entries` on top."""
    rng = np.random.default_rng(0)
    table = {p: rng.standard_normal(dim).astype(np.float32) for p in (*CANONICAL_PHRASES, "sofa", "table")}
    table.update(entries)
    path = tmp_path / "text_embeddings.npz"
    np.savez(path, **table)
    return path


def test_table_known_phrase_returns_the_normalised_vector(tmp_path: Path) -> None:
    vec = np.zeros(8, np.float32)
    vec[:2] = (3.0, 4.0)
    enc = TableTextEncoder(_table(tmp_path, **{"lamp shade": vec}))
    out = enc.encode_text(["lamp shade", "sofa"])
    assert out.shape == (2, 8) and out.dtype == np.float32 and enc.dim == 8
    np.testing.assert_allclose(out[0, :3], [0.6, 0.8, 0.0], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-6)
    assert "lamp shade" in enc.phrases and "object" in enc and len(enc) == 7
    assert isinstance(enc, TextEncoder) and not isinstance(enc, ImageTextEncoder)


def test_table_folds_case_and_whitespace_like_clip(tmp_path: Path) -> None:
    enc = TableTextEncoder(_table(tmp_path))
    np.testing.assert_array_equal(enc.encode_text(["  Sofa "]), enc.encode_text(["sofa"]))


def test_table_unknown_phrase_names_phrase_file_and_close_match(tmp_path: Path) -> None:
    path = _table(tmp_path)
    enc = TableTextEncoder(path)
    with pytest.raises(UnknownPhraseError) as info:
        enc.encode_text(["sofa", "sofas"])
    msg = str(info.value)
    assert isinstance(info.value, KeyError)
    assert "'sofas'" in msg and str(path) in msg and "Did you mean 'sofa'" in msg
    assert "'texture'" in msg  # known phrases are listed
    assert info.value.phrase == "sofas" and info.value.suggestions[0] == "sofa"


def test_table_rejects_missing_canonical_phrase(tmp_path: Path) -> None:
    path = tmp_path / "t.npz"
    np.savez(path, object=np.ones(4), things=np.ones(4), stuff=np.ones(4), sofa=np.ones(4))
    with pytest.raises(TextTableError, match="canonical") as info:
        TableTextEncoder(path)
    assert str(path) in str(info.value) and "'texture'" in str(info.value)


def test_table_rejects_nan_vector(tmp_path: Path) -> None:
    bad = np.ones(8, np.float32)
    bad[3] = np.nan
    path = _table(tmp_path, chair=bad)
    with pytest.raises(TextTableError, match="NaN") as info:
        TableTextEncoder(path)
    assert str(path) in str(info.value) and "'chair'" in str(info.value)


def test_table_rejects_mixed_lengths(tmp_path: Path) -> None:
    path = _table(tmp_path, chair=np.ones(5, np.float32))
    with pytest.raises(TextTableError, match="length 5") as info:
        TableTextEncoder(path)
    assert str(path) in str(info.value) and "'chair'" in str(info.value)


def test_table_rejects_zero_and_2d_vectors_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(TextTableError, match="'chair' is a zero vector"):
        TableTextEncoder(_table(tmp_path, chair=np.zeros(8, np.float32)))
    with pytest.raises(TextTableError, match=r"'chair' must be a non-empty 1-D vector, got shape \(1, 8\)"):
        TableTextEncoder(_table(tmp_path, chair=np.ones((1, 8), np.float32)))
    with pytest.raises(TextTableError, match="not found") as info:
        TableTextEncoder(tmp_path / "nope.npz")
    assert "nope.npz" in str(info.value)


def test_table_cannot_encode_images(tmp_path: Path) -> None:
    enc = TableTextEncoder(_table(tmp_path))
    with pytest.raises(NotImplementedError, match="answers phrases only"):
        enc.encode_images(np.zeros((1, 8, 8, 3), np.float32))


def test_table_reads_the_synthetic_scene(tmp_path: Path) -> None:
    from langfield.synthetic import SYNONYMS, make_room

    scene = make_room(tmp_path / "room", width=16, height=12, n_train=1, n_test=0)
    enc = TableTextEncoder(scene / "text_embeddings.npz")
    assert enc.dim == 512
    rows = enc.encode_text(["sofa", "couch", *CANONICAL_PHRASES])
    np.testing.assert_allclose(np.linalg.norm(rows, axis=1), 1.0, atol=1e-5)
    assert SYNONYMS["couch"] == "sofa" and rows[0] @ rows[1] > 0.9  # a synonym is near its label
