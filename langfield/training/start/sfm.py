"""Sparse structure from the training views with their known poses, by COLMAP (pycolmap).

FSGS (Zhu et al. 2024) and CoR-GS (Zhang et al. 2024) start their Gaussians from COLMAP's sparse
points of the few training views: SIFT features, exhaustive matching with geometric verification,
and COLMAP's point triangulator with the given poses held fixed (Schönberger and Frahm 2016,
"Structure-from-Motion Revisited"; https://colmap.github.io/faq.html, "Reconstruct sparse/dense
model from known camera poses"). :func:`sfm_points` runs that pipeline through pycolmap (4.2):

1. the images go to a temporary folder as PNGs; ``pycolmap.extract_features`` (CPU SIFT) fills a
   fresh database, one PINHOLE camera per image, whose parameters are then set to the known ones;
2. ``pycolmap.match_exhaustive`` matches every pair and verifies it with the calibrated two-view
   geometry (an essential matrix, since the focal lengths are known);
3. a ``pycolmap.Reconstruction`` is built with the database's camera, rig, frame and image ids and
   the known poses, and ``pycolmap.triangulate_points`` triangulates the verified tracks. It holds
   every frame fixed (``fix_existing_frames``), so its bundle adjustment only moves the points, and
   ``refine_intrinsics=False`` keeps the intrinsics.

The SIFT settings are COLMAP's defaults except 0.3 times its peak threshold (0.002) and
domain-size pooling (Dong and Soatto 2015), which gave the most correct points on the sparse-view
scenes: LLFF fern's 3 views at 504x378 give 178 points (COLMAP's defaults: 104), nearly all seen in
all three views, at 0.2-0.3 px median reprojection error.

Example:
    >>> scene = langfield.load_scene("llff_fern", n_views=3)  # doctest: +SKIP
    >>> cams = scene.cameras("train")  # doctest: +SKIP
    >>> points, colors, stats = sfm_points(cams, [scene.image(c.name) for c in cams])  # doctest: +SKIP
    >>> stats["points"]  # doctest: +SKIP
    178
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from langfield.camera import Camera

__all__ = ["sfm_points"]

# 0.3 times COLMAP's default peak threshold (0.02 / octave_resolution 3): more features in the
# low-contrast parts of the photos; with domain-size pooling their descriptors stay distinctive
# enough to pass verification (LLFF fern: 104 -> 178 points, about the same reprojection error).
_PEAK_THRESHOLD = 0.002
_SEED = 0


def sfm_points(
    cameras: list[Camera], images: list[np.ndarray], *, two_view_tracks: bool = False
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Sparse points of the training views: COLMAP's SIFT extraction, exhaustive matching and
    triangulation with the known, fixed poses (pycolmap), as FSGS and CoR-GS start.

    Finding few or no points is not an error (the caller falls back to another start): blank images,
    no verified pair or nothing triangulated give empty arrays and a ``reason`` in the stats.

    Args:
        cameras: the training cameras (at least 2); intrinsics in pixels, poses OpenGL camera-to-world.
        images: one [H, W, 3] float RGB image in [0, 1] per camera, at its camera's size.
        two_view_tracks: also triangulate points matched in only two views. COLMAP skips them by
            default (``ignore_two_view_tracks``), and so does FSGS's start; on three views they are
            most of the candidates (fern: 178 -> 558 points) but less reliable (on the
            synthetic room twice as many land more than 2 % of the scene's size off a surface).

    Returns:
        (points, colors, stats): points [N, 3] float32 world coordinates; colors [N, 3] float32 RGB in
        [0, 1] (COLMAP's mean over the observations); stats with ``features_per_view`` (list of SIFT
        keypoint counts), ``verified_pairs``, ``matches`` (verified inlier matches summed over the
        pairs), ``points``, ``mean_track_length``, ``mean_reprojection_error`` (pixels), ``seconds``
        and ``reason`` (None, or why no points came out).

    Raises:
        ValueError: fewer than 2 views, a different number of images and cameras, an image whose
            shape is not [camera height, camera width, 3], or a pose that is a reflection.
        ImportError: pycolmap is not installed.
    """
    start = time.perf_counter()
    _check_inputs(cameras, images)
    try:
        import pycolmap
    except ImportError as err:  # an optional dependency: only this start method needs it
        raise ImportError("sfm_points needs pycolmap (pip install pycolmap)") from err

    stats: dict = {
        "features_per_view": [0] * len(cameras),
        "verified_pairs": 0,
        "matches": 0,
        "points": 0,
        "mean_track_length": 0.0,
        "mean_reprojection_error": 0.0,
        "seconds": 0.0,
        "reason": None,
    }
    # COLMAP logs every step at INFO through glog; keep warnings quiet too, errors still show.
    old_level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = int(pycolmap.logging.ERROR)
    try:
        with tempfile.TemporaryDirectory(prefix="langfield_sfm_") as tmp:
            points, colors = _run(pycolmap, Path(tmp), cameras, images, two_view_tracks, stats)
    finally:
        pycolmap.logging.minloglevel = old_level
    stats["points"] = len(points)
    stats["seconds"] = time.perf_counter() - start
    return points, colors, stats


