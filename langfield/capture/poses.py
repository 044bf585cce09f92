"""Camera poses, intrinsics and sparse points of unposed frames, by COLMAP's incremental structure from
motion (pycolmap; Schönberger and Frahm 2016, "Structure-from-Motion Revisited").

:func:`solve_poses` runs, in a work folder:

1. SIFT features of every frame into a COLMAP database, one camera shared by all frames or one per
   frame. The camera is COLMAP's default model, SIMPLE_RADIAL: one focal length (square pixels, as
   every phone and video camera has), the principal point and one radial distortion k1, written out
   as OPENCV (fx = fy, k2 = p1 = p2 = 0) for the loaders to undistort. More free parameters fit
   worse on few or narrow views; on a video of the built-in room (24 frames on an 80 degree arc,
   largest rotation error after alignment): OPENCV 13-14 degrees, its vertical focal length drifting
   to 866 pixels against a horizontal 282 (true: 277 for both) since the camera moves sideways;
   RADIAL (k1, k2) 1.8 degrees; SIMPLE_RADIAL 0.8 degrees;
2. matching of the chosen pairs and their geometric verification. A few photos are matched
   exhaustively. A video's frames are matched sequentially (each with the next 10 and those 2^k
   further on, COLMAP's ``quadratic_overlap``), and loops are closed by matching every pair of
   keyframes (about 15 frames spread over the video): COLMAP's own loop detection needs a vocabulary
   tree file, which nothing here can download;
3. incremental mapping, which may split the frames into several models.

Input that the defaults cannot pose (dense foliage and repeated texture register 3 of 34 LLFF frames
at 504 x 378) is tried again with stated options, each an *attempt* of :data:`ATTEMPTS`: more and
finer SIFT features (a third of the peak threshold, domain-size pooling) matched exhaustively with
guided matching, then the same matches with a mapper that accepts weaker geometry. The attempt that
registers the most frames in one model wins, then the one that places the most frames in any model
(the first, on a tie); every attempt is reported.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from itertools import combinations
from pathlib import Path
from typing import Literal

import numpy as np

__all__ = ["ATTEMPTS", "Attempt", "PoseModel", "PoseResult", "frame_pairs", "solve_poses"]

CameraSharing = Literal["single", "per-image"]
Matching = Literal["exhaustive", "sequential"]
Progress = Callable[[str, int], Callable[[int], None]]  # (stage, total) -> advance(n)

_SEED = 0
# COLMAP repeats a run only on one thread: its feature extraction, RANSAC draws and Ceres' bundle
# adjustment depend on the threads' order otherwise (colmap/colmap#727, #3544; here the extraction too,
# tested), and a capture that does not repeat gives a scene, and figures, that do not either.
_THREADS = 1
_SEQUENTIAL_OVERLAP = 10  # COLMAP's default for sequential matching
_KEYFRAMES = 15  # loop closure: every pair among about this many frames spread over the video
_PAIR_CHUNK = 40  # pairs matched per pycolmap call, so that the bar moves
_FEATURE_CHUNK = 4
MIN_FRAMES = 3


@dataclass(frozen=True)
class Attempt:
    """One set of COLMAP options tried in turn.

    Attributes:
        name: how the report names it.
        features: "default" (COLMAP's SIFT) or "dense" (a third of the peak threshold, 16384 features
            at most, domain-size pooling).
        exhaustive: match every pair, also for a video.
        guided: guided matching (a second matching pass constrained by the verified geometry).
        relaxed: a mapper that accepts weaker geometry (fewer inliers to start and to register a
            frame, a smaller starting triangulation angle).
    """

    name: str
    features: Literal["default", "dense"] = "default"
    exhaustive: bool = False
    guided: bool = False
    relaxed: bool = False


ATTEMPTS: tuple[Attempt, ...] = (
    Attempt("defaults"),
    Attempt("more features", features="dense", exhaustive=True, guided=True),
    Attempt("relaxed mapper", features="dense", exhaustive=True, guided=True, relaxed=True),
)


@dataclass
class PoseModel:
    """One model COLMAP made: the frames it registered and where they are.

    Attributes:
        names: the registered frames, in input order.
        cam_from_world: name -> [3, 4] float64 world-to-camera (OpenCV axes, COLMAP's convention).
        cameras: name -> {"model", "width", "height", "params"} (OPENCV: fx fy cx cy k1 k2 p1 p2).
        points: [P, 3] float64 sparse points; colors: [P, 3] uint8 RGB.
        depth_range: name -> (near, far), the 1st and 99th percentiles of the z-depths of the points
            the frame observes (LLFF's ``poses_bounds.npy`` takes the 0.1th and 99.9th of a
            full-resolution model's many points; over the few hundred a small frame sees those are
            single outliers: fern's near 31 % nearer and far 21 % farther than LLFF's, where the 1st
            and 99th are within 5 %); absent for a frame that sees none.
        reprojection_error: mean, in pixels.
    """

    names: list[str]
    cam_from_world: dict[str, np.ndarray]
    cameras: dict[str, dict]
    points: np.ndarray
    colors: np.ndarray
    depth_range: dict[str, tuple[float, float]]
    reprojection_error: float


@dataclass
class PoseResult:
    """Every model of the winning attempt (largest first), the frames none registered, the attempts."""

    models: list[PoseModel]
    unregistered: list[str]
    attempts: list[dict] = field(default_factory=list)
    attempt: str = ""


def frame_pairs(names: Sequence[str], matching: Matching) -> list[tuple[str, str]]:
    """The image pairs to match: every pair, or a video's sequential pairs and its keyframe loops."""
    if matching == "exhaustive":
        return list(combinations(names, 2))
    n = len(names)
    pairs: set[tuple[int, int]] = set()
    for i in range(n):
        for step in range(1, _SEQUENTIAL_OVERLAP + 1):
            if i + step < n:
                pairs.add((i, i + step))
        for k in range(_SEQUENTIAL_OVERLAP):  # COLMAP's quadratic overlap: i + 2^k, k < overlap
            if i + 2**k >= n:
                break
            pairs.add((i, i + 2**k))
    keyframes = np.unique(np.linspace(0, n - 1, min(n, _KEYFRAMES)).round().astype(int))
    pairs.update((int(a), int(b)) for a, b in combinations(keyframes, 2))
    return [(names[a], names[b]) for a, b in sorted(pairs)]


def _no_progress(stage: str, total: int) -> Callable[[int], None]:
    return lambda n: None


def solve_poses(
    image_dir: Path,
    names: Sequence[str],
    work: Path,
    *,
    camera: CameraSharing = "single",
    matching: Matching = "exhaustive",
    attempts: Sequence[Attempt] = ATTEMPTS,
    focal_priors: dict[str, float] | None = None,
    verbose: bool = False,
    progress: Progress = _no_progress,
) -> PoseResult:
    """Poses of the image files ``image_dir/<name>`` by COLMAP (see the module docstring).

    Attempts run in order until one registers every frame in one model. ``work`` is an empty folder
    for the databases and models; the caller removes it. ``focal_priors`` (file name -> focal length in
    pixels, from the photos' EXIF) start each camera's focal length there, marked as a prior that
    COLMAP trusts (a shared camera takes their median); others start at COLMAP's guess, 1.2 times the
    longer side.

    Returns:
        :class:`PoseResult`; its ``models`` may be empty (nothing registered).
    """
    import pycolmap

    old_level = pycolmap.logging.minloglevel
    # Quiet unless asked: COLMAP logs even a model it could not make as an error, and the capture says
    # that itself, in one line.
    pycolmap.logging.minloglevel = int(pycolmap.logging.INFO if verbose else pycolmap.logging.FATAL)
    best: PoseResult | None = None
    reports: list[dict] = []
    databases: dict[tuple, Path] = {}
    try:
        for attempt in attempts:
            start = time.perf_counter()
            result = _attempt(
                pycolmap,
                image_dir,
                list(names),
                work,
                attempt,
                camera,
                matching,
                databases,
                progress,
                focal_priors,
            )
            registered = _score(result)[0]
            reports.append(
                {
                    "name": attempt.name,
                    "options": _describe(attempt, matching),
                    "models": [len(m.names) for m in result.models],
                    "registered": registered,
                    "seconds": round(time.perf_counter() - start, 2),
                }
            )
            if best is None or _score(result) > _score(best):
                best, best.attempt = result, attempt.name
            if registered == len(names):
                break
    finally:
        pycolmap.logging.minloglevel = old_level
    assert best is not None
    best.attempts = reports
    return best


def _score(result: PoseResult) -> tuple[int, int]:
    """Frames in the largest model, then frames in any model: what makes one attempt better."""
    sizes = [len(m.names) for m in result.models]
    return (max(sizes, default=0), sum(sizes))


def _describe(attempt: Attempt, matching: Matching) -> str:
    parts = ["SIFT: COLMAP defaults" if attempt.features == "default" else "SIFT: peak 0.0022, 16384, DSP"]
    parts.append("exhaustive" if attempt.exhaustive or matching == "exhaustive" else "sequential + loops")
    if attempt.guided:
        parts.append("guided matching")
    parts.append("relaxed mapper" if attempt.relaxed else "mapper defaults")
    return ", ".join(parts)


def _attempt(
    pycolmap,
    image_dir: Path,
    names: list[str],
    work: Path,
    attempt: Attempt,
    camera: CameraSharing,
    matching: Matching,
    databases: dict[tuple, Path],
    progress: Progress,
    focal_priors: dict[str, float] | None = None,
) -> PoseResult:
    """One attempt: features and matches (reused from an earlier attempt with the same ones), mapping."""
    chosen: Matching = "exhaustive" if attempt.exhaustive else matching
    key = (attempt.features, chosen, attempt.guided)
    if key not in databases:
        database = work / f"database_{len(databases)}.db"
        _extract(pycolmap, database, image_dir, names, camera, attempt, progress)
        if focal_priors:
            _set_focal_priors(pycolmap, database, focal_priors)
        _match(pycolmap, database, work, frame_pairs(names, chosen), attempt, progress)
        databases[key] = database
    out = work / f"models_{attempt.name.replace(' ', '_')}"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    reconstructions = _map(pycolmap, databases[key], image_dir, out, names, attempt, progress)
    order = {name: i for i, name in enumerate(names)}
    found = sorted(
        (_model(r, order) for r in reconstructions.values() if r.num_reg_images() >= MIN_FRAMES),
        key=lambda m: (-len(m.names), order[m.names[0]]),
    )
    # COLMAP lets a later model share up to 20 frames with earlier ones; one that adds no frame of its
    # own is the same part of the scene again and is not a model of its own here.
    models: list[PoseModel] = []
    placed: set[str] = set()
    for model in found:
        if set(model.names) - placed:
            models.append(model)
            placed.update(model.names)
    return PoseResult(models, [n for n in names if n not in placed])


def _extract(pycolmap, database: Path, image_dir: Path, names, camera, attempt, progress) -> None:
    advance = progress("features", len(names))
    for k in range(0, len(names), _FEATURE_CHUNK):
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_RADIAL"
        mode = pycolmap.CameraMode.PER_IMAGE
        if camera == "single":
            mode = pycolmap.CameraMode.SINGLE
            if k:  # later chunks join the first chunk's camera
                reader.existing_camera_id = 1
        options = pycolmap.FeatureExtractionOptions()
        options.use_gpu = False
        options.num_threads = _THREADS
        if attempt.features == "dense":
            options.sift.peak_threshold = 0.02 / 9  # a third of COLMAP's 0.02 / octave_resolution
            options.sift.max_num_features = 16384
            options.sift.domain_size_pooling = True
        chunk = list(names[k : k + _FEATURE_CHUNK])
        pycolmap.extract_features(
            database,
            image_dir,
            image_names=chunk,
            camera_mode=mode,
            reader_options=reader,
            extraction_options=options,
            device=pycolmap.Device.cpu,
        )
        advance(len(chunk))


def _set_focal_priors(pycolmap, database_path: Path, priors: dict[str, float]) -> None:
    """Each camera's focal length (parameter 0 of SIMPLE_RADIAL) from its images' EXIF priors."""
    database = pycolmap.Database.open(database_path)
    try:
        by_camera: dict[int, list[float]] = {}
        for image in database.read_all_images():
            if image.name in priors:
                by_camera.setdefault(image.camera_id, []).append(priors[image.name])
        for camera_id, values in by_camera.items():
            camera = database.read_camera(camera_id)
            params = list(camera.params)
            params[0] = float(np.median(values))
            camera.params = params
            camera.has_prior_focal_length = True
            database.update_camera(camera)
    finally:
        database.close()


def _match(pycolmap, database: Path, work: Path, pairs, attempt, progress) -> None:
    advance = progress("matching", len(pairs))
    pair_file = work / "pairs.txt"
    for k in range(0, len(pairs), _PAIR_CHUNK):
        chunk = pairs[k : k + _PAIR_CHUNK]
        pair_file.write_text("".join(f"{a} {b}\n" for a, b in chunk))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pair_file)
        options = pycolmap.FeatureMatchingOptions()
        options.use_gpu = False
        options.num_threads = _THREADS
        options.guided_matching = attempt.guided
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = _SEED
        pycolmap.match_image_pairs(
            database,
            matching_options=options,
            pairing_options=pairing,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )
        advance(len(chunk))


