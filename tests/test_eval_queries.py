"""Text queries in the evaluation (langfield/evaluate.py): per (view, phrase) IoU and hit, mIoU, mAcc."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch import Tensor, nn

from encoders.autoencoder import LanguageDecoder
from encoders.cache import read_feature_cache
from langfield import LanguageField, TrainConfig, evaluate, load_scene
from langfield.evaluate import write_report
from langfield.synthetic import make_room
from langfield.trainer import build_field

W, H = 64, 48


class CodebookDecoder(LanguageDecoder):
    """Decodes a latent to the feature of its nearest code: with each mask's code as its latent, the
    decoded features are the scene's mask features exactly (no autoencoder error). Its MLP weights are
    only there to be saved and sized.

    A zero latent (a pixel with no mask at that level) decodes to a zero feature. The codes are unit
    vectors, so a zero latent is equally far from all of them: its nearest code was picked by the
    rounding of the codes' norms, which differs between CPUs, and when the pick was an object's code,
    a few unmasked pixels joined that object's query (mIoU 0.9997 instead of 1 on some machines)."""

    def __init__(self, codes: Tensor, features: Tensor) -> None:
        super().__init__()
        self.codes, self.features = codes, features

    def decode(self, z: Tensor) -> Tensor:
        flat = z.reshape(-1, z.shape[-1])
        decoded = self.features[torch.cdist(flat, self.codes).argmin(dim=-1)]
        decoded = decoded * (flat != 0).any(dim=-1, keepdim=True)
        return decoded.reshape(*z.shape[:-1], self.features.shape[-1])


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    return make_room(tmp_path_factory.mktemp("room"), seed=0, width=W, height=H)


def ground_truth_field(scene, shift: int = 0) -> LanguageField:
    """A field whose render of view i gives the ground-truth latents of view i + ``shift`` (of the same
    split) and an opacity of 1 exactly where the view has a whole-level mask."""
    field = build_field(scene, TrainConfig(num_gaussians=200))
    codes, features, truth = [], [], {}
    generator = torch.Generator().manual_seed(0)
    for name in scene.names("all"):
        cam = scene.camera(name)
        cache = read_feature_cache(*scene.feature_paths(name), expected_hw=(cam.height, cam.width))
        code = nn.functional.normalize(torch.randn(len(cache.features), 3, generator=generator), dim=-1)
        seg = torch.from_numpy(cache.segments.astype(np.int64))
        latents = code[seg.clamp_min(0)] * (seg >= 0)[..., None]
        truth[name] = (latents, (seg[2] >= 0).float())
        codes.append(code)
        features.append(torch.from_numpy(cache.features))
    field.decoder = CodebookDecoder(torch.cat(codes), torch.cat(features))
    names = scene.names("test")
    source = {n: names[(i + shift) % len(names)] for i, n in enumerate(names)}
    render = field.render

    def render_truth(camera, **kwargs):
        latents, alpha = truth[source.get(camera.name, camera.name)]
        return render(camera, **kwargs)._replace(latents=latents, alpha=alpha)

    field.render = render_truth
    return field


def test_ground_truth_latents_give_miou_1(scene_dir, tmp_path) -> None:
    scene = load_scene(scene_dir)
    report = evaluate(ground_truth_field(scene), scene, save_dir=tmp_path / "pics")
    assert report["mIoU"] == 1.0 and report["mAcc"] == 1.0
    for view in report["views"]:
        labelled = {p.stem for p in (scene_dir / "segmentations" / view["name"]).glob("*.png")}
        assert set(view["queries"]) == labelled and len(labelled) >= 5
        for record in view["queries"].values():
            assert record == {"iou": 1.0, "hit": True}


def test_pixels_without_a_mask_at_a_level_decode_to_no_feature(scene_dir) -> None:
    # The ground-truth field must not depend on how a CPU rounds: the test views have covered pixels
    # without a mask at a finer level (masks under MIN_MASK_PIXELS), whose zero latent has no nearest code.
    scene = load_scene(scene_dir)
    field = ground_truth_field(scene)
    unlabelled = 0
    for name in scene.names("test"):
        cam = scene.camera(name)
        seg = read_feature_cache(*scene.feature_paths(name), expected_hw=(cam.height, cam.width)).segments
        unlabelled += int(((seg[2] >= 0) & (seg[:2] < 0).any(axis=0)).sum())
    assert unlabelled > 0
    assert torch.count_nonzero(field.decode(torch.zeros(5, 3))) == 0


