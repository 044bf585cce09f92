"""`langfield capture`: a video and photo folders of the built-in room, whose true poses are known,
go through frames -> COLMAP -> scene folder; bad input is refused before any work."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from langfield.camera import Camera
from langfield.capture import CaptureError, CaptureOptions, capture
from langfield.capture.alignment import pose_errors
from langfield.cli import main
from langfield.io.scene import load_scene
from langfield.synthetic import render_room
from langfield.viewer.video import write_video

TARGET = np.array([0.0, 0.8, 0.55])
ROOM_SIZE = 4.0  # the built-in room is 4 m x 4 m (scale 1)
FPS = 10.0


def arc_cameras(
    count: int, span: float = 80.0, width: int = 320, height: int = 240, seed: int = 0
) -> list[Camera]:
    """A hand-held walk along an arc around the room's centre: the height and the aim wander a little."""
    rng = np.random.default_rng(seed)
    cams = []
    for i, angle in enumerate(np.linspace(-span / 2, span / 2, count)):
        a = np.radians(angle)
        eye = [TARGET[0] + 2.7 * np.sin(a), TARGET[1] - 2.7 * np.cos(a), 1.5 + 0.2 * np.sin(3 * a)]
        target = TARGET + rng.normal(0.0, 0.05, 3)
        cams.append(Camera.look_at(eye, target, width=width, height=height, fov_x_deg=60, name=f"{i:03d}"))
    return cams


def write_photos(folder: Path, cameras: list[Camera], prefix: str = "photo", **room) -> Path:
    """PNG photos of the room (``render_room``'s seed, layout) named ``<prefix>_<camera name>``."""
    folder.mkdir(parents=True, exist_ok=True)
    for cam, rgb in zip(cameras, render_room(cameras, **room), strict=True):
        cv2.imwrite(str(folder / f"{prefix}_{cam.name}.png"), rgb[..., ::-1])
    return folder


@pytest.fixture(scope="module")
def room_video(tmp_path_factory):
    """A 24-frame 480 x 360 video of the room at 10 frames per second, its cameras, and its capture.

    Motion JPEG: OpenCV's MPEG-4 Part 2 blurs the room's fine periodic textures into 1.2 degrees of
    rotation error; the room's own limit (its repeated textures and flat walls) is about 0.75 degrees
    at 320 x 240 to 640 x 480 alike, where LLFF fern's 20 photos reach 0.26 (docs/capture.md)."""
    root = tmp_path_factory.mktemp("capture_video")
    cams = arc_cameras(24, width=480, height=360)
    video = root / "walk.avi"
    write_video(video, iter(render_room(cams)), FPS)
    report = capture(video, root / "scene", CaptureOptions(frames=24))
    return cams, root / "scene", report


def test_a_video_of_the_room_is_posed_to_within_a_degree_and_a_percent(room_video) -> None:
    cams, scene_dir, report = room_video
    scene = load_scene(scene_dir)
    names = scene.names("all")
    assert len(names) >= 0.9 * len(cams)
    # Frames are named by their time stamp: frame i of a 10 fps video is i / 10 seconds in.
    truth = {f"t{i / FPS:07.3f}s": cam for i, cam in enumerate(cams)}
    errors = pose_errors(
        np.array([scene.camera(n).c2w for n in names]), np.array([truth[n].c2w for n in names])
    )
    assert errors["rotation_deg"].max() < 1.0
    assert errors["centre"].max() < 0.01 * ROOM_SIZE
    assert abs(scene.camera(names[0]).fx - cams[0].fx) < 0.03 * cams[0].fx
    assert report["scene"]["train"] == scene.names("train") and len(scene.names("train")) == 3
    assert sorted(report["scene"]["test"]) == sorted(scene.names("test"))


def test_the_captured_scene_has_what_train_and_init_points_read(room_video) -> None:
    _, scene_dir, report = room_video
    meta = json.loads((scene_dir / "transforms.json").read_text())
    assert meta["camera_model"] == "OPENCV" and meta["ply_file_path"] == "sparse_pc.ply"
    assert all(0 < f["near"] < f["far"] for f in meta["frames"])
    scene = load_scene(scene_dir)
    assert scene.points_path == scene_dir / "sparse_pc.ply"
    # nerfstudio's normalisation: cameras centred, their mean up along +z, the largest coordinate 1.
    c2w = np.array([scene.camera(n).c2w for n in scene.names("all")])
    np.testing.assert_allclose(c2w[:, :3, 3].mean(axis=0), 0.0, atol=1e-9)
    assert abs(np.abs(c2w[:, :3, 3]).max() - 1.0) < 1e-9
    up = c2w[:, :3, 1].mean(axis=0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0.0, 0.0, 1.0], atol=1e-9)
    saved = json.loads((scene_dir / "capture.json").read_text())
    assert saved["models"][0]["points"] == report["models"][0]["points"] > 100


