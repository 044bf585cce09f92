"""Scene preprocessing (langfield/io/preprocess.py) with the stub models and the graph segmenter: the files
docs/format.md describes, skipping views already done, depth_kind bookkeeping, and model-folder errors."""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import bare_room, run_models_cli

from encoders.cache import read_feature_cache
from encoders.manifest import ManifestError
from encoders.stubs import StubDepthEstimator, StubImageTextEncoder, StubSegmenter
from langfield.cli import models as cli_models
from langfield.io.preprocess import PreprocessError, load_models, preprocess_scene
from langfield.io.scene import load_scene

W, H = 48, 36


@pytest.fixture(scope="module", name="bare_room")
def bare_room_fixture(tmp_path_factory) -> Path:
    """The synthetic room without its language features, depth priors and depth_kind."""
    return bare_room(tmp_path_factory.mktemp("room"), W, H)


@pytest.fixture
def room(bare_room, tmp_path) -> Path:
    return Path(shutil.copytree(bare_room, tmp_path / "room"))


def stubs(kind: str = "disparity") -> tuple[StubSegmenter, StubImageTextEncoder, StubDepthEstimator]:
    return StubSegmenter(), StubImageTextEncoder(image_size=16), StubDepthEstimator(kind)


# ---------------------------------------------------------------- outputs


def test_writes_feature_caches_and_depths_of_every_view(room) -> None:
    report = preprocess_scene(room, *stubs(), progress=False)
    names = load_scene(room).names("all")
    assert report.views == names and report.features_written == names and report.depths_written == names
    for name in names:
        f = np.load(room / "language_features" / f"{name}_f.npy")
        s = np.load(room / "language_features" / f"{name}_s.npy")
        d = np.load(room / "depths" / f"{name}.npy")
        assert f.dtype == np.float32 and f.ndim == 2 and f.shape[1] == 512
        assert s.dtype == np.int32 and s.shape == (3, H, W)
        assert d.dtype == np.float32 and d.shape == (H, W) and np.isfinite(d).all()
        cache = read_feature_cache(
            room / "language_features" / f"{name}_f.npy", s_path_of(room, name), dim=512
        )
        assert cache.num_masks == f.shape[0] > 0
    assert set(report.seconds_per_image) == {"segmenter", "encoder", "depth"}
    assert all(v >= 0 for v in report.seconds_per_image.values())
    assert report.num_masks == sum(np.load(room / "language_features" / f"{n}_f.npy").shape[0] for n in names)


def s_path_of(room: Path, name: str) -> Path:
    return room / "language_features" / f"{name}_s.npy"


def test_the_scene_reads_what_was_written(room) -> None:
    preprocess_scene(room, *stubs(), progress=False)
    scene = load_scene(room)
    name = scene.names("train")[0]
    assert scene.depth_kind == "disparity"
    np.testing.assert_array_equal(scene.depth(name), StubDepthEstimator().estimate(scene.image(name)))
    assert scene.feature_paths(name) is not None


def test_depth_kind_is_added_and_other_keys_kept(room) -> None:
    before = json.loads((room / "transforms.json").read_text())
    report = preprocess_scene(room, None, None, StubDepthEstimator("depth"), progress=False)
    after = json.loads((room / "transforms.json").read_text())
    assert after == {**before, "depth_kind": "depth"}
    assert report.depth_kind_recorded == room / "transforms.json"
    assert list(after)[: len(before)] == list(before)  # key order kept
    assert not list(room.glob(".*tmp"))
    assert load_scene(room).depth_kind == "depth"


def test_depth_kind_already_there_is_left_alone(room) -> None:
    meta = json.loads((room / "transforms.json").read_text())
    (room / "transforms.json").write_text(json.dumps({**meta, "depth_kind": "disparity"}))
    text = (room / "transforms.json").read_text()
    report = preprocess_scene(room, None, None, StubDepthEstimator("disparity"), progress=False)
    assert (room / "transforms.json").read_text() == text and report.depth_kind_recorded is None


