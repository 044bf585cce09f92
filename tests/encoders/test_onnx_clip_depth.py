"""CLIP and depth on ONNX: tokenizer, exporters against PyTorch, and the export -> preprocess -> train ->
query chain.

The tokenizer tests on a small hand-written vocabulary and the error tests need only the main
install. The tests marked ``export`` (``make test-export``) need the export extra (open_clip,
transformers, onnxscript, and segment-anything for the chain): they build tiny, randomly initialised
models of the real architectures (an OpenCLIP ViT, a Depth Anything and a DPT, a SAM), export them with
the project's exporters and compare onnxruntime with PyTorch on the same inputs.
"""

from __future__ import annotations

import gzip
import json
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch
from conftest import run_models_cli, tiny_sam

from encoders.cache import build_feature_cache, read_feature_cache
from encoders.manifest import ManifestError, read_manifest
from encoders.onnx_clip import ClipTokenizer, OnnxClipEncoder
from encoders.onnx_depth import OnnxDepthEstimator
from encoders.protocols import DepthEstimator, ImageTextEncoder
from encoders.stubs import StubSegmenter

TOL = 1e-4  # max |ONNX - PyTorch|
CLIP_NAME = "langfield-tiny-clip"
CLIP_CFG = {  # the ViT-B-16 layout, shrunk; embed_dim 512 and the real vocabulary so caches are as specified
    "embed_dim": 512,
    "vision_cfg": {"image_size": 32, "layers": 2, "width": 64, "patch_size": 16, "head_width": 32},
    "text_cfg": {"context_length": 77, "vocab_size": 49408, "width": 64, "heads": 2, "layers": 2},
}
DEPTH_HW = (56, 70)  # Depth Anything / DPT input of the tiny models (multiples of 14)
PHRASES = [
    "a photo of a cat",
    "Hello, World!!",
    "it's 42 o'clock; isn't it?",
    "UPPER lower MiXeD",
    "café CRÈME brûlée",
    "“curly quotes” and the ﬁsh ligature",
    "日本語のテキスト",
    "emoji 😀🎉 and #hashtags @user",
    "&amp;amp;amp; &lt;b&gt;",
    "  many   spaces\tand\nnewlines  ",
    "",
    "<end_of_text> typed a!<start_of_text>",
    "'ſ long s",
    "word " * 100,
]


# ---------------------------------------------------------------- tokenizer on a hand-written vocabulary


@pytest.fixture
def small_vocab(tmp_path) -> Path:
    """open_clip's vocabulary format: a header line, then merges in rank order."""
    path = tmp_path / "vocab.txt.gz"
    path.write_bytes(gzip.compress(b"#version: 0.2\nt h\nth e</w>\nc a\nca t</w>\n"))
    return path


def test_tokenizer_ids_sot_eot_and_padding(small_vocab) -> None:
    tok = ClipTokenizer(small_vocab)
    # ids: 256 bytes, 256 bytes + </w>, then the merges (th 512, the</w> 513, ca 514, cat</w> 515), SOT, EOT
    assert (tok.vocab_size, tok.sot_id, tok.eot_id) == (518, 516, 517)
    tokens = tok(["The  CAT", ""])
    assert tokens.shape == (2, 77) and tokens.dtype == np.int64
    assert tokens[0, :4].tolist() == [516, 513, 515, 517] and not tokens[0, 4:].any()
    assert tokens[1, :2].tolist() == [516, 517] and not tokens[1, 2:].any()


def test_tokenizer_cuts_long_phrases_and_ends_with_eot(small_vocab) -> None:
    tokens = ClipTokenizer(small_vocab, context_length=8)(["the " * 20])
    assert tokens[0].tolist() == [516] + [513] * 6 + [517]


def test_tokenizer_refuses_a_bare_string(small_vocab) -> None:
    with pytest.raises(TypeError, match="not a bare string"):
        ClipTokenizer(small_vocab)("the cat")


def test_without_ftfy_only_text_ftfy_leaves_alone_is_tokenized(small_vocab, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "ftfy", None)  # import ftfy now raises ImportError
    tok = ClipTokenizer(small_vocab)
    assert tok(["The cat!\t(42)"])[0, 1:3].tolist() == [513, 515]
    for phrase in ("café", "a & b", "a\x0bb"):
        with pytest.raises(ValueError, match="pip install ftfy"):
            tok([phrase])


