"""Preprocessing on a local Ray (langfield/io/preprocess_ray.py): the same files as a local run, every
view of several scenes, and nothing redone on a second run."""

from __future__ import annotations

import json
import shutil
from functools import partial
from pathlib import Path

import numpy as np
import pytest
from conftest import bare_room

from encoders.stubs import StubDepthEstimator, StubImageTextEncoder, StubSegmenter
from langfield.io.preprocess import Models, preprocess_scene

pytest.importorskip("ray", reason="needs the cluster extra (pip install -e '.[cluster]')")

from langfield.io.preprocess_ray import preprocess_on_ray  # noqa: E402

W, H = 40, 30


# Ray's workers build the models with this: a partial of package classes, so that it pickles by name.
MAKE_STUBS = partial(
    Models, StubSegmenter(), StubImageTextEncoder(image_size=16), StubDepthEstimator("disparity")
)


def stub_models() -> Models:
    return MAKE_STUBS()


def _outputs(root: Path) -> dict[str, np.ndarray]:
    files = sorted((root / "language_features").glob("*.npy")) + sorted((root / "depths").glob("*.npy"))
    return {f"{f.parent.name}/{f.name}": np.load(f) for f in files}


@pytest.mark.slow
def test_ray_preprocessing_writes_what_a_local_run_writes(tmp_path) -> None:
    scenes = [bare_room(tmp_path / f"room{k}", W, H, seed=k, n_test=1) for k in range(2)]
    local = Path(shutil.copytree(scenes[0], tmp_path / "local"))
    m = stub_models()
    preprocess_scene(local, m.segmenter, m.encoder, m.depth, progress=False)
    reports = preprocess_on_ray(scenes, stub_models(), MAKE_STUBS, progress=False)
    assert [r.scene for r in reports] == scenes
    for root, report in zip(scenes, reports, strict=True):
        assert report.features_written == report.views == report.depths_written
        assert set(report.seconds_per_image) == {"segmenter", "encoder", "depth"}
        assert json.loads((root / "transforms.json").read_text())["depth_kind"] == "disparity"
    expected, got = _outputs(local), _outputs(scenes[0])
    assert expected.keys() == got.keys() and len(got) == 3 * len(reports[0].views)
    for name, arr in expected.items():
        assert got[name].dtype == arr.dtype, name
        if np.issubdtype(arr.dtype, np.integer):  # the masks: identical
            np.testing.assert_array_equal(got[name], arr, err_msg=name)
        else:  # a worker runs one thread, this process two: the sums round differently (1e-8)
            np.testing.assert_allclose(got[name], arr, rtol=1e-5, atol=1e-6, err_msg=name)
    (scenes[1] / "depths" / f"{reports[1].views[0]}.npy").unlink()  # one view to redo, no more
    again = preprocess_on_ray(scenes, stub_models(), MAKE_STUBS, progress=False)
    assert [r.features_written for r in again] == [[], []]
    assert [r.depths_written for r in again] == [[], [reports[1].views[0]]]