def test_depth_kind_that_disagrees_is_an_error_naming_the_file(room) -> None:
    meta = json.loads((room / "transforms.json").read_text())
    (room / "transforms.json").write_text(json.dumps({**meta, "depth_kind": "depth"}))
    with pytest.raises(PreprocessError, match=r"transforms\.json: depth_kind is 'depth'.*'disparity'"):
        preprocess_scene(room, None, None, StubDepthEstimator("disparity"), progress=False)
    assert not (room / "depths").exists()


def test_depth_model_of_another_kind_than_existing_maps_is_refused(room) -> None:
    preprocess_scene(room, None, None, StubDepthEstimator("disparity"), progress=False)
    meta = json.loads((room / "transforms.json").read_text())
    del meta["depth_kind"]  # maps without a kind are read as disparity
    (room / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(PreprocessError, match="depths: holds maps without a depth_kind"):
        preprocess_scene(room, None, None, StubDepthEstimator("depth"), progress=False)
    report = preprocess_scene(room, None, None, StubDepthEstimator("depth"), overwrite=True, progress=False)
    assert len(report.depths_written) == len(report.views) and load_scene(room).depth_kind == "depth"


# ---------------------------------------------------------------- skipping views already done


def test_second_run_skips_every_view(room) -> None:
    preprocess_scene(room, *stubs(), progress=False)
    stamp = {p: p.stat().st_mtime_ns for p in room.rglob("*.npy")}
    report = preprocess_scene(room, *stubs(), progress=False)
    assert report.features_written == [] and report.depths_written == [] and report.seconds_per_image == {}
    assert {p: p.stat().st_mtime_ns for p in room.rglob("*.npy")} == stamp
    assert "already done" in report.summary()


def test_only_missing_or_broken_views_are_redone(room) -> None:
    preprocess_scene(room, *stubs(), progress=False)
    names = load_scene(room).names("all")
    (room / "language_features" / f"{names[0]}_s.npy").unlink()
    np.save(room / "depths" / f"{names[1]}.npy", np.full((H, W), np.nan, np.float32))
    np.save(room / "language_features" / f"{names[2]}_f.npy", np.ones((3, 512), np.float32))  # not unit
    report = preprocess_scene(room, *stubs(), progress=False)
    assert report.features_written == [names[0], names[2]]
    assert report.depths_written == [names[1]]
    assert set(report.seconds_per_image) == {"segmenter", "encoder", "depth"}


def test_cache_of_another_dimension_is_redone(room) -> None:
    preprocess_scene(room, StubSegmenter(), StubImageTextEncoder(dim=8, image_size=16), progress=False)
    report = preprocess_scene(room, StubSegmenter(), StubImageTextEncoder(image_size=16), progress=False)
    assert len(report.features_written) == len(report.views)


def test_overwrite_redoes_every_view(room) -> None:
    preprocess_scene(room, *stubs(), progress=False)
    report = preprocess_scene(room, *stubs(), overwrite=True, progress=False)
    assert len(report.features_written) == len(report.depths_written) == len(report.views)


def test_features_only_and_depth_only(room) -> None:
    seg, enc, _ = stubs()
    report = preprocess_scene(room, seg, enc, progress=False)
    assert "depth" not in report.seconds_per_image and not (room / "depths").exists()
    assert "depth_kind" not in json.loads((room / "transforms.json").read_text())
    report = preprocess_scene(room, None, None, StubDepthEstimator(), progress=False)
    assert set(report.seconds_per_image) == {"depth"}


def test_half_a_model_pair_or_no_model_is_an_error(room) -> None:
    with pytest.raises(PreprocessError, match="both a segmenter and an encoder"):
        preprocess_scene(room, StubSegmenter(), None, progress=False)
    with pytest.raises(PreprocessError, match="no model given"):
        preprocess_scene(room, None, None, progress=False)


def test_depth_of_the_wrong_shape_is_an_error_naming_the_model(room) -> None:
    class Wrong:
        kind = "disparity"

        def estimate(self, image):
            return np.zeros((4, 4), np.float32)

    with pytest.raises(PreprocessError, match=r"Wrong\.estimate returned float32 \(4, 4\)"):
        preprocess_scene(room, None, None, Wrong(), progress=False)


def test_graph_segmenter(room) -> None:
    classical = pytest.importorskip("encoders.classical")
    try:
        segmenter = classical.GraphSegmenter()
    except ImportError as exc:
        pytest.skip(str(exc))
    report = preprocess_scene(room, segmenter, StubImageTextEncoder(image_size=16), progress=False)
    name = report.views[0]
    cache = read_feature_cache(room / "language_features" / f"{name}_f.npy", s_path_of(room, name))
    assert cache.segments.shape == (3, H, W) and (cache.segments >= 0).all()  # partitions cover the image
    assert report.seconds_per_image["segmenter"] > 0


# ---------------------------------------------------------------- model folders


def test_missing_models_folder(tmp_path) -> None:
    with pytest.raises(PreprocessError, match=f"{tmp_path / 'nope'}: models folder not found"):
        load_models(tmp_path / "nope")


def test_empty_models_folder(tmp_path) -> None:
    with pytest.raises(PreprocessError, match="no models in .*clip/, sam/ and depth/"):
        load_models(tmp_path)


def test_clip_without_a_segmenter(tmp_path) -> None:
    (tmp_path / "clip").mkdir()
    with pytest.raises(PreprocessError, match="found clip but no sam/ folder .*--segmenter graph"):
        load_models(tmp_path)


def test_sam_and_graph_contradict(tmp_path) -> None:
    with pytest.raises(PreprocessError, match="contradict"):
        load_models(clip=tmp_path, sam=tmp_path, segmenter="graph")


def test_bad_model_folder_error_names_the_manifest(tmp_path) -> None:
    (tmp_path / "depth").mkdir()
    with pytest.raises(ManifestError, match=f"{tmp_path / 'depth' / 'manifest.json'}: no model manifest"):
        load_models(tmp_path)


def test_manifest_of_another_kind_names_the_file(tmp_path) -> None:
    from encoders.manifest import write_manifest

    (tmp_path / "m.onnx").write_bytes(b"")
    write_manifest(tmp_path, "clip", "x", {"model": "m.onnx"})
    with pytest.raises(ManifestError, match=r"manifest\.json: holds a 'clip' model, expected 'depth'"):
        load_models(depth=tmp_path)


def test_cli_bad_model_folder_is_one_line_naming_the_file(room, tmp_path) -> None:
    code, out, err = run_models_cli(["preprocess", str(room), "--depth", str(tmp_path)])
    assert code == 2
    assert err.strip() == (
        f"langfield preprocess: error: {tmp_path / 'manifest.json'}: no model manifest "
        f"(export the model with `langfield export depth ... --out {tmp_path}`)"
    )


def test_cli_parses_every_flag() -> None:
    parser = argparse.ArgumentParser(prog="langfield")
    cli_models.add_parsers(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(
        ["preprocess", "s", "--models", "m", "--clip", "c", "--sam", "a", "--depth", "d", "--overwrite"]
    )
    assert (args.scenes, args.models, args.clip, args.sam, args.depth) == (["s"], "m", "c", "a", "d")
    assert args.address is None
    assert args.overwrite and args.segmenter == "sam" and args.func is cli_models.cmd_preprocess
    args = parser.parse_args(
        ["export", "depth", "--checkpoint", "f", "--input-size", "518", "686", "--out", "o"]
    )
    assert args.kind == "depth" and args.input_size == [518, 686] and args.func is cli_models.cmd_export
    with contextlib.redirect_stderr(io.StringIO()), pytest.raises(SystemExit):
        parser.parse_args(["export", "depth", "--checkpoint", "f", "--model", "id", "--out", "o"])