@pytest.mark.slow
def test_training_runs_on_the_three_views_capture_chose(room_video) -> None:
    from langfield.training.config import TrainConfig
    from langfield.training.loop import train

    _, scene_dir, _ = room_video
    scene = load_scene(scene_dir, resolution=4)
    field = train(scene, TrainConfig(iterations=20, init="points", densify=False), progress=False)
    assert field.meta["init"]["used"] == "points"
    assert field.meta["train_views"] == scene.names("train")


def test_photos_of_two_unrelated_places_give_two_models(tmp_path) -> None:
    photos = tmp_path / "photos"
    write_photos(photos, arc_cameras(5, span=30.0), seed=0, prefix="a")
    write_photos(photos, arc_cameras(5, span=30.0, seed=1), seed=7, layout=2, prefix="b")
    report = capture(photos, tmp_path / "scene", CaptureOptions(all_models=True, train_views=2))
    groups = [sorted(m["frames"]) for m in report["models"]]
    assert len(groups) == 2
    assert sorted(groups) == [[f"a_{i:03d}" for i in range(5)], [f"b_{i:03d}" for i in range(5)]]
    other = tmp_path / "scene" / report["models"][1]["scene"]
    assert (
        sorted(load_scene(other, n_views=2).names("all"))
        == groups[1]
        != sorted(load_scene(tmp_path / "scene", n_views=2).names("all"))
    )


