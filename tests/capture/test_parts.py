"""The capture's parts one at a time: frame picking, image pairs, normalisation, view spread, pose
errors, and what the loader and the start read of a captured scene."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from langfield.camera import Camera
from langfield.capture.alignment import pose_errors, umeyama
from langfield.capture.frames import video_frames
from langfield.capture.poses import frame_pairs, opencv_params
from langfield.capture.scene_folder import write_points
from langfield.capture.views import normalise, spread_views
from langfield.io.layout import SceneError
from langfield.io.ply import read_points
from langfield.io.scene import load_scene
from langfield.viewer.video import write_video


def _rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    rvec = np.asarray(axis, np.float64) / np.linalg.norm(axis) * np.radians(degrees)
    return cv2.Rodrigues(rvec)[0]


def test_video_frames_drops_the_blurred_and_the_repeated_frame(tmp_path) -> None:
    rng = np.random.default_rng(0)
    texture = cv2.resize(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8), (320, 240), cv2.INTER_NEAREST)
    frames = [np.roll(texture, 12 * i, axis=1) for i in range(8)]
    frames[3] = cv2.GaussianBlur(frames[3], (0, 0), 6)  # a shaken frame
    frames[6] = frames[5].copy()  # the camera rested
    video = tmp_path / "v.avi"
    write_video(video, iter(frames), 4.0)
    out = tmp_path / "frames"
    out.mkdir()
    choice = video_frames(video, out, count=8, max_size=200)
    assert choice.decoded == 8
    dropped = {r["index"]: r["reason"] for r in choice.dropped}
    assert sorted(dropped) == [3, 6]
    assert dropped[3].startswith("blurred") and dropped[6] == "near-duplicate of t001.250s"
    kept = [r["name"] for r in choice.kept]
    assert kept == ["t000.000s", "t000.250s", "t000.500s", "t001.000s", "t001.250s", "t001.750s"]
    assert sorted(p.stem for p in out.iterdir()) == kept
    assert cv2.imread(str(out / "t000.000s.png")).shape == (150, 200, 3)  # longer side 200


def test_video_frames_keeps_the_sharpest_of_each_stretch(tmp_path) -> None:
    rng = np.random.default_rng(1)
    texture = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    frames = [np.roll(cv2.GaussianBlur(texture, (0, 0), 1.5), 3 * i, axis=1) for i in range(6)]
    frames[4] = np.roll(texture, 12, axis=1)  # the only unblurred frame of the second half
    video = tmp_path / "v.avi"
    write_video(video, iter(frames), 2.0)
    choice = video_frames(video, tmp_path, count=2, max_size=64)
    assert [r["index"] for r in choice.kept][1] == 4


def test_exhaustive_pairs_are_every_pair_and_sequential_pairs_close_loops() -> None:
    names = [f"f{i:02d}" for i in range(40)]
    assert len(frame_pairs(names[:6], "exhaustive")) == 15
    pairs = set(frame_pairs(names, "sequential"))
    assert ("f00", "f01") in pairs and ("f00", "f10") in pairs and ("f00", "f12") not in pairs
    assert ("f00", "f16") in pairs and ("f00", "f32") in pairs  # quadratic overlap
    assert ("f00", "f39") in pairs  # the keyframes' loop: first and last frames are matched
    many = [f"f{i:03d}" for i in range(120)]
    assert len(frame_pairs(many, "sequential")) < len(frame_pairs(many, "exhaustive")) / 3


def test_normalise_centres_the_cameras_puts_their_up_on_z_and_scales_them_to_one() -> None:
    rng = np.random.default_rng(2)
    tilt = _rotation([1.0, 0.3, 0.0], 50.0)
    w2c = []
    for i in range(5):
        c2w = np.eye(4)
        c2w[:3, :3] = tilt @ _rotation([0.0, 1.0, 0.0], 10.0 * i) @ np.diag([1.0, -1.0, -1.0])  # to OpenCV
        c2w[:3, 3] = rng.normal(size=3) * 3 + 7
        w2c.append(np.linalg.inv(c2w)[:3])
    norm = normalise(w2c)
    gl = np.array([norm.camera_to_world(p) for p in w2c])
    np.testing.assert_allclose(gl[:, :3, 3].mean(axis=0), 0.0, atol=1e-9)
    assert abs(np.abs(gl[:, :3, 3]).max() - 1.0) < 1e-9
    up = gl[:, :3, 1].mean(axis=0)
    np.testing.assert_allclose(up / np.linalg.norm(up), [0, 0, 1], atol=1e-9)
    for m in gl:
        np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-9)


def test_normalise_a_turn_on_the_spot_takes_its_scale_from_the_points() -> None:
    w2c = [np.hstack([_rotation([0, 1, 0], 20.0 * i), np.zeros((3, 1))]) for i in range(3)]
    norm = normalise(w2c, points=np.array([[0.0, 0.0, 4.0], [1.0, 0.0, 5.0]]))
    assert np.isfinite(norm.scale) and 0.1 < norm.scale < 1.0


def test_spread_views_takes_the_middle_and_both_ends_of_a_sweep() -> None:
    cams = [
        Camera.look_at((x, -3.0, 0.0), (0.0, 0.0, 0.0), width=40, height=30).c2w
        for x in np.linspace(-2, 2, 9)
    ]
    assert spread_views(np.array(cams), np.zeros(3), 3) == [0, 4, 8]
    assert spread_views(np.array(cams), np.zeros(3), 1) == [4]
    with pytest.raises(ValueError, match="cannot choose 10 of 9"):
        spread_views(np.array(cams), np.zeros(3), 10)


def test_pose_errors_are_zero_after_a_similarity_and_see_a_turned_camera() -> None:
    cams = np.array(
        [
            Camera.look_at((x, -3.0, 0.3 * x * x), (0, 0, 0), width=40, height=30).c2w
            for x in np.linspace(-2, 2, 6)
        ]
    )
    rotation, scale, shift = _rotation([1.0, 2.0, 3.0], 40.0), 2.5, np.array([1.0, -2.0, 3.0])
    moved = cams.copy()
    moved[:, :3, :3] = np.einsum("ij,njk->nik", rotation, cams[:, :3, :3])
    moved[:, :3, 3] = scale * cams[:, :3, 3] @ rotation.T + shift
    errors = pose_errors(moved, cams)
    assert errors["rotation_deg"].max() < 1e-6 and errors["centre"].max() < 1e-9
    assert abs(errors["scale"] - 1 / scale) < 1e-9
    moved[2, :3, :3] = moved[2, :3, :3] @ _rotation([0.0, 1.0, 0.0], 3.0)
    errors = pose_errors(moved, cams)
    assert 2.0 < errors["rotation_deg"][2] < 3.0 and errors["rotation_deg"][0] < 1.0


def test_umeyama_refuses_coinciding_points() -> None:
    with pytest.raises(ValueError, match="coincide"):
        umeyama(np.ones((4, 3)), np.random.default_rng(0).normal(size=(4, 3)))


def test_opencv_params_of_colmaps_radial_models() -> None:
    assert opencv_params("SIMPLE_RADIAL", [300.0, 160.0, 120.0, 0.1]) == [300, 300, 160, 120, 0.1, 0, 0, 0]
    assert opencv_params("PINHOLE", [1.0, 2.0, 3.0, 4.0]) == [1, 2, 3, 4, 0, 0, 0, 0]
    with pytest.raises(ValueError, match="FOV"):
        opencv_params("FOV", [1.0] * 5)


def _scene(tmp_path: Path, frames_extra: list[dict], meta_extra: dict) -> Path:
    (tmp_path / "images").mkdir(parents=True)
    frames = []
    for i, extra in enumerate(frames_extra):
        cv2.imwrite(str(tmp_path / "images" / f"{i}.png"), np.full((12, 16, 3), 100, np.uint8))
        c2w = np.eye(4)
        c2w[0, 3] = i
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": c2w.tolist(), **extra})
    meta = {"w": 16, "h": 12, "fl_x": 20.0, "frames": frames, **meta_extra}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    return tmp_path


def test_the_loader_reads_near_far_and_the_point_cloud(tmp_path) -> None:
    write_points(
        tmp_path / "pc.ply", np.array([[0, 0, -2.0], [1, 0, -3.0]]), np.array([[255, 0, 0], [0, 0, 255]])
    )
    bounds = [{"near": 1.0, "far": 4.0}, {"near": 2.0, "far": 5.0}, {"near": 1.5, "far": 6.0}]
    scene = load_scene(_scene(tmp_path, bounds, {"ply_file_path": "pc.ply"}))
    assert scene.near_far == (1.0, 6.0) and scene.points_path == tmp_path / "pc.ply"
    points, colors = read_points(scene.points_path)
    np.testing.assert_allclose(points, [[0, 0, -2], [1, 0, -3]])
    np.testing.assert_allclose(colors, [[1, 0, 0], [0, 0, 1]])
    box = scene.bounds()
    assert box[0, 2] < -1.0 and box[1, 2] < 0.0  # in front of the cameras, out to their far


@pytest.mark.parametrize(
    ("frames_extra", "meta_extra", "expected"),
    [
        ([{"near": 1.0, "far": 4.0}, {}, {}], {}, "needs both near and far"),
        ([{"near": 4.0, "far": 1.0}] * 3, {}, "0 <= near < far"),
        ([{"near": float("nan"), "far": 1.0}] * 3, {}, "near must be a finite number"),
        ([{}] * 3, {"ply_file_path": "missing.ply"}, "ply_file_path 'missing.ply' is not a file"),
    ],
)
def test_the_loader_refuses_bad_near_far_and_a_missing_point_cloud(
    tmp_path, frames_extra, meta_extra, expected
):
    with pytest.raises(SceneError, match=expected):
        load_scene(_scene(tmp_path, frames_extra, meta_extra))


def test_read_points_refuses_a_file_that_is_not_a_point_cloud(tmp_path) -> None:
    (tmp_path / "bad.ply").write_text("not a ply")
    with pytest.raises(SceneError, match="no points could be read"):
        read_points(tmp_path / "bad.ply")
    with pytest.raises(SceneError, match="not found"):
        read_points(tmp_path / "none.ply")


def test_init_points_starts_from_the_point_cloud_and_needs_one(tmp_path) -> None:
    from langfield.training.config import TrainConfig
    from langfield.training.setup import init_method
    from langfield.training.start import start_points

    rng = np.random.default_rng(3)
    cloud = (rng.uniform(-1, 1, (500, 3)).astype(np.float32), rng.uniform(0, 1, (500, 3)).astype(np.float32))
    cloud[0][:100] += 10.0  # outside the bounds: left out
    bounds = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    start = start_points("points", [], [], bounds, 900, scene_points=cloud, fill=0.5)
    assert start.method == "points" and len(start.points) == 900 and start.stats["photo_points"] == 400
    assert start.stats["points"] == {"file_points": 500, "inside_bounds": 400}
    assert np.all(np.abs(start.points) <= 1.0 + 1e-6)
    scene = load_scene(_scene(tmp_path, [{}] * 3, {}))
    with pytest.raises(SceneError, match="--init points: .* has no point cloud"):
        init_method(scene, TrainConfig(init="points"))


def test_exif_focal_length_is_read_where_a_photo_has_one(tmp_path) -> None:
    from PIL import Image

    from langfield.capture.frames import exif_focal_35mm, focal_pixels

    image = Image.fromarray(np.zeros((30, 40, 3), np.uint8))
    exif = image.getexif()
    exif.get_ifd(0x8769)[0xA405] = 26
    image.save(tmp_path / "a.jpg", exif=exif)
    image.save(tmp_path / "b.png")
    assert exif_focal_35mm(tmp_path / "a.jpg") == 26.0
    assert exif_focal_35mm(tmp_path / "b.png") is None
    for impossible in (1, 5000):  # parses, but is no lens's 35 mm-equivalent: no prior
        exif.get_ifd(0x8769)[0xA405] = impossible
        image.save(tmp_path / f"c{impossible}.jpg", exif=exif)
        assert exif_focal_35mm(tmp_path / f"c{impossible}.jpg") is None
    # 35 mm-equivalent keeps the diagonal field of view of a 36 x 24 mm frame.
    assert abs(focal_pixels(36.0, 3600, 2400) - 3600) < 1e-9
