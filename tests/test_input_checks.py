"""Bad input is refused before any work is spent: exit 2, one line naming the file or flag, and
nothing already written is lost (the CLI in-process through ``main``; FieldFileError; check_inputs)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import langfield
import langfield.cli.warmup
import langfield.kernels
import langfield.training.setup
import langfield.training.targets
from langfield import LanguageField, TrainConfig, load_scene
from langfield.cli import build_parser, main
from langfield.io.field_meta import FieldFileError
from langfield.synthetic import make_room

W, H = 48, 36


@pytest.fixture(scope="module")
def scene_dir(room_factory) -> Path:
    return room_factory(W, H, n_test=2)


@pytest.fixture(scope="module")
def field_dir(scene_dir, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("field") / "out"
    assert main([str(a) for a in train_argv(scene_dir, out)]) == 0
    return out


@pytest.fixture
def no_work(monkeypatch):
    """Fails the test if training's first piece of work (the autoencoder, the first render) starts."""

    def refuse(*args, **kwargs):
        raise AssertionError("work was started before the input was checked")

    monkeypatch.setattr(langfield.training.setup, "language_targets", refuse)
    monkeypatch.setattr(langfield.training.setup, "build_field", refuse)


def copy_scene(scene_dir: Path, dest: Path) -> Path:
    shutil.copytree(scene_dir, dest)
    return dest


def run_error(argv: list[str], capsys) -> str:
    """Runs the command, asserts exit status 2 and a one-line error; returns that line."""
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    lines = [line for line in err if line.startswith("langfield")]
    assert len(lines) == 1, err
    return lines[0]


def train_argv(scene: Path, out: Path, *extra) -> list:
    return ["train", scene, "--out", out, "--iterations", "2", "--num-gaussians", "200", *extra]


def same_field(a: LanguageField, b: LanguageField) -> bool:
    return torch.equal(a.splats["means"], b.splats["means"])


# ---------------------------------------------------------------- train: the output folder


def test_train_out_that_is_a_file_exits_2_before_work(scene_dir, tmp_path, capsys, no_work) -> None:
    target = tmp_path / "field.txt"
    target.write_text("mine")
    line = run_error(train_argv(scene_dir, target), capsys)
    assert str(target) in line and "is a file" in line
    assert target.read_text() == "mine"


def test_train_out_inside_a_file_exits_2_before_work(scene_dir, tmp_path, capsys, no_work) -> None:
    (tmp_path / "f").write_text("mine")
    line = run_error(train_argv(scene_dir, tmp_path / "f" / "out"), capsys)
    assert "is a file" in line


def test_train_refuses_an_out_that_holds_a_field(scene_dir, field_dir, capsys, no_work) -> None:
    before = (field_dir / "field.json").read_bytes()
    line = run_error(train_argv(scene_dir, field_dir), capsys)
    assert "--force" in line and str(field_dir) in line
    assert (field_dir / "field.json").read_bytes() == before


@pytest.mark.slow
def test_train_force_replaces_the_field(scene_dir, field_dir, tmp_path, capsys) -> None:
    out = tmp_path / "out"
    shutil.copytree(field_dir, out)
    (out / "report.json").write_text("{}")  # the user's own file beside the field stays
    assert main([str(a) for a in train_argv(scene_dir, out, "--force", "--seed", "1")]) == 0
    new = LanguageField.load(out)
    assert new.meta["config"]["seed"] == 1 and (out / "report.json").read_text() == "{}"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging folder left


