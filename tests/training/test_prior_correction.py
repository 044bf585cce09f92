"""Each view's aligned depth prior corrected by a smooth field (langfield/training/prior_correction.py)."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest

import langfield as lf
from langfield.training.start import INIT_ALIGNS, depth_prior_points
from langfield.training.start.correction import (
    AGREE,
    GRID,
    _basis,
    band_offsets,
    correct_priors,
    fuse_views,
    smooth_field,
)

W, H = 96, 72


@pytest.fixture(scope="module")
def views(room_factory):
    """The built-in room's training cameras, images and true z-depths (NaN where no surface)."""
    scene = lf.load_scene(room_factory(W, H))
    cams = scene.cameras("train")
    images = [scene.image(c.name) for c in cams]
    depths = [np.load(Path(scene.root) / "gt" / "depth" / f"{c.name}.npy").astype(np.float64) for c in cams]
    return scene, cams, images, [np.where(d > 0, d, np.nan) for d in depths]


def _error(depth: np.ndarray, truth: np.ndarray) -> float:
    return float(np.nanmedian(np.abs(np.log(depth / truth))))


def test_a_smooth_bend_of_one_view_is_mostly_removed(views) -> None:
    _, cams, images, depths = views
    bend = _basis(H, W) @ np.random.default_rng(0).standard_normal(GRID[0] * GRID[1]) * 0.03
    bent = [depths[0], depths[1] * np.exp(bend), depths[2]]
    before = _error(bent[1], depths[1])
    assert before > 0.015
    start = time.perf_counter()
    corrected, stats = correct_priors(cams, images, bent)
    elapsed = time.perf_counter() - start
    assert _error(corrected[1], depths[1]) < 0.6 * before
    # The views that were right stay within 1 %: the field moves them only where the photos say so.
    for k in (0, 2):
        assert _error(corrected[k], depths[k]) < 0.01
    assert all(0.02 < v["matched"] < 0.5 for v in stats["views"]) and 0 < stats["seconds"] <= elapsed
    assert all(np.isnan(c).sum() == np.isnan(d).sum() for c, d in zip(corrected, depths, strict=True))


def test_the_band_finds_a_common_error_where_the_photos_are_textured(views) -> None:
    _, cams, images, depths = views
    offsets = band_offsets(cams, images, [d * 1.05 for d in depths])
    for offset, kept in offsets:
        assert kept.mean() > 0.03
        assert np.median(offset[kept]) == pytest.approx(math.log(1 / 1.05), abs=0.004)
    flat = [np.full_like(im, 0.5) for im in images]  # no texture: no match is trusted
    assert not any(kept.any() for _, kept in band_offsets(cams, flat, depths))


def test_the_field_fit_is_robust_and_empty_without_data() -> None:
    basis = _basis(H, W)
    rng = np.random.default_rng(1)
    truth = basis @ (rng.standard_normal(basis.shape[-1]) * 0.02)
    clean = smooth_field(basis, truth, np.ones((H, W)))
    spoiled = truth.copy()
    outliers = rng.random((H, W)) < 0.2
    spoiled[outliers] += 0.5
    plain = smooth_field(basis, spoiled, np.ones((H, W)))
    robust = smooth_field(basis, spoiled, np.ones((H, W)), robust=True)
    assert np.median(np.abs(plain - clean)) > 0.05
    assert np.median(np.abs(robust - clean)) < 0.01
    assert not smooth_field(basis, truth, np.zeros((H, W))).any()
    nowhere = np.full((H, W), np.nan)
    assert not smooth_field(basis, nowhere, np.ones((H, W)), robust=True).any()


def test_views_without_depths_pass_through_and_bad_arguments_are_refused(views) -> None:
    _, cams, images, depths = views
    unknown = np.full((H, W), np.nan)
    alone, stats = correct_priors(cams, images, [depths[0], unknown, unknown])
    assert np.array_equal(alone[0], depths[0], equal_nan=True) and np.isnan(alone[1]).all()
    assert stats["views"] == [None, None, None]
    two, stats = correct_priors(cams, images, [depths[0], unknown, depths[2]])
    assert np.isnan(two[1]).all() and stats["views"][1] is None and stats["views"][0] is not None
    with pytest.raises(ValueError, match="one image and one depth map per camera"):
        correct_priors(cams, images[:2], depths)


