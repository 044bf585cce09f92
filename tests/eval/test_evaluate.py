"""Text queries in the evaluation (langfield/eval/evaluate.py): per (view, phrase) IoU and hit, mIoU, mAcc."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace
from typing import NamedTuple

import cv2
import numpy as np
import open3d as o3d
import pytest
import torch
from torch import Tensor, nn

from encoders.autoencoder import LanguageDecoder
from encoders.cache import read_feature_cache
from langfield import LanguageField, TrainConfig, evaluate, load_scene
from langfield.eval.evaluate import write_report
from langfield.eval.geometry import selection_scores
from langfield.io.field_meta import FieldMeta
from langfield.synthetic.ground_truth import uncovered_triangles
from langfield.training.setup import build_field
from langfield.training.targets import scene_bounds

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
def scene_dir(room_factory) -> Path:
    return room_factory(W, H)


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
    # Per-Gaussian latents (all zero) make it a field with language, as every field evaluate queries is;
    # its renders' latents are replaced below.
    field.splats["lang"] = nn.Parameter(torch.zeros(field.num_gaussians, 9), requires_grad=False)
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
    # Each view is classed against the training views, and each class's scores are summarised.
    classes = [v["view_class"]["class"] for v in written["views"]]
    assert sum(c["views"] for c in written["by_view_class"].values()) == len(scene.names("test"))
    for kind in set(classes):
        psnrs = [v["PSNR"] for v in written["views"] if v["view_class"]["class"] == kind]
        assert written["by_view_class"][kind]["PSNR"] == pytest.approx(sum(psnrs) / len(psnrs))
        assert f"| {kind} | {classes.count(kind)} |" in text
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


def test_the_oracle_scores_the_true_features_as_the_ground_truth_field(scene_dir, tmp_path) -> None:
    # The ground-truth field renders each view's own mask features, so its queries are the oracle's.
    scene = load_scene(scene_dir)
    report = evaluate(ground_truth_field(scene), scene, oracle=True)
    assert report["oracle"] == {"mIoU": 1.0, "mAcc": 1.0, "ratio": 1.0}
    for view in report["views"]:
        assert view["oracle_queries"] == view["queries"]
    md = write_report(report, tmp_path / "report.json")
    assert "Oracle" in md.read_text() and json.loads((tmp_path / "report.json").read_text())["oracle"]


def test_the_oracle_does_not_follow_the_field(scene_dir) -> None:
    scene = load_scene(scene_dir)
    report = evaluate(ground_truth_field(scene, shift=1), scene, oracle=True)
    oracle = report["oracle"]
    assert oracle["mIoU"] == 1.0 and report["mIoU"] < 0.7
    assert oracle["ratio"] == pytest.approx(report["mIoU"] / oracle["mIoU"])
    assert evaluate(ground_truth_field(scene), scene)["oracle"] is None  # only when asked


def test_the_oracle_refuses_a_view_without_a_feature_cache_before_any_render(scene_dir, tmp_path) -> None:
    root = _copy_scene(scene_dir, tmp_path / "room")
    for suffix in ("_f.npy", "_s.npy"):
        (root / "language_features" / f"test_001{suffix}").unlink()
    scene = load_scene(root)
    field = ground_truth_field(load_scene(scene_dir))

    def no_render(*args, **kwargs):
        raise AssertionError("rendered before the check")

    field.render = no_render
    with pytest.raises(ValueError, match="test_001_f.npy: missing; --oracle"):
        evaluate(field, scene, oracle=True)
    with pytest.raises(ValueError, match="no language"):
        evaluate(build_field(scene, TrainConfig(num_gaussians=200)), scene, oracle=True)


# ---------------------------------------------------------------- 3D selection against the true surfaces


class _Chosen(NamedTuple):
    indices: Tensor


class _SelectionField:
    """A field of points on the room's surfaces whose 3D query answers are set by the test."""

    def __init__(self, scene, means: np.ndarray, answers: dict[str, np.ndarray]) -> None:
        self.meta = FieldMeta({"bounds": scene_bounds(scene, TrainConfig()).tolist()})
        self.splats = {"means": torch.from_numpy(means).float()}
        self.decoder, self.has_language, self.answers = object(), True, answers
        self.queried: list[str] = []

    def query(self, phrases, text_encoder=None, scene=None):
        self.queried = list(phrases)
        answers = [_Chosen(torch.from_numpy(self.answers.get(p, np.zeros(0, np.int64)))) for p in phrases]
        return SimpleNamespace(gaussians=lambda: answers)