def test_an_interrupted_save_keeps_the_old_field(scene_dir, field_dir, tmp_path, monkeypatch) -> None:
    out = tmp_path / "out"
    shutil.copytree(field_dir, out)
    old = LanguageField.load(out)
    cfg = TrainConfig(iterations=1, num_gaussians=150)
    field = langfield.train(load_scene(scene_dir), cfg, progress=False)

    def crash(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("langfield.field.write_gaussian_ply", crash)
    with pytest.raises(KeyboardInterrupt):
        field.save(out, overwrite=True)
    assert same_field(LanguageField.load(out), old)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


# ---------------------------------------------------------------- train: flags and scene files


@pytest.mark.parametrize(
    ("flags", "named"),
    [
        (["--language-grid-scale", "0"], "--language-grid-scale"),
        (["--num-gaussians", "0"], "--num-gaussians"),
        (["--iterations", "-3"], "--iterations"),
        (["--lambda-opacity", "nan"], "--lambda-opacity"),
        (["--bounds", "0,0,0,1,1,0"], "--bounds"),
        (["--drop-gamma", "1.5"], "--drop-gamma"),
        (["--lambda-virtual", "-1"], "--lambda-virtual"),
        (["--virtual-baseline", "0"], "--virtual-baseline"),
        (["--lambda-smooth", "inf"], "--lambda-smooth"),
        (["--lambda-spread", "-1"], "--lambda-spread"),
        (["--lambda-crossview", "-1"], "--lambda-crossview"),
        (["--lambda-anisotropy", "-0.1"], "--lambda-anisotropy"),
        (["--lambda-empty", "-1"], "--lambda-empty"),
        (["--opacity-decay", "1.5"], "--opacity-decay"),
        (["--virtual-every", "0"], "--virtual-every"),
        (["--virtual-resolution", "0"], "--virtual-resolution"),
        (["--virtual-resolution", "1.5"], "--virtual-resolution"),
        (["--half-resolution-until", "-0.1"], "--half-resolution-until"),
        (["--language-start", "1.5"], "--language-start"),
        (["--language-balance", "-0.5"], "--language-balance"),
        (["--language-balance", "2"], "--language-balance"),
        (["--lambda-visibility", "nan"], "--lambda-visibility"),
        (["--carve-free-space", "--init", "random"], "--carve-free-space"),
    ],
)
def test_bad_flag_values_exit_2_naming_the_flag(scene_dir, tmp_path, capsys, no_work, flags, named) -> None:
    argv = ["train", scene_dir, "--out", tmp_path / "out", *flags]
    line = run_error(argv, capsys)
    assert named in line
    assert not (tmp_path / "out").exists()


def test_test_view_of_the_wrong_size_exits_2_before_work(
    scene_dir, field_dir, tmp_path, capsys, no_work
) -> None:
    scene = copy_scene(scene_dir, tmp_path / "room")
    image = scene / "images" / "test_001.png"
    cv2.imwrite(str(image), np.zeros((H + 2, W, 4), np.uint8))
    out = tmp_path / "out"
    shutil.copytree(field_dir, out)
    before = (out / "field.safetensors").read_bytes()
    line = run_error(train_argv(scene, out, "--force"), capsys)
    assert str(image) in line and f"{W}x{H + 2}" in line
    assert (out / "field.safetensors").read_bytes() == before


@pytest.mark.parametrize("view", ["train_001", "test_000"])
def test_a_bad_depth_prior_exits_2_before_work(scene_dir, tmp_path, capsys, no_work, view) -> None:
    scene = copy_scene(scene_dir, tmp_path / "room")
    prior = np.load(scene / "depths" / f"{view}.npy")
    prior[3, 4] = np.nan
    np.save(scene / "depths" / f"{view}.npy", prior)
    line = run_error(train_argv(scene, tmp_path / "out"), capsys)
    assert f"{view}.npy" in line and "NaN" in line


def test_a_missing_segment_map_in_one_training_view_exits_2(scene_dir, tmp_path, capsys, no_work) -> None:
    scene = copy_scene(scene_dir, tmp_path / "room")
    (scene / "language_features" / "train_002_s.npy").unlink()
    line = run_error(train_argv(scene, tmp_path / "out"), capsys)
    assert "train_002_s.npy" in line and "missing" in line


def test_a_training_view_without_a_cache_among_views_with_one_exits_2(
    scene_dir, tmp_path, capsys, no_work
) -> None:
    scene = copy_scene(scene_dir, tmp_path / "room")
    for suffix in ("_f.npy", "_s.npy"):
        (scene / "language_features" / f"train_000{suffix}").unlink()
    line = run_error(train_argv(scene, tmp_path / "out"), capsys)
    assert "train_000" in line and "--no-language" in line


def test_a_training_view_without_a_cache_trains_with_no_language(scene_dir, tmp_path, capsys) -> None:
    scene = copy_scene(scene_dir, tmp_path / "room")
    for suffix in ("_f.npy", "_s.npy"):
        (scene / "language_features" / f"train_000{suffix}").unlink()
    assert main([str(a) for a in train_argv(scene, tmp_path / "out", "--no-language")]) == 0


def test_a_damaged_test_view_cache_exits_2_before_work(scene_dir, tmp_path, capsys, no_work) -> None:
    scene = copy_scene(scene_dir, tmp_path / "room")
    (scene / "language_features" / "test_000_f.npy").write_bytes(b"not numpy")
    line = run_error(train_argv(scene, tmp_path / "out"), capsys)
    assert "test_000_f.npy" in line


def test_check_inputs_reads_every_view_once_without_keeping_test_images(scene_dir) -> None:
    scene = load_scene(scene_dir)
    langfield.training.targets.check_inputs(scene, TrainConfig(), progress=False)
    assert set(scene._cache) <= set(scene.names("train"))


# ---------------------------------------------------------------- malformed field folders


def edited_field(field_dir: Path, dest: Path, edit) -> Path:
    shutil.copytree(field_dir, dest)
    meta = json.loads((dest / "field.json").read_text())
    meta = edit(meta)
    (dest / "field.json").write_text(json.dumps(meta))
    return dest


def _set(path: str, value):
    def edit(meta):
        target = meta
        *parents, last = path.split(".")
        for key in parents:
            target = target[key]
        target[last] = value
        return meta

    return edit


@pytest.mark.parametrize(
    ("edit", "key"),
    [
        (lambda meta: [], "top level"),
        (_set("background", "red"), "background"),
        (_set("color_field", {}), "color_field"),
        (_set("color_field.grid.log2_table_size", 20), "color.grid"),
        (_set("color_field.hidden", -1), "color_field.hidden"),
        (_set("language.features", "bogus"), "language.features"),
        (_set("language.codebook", [3, 2]), "language.codebook"),
        (_set("language.codebook", [3, -1, 2]), "language.codebook"),
        (_set("language.codebook", [3, True, 2]), "language.codebook"),
        (_set("language.codebook", "3,2,2"), "language.codebook"),
        (_set("language.decode", "mode"), "language.decode"),
        (_set("language.registered", "yes"), "language.registered"),
        (_set("language.registered", False), "entries"),  # the tensors file still holds them
        (_set("language.decode", "continuous"), "language.decode"),  # the field has a codebook
        (_set("text_encoder", {"kind": "magic"}), "text_encoder.kind"),
        (_set("scene_args", "fast"), "scene_args"),
        (_set("format_version", 99), "format_version"),
    ],
)
def test_a_malformed_field_json_exits_2_naming_the_file_and_key(
    field_dir, tmp_path, capsys, edit, key
) -> None:
    out = edited_field(field_dir, tmp_path / "out", edit)
    line = run_error(["render", out, "--save", tmp_path / "pics"], capsys)
    assert key in line and str(out) in line
    assert not (tmp_path / "pics").exists()


def test_a_changed_table_size_names_the_tensor_and_both_files(field_dir, tmp_path) -> None:
    out = edited_field(field_dir, tmp_path / "out", _set("color_field.grid.log2_table_size", 20))
    with pytest.raises(FieldFileError, match=r"field\.safetensors: tensor 'color\.grid\.table' has shape"):
        LanguageField.load(out)


def test_a_codebook_size_that_disagrees_names_the_tensor(field_dir, tmp_path) -> None:
    def grow(meta):
        meta["language"]["codebook"][1] += 1
        return meta

    out = edited_field(field_dir, tmp_path / "out", grow)
    with pytest.raises(FieldFileError, match=r"field\.safetensors: tensor 'codebook\.1' has shape"):
        LanguageField.load(out)


def test_damaged_tensors_file_is_one_error(field_dir, tmp_path) -> None:
    out = edited_field(field_dir, tmp_path / "out", lambda meta: {**meta, "tensors_sha256": None})
    (out / "field.safetensors").write_bytes(b"\x00" * 16)
    with pytest.raises(FieldFileError, match="field.safetensors"):
        LanguageField.load(out)


def test_not_json_is_one_error(field_dir, tmp_path) -> None:
    shutil.copytree(field_dir, tmp_path / "out")
    (tmp_path / "out" / "field.json").write_bytes(b"\xff\xfe{")
    with pytest.raises(FieldFileError, match="field.json: not valid JSON"):
        LanguageField.load(tmp_path / "out")


# ---------------------------------------------------------------- output paths of the other commands


def test_render_save_that_is_a_file_exits_2(field_dir, tmp_path, capsys) -> None:
    (tmp_path / "pics").write_text("mine")
    line = run_error(["render", field_dir, "--save", tmp_path / "pics"], capsys)
    assert "is a file" in line and (tmp_path / "pics").read_text() == "mine"


def test_query_save_that_is_a_file_exits_2(field_dir, tmp_path, capsys) -> None:
    (tmp_path / "pics").write_text("mine")
    line = run_error(["query", field_dir, "sofa", "--save", tmp_path / "pics"], capsys)
    assert "is a file" in line


def test_eval_json_that_is_a_folder_exits_2_and_leaves_no_tmp(field_dir, tmp_path, capsys) -> None:
    (tmp_path / "report").mkdir()
    line = run_error(["eval", field_dir, "--json", tmp_path / "report"], capsys)
    assert "is a folder" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


# ---------------------------------------------------------------- small defects


def test_empty_phrase_is_refused_by_every_encoder(field_dir) -> None:
    from encoders.onnx_clip import OnnxClipEncoder
    from encoders.stubs import StubImageTextEncoder
    from encoders.text_table import TableTextEncoder

    field = LanguageField.load(field_dir)
    for phrase in ("", "  "):
        with pytest.raises(ValueError, match="empty phrase"):
            field.query(phrase)
        with pytest.raises(ValueError, match="empty phrase"):
            TableTextEncoder(field_dir / "text_embeddings.npz").encode_text([phrase])
        with pytest.raises(ValueError, match="empty phrase"):
            StubImageTextEncoder().encode_text([phrase])
        # The ONNX encoder refuses it before its model runs (no model is needed to see that).
        with pytest.raises(ValueError, match="empty phrase"):
            OnnxClipEncoder.__new__(OnnxClipEncoder).encode_text(["sofa", phrase])


def test_langfield_synthetic_is_reachable_from_the_package(tmp_path) -> None:
    assert langfield.synthetic.make_room is make_room
    with pytest.raises(AttributeError, match="nonsense"):
        _ = langfield.nonsense


def test_renders_of_a_loaded_field_carry_no_graph(field_dir, scene_dir) -> None:
    field = LanguageField.load(field_dir)
    r = field.render(load_scene(scene_dir).camera(0))
    assert not r.rgb.requires_grad and r.rgb.numpy().shape == (H, W, 3)
    assert r.latents is not None and not r.latents.requires_grad


def test_every_flag_has_help() -> None:
    import argparse

    missing = []

    def walk(parser, prefix):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, f"{prefix} {name}")
            elif not action.help and not isinstance(action, argparse._HelpAction):
                missing.append(f"{prefix} {'/'.join(action.option_strings) or action.dest}")

    walk(build_parser(), "langfield")
    assert not missing


