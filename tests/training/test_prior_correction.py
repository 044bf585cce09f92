"""Each view's aligned depth prior corrected by a smooth field (langfield/training/prior_correction.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import langfield as lf
from langfield.training.initialisation import INIT_ALIGNS, depth_prior_points
from langfield.training.prior_correction import GRID, _basis, band_offsets, correct_priors, smooth_field

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
    corrected, stats = correct_priors(cams, images, bent)
    assert _error(corrected[1], depths[1]) < 0.6 * before
    # The views that were right stay within 1 %: the field moves them only where the photos say so.
    for k in (0, 2):
        assert _error(corrected[k], depths[k]) < 0.01
    assert all(0.02 < v["matched"] < 0.5 for v in stats["views"]) and stats["seconds"] >= 0
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


def test_the_depth_start_corrects_by_default_and_records_it(views) -> None:
    _, cams, images, depths = views
    assert INIT_ALIGNS[0] == "smooth"
    priors = [(1.0 / d).astype(np.float32) for d in depths]
    stereo = [np.where(np.indices(d.shape).sum(0) % 5 == 0, d, np.nan) for d in depths]
    points, _, stats = depth_prior_points(cams, images, priors, "disparity", np.zeros((0, 3)), stereo)
    assert [v is not None for v in stats["correction"]["views"]] == [True] * 3
    assert len(points) == sum(int(np.isfinite(d).sum()) for d in depths)
    _, _, lines_only = depth_prior_points(
        cams, images, priors, "disparity", np.zeros((0, 3)), stereo, align="views"
    )
    assert "correction" not in lines_only and "align_seconds" in lines_only