def test_vocabulary_file_errors_name_the_file(tmp_path) -> None:
    with pytest.raises(
        FileNotFoundError, match=f"{tmp_path / 'none.gz'}: CLIP BPE vocabulary file not found"
    ):
        ClipTokenizer(tmp_path / "none.gz")
    bad = tmp_path / "bad.gz"
    bad.write_bytes(gzip.compress(b"#version\nt h\nthree symbols here\n"))
    with pytest.raises(ValueError, match=f"{bad}: line 3 is not a merge of two symbols"):
        ClipTokenizer(bad)
    plain = tmp_path / "plain.gz"
    plain.write_text("t h\n")
    with pytest.raises(ValueError, match=f"{plain}: not a gzip-compressed"):
        ClipTokenizer(plain)


def test_runtime_classes_name_the_missing_manifest(tmp_path) -> None:
    with pytest.raises(ManifestError, match=f"{tmp_path / 'manifest.json'}: no model manifest"):
        OnnxClipEncoder(tmp_path)
    with pytest.raises(ManifestError, match=f"{tmp_path / 'manifest.json'}: no model manifest"):
        OnnxDepthEstimator(tmp_path)


# ---------------------------------------------------------------- export fixtures (the export extra)


def _import_or_skip(name: str) -> Any:
    return pytest.importorskip(name, reason=f"needs {name} from the export extra (make test-export)")


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory) -> Path:
    """The folder `langfield preprocess --models` reads: clip/, depth/, sam/ are exported into it."""
    return tmp_path_factory.mktemp("models")


@pytest.fixture(scope="module")
def clip(models_dir, tmp_path_factory) -> tuple[Any, Path, str]:
    """(tiny OpenCLIP model, its export folder, the export command's output), exported by the CLI."""
    open_clip = _import_or_skip("open_clip")
    _import_or_skip("onnxscript")
    configs = tmp_path_factory.mktemp("open_clip_configs")
    (configs / f"{CLIP_NAME}.json").write_text(json.dumps(CLIP_CFG))
    open_clip.add_model_config(configs)
    torch.manual_seed(0)
    model = open_clip.create_model(CLIP_NAME).eval()
    checkpoint = configs / "tiny_clip.pt"
    torch.save(model.state_dict(), checkpoint)
    out = models_dir / "clip"
    code, stdout, stderr = run_models_cli(
        ["export", "clip", "--model", CLIP_NAME, "--checkpoint", str(checkpoint), "--out", str(out)]
    )
    assert code == 0, stderr
    return model, out, stdout


def tiny_depth_anything(metric: bool = False) -> Any:
    """A Depth Anything (DINOv2 backbone, DPT head) of 4 tiny layers; outputs of order 1, not ~0."""
    transformers = _import_or_skip("transformers")
    backbone = transformers.Dinov2Config(
        image_size=DEPTH_HW[0],
        patch_size=14,
        hidden_size=32,
        num_hidden_layers=4,
        num_attention_heads=2,
        intermediate_size=64,
        out_indices=[1, 2, 3, 4],
        reshape_hidden_states=False,
        initializer_range=0.1,
    )
    config = transformers.DepthAnythingConfig(
        backbone_config=backbone,
        reassemble_hidden_size=32,
        neck_hidden_sizes=[8, 16, 32, 32],
        fusion_hidden_size=16,
        head_hidden_size=8,
        initializer_range=0.1,
        depth_estimation_type="metric" if metric else "relative",
    )
    torch.manual_seed(1)
    model = transformers.DepthAnythingForDepthEstimation(config).eval()
    with torch.no_grad():  # a random head ends in a ReLU that zeroes almost everything: lift it
        model.head.conv3.bias.fill_(1.0)
        model.head.conv3.weight.mul_(10.0)
    return model


