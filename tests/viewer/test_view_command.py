"""``langfield view``: it serves the page until Ctrl-C, and refuses bad input with one line."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import urllib.request

import pytest

from langfield.cli import main


@pytest.mark.slow
def test_view_serves_the_page_and_stops_on_ctrl_c(viewer_field_dir) -> None:
    run = "import sys; from langfield.cli import main; sys.exit(main())"
    argv = [sys.executable, "-u", "-c", run, "view", str(viewer_field_dir), "--port", "0"]
    # Ctrl-C as in a terminal: a suite started as a background job (`cmd &` in a script) inherits an
    # ignored SIGINT, and a Python started with SIGINT ignored never raises KeyboardInterrupt.
    terminal = lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)  # noqa: E731
    proc = subprocess.Popen(
        argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, preexec_fn=terminal
    )
    try:
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if line.startswith("langfield view:"):
                break
        url = re.search(r"at (http://\S+)", lines[-1]).group(1)
        assert "Gaussians" in lines[-1] and "cameras" in lines[-1]
        with urllib.request.urlopen(url, timeout=30) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
        proc.send_signal(signal.SIGINT)
        rest = proc.communicate(timeout=60)[0]
    finally:
        proc.kill()
    assert proc.returncode == 0 and "stopped" in rest


def test_view_refuses_bad_input(viewer_field_dir, tmp_path, capsys) -> None:
    cases = [
        ([str(tmp_path / "nothing")], "nothing"),
        ([str(viewer_field_dir), "--port", "70000"], "--port"),
        ([str(viewer_field_dir), "--scene", str(tmp_path / "no_scene")], "no_scene"),
    ]
    for argv, message in cases:
        assert main(["view", *argv]) == 2, argv
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, (argv, err)


def test_view_shows_a_field_whose_scene_moved_without_cameras(viewer_field_dir, tmp_path, capsys) -> None:
    from langfield import LanguageField
    from langfield.cli.view import scene_for

    field = LanguageField.load(viewer_field_dir)
    assert scene_for(field, None) is not None
    field.meta["scene"] = str(tmp_path / "gone")
    assert scene_for(field, None) is None
    assert "no cameras shown" in capsys.readouterr().out
    with pytest.raises(ValueError):
        scene_for(field, str(tmp_path / "gone"))  # named with --scene: it must load
