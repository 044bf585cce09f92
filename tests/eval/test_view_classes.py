"""Test views classed against the training views: near, between, beyond (langfield/eval/view_classes.py)."""

from __future__ import annotations

import numpy as np
import pytest

from langfield.camera import Camera
from langfield.eval.view_classes import by_class, classify_views, hull_distance


def _cam(name: str, x: float, yaw_deg: float = 0.0) -> Camera:
    yaw = np.radians(yaw_deg)
    target = (x + 5.0 * np.sin(yaw), 5.0 * np.cos(yaw), 0.0)
    return Camera.look_at((x, 0.0, 0.0), target, (0.0, 0.0, 1.0), width=32, height=24, name=name)


def test_hull_distance_is_zero_inside_and_the_gap_outside() -> None:
    triangle = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    assert hull_distance(np.array([0.5, 0.5, 0.0]), triangle) == pytest.approx(0.0, abs=1e-6)
    assert hull_distance(np.array([0.5, 0.5, 3.0]), triangle) == pytest.approx(3.0, abs=1e-6)
    assert hull_distance(np.array([-1.0, -1.0, 0.0]), triangle) == pytest.approx(np.sqrt(2.0), abs=1e-6)
    assert hull_distance(np.array([2.0, 2.0, 0.0]), triangle) == pytest.approx(np.sqrt(2.0), abs=1e-6)


def test_views_at_between_and_beyond_the_training_cameras_are_classed_so() -> None:
    train = [_cam("a", 0.0), _cam("b", 1.0), _cam("c", 2.0)]  # baseline (1 + 2 + 1) / 3
    test = [_cam("at_b", 1.05), _cam("mid", 1.5), _cam("turned", 1.0, yaw_deg=40.0), _cam("far", 4.0)]
    classes = classify_views(train, test)
    assert {k: v["class"] for k, v in classes.items()} == {
        "at_b": "near", "mid": "between", "turned": "between", "far": "beyond"
    }  # fmt: skip
    assert classes["far"]["outside"] == pytest.approx(2.0 / (4.0 / 3.0), rel=1e-4)
    assert classes["turned"]["angle"] == pytest.approx(40.0, abs=0.01)


def test_one_training_view_has_no_span_between() -> None:
    classes = classify_views([_cam("a", 0.0)], [_cam("same", 0.0), _cam("other", 0.5)])
    assert classes["same"]["class"] == "near" and classes["other"]["class"] == "beyond"


def test_by_class_counts_and_averages_each_class() -> None:
    views = [
        {"PSNR": 20.0, "view_class": {"class": "near"}},
        {"PSNR": 24.0, "view_class": {"class": "near"}},
        {"PSNR": 12.0, "masked_PSNR": 15.0, "view_class": {"class": "beyond"}},
    ]
    summary = by_class(views)
    assert summary["near"] == {"views": 2, "PSNR": 22.0, "SSIM": None, "masked_PSNR": None}
    assert summary["between"]["views"] == 0 and summary["between"]["PSNR"] is None
    assert summary["beyond"]["masked_PSNR"] == 15.0
