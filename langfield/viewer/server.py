"""The browser viewer (``langfield view``): a viser server showing the field's Gaussians as splats, the
scene's cameras as frustums, and a panel that asks the field text queries.

viser draws the splats in the browser (WebGL), each Gaussian with the colour the PLY export bakes at its
centre. The panel's phrase runs ``field.query(phrase)``: the Gaussians it selects keep their colour and
the rest are dimmed or hidden (a toggle); langfield renders the query's heat map for the browser's
current camera and shows it in the panel, redrawn as the camera moves (the newest pose wins: poses that
arrive during a render are not queued). The level choice and the threshold act on the selection and on
the heat map's outline as on :meth:`langfield.query.Query.gaussians`. "Export selection" writes the
selected Gaussians as a 3DGS PLY into the save folder, never over an existing file.

The server binds ``host`` (default localhost only) and, where ``port`` is taken, the next free port:
:attr:`Viewer.url` is the address actually served. Nothing is downloaded: the page is viser's own,
installed with it.
"""

from __future__ import annotations

import contextlib
import io
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import torch
import viser
import viser.transforms as tf

from encoders.text_table import UnknownPhraseError
from langfield.camera import Camera
from langfield.model import gaussians as G
from langfield.query import MATCH_RELEVANCY, Query, text_encoder_for
from langfield.raster.projection import covariance_3d
from langfield.viewer.paths import look_target
from langfield.viewer.video import heat_of, render_rgb, to_uint8
from querying.relevancy import MASK_THRESHOLD
from querying.visualize import heatmap_overlay

if TYPE_CHECKING:
    from langfield.field import LanguageField
    from langfield.io.scene import Scene

LEVELS = ("auto", "subpart", "part", "whole")  # the panel's level choice: auto, then levels 0, 1, 2
HEAT_WIDTH = 240  # pixels across the panel's heat map: a query view at this size takes ~0.05 s read as the
# nearest codebook entry, ~0.25 s read by vote (two cores, a room of 4,400 Gaussians and 140 entries)
DIM_COLOUR = 0.3  # unselected Gaussians, dimmed: colour and opacity scaled by this
FRUSTUM_SIZE = 0.01  # frustum depth, of the bounds' diagonal
FRUSTUM_LINE = 2.0  # pixels
PULL_BACK = 1.6  # the first view: this much farther than the cameras from what they look at
PROMPT = "Type a phrase (a thing in the scene): it is asked as you type."
NO_LANGUAGE = "This field has no language features: it shows the splats and cameras, and answers no phrase."
TRAIN_COLOUR, TEST_COLOUR = (230, 120, 20), (40, 110, 230)
_CV_TO_GL = np.diag([1.0, -1.0, -1.0])


@dataclass
class Answer:
    """What the panel says after a phrase: the text shown, and the selection (empty when none)."""

    text: str
    phrase: str = ""
    indices: np.ndarray | None = None
    seconds: float = 0.0


def browser_camera(position, wxyz, fov_y: float, aspect: float, width: int = HEAT_WIDTH) -> Camera:
    """A langfield camera at a viser camera's pose (OpenCV axes: x right, y down, z forward) with its
    vertical field of view (radians) and aspect ratio, ``width`` pixels across."""
    height = max(int(round(width / max(aspect, 1e-6))), 1)
    fy = 0.5 * height / np.tan(0.5 * fov_y)
    c2w = np.eye(4)
    c2w[:3, :3] = tf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix() @ _CV_TO_GL
    c2w[:3, 3] = position
    return Camera("browser", width, height, fy, fy, width / 2.0, height / 2.0, c2w)


