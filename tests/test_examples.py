"""The scripts in examples/ run (on a tiny field) and say what they promise."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from langfield import TrainConfig, load_scene, train
from langfield.synthetic import make_room

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _module(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def tiny_field(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("examples")
    scene = load_scene(make_room(root / "room", seed=0, width=48, height=36))
    cfg = TrainConfig(iterations=30, num_gaussians=400, autoencoder_iterations=30, language_start=0.0)
    train(scene, cfg, progress=False).save(root / "field")
    return root / "field"


@pytest.mark.slow
def test_language_losses_tabulates_every_stage(tiny_field, tmp_path, capsys) -> None:
    out = tmp_path / "losses.json"
    assert _module("language_losses").main([str(tiny_field), "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["decoder_difference"] == 0.0  # the autoencoder refits exactly as training fitted it
    rows = result["rows"]
    assert rows["oracle"]["mIoU"] > 0.95
    assert any(key.startswith("aggregated latents") for key in rows)
    assert rows["field"] == rows["field, read by vote among the Gaussians' codebook entries"]  # the default
    assert all(0.0 <= r["mIoU"] <= 1.0 for r in rows.values())
    assert "| field |" in capsys.readouterr().out


def test_capture_against_poses_reports_the_errors_of_a_posed_scene(room_factory, tmp_path, capsys) -> None:
    """The built-in room's 8 views captured without their poses (3 on an arc, 5 off it)."""
    out = tmp_path / "errors.json"
    room = room_factory(320, 240)
    argv = [str(room), "--out", str(tmp_path / "captured"), "--json", str(out)]
    assert _module("capture_against_poses").main(argv) == 0
    result = json.loads(out.read_text())
    assert result["posed"] == result["frames"] == 8
    assert result["rotation_deg"]["max"] < 3.0 and result["centre_share"]["max"] < 0.05
    assert "8 of 8 frames posed" in capsys.readouterr().out
    assert load_scene(tmp_path / "captured").names("train") == result["train_views"]


def test_capture_against_poses_adds_uncaptured_test_views(room_factory, tmp_path) -> None:
    """Photos left out of the capture come back as test views, posed in the captured scene's frame."""
    from langfield.capture.alignment import pose_errors

    room = room_factory(320, 240)
    out = tmp_path / "captured"
    argv = [str(room), "--out", str(out), "--views", "train_000,train_001,train_002,test_000,test_001"]
    assert _module("capture_against_poses").main([*argv, "--test-views", "test_002,test_003,test_004"]) == 0
    captured, truth = load_scene(out), load_scene(room)
    assert {"test_002", "test_003", "test_004"} <= set(captured.names("test"))
    names = captured.names("all")
    errors = pose_errors(
        np.array([captured.camera(n).c2w for n in names]), np.array([truth.camera(n).c2w for n in names])
    )
    assert errors["rotation_deg"].max() < 3.0 and errors["centre"].max() < 0.05 * errors["size"]