class _Child:
    """Stands in for subprocess.run: records the call, and the kernels it leaves uncompiled."""

    def __init__(self, monkeypatch, before: list[str], after: list[str], returncode: int = 0) -> None:
        self.calls: list[tuple[list[str], dict]] = []
        self.left = list(before)
        self.after, self.returncode = after, returncode
        monkeypatch.setattr(langfield.kernels, "_noticed", False)
        monkeypatch.setattr(langfield.kernels, "uncompiled_kernels", lambda: list(self.left))
        monkeypatch.setattr(langfield.kernels.subprocess, "run", self.run)

    def run(self, argv, env, check):
        self.calls.append((argv, env))
        self.left = list(self.after)
        return subprocess.CompletedProcess(argv, self.returncode)


def test_the_first_compilation_is_announced_once_and_done_in_a_child(monkeypatch, capsys) -> None:
    monkeypatch.delenv(langfield.kernels.COMPILE_HERE, raising=False)
    child = _Child(monkeypatch, before=["a", "b"], after=[])
    langfield.kernels.notice_once()
    langfield.kernels.notice_once()
    err = capsys.readouterr().err
    assert err.count("compiling 2 CPU kernels, once") == 1
    assert "in this process" not in err
    # One child, this interpreter, told to compile there (not to start a child of its own).
    [(argv, env)] = child.calls
    assert argv[0] == sys.executable and "warm_up()" in argv[-1]
    assert env[langfield.kernels.COMPILE_HERE] == "child"


