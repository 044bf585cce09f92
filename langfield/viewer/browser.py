"""A headless Chromium on the viewer's page: for the browser test and the demo's screenshot.

Driven by Playwright (the ``test`` extra) with the system's Chromium (Debian's ``chromium`` package,
which ``make system`` installs where it can); Playwright's own browser download is never used. WebGL runs
on SwiftShader, Chromium's CPU renderer, so splats are drawn without a GPU.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import cv2
import numpy as np

# No first-run, sync or update traffic (a closed network refuses it), no sandbox (CI runs as root), and
# WebGL on the CPU.
CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)
CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")


def find_chromium() -> str | None:
    """The Chromium to drive: ``$LANGFIELD_CHROMIUM``, else the first of :data:`CHROMIUM_NAMES` on the
    PATH; None when there is none."""
    given = os.environ.get("LANGFIELD_CHROMIUM")
    if given:
        return given if Path(given).is_file() else None
    return next((found for name in CHROMIUM_NAMES if (found := shutil.which(name))), None)


def browser_missing() -> str | None:
    """Why no browser can be driven here (None when one can)."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "Playwright is not installed (pip install -e '.[test]')"
    if find_chromium() is None:
        return "no Chromium found (Debian: apt-get install chromium; or set LANGFIELD_CHROMIUM)"
    return None


@contextmanager
def open_page(url: str, width: int = 1000, height: int = 700) -> Iterator:
    """A Playwright page showing ``url`` in headless Chromium, closed on exit."""
    from playwright.sync_api import sync_playwright

    reason = browser_missing()
    if reason is not None:
        raise RuntimeError(reason)
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=find_chromium(), args=list(CHROMIUM_FLAGS))
        try:
            page = browser.new_page(viewport={"width": width, "height": height})
            page.goto(url)
            yield page
        finally:
            browser.close()


def grab(page) -> np.ndarray:
    """``uint8 [H, W, 3]`` RGB screenshot of the page."""
    png = np.frombuffer(page.screenshot(), np.uint8)
    return cv2.cvtColor(cv2.imdecode(png, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def scene_region(shot: np.ndarray) -> np.ndarray:
    """The part of a viewer screenshot that only the 3D scene covers: viser's panel sits at the top right
    and its notices at the top left, so the lower-left half of the page."""
    h, w = shot.shape[:2]
    return shot[h // 4 :, : int(w * 0.6)]


def wait_for(condition: Callable[[], bool], timeout: float = 30.0, step: float = 0.25) -> bool:
    """Polls ``condition`` until it holds or ``timeout`` seconds pass; whether it held."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(step)
    return condition()


def phrase_box(page):
    """The panel's phrase box: the first input after the label "Phrase" (viser's labels name no input)."""
    return page.locator("xpath=//*[normalize-space(text())='Phrase']/following::input[1]")


def splats_drawn(shot: np.ndarray) -> bool:
    """Whether a viewer screenshot's scene region shows splats (not one flat colour)."""
    return float(scene_region(shot).std(axis=(0, 1)).mean()) > 10.0


def screenshot_viewer(url: str, path: str | Path) -> Path:
    """Writes the viewer's page at ``url`` to ``path`` (its format by the suffix) once the splats are drawn.

    Every screenshot is a frame, and on a CPU a frame of the splats takes seconds (SwiftShader); so does
    typing into the page, whose actionability checks wait for frames too. A caller that wants the
    viewer answering a phrase sets it on the server first (``viewer.phrase_box.value``): the page then
    opens with the answer, and the first frame that shows the splats is the one kept."""
    path = Path(path)
    with open_page(url) as page:
        # viser's notice of software WebGL covers the scene's top left; hidden by a style rule rather than
        # its close button, whose click waits for a frame.
        page.add_style_tag(content=".mantine-Notification-root { display: none !important; }")
        phrase_box(page).wait_for(timeout=30_000)
        page.wait_for_timeout(500)  # the heat map image arrives and the splats' sort settles
        last: list[np.ndarray] = []

        def drawn() -> bool:
            last[:] = [grab(page)]
            return splats_drawn(last[0])

        if not wait_for(drawn):
            raise RuntimeError("the viewer's page showed no splats")
    cv2.imwrite(str(path), cv2.cvtColor(last[0], cv2.COLOR_RGB2BGR))
    return path