@pytest.fixture(scope="module")
def depth(models_dir, tmp_path_factory) -> tuple[Any, Path, str]:
    """(tiny Depth Anything, its export folder, the export command's output), exported by the CLI from a
    transformers folder as a user downloads one (config.json, model.safetensors, preprocessor_config.json)."""
    transformers = _import_or_skip("transformers")
    _import_or_skip("onnxscript")
    model = tiny_depth_anything()
    folder = tmp_path_factory.mktemp("hf") / "tiny-depth-anything"
    model.save_pretrained(folder)
    transformers.DPTImageProcessor(
        size={"height": DEPTH_HW[0], "width": DEPTH_HW[1]},
        keep_aspect_ratio=True,
        ensure_multiple_of=14,
        image_mean=[0.485, 0.456, 0.406],
        image_std=[0.229, 0.224, 0.225],
    ).save_pretrained(folder)
    out = models_dir / "depth"
    code, stdout, stderr = run_models_cli(["export", "depth", "--checkpoint", str(folder), "--out", str(out)])
    assert code == 0, stderr
    return model, out, stdout


# ---------------------------------------------------------------- CLIP


@pytest.mark.export
def test_clip_export_summary_and_manifest(clip) -> None:
    open_clip = _import_or_skip("open_clip")
    _, folder, stdout = clip
    assert stdout.splitlines()[-1].startswith(f"exported clip {CLIP_NAME}/tiny_clip.pt in ")
    m = read_manifest(folder, "clip")
    assert {k: p.name for k, p in m["files"].items()} == {
        "image": "image.onnx",
        "text": "text.onnx",
        "vocab": "bpe_simple_vocab_16e6.txt.gz",
    }
    assert (m["input_size"], m["context_length"], m["vocab_size"], m["dim"]) == (32, 77, 49408, 512)
    assert m["mean"] == pytest.approx(open_clip.OPENAI_DATASET_MEAN)
    assert m["std"] == pytest.approx(open_clip.OPENAI_DATASET_STD)
    assert max(m["check"].values()) <= TOL


@pytest.mark.export
def test_tokens_match_open_clip_tokenize(clip) -> None:
    open_clip = _import_or_skip("open_clip")
    _, folder, _ = clip
    ours = OnnxClipEncoder(folder).tokenizer(PHRASES)
    for phrase, row, ref in zip(PHRASES, ours, open_clip.tokenize(PHRASES).numpy(), strict=True):
        np.testing.assert_array_equal(row, ref, err_msg=repr(phrase))
    ref = open_clip.get_tokenizer(CLIP_NAME)(PHRASES).numpy()
    np.testing.assert_array_equal(ours, ref)


@pytest.mark.export
def test_text_tower_matches_pytorch(clip) -> None:
    open_clip = _import_or_skip("open_clip")
    model, folder, _ = clip
    enc = OnnxClipEncoder(folder)
    # The tokenizer handles the empty phrase (above); the encoder refuses it, as every text encoder does.
    phrases = [p for p in PHRASES if p.strip()]
    with torch.no_grad():
        expected = model.encode_text(open_clip.tokenize(phrases), normalize=True).numpy()
    got = enc.encode_text(phrases)
    assert got.dtype == np.float32 and got.shape == (len(phrases), 512)
    assert np.abs(got - expected).max() <= TOL
    assert isinstance(enc, ImageTextEncoder)
    with pytest.raises(ValueError, match="empty phrase"):
        enc.encode_text(["a cat", ""])


@pytest.mark.export
@pytest.mark.parametrize("batch", [1, 7])
def test_image_tower_matches_pytorch_with_clip_normalisation(clip, batch) -> None:
    open_clip = _import_or_skip("open_clip")
    model, folder, _ = clip
    images = np.random.default_rng(batch).random((batch, 32, 32, 3), dtype=np.float32)
    mean, std = torch.tensor(open_clip.OPENAI_DATASET_MEAN), torch.tensor(open_clip.OPENAI_DATASET_STD)
    pixels = ((torch.from_numpy(images) - mean) / std).permute(0, 3, 1, 2).float()
    with torch.no_grad():
        expected = model.encode_image(pixels, normalize=True).numpy()
    got = OnnxClipEncoder(folder).encode_images(images)
    assert got.shape == (batch, 512) and np.abs(got - expected).max() <= TOL


@pytest.mark.export
def test_clip_builds_a_format_md_feature_cache(clip) -> None:
    _, folder, _ = clip
    image = np.zeros((24, 32, 3), np.float32)
    image[:, 16:] = (0.9, 0.2, 0.1)
    cache = build_feature_cache(image, StubSegmenter(blur_sigma=0), OnnxClipEncoder(folder))
    assert cache.features.shape == (cache.num_masks, 512) and cache.segments.shape == (3, 24, 32)


