"""Fly-through videos (langfield/viewer/video.py, ``langfield render --path ... --video``)."""

from __future__ import annotations

import numpy as np
import pytest

from langfield.cli import main
from langfield.viewer.video import read_video, write_video

from .conftest import H, W


def test_write_video_pads_odd_sizes_and_leaves_no_partial_file(tmp_path) -> None:
    frames = [np.full((7, 9, 3), 40 * i, np.uint8) for i in range(5)]
    path = tmp_path / "v.mp4"
    assert write_video(path, iter(frames), 10.0) == 5
    back = read_video(path)
    assert len(back) == 5 and back[0].shape == (8, 10, 3)
    assert abs(float(back[4].mean()) - 160.0) < 6.0  # lossy, but the frames are the ones written
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v.mp4"]


def test_interrupted_video_leaves_nothing(tmp_path) -> None:
    def frames():
        yield np.zeros((8, 8, 3), np.uint8)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_video(tmp_path / "v.mp4", frames(), 10.0)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
@pytest.mark.parametrize("path_kind", ["orbit", "interpolate"])
def test_render_video_frames_size_and_motion(viewer_field_dir, tmp_path, capsys, path_kind) -> None:
    video = tmp_path / f"{path_kind}.mp4"
    argv = ["render", str(viewer_field_dir), "--path", path_kind, "--video", str(video), "--frames", "12"]
    assert main(argv) == 0
    frames = read_video(video)
    assert len(frames) == 12 and frames[0].shape == (H, W, 3)
    diffs = [np.abs(a.astype(int) - b.astype(int)).mean() for a, b in zip(frames, frames[1:], strict=False)]
    assert min(diffs) > 0.5  # the camera moves every frame
    assert f"{path_kind} path of 12 frames" in capsys.readouterr().out


@pytest.mark.slow
def test_render_video_with_query_sets_the_heat_map_beside(viewer_field_dir, tmp_path) -> None:
    video = tmp_path / "sofa.avi"
    argv = ["render", str(viewer_field_dir), "--video", str(video), "--frames", "6", "--query", "sofa"]
    assert main(argv) == 0
    frames = read_video(video)
    assert len(frames) == 6 and frames[0].shape == (H, 2 * W, 3)
    left, right = frames[0][:, :W].astype(int), frames[0][:, W:].astype(int)
    assert np.abs(left - right).mean() > 10.0  # the heat map, not a copy of the render


def test_render_video_refuses_bad_input_before_work(viewer_field_dir, tmp_path, capsys) -> None:
    out = str(viewer_field_dir)
    existing = tmp_path / "old.mp4"
    existing.write_bytes(b"keep me")
    cases = [
        (["--video", str(existing)], "exists"),
        (["--video", str(tmp_path / "v.gif")], ".mp4 or .avi"),
        (["--video", str(tmp_path / "no" / "v.mp4")], "does not exist"),
        (["--video", str(tmp_path / "v.mp4"), "--frames", "1"], "--frames"),
        (["--video", str(tmp_path / "v.mp4"), "--save", str(tmp_path / "pngs")], "not both"),
        (["--video", str(tmp_path / "v.mp4"), "--query", "no such thing"], "no such thing"),
        (["--query", "sofa", "--save", str(tmp_path / "pngs")], "--query"),
        ([], "--save"),
    ]
    for extra, message in cases:
        assert main(["render", out, *extra]) == 2, extra
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, (extra, err)
    assert existing.read_bytes() == b"keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old.mp4"]
