"""The viewer's logic without a browser (langfield/viewer/server.py): queries, the selection shown,
levels and threshold, export, the heat map and the browser's camera convention."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import viser.transforms as tf

from langfield import LanguageField
from langfield.io.ply import read_gaussian_ply
from langfield.viewer.server import DIM_COLOUR, Viewer, browser_camera

from .conftest import H, W


@pytest.fixture(scope="module")
def viewer(viewer_field_dir, tmp_path_factory):
    field = LanguageField.load(viewer_field_dir)
    v = Viewer(field, field.trained_scene(), port=0, save=tmp_path_factory.mktemp("selections"))
    yield v
    v.close()


def _shown(viewer: Viewer) -> tuple[np.ndarray, np.ndarray]:
    """The colours and opacities viser sends to the browser, in [0, 1] (it stores them as bytes)."""
    return viewer.splats.rgbs / 255.0, viewer.splats.opacities / 255.0


def test_viewer_serves_on_a_free_port_with_the_field_and_cameras(viewer) -> None:
    assert viewer.url.startswith("http://127.0.0.1:") and not viewer.url.endswith(":0")
    assert len(viewer.splats.centers) == viewer.field.num_gaussians


def test_a_phrase_selects_and_dims_the_rest_then_hides_it(viewer) -> None:
    base_rgb, base_opacity = _shown(viewer)
    answer = viewer.ask("sofa")
    expected = viewer.field.query("sofa").gaussians()
    assert np.array_equal(answer.indices, expected.indices.numpy()) and len(answer.indices) > 0
    assert "sofa" in answer.text and f"{len(answer.indices)} of" in viewer.status.content
    rgb, opacity = _shown(viewer)
    rest = np.ones(len(rgb), bool)
    rest[answer.indices] = False
    # Bytes: compare to one step, plus one for the rounding of the dimmed value.
    assert np.array_equal(rgb[answer.indices], base_rgb[answer.indices])
    assert np.allclose(opacity[rest], base_opacity[rest] * DIM_COLOUR, atol=2 / 255)
    assert np.allclose(rgb[rest], base_rgb[rest] * DIM_COLOUR, atol=2 / 255)
    viewer.hide_box.value = True
    viewer.refresh()
    assert np.all(_shown(viewer)[1][rest] == 0.0)
    viewer.hide_box.value = False
    viewer.ask("")
    assert np.array_equal(_shown(viewer)[1], base_opacity)  # no phrase: everything shown as before


def test_level_and_threshold_change_the_selection_as_query_gaussians(viewer) -> None:
    viewer.ask("lamp")
    query = viewer.field.query("lamp")
    for level_name, level in (("subpart", 0), ("whole", 2)):
        viewer.level_box.value = level_name
        for threshold in (0.2, 0.8):
            viewer.threshold_box.value = threshold
            answer = viewer.refresh()
            assert np.array_equal(answer.indices, query.gaussians(level, threshold).indices.numpy())
    strict = viewer.refresh().indices
    viewer.threshold_box.value = 0.2
    assert len(viewer.refresh().indices) >= len(strict)
    viewer.level_box.value, viewer.threshold_box.value = "auto", 0.4


def test_unknown_phrase_is_answered_in_the_panel(viewer) -> None:
    answer = viewer.ask("flux capacitor")
    assert "flux capacitor" in answer.text and answer.indices is None
    assert "flux capacitor" in viewer.status.content


def test_export_writes_the_selection_and_never_overwrites(viewer) -> None:
    answer = viewer.ask("sofa")
    first = viewer.export_selection()
    second = viewer.export_selection()
    paths = sorted(viewer.save.glob("sofa*.ply"))
    assert [p.name for p in paths] == ["sofa-2.ply", "sofa.ply"]
    assert "sofa.ply" in first.text and "sofa-2.ply" in second.text
    ply = read_gaussian_ply(paths[1])
    means = viewer.field.splats["means"].detach().numpy()[answer.indices]
    assert np.allclose(np.stack([ply["x"], ply["y"], ply["z"]], 1), means)
    viewer.ask("")
    assert "Nothing selected" in viewer.export_selection().text


def test_browser_camera_at_a_scene_camera_renders_that_view(viewer) -> None:
    """viser reports the camera in OpenCV axes; converted back it must be the scene's own camera."""
    scene = viewer.field.trained_scene()
    cam = scene.camera(scene.names("test")[0])
    wxyz = tf.SO3.from_matrix(cam.c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])).wxyz
    fov_y = 2.0 * np.arctan(0.5 * cam.height / cam.fy)
    again = browser_camera(cam.center, wxyz, fov_y, cam.width / cam.height, width=cam.width)
    assert np.allclose(again.c2w, cam.c2w, atol=1e-9) and again.fy == pytest.approx(cam.fy)
    with torch.no_grad():
        a = viewer.field.render(cam, language=False).rgb
        b = viewer.field.render(again, language=False).rgb
    assert torch.allclose(a, b, atol=1e-5)


def test_heat_view_is_the_render_or_its_heat_map(viewer) -> None:
    scene = viewer.field.trained_scene()
    cam = scene.camera(scene.names("test")[0])
    viewer.ask("")
    plain = viewer.heat_view(cam)
    with torch.no_grad():
        rgb = viewer.field.render(cam, language=False).rgb.clamp(0, 1).numpy()
    assert plain.shape == (H, W, 3) and np.abs(plain.astype(float) - rgb * 255).max() <= 1.0
    viewer.ask("sofa")
    heat = viewer.heat_view(cam)
    assert heat.shape == (H, W, 3) and np.abs(heat.astype(int) - plain.astype(int)).mean() > 10.0
    viewer.ask("")


def test_a_field_without_language_is_shown_and_asks_nothing(viewer_field_dir) -> None:
    field = LanguageField.load(viewer_field_dir)
    field.language = None  # as a field trained with --no-language
    assert not field.has_language
    v = Viewer(field, None, port=0)
    try:
        assert "no language" in v.status.content and v.phrase_box.disabled and v.export_button.disabled
        answer = v.ask("sofa")
        assert "no language" in answer.text and answer.indices is None
        assert len(v.splats.centers) == field.num_gaussians
    finally:
        v.close()