@pytest.mark.export
def test_clip_export_needs_weights_and_names_a_missing_checkpoint(tmp_path) -> None:
    _import_or_skip("open_clip")
    from encoders.export.clip import export_clip

    with pytest.raises(ValueError, match="give the weights of ViT-B-16"):
        export_clip(tmp_path, "ViT-B-16")
    with pytest.raises(FileNotFoundError, match=f"{tmp_path / 'no.pt'}: no such checkpoint file"):
        export_clip(tmp_path, "ViT-B-16", pretrained=tmp_path / "no.pt")


# ---------------------------------------------------------------- depth


@pytest.mark.export
def test_depth_export_summary_and_manifest(depth) -> None:
    _, folder, stdout = depth
    assert stdout.splitlines()[-1].startswith("exported depth tiny-depth-anything in ")
    m = read_manifest(folder, "depth")
    assert m["output"] == "disparity" and m["input_size"] == list(DEPTH_HW)
    assert m["mean"] == pytest.approx([0.485, 0.456, 0.406]) and m["std"] == pytest.approx(
        [0.229, 0.224, 0.225]
    )
    assert m["check"]["max_abs_err"] <= TOL


def _normalised(image: np.ndarray) -> torch.Tensor:
    mean, std = np.array([0.485, 0.456, 0.406], np.float32), np.array([0.229, 0.224, 0.225], np.float32)
    return torch.from_numpy(((image - mean) / std).transpose(2, 0, 1)[None].copy())


@pytest.mark.export
def test_depth_at_the_input_size_matches_pytorch(depth) -> None:
    model, folder, _ = depth
    image = np.random.default_rng(0).random((*DEPTH_HW, 3), dtype=np.float32)
    with torch.no_grad():
        expected = model(pixel_values=_normalised(image)).predicted_depth[0].numpy()
    est = OnnxDepthEstimator(folder)
    got = est.estimate(image)
    assert isinstance(est, DepthEstimator) and est.kind == "disparity"
    assert got.dtype == np.float32 and got.shape == DEPTH_HW
    assert np.abs(expected).max() > 0.1 and np.abs(got - expected).max() <= TOL


@pytest.mark.export
@pytest.mark.parametrize("hw", [(36, 48), (120, 90)])
def test_depth_is_resized_in_and_out(depth, hw) -> None:
    import cv2

    model, folder, _ = depth
    image = np.random.default_rng(1).random((*hw, 3), dtype=np.float32)
    shrink = DEPTH_HW[0] * DEPTH_HW[1] < hw[0] * hw[1]
    net_in = cv2.resize(image, DEPTH_HW[::-1], interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC)
    with torch.no_grad():
        net_out = model(pixel_values=_normalised(net_in)).predicted_depth[0].numpy()
    expected = cv2.resize(net_out, hw[::-1], interpolation=cv2.INTER_LINEAR)
    got = OnnxDepthEstimator(folder).estimate(image)
    assert got.shape == hw and got.dtype == np.float32 and np.isfinite(got).all()
    assert np.abs(got - expected).max() <= TOL


@pytest.mark.export
def test_metric_depth_anything_exports_depth(tmp_path) -> None:
    _import_or_skip("onnxscript")
    from encoders.export.depth import export_depth

    export_depth(
        tmp_path, model=tiny_depth_anything(metric=True), input_size=DEPTH_HW, mean=[0.5] * 3, std=[0.5] * 3
    )
    assert OnnxDepthEstimator(tmp_path).kind == "depth"


@pytest.mark.export
def test_dpt_exports_and_matches_pytorch(tmp_path) -> None:
    transformers = _import_or_skip("transformers")
    _import_or_skip("onnxscript")
    from encoders.export.depth import export_depth

    config = transformers.DPTConfig(
        hidden_size=32,
        num_hidden_layers=4,
        num_attention_heads=2,
        intermediate_size=64,
        image_size=64,
        patch_size=16,
        backbone_out_indices=[0, 1, 2, 3],
        neck_hidden_sizes=[8, 16, 32, 32],
        fusion_hidden_size=16,
        head_in_index=-1,
        initializer_range=0.1,
    )
    torch.manual_seed(3)
    model = transformers.DPTForDepthEstimation(config).eval()
    with torch.no_grad():  # lift the final ReLU's input, as for Depth Anything
        model.head.head[-2].bias.fill_(1.0)
        model.head.head[-2].weight.mul_(10.0)
    export_depth(tmp_path, model=model, input_size=64, mean=[0.5] * 3, std=[0.5] * 3)
    image = np.random.default_rng(2).random((64, 64, 3), dtype=np.float32)
    with torch.no_grad():
        pixels = torch.from_numpy(((image - 0.5) / 0.5).transpose(2, 0, 1)[None].copy())
        expected = model(pixel_values=pixels).predicted_depth[0].numpy()
    est = OnnxDepthEstimator(tmp_path)
    got = est.estimate(image)
    assert est.kind == "disparity" and np.abs(expected).max() > 0.1
    assert np.abs(got - cv2_resize_like(expected, got.shape)).max() <= TOL


