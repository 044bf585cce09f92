"""The language feature cache (docs/format.md language_features/): reader, writer and eq. 1 builder."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from encoders.cache import (
    FeatureCache,
    FeatureCacheError,
    build_feature_cache,
    build_scene_cache,
    feature_cache_paths,
    mask_crop,
    read_feature_cache,
    write_feature_cache,
)
from encoders.protocols import ImageTextEncoder, Segmenter
from encoders.stubs import StubImageTextEncoder, StubSegmenter

H, W, D = 6, 8, 16


def _unit(rows: int, dim: int = D, seed: int = 0) -> np.ndarray:
    v = np.random.default_rng(seed).standard_normal((rows, dim))
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def _segments(levels: int = 3, m: int = 3) -> np.ndarray:
    """[L, H, W] int32: level l uses row l % m on its left half, -1 on the right half."""
    s = np.full((levels, H, W), -1, np.int32)
    for lvl in range(levels):
        s[lvl, :, : W // 2] = lvl % m
    return s


def _save(tmp_path: Path, f: np.ndarray | None, s: np.ndarray | None) -> tuple[Path, Path]:
    f_path, s_path = tmp_path / "v_f.npy", tmp_path / "v_s.npy"
    if f is not None:
        np.save(f_path, f)
    if s is not None:
        np.save(s_path, s)
    return f_path, s_path


def _rejects(f_path: Path, s_path: Path, blamed: Path, what: str, **kwargs: object) -> str:
    """Read must fail with a message naming the `blamed` file and containing `what`."""
    with pytest.raises(FeatureCacheError) as info:
        read_feature_cache(f_path, s_path, **kwargs)  # type: ignore[arg-type]
    msg = str(info.value)
    assert str(blamed) in msg, msg
    assert what in msg, msg
    return msg


# ---------------------------------------------------------------------------------- reader: rejected


def test_read_rejects_missing_f(tmp_path: Path) -> None:
    f_path, s_path = _save(tmp_path, None, _segments())
    _rejects(f_path, s_path, f_path, "missing")


def test_read_rejects_missing_s(tmp_path: Path) -> None:
    f_path, s_path = _save(tmp_path, _unit(3), None)
    _rejects(f_path, s_path, s_path, "missing")


def test_read_rejects_unreadable_file(tmp_path: Path) -> None:
    f_path, s_path = _save(tmp_path, _unit(3), None)
    s_path.write_bytes(b"not a numpy file")
    _rejects(f_path, s_path, s_path, "cannot read")


def test_read_rejects_fractional_float_segments(tmp_path: Path) -> None:
    s = _segments().astype(np.float32)
    s[1, 2, 3] = 0.5
    f_path, s_path = _save(tmp_path, _unit(3), s)
    msg = _rejects(f_path, s_path, s_path, "integer row indices")
    assert "level 1, pixel (y=2, x=3)" in msg


def test_read_rejects_bool_segments(tmp_path: Path) -> None:
    f_path, s_path = _save(tmp_path, _unit(3), _segments() >= 0)
    _rejects(f_path, s_path, s_path, "must be integers")


def test_read_rejects_segments_of_wrong_ndim(tmp_path: Path) -> None:
    f_path, s_path = _save(tmp_path, _unit(3), _segments()[0])
    _rejects(f_path, s_path, s_path, "must be 3-D [L, H, W], got shape (6, 8)")


def test_read_rejects_segment_value_past_last_row(tmp_path: Path) -> None:
    s = _segments()
    s[2, 4, 5] = 3
    f_path, s_path = _save(tmp_path, _unit(3), s)
    msg = _rejects(f_path, s_path, s_path, "not a row of v_f.npy, which has 3 rows")
    assert "level 2, pixel (y=4, x=5)" in msg


def test_read_rejects_segment_value_below_minus_one(tmp_path: Path) -> None:
    s = _segments()
    s[0, 0, 7] = -2
    f_path, s_path = _save(tmp_path, _unit(3), s)
    _rejects(f_path, s_path, s_path, "segment value -2 at level 0, pixel (y=0, x=7) is below -1")


def test_read_rejects_used_row_that_is_not_unit(tmp_path: Path) -> None:
    f = _unit(3)
    f[1] *= 1.01
    f_path, s_path = _save(tmp_path, f, _segments())
    _rejects(f_path, s_path, f_path, "row 1 has norm 1.01")


def test_read_rejects_unnormalised_unused_row(tmp_path: Path) -> None:
    # A raw CLIP embedding (norm ~10) anywhere in the file means the file was not normalised.
    f = np.concatenate([_unit(3), 10.0 * _unit(1, seed=1)])
    f_path, s_path = _save(tmp_path, f, _segments())
    _rejects(f_path, s_path, f_path, "row 3 has norm 10")


def test_read_rejects_used_zero_row(tmp_path: Path) -> None:
    f = _unit(3)
    f[2] = 0.0
    f_path, s_path = _save(tmp_path, f, _segments())
    _rejects(f_path, s_path, f_path, "row 2 is a zero vector")


def test_read_rejects_nan_row(tmp_path: Path) -> None:
    f = _unit(4)
    f[3, 5] = np.nan
    f_path, s_path = _save(tmp_path, f, _segments())  # row 3 is unused: NaN is rejected anyway
    _rejects(f_path, s_path, f_path, "row 3 has NaN or inf")


def test_read_rejects_five_levels(tmp_path: Path) -> None:
    f_path, s_path = _save(tmp_path, _unit(3), _segments(levels=5))
    _rejects(f_path, s_path, s_path, "has 5 levels; expected 3")


def test_read_rejects_size_of_other_aspect(tmp_path: Path) -> None:
    f_path, s_path = _save(tmp_path, _unit(3), _segments())
    msg = _rejects(f_path, s_path, s_path, "8x6 (WxH) but the image is 8x8", expected_hw=(8, 8))
    assert "aspect" in msg


def test_read_rejects_feature_dimension_mismatch(tmp_path: Path) -> None:
    f_path, s_path = _save(tmp_path, _unit(3), _segments())
    _rejects(f_path, s_path, f_path, f"dimension {D}, but the encoder's is 512", dim=512)


def test_read_rejects_features_not_2d_or_not_float(tmp_path: Path) -> None:
    f_path, s_path = _save(tmp_path, _unit(3).ravel(), _segments())
    _rejects(f_path, s_path, f_path, "must be 2-D [M, D]")
    f_path, s_path = _save(tmp_path, np.ones((3, D), np.int32), _segments())
    _rejects(f_path, s_path, f_path, "must be float")


# ---------------------------------------------------------------------------------- reader: accepted


def test_read_langsplat_four_levels_drops_level_zero(tmp_path: Path) -> None:
    # LangSplat layout: rows of "default" first (0, 1), then s (2), m (3), l (4); float32 maps as
    # its preprocess.py saves them.
    f = _unit(5)
    s = np.full((4, H, W), -1, np.float32)
    s[0, :, :4], s[0, :, 4:] = 0, 1
    s[1, :2], s[2, :4], s[3] = 2, 3, 4
    f_path, s_path = _save(tmp_path, f, s)
    cache = read_feature_cache(f_path, s_path, expected_hw=(H, W), dim=D)
    assert cache.segments.shape == (3, H, W) and cache.segments.dtype == np.int32
    np.testing.assert_allclose(cache.features, f[2:], atol=1e-6)  # default rows removed
    expected = np.where(s[1:] >= 0, s[1:] - 2, -1).astype(np.int32)
    np.testing.assert_array_equal(cache.segments, expected)


def test_read_accepts_unused_zero_rows_and_drops_them(tmp_path: Path) -> None:
    f = np.concatenate([np.zeros((1, D), np.float32), _unit(3), np.zeros((2, D), np.float32)])
    s = _segments() + (_segments() >= 0)  # rows 1..3 used, 0, 4, 5 are empty slots
    f_path, s_path = _save(tmp_path, f, s)
    cache = read_feature_cache(f_path, s_path)
    np.testing.assert_allclose(cache.features, f[1:4], atol=1e-6)
    np.testing.assert_array_equal(cache.segments, _segments())


def test_read_resizes_maps_of_same_aspect_by_nearest_neighbour(tmp_path: Path) -> None:
    s = _segments()
    s[0, 1, 1] = 1
    f_path, s_path = _save(tmp_path, _unit(3), s)
    cache = read_feature_cache(f_path, s_path, expected_hw=(2 * H, 2 * W))
    np.testing.assert_array_equal(cache.segments, s.repeat(2, axis=1).repeat(2, axis=2))


def test_read_synthetic_scene_cache(tmp_path: Path) -> None:
    from langfield.synthetic import make_room

    scene = make_room(tmp_path / "room", width=64, height=48, n_train=2, n_test=0)
    for name in ("train_000", "train_001"):
        f_path, s_path = feature_cache_paths(scene / "language_features", name)
        cache = read_feature_cache(f_path, s_path, expected_hw=(48, 64), dim=512)
        assert cache.segments.shape == (3, 48, 64) and cache.num_masks > 3
        np.testing.assert_array_equal(cache.segments, np.load(s_path))  # every row used: no renumbering
        np.testing.assert_allclose(cache.features, np.load(f_path), atol=1e-6)
        ids, masks = cache.masks("whole")
        assert masks.shape == (len(ids), 48, 64) and not (masks.sum(axis=0) > 1).any()
        per_pixel, valid = cache.pixel_features(2)
        np.testing.assert_allclose(np.linalg.norm(per_pixel[valid], axis=1), 1.0, atol=1e-5)


# --------------------------------------------------------------------------------------------- builder


class _FixedSegmenter:
    """Returns the given masks whatever the image."""

    def __init__(self, levels: Sequence[np.ndarray]) -> None:
        self.levels = [np.asarray(m, bool) for m in levels]
        self.calls = 0

    def segment(self, image: np.ndarray) -> list[np.ndarray]:
        self.calls += 1
        return self.levels


class _RecordingEncoder:
    """Records every crop; a crop's feature is (mean colour, 1) normalised, so it is never zero."""

    def __init__(self, image_size: int = 8) -> None:
        self.image_size, self.dim = image_size, 4
        self.crops: list[np.ndarray] = []

    def encode_images(self, images: np.ndarray) -> np.ndarray:
        self.crops.extend(images)
        x = np.concatenate([images.mean(axis=(1, 2)), np.ones((len(images), 1))], axis=1)
        return 3.0 * x  # not normalised: the builder must do it

    def encode_text(self, phrases: Sequence[str]) -> np.ndarray:
        raise NotImplementedError


