"""The ONNX image refiner: manifest errors (main install) and export -> refine against PyTorch (export extra).

The error tests need only the main install: they write manifests by hand beside an empty or garbage
"ONNX" file. The tests marked ``export`` (``make test-export``) export a tiny random conv net with
:func:`encoders.export.refiner.export_refiner` (with and without a confidence channel, at a fixed and at
any size), load it with :class:`encoders.onnx_refiner.OnnxImageRefiner` and compare with PyTorch.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from encoders.manifest import ManifestError, write_manifest
from encoders.onnx_refiner import OnnxImageRefiner

TOL = 1e-4  # max |ONNX - PyTorch|
MEAN, STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
FIXED = (24, 40)  # the fixed-size model's input (H, W)


def _manifest(folder: Path, **override) -> Path:
    """A well-formed refiner manifest beside a placeholder model.onnx, with fields overridden."""
    (folder / "model.onnx").write_bytes(b"not an onnx file")
    fields = {"input_size": [32, 48], "mean": [0.5] * 3, "std": [0.5] * 3, "confidence": False, **override}
    return write_manifest(folder, "refiner", "test", {"model": "model.onnx"}, **fields)


# ---------------------------------------------------------------- manifest errors (main install)


def test_missing_folder_and_missing_manifest_are_named(tmp_path) -> None:
    with pytest.raises(ManifestError, match=f"{tmp_path / 'none'}: no such refiner model folder"):
        OnnxImageRefiner(tmp_path / "none")
    with pytest.raises(ManifestError, match=f"{tmp_path / 'manifest.json'}: no model manifest"):
        OnnxImageRefiner(tmp_path)


def test_a_manifest_of_another_kind_is_refused(tmp_path) -> None:
    (tmp_path / "depth.onnx").write_bytes(b"")
    write_manifest(tmp_path, "depth", "x", {"model": "depth.onnx"}, input_size=[14, 14], output="depth")
    with pytest.raises(
        ManifestError, match=f"{tmp_path / 'manifest.json'}: holds a 'depth' model, expected 'refiner'"
    ):
        OnnxImageRefiner(tmp_path)


def test_a_missing_or_unreadable_onnx_file_is_named(tmp_path) -> None:
    _manifest(tmp_path)
    with pytest.raises(ValueError, match=f"{tmp_path / 'model.onnx'}: cannot load ONNX model"):
        OnnxImageRefiner(tmp_path)
    (tmp_path / "model.onnx").unlink()
    with pytest.raises(
        ManifestError, match=f"file {tmp_path / 'model.onnx'} named for 'model' does not exist"
    ):
        OnnxImageRefiner(tmp_path)


def test_malformed_manifests_are_named(tmp_path) -> None:
    where = tmp_path / "manifest.json"
    cases = [
        ({"input_size": [32]}, "'input_size' must be \\[H, W\\]"),
        ({"input_size": [32, 0]}, "'input_size' must be \\[H, W\\]"),
        ({"input_size": "any"}, "'input_size' must be \\[H, W\\]"),
        ({"confidence": "yes"}, "'confidence' must be true or false"),
        ({"confidence": None}, "'confidence' must be true or false"),
        ({"mean": [0.5, 0.5]}, "'mean' must be three numbers"),
        ({"std": [0.5, 0.0, 0.5]}, "'std' must be positive"),
    ]
    for override, message in cases:
        _manifest(tmp_path, **override)
        with pytest.raises(ManifestError, match=f"{where}: {message}"):
            OnnxImageRefiner(tmp_path)
    _manifest(tmp_path)
    data = json.loads(where.read_text())
    del data["input_size"]
    where.write_text(json.dumps(data))
    with pytest.raises(ManifestError, match=f"{where}: no 'input_size'"):
        OnnxImageRefiner(tmp_path)
    where.write_text("{not json")
    with pytest.raises(ManifestError, match=f"{where}: not valid JSON"):
        OnnxImageRefiner(tmp_path)


# ---------------------------------------------------------------- export -> refine (the export extra)


class TinyRefiner(torch.nn.Module):
    """Conv2d(3, 3 | 4, 3): a sigmoid on the RGB channels, the fourth channel left as logits."""

    def __init__(self, confidence: bool, seed: int = 0) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.conv = torch.nn.Conv2d(3, 4 if confidence else 3, 3, padding=1)
        with torch.no_grad():  # logits of order 1-3, so that the sigmoid is not flat
            self.conv.weight.mul_(3.0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.conv(x)
        return torch.cat([torch.sigmoid(y[:, :3]), y[:, 3:]], dim=1)


def _expected(module: torch.nn.Module, image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """What refine should return at the network's size: (RGB [H, W, 3], confidence [H, W] or None)."""
    mean, std = np.asarray(MEAN, np.float32), np.asarray(STD, np.float32)
    x = torch.from_numpy(((image - mean) / std).transpose(2, 0, 1)[None].copy())
    with torch.no_grad():
        y = module(x)[0].numpy()
    rgb = np.clip(y[:3].transpose(1, 2, 0) * std + mean, 0.0, 1.0)
    conf = torch.sigmoid(torch.from_numpy(y[3])).numpy() if y.shape[0] == 4 else None
    return rgb, conf


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> dict[tuple[bool, bool], tuple[torch.nn.Module, Path]]:
    """(confidence, fixed size) -> (module, folder), exported once for the module's tests."""
    pytest.importorskip("onnxscript", reason="needs onnxscript from the export extra (make test-export)")
    from encoders.export.refiner import export_refiner

    out = {}
    for confidence in (False, True):
        for fixed in (False, True):
            module = TinyRefiner(confidence, seed=int(confidence) + 2 * int(fixed))
            folder = tmp_path_factory.mktemp(f"refiner_{int(confidence)}{int(fixed)}")
            export_refiner(
                module, folder, size=FIXED if fixed else None, mean=MEAN, std=STD, confidence=confidence
            )
            out[confidence, fixed] = module, folder
    return out


