"""``langfield demo``: the built-in scene generated, trained on 3 views, scored, queried, filmed and shown
in the viewer."""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path


def cmd_demo(args: argparse.Namespace) -> int:
    from langfield.io.scene import load_scene
    from langfield.synthetic import make_room
    from langfield.training.config import TrainConfig
    from langfield.training.loop import summary_line, train
    from langfield.training.setup import training_length

    if args.layout < 0:
        raise ValueError(f"--layout: a whole number >= 0, got {args.layout}")
    out = Path(args.out)
    t0 = time.perf_counter()
    scene_dir = make_room(
        out / "scene", seed=args.seed, layout=args.layout, width=args.width, height=args.height
    )
    print(f"[1/6] built-in scene written to {scene_dir}")
    scene = load_scene(scene_dir)
    length = training_length(args.iterations, len(scene.names("train")))
    most = "" if length["forced"] else "at most "
    print(f"[2/6] training on {len(scene.names('train'))} views ({most}{length['iterations']} iterations)")
    field = train(scene, TrainConfig(iterations=args.iterations, seed=args.seed))
    field.meta["scene_args"] = {"resolution": 1.0, "views": None, "n_views": None}
    field.save(out / "field", overwrite=True)  # the demo's folder is its own: a rerun replaces it
    shot = _start_viewer_shot(out)
    try:
        report, pictures, queries, pictures_of_viewer = _score_query_film(field, scene, scene_dir, out, shot)
    finally:
        if not isinstance(shot, str) and shot.poll() is None:
            shot.kill()
    miou = report.get("mIoU")
    query_txt = f", novel-view mIoU {miou:.3f}, mAcc {report['mAcc']:.3f}" if miou is not None else ""
    print(
        summary_line(field, report["PSNR"]) + f", SSIM {report['SSIM']:.3f}{query_txt}; "
        f"demo took {time.perf_counter() - t0:.0f} s; pictures in {pictures} and {queries}"
    )
    print(f"{pictures_of_viewer}\nsee it and ask it in a browser: langfield view {out / 'field'}")
    return 0


def _score_query_film(field, scene, scene_dir: Path, out: Path, shot: subprocess.Popen | str):
    """Steps 3 to 6 (the viewer's screenshot is taken meanwhile by ``shot``): the report, the folders of
    the renders and the queries, and what step 6 wrote, in words."""
    from langfield.cli.query import cmd_query
    from langfield.eval.evaluate import evaluate, write_report

    pictures = out / "renders"
    print(f"[3/6] rendering and scoring {len(scene.names('test'))} novel views to {pictures}")
    report = evaluate(field, scene, save_dir=pictures)
    md = write_report(report, out / "report.json", pictures)
    print(f"[4/6] report: {out / 'report.json'} and {md}")
    queries = out / "queries"
    print(f"[5/6] text queries on the novel views ('couch' is a synonym the table knows) -> {queries}")
    query_args = argparse.Namespace(
        out=str(out / "field"),
        phrases=list(DEMO_PHRASES),
        views="test",
        save=str(queries),
        scene=str(scene_dir),
        text_encoder=None,
        exact=False,
    )
    cmd_query(query_args)
    written = _film(field, scene, out)
    return report, pictures, queries, f"{written}{_end_viewer_shot(shot)}"


def _film(field, scene, out: Path) -> str:
    """Step 6: an orbit video with the heat map of 'sofa' and one frame of it as a PNG; what was
    written, in words."""
    import cv2

    from langfield.viewer.paths import orbit
    from langfield.viewer.video import path_frames, read_video, write_video

    video = out / "orbit_sofa.mp4"
    print(f"[6/6] an orbit video with the heat map of 'sofa' ({video}) and the viewer")
    cameras = scene.cameras("all")
    query = field.query("sofa", scene=scene)
    path = orbit(cameras, DEMO_FRAMES, fallback=field.meta.centre)
    write_video(video, path_frames(field, path, query), fps=30.0)
    frame = read_video(video)[DEMO_FRAMES // 8]  # half-way out on the swing
    cv2.imwrite(str(out / "orbit_frame.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    return f"video {video}, one frame of it {out / 'orbit_frame.png'}"


def _start_viewer_shot(out: Path) -> subprocess.Popen | str:
    """Starts :func:`viewer_shot` on the saved field in a process of its own (or says why not).

    The screenshot mostly waits on the browser's software-rendered frames; beside the evaluation and the
    video it costs little, after them seconds. A process, not a thread: the viewer renders its heat map
    with numba kernels, whose workqueue threads may not run two kernels at once in one process."""
    from langfield.viewer.browser import browser_missing

    reason = browser_missing()
    if reason is not None:
        return reason
    code = "import sys; from langfield.cli.demo import viewer_shot; print(viewer_shot(sys.argv[1]))"
    return subprocess.Popen(
        [sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )


def _end_viewer_shot(shot: subprocess.Popen | str) -> str:
    """What the screenshot process wrote, in words (a failure is said, never raised: the picture is for
    the README, not a reason to fail the demo)."""
    if isinstance(shot, str):
        return f"; no screenshot of the viewer: {shot}"
    try:
        said, _ = shot.communicate(timeout=SHOT_TIMEOUT)
    except subprocess.TimeoutExpired:
        shot.kill()
        shot.communicate()
        return f"; no screenshot of the viewer: none within {SHOT_TIMEOUT} s"
    last = said.strip().splitlines()[-1] if said.strip() else f"it exited with {shot.returncode}"
    return last if shot.returncode == 0 else f"; no screenshot of the viewer: {last}"


def viewer_shot(out: str | Path) -> str:
    """A screenshot of the viewer answering 'sofa' on the demo's field in ``out``, as ``out/viewer.jpg``;
    what was written, in words (raises where it fails)."""
    from langfield.field import LanguageField
    from langfield.io.scene import load_scene
    from langfield.viewer.browser import screenshot_viewer, wait_for
    from langfield.viewer.server import Viewer

    out = Path(out)
    viewer = Viewer(
        LanguageField.load(out / "field"), load_scene(out / "scene"), port=0, save=out / "selections"
    )
    try:
        # Set on the server, as if typed: the page opens with the answer shown (see screenshot_viewer).
        viewer.phrase_box.value = "sofa"
        if not wait_for(lambda: viewer.answer.phrase == "sofa"):
            raise RuntimeError(f"the viewer did not answer 'sofa': {viewer.answer.text}")
        shot = screenshot_viewer(viewer.url, out / "viewer.jpg")
    finally:
        viewer.close()
    return f", the viewer answering 'sofa' {shot}"


DEMO_PHRASES = ("sofa", "couch", "lamp", "mug")
DEMO_FRAMES = 120
SHOT_TIMEOUT = 180  # seconds the screenshot may take after the video (it takes ~10 on two cores)


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Registers ``langfield demo``."""
    p = sub.add_parser("demo", help="generate the built-in scene, train on 3 views, render and report")
    p.add_argument(
        "--out", default="demo_out", help="the demo's own folder, replaced on a rerun (default demo_out)"
    )
    p.add_argument(
        "--iterations", type=int, default=None, help="training iterations (default: sized by the scene)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the scene and the training (default 0)")
    p.add_argument(
        "--layout",
        type=int,
        default=0,
        help="the room's furniture: 0 the built-in room, other numbers random arrangements (default 0)",
    )
    p.add_argument("--width", type=int, default=160, help="image width of the built-in scene (default 160)")
    p.add_argument("--height", type=int, default=120, help="image height of the built-in scene (default 120)")
    p.set_defaults(func=cmd_demo)