def cv2_resize_like(array: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    import cv2

    return array if array.shape == hw else cv2.resize(array, hw[::-1], interpolation=cv2.INTER_LINEAR)


@pytest.mark.export
def test_depth_export_refuses_unknown_model_types_and_missing_folders(tmp_path) -> None:
    from encoders.export.depth import export_depth

    other = torch.nn.Identity()
    other.config = SimpleNamespace(model_type="zoedepth")
    with pytest.raises(ValueError, match="model type 'zoedepth' is not supported"):
        export_depth(tmp_path, model=other, input_size=14, mean=[0.5] * 3, std=[0.5] * 3)
    with pytest.raises(FileNotFoundError, match=f"{tmp_path / 'none' / 'config.json'}: not found"):
        export_depth(tmp_path, checkpoint=tmp_path / "none")


# ---------------------------------------------------------------- export -> preprocess -> train -> query


@pytest.mark.export
def test_export_preprocess_train_query(clip, depth, models_dir, tmp_path) -> None:
    _import_or_skip("segment_anything")
    from encoders.export.sam import export_sam
    from encoders.onnx_sam import OnnxSamSegmenter
    from langfield import TrainConfig, load_scene, train
    from langfield.io.preprocess import load_models, preprocess_scene
    from langfield.synthetic import make_room

    export_sam(models_dir / "sam", model=tiny_sam(64, 2, 2))
    room = make_room(tmp_path / "room", seed=0, width=48, height=36, n_test=2)
    shutil.rmtree(room / "language_features")
    shutil.rmtree(room / "depths")
    meta = json.loads((room / "transforms.json").read_text())
    del meta["depth_kind"]
    (room / "transforms.json").write_text(json.dumps(meta))

    # The command, with SAM's default thresholds: every file docs/format.md lists, at the image size.
    code, stdout, stderr = run_models_cli(["preprocess", str(room), "--models", str(models_dir)])
    assert code == 0, stderr
    assert "s/image" in stdout.splitlines()[-1] and "depth_kind recorded" in stdout.splitlines()[-1]
    scene = load_scene(room)
    assert scene.depth_kind == "disparity"
    for name in scene.names("all"):
        cache = read_feature_cache(*scene.feature_paths(name), dim=512)
        assert cache.segments.shape == (3, 36, 48)
        assert np.load(room / "depths" / f"{name}.npy").shape == (36, 48)
    code, stdout, _ = run_models_cli(["preprocess", str(room), "--models", str(models_dir)])
    assert code == 0 and "every view was already done" in stdout

    # A random SAM's masks rarely pass SAM's quality thresholds; lower them so every level has masks.
    models = load_models(models_dir)
    loose = OnnxSamSegmenter(
        models_dir / "sam",
        points_per_side=4,
        pred_iou_thresh=-1e9,
        stability_score_thresh=-1e9,
        min_mask_area=0,
    )
    report = preprocess_scene(room, loose, models.encoder, overwrite=True, progress=False)
    assert report.num_masks > 0

    field = train(
        load_scene(room),
        TrainConfig(iterations=10, num_gaussians=300, autoencoder_iterations=20),
        progress=False,
    )
    assert field.has_language
    text = torch.from_numpy(models.encoder.encode_text(["a chair", "object"]))
    cam = scene.camera(scene.names("test")[0])
    with torch.no_grad():
        decoded = field.decode(field.render(cam).latents)  # [3, H, W, 512]
    relevance = decoded @ text.T
    assert relevance.shape == (3, 36, 48, 2) and torch.isfinite(relevance).all()
    assert relevance.abs().max() <= 1 + 1e-4