def _image(h: int = 24, w: int = 32) -> np.ndarray:
    return (0.2 + 0.8 * np.random.default_rng(1).random((h, w, 3))).astype(np.float32)


def _none(h: int = 24, w: int = 32) -> np.ndarray:
    return np.zeros((0, h, w), bool)


def test_fakes_satisfy_protocols() -> None:
    assert isinstance(_FixedSegmenter([_none()] * 3), Segmenter)
    assert isinstance(_RecordingEncoder(), ImageTextEncoder)


def test_build_one_pixel_mask(tmp_path: Path) -> None:
    image = _image()
    mask = np.zeros((1, 24, 32), bool)
    mask[0, 3, 5] = True
    enc = _RecordingEncoder(image_size=8)
    cache = build_feature_cache(image, _FixedSegmenter([mask, _none(), _none()]), enc)
    assert cache.num_masks == 1 and len(enc.crops) == 1
    np.testing.assert_allclose(enc.crops[0], np.broadcast_to(image[3, 5], (8, 8, 3)), atol=1e-6)
    assert cache.segments[0, 3, 5] == 0 and (cache.segments[0] >= 0).sum() == 1
    assert (cache.segments[1:] == -1).all()


def test_build_drops_empty_mask() -> None:
    masks = np.zeros((2, 24, 32), bool)
    masks[1, 10:, :] = True  # mask 0 is empty
    enc = _RecordingEncoder()
    cache = build_feature_cache(_image(), _FixedSegmenter([_none(), masks, _none()]), enc)
    assert cache.num_masks == 1 and len(enc.crops) == 1
    np.testing.assert_array_equal(cache.segments[1], np.where(masks[1], 0, -1))