def test_fewer_than_three_posed_frames_is_one_line_and_nothing_written(tmp_path, capsys) -> None:
    photos = tmp_path / "noise"
    photos.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):  # unrelated noise: no pair verifies, no model
        cv2.imwrite(str(photos / f"n{i}.png"), rng.integers(0, 255, (120, 160, 3), dtype=np.uint8))
    assert main(["capture", str(photos), "--out", str(tmp_path / "scene")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "frames could be posed together" in err[0]
    assert not (tmp_path / "scene").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["noise"]  # no staging folder left behind
    with pytest.raises(CaptureError):
        capture(photos, tmp_path / "scene")


@pytest.fixture
def three_photos(tmp_path) -> Path:
    return write_photos(tmp_path / "photos", arc_cameras(3, width=64, height=48))


def _bad_video(tmp_path: Path) -> Path:
    path = tmp_path / "clip.mp4"
    path.write_bytes(b"not a video at all")
    return path


def _damaged_photo(tmp_path: Path) -> Path:
    folder = write_photos(tmp_path / "damaged", arc_cameras(3, width=64, height=48))
    first = sorted(folder.iterdir())[0]
    first.write_bytes(first.read_bytes()[:40])
    return folder


def _two_photos(tmp_path: Path) -> Path:
    return write_photos(tmp_path / "two", arc_cameras(2, width=64, height=48))


def _mixed_sizes(tmp_path: Path) -> Path:
    folder = write_photos(tmp_path / "mixed", arc_cameras(3, width=64, height=48))
    write_photos(folder, arc_cameras(1, width=80, height=48), prefix="wide")
    return folder


@pytest.mark.parametrize(
    ("make_input", "flags", "expected"),
    [
        (lambda tmp, photos: tmp / "missing", [], "no such folder"),
        (lambda tmp, photos: _two_photos(tmp), [], "at least 3"),
        (lambda tmp, photos: _damaged_photo(tmp), [], "cannot read this image"),
        (lambda tmp, photos: _bad_video(tmp), [], "cannot decode this video"),
        (lambda tmp, photos: photos, ["--frames", "2"], "--frames"),
        (lambda tmp, photos: photos, ["--train-views", "0"], "--train-views"),
        (lambda tmp, photos: photos, ["--max-size", "10"], "--max-size"),
        (lambda tmp, photos: photos, ["--views", "photo_000,nope"], "no photo named nope"),
        (lambda tmp, photos: photos, ["--views", "photo_000,photo_000"], "more than once"),
        (lambda tmp, photos: _mixed_sizes(tmp), ["--camera", "single"], "--camera per-image"),
    ],
)
def test_bad_input_is_refused_in_one_line_before_any_work(
    tmp_path, three_photos, capsys, make_input, flags, expected
) -> None:
    source = make_input(tmp_path, three_photos)
    out = tmp_path / "scene"
    assert main(["capture", str(source), "--out", str(out), *flags]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0], err
    assert not out.exists()
    assert not any(p.name.startswith(".scene") for p in tmp_path.iterdir())


def test_an_existing_scene_is_kept_unless_forced(tmp_path, three_photos, capsys, monkeypatch) -> None:
    out = tmp_path / "scene"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    assert main(["capture", str(three_photos), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    (tmp_path / "file").write_text("x")
    assert main(["capture", str(three_photos), "--out", str(tmp_path / "file" / "scene")]) == 2
    # A capture that fails midway, forced or not, leaves the old folder as it was.
    import langfield.capture as capture_module

    def fail(*args, **kwargs):
        raise CaptureError("stopped")

    monkeypatch.setattr(capture_module, "solve_poses", fail)
    assert main(["capture", str(three_photos), "--out", str(out), "--force"]) == 2
    assert (out / "mine.txt").read_text() == "keep"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "photos", "scene"]
    # The input itself, or a folder holding it, is never the output, forced or not.
    for target in (three_photos, tmp_path):
        assert main(["capture", str(three_photos), "--out", str(target), "--force"]) == 2
        assert "holds the input" in capsys.readouterr().err
    assert len(list(three_photos.iterdir())) == 3


@pytest.mark.slow
def test_the_readme_commands_run_on_a_photo_folder(tmp_path, capsys) -> None:
    """README, "Your own photos": capture, then train (preprocess needs real models: left out)."""
    photos = write_photos(tmp_path / "my_photos", arc_cameras(8, width=200, height=150))
    assert main(["capture", str(photos), "--out", str(tmp_path / "my_scene")]) == 0
    printed = capsys.readouterr().out
    assert "poses: 8 of 8 frames" in printed and "5 test views" in printed
    argv = ["train", str(tmp_path / "my_scene"), "--out", str(tmp_path / "my_field"), "--iterations", "20"]
    assert main(argv) == 0
    assert (tmp_path / "my_field" / "field.safetensors").is_file()
    shutil.rmtree(tmp_path / "my_field")


@pytest.mark.slow
def test_a_capture_repeats_exactly(tmp_path) -> None:
    """COLMAP runs on one thread: its results depend on the threads' order otherwise."""
    photos = write_photos(tmp_path / "photos", arc_cameras(8, width=200, height=150))
    poses = []
    for out in ("a", "b"):
        capture(photos, tmp_path / out, CaptureOptions())
        scene = load_scene(tmp_path / out)
        poses.append(np.array([scene.camera(n).c2w for n in scene.names("all")]))
    assert len(poses[0]) == 8
    np.testing.assert_array_equal(poses[0], poses[1])


def test_three_photos_with_an_exif_focal_length_are_posed(tmp_path) -> None:
    """Three photos are the least a scene needs; their EXIF 35 mm focal length (30 mm: the room's 60
    degree lens at 320 x 240 is 277 pixels) starts COLMAP's focal length (without it: 3.3 degrees)."""
    from PIL import Image

    cams = arc_cameras(3, span=15.0)
    photos = tmp_path / "phone"
    photos.mkdir()
    for cam, rgb in zip(cams, render_room(cams), strict=True):
        image = Image.fromarray(rgb)
        exif = image.getexif()
        exif.get_ifd(0x8769)[0xA405] = 30  # FocalLengthIn35mmFilm
        image.save(photos / f"IMG_{cam.name}.jpg", quality=95, exif=exif)
    report = capture(photos, tmp_path / "scene", CaptureOptions())
    assert report["focal_priors_px"] == {f"IMG_{c.name}": 277.35 for c in cams}
    scene = load_scene(tmp_path / "scene")
    assert scene.names("train") == ["IMG_000", "IMG_001", "IMG_002"] and scene.names("test") == []
    errors = pose_errors(
        np.array([scene.camera(n).c2w for n in scene.names("all")]), np.array([c.c2w for c in cams])
    )
    assert errors["rotation_deg"].max() < 2.5


def test_a_video_of_a_resting_camera_is_one_line_and_nothing_written(tmp_path, capsys) -> None:
    frame = render_room(arc_cameras(1, width=96, height=72))[0]
    video = tmp_path / "still.avi"
    write_video(video, iter([frame] * 6), FPS)  # every frame a near-duplicate of the first
    assert main(["capture", str(video), "--out", str(tmp_path / "scene")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "only 1 sharp, distinct frame(s) of 6" in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["still.avi"]