def test_fusion_moves_views_that_disagree_a_little_to_their_mean(views) -> None:
    _, cams, _, depths = views
    spread = [depths[0] * math.exp(0.02), depths[1] * math.exp(-0.02), depths[2]]
    fused, stats = fuse_views(cams, spread)
    for k in range(3):
        before, after = _error(spread[k], depths[k]), _error(fused[k], depths[k])
        assert after < 0.6 * before if k < 2 else after < 0.01
    # A pixel no other view agrees with keeps its depth; the share that moved is what stats report.
    for k, view in enumerate(stats["views"]):
        moved = np.abs(np.log(fused[k] / spread[k])) > 1e-9
        assert 0.2 < view["fused"] < 1.0 and moved.mean() == pytest.approx(view["fused"], abs=0.05)
        assert np.array_equal(np.isnan(fused[k]), np.isnan(depths[k]))
        # Nor does a pixel at a depth edge: an interpolated depth there is neither side's.
        log = np.nan_to_num(np.log(spread[k]), nan=0.0)
        shifted = [np.roll(log, (dy, dx), (0, 1)) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
        span = np.max(shifted, 0) - np.min(shifted, 0)
        edge = span > 2 * AGREE
        edge[[0, -1]] = edge[:, [0, -1]] = False  # np.roll wraps around there
        assert edge.sum() > 50 and not moved[edge].any()
    # Views further apart than AGREE leave each other alone, but where their surfaces, scaled about
    # different cameras, happen to cross (under 1 % of the pixels here).
    apart = [d * math.exp(f * AGREE) for d, f in zip(depths, (2, -2, 6), strict=True)]
    kept, stats = fuse_views(cams, apart)
    for k, view in enumerate(stats["views"]):
        assert view["fused"] < 0.01
        assert np.nanmax(np.abs(np.log(kept[k] / apart[k]))) < AGREE


def test_fusion_passes_views_without_depths_through_and_refuses_bad_arguments(views) -> None:
    _, cams, _, depths = views
    unknown = np.full((H, W), np.nan)
    alone, stats = fuse_views(cams, [depths[0], unknown, unknown])
    assert np.array_equal(alone[0], depths[0], equal_nan=True) and stats["views"] == [None, None, None]
    two, stats = fuse_views(cams, [depths[0] * 1.01, unknown, depths[2]])
    assert np.isnan(two[1]).all() and stats["views"][1] is None and stats["views"][0]["fused"] > 0
    with pytest.raises(ValueError, match="one depth map per camera"):
        fuse_views(cams[:2], depths)


def test_the_depth_start_corrects_and_fuses_by_default_and_records_it(views) -> None:
    _, cams, images, depths = views
    assert INIT_ALIGNS[0] == "fused"
    priors = [(1.0 / d).astype(np.float32) for d in depths]
    stereo = [np.where(np.indices(d.shape).sum(0) % 5 == 0, d, np.nan) for d in depths]
    points, _, stats = depth_prior_points(cams, images, priors, "disparity", np.zeros((0, 3)), stereo)
    assert [v is not None for v in stats["correction"]["views"]] == [True] * 3
    assert [v is not None for v in stats["fusion"]["views"]] == [True] * 3
    assert len(points) == sum(int(np.isfinite(d).sum()) for d in depths)
    _, _, lines_only = depth_prior_points(
        cams, images, priors, "disparity", np.zeros((0, 3)), stereo, align="views"
    )
    assert "correction" not in lines_only and "align_seconds" in lines_only
    _, _, unfused = depth_prior_points(
        cams, images, priors, "disparity", np.zeros((0, 3)), stereo, align="smooth"
    )
    assert "correction" in unfused and "fusion" not in unfused
