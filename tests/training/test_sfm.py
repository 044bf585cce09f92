"""Sparse SfM points with known poses (langfield.training.start.sfm, pycolmap) on the synthetic room."""

import numpy as np
import pytest

import langfield as lf
from langfield.synthetic import distance_to_surfaces, make_room

pytest.importorskip("pycolmap")

from langfield.training.start.sfm import sfm_points  # noqa: E402


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    """The room with 11 training views on its 70 degree arc; three neighbours 7 degrees apart.

    The default 3 views stand 35 degrees apart, too wide for SIFT on the room's procedural textures
    (no pair passes verification); neighbouring views of a denser arc match like real photos do.
    """
    root = make_room(tmp_path_factory.mktemp("room"), seed=0, width=160, height=120, n_train=11, n_test=0)
    scene = lf.load_scene(root)
    cams = scene.cameras("train")[4:7]
    return root, scene, cams, [scene.image(c.name) for c in cams]


def test_points_lie_on_the_room_surfaces(room):
    root, scene, cams, images = room
    points, colors, stats = sfm_points(cams, images)
    assert points.shape == colors.shape and points.shape[1] == 3 and len(points) >= 10, stats
    assert points.dtype == np.float32 and colors.dtype == np.float32
    assert colors.min() >= 0.0 and colors.max() <= 1.0
    assert stats["points"] == len(points) and stats["reason"] is None
    assert len(stats["features_per_view"]) == 3 and min(stats["features_per_view"]) > 0
    assert stats["matches"] > 0 and stats["seconds"] > 0

    diagonal = float(np.linalg.norm(np.diff(scene.bounds(), axis=0)))
    distance = distance_to_surfaces(root, points)
    assert np.median(distance) < 0.02 * diagonal, (np.median(distance), diagonal)

    # Every point is in front of every view and inside its image, with the photo's colour there.
    for cam, image in zip(cams, images, strict=True):
        w2c = cam.world_to_camera().numpy().astype(np.float64)
        p = points @ w2c[:3, :3].T + w2c[:3, 3]
        assert (p[:, 2] > 0).all()
        u, v = cam.fx * p[:, 0] / p[:, 2] + cam.cx, cam.fy * p[:, 1] / p[:, 2] + cam.cy
        assert ((u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)).all()
        seen = image[v.astype(int), u.astype(int)]
        assert np.abs(seen - colors).mean() < 0.05


def test_deterministic(room):
    _, _, cams, images = room
    a, b = sfm_points(cams, images), sfm_points(cams, images)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_blank_images_give_no_points(room):
    _, _, cams, images = room
    blank = [np.full_like(images[0], 0.5), np.full_like(images[1], 0.5)]
    points, colors, stats = sfm_points(cams[:2], blank)
    assert points.shape == (0, 3) and colors.shape == (0, 3)
    assert stats["points"] == 0 and stats["reason"]


def test_bad_inputs_raise(room):
    _, _, cams, images = room
    with pytest.raises(ValueError, match="at least 2 views"):
        sfm_points(cams[:1], images[:1])
    with pytest.raises(ValueError, match="shape"):
        sfm_points(cams[:2], [images[0], images[1][:-1]])
    with pytest.raises(ValueError, match="images for"):
        sfm_points(cams[:2], images[:1])
