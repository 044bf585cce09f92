"""The depth priors aligned to one another (langfield/training/prior_alignment.py)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

import langfield as lf
from langfield.synthetic import distance_to_surfaces
from langfield.training.start import depth_prior_points
from langfield.training.start.alignment import CAP, alignment_cost, refine_alignment


@pytest.fixture(scope="module")
def views(room_factory):
    """The built-in room's training cameras and their true z-depths (NaN where a pixel sees no surface:
    priors from them are unknown there)."""
    scene = lf.load_scene(room_factory(64, 48))
    cams = scene.cameras("train")
    depths = [np.load(Path(scene.root) / "gt" / "depth" / f"{c.name}.npy").astype(np.float64) for c in cams]
    assert all(d.shape == (c.height, c.width) for c, d in zip(cams, depths, strict=True))
    depths = [np.where(d > 0, d, np.nan) for d in depths]
    assert np.isnan(depths[0]).any()  # the open side of the room
    return scene, cams, depths


def _relative_error(depth: np.ndarray, prior: np.ndarray, line, kind: str) -> float:
    t = line[0] * prior + line[1]
    z = 1.0 / t if kind == "disparity" else t
    return float(np.nanmedian(np.abs(z / depth - 1.0)))


@pytest.mark.parametrize("kind", ["disparity", "depth"])
def test_a_view_fitted_wrong_is_brought_back_by_the_others(views, kind) -> None:
    _, cams, depths = views
    priors = [(1.0 / d if kind == "disparity" else d).astype(np.float32) for d in depths]
    # The truth is the line (1, 0) in every view; the middle view's own fit went wrong (its stereo
    # matched the wrong tiles), the others' are right.
    wrong = (0.6, 0.15) if kind == "disparity" else (1.3, -0.4)
    lines = [(1.0, 0.0), wrong, (1.0, 0.0)]
    assert _relative_error(depths[1], priors[1], wrong, kind) > 0.1
    refined = refine_alignment(cams, priors, kind, lines)
    for depth, prior, line in zip(depths, priors, refined, strict=True):
        assert _relative_error(depth, prior, line, kind) < 0.01
    assert alignment_cost(cams, priors, kind, refined) < alignment_cost(cams, priors, kind, lines)


def test_anchors_count_in_the_cost_and_hold_the_lines(views) -> None:
    _, cams, depths = views
    priors = [(1.0 / d).astype(np.float32) for d in depths]
    truth = [(1.0, 0.0)] * 3
    anchors = []
    for p, d in zip(priors, depths, strict=True):
        known = np.isfinite(d[::7, ::7])
        anchors.append((p[::7, ::7][known], d[::7, ::7][known]))
    free = alignment_cost(cams, priors, "disparity", truth)
    assert alignment_cost(cams, priors, "disparity", truth, anchors) == pytest.approx(free, abs=1e-6)
    # Every view 30 % too far: its anchors are all past the truncation.
    far = [(1 / 1.3, 0.0)] * 3
    assert (
        alignment_cost(cams, priors, "disparity", far, anchors)
        >= alignment_cost(cams, priors, "disparity", far) + 3 * CAP - 1e-9
    )
    refined = refine_alignment(cams, priors, "disparity", far, anchors)
    for depth, prior, line in zip(depths, priors, refined, strict=True):
        assert _relative_error(depth, prior, line, "disparity") < 0.01


def test_the_cost_of_held_lines_is_the_cost_computed_afresh(views) -> None:
    # A view's search reuses where the other views' pixels landed (they hold their lines); each cost
    # must equal that of a fresh evaluation with the same counted pixels, whichever lines moved.
    from langfield.training.start.alignment import _Views

    _, cams, depths = views
    priors = [(1.0 / d).astype(np.float32) for d in depths]
    start = [(1.0, 0.0), (0.6, 0.15), (1.1, -0.02)]
    reused = _Views(cams, priors, "disparity", [None] * 3)
    reused.freeze(start)
    trials = [start, [start[0], (0.9, 0.05), start[2]], [start[0], (0.95, 0.0), start[2]], [(0.8, 0.1)] * 3]
    for lines in trials:
        fresh = _Views(cams, priors, "disparity", [None] * 3)
        fresh.freeze(start)
        for only in (None, 0, 1):
            assert reused.cost(lines, only=only) == fresh.cost(lines, only=only)
    assert len(reused.landed) < 6 * len(trials)  # the held views' landings were reused


def test_views_without_a_line_or_without_a_usable_prior_are_left_alone(views) -> None:
    _, cams, depths = views
    priors = [(1.0 / d).astype(np.float32) for d in depths]
    wrong = (0.6, 0.15)
    assert refine_alignment(cams, priors, "disparity", [None, wrong, None]) == [None, wrong, None]
    assert refine_alignment(cams[:1], priors[:1], "disparity", [wrong]) == [wrong]
    flat = [priors[0], np.full_like(priors[1], 0.3), priors[2]]  # a constant prior: no line to search
    refined = refine_alignment(cams, flat, "disparity", [(1.0, 0.0), wrong, (1.0, 0.0)])
    assert refined[1] == wrong
    nowhere = [(1.0, 0.0), (-1.0, 0.0), (1.0, 0.0)]  # no positive depth at all
    assert refine_alignment(cams, priors, "disparity", nowhere)[1] == (-1.0, 0.0)
    holes = [p.copy() for p in priors]
    holes[1][:10] = np.nan  # unknown pixels of a prior are skipped, not propagated
    refined = refine_alignment(cams, holes, "disparity", [(1.0, 0.0), wrong, (1.0, 0.0)])
    assert all(np.isfinite(v) for line in refined for v in line)
    assert _relative_error(depths[1][10:], priors[1][10:], refined[1], "disparity") < 0.01


def test_bad_arguments_are_refused(views) -> None:
    _, cams, depths = views
    priors = [(1.0 / d).astype(np.float32) for d in depths]
    with pytest.raises(ValueError, match="depth_kind"):
        refine_alignment(cams, priors, "inverse", [(1.0, 0.0)] * 3)
    with pytest.raises(ValueError, match="one prior and one line per camera"):
        refine_alignment(cams, priors[:2], "disparity", [(1.0, 0.0)] * 3)
    with pytest.raises(ValueError, match="align must be one of"):
        depth_prior_points(
            cams, [np.zeros((48, 64, 3))] * 3, priors, "disparity", np.zeros((0, 3)), align="x"
        )


def test_the_depth_start_refines_the_fits_and_records_both(views) -> None:
    scene, cams, depths = views
    images = [scene.image(c.name) for c in cams]
    priors = [(2.0 / d + 0.1).astype(np.float32) for d in depths]  # 1/z = 0.5 p - 0.05
    # Anchors for the middle view's fit only at one depth band, off by 20 %: its own fit is wrong.
    stereo = [np.where(np.indices(d.shape).sum(0) % 5 == 0, d, np.nan) for d in depths]
    stereo[1] = stereo[1] * 1.2
    kept, _, alone = depth_prior_points(
        cams, images, priors, "disparity", np.zeros((0, 3)), stereo, align="anchors"
    )
    start = time.perf_counter()
    points, _, both = depth_prior_points(cams, images, priors, "disparity", np.zeros((0, 3)), stereo)
    elapsed = time.perf_counter() - start
    assert "anchor_scale" not in alone["fits"][1] and "align_seconds" not in alone
    fit = both["fits"][1]
    assert (fit["anchor_scale"], fit["anchor_shift"]) == (
        alone["fits"][1]["scale"],
        alone["fits"][1]["shift"],
    )
    assert 0 < both["align_seconds"] < elapsed  # the alignment is timed, and is a part of the start
    # The fits of the right views hold; the wrong one is brought to the truth, and with it its points.
    for k in (0, 2):
        assert both["fits"][k]["scale"] == pytest.approx(0.5, rel=0.02)
    assert fit["scale"] == pytest.approx(0.5, rel=0.02) and fit["shift"] == pytest.approx(-0.05, abs=0.005)
    counts = [int(np.isfinite(d).sum()) for d in depths]
    assert len(points) == len(kept) == sum(counts)
    middle = slice(counts[0], counts[0] + counts[1])
    truth = distance_to_surfaces(scene.root, points[middle])
    before = distance_to_surfaces(scene.root, kept[middle])
    assert np.median(truth) < 0.01 < np.median(before)