@pytest.mark.export
@pytest.mark.parametrize("confidence", [False, True])
@pytest.mark.parametrize("fixed", [False, True])
def test_refine_shapes_and_ranges(exported, confidence, fixed) -> None:
    module, folder = exported[confidence, fixed]
    refiner = OnnxImageRefiner(folder)
    assert refiner.confidence is confidence and refiner.input_size == (FIXED if fixed else None)
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["kind"] == "refiner" and manifest["check"]["max_abs_err"] <= TOL
    image = np.random.default_rng(0).random((37, 53, 3), dtype=np.float32)
    rgb, conf = refiner.refine(image)
    assert rgb.shape == (37, 53, 3) and conf.shape == (37, 53)
    assert rgb.dtype == np.float32 and conf.dtype == np.float32
    assert 0.0 <= rgb.min() and rgb.max() <= 1.0 and 0.0 <= conf.min() and conf.max() <= 1.0
    if not confidence:
        assert (conf == 1.0).all()
    else:
        assert conf.std() > 0.01  # a real confidence map, not a constant
    if fixed:  # the network ran at its own size, on the image resized with area averaging
        import cv2

        net_in = cv2.resize(image, FIXED[::-1], interpolation=cv2.INTER_AREA)
        want_rgb, want_conf = _expected(module, net_in)
        want_rgb = cv2.resize(want_rgb, (53, 37), interpolation=cv2.INTER_LINEAR)
        assert np.abs(rgb - want_rgb).max() <= TOL
        if confidence:
            want_conf = cv2.resize(want_conf, (53, 37), interpolation=cv2.INTER_LINEAR)
            assert np.abs(conf - want_conf).max() <= TOL


@pytest.mark.export
@pytest.mark.parametrize("confidence", [False, True])
def test_dynamic_size_matches_pytorch_without_resizing(exported, confidence) -> None:
    module, folder = exported[confidence, False]
    image = np.random.default_rng(1).random((32, 48, 3), dtype=np.float32)
    rgb, conf = OnnxImageRefiner(folder).refine(image)
    want_rgb, want_conf = _expected(module, image)
    assert np.abs(rgb - want_rgb).max() <= TOL
    if confidence:  # the fourth channel's sigmoid
        assert np.abs(conf - want_conf).max() <= TOL and want_conf.min() < 0.2 and want_conf.max() > 0.8
    else:
        assert (conf == 1.0).all()


@pytest.mark.export
def test_refine_checks_its_input(exported) -> None:
    _, folder = exported[True, False]
    refiner = OnnxImageRefiner(folder)
    where = f"OnnxImageRefiner\\({folder}\\).refine"
    with pytest.raises(ValueError, match=f"{where}: image must have shape \\[H, W, 3\\]"):
        refiner.refine(np.zeros((8, 8), np.float32))
    with pytest.raises(ValueError, match=f"{where}: image has NaN or inf"):
        refiner.refine(np.full((8, 8, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match=f"{where}: float image must lie in \\[0, 1\\]"):
        refiner.refine(np.full((8, 8, 3), 1.5, np.float32))


@pytest.mark.export
def test_a_manifest_that_disagrees_with_the_model_is_named(exported, tmp_path) -> None:
    import shutil

    _, folder = exported[False, False]
    shutil.copy(folder / "model.onnx", tmp_path / "model.onnx")
    manifest = json.loads((folder / "manifest.json").read_text())
    for change, message in [
        ({"confidence": True}, "expected an output of shape \\[batch, 4, H, W\\]"),
        ({"input_size": [20, 30]}, None),  # a dynamic model also runs at a fixed size
    ]:
        (tmp_path / "manifest.json").write_text(json.dumps({**manifest, **change}))
        if message is None:
            assert OnnxImageRefiner(tmp_path).refine(np.zeros((9, 11, 3), np.float32))[0].shape == (9, 11, 3)
        else:
            with pytest.raises(ValueError, match=f"{tmp_path / 'model.onnx'}: {message}"):
                OnnxImageRefiner(tmp_path)
    _, fixed = exported[False, True]
    shutil.copy(fixed / "model.onnx", tmp_path / "model.onnx")
    (tmp_path / "manifest.json").write_text(json.dumps({**manifest, "input_size": None}))
    with pytest.raises(ValueError, match="with dynamic H and W"):
        OnnxImageRefiner(tmp_path)


@pytest.mark.export
def test_export_refiner_refuses_bad_arguments(tmp_path) -> None:
    from encoders.export.refiner import export_refiner

    with pytest.raises(ValueError, match="must return \\[B, 4, H, W\\]"):
        export_refiner(TinyRefiner(False), tmp_path, confidence=True)
    with pytest.raises(ValueError, match="size must be None, H or \\(H, W\\)"):
        export_refiner(TinyRefiner(False), tmp_path, size=(0, 8), confidence=False)
    with pytest.raises(ValueError, match="std positive"):
        export_refiner(TinyRefiner(False), tmp_path, std=(1, 0, 1), confidence=False)
    assert not (tmp_path / "manifest.json").exists()
