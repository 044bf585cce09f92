"""The viewer in a real browser: headless Chromium loads the page, splats are drawn, and typing a
phrase changes what is shown (langfield/viewer/browser.py drives it)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from langfield import LanguageField
from langfield.viewer.browser import (
    browser_missing,
    grab,
    open_page,
    phrase_box,
    scene_region,
    splats_drawn,
    wait_for,
)
from langfield.viewer.server import Viewer

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(browser_missing() is not None, reason=f"no browser test: {browser_missing()}"),
]


def _differ(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(scene_region(a).astype(int) - scene_region(b).astype(int)).mean())


def test_viewer_draws_splats_and_answers_a_typed_phrase(viewer_field_dir, tmp_path) -> None:
    field = LanguageField.load(viewer_field_dir)
    viewer = Viewer(field, field.trained_scene(), port=0, save=tmp_path / "selections")
    try:
        with open_page(viewer.url) as page:
            page.get_by_text("Type a phrase").wait_for(timeout=30_000)
            drawn = wait_for(lambda: splats_drawn(grab(page)))
            assert drawn, "the page never showed anything but a flat canvas"
            page.wait_for_timeout(1000)  # the splats' depth sort settles
            with_splats = grab(page)
            viewer.splats.visible = False
            assert wait_for(lambda: _differ(grab(page), with_splats) > 5.0), "hiding splats changed nothing"
            viewer.splats.visible = True
            assert wait_for(lambda: _differ(grab(page), with_splats) < 2.0), "the splats did not come back"

            phrase_box(page).press_sequentially("sofa", delay=30)
            assert wait_for(lambda: viewer.answer.phrase == "sofa"), viewer.answer.text
            page.get_by_text(re.compile(r"of \d+ Gaussians")).wait_for(timeout=30_000)
            assert wait_for(lambda: _differ(grab(page), with_splats) > 3.0), "the selection is not shown"
    finally:
        viewer.close()
    assert len(viewer.answer.indices) > 0
