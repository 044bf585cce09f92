"""eval.geometry.depth_agreement: the training views' rendered depths describe one surface or not."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import torch

from langfield.camera import Camera
from langfield.eval.geometry import depth_agreement, ray_lengths

W, H = 40, 30


class PlaneViews:
    """Three cameras looking down -z at the plane z = -2 (a stand-in for a Scene)."""

    def __init__(self, n: int = 3) -> None:
        self.cams = {
            f"v{i}": replace(
                Camera.look_at((x, 0.0, 0.0), (x, 0.0, -1.0), (0.0, 1.0, 0.0), width=W, height=H),
                name=f"v{i}",
            )
            for i, x in enumerate(np.linspace(-0.2, 0.2, n))
        }

    def names(self, split: str) -> list[str]:
        return list(self.cams)

    def camera(self, name: str) -> Camera:
        return self.cams[name]


class PlaneField:
    """Renders the plane z = -depth_of(view) with full (or given) coverage (a stand-in for a field)."""

    def __init__(self, depth_of, alpha: float = 1.0) -> None:
        self.depth_of, self.alpha = depth_of, alpha

    def render(self, cam: Camera):
        alpha = torch.full((H, W), self.alpha)
        distance = torch.from_numpy(self.depth_of(cam) * ray_lengths(cam)).float()
        return SimpleNamespace(alpha=alpha, depth=distance * alpha)  # soft depth: alpha-weighted


def test_one_surface_seen_three_times_agrees() -> None:
    result = depth_agreement(PlaneField(lambda cam: 2.0), PlaneViews())
    assert result["agreement"] > 0.99 and result["landed"] > 3 * W * H


def test_each_view_with_its_own_depth_does_not_agree() -> None:
    depths = {}
    result = depth_agreement(
        PlaneField(lambda cam: depths.setdefault(cam.name, 2.0 + 0.3 * len(depths))), PlaneViews()
    )
    assert result["agreement"] < 0.05


def test_soft_depth_is_divided_by_alpha_and_uncovered_views_give_none() -> None:
    # Alpha 0.6 everywhere: the surface is still at depth / alpha = 2.
    assert depth_agreement(PlaneField(lambda cam: 2.0, alpha=0.6), PlaneViews())["agreement"] > 0.99
    assert depth_agreement(PlaneField(lambda cam: 2.0, alpha=0.2), PlaneViews()) is None
    assert depth_agreement(PlaneField(lambda cam: 2.0), PlaneViews(n=1)) is None