class Viewer:
    """A viser server for one field (see the module's docstring).

    Args:
        field: a trained field.
        scene: its scene, for the camera frustums and the first view (optional).
        host, port: where to serve (the next free port if ``port`` is taken).
        text_encoder: as for :meth:`langfield.field.LanguageField.query` (default the field's own).
        save: folder the "Export selection" button writes PLYs into (made when first needed).
    """

    def __init__(
        self,
        field: LanguageField,
        scene: Scene | None = None,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        text_encoder=None,
        save: str | Path = "selections",
    ) -> None:
        self.field = field
        if field.has_language and (text_encoder is not None or field.meta.text_encoder is not None):
            # Read now, so that a phrase table that cannot answer stops the viewer before it serves.
            text_encoder = text_encoder_for(field, text_encoder)
        self.text_encoder = text_encoder
        self.save = Path(save)
        self.query: Query | None = None
        self.answer = Answer(PROMPT if field.has_language else NO_LANGUAGE)
        self._lock = threading.RLock()
        self._splat_data = self._splat_arrays()
        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: `langfield view` says where
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        cameras = scene.cameras("all") if scene is not None else []
        train = set(scene.names("train")) if scene is not None else set()
        self._place_scene(cameras, train)
        self.splats = self.server.scene.add_gaussian_splats("/field", *self._splat_data)
        self._heat = _LatestOnly(self._draw_heat)  # before the panel, whose callbacks use them
        self._asker = _LatestOnly(self.ask)
        self._build_panel()
        self.server.on_client_connect(self._on_connect)

    # ------------------------------------------------------------------ setup

    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def _splat_arrays(self) -> tuple[np.ndarray, ...]:
        splats = {k: v.detach() for k, v in self.field.splats.items()}
        with torch.no_grad():
            cov = covariance_3d(G.quats_normalized(splats), G.scales(splats))
            rgb = self.field.color.bake_dc(splats["means"]).clamp(0.0, 1.0)
        opacity = torch.sigmoid(splats["opacity_logits"]).reshape(-1, 1)
        return tuple(t.numpy().astype(np.float32) for t in (splats["means"], cov, rgb, opacity))

    def _place_scene(self, cameras: list[Camera], train: set[str]) -> None:
        """Frustums for the cameras; the browser's first view looks where they look, from behind them
        (without a scene, at the bounds' centre from their -y side)."""
        centre = self.field.meta.centre
        bounds = self.field.meta.bounds if self.field.meta.get("bounds") is not None else None
        size = float(np.linalg.norm(bounds[1] - bounds[0])) if bounds is not None else 1.0
        for cam in cameras:
            self.server.scene.add_camera_frustum(
                f"/cameras/{'train' if cam.name in train else 'test'}/{cam.name}",
                fov=2.0 * np.arctan(0.5 * cam.height / cam.fy),
                aspect=cam.width / cam.height,
                scale=FRUSTUM_SIZE * size,
                wxyz=tf.SO3.from_matrix(cam.c2w[:3, :3] @ _CV_TO_GL).wxyz,
                position=cam.center,
                color=TRAIN_COLOUR if cam.name in train else TEST_COLOUR,
                thickness=FRUSTUM_LINE,
                thickness_units="screen",
            )
        initial = self.server.initial_camera
        if cameras:
            # Behind the cameras' mean position, so that their frustums are in view and none fills it.
            target = look_target(cameras, centre)
            middle = np.mean([c.center for c in cameras], axis=0)
            initial.position = target + PULL_BACK * (middle - target)
            initial.look_at = target
            initial.up = np.mean([c.c2w[:3, 1] for c in cameras], axis=0)
            initial.fov = 2.0 * np.arctan(0.5 * cameras[0].height / cameras[0].fy)
        else:
            initial.position = centre + np.array([0.0, -1.2 * size, 0.4 * size])
            initial.look_at = centre
            initial.up = (0.0, 0.0, 1.0)

    def _build_panel(self) -> None:
        gui = self.server.gui
        self.phrase_box = gui.add_text("Phrase", initial_value="")
        self.level_box = gui.add_dropdown("Level", LEVELS, initial_value="auto")
        self.threshold_box = gui.add_slider("Threshold", 0.0, 1.0, 0.01, MASK_THRESHOLD)
        self.hide_box = gui.add_checkbox("Hide unselected", False)
        self.export_button = gui.add_button("Export selection")
        self.status = gui.add_markdown(self.answer.text)
        self.heat_image = gui.add_image(np.zeros((1, 1, 3), np.uint8), label="Relevancy (this view)")
        # The box reports every keystroke: the newest text is asked, the ones typed meanwhile skipped.
        self.phrase_box.on_update(lambda _: self._asker.request(self.phrase_box.value))
        for box in (self.level_box, self.threshold_box, self.hide_box):
            box.on_update(lambda _: self.refresh())
        self.export_button.on_click(lambda _: self._say(self.export_selection()))
        if not self.field.has_language:  # nothing to ask: the controls are shown, greyed out
            for handle in (self.phrase_box, self.level_box, self.threshold_box, self.hide_box):
                handle.disabled = True
            self.export_button.disabled = True

    def _on_connect(self, client: viser.ClientHandle) -> None:
        client.camera.on_update(lambda cam: self._heat.request(cam))

    # ------------------------------------------------------------------ queries

    def ask(self, phrase: str) -> Answer:
        """Runs ``field.query(phrase)`` and shows its selection and heat map; the panel's answer."""
        phrase = phrase.strip()
        t0 = time.perf_counter()
        with self._lock:
            if not phrase:
                self.query = None
            elif not self.field.has_language:
                return self._say(Answer(NO_LANGUAGE))
            else:
                try:
                    self.query = self.field.query(phrase, self.text_encoder)
                except (UnknownPhraseError, ValueError) as err:
                    self.query = None
                    self._show_selection(None)
                    return self._say(Answer(f"**{phrase}**: {err}", phrase))
            answer = self.refresh(t0)
        return answer

    def _level(self) -> int | None:
        index = LEVELS.index(self.level_box.value)
        return None if index == 0 else index - 1

    def refresh(self, t0: float | None = None) -> Answer:
        """Re-applies the current phrase with the panel's level, threshold and hiding."""
        t0 = time.perf_counter() if t0 is None else t0
        with self._lock:
            if self.query is None:
                self._show_selection(None)
                self._redraw_heat()
                return self._say(Answer(PROMPT if self.field.has_language else NO_LANGUAGE))
            phrase = self.query.phrases[0]
            sel = self.query.gaussians(self._level(), float(self.threshold_box.value))
            indices = sel.indices.numpy()
            self._show_selection(indices)
            self._redraw_heat()
            seconds = time.perf_counter() - t0
            n = self.field.num_gaussians
            if len(indices) == 0:
                text = (
                    f"**{phrase}**: found nowhere (best relevancy {sel.best:.2f}, not above "
                    f"{MATCH_RELEVANCY}); answered in {seconds:.2f} s"
                )
            else:
                text = (
                    f"**{phrase}**: {len(indices)} of {n} Gaussians, level {LEVELS[sel.level + 1]}, "
                    f"best relevancy {sel.best:.2f}; selected in {seconds:.2f} s"
                )
            return self._say(Answer(text, phrase, indices, seconds))

    def _say(self, answer: Answer) -> Answer:
        self.answer = answer
        self.status.content = answer.text
        return answer

    def _show_selection(self, indices: np.ndarray | None) -> None:
        centers, cov, rgb, opacity = self._splat_data
        if indices is not None and len(indices) > 0:
            keep = np.zeros(len(centers), dtype=bool)
            keep[indices] = True
            factor = 0.0 if self.hide_box.value else DIM_COLOUR
            rgb = np.where(keep[:, None], rgb, rgb * factor)
            opacity = np.where(keep[:, None], opacity, opacity * factor)
        self.splats.set_gaussians(centers, cov, rgb, opacity)

    def export_selection(self) -> Answer:
        """Writes the current selection as a PLY in the save folder (a new name if the file exists)."""
        answer = self.answer
        said = answer.text.split("\n\n")[0]  # without what an earlier export added
        if answer.indices is None or len(answer.indices) == 0:
            return replace(answer, text=f"{said}\n\nNothing selected to export.")
        stem = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in answer.phrase) or "selection"
        path, k = self.save / f"{stem}.ply", 1
        while path.exists():
            k += 1
            path = self.save / f"{stem}-{k}.ply"
        self.field.export_ply(path, torch.as_tensor(answer.indices))
        return replace(answer, text=f"{said}\n\nExported {len(answer.indices)} Gaussians to `{path}`.")

    # ------------------------------------------------------------------ the heat map

    def _redraw_heat(self) -> None:
        clients = list(self.server.get_clients().values())
        if clients:
            self._heat.request(clients[-1].camera)

    def heat_view(self, camera: Camera) -> np.ndarray:
        """``uint8 [H, W, 3]``: the render at ``camera``, with the current query's heat map over it and
        the outline where it passes the threshold (the plain render without a query)."""
        with self._lock:  # one query is not shared across threads
            rgb = render_rgb(self.field, camera)
            if self.query is None:
                return to_uint8(rgb)
            heat = heat_of(self.query.view(camera), self._level())
            threshold = float(self.threshold_box.value)
        image = heatmap_overlay(rgb, heat)
        mask = (heat > threshold).numpy().astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(image, contours, -1, (255, 255, 255), 1)
        return image

    def _draw_heat(self, cam) -> None:
        camera = browser_camera(cam.position, cam.wxyz, cam.fov, cam.aspect)
        self.heat_image.image = self.heat_view(camera)

    def close(self) -> None:
        self._asker.stop()
        self._heat.stop()
        self.server.stop()


class _LatestOnly:
    """Runs ``work(item)`` on a thread of its own for the newest item requested: items that arrive while
    it works replace each other, so a moving camera never builds a queue of renders."""

    def __init__(self, work) -> None:
        self._work = work
        self._item = None
        self._wake = threading.Condition()
        self._stopped = False
        self._thread = threading.Thread(target=self._run, daemon=True, name="langfield-heat")
        self._thread.start()

    def request(self, item) -> None:
        with self._wake:
            self._item = item
            self._wake.notify()

    def _run(self) -> None:
        while True:
            with self._wake:
                while self._item is None and not self._stopped:
                    self._wake.wait()
                if self._stopped:
                    return
                item, self._item = self._item, None
            try:
                self._work(item)
            except Exception as err:  # a failed redraw must not end the thread; the panel says why
                print(f"langfield view: {err}")

    def stop(self) -> None:
        with self._wake:
            self._stopped = True
            self._wake.notify()
        self._thread.join(timeout=5.0)