def test_latents_of_another_view_score_lower(scene_dir) -> None:
    scene = load_scene(scene_dir)
    report = evaluate(ground_truth_field(scene, shift=1), scene)
    assert report["mIoU"] < 0.7 and report["mAcc"] < 0.9
    pairs = [q for v in report["views"] for q in v["queries"].values()]
    assert report["mIoU"] == pytest.approx(np.mean([q["iou"] for q in pairs]))
    assert report["mAcc"] == pytest.approx(np.mean([q["hit"] for q in pairs]))


def test_report_json_and_markdown_show_the_queries(scene_dir, tmp_path) -> None:
    scene = load_scene(scene_dir)
    pics = tmp_path / "pics"
    report = evaluate(ground_truth_field(scene), scene, save_dir=pics)
    md = write_report(report, tmp_path / "report.json", pics)
    written = json.loads((tmp_path / "report.json").read_text())
    assert written["mIoU"] == 1.0 and written["views"][0]["queries"]["wall"] == {"iou": 1.0, "hit": True}
    text = md.read_text()
    assert "## Text queries" in text and "| sofa |" in text
    for name in scene.names("test"):
        sheet = cv2.imread(str(pics / f"{name}_queries.png"))
        assert sheet is not None and sheet.shape[0] > 2 * H, name
        assert f"{name}_queries.png" in text


def _copy_scene(scene_dir: Path, dest: Path, *, segmentations: bool = True, table: bool = True) -> Path:
    ignore = [] if segmentations else ["segmentations"]
    ignore += [] if table else ["text_embeddings.npz"]
    shutil.copytree(scene_dir, dest, ignore=shutil.ignore_patterns(*ignore))
    return dest


def test_scene_without_labels_gives_null(scene_dir, tmp_path) -> None:
    scene = load_scene(_copy_scene(scene_dir, tmp_path / "room", segmentations=False))
    report = evaluate(ground_truth_field(scene), scene)
    assert report["mIoU"] is None and report["mAcc"] is None
    assert all(view["queries"] == {} for view in report["views"])


def test_field_without_language_gives_null(scene_dir) -> None:
    scene = load_scene(scene_dir)
    report = evaluate(build_field(scene, TrainConfig(num_gaussians=200)), scene)
    assert report["mIoU"] is None and report["mAcc"] is None
    assert all(view["queries"] == {} for view in report["views"])


def test_a_labelled_phrase_the_encoder_does_not_know_is_a_clear_error(scene_dir, tmp_path) -> None:
    root = _copy_scene(scene_dir, tmp_path / "room")
    cv2.imwrite(str(root / "segmentations" / "test_000" / "spaceship.png"), np.full((H, W), 255, np.uint8))
    scene = load_scene(root)
    with pytest.raises(ValueError, match="'spaceship'"):
        evaluate(ground_truth_field(scene), scene)


def test_no_text_encoder_warns_and_gives_null(scene_dir, tmp_path) -> None:
    scene = load_scene(_copy_scene(scene_dir, tmp_path / "room", table=False))
    field = ground_truth_field(scene)
    assert field.meta["text_encoder"] is None  # the copy has no text_embeddings.npz
    with pytest.warns(UserWarning, match="mIoU, mAcc null"):
        report = evaluate(field, scene)
    assert report["mIoU"] is None and report["PSNR"] is not None


def test_a_text_encoder_can_be_given_to_the_evaluation(scene_dir, tmp_path) -> None:
    scene = load_scene(_copy_scene(scene_dir, tmp_path / "room", table=False))
    report = evaluate(ground_truth_field(scene), scene, text_encoder=scene_dir / "text_embeddings.npz")
    assert report["mIoU"] == 1.0
