"""Shared fixtures: small seeded Gaussian scenes for rasterizer tests."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as langfield/__init__.py, before torch loads

import pytest
import torch

from langfield.camera import Camera


def random_gaussians(n: int, channels: int, seed: int = 0, log_scale: float = -3.0) -> list[torch.Tensor]:
    """means, quats, scales, opacities, features of n random Gaussians around the origin."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 2
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.randn(n, 3, generator=g) * 0.5 + log_scale)
    opacities = torch.rand(n, generator=g) * 0.9 + 0.05
    features = torch.rand(n, channels, generator=g)
    return [means, quats, scales, opacities, features]


@pytest.fixture
def small_camera() -> Camera:
    return Camera.look_at((0.0, -3.0, 0.5), (0.0, 0.0, 0.0), width=40, height=30, fov_x_deg=60)


@pytest.fixture(scope="session")
def room_factory(tmp_path_factory):
    """``room_factory(width, height, **kwargs)``: the built-in room (seed 0 unless given), generated once
    per session for each set of arguments. Shared between modules: copy it before changing a file."""
    from langfield.synthetic import make_room

    made = {}

    def room(width: int, height: int, **kwargs):
        key = (width, height, tuple(sorted(kwargs.items())))
        if key not in made:
            made[key] = make_room(tmp_path_factory.mktemp("room"), width=width, height=height, **kwargs)
        return made[key]

    return room