def test_nothing_is_compiled_ahead_when_every_kernel_is_cached(monkeypatch, capsys) -> None:
    child = _Child(monkeypatch, before=[], after=[])
    langfield.kernels.notice_once()
    assert child.calls == [] and capsys.readouterr().err == ""


@pytest.mark.parametrize("here, said", [("1", True), ("child", False)])
def test_the_warm_up_and_the_child_compile_in_their_own_process(monkeypatch, capsys, here, said) -> None:
    monkeypatch.setenv(langfield.kernels.COMPILE_HERE, here)
    child = _Child(monkeypatch, before=["a"], after=[])
    langfield.kernels.notice_once()
    assert child.calls == []
    assert ("compiling 1 CPU kernels" in capsys.readouterr().err) == said


@pytest.mark.parametrize("returncode, after", [(1, ["a", "b"]), (0, ["b"])])
def test_a_failed_compile_ahead_falls_back_to_this_process_and_says_so(
    monkeypatch, capsys, returncode, after
) -> None:
    monkeypatch.delenv(langfield.kernels.COMPILE_HERE, raising=False)
    _Child(monkeypatch, before=["a", "b"], after=after, returncode=returncode)
    langfield.kernels.notice_once()
    err = capsys.readouterr().err
    assert f"{len(after)} CPU kernels were not cached by a separate compile (exit {returncode})" in err