def _check_inputs(cameras: list[Camera], images: list[np.ndarray]) -> None:
    if len(cameras) < 2:
        raise ValueError(f"sfm_points: need at least 2 views to triangulate, got {len(cameras)}")
    if len(images) != len(cameras):
        raise ValueError(f"sfm_points: {len(images)} images for {len(cameras)} cameras")
    for cam, image in zip(cameras, images, strict=True):
        shape = np.shape(image)
        if shape != (cam.height, cam.width, 3):
            raise ValueError(
                f"sfm_points: image of view {cam.name!r} has shape {shape}, its camera expects "
                f"({cam.height}, {cam.width}, 3)"
            )


def _run(
    pycolmap, root: Path, cameras: list[Camera], images: list[np.ndarray], two_view_tracks: bool, stats: dict
) -> tuple[np.ndarray, np.ndarray]:
    """The pipeline in the temporary folder `root`; fills `stats`, returns (points, colors)."""
    empty = np.zeros((0, 3), dtype=np.float32)
    image_dir, database_path, out_dir = root / "images", root / "database.db", root / "sparse"
    image_dir.mkdir()
    out_dir.mkdir()
    # Our own file names, not the views' names: those may repeat or hold characters a path cannot.
    names = [f"{i:04d}.png" for i in range(len(cameras))]
    for name, image in zip(names, images, strict=True):
        rgb8 = (np.clip(np.nan_to_num(np.asarray(image, dtype=np.float32)), 0.0, 1.0) * 255.0 + 0.5).astype(
            np.uint8
        )
        cv2.imwrite(str(image_dir / name), cv2.cvtColor(rgb8, cv2.COLOR_RGB2BGR))
    db_images = _extract(pycolmap, database_path, image_dir, names, cameras, stats)
    if sum(n > 0 for n in stats["features_per_view"]) < 2:
        stats["reason"] = "SIFT found features in fewer than 2 views"
        return empty, empty
    matched = _match(pycolmap, database_path, cameras, db_images, two_view_tracks, stats)
    if matched is None:
        return empty, empty
    reconstruction, pipeline = matched
    return _triangulate(pycolmap, reconstruction, database_path, image_dir, out_dir, pipeline, stats)