def test_build_overlapping_masks_smaller_wins() -> None:
    masks = np.zeros((2, 24, 32), bool)
    masks[0, 4:8, 4:8] = True  # small, listed first
    masks[1] = True  # the whole image, listed last: drawn first because it is larger
    cache = build_feature_cache(_image(), _FixedSegmenter([_none(), _none(), masks]), _RecordingEncoder())
    expected = np.ones((24, 32), np.int32)
    expected[4:8, 4:8] = 0
    np.testing.assert_array_equal(cache.segments[2], expected)


def test_build_mask_hidden_by_smaller_ones_gets_no_row() -> None:
    masks = np.zeros((3, 24, 32), bool)
    masks[0, :, :16], masks[1, :, 16:] = True, True  # two halves
    masks[2, 2:20, 2:30] = True  # inside their union: no pixel of its own
    enc = _RecordingEncoder()
    cache = build_feature_cache(_image(), _FixedSegmenter([masks, _none(), _none()]), enc)
    assert cache.num_masks == 2 and len(enc.crops) == 2
    assert set(np.unique(cache.segments[0]).tolist()) == {0, 1}


def test_eq1_crop_blacks_out_crops_box_and_centres() -> None:
    image = _image()
    mask = np.zeros((24, 32), bool)
    mask[10:14, 4:12] = True  # 4 tall, 8 wide
    mask[11, 6] = False  # a hole: must come out black
    enc = _RecordingEncoder(image_size=8)  # box side 8 = image_size: no resampling, exact values
    build_feature_cache(image, _FixedSegmenter([mask[None], _none(), _none()]), enc)
    crop = enc.crops[0]
    assert crop.shape == (8, 8, 3) and crop.dtype == np.float32
    assert (crop[:2] == 0).all() and (crop[6:] == 0).all()  # padding above and below: centred
    expected = np.where(mask[10:14, 4:12, None], image[10:14, 4:12], 0.0)
    np.testing.assert_array_equal(crop[2:6], expected)
    assert (crop[3, 2] == 0).all()  # the hole