def test_every_kernel_is_cached_after_the_warm_up() -> None:
    langfield.cli.warmup.warm_up()
    assert len(langfield.kernels._dispatchers()) >= 9
    assert langfield.kernels.uncompiled_kernels() == []


# ---------------------------------------------------------------- values that parse but cannot be right


def _edited_scene(scene_dir: Path, dest: Path, edit) -> Path:
    """A copy of the scene whose transforms.json ``edit(meta)`` changed."""
    root = copy_scene(scene_dir, dest)
    meta = json.loads((root / "transforms.json").read_text())
    edit(meta)
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


def _scaled(meta) -> None:
    m = np.array(meta["frames"][1]["transform_matrix"])
    m[:3, :3] *= 2.0
    meta["frames"][1]["transform_matrix"] = m.tolist()


def _mirrored(meta) -> None:
    m = np.array(meta["frames"][1]["transform_matrix"])
    m[:3, 1] *= -1.0  # y down: an OpenCV camera written as it is
    meta["frames"][1]["transform_matrix"] = m.tolist()


def _transposed(meta) -> None:
    meta["frames"][1]["transform_matrix"] = np.array(meta["frames"][1]["transform_matrix"]).T.tolist()


@pytest.mark.parametrize(
    ("edit", "said"),
    [
        (_scaled, "rotation scaled by 2"),
        (_mirrored, "reflection"),
        (_transposed, "bottom row"),
        (lambda meta: meta.update(fl_x=1.5, fl_y=1.5), "fx 1.5 pixels"),  # millimetres
        (lambda meta: meta.update(cx=-30.0), "principal point"),
        (lambda meta: meta.update(fl_y=400.0), "differ by more than"),
    ],
    ids=["scaled", "mirrored", "transposed", "focal-in-mm", "principal-point", "aspect"],
)
def test_a_camera_that_is_not_a_camera_exits_2_naming_file_and_frame(
    scene_dir, tmp_path, capsys, no_work, edit, said
) -> None:
    root = _edited_scene(scene_dir, tmp_path / "scene", edit)
    line = run_error(train_argv(root, tmp_path / "out"), capsys)
    assert str(root / "transforms.json") in line and said in line
    assert not (tmp_path / "out").exists()


def test_fewer_training_views_than_a_run_trains_on_exits_2_naming_them(scene_dir, tmp_path, capsys, no_work):
    root = _edited_scene(scene_dir, tmp_path / "scene", lambda meta: meta["frames"][2].update(split="test"))
    line = run_error(train_argv(root, tmp_path / "out"), capsys)
    assert "2 training view(s) (train_000, train_001)" in line and "--n-views 2" in line
    assert load_scene(root, n_views=2).names("train") == ["train_000", "train_001"]  # on purpose