def _extract(
    pycolmap, database_path: Path, image_dir: Path, names: list[str], cameras: list[Camera], stats: dict
) -> list:
    """Step 1: SIFT features of every image into the database, with the known intrinsics; returns the
    database's images in the order of ``names``."""
    # SIFT on the CPU, one thread: the keypoints and the ids the database hands out do not
    # depend on scheduling. PER_IMAGE gives each image its own camera (and trivial rig and frame),
    # so views with different intrinsics keep theirs.
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    extraction.num_threads = 1
    extraction.sift.peak_threshold = _PEAK_THRESHOLD
    extraction.sift.domain_size_pooling = True
    pycolmap.extract_features(
        database_path,
        image_dir,
        image_names=names,
        camera_mode=pycolmap.CameraMode.PER_IMAGE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    database = pycolmap.Database.open(database_path)
    try:
        by_name = {image.name: image for image in database.read_all_images()}
        db_images = [by_name[name] for name in names]
        # The reader guessed the intrinsics from the image size; the known ones replace them before
        # matching, and the focal-length prior makes verification use the calibrated model (E).
        for cam, db_image in zip(cameras, db_images, strict=True):
            db_camera = database.read_camera(db_image.camera_id)
            db_camera.params = [cam.fx, cam.fy, cam.cx, cam.cy]
            db_camera.has_prior_focal_length = True
            database.update_camera(db_camera)
        stats["features_per_view"] = [database.num_keypoints_for_image(im.image_id) for im in db_images]
    finally:
        database.close()
    return db_images


def _match(
    pycolmap, database_path: Path, cameras: list[Camera], db_images: list, two_view_tracks: bool, stats: dict
):
    """Step 2: matching and verification; returns (the posed reconstruction, the pipeline options), or
    None (the reason in ``stats``) when no pair is verified."""
    # Exhaustive matching and geometric verification; a fixed RANSAC seed for repeatable inliers.
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = 1
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = _SEED
    pycolmap.match_exhaustive(
        database_path,
        matching_options=matching,
        verification_options=verification,
        device=pycolmap.Device.cpu,
    )
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.num_threads = 1
    pipeline.random_seed = _SEED
    pipeline.triangulation.ignore_two_view_tracks = not two_view_tracks
    database = pycolmap.Database.open(database_path)
    try:
        _, geometries = database.read_two_view_geometries()
        # The triangulator's database cache drops pairs below min_num_matches; count what it will use.
        inliers = [len(g.inlier_matches) for g in geometries]
        inliers = [n for n in inliers if n >= pipeline.min_num_matches]
        stats["verified_pairs"], stats["matches"] = len(inliers), int(sum(inliers))
        if not inliers:
            stats["reason"] = "no image pair passed geometric verification"
            return None
        reconstruction = _posed_reconstruction(pycolmap, database, cameras, db_images)
    finally:
        database.close()
    return reconstruction, pipeline


def _triangulate(
    pycolmap, reconstruction, database_path: Path, image_dir: Path, out_dir: Path, pipeline, stats: dict
):
    """Step 3: the tracks triangulated with the poses fixed; returns (points, colors)."""
    empty = np.zeros((0, 3), dtype=np.float32)
    # Triangulation with the poses fixed; it also extracts the points' colours from the PNGs.
    result = pycolmap.triangulate_points(
        reconstruction, database_path, image_dir, out_dir, options=pipeline, refine_intrinsics=False
    )
    points3d = list(result.points3D.values())
    if not points3d:
        stats["reason"] = "no track was triangulated (baselines too wide or too few matches)"
        return empty, empty
    stats["mean_track_length"] = float(result.compute_mean_track_length())
    stats["mean_reprojection_error"] = float(result.compute_mean_reprojection_error())
    points = np.array([p.xyz for p in points3d], dtype=np.float32)
    colors = np.array([p.color for p in points3d], dtype=np.float32) / 255.0
    return points, colors


def _posed_reconstruction(pycolmap, database, cameras: list[Camera], db_images: list) -> object:
    """A pycolmap.Reconstruction with the database's cameras and images, registered at the known poses.

    COLMAP 4 poses frames of rigs, not images. Each image here has its own camera, and the database
    holds one trivial rig per camera (rig id = camera id) and one frame per image (frame id = image
    id), which is exactly what ``add_camera_with_trivial_rig`` and ``add_image_with_trivial_frame``
    create; the ids have to agree because the triangulator looks the images up in the database.
    """
    reconstruction = pycolmap.Reconstruction()
    for cam, db_image in zip(cameras, db_images, strict=True):
        if db_image.frame_id != db_image.image_id:
            raise RuntimeError(
                f"pycolmap database: image {db_image.image_id} is in frame {db_image.frame_id}, "
                "expected a trivial frame with the same id"
            )
        reconstruction.add_camera_with_trivial_rig(database.read_camera(db_image.camera_id))
        image = pycolmap.Image(name=db_image.name, camera_id=db_image.camera_id, image_id=db_image.image_id)
        reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(_cam_from_world(cam)))
    return reconstruction


def _cam_from_world(cam: Camera) -> np.ndarray:
    """[3, 4] float64 world-to-camera in the OpenCV convention, which is COLMAP's cam_from_world.

    The rotation is snapped to the nearest orthonormal one (SVD): COLMAP stores it as a unit
    quaternion, and a pose with a little scale or shear in it would otherwise be converted arbitrarily.
    """
    w2c = cam.world_to_camera(dtype=torch.float64).numpy()[:3].copy()
    u, _, vt = np.linalg.svd(w2c[:, :3])
    rotation = u @ vt
    if np.linalg.det(rotation) < 0:
        raise ValueError(f"sfm_points: the pose of view {cam.name!r} is a reflection, not a rotation")
    w2c[:, :3] = rotation
    return w2c