def test_eq1_crop_of_tall_mask_is_shrunk_square_and_centred() -> None:
    image = _image()
    mask = np.zeros((24, 32), bool)
    mask[0:16, 20:24] = True  # 16 tall, 4 wide -> 16x16 square -> 8x8
    crop = mask_crop(image, mask, 8)
    assert crop.shape == (8, 8, 3)
    assert (crop[:, :3] == 0).all() and (crop[:, 5:] == 0).all()  # black side bands (6 of 16 px each)
    assert (crop[:, 3:5] > 0).all()
    np.testing.assert_allclose(
        crop[:, 3:5].mean(axis=(0, 1)), image[0:16, 20:24].mean(axis=(0, 1)), atol=1e-5
    )


def test_build_round_trips_through_write_and_read(tmp_path: Path) -> None:
    image = _image(24, 32)
    image[:12, :16] = (0.9, 0.1, 0.1)
    encoder = StubImageTextEncoder(dim=D, image_size=16)
    cache = build_feature_cache(image, StubSegmenter(), encoder, batch_size=5)
    assert cache.segments.shape == (3, 24, 32) and cache.num_masks > 3 and cache.dim == D
    np.testing.assert_allclose(np.linalg.norm(cache.features, axis=1), 1.0, atol=1e-5)
    assert (cache.segments[2] >= 0).any()
    f_path, s_path = write_feature_cache(tmp_path / "lf", "view", cache)
    assert sorted(p.name for p in (tmp_path / "lf").iterdir()) == [
        "view_f.npy",
        "view_s.npy",
    ]  # no temp files
    back = read_feature_cache(f_path, s_path, expected_hw=(24, 32), dim=D)
    np.testing.assert_array_equal(back.segments, cache.segments)
    np.testing.assert_allclose(back.features, cache.features, atol=1e-6)
    again = build_feature_cache(image, StubSegmenter(), encoder, batch_size=32)  # batching changes nothing
    np.testing.assert_allclose(again.features, cache.features, atol=1e-6)


def test_build_rejects_bad_segmenter_output() -> None:
    with pytest.raises(ValueError, match="returned 2 levels"):
        build_feature_cache(_image(), _FixedSegmenter([_none(), _none()]), _RecordingEncoder())
    with pytest.raises(ValueError, match=r"part masks must have shape \[M, 24, 32\]"):
        build_feature_cache(_image(), _FixedSegmenter([_none(), _none(8, 8), _none()]), _RecordingEncoder())


def test_build_scene_cache_skips_existing_views(tmp_path: Path) -> None:
    images = {"a": _image(), "b": _image()[::-1].copy()}
    folder = tmp_path / "language_features"
    seg = StubSegmenter()
    enc = _RecordingEncoder()
    first = build_scene_cache(images, folder, seg, enc, progress=False)
    assert sorted(first) == ["a", "b"] and all(t >= 0 for t in first.values())
    n_crops = len(enc.crops)
    assert build_scene_cache(images, folder, seg, enc, progress=False) == {}
    assert len(enc.crops) == n_crops  # nothing encoded the second time
    np.save(folder / "b_s.npy", np.zeros((3, 5, 5), np.int32))  # a stale cache of another size
    assert sorted(build_scene_cache(images, folder, seg, enc, progress=False)) == ["b"]
    assert sorted(build_scene_cache(images, folder, seg, enc, skip_existing=False, progress=False)) == [
        "a",
        "b",
    ]


def test_feature_cache_checks_its_invariants() -> None:
    with pytest.raises(ValueError, match=r"segments must be int \[3, H, W\]"):
        FeatureCache(_unit(2), np.zeros((4, 2, 2), np.int32))
    with pytest.raises(ValueError, match="row 0 is used by segments but has norm 2"):
        FeatureCache(2 * _unit(1), np.zeros((3, 2, 2), np.int32))