def test_a_view_named_twice_exits_2(scene_dir, tmp_path, capsys, no_work) -> None:
    line = run_error(
        train_argv(scene_dir, tmp_path / "out", "--views", "train_000,train_000,train_001"), capsys
    )
    assert "'train_000'" in line and "a second time" in line
    line = run_error(train_argv(scene_dir, tmp_path / "out", "--views", "0,train_000,train_001"), capsys)
    assert "a second time" in line


def test_a_phrase_table_without_the_canonical_phrases_exits_2_before_training(
    scene_dir, tmp_path, capsys, no_work
) -> None:
    root = copy_scene(scene_dir, tmp_path / "scene")
    with np.load(root / "text_embeddings.npz") as npz:
        table = {k: npz[k] for k in npz.files if k not in ("stuff", "texture")}
    np.savez(root / "text_embeddings.npz", **table)
    line = run_error(train_argv(root, tmp_path / "out"), capsys)
    assert "text_embeddings.npz" in line and "'stuff', 'texture'" in line


def test_an_empty_object_mask_exits_2_before_training(scene_dir, tmp_path, capsys, no_work) -> None:
    root = copy_scene(scene_dir, tmp_path / "scene")
    (root / "masks").mkdir()
    for name in load_scene(root).names("all"):
        mask = np.full((H, W), 255, np.uint8)
        if name == "test_001":
            mask[:] = 0  # parses as a mask, but the masked scores would compare no pixel
        cv2.imwrite(str(root / "masks" / f"{name}.png"), mask)
    line = run_error(train_argv(root, tmp_path / "out"), capsys)
    assert "test_001.png" in line and "empty" in line


def _table_without(scene_dir: Path, dest: Path, *dropped: str) -> Path:
    with np.load(scene_dir / "text_embeddings.npz") as npz:
        table = {k: npz[k] for k in npz.files if k not in dropped}
    np.savez(dest, **table)
    return dest


def test_query_refuses_a_phrase_table_without_the_canonical_phrases(scene_dir, field_dir, tmp_path, capsys):
    table = _table_without(scene_dir, tmp_path / "table.npz", "object")
    argv = ["query", field_dir, "sofa", "--text-encoder", table, "--save", tmp_path / "queries"]
    line = run_error(argv, capsys)
    assert "table.npz" in line and "'object'" in line
    assert not (tmp_path / "queries").exists()


def test_the_viewer_refuses_a_phrase_table_without_the_canonical_phrases_before_it_serves(
    scene_dir, field_dir, tmp_path
) -> None:
    from encoders.text_table import TextTableError
    from langfield.viewer.server import Viewer

    table = _table_without(scene_dir, tmp_path / "table.npz", "things")
    with pytest.raises(TextTableError, match="'things'"):
        Viewer(LanguageField.load(field_dir), None, port=0, text_encoder=table)


def test_a_camera_facing_away_from_the_scene_box_exits_2_with_a_hint(scene_dir, tmp_path, capsys, no_work):
    def opencv_axes(meta) -> None:
        meta["aabb"] = [[-0.3, -0.3, 0.3], [0.3, 0.3, 0.9]]  # a box the room's cameras look at
        m = np.array(meta["frames"][1]["transform_matrix"])
        m[:3, 1:3] *= -1.0  # y down, z forward: still a rotation, looking the other way
        meta["frames"][1]["transform_matrix"] = m.tolist()

    root = _edited_scene(scene_dir, tmp_path / "scene", opencv_axes)
    line = run_error(train_argv(root, tmp_path / "out"), capsys)
    assert "'train_001'" in line and "behind the camera" in line and "world-to-camera" in line
    good = _edited_scene(
        scene_dir, tmp_path / "good", lambda meta: meta.update(aabb=[[-0.3, -0.3, 0.3], [0.3, 0.3, 0.9]])
    )
    assert load_scene(good).names("train")  # the same box is in front of every camera


def test_bounds_behind_every_training_view_exit_2_before_work(scene_dir, tmp_path, capsys, no_work) -> None:
    line = run_error(train_argv(scene_dir, tmp_path / "out", "--bounds", "-0.1,-0.1,100,0.1,0.1,101"), capsys)
    assert "--bounds" in line and "behind training view(s) train_000, train_001, train_002" in line
