"""Tests of phrase relevancy and LangSplat's mask pipeline (querying/relevancy.py)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from querying.relevancy import (
    MASK_THRESHOLD,
    REFERENCE_WIDTH,
    box_filter,
    choose_level,
    localization_hit,
    localization_point,
    majority_filter,
    normalize_map,
    relevancy,
    relevancy_mask,
    scaled_size,
    smooth_map,
)

WIDTH, HEIGHT = 160, 120


def _sigmoid(x: float) -> float:
    return 1.0 / (1.0 + math.exp(-x))


def _rect(top: int, left: int, height: int, width: int, shape=(HEIGHT, WIDTH)) -> torch.Tensor:
    mask = torch.zeros(shape, dtype=torch.bool)
    mask[top : top + height, left : left + width] = True
    return mask


def _disc(cy: float, cx: float, radius: float, shape=(HEIGHT, WIDTH)) -> torch.Tensor:
    y, x = torch.meshgrid(torch.arange(shape[0]), torch.arange(shape[1]), indexing="ij")
    return (y - cy) ** 2 + (x - cx) ** 2 <= radius**2


# ---------------------------------------------------------------- relevancy


def test_relevancy_of_orthogonal_unit_vectors() -> None:
    e = torch.eye(4)
    # Feature = phrase, orthogonal to both canonicals: s_q = 1, s_c = 0 -> 1 / (1 + e^-10).
    assert float(relevancy(e[0], e[:1], e[1:3])) == pytest.approx(_sigmoid(10.0), rel=1e-6)
    # Feature = a canonical, orthogonal to the phrase: s_q = 0, max s_c = 1 -> 1 / (1 + e^10).
    assert float(relevancy(e[1], e[:1], e[1:3])) == pytest.approx(_sigmoid(-10.0), rel=1e-5)
    # Orthogonal to all: every softmax is 1/2.
    assert float(relevancy(e[3], e[:1], e[1:3])) == pytest.approx(0.5)


def test_relevancy_is_the_minimum_over_canonical_phrases() -> None:
    feature = torch.tensor([0.6, 0.8, 0.0, 0.0])  # s_q = 0.6 with e0; 0.8 with e1, 0 with e2
    e = torch.eye(4)
    per_canonical = [
        math.exp(6.0) / (math.exp(6.0) + math.exp(8.0)),  # vs e1: 1 / (1 + e^2) = 0.1192
        math.exp(6.0) / (math.exp(6.0) + math.exp(0.0)),  # vs e2: 1 / (1 + e^-6) = 0.9975
    ]
    expected = min(per_canonical)
    assert expected == pytest.approx(0.11920292)
    assert float(relevancy(feature, e[:1], e[1:3])) == pytest.approx(expected, rel=1e-5)
    assert float(relevancy(feature, e[:1], e[[2, 1]])) == pytest.approx(expected, rel=1e-5)
    # With the weaker canonical alone, the relevancy is its own pairwise softmax.
    assert float(relevancy(feature, e[:1], e[2:3])) == pytest.approx(per_canonical[1], rel=1e-5)


def test_relevancy_normalises_features_and_embeddings() -> None:
    g = torch.Generator().manual_seed(0)
    feats, phrases, canon = (
        torch.randn(5, 7, 16, generator=g),
        torch.randn(2, 16, generator=g),
        torch.randn(4, 16),
    )
    unit = torch.nn.functional.normalize
    expected = relevancy(unit(feats, dim=-1), unit(phrases, dim=-1), unit(canon, dim=-1))
    torch.testing.assert_close(relevancy(feats * 7.0, phrases * 3.0, canon * 0.1), expected)


def test_relevancy_matches_the_lerf_softmax_form() -> None:
    g = torch.Generator().manual_seed(1)
    feats, phrases, canon = (
        torch.randn(50, 32, generator=g),
        torch.randn(3, 32, generator=g),
        torch.randn(4, 32),
    )
    f, p, c = (torch.nn.functional.normalize(x.double(), dim=-1) for x in (feats, phrases, canon))
    s_q, s_c = f @ p.T, f @ c.T  # [N, Q], [N, C]
    pairs = torch.stack(torch.broadcast_tensors(s_q[:, :, None], s_c[:, None, :]), dim=-1)  # [N, Q, C, 2]
    expected = torch.softmax(10.0 * pairs, dim=-1)[..., 0].amin(dim=-1).T  # [Q, N]
    torch.testing.assert_close(relevancy(feats, phrases, canon).double(), expected, atol=1e-6, rtol=1e-5)


def test_relevancy_batched_over_phrases_equals_single_calls() -> None:
    g = torch.Generator().manual_seed(2)
    feats, phrases, canon = (
        torch.randn(3, 6, 8, 24, generator=g),
        torch.randn(4, 24, generator=g),
        torch.randn(4, 24),
    )
    batched = relevancy(feats, phrases, canon)
    assert batched.shape == (4, 3, 6, 8)
    for q in range(4):
        torch.testing.assert_close(batched[q], relevancy(feats, phrases[q : q + 1], canon)[0])


def test_relevancy_of_zero_features_is_one_half_not_nan() -> None:
    rel = relevancy(torch.zeros(2, 3, 8), torch.randn(2, 8), torch.randn(4, 8))
    assert not torch.isnan(rel).any()
    torch.testing.assert_close(rel, torch.full((2, 2, 3), 0.5))


def test_relevancy_stays_finite_at_a_huge_temperature() -> None:
    e = torch.eye(3)
    rel = relevancy(torch.stack([e[0], e[1]]), e[:1], e[1:], temperature=1e4)
    assert torch.isfinite(rel).all()
    torch.testing.assert_close(rel, torch.tensor([[1.0, 0.0]]))


def test_relevancy_rejects_mismatched_dimensions() -> None:
    with pytest.raises(ValueError, match="relevancy|cosine"):
        relevancy(torch.zeros(4, 8), torch.zeros(1, 7), torch.zeros(4, 7))


# ---------------------------------------------------------------- sizes and filters


@pytest.mark.parametrize(
    ("size", "width", "expected"),
    [
        # From the narrowest LERF-OVS width (985) on: LangSplat's own sizes, whatever the width.
        (30, 985, 30),
        (30, 988, 30),
        (7, 986, 7),
        (7, 988, 7),
        (30, 1000, 30),
        (30, 2000, 30),
        (7, 2000, 7),
        # Below it: the largest odd size not above size x width / 985.
        (30, 984, 29),
        (7, 984, 5),
        (30, 160, 3),
        (30, 320, 9),
        (7, 160, 1),
        (7, 640, 3),
        (30, 10, 1),
    ],
)
def test_scaled_size(size, width, expected) -> None:
    assert scaled_size(size, width) == expected


def test_scaled_size_is_never_wider_than_langsplats_below_the_reference() -> None:
    # Relative to the image, no wider than LangSplat's 30 and 7 at 985 px, and reaching no further
    # than LangSplat's windows: 15 pixels before a pixel (box), 3 either side (vote).
    for width in range(1, REFERENCE_WIDTH):
        box, vote = scaled_size(30, width), scaled_size(7, width)
        assert box % 2 == 1 and vote % 2 == 1
        assert box / width <= 30 / REFERENCE_WIDTH or box == 1
        assert vote / width <= 7 / REFERENCE_WIDTH or vote == 1
        assert (box - 1) / 2 / width <= 15 / REFERENCE_WIDTH
        assert (vote - 1) / 2 / width <= 3 / REFERENCE_WIDTH


def test_box_filter_of_a_delta_is_a_uniform_square() -> None:
    delta = torch.zeros(9, 9)
    delta[4, 4] = 1.0
    expected = torch.zeros(9, 9)
    expected[3:6, 3:6] = 1.0 / 9.0
    torch.testing.assert_close(box_filter(delta, 3), expected)
    wide = box_filter(delta, 5)
    assert float(wide.sum()) == pytest.approx(1.0)
    assert float(wide[2, 2]) == pytest.approx(1.0 / 25.0)


def test_box_filter_matches_langsplats_cv2_filter2d() -> None:
    image = np.random.default_rng(0).random((20, 30)).astype(np.float32)
    expected = cv2.filter2D(image, -1, np.ones((5, 5), np.float32) / 25.0)  # BORDER_REFLECT_101
    torch.testing.assert_close(box_filter(torch.from_numpy(image), 5), torch.from_numpy(expected))


def test_box_filter_keeps_leading_dimensions() -> None:
    maps = torch.rand(2, 3, 4, 5)
    assert box_filter(maps, 3).shape == (2, 3, 4, 5)
    assert box_filter(maps, 30).shape == (2, 3, 4, 5)
    torch.testing.assert_close(box_filter(maps, 1), maps)


@pytest.mark.parametrize(("shape", "size"), [((20, 30), 4), ((4, 5), 31), ((4, 5), 30), ((1, 7), 6)])
def test_box_filter_matches_cv2_for_even_sizes_and_windows_longer_than_the_image(shape, size) -> None:
    # OpenCV mirrors again where the window is longer than the image; so does box_filter.
    image = np.random.default_rng(1).random(shape).astype(np.float32)
    expected = cv2.filter2D(image, -1, np.ones((size, size)) / size**2)
    np.testing.assert_allclose(box_filter(torch.from_numpy(image), size).numpy(), expected, atol=1e-6)


def test_box_filter_rejects_sizes_below_one() -> None:
    with pytest.raises(ValueError, match="positive"):
        box_filter(torch.rand(5, 5), 0)


def test_box_filter_at_the_reference_width_is_langsplats_cv2_filter2d() -> None:
    # LangSplat activate_stream: kernel = np.ones((30, 30)) / 900; cv2.filter2D(np_relev, -1, kernel).
    image = np.random.default_rng(2).random((731, 988)).astype(np.float32)
    expected = cv2.filter2D(image, -1, np.ones((30, 30)) / 900.0)
    size = scaled_size(30, 988)
    assert size == 30
    np.testing.assert_allclose(box_filter(torch.from_numpy(image), size).numpy(), expected, atol=1e-6)
    smoothed = smooth_map(torch.from_numpy(image)).numpy()
    np.testing.assert_allclose(smoothed, 0.5 * (expected + image), atol=1e-6)


def test_box_filter_window_of_30_spans_minus_15_to_plus_14() -> None:
    # cv2.filter2D's default anchor of an even kernel is (15, 15): pixel p averages p - 15 .. p + 14,
    # so an impulse at r reaches the outputs r - 14 .. r + 15.
    impulse = torch.zeros(80, 90)
    impulse[40, 45] = 1.0
    out = box_filter(impulse, 30)
    expected = torch.zeros(80, 90)
    expected[40 - 14 : 40 + 16, 45 - 14 : 45 + 16] = 1.0 / 900.0
    torch.testing.assert_close(out, expected, atol=1e-9, rtol=0)


def test_majority_filter_on_a_hand_made_mask() -> None:
    ring = torch.zeros(5, 5, dtype=torch.bool)
    ring[1:4, 1:4] = True
    ring[2, 2] = False
    # Centre: 8 of 9 -> set (hole filled); ring edges: 5 of 9 -> set; ring corners: 3 of 9 -> cleared;
    # outside at (0, 2): 3 of the 6 in-image pixels -> a tie, cleared as in LangSplat.
    expected = torch.zeros(5, 5, dtype=torch.bool)
    expected[2, 1:4] = True
    expected[1:4, 2] = True
    assert torch.equal(majority_filter(ring, 3, last_line_votes=True), expected)
    # As in LangSplat's smooth, by default the last row and column do not vote: (4, 2) sees only row 3,
    # all set; (1, 4) sees column 3 only, 2 of 3 set; (1, 3) loses column 4, 3 of 6 -> a tie, cleared.
    langsplat = torch.tensor(
        [
            [0, 0, 0, 0, 0],
            [0, 0, 1, 0, 1],
            [0, 1, 1, 1, 1],
            [0, 0, 1, 1, 1],
            [0, 1, 1, 1, 1],
        ],
        dtype=torch.bool,
    )
    assert torch.equal(majority_filter(ring, 3), langsplat)


def test_majority_filter_matches_a_loop_over_clipped_windows() -> None:
    g = torch.Generator().manual_seed(3)
    mask = torch.rand(2, 11, 13, generator=g) > 0.5
    got = majority_filter(mask, 5, last_line_votes=True)
    for b in range(2):
        for i in range(11):
            for j in range(13):
                window = mask[b, max(0, i - 2) : i + 3, max(0, j - 2) : j + 3]
                assert bool(got[b, i, j]) == (2 * int(window.sum()) > window.numel())


def test_majority_filter_keeps_full_and_empty_masks() -> None:
    assert majority_filter(torch.ones(6, 6, dtype=torch.bool), 5).all()
    assert not majority_filter(torch.zeros(6, 6, dtype=torch.bool), 5).any()
    mask = torch.rand(6, 6) > 0.5
    assert torch.equal(majority_filter(mask, 1), mask)


def _langsplat_smooth(mask: np.ndarray) -> np.ndarray:
    """LangSplat eval/utils.py smooth, written out: the most frequent value of the window i-3 .. i+3
    (its slice stops at min(i + 4, h - 1)), ties to 0 by np.argmax(np.bincount(...))."""
    h, w = mask.shape
    out = mask.copy()
    for i in range(h):
        for j in range(w):
            window = mask[max(0, i - 3) : min(i + 4, h - 1), max(0, j - 3) : min(j + 4, w - 1)]
            out[i, j] = np.argmax(np.bincount(window.reshape(-1)))
    return out


@pytest.mark.parametrize("shape", [(37, 53), (8, 9)])
def test_majority_filter_7_is_langsplats_smooth(shape) -> None:
    mask = (np.random.default_rng(5).random(shape) > 0.5).astype(np.uint8)
    got = majority_filter(torch.from_numpy(mask), 7)
    assert scaled_size(7, 988) == 7
    np.testing.assert_array_equal(got.numpy().astype(np.uint8), _langsplat_smooth(mask))


def test_mask_and_localization_at_988_px_are_langsplats() -> None:
    # LangSplat's activate_stream and lerf_localization written out with cv2, on a strip of a
    # 988-pixel-wide view (the width sets the sizes; a short strip keeps the smooth loop fast).
    rng = np.random.default_rng(6)
    noise = rng.random((3, 60, 988)).astype(np.float32)
    maps = np.stack([cv2.GaussianBlur(m, (0, 0), 6.0) for m in noise])
    maps *= np.float32([0.9, 1.0, 0.8])[:, None, None]
    kernel = np.ones((30, 30)) / 900.0
    smoothed = np.stack([0.5 * (cv2.filter2D(m, -1, kernel) + m) for m in maps])
    level = int(np.argmax(smoothed.reshape(3, -1).max(axis=1)))
    out = smoothed[level] - smoothed[level].min()
    out = np.clip(out / (out.max() + 1e-9) * 2.0 - 1.0, 0, 1)
    expected_mask = _langsplat_smooth((out > 0.4).astype(np.uint8))
    result = relevancy_mask(torch.from_numpy(maps))
    assert int(result.level) == level
    np.testing.assert_array_equal(result.mask.numpy().astype(np.uint8), expected_mask)
    filtered = np.stack([cv2.filter2D(m, -1, kernel) for m in maps])
    loc_level = int(np.argmax(filtered.reshape(3, -1).max(axis=1)))
    yx = np.unravel_index(np.argmax(filtered[loc_level]), filtered[loc_level].shape)
    got_level, got_yx = localization_point(torch.from_numpy(maps))
    assert int(got_level) == loc_level and tuple(got_yx.tolist()) == tuple(int(v) for v in yx)


# ---------------------------------------------------------------- level choice and normalisation


def test_smooth_map_is_half_box_half_map() -> None:
    delta = torch.zeros(7, 7)
    delta[3, 3] = 1.0
    smoothed = smooth_map(delta, box_size=3)
    assert float(smoothed[3, 3]) == pytest.approx(0.5 + 0.5 / 9.0)
    assert float(smoothed[2, 2]) == pytest.approx(0.5 / 9.0)
    torch.testing.assert_close(smooth_map(torch.full((7, 7), 0.3), box_size=3), torch.full((7, 7), 0.3))


def test_choose_level_uses_the_smoothed_maximum() -> None:
    maps = torch.zeros(3, 20, 20)
    maps[0, 5, 5] = 1.0  # a one-pixel spike: highest raw value, smoothed max 0.5 + 0.5 / 9
    maps[1, 8:14, 8:14] = 0.8  # a solid region: smoothed max 0.8
    maps[2, 8:14, 8:14] = 0.7
    level, smoothed = choose_level(maps, box_size=3)
    assert int(level) == 1
    assert float(smoothed[0].max()) == pytest.approx(0.5 + 0.5 / 9.0)
    assert float(smoothed[1].max()) == pytest.approx(0.8)


def test_choose_level_per_phrase() -> None:
    maps = torch.zeros(2, 3, 20, 20)
    maps[0, 2, 5:10, 5:10] = 0.9
    maps[1, 0, 5:10, 5:10] = 0.9
    level, smoothed = choose_level(maps)
    assert level.tolist() == [2, 0]
    assert smoothed.shape == maps.shape


def test_normalize_map_by_hand() -> None:
    ramp = torch.tensor([[0.0, 0.25, 0.5, 0.75, 1.0]])
    expected = torch.tensor([[0.0, 0.0, 0.0, 0.5, 1.0]])
    torch.testing.assert_close(normalize_map(ramp), expected)
    torch.testing.assert_close(normalize_map(ramp * 0.2 + 0.4), expected)


def test_normalize_map_of_a_constant_map_is_zero_not_nan() -> None:
    out = normalize_map(torch.full((2, 4, 5), 0.37))
    assert not torch.isnan(out).any()
    assert torch.equal(out, torch.zeros(2, 4, 5))
    assert not relevancy_mask(torch.full((3, 12, 16), 0.5)).mask.any()


def test_threshold_04_is_07_of_the_min_max_range() -> None:
    values = torch.tensor([[0.0, 0.69, 0.71, 1.0]])
    assert (normalize_map(values) > MASK_THRESHOLD).tolist() == [[False, False, True, True]]


# ---------------------------------------------------------------- full mask pipeline


@pytest.mark.parametrize(
    "gt",
    [_rect(40, 50, 30, 40), _rect(10, 10, 2, 2), _rect(0, 0, 25, 160), _disc(60, 80, 15), _disc(30, 120, 4)],
    ids=["rectangle", "2x2", "top-band", "disc", "small-disc"],
)
def test_a_perfect_map_gives_its_mask_back_at_160x120(gt) -> None:
    maps = torch.stack([gt.float() * 0.3, gt.float(), gt.float() * 0.6])
    result = relevancy_mask(maps)
    assert int(result.level) == 1
    assert torch.equal(result.mask, gt)


def test_a_perfect_map_of_relevancy_values_gives_its_mask_back() -> None:
    gt = _disc(70, 60, 20) | _rect(20, 100, 30, 45)
    maps = torch.where(gt, 0.62, 0.45)[None].expand(3, -1, -1)  # relevancy values, not 0/1
    assert torch.equal(relevancy_mask(maps).mask, gt)


def test_a_one_pixel_line_vanishes_and_a_two_pixel_band_survives() -> None:
    # Documented small-object limit: at 160 px (3x3 box) a band needs width > 0.4 x 3 pixels when the
    # map's maximum is a solid region (the block) and its minimum the background.
    thin, band, block = _rect(20, 30, 60, 1), _rect(20, 90, 60, 2), _rect(20, 120, 30, 30)
    mask = relevancy_mask((thin | band | block).float()[None]).mask
    assert not (mask & thin).any()
    assert torch.equal(mask & ~thin, band | block)


def test_relevancy_mask_from_features_equal_to_the_ground_truth() -> None:
    e = torch.eye(16)
    mug, table = _disc(60, 40, 12), _rect(70, 80, 40, 70)
    feats = torch.zeros(3, HEIGHT, WIDTH, 16)
    feats[:] = e[6]  # background: a concept of its own
    feats[2][mug], feats[2][table] = e[0], e[1]  # whole level
    feats[1][mug], feats[1][table] = (e[0] + e[2]) / 2**0.5, (e[1] + e[3]) / 2**0.5  # parts: cos 0.7
    maps = relevancy(feats, e[:2], e[8:12])  # [2, 3, H, W]
    result = relevancy_mask(maps)
    assert result.level.tolist() == [2, 2]
    assert torch.equal(result.mask[0], mug)
    assert torch.equal(result.mask[1], table)


def test_relevancy_mask_batched_equals_single_calls() -> None:
    g = torch.Generator().manual_seed(4)
    maps = torch.rand(3, 3, 30, 40, generator=g)
    batched = relevancy_mask(maps)
    for q in range(3):
        single = relevancy_mask(maps[q])
        assert torch.equal(batched.mask[q], single.mask)
        assert int(batched.level[q]) == int(single.level)
        torch.testing.assert_close(batched.normalized[q], single.normalized)


def test_relevancy_mask_at_langsplats_resolution_keeps_a_large_object() -> None:
    # 1000 px: LangSplat's 30-px box and 7x7 majority vote; only the corners round off.
    gt = _rect(200, 300, 300, 400, shape=(750, 1000))
    mask = relevancy_mask(gt.float()[None]).mask
    assert not (mask & ~gt).any()
    corners = _rect(200, 300, 20, 20, (750, 1000)) | _rect(200, 680, 20, 20, (750, 1000))
    corners |= _rect(480, 300, 20, 20, (750, 1000)) | _rect(480, 680, 20, 20, (750, 1000))
    assert torch.equal(mask & ~corners, gt & ~corners)


# ---------------------------------------------------------------- localization


def test_localization_hit_inside_and_outside() -> None:
    gt = _rect(40, 50, 30, 40)
    inside = torch.zeros(HEIGHT, WIDTH)
    inside[50:60, 60:70] = 0.9
    assert localization_hit(inside, gt)
    outside = torch.zeros(HEIGHT, WIDTH)
    outside[90:100, 120:130] = 0.9
    assert not localization_hit(outside, gt)


def test_localization_uses_the_box_filtered_maximum_over_levels() -> None:
    gt = _rect(40, 50, 30, 40)
    maps = torch.zeros(2, HEIGHT, WIDTH)
    maps[0, 100, 10] = 1.0  # a speck outside: highest raw value, box-filtered 1/9
    maps[1, 45:65, 55:85] = 0.5  # the object's level
    level, yx = localization_point(maps)
    assert int(level) == 1
    assert bool(gt[yx[0], yx[1]])
    assert localization_hit(maps, gt)
    assert not localization_hit(maps, _rect(0, 0, 20, 20))


def test_localization_of_a_flat_map_points_at_its_centre() -> None:
    flat = torch.full((3, 20, 30), 0.5)
    level, yx = localization_point(flat)
    # Every pixel ties; rows 9-10 and columns 9-20 are 10 pixels from the border, the first of them wins.
    assert int(level) == 0 and yx.tolist() == [9, 9]
    assert not localization_hit(flat, _rect(0, 0, 5, 5, shape=(20, 30)))


def test_localization_of_a_plateau_points_deep_inside_it() -> None:
    """A codebook-read map is constant over a concept's pixels: a plateau that spills a thin band
    above the object ties with it everywhere; its deepest point is the object's, not the band's."""
    gt = _rect(40, 50, 30, 40)  # rows 40-69, columns 50-89
    maps = torch.zeros(1, HEIGHT, WIDTH)
    maps[0, 40:70, 50:90] = 0.9
    maps[0, 30:40, 20:140] = 0.9  # the spill, first in row-major order
    level, yx = localization_point(maps, box_size=1)
    assert bool(gt[yx[0], yx[1]]) and localization_hit(maps, gt)
    # Across levels too: the level whose plateau is deeper is taken, though another ties in value.
    two = torch.zeros(2, HEIGHT, WIDTH)
    two[0, 0:3, 0:3] = 0.9
    two[1, 40:70, 50:90] = 0.9
    level, yx = localization_point(two, box_size=1)
    assert int(level) == 1 and bool(gt[yx[0], yx[1]])


def test_localization_ties_after_the_box_filter_point_inside_the_larger_plateau() -> None:
    """With the default box (3x3 at this width) a saturated object region and a thin saturated band
    both reach the same filtered maximum; the band is first in row-major order, the object deeper."""
    gt = _rect(40, 50, 30, 40)
    maps = torch.zeros(HEIGHT, WIDTH)
    maps[40:70, 50:90] = 1.0
    maps[5:8, 10:150] = 1.0  # three rows: its middle row reaches the maximum too
    level, yx = localization_point(maps)
    assert level.shape == () and yx.shape == (2,)
    assert bool(gt[yx[0], yx[1]]) and localization_hit(maps, gt)


def test_localization_of_batched_maps_is_per_map() -> None:
    maps = torch.zeros(2, 3, 20, 30)
    maps[0, 2, 5, 7] = 1.0
    maps[1, 0, 12, 3] = 1.0
    level, yx = localization_point(maps, box_size=1)
    assert level.tolist() == [2, 0] and yx.tolist() == [[5, 7], [12, 3]]
    # Plateaus of different depths in one batch: each map takes its own deepest pixel.
    plateaus = torch.zeros(2, 1, 20, 30)
    plateaus[0, 0, 2:5, 2:5] = 1.0  # depth 2 at (3, 3)
    plateaus[1, 0, 4:17, 10:23] = 1.0  # depth 7 at (10, 16)
    level, yx = localization_point(plateaus, box_size=1)
    assert level.tolist() == [0, 0] and yx.tolist() == [[3, 3], [10, 16]]


def test_localization_hit_rejects_a_mismatched_mask() -> None:
    with pytest.raises(ValueError, match="localization_hit"):
        localization_hit(torch.rand(10, 12), torch.zeros(12, 10, dtype=torch.bool))