def _map(pycolmap, database: Path, image_dir: Path, out: Path, names, attempt, progress) -> dict:
    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = _SEED
    options.num_threads = _THREADS
    options.min_model_size = MIN_FRAMES  # report small models too, rather than drop their frames
    if attempt.relaxed:
        options.min_num_matches = 10
        options.mapper.init_min_num_inliers = 30
        options.mapper.init_min_tri_angle = 4.0
        options.mapper.abs_pose_min_num_inliers = 15
        options.mapper.abs_pose_min_inlier_ratio = 0.15
        options.mapper.max_reg_trials = 5
    advance = progress("mapping", len(names))
    return pycolmap.incremental_mapping(
        database,
        image_dir,
        out,
        options=options,
        initial_image_pair_callback=lambda: advance(2),
        next_image_callback=lambda: advance(1),
    )


def opencv_params(model: str, params: list[float]) -> list[float]:
    """OPENCV's fx fy cx cy k1 k2 p1 p2 of a COLMAP pinhole or radial camera."""
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        f, cx, cy, *k = params
        k = (k + [0.0, 0.0])[:2]
        return [f, f, cx, cy, k[0], k[1], 0.0, 0.0]
    if model == "PINHOLE":
        return [*params, 0.0, 0.0, 0.0, 0.0]
    if model == "OPENCV":
        return list(params)
    raise ValueError(f"COLMAP camera model {model} has no OPENCV equivalent")