def _surface_points(scene_dir: Path, whole: str, n: int, seed: int) -> np.ndarray:
    """``n`` points on the object's surface that no other part covers and some camera faces."""
    records = json.loads((scene_dir / "gt" / "primitives.json").read_text())
    viewpoints = np.stack([cam.center for cam in load_scene(scene_dir).cameras("all")])
    surfaces = uncovered_triangles(scene_dir, viewpoints)
    mine = [t for t, r in zip(surfaces, records, strict=True) if r["labels"]["whole"] == whole]
    tris = np.concatenate(mine)
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(tris.reshape(-1, 3).astype(np.float64)),
        o3d.utility.Vector3iVector(np.arange(3 * len(tris)).reshape(-1, 3)),
    )
    o3d.utility.random.seed(seed)
    return np.asarray(mesh.sample_points_uniformly(n).points)


def test_selection_precision_and_recall_against_the_objects_surfaces(scene_dir) -> None:
    scene = load_scene(scene_dir)
    parts = {name: _surface_points(scene_dir, name, 40, i) for i, name in enumerate(["sofa", "mug", "lamp"])}
    floaters = np.array([[0.0, 0.0, 1.8], [0.5, -1.0, 2.0]])  # mid-air: nobody's Gaussians
    means = np.concatenate([*parts.values(), floaters])
    sofa, mug, lamp = (np.arange(40) + 40 * k for k in range(3))
    answers = {
        "sofa": sofa,  # exactly the sofa
        "mug": np.concatenate([mug, lamp[:20], [120, 121]]),  # the mug, half the lamp, both floaters
        "lamp": lamp[::2],  # half the lamp, nothing else
        "table": np.zeros(0, np.int64),  # nothing
    }
    field = _SelectionField(scene, means, answers)
    result = selection_scores(field, scene)
    objects = result["objects"]
    assert field.queried == sorted(objects) and {"sofa", "mug", "lamp", "table", "wall"} <= set(objects)
    assert objects["sofa"] == {
        "precision": 1.0,
        "recall": 1.0,
        "surface_precision": 1.0,
        "selected": 40,
        "gaussians": 40,
    }
    assert objects["mug"]["precision"] == pytest.approx(40 / 62) and objects["mug"]["recall"] == 1.0
    # The floaters are on no surface: the language part of the mistake is the half lamp alone.
    assert objects["mug"]["surface_precision"] == pytest.approx(40 / 60)
    assert objects["lamp"]["precision"] == 1.0 and objects["lamp"]["recall"] == 0.5
    # No Gaussian lies on the table or the walls: they have no recall and stay out of the means.
    assert objects["table"] == {
        "precision": 0.0,
        "recall": None,
        "surface_precision": 0.0,
        "selected": 0,
        "gaussians": 0,
    }
    assert result["precision"] == pytest.approx((1 + 40 / 62 + 1) / 3)
    assert result["recall"] == pytest.approx((1 + 1 + 0.5) / 3)
    assert result["surface_precision"] == pytest.approx((1 + 40 / 60 + 1) / 3)
    assert result["off_surface"] == pytest.approx(2 / 122)
    assert 0.03 < result["tolerance"] < 0.1  # 1 % of the room's bounds


def test_selection_scores_need_ground_truth_and_language(scene_dir, tmp_path) -> None:
    scene = load_scene(scene_dir)
    assert selection_scores(build_field(scene, TrainConfig(num_gaussians=200)), scene) is None
    bare = load_scene(_copy_scene(scene_dir, tmp_path / "room"))
    shutil.rmtree(tmp_path / "room" / "gt")
    assert selection_scores(_SelectionField(bare, np.zeros((3, 3)), {}), bare) is None
