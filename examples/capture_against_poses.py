"""How close `langfield capture` comes to a scene's known poses: its photos are captured without their
poses, then the recovered cameras are compared with the scene's own after a similarity alignment.

python examples/capture_against_poses.py ../shared/data/llff_fern --out fern_captured [--views a,b,c]
    [--json errors.json]

Prints the frames posed, the largest and mean rotation errors (degrees) and centre errors (as a share
of the cameras' largest distance from their mean), and the capture's time per step. The captured scene
stays in --out for training (`langfield train OUT --views ...`).
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
from langfield.capture.alignment import pose_errors
from langfield.io.scene import load_scene


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scene", help="a posed scene folder (any layout load_scene reads)")
    parser.add_argument("--out", required=True, help="the captured scene folder to write (replaced)")
    parser.add_argument("--views", default=None, help="capture only these photos (comma-separated names)")
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