def _model(reconstruction, order: dict[str, int]) -> PoseModel:
    """A :class:`PoseModel` of one pycolmap reconstruction (names are the image files' names)."""
    points = {pid: p for pid, p in reconstruction.points3D.items()}
    ids = list(points)
    xyz = np.array([points[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    colors = np.array([points[i].color for i in ids], dtype=np.uint8).reshape(-1, 3)
    row = {pid: k for k, pid in enumerate(ids)}
    poses, cameras, ranges = {}, {}, {}
    for image in reconstruction.images.values():
        if not image.has_pose:
            continue
        name = image.name
        pose = image.cam_from_world().matrix()
        poses[name] = pose
        cam = reconstruction.cameras[image.camera_id]
        cameras[name] = {
            "model": "OPENCV",
            "width": int(cam.width),
            "height": int(cam.height),
            "params": opencv_params(cam.model_name, [float(v) for v in cam.params]),
        }
        seen = [row[p.point3D_id] for p in image.get_observation_points2D() if p.point3D_id in row]
        if seen:
            z = xyz[seen] @ pose[2, :3] + pose[2, 3]
            z = z[z > 0]
            if len(z):
                ranges[name] = (float(np.percentile(z, 1.0)), float(np.percentile(z, 99.0)))
    names = sorted(poses, key=lambda n: order[n])
    error = float(reconstruction.compute_mean_reprojection_error()) if len(ids) else 0.0
    return PoseModel(names, poses, cameras, xyz, colors, ranges, error)
