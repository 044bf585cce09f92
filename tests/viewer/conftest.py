"""A field trained briefly on the built-in room, saved, shared by the viewer's tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from langfield import TrainConfig, load_scene, train

W, H = 64, 48


@pytest.fixture(scope="session")
def viewer_field_dir(room_factory, tmp_path_factory) -> Path:
    scene = load_scene(room_factory(W, H))
    # Language from the first step: a short run's fit, not the default schedule, is what these test.
    field = train(scene, TrainConfig(iterations=150, seed=0, language_start=0.0), progress=False)
    field.meta["scene_args"] = {"resolution": 1.0, "views": None, "n_views": None}
    return field.save(tmp_path_factory.mktemp("viewer_field") / "out")
