"""How close `langfield capture` comes to a scene's known poses: its photos are captured without their
poses, then the recovered cameras are compared with the scene's own after a similarity alignment.

python examples/capture_against_poses.py ../shared/data/llff_fern --out fern_captured [--views a,b,c]
    [--test-views d,e,f] [--json errors.json]

Prints the frames posed, the largest and mean rotation errors (degrees) and centre errors (as a share
of the cameras' largest distance from their mean), and the capture's time per step. The captured scene
stays in --out for training (`langfield train OUT --views ...`). ``--test-views`` adds photos that were
not captured as test views of OUT, posed by the scene's own poses carried into OUT's frame by the
similarity that aligns the captured cameras with theirs (how a capture of only three photos is scored).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from langfield.capture import CaptureOptions, capture
from langfield.capture.alignment import align_poses, pose_errors
from langfield.io.scene import load_scene


def _add_test_views(truth, captured, names: list[str], out: Path) -> None:
    """Writes ``names`` into OUT's transforms.json as test views: their known poses taken into OUT's
    frame, OUT's shared camera, the median near / far, the photo copied into images/."""
    posed = captured.names("all")
    scale, rotation, shift = align_poses(
        np.array([truth.camera(n).c2w for n in posed]), np.array([captured.camera(n).c2w for n in posed])
    )
    meta = json.loads((out / "transforms.json").read_text())
    near, far = np.median([[f["near"], f["far"]] for f in meta["frames"]], axis=0)
    for name in names:
        c2w = truth.camera(name).c2w
        pose = np.eye(4)
        pose[:3, :3] = rotation @ c2w[:3, :3]
        pose[:3, 3] = scale * rotation @ c2w[:3, 3] + shift
        path = truth.views[truth.names("all").index(name)].image_path
        shutil.copyfile(path, out / "images" / f"{name}{path.suffix}")
        frame = {"file_path": f"images/{name}{path.suffix}", "transform_matrix": pose.tolist()}
        meta["frames"].append({**frame, "split": "test", "near": float(near), "far": float(far)})
    (out / "transforms.json").write_text(json.dumps(meta, indent=2))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene", help="a posed scene folder (any layout load_scene reads)")
    parser.add_argument("--out", required=True, help="the captured scene folder to write (replaced)")
    parser.add_argument("--views", default=None, help="capture only these photos (comma-separated names)")
    parser.add_argument("--test-views", default=None, help="add these uncaptured photos as test views")
    parser.add_argument("--json", default=None, help="write the errors and timings here")
    args = parser.parse_args(argv)

    truth = load_scene(args.scene)
    names = truth.names("all") if args.views is None else args.views.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        photos = Path(tmp) / "photos"
        photos.mkdir()
        for name in names:  # the stored photos, as a person has them: no poses, no undistortion
            path = truth.views[truth.names("all").index(name)].image_path
            shutil.copyfile(path, photos / f"{name}{path.suffix}")
        report = capture(photos, args.out, CaptureOptions(force=True))
    captured = load_scene(args.out)
    posed = captured.names("all")
    errors = pose_errors(
        np.array([captured.camera(n).c2w for n in posed]), np.array([truth.camera(n).c2w for n in posed])
    )
    if args.test_views:
        _add_test_views(truth, captured, args.test_views.split(","), Path(args.out))
    result = {
        "frames": len(names),
        "posed": len(posed),
        "rotation_deg": {
            "mean": float(errors["rotation_deg"].mean()),
            "max": float(errors["rotation_deg"].max()),
        },
        "centre_share": {
            "mean": float(errors["centre"].mean() / errors["size"]),
            "max": float(errors["centre"].max() / errors["size"]),
        },
        "train_views": report["scene"]["train"],
        "seconds": report["seconds"],
    }
    rotation, centre, seconds = result["rotation_deg"], result["centre_share"], report["seconds"]
    print(
        f"{result['posed']} of {result['frames']} frames posed; rotation error {rotation['mean']:.3f} deg "
        f"mean, {rotation['max']:.3f} max; centre error {100 * centre['mean']:.2f} % of the cameras' size "
        f"mean, {100 * centre['max']:.2f} % max; capture {seconds['total']:.1f} s (frames "
        f"{seconds['frames']:.1f}, poses {seconds['poses']:.1f}); "
        f"training views {', '.join(result['train_views'])}"
    )
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
